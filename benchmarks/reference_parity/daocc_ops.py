"""PyTorch definitions of the compiled ops that DAOcc's model runs, and placeholders for those it does not.

AlphaPlusTT/DAOcc vendors BEVFusion's ``mmdet3d``, whose ``mmdet3d/ops`` wraps CUDA extensions in Python, and imports
mmcv 1.x's ``mmcv.ops``; none of them builds here. The reference's own Python wrappers stay in use (its
``Voxelization`` module, its spconv 1.x ``SparseConvolution`` / ``SparseSequential`` / ``SparseConvTensor``); only
the extension modules under them are replaced:

* ``mmdet3d.ops.voxel.voxel_layer``: :func:`hard_voxelize`, BEVFusion's hard voxelization;
* ``mmdet3d.ops.spconv.sparse_conv_ext``: :func:`get_indice_pairs` and :func:`indice_conv`, spconv 1.x's rulebook and
  gather-GEMM-scatter convolution (the forward pass only);
* every other extension module (``bev_pool_ext``, ``iou3d_cuda``, ``roiaware_pool3d_ext``, the PointNet++ ops, ...) and
  all of ``mmcv.ops``: placeholders that import, and raise as soon as anything calls or instantiates them.

:func:`installed` puts them in front of the import system. The ops' semantics come from the reference's Python
wrappers (``mmdet3d/ops/voxel/voxelize.py``, ``mmdet3d/ops/spconv/{ops,conv,structure}.py``) and from the kernels
they were built from (BEVFusion's ``voxelization_cpu.cpp`` / ``voxelization_cuda.cu`` and mmdet3d's spconv 1.x
``indice.cc`` / ``indice.cu`` / ``indice_conv``), which the reference checkout ships without; each function's
docstring states what it reproduces.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Sequence
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import openmmlab  # noqa: E402 - beside this module


def hard_voxelize(points: torch.Tensor, voxels: torch.Tensor, coors: torch.Tensor, num_points_per_voxel: torch.Tensor,
                  voxel_size: Sequence[float], coors_range: Sequence[float], max_points: int, max_voxels: int,
                  ndim: int = 3, deterministic: bool = True) -> int:
    """BEVFusion's ``hard_voxelize``: fills ``voxels`` (M, max_points, C), ``coors`` (M, 3) and
    ``num_points_per_voxel`` (M,) in place and returns the number of voxels made.

    A point's cell is ``floor((p - range_min) / voxel_size)`` per axis, computed in float32 as the kernels do; a point
    with a cell outside ``[0, round((range_max - range_min) / voxel_size))`` on any axis is dropped. Voxels are
    numbered in the order of their first point, at most ``max_voxels`` of them (the points of later cells are
    dropped); each keeps its first ``max_points`` points in point order, the rest of its rows staying as the caller
    allocated them (zeros). ``coors`` is written ``(x, y, z)``: BEVFusion's kernels write
    ``coor[j] = c`` where mmdet3d's wrote ``coor[ndim - 1 - j]`` (``z, y, x``). Both of BEVFusion's kernels (the CPU
    loop and the deterministic CUDA path) give this; ``deterministic`` only chooses between them there.
    """
    if ndim != 3:
        raise ValueError(f"hard_voxelize supports ndim=3, not {ndim}")
    size = torch.tensor(voxel_size, dtype=torch.float32)
    low = torch.tensor(coors_range[:3], dtype=torch.float32)
    grid = torch.round((torch.tensor(coors_range[3:6], dtype=torch.float32) - low) / size).long()
    cells = torch.floor((points[:, :3].float() - low) / size).long()
    kept = torch.nonzero(((cells >= 0) & (cells < grid)).all(dim=1)).squeeze(1)  # in point order
    if kept.numel() == 0:
        return 0
    cells = cells[kept]
    _, group = torch.unique((cells[:, 0] * grid[1] + cells[:, 1]) * grid[2] + cells[:, 2], return_inverse=True)
    position = torch.arange(len(kept))
    first = torch.full((int(group.max()) + 1,), len(kept)).scatter_reduce(0, group, position, "amin")
    # Voxels are numbered by their first point; a point's rank in its voxel is the number of its earlier points.
    first_sorted, voxel_group = torch.sort(first)
    voxel_of_group = torch.empty_like(voxel_group)
    voxel_of_group[voxel_group] = torch.arange(len(voxel_group))
    voxel = voxel_of_group[group]
    by_voxel = torch.sort(voxel * len(kept) + position).indices
    rank = torch.empty_like(position)
    rank[by_voxel] = position - torch.searchsorted(voxel[by_voxel], voxel[by_voxel])
    count = min(len(first), max_voxels)
    take = (voxel < count) & (rank < max_points)
    voxels[voxel[take], rank[take]] = points[kept[take]].to(voxels.dtype)
    coors[:count] = cells[first_sorted[:count]].to(coors.dtype)
    num_points_per_voxel[:count] = torch.bincount(voxel[take], minlength=count).to(num_points_per_voxel.dtype)
    return count


def _kernel_offsets(kernel_size: Sequence[int]) -> torch.Tensor:
    """(K, ndim) kernel offsets in spconv's numbering: row-major over the kernel's axes, the last one fastest, which is
    also the order of the leading axes of its (k0, ..., k_{n-1}, in, out) weights."""
    axes = [torch.arange(k) for k in kernel_size]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, len(kernel_size))


def _linear(indices: torch.Tensor, shape: Sequence[int]) -> torch.Tensor:
    """Row-major linear index of (batch, i0, ..., i_{n-1}) rows in a (batch, *shape) volume."""
    linear = indices[:, 0].long()
    for axis, size in enumerate(shape):
        linear = linear * size + indices[:, axis + 1].long()
    return linear


def get_indice_pairs(indices: torch.Tensor, batch_size: int, out_shape: Sequence[int], spatial_shape: Sequence[int],
                     kernel_size: Sequence[int], stride: Sequence[int], padding: Sequence[int],
                     dilation: Sequence[int], out_padding: Sequence[int], subm: int,
                     transpose: int) -> list[torch.Tensor]:
    """spconv 1.x's rulebook (``get_indice_pairs_{n}d``): ``[out_indices, indice_pairs, indice_pair_num]``.

    ``indices`` are the active input sites, rows ``(batch, i0, ..., i_{n-1})``. Input site ``p`` feeds output site
    ``o`` through kernel offset ``k`` when ``p = o * stride - padding + k * dilation`` on every axis, with ``o`` inside
    ``out_shape`` (a cross-correlation, as ``torch.nn.functional.conv3d``). A submanifold convolution (``subm``) has
    its outputs at exactly the input sites, in input order, and pairs only active sites with active sites; a regular
    one has an output at every site that some active input reaches, ordered by (batch, row-major position) as the
    CUDA rulebook leaves them (it sorts the output keys before numbering them). ``indice_pairs`` is (K, 2, n_in),
    ``[k, 0, j]`` the input row and ``[k, 1, j]`` the output row of offset ``k``'s ``j``-th pair, in input order,
    padded with -1; ``indice_pair_num`` (K,) counts each offset's pairs. Transposed convolutions are not run by the
    model and refuse. ``batch_size`` and ``spatial_shape`` are implied (the sites carry their batch, ``out_shape``
    bounds the outputs) and ``out_padding`` only matters to transposed convolutions.
    """
    if transpose:
        raise NotImplementedError("transposed sparse convolution is not run by DAOcc and has no stand-in")
    ndim = indices.shape[1] - 1
    offsets = _kernel_offsets(kernel_size)
    stride_, padding_, dilation_ = (torch.tensor(v).long() for v in (stride, padding, dilation))
    out_shape_ = torch.tensor(list(out_shape)).long()
    positions = indices[:, 1:].long()
    # Output position of every (offset, input) pair, and whether it exists.
    numerator = positions[None] + padding_ - offsets[:, None] * dilation_  # (K, n_in, ndim)
    outputs = torch.div(numerator, stride_, rounding_mode="floor")
    valid = ((numerator % stride_ == 0) & (outputs >= 0) & (outputs < out_shape_)).all(dim=-1)
    batch = indices[:, 0].long().expand(len(offsets), -1)
    keys = _linear(torch.cat([batch[..., None], outputs], dim=-1).reshape(-1, ndim + 1), out_shape).view(valid.shape)
    if subm:
        out_indices = indices
        active_keys = _linear(indices, out_shape)
        order = torch.argsort(active_keys)
        slot = torch.searchsorted(active_keys[order], keys).clamp(max=len(order) - 1)
        valid &= active_keys[order][slot] == keys
        out_rows = order[slot]
    else:
        unique_keys = torch.unique(keys[valid])  # sorted
        out_rows = torch.searchsorted(unique_keys, keys)
        coordinates, remainder = [], unique_keys
        for size in reversed(list(out_shape)):
            coordinates.append(remainder % size)
            remainder = torch.div(remainder, size, rounding_mode="floor")
        out_indices = torch.stack([remainder, *reversed(coordinates)], dim=1).to(indices.dtype)
    pairs = torch.full((len(offsets), 2, len(indices)), -1, dtype=torch.int32)
    counts = valid.sum(dim=1)
    for k in range(len(offsets)):
        rows = torch.nonzero(valid[k]).squeeze(1)
        pairs[k, 0, : len(rows)] = rows.int()
        pairs[k, 1, : len(rows)] = out_rows[k, rows].int()
    return [out_indices, pairs, counts.int()]


def indice_conv(features: torch.Tensor, filters: torch.Tensor, indice_pairs: torch.Tensor,
                indice_pair_num: torch.Tensor, num_activate_out: int, inverse: int = 0,
                subm: int = 0) -> torch.Tensor:
    """spconv 1.x's ``indice_conv`` forward: ``out[o] = sum_k features[i] @ W[k]`` over the pairs ``(i, o)`` of every
    offset ``k``, with ``filters`` in spconv 1.x's layout ``(k0, ..., k_{n-1}, in, out)`` (offset ``k`` is the
    row-major index over the leading axes).

    The sum is taken in the kernel's order: a submanifold convolution starts from ``features @ W[c]``, ``c`` the
    offset with the most pairs (the centre, where every site pairs with itself), and every convolution then adds the
    other offsets in increasing order, each a gather, a GEMM and a scatter-add (no output occurs twice in one offset,
    so the scatter is exact). The inverse convolution is not run by the model and refuses.
    """
    if inverse:
        raise NotImplementedError("inverse sparse convolution is not run by DAOcc and has no stand-in")
    weights = filters.reshape(-1, filters.shape[-2], filters.shape[-1])
    counts = [int(n) for n in indice_pair_num]
    centre = max(range(len(counts)), key=lambda k: (counts[k], -k)) if subm else -1
    output = features @ weights[centre] if subm else features.new_zeros(num_activate_out, weights.shape[-1])
    for k, count in enumerate(counts):
        if count <= 0 or k == centre:
            continue
        inputs, outputs = indice_pairs[k, 0, :count].long(), indice_pairs[k, 1, :count].long()
        output = output.index_add(0, outputs, features[inputs] @ weights[k])
    return output


#: The compiled modules that DAOcc's ``mmdet3d`` imports, and the names given PyTorch definitions; every other name
#: of theirs is an :func:`openmmlab.placeholder`.
COMPILED: dict[str, dict[str, object]] = {
    "mmdet3d.ops.voxel.voxel_layer": {"hard_voxelize": hard_voxelize},
    "mmdet3d.ops.spconv.sparse_conv_ext": {"get_indice_pairs_3d": get_indice_pairs, "indice_conv_fp32": indice_conv},
    **{f"mmdet3d.ops.{name}": {} for name in (
        "ball_query.ball_query_ext", "bev_pool.bev_pool_ext", "furthest_point_sample.furthest_point_sample_ext",
        "gather_points.gather_points_ext", "group_points.group_points_ext", "interpolate.interpolate_ext",
        "iou3d.iou3d_cuda", "knn.knn_ext", "paconv.assign_score_withk_ext", "pointnet2.pointnet2_ext",
        "roiaware_pool3d.roiaware_pool3d_ext")},
}


def installed() -> contextlib.AbstractContextManager[None]:
    """The stand-ins answer imports (:data:`COMPILED`, and all of ``mmcv.ops`` as placeholders) while the context
    lasts; the modules they made are removed on exit."""
    return openmmlab.stand_ins(COMPILED, ("mmcv.ops",))
