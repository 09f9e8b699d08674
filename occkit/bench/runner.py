"""Forward passes of a model on one batch, in a precision, timed: what every measurement of a run calls."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from occkit.bench.config import PRECISIONS
from occkit.bench.timing import synchronizer, timed
from occkit.types import Batch

__all__ = ["ModelRunner"]


class ModelRunner:
    """Forward passes of models on one batch, in a precision (autocast below fp32), without autograd.

    Args:
        batch: the input, already on ``device``; device: where the models run; precision: a key of
            :data:`PRECISIONS`.
    """

    def __init__(self, batch: Batch, device: torch.device, precision: str = "fp32") -> None:
        self.batch = batch
        self.device = device
        self.dtype = PRECISIONS[precision]
        self.synchronize = synchronizer(device)

    def forward(self, model: nn.Module, detect: bool = False) -> Tensor:
        """Occupancy logits ``(B, K, X, Y, Z)`` of one pass."""
        autocast = torch.autocast(self.device.type, dtype=self.dtype, enabled=self.dtype != torch.float32)
        with torch.no_grad(), autocast:
            output = model(self.batch, detect=True) if detect else model(self.batch)
        return output.occupancy

    def time(self, model: nn.Module) -> float:
        """Seconds of one pass, the device's queue drained before and after."""
        return timed(lambda: self.forward(model), self.synchronize)
