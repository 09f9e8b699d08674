"""Sparse convolution as gather + one matrix product per block of output sites: occkit's CPU path for the LiDAR encoder.

spconv's CPU build runs a convolution offset by offset: for each of the ``K`` kernel offsets it gathers the input rows
of that offset's pairs, multiplies them by the offset's ``(C_in, C_out)`` weight and scatter-adds the products, every
step in a parallel region of its own. That is thousands of small OpenMP regions per training step, which cost little
on an idle machine but stall on their barriers as soon as another process competes for the cores (data-loading
workers, a second job): the encoder then runs ten times slower.

Here a convolution is an implicit GEMM over a **neighbour table**: for every output site, the input row each kernel
offset reads, or a zero row where that neighbour is not active. A block of output sites gathers its rows into a
``(rows, K * C_in)`` matrix and multiplies it by the weight reshaped to ``(K * C_in, C_out)``: one gather and one GEMM
per block of a few megabytes, the products summed inside the GEMM, no scatter. The backward pass is the same two
operations: the input gradient gathers the output gradient through the **transposed table** (for every input site, the
output row each offset writes) and multiplies it by the transposed weight; the weight gradient is one GEMM per block.
Nothing is added atomically, so forward and backward repeat bitwise.

The price is the zero rows: a table entry exists for every offset, whether or not its neighbour is active (a LiDAR
surface fills about half of a 3 x 3 x 3 neighbourhood), so the GEMMs multiply some zeros that spconv skips.

The tables are built once per batch of voxels (:func:`build_neighbour_tables`, no gradient) and shared by every
layer with the same ``indice_key``, with plain tensor operations: a two-level index of the active sites, a dense
map of the occupied ``(batch, x, y)`` columns and a ``(columns, Z)`` table of rows, answers each neighbour query with
two gathers. Geometry and conventions are those of :mod:`occkit.models.sparse_rules` (weights ``(C_out, kx, ky, kz,
C_in)``, flat kernel offset ``(ix * Ky + iy) * Kz + iz``, output site ``o`` reading input ``o * s - p + i``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from occkit.models.sparse_rules import ConvSpec, decode_keys, kernel_offsets

__all__ = ["SiteIndex", "NeighbourTable", "neighbour_table", "build_neighbour_tables", "gather_gemm_conv"]

#: Bytes of gathered rows per block: large enough for an efficient GEMM, small enough to stay in the caches between
#: the gather and the product (measured on a 2-core machine, blocks of 1 to 16 MB: 4 MB was fastest).
BLOCK_BYTES = 4 << 20


class SiteIndex:
    """Row of each active site ``(batch, x, y, z)`` and of its neighbours, looked up with two gathers and no masks.

    A dense map over the ``(batch, x, y)`` columns holds each occupied column's number; a ``(columns + 1, Z)`` table
    holds the row of each site of those columns, -1 where inactive. Both are padded by ``halo`` cells on every side
    (and empty columns point at the last, all -1 column), so a neighbour up to ``halo`` cells away needs no bounds
    check: it lands in padding. For DAOcc's 1440 x 1440 x 41 grid that is 17 MB per sample plus ``Z + 2`` entries per
    occupied column, instead of a dense grid of 85 million cells.

    Args:
        coords: ``(N, 4)`` int64 unique ``(batch, x, y, z)`` sites inside ``shape``.
        shape: ``(X, Y, Z)``.
        batch_size: ``B``, more than the largest batch index.
        halo: ``(hx, hy, hz)`` cells of padding, the farthest neighbour looked up along each axis.
    """

    def __init__(self, coords: Tensor, shape: Sequence[int], batch_size: int, halo: Sequence[int]) -> None:
        self.halo = tuple(int(h) for h in halo)
        hx, hy, hz = self.halo
        size_x, size_y, size_z = (int(s) for s in shape)
        self.padded = (size_x + 2 * hx, size_y + 2 * hy, size_z + 2 * hz)
        device = coords.device
        self.site_columns = self.column_keys(coords)
        occupied, column_number = torch.unique(self.site_columns, return_inverse=True)
        empty = occupied.numel()
        self.columns = torch.full((batch_size * self.padded[0] * self.padded[1],), empty, dtype=torch.int64,
                                  device=device)  # fmt: skip
        self.columns[occupied] = torch.arange(empty, device=device)
        self.rows = torch.full((empty + 1, self.padded[2]), -1, dtype=torch.int64, device=device)
        self.rows[column_number, coords[:, 3] + hz] = torch.arange(coords.shape[0], device=device)
        self.rows = self.rows.view(-1)

    def column_keys(self, coords: Tensor) -> Tensor:
        """``(N,)`` flat padded-column keys of ``(N, 4)`` sites."""
        hx, hy, _ = self.halo
        return (coords[:, 0] * self.padded[0] + coords[:, 1] + hx) * self.padded[1] + coords[:, 2] + hy

    def neighbours(self, coords: Tensor, delta: Tensor) -> Tensor:
        """``(N, K)`` rows of the sites ``coords + delta[k]`` (-1 where inactive or outside the grid).

        Args:
            coords: ``(N, 4)`` sites inside the grid (usually the indexed ones).
            delta: ``(K, 3)`` int64 offsets within the halo, grouped by ``(dx, dy)``: ``K = columns * dz``, the
                ``dz`` varying fastest with the same values in every group (a kernel's flat offset order).
        """
        depth = int((delta[:, :2] == delta[:1, :2]).all(dim=1).sum())
        groups = delta.view(-1, depth, 3)
        shift = groups[:, 0, 0] * self.padded[1] + groups[:, 0, 1]  # (G,) column offsets
        columns = self.columns[self.column_keys(coords)[:, None] + shift]  # (N, G)
        z = coords[:, 3, None] + self.halo[2] + groups[0, :, 2]  # (N, dz)
        cells = (columns * self.padded[2])[:, :, None] + z[:, None, :]  # (N, G, dz)
        return self.rows[cells.view(coords.shape[0], -1)]


@dataclass
class NeighbourTable:
    """The pairs of one sparse convolution layer for one set of active sites, as gather tables."""

    table: Tensor
    """``(N_out, K)`` int64 input row read by each output site through each offset; ``N_in`` where none."""
    transposed: Tensor
    """``(N_in, K)`` int64 output row each input site feeds through each offset; ``N_out`` where none."""
    out_coords: Tensor
    """``(N_out, 4)`` int64 ``(batch, x, y, z)`` output sites: the input sites for a submanifold convolution,
    ascending ``(batch, x, y, z)`` for a strided one."""

    @property
    def num_pairs(self) -> int:
        """Active (input, output, offset) triples."""
        return int((self.transposed < self.table.shape[0]).sum())


def neighbour_table(coords: Tensor, spec: ConvSpec, batch_size: int) -> NeighbourTable:
    """The neighbour table of one layer.

    Args:
        coords: ``(N, 4)`` int64 unique ``(batch, x, y, z)`` active input sites inside ``spec.in_shape``.
        spec: the layer's geometry; dilation 1.
        batch_size: ``B``.

    Returns:
        The table, all ``K`` offsets listed (a submanifold convolution's centre too: it reads the site itself).
    """
    coords = coords.to(torch.int64)
    device = coords.device
    num_in = coords.shape[0]
    kernel = kernel_offsets(spec.kernel_size, range(spec.num_offsets), device)  # (K, 3)
    if spec.subm:
        if any(k % 2 == 0 for k in spec.kernel_size):
            raise ValueError(f"submanifold convolution {spec.key!r} needs an odd kernel, got {spec.kernel_size}")
        index = SiteIndex(coords, spec.in_shape, batch_size, spec.padding)
        rows = index.neighbours(coords, kernel - torch.tensor(spec.padding, device=device))
        table = torch.where(rows >= 0, rows, num_in)
        # Site j is site i's neighbour through offset k exactly when i is j's through the mirrored offset K - 1 - k.
        return NeighbourTable(table, table.flip(1), coords)
    # Input i reaches output o through offset k when i + p - k = o * s, with 0 <= o < out_shape. Per axis that is a
    # small table: input coordinate -> output coordinate through each kernel index, or -1.
    per_axis = []
    for axis in range(3):
        position = torch.arange(spec.in_shape[axis], device=device)[:, None]
        numerator = position + spec.padding[axis] - torch.arange(spec.kernel_size[axis], device=device)
        out = torch.div(numerator, spec.stride[axis], rounding_mode="floor")
        hit = (numerator >= 0) & (numerator % spec.stride[axis] == 0) & (out < spec.out_shape[axis])
        per_axis.append(torch.where(hit, out, -1)[coords[:, axis + 1]])  # (N, k_axis)
    ox, oy, oz = per_axis
    valid = ((ox >= 0)[:, :, None, None] & (oy >= 0)[:, None, :, None] & (oz >= 0)[:, None, None, :]).view(num_in, -1)
    size_x, size_y, size_z = spec.out_shape
    column = (coords[:, 0, None] * size_x + ox)[:, :, None] * size_y + oy[:, None, :]  # (N, kx, ky)
    keys = (column[:, :, :, None] * size_z + oz[:, None, None, :]).view(num_in, -1)  # (N, K)
    source, offset = valid.nonzero(as_tuple=True)
    hits = keys[source, offset]
    occupied = torch.zeros(batch_size * size_x * size_y * size_z, dtype=torch.bool, device=device)
    occupied[hits] = True
    out_keys = occupied.nonzero().squeeze(1)  # ascending
    out_rows = torch.searchsorted(out_keys, hits)
    num_out = out_keys.numel()
    transposed = torch.full((num_in, spec.num_offsets), num_out, dtype=torch.int64, device=device)
    transposed[source, offset] = out_rows
    table = torch.full((num_out, spec.num_offsets), num_in, dtype=torch.int64, device=device)
    table[out_rows, offset] = source
    return NeighbourTable(table, transposed, decode_keys(out_keys, spec.out_shape))


def build_neighbour_tables(specs: Sequence[ConvSpec], coords: Tensor, batch_size: int) -> dict[str, NeighbourTable]:
    """Tables of every layer of an encoder for one batch of voxels, in the order of ``specs`` (forward order).

    Args:
        specs: from :func:`~occkit.models.sparse_rules.encoder_conv_specs`.
        coords: ``(V, 4)`` integer unique ``(batch, x, y, z)`` voxel sites inside ``specs[0].in_shape``.
        batch_size: ``B``.
    """
    sites = coords.to(torch.int64)
    tables = {}
    with torch.no_grad():
        for spec in specs:
            tables[spec.key] = neighbour_table(sites, spec, batch_size)
            sites = tables[spec.key].out_coords
    return tables


def _block_rows(width: int, element_size: int) -> int:
    """Rows per block of a gathered ``(rows, width)`` matrix."""
    return max(64, BLOCK_BYTES // max(1, width * element_size))


def _gathered_blocks(rows: Tensor, table: Tensor):
    """``(start, block)`` for blocks of the table's rows: ``block[o] = concat_k(rows_padded[table[start + o, k]])``,
    ``rows_padded`` being ``rows`` with a zero row appended at index ``len(rows)``."""
    padded = torch.cat((rows, rows.new_zeros(1, rows.shape[1])))
    width = table.shape[1] * rows.shape[1]
    step = _block_rows(width, rows.element_size())
    for start in range(0, table.shape[0], step):
        yield start, padded.index_select(0, table[start : start + step].reshape(-1)).view(-1, width)


def _gather_gemm(rows: Tensor, table: Tensor, matrix: Tensor) -> Tensor:
    """``out[o] = concat_k(rows_padded[table[o, k]]) @ matrix``, block by block (:func:`_gathered_blocks`).
    ``(R, C) x (M, K) x (K * C, D) -> (M, D)``."""
    out = rows.new_empty(table.shape[0], matrix.shape[1])
    for start, block in _gathered_blocks(rows, table):
        torch.mm(block, matrix, out=out[start : start + block.shape[0]])
    return out


class _GatherGemmConv(torch.autograd.Function):
    """Sparse convolution through a neighbour table, with its backward pass through the transposed table."""

    @staticmethod
    def forward(ctx, features: Tensor, weight: Tensor, table: Tensor, transposed: Tensor) -> Tensor:
        c_out = weight.shape[0]
        weight = weight.to(features.dtype)
        ctx.save_for_backward(features, weight, table, transposed)
        return _gather_gemm(features, table, weight.reshape(c_out, -1).t())

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        features, weight, table, transposed = ctx.saved_tensors
        c_out, c_in = weight.shape[0], weight.shape[-1]
        offsets = table.shape[1]
        grad_out = grad_out.contiguous()
        grad_features = grad_weight = None
        if ctx.needs_input_grad[0]:
            # d features[i] = sum_k grad_out[transposed[i, k]] @ W_k, W_k the (C_out, C_in) weight of offset k.
            per_offset = weight.reshape(c_out, offsets, c_in).transpose(0, 1).reshape(offsets * c_out, c_in)
            grad_features = _gather_gemm(grad_out, transposed, per_offset)
        if ctx.needs_input_grad[1]:
            grad = features.new_zeros(c_out, offsets * c_in)
            for start, block in _gathered_blocks(features, table):
                grad.addmm_(grad_out[start : start + block.shape[0]].t(), block)
            grad_weight = grad.view_as(weight)
        return grad_features, grad_weight, None, None


def gather_gemm_conv(features: Tensor, weight: Tensor, table: NeighbourTable) -> Tensor:
    """One sparse convolution (no bias) through its neighbour table; differentiable in ``features`` and ``weight``.

    Args:
        features: ``(N_in, C_in)`` features of the table's input sites.
        weight: ``(C_out, kx, ky, kz, C_in)``, spconv 2.x's layout.
        table: the layer's :class:`NeighbourTable`.

    Returns:
        ``(N_out, C_out)`` features at ``table.out_coords``.
    """
    if features.shape[0] != table.transposed.shape[0]:
        raise ValueError(f"features have {features.shape[0]} rows but the table lists {table.transposed.shape[0]} "
                         "input sites")
    return _GatherGemmConv.apply(features.contiguous(), weight, table.table, table.transposed)
