"""Parameter and multiply-accumulate (MAC) counts, the papers' "FLOPs".

Convention: one MAC is one multiply plus one add; the papers' "GFLOPs" (mmcv's ``get_flops``) are MAC counts.
Dense layers are counted by PyTorch's ``FlopCounterMode`` (convolutions, linear layers, matrix products; FLOPs / 2).
Sparse convolutions are counted from their active sites: ``pairs x C_in x C_out``, where a pair is an (input site,
output site, kernel offset) triple that the convolution actually multiplies, computed from the sites themselves so
the count does not depend on how spconv schedules its kernels (its CPU path multiplies padded buffers). Elementwise
work, normalisation, sampling and pooling are not counted, as in the papers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn
from torch.utils.flop_counter import FlopCounterMode

__all__ = ["count_parameters", "count_macs", "MacCount", "sparse_conv_pairs"]


def count_parameters(module: nn.Module, trainable_only: bool = False) -> int:
    """Number of parameters (shared ones once)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only)


def _keys(coords: Tensor, shape: Tensor) -> Tensor:
    """Flat int64 keys of ``(V, 4)`` (batch, d0, d1, d2) coordinates in a grid of ``shape`` (3,)."""
    coords = coords.long()
    return ((coords[:, 0] * shape[0] + coords[:, 1]) * shape[1] + coords[:, 2]) * shape[2] + coords[:, 3]


def sparse_conv_pairs(
    in_coords: Tensor,
    out_coords: Tensor,
    out_shape: tuple[int, int, int],
    kernel_size: tuple[int, int, int],
    stride: tuple[int, int, int],
    padding: tuple[int, int, int],
    dilation: tuple[int, int, int] = (1, 1, 1),
) -> int:
    """Number of (input site, output site, kernel offset) triples of a sparse convolution.

    Args:
        in_coords, out_coords: ``(V_in, 4)`` and ``(V_out, 4)`` ``(batch, d0, d1, d2)`` active sites.
        out_shape: output grid size; kernel_size, stride, padding, dilation: per axis.
    """
    device = out_coords.device  # every index tensor on the sites' device (a CUDA run counts on the GPU)
    shape = torch.tensor(out_shape, device=device)
    out_keys = torch.sort(_keys(out_coords, shape)).values
    total = 0
    spatial = in_coords[:, 1:].long()
    padding_t, dilation_t, stride_t = (torch.tensor(v, device=device) for v in (padding, dilation, stride))
    offsets = torch.cartesian_prod(*[torch.arange(k, device=device) for k in kernel_size]).reshape(-1, 3)
    for offset in offsets:
        numerator = spatial + padding_t - offset * dilation_t
        target = torch.div(numerator, stride_t, rounding_mode="floor")
        ok = (numerator % stride_t == 0).all(1) & (target >= 0).all(1) & (target < shape).all(1)
        candidates = torch.cat([in_coords[ok, :1].long(), target[ok]], dim=1)
        keys = _keys(candidates, shape)
        position = torch.searchsorted(out_keys, keys).clamp_max(max(out_keys.numel() - 1, 0))
        total += int((out_keys.numel() > 0) * (out_keys[position] == keys).sum())
    return total


@dataclass
class MacCount:
    """MACs of one call, in total and per top-level child module."""

    total: int = 0
    by_module: dict[str, int] = field(default_factory=dict)


def _sparse_modules(model: nn.Module) -> dict[str, nn.Module]:
    from occkit.models.sparse import SparseConv3d, SubMConv3d

    return {name: m for name, m in model.named_modules() if isinstance(m, (SubMConv3d, SparseConv3d))}


def count_macs(model: nn.Module, run: Callable[[], object]) -> MacCount:
    """MACs of ``run()`` (a call of ``model``), split by ``model``'s direct children.

    Args:
        model: the module whose children name the split.
        run: a closure that calls the model once.
    """
    sparse = _sparse_modules(model)
    sparse_macs: dict[str, int] = {}

    def hook(name: str):
        def record(module, inputs, output) -> None:
            source = inputs[0]
            pairs = sparse_conv_pairs(
                source.indices, output.indices, tuple(output.spatial_shape), tuple(module.kernel_size),
                tuple(module.stride), tuple(module.padding), tuple(module.dilation),
            )  # fmt: skip
            sparse_macs[name] = sparse_macs.get(name, 0) + pairs * module.in_channels * module.out_channels

        return record

    handles = [m.register_forward_hook(hook(name)) for name, m in sparse.items()]
    # The pairs are read from spconv's index tensors, so sparse encoders count through spconv (the same pairs as any
    # backend's, hence the same MACs).
    from occkit.models.lidar_encoder import SparseEncoder

    encoders = [m for m in model.modules() if isinstance(m, SparseEncoder)]
    backends = [encoder.backend for encoder in encoders]
    try:
        for encoder in encoders:
            encoder.backend = "spconv"
        with FlopCounterMode(display=False) as counter:
            run()
    finally:
        for handle in handles:
            handle.remove()
        for encoder, backend in zip(encoders, backends, strict=True):
            encoder.backend = backend
    counts = counter.get_flop_counts()
    result = MacCount()
    children = [name for name, _ in model.named_children()]
    model_key = type(model).__name__
    for child in children:
        dense = sum(counts.get(f"{model_key}.{child}", {}).values()) // 2
        # spconv's own matrix products, counted above by the dense counter, are replaced by the exact pair count.
        for name in sparse:
            if name == child or name.startswith(child + "."):
                dense -= sum(counts.get(f"{model_key}.{name}", {}).values()) // 2
                dense += sparse_macs.get(name, 0)
        if dense:
            result.by_module[child] = dense
    spconv_dense = sum(sum(counts.get(f"{model_key}.{name}", {}).values()) // 2 for name in sparse)
    result.total = sum(counts.get("Global", {}).values()) // 2 - spconv_dense + sum(sparse_macs.values())
    return result
