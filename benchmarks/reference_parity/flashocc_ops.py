"""FlashOcc's CUDA op, defined in PyTorch for the parity harness: BEVPoolv2.

``projects/mmdet3d_plugin/ops/bev_pool_v2`` of Yzichen/FlashOCC (BEVDet's op, Huang & Huang 2022, "BEVPoolv2") is a
CUDA kernel. Its Python wrapper documents the arguments and its kernel (``bev_pool_cuda.cu``) computes, for each
pillar ``p`` (a run ``interval_starts[p] : interval_starts[p] + interval_lengths[p]`` of frustum points sorted by
``ranks_bev``) and channel ``c``::

    out[ranks_bev[interval_starts[p]], c] = sum_i depth.flat[ranks_depth[i]] * feat.reshape(-1, C)[ranks_feat[i], c]

over the points ``i`` of the pillar, into a zero-initialised ``(B, Dz, Dy, Dx, C)`` buffer whose flat index is
``ranks_bev``, which the wrapper permutes to ``(B, C, Dz, Dy, Dx)``. Every point of a pillar has the same
``ranks_bev``, so the sum is a scatter-add of the products onto ``ranks_bev``; cells without a pillar stay zero.
"""

from __future__ import annotations

import types
from collections.abc import Sequence

from torch import Tensor


def bev_pool_v2(
    depth: Tensor,
    feat: Tensor,
    ranks_depth: Tensor,
    ranks_feat: Tensor,
    ranks_bev: Tensor,
    bev_feat_shape: Sequence[int],
    interval_starts: Tensor,
    interval_lengths: Tensor,
) -> Tensor:
    """The wrapper's signature: ``depth (B, N, D, fH, fW)``, ``feat (B, N, fH, fW, C)``, the ranks ``(P,)``,
    ``bev_feat_shape = (B, Dz, Dy, Dx, C)`` -> ``(B, C, Dz, Dy, Dx)``.

    The pillars' intervals only group the points by ``ranks_bev``; they are checked to cover every point once.
    """
    starts, lengths = interval_starts.long(), interval_lengths.long()
    if int(lengths.sum()) != ranks_bev.numel() or (starts.numel() and int(starts[0]) != 0):
        raise ValueError("the intervals of bev_pool_v2 must cover the sorted points once, from the first")
    channels = feat.shape[-1]
    products = depth.reshape(-1)[ranks_depth.long()].unsqueeze(1) * feat.reshape(-1, channels)[ranks_feat.long()]
    out = feat.new_zeros(tuple(bev_feat_shape)).reshape(-1, channels)
    out.index_add_(0, ranks_bev.long(), products.to(out.dtype))
    return out.reshape(tuple(bev_feat_shape)).permute(0, 4, 1, 2, 3).contiguous()


def module(placeholder) -> types.ModuleType:
    """``projects.mmdet3d_plugin.ops`` with :func:`bev_pool_v2`; its other ops (TensorRT's BEVPoolv2, the panoptic
    ``nearest_assign``) are imported by the detectors' module but not run by the models the harness builds."""
    ops = types.ModuleType("projects.mmdet3d_plugin.ops")
    ops.__path__ = []
    ops.bev_pool_v2 = bev_pool_v2
    ops.TRTBEVPoolv2 = placeholder("TRTBEVPoolv2")
    ops.nearest_assign = placeholder("nearest_assign")
    ops.bev_pool = placeholder("bev_pool")
    return ops
