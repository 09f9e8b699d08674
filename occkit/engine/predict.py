"""Prediction with a trained model: one ``<token>.npz`` file per key frame of a dataset split
(:func:`occkit.metrics.evaluate.write_prediction`).

It runs over the split in order, sharded over ranks under torchrun (each rank writes the files of its share); a
temporal model is streamed scene by scene (:func:`occkit.engine.evaluate.stream_memory`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

from occkit.data.dataset import OccupancyDataset
from occkit.engine import distributed
from occkit.engine.evaluate import split_loader, stream_memory
from occkit.metrics.evaluate import write_prediction

__all__ = ["predict_to_folder"]


@torch.no_grad()
def predict_to_folder(model: nn.Module, dataset: OccupancyDataset, out: Path, batch_size: int = 1, workers: int = 0,
                      context: distributed.Context | None = None,
                      progress: Callable[[int], None] | None = None) -> dict[str, int]:  # fmt: skip
    """Write ``out/<token>.npz`` predictions of every frame of ``dataset`` (this rank's share under torchrun).

    Returns:
        ``written`` and ``skipped`` (frames that failed to load under ``on_error="skip"``), summed over ranks.
    """
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    memory, batch_size = stream_memory(model, batch_size)
    loader = split_loader(dataset, batch_size, workers, context, by_scene=memory is not None)
    share, written = len(loader.sampler), 0
    for index, batch in enumerate(loader):
        if len(batch) > 0:  # else every frame of the batch failed to load (on_error="skip")
            batch = batch.to(device)
            prediction = model.predict(batch) if memory is None else model.predict(batch, memory=memory)
            semantics = prediction.semantics.cpu().numpy()
            flows = [None] * len(semantics) if prediction.flow is None else prediction.flow.float().cpu().numpy()
            for token, grid, flow in zip(batch.tokens, semantics, flows, strict=True):
                write_prediction(out, token, grid, flow)
            written += len(batch)
        if progress is not None:
            progress(min(batch_size, share - index * batch_size))
    model.train(was_training)
    written, skipped = (int(n) for n in distributed.all_reduce_sum(np.array([written, share - written])))
    return {"written": written, "skipped": skipped}
