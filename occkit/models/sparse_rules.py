"""Sparse convolution without spconv: rulebooks built in plain PyTorch, convolutions as gather -> matmul -> scatter-add.

spconv runs its convolutions from "rulebooks": for every kernel offset, the pairs (input row, output row) of active
sites it connects. This module builds the same rulebooks with plain tensor operations and executes the LiDAR
encoder (:class:`~occkit.models.lidar_encoder.SparseEncoder`) from them with standard operators only, so that the
encoder exports to ONNX: voxelization and rulebook building stay outside the graph (they only need the voxel
coordinates), the graph takes the rulebooks as index tensors.

Conventions (spconv's, see :mod:`occkit.models.sparse`): coordinates are ``(batch, x, y, z)`` int64 rows; a
convolution's weight is ``(C_out, kx, ky, kz, C_in)`` and kernel offset ``k`` is the flat index
``(ix * Ky + iy) * Kz + iz`` of ``weight.reshape(C_out, K, C_in)``. Output site ``o`` of a convolution with stride
``s`` and padding ``p`` reads input site ``o * s - p + i`` through offset ``i`` (cross-correlation, as ``conv3d``):

* submanifold convolution: the output sites are the input sites (same rows, same order);
* strided ("regular") sparse convolution: the output sites are every ``o`` inside the output shape that some input
  site reaches, listed in ascending ``(batch, x, y, z)`` order.

Rulebook layout, one ``(2, K', L)`` int64 tensor per layer: ``[0, k]`` input rows and ``[1, k]`` output rows of the
pairs of offset ``offsets[k]``, padded to the longest offset's ``L`` pairs with input row 0 and output row
``N_out`` (a dump row dropped after the scatter). A submanifold rulebook leaves out the centre offset, which pairs
every site with itself and runs as one plain matrix product; without it ``L`` is the busiest neighbour direction
rather than the number of sites.

Execution (:func:`sparse_conv`): gather the input rows ``(K', L, C_in)``, one batched matrix product with the
offsets' weights ``(K', C_in, C_out)``, scatter-add the products into ``(N_out + 1) * K'`` rows (one per output row
and offset) and sum over the offsets. Its largest intermediate is that ``(N_out + 1) * K' x C_out`` buffer: 390 MB
(fp32) in DAOcc's second stage for a 10-sweep cloud of the synthetic world (310k points, 103k voxels).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from occkit.models.indexing import take
from occkit.models.sparse import SparseConv3d, SubMConv3d

__all__ = [
    "ConvSpec",
    "Rulebook",
    "encoder_conv_specs",
    "coordinate_keys",
    "decode_keys",
    "kernel_offsets",
    "submanifold_rulebook",
    "strided_rulebook",
    "build_rulebooks",
    "sparse_conv",
    "RulebookSparseEncoder",
]


@dataclass(frozen=True)
class ConvSpec:
    """Geometry of one sparse convolution layer, i.e. of one spconv ``indice_key`` (layers sharing it share sites)."""

    key: str
    """spconv's ``indice_key``, the name of the rulebook."""
    subm: bool
    """Submanifold (output sites = input sites) or strided sparse convolution."""
    kernel_size: tuple[int, int, int]
    """Kernel ``(kx, ky, kz)``."""
    stride: tuple[int, int, int]
    """Stride per axis (1 for submanifold convolutions)."""
    padding: tuple[int, int, int]
    """Padding per axis (``kernel // 2`` for submanifold convolutions)."""
    in_shape: tuple[int, int, int]
    """Spatial shape ``(X, Y, Z)`` of the input sites."""
    out_shape: tuple[int, int, int]
    """Spatial shape of the output sites (``in_shape`` for submanifold convolutions)."""

    @property
    def num_offsets(self) -> int:
        """``K = kx * ky * kz``."""
        return self.kernel_size[0] * self.kernel_size[1] * self.kernel_size[2]

    @property
    def centre(self) -> int | None:
        """Flat offset of the kernel centre for a submanifold convolution (run without the rulebook), else None."""
        if not self.subm:
            return None
        kx, ky, kz = self.kernel_size
        return ((kx // 2) * ky + ky // 2) * kz + kz // 2

    @property
    def offsets(self) -> tuple[int, ...]:
        """Flat kernel offsets listed in the rulebook, in order: all ``K``, less the centre when submanifold."""
        return tuple(k for k in range(self.num_offsets) if k != self.centre)


@dataclass
class Rulebook:
    """The pairs of one :class:`ConvSpec` for one set of active input sites."""

    pairs: Tensor
    """``(2, K', L)`` int64: input rows ``[0]`` and output rows ``[1]`` per listed offset; padding ``(0, N_out)``."""
    out_coords: Tensor
    """``(N_out, 4)`` int64 ``(batch, x, y, z)`` output sites; the input sites for a submanifold convolution."""

    @property
    def num_out(self) -> int:
        """``N_out``, the number of output sites."""
        return int(self.out_coords.shape[0])


def _conv_modules(module: nn.Module) -> Iterator[nn.Module]:
    """Sparse convolutions of an encoder in the order its forward pass runs them."""
    for child in module.children():
        if isinstance(child, (SubMConv3d, SparseConv3d)):
            yield child
        else:
            yield from _conv_modules(child)


def encoder_conv_specs(encoder: nn.Module) -> list[ConvSpec]:
    """One :class:`ConvSpec` per rulebook key of ``encoder`` (a :class:`~occkit.models.lidar_encoder.SparseEncoder`),
    in forward order (``subm1, spconv1, ..., spconv_down2``).

    Raises:
        ValueError: if two convolutions share a key but differ in geometry (the rulebook could not serve both),
            or a convolution is dilated.
    """
    specs: dict[str, ConvSpec] = {}
    shape = tuple(encoder.sparse_shape)
    for conv in _conv_modules(encoder):
        kernel, stride, padding = (tuple(int(v) for v in getattr(conv, a)) for a in ("kernel_size", "stride",
                                                                                      "padding"))
        if any(int(d) != 1 for d in conv.dilation):
            raise ValueError(f"sparse convolution {conv.indice_key!r} is dilated; rulebooks support dilation 1 only")
        if conv.subm:
            out_shape = shape
            stride = (1, 1, 1)
            padding = tuple(k // 2 for k in kernel)
        else:
            out_shape = tuple((n + 2 * p - k) // s + 1 for n, k, s, p in zip(shape, kernel, stride, padding,
                                                                              strict=True))
        spec = ConvSpec(conv.indice_key, bool(conv.subm), kernel, stride, padding, shape, out_shape)
        if spec.key in specs and specs[spec.key] != spec:
            raise ValueError(f"sparse convolutions sharing key {spec.key!r} differ: {specs[spec.key]} vs {spec}")
        specs[spec.key] = spec
        shape = out_shape
    return list(specs.values())


def coordinate_keys(coords: Tensor, shape: Sequence[int]) -> Tensor:
    """``(N,)`` int64 row-major keys of ``(N, 4)`` ``(batch, x, y, z)`` coordinates inside ``shape = (X, Y, Z)``."""
    size_x, size_y, size_z = (int(s) for s in shape)
    return ((coords[:, 0] * size_x + coords[:, 1]) * size_y + coords[:, 2]) * size_z + coords[:, 3]


def decode_keys(keys: Tensor, shape: Sequence[int]) -> Tensor:
    """Inverse of :func:`coordinate_keys`: ``(N,)`` keys -> ``(N, 4)`` ``(batch, x, y, z)``."""
    size_x, size_y, size_z = (int(s) for s in shape)
    z = keys % size_z
    y = keys // size_z % size_y
    x = keys // (size_z * size_y) % size_x
    return torch.stack((keys // (size_z * size_y * size_x), x, y, z), dim=1)


def kernel_offsets(kernel_size: Sequence[int], offsets: Sequence[int], device: torch.device) -> Tensor:
    """``(K', 3)`` int64 ``(ix, iy, iz)`` of the flat kernel offsets."""
    flat = torch.tensor(list(offsets), dtype=torch.int64, device=device)
    _, ky, kz = kernel_size
    return torch.stack((flat // (ky * kz), flat // kz % ky, flat % kz), dim=1)


def _pad_pairs(found: Tensor, in_rows: Tensor, out_rows: Tensor, num_out: int) -> Tensor:
    """``(K', N)`` candidate pairs and their validity -> the ``(2, K', L)`` padded rulebook, pairs kept in order."""
    counts = found.sum(dim=1)
    longest = int(counts.max()) if counts.numel() else 0
    pairs = torch.zeros(2, found.shape[0], longest, dtype=torch.int64, device=found.device)
    pairs[1] = num_out
    offset, column = found.nonzero(as_tuple=True)
    slot = (found.cumsum(dim=1) - 1)[offset, column]  # rank of each valid pair within its offset
    pairs[0, offset, slot] = in_rows[offset, column]
    pairs[1, offset, slot] = out_rows[offset, column]
    return pairs


def submanifold_rulebook(coords: Tensor, spec: ConvSpec) -> Tensor:
    """Rulebook of a submanifold convolution (odd kernel, stride 1, padding ``kernel // 2``), centre left out.

    Args:
        coords: ``(N, 4)`` int64 unique ``(batch, x, y, z)`` active sites inside ``spec.in_shape``.
        spec: the layer (``subm`` True).

    Returns:
        ``(2, K - 1, L)`` pairs, see the module docstring; the output rows are the rows of ``coords``.
    """
    if any(k % 2 == 0 for k in spec.kernel_size):
        raise ValueError(f"submanifold convolution {spec.key!r} needs an odd kernel, got {spec.kernel_size}")
    coords = coords.to(torch.int64)
    device = coords.device
    keys, order = torch.sort(coordinate_keys(coords, spec.in_shape))
    delta = kernel_offsets(spec.kernel_size, spec.offsets, device) - torch.tensor(spec.padding, device=device)
    neighbours = coords[None, :, 1:] + delta[:, None]  # (K', N, 3): the input each output reads through offset k
    upper = torch.tensor(spec.in_shape, device=device)
    inside = ((neighbours >= 0) & (neighbours < upper)).all(dim=-1)  # (K', N)
    batch = coords[None, :, :1].expand(len(spec.offsets), -1, -1)
    query = coordinate_keys(torch.cat((batch, neighbours), dim=-1).reshape(-1, 4), spec.in_shape).view_as(inside)
    # Hash lookup by binary search in the sorted keys; a miss lands on some other key (or is clamped) and fails ==.
    position = torch.searchsorted(keys, query).clamp(max=max(keys.numel() - 1, 0))
    found = inside & (keys[position] == query)
    outputs = torch.arange(coords.shape[0], device=device).expand_as(found)
    return _pad_pairs(found, order[position], outputs, coords.shape[0])


def strided_rulebook(coords: Tensor, spec: ConvSpec) -> tuple[Tensor, Tensor]:
    """Rulebook and output sites of a strided (regular) sparse convolution.

    Args:
        coords: ``(N, 4)`` int64 unique ``(batch, x, y, z)`` active input sites inside ``spec.in_shape``.
        spec: the layer (``subm`` False).

    Returns:
        pairs: ``(2, K, L)``, see the module docstring.
        out_coords: ``(N_out, 4)`` every output site some input reaches, ascending ``(batch, x, y, z)``.
    """
    coords = coords.to(torch.int64)
    device = coords.device
    kernel = kernel_offsets(spec.kernel_size, spec.offsets, device)  # (K, 3)
    stride = torch.tensor(spec.stride, device=device)
    # Input i reaches output o through offset k when i + p - k = o * s with 0 <= o < out_shape.
    numerator = coords[None, :, 1:] + torch.tensor(spec.padding, device=device) - kernel[:, None]  # (K, N, 3)
    outputs = torch.div(numerator, stride, rounding_mode="floor")
    upper = torch.tensor(spec.out_shape, device=device)
    valid = ((numerator >= 0) & (numerator % stride == 0) & (outputs < upper)).all(dim=-1)  # (K, N)
    batch = coords[None, :, :1].expand(len(spec.offsets), -1, -1)
    keys = coordinate_keys(torch.cat((batch, outputs), dim=-1).reshape(-1, 4), spec.out_shape).view_as(valid)
    out_keys = torch.unique(keys[valid])  # sorted
    out_rows = torch.searchsorted(out_keys, keys).clamp(max=max(out_keys.numel() - 1, 0))
    inputs = torch.arange(coords.shape[0], device=device).expand_as(valid)
    pairs = _pad_pairs(valid, inputs, out_rows, out_keys.numel())
    return pairs, decode_keys(out_keys, spec.out_shape)


def build_rulebooks(specs: Sequence[ConvSpec], coords: Tensor) -> dict[str, Rulebook]:
    """Rulebooks of every layer of an encoder for one batch of voxels: what spconv computes on the fly.

    Args:
        specs: from :func:`encoder_conv_specs`, in forward order.
        coords: ``(V, 4)`` integer ``(batch, x, y, z)`` unique voxel sites inside ``specs[0].in_shape``.

    Returns:
        key -> :class:`Rulebook`, in the order of ``specs``.
    """
    if coords.dim() != 2 or coords.shape[1] != 4 or coords.is_floating_point():
        raise ValueError(f"coords must be an integer (V, 4) tensor of (batch, x, y, z), got {tuple(coords.shape)} "
                         f"{coords.dtype}")
    sites = coords.to(torch.int64)
    rulebooks = {}
    with torch.no_grad():
        for spec in specs:
            if spec.subm:
                rulebooks[spec.key] = Rulebook(submanifold_rulebook(sites, spec), sites)
            else:
                pairs, sites = strided_rulebook(sites, spec)
                rulebooks[spec.key] = Rulebook(pairs, sites)
    return rulebooks


def sparse_conv(features: Tensor, weight: Tensor, pairs: Tensor, spec: ConvSpec, num_out: int) -> Tensor:
    """One sparse convolution from its rulebook: gather -> batched matmul -> scatter-add (+ the centre, submanifold).

    Args:
        features: ``(N_in, C_in)`` features of the input sites.
        weight: ``(C_out, kx, ky, kz, C_in)`` spconv weight.
        pairs: ``(2, K', L)`` rulebook of ``spec``.
        spec: the layer.
        num_out: ``N_out``, an int (a symbolic size while exporting, read from a coordinate input).

    Returns:
        ``(N_out, C_out)``.
    """
    c_out, c_in = weight.shape[0], weight.shape[-1]
    kernel = weight.reshape(c_out, spec.num_offsets, c_in)  # (C_out, K, C_in)
    listed = kernel[:, list(spec.offsets)].permute(1, 2, 0)  # (K', C_in, C_out)
    offsets = len(spec.offsets)
    # take: an input row is read through several offsets, and take's backward sums them in a fixed order on the CPU.
    products = torch.bmm(take(features, pairs[0]), listed)  # (K', L, C_out)
    # Each (output row, offset) gets a row of its own, (N_out + 1) * K' rows: within one offset an output row
    # occurs once, so only padding pairs (into the dump row N_out) share a row. index_add becomes a row-wise
    # ScatterND(reduction="add"), which onnxruntime spreads over threads without guarding repeated rows: summing
    # the offsets in the scatter itself would race. (scatter_add, i.e. ScatterElements, is race-free there but
    # element by element, ten times slower; one scatter per offset multiplies the graph's nodes by K'.)
    slots = pairs[1] * offsets + torch.arange(offsets, device=pairs.device)[:, None]  # (K', L)
    per_offset = features.new_zeros((num_out + 1) * offsets, c_out)
    per_offset = per_offset.index_add(0, slots.reshape(-1), products.reshape(-1, c_out))
    out = per_offset.view(-1, offsets, c_out).sum(dim=1)[:-1]  # (N_out, C_out), the dump row dropped
    if spec.centre is not None:
        out = out + features @ kernel[:, spec.centre].T
    return out


class RulebookSparseEncoder(nn.Module):
    """A :class:`SparseEncoder` executed from rulebooks with standard operators; it shares the encoder's parameters.

    ``forward(features, pairs, out_coords)`` with ``pairs`` one ``(2, K', L)`` tensor per :attr:`specs` entry and
    ``out_coords`` one ``(N_out, 4)`` tensor per :attr:`strided_specs` entry (their lengths size the outputs; the
    last one places the final features in the dense volume) returns the encoder's ``(B, C * Z', X', Y')`` BEV map.

    Args:
        encoder: the spconv encoder, usually in eval mode (BatchNorm runs as the encoder's modules are set).
        batch_size: ``B`` of the BEV map.
    """

    def __init__(self, encoder: nn.Module, batch_size: int) -> None:
        super().__init__()
        self.encoder = encoder
        self.batch_size = batch_size
        self.specs = encoder_conv_specs(encoder)
        self.strided_specs = [spec for spec in self.specs if not spec.subm]
        if not self.strided_specs or tuple(self.strided_specs[-1].out_shape) != tuple(encoder.output_shape):
            raise ValueError(f"the encoder's last convolution must be strided and produce {encoder.output_shape}")
        self._spec_index = {spec.key: i for i, spec in enumerate(self.specs)}

    def rulebook_tensors(self, coords: Tensor) -> tuple[list[Tensor], list[Tensor]]:
        """``(pairs, out_coords)`` for :meth:`forward` from ``(V, 4)`` voxel coordinates (outside any graph)."""
        rulebooks = build_rulebooks(self.specs, coords)
        return [rulebooks[s.key].pairs for s in self.specs], [rulebooks[s.key].out_coords for s in self.strided_specs]

    def forward(self, features: Tensor, pairs: Sequence[Tensor], out_coords: Sequence[Tensor]) -> Tensor:
        if len(pairs) != len(self.specs) or len(out_coords) != len(self.strided_specs):
            raise ValueError(f"expected {len(self.specs)} rulebooks and {len(self.strided_specs)} coordinate tensors, "
                             f"got {len(pairs)} and {len(out_coords)}")
        sizes = {spec.key: coords.shape[0] for spec, coords in zip(self.strided_specs, out_coords, strict=True)}
        rules = dict(zip((s.key for s in self.specs), pairs, strict=True))
        x = self.encoder.run_rows(features, lambda conv, rows: self._conv(conv, rows, rules, sizes))
        return self.encoder.bev_from_rows(x, out_coords[-1], self.batch_size)

    def _conv(self, conv: nn.Module, x: Tensor, rules: Mapping[str, Tensor], sizes: Mapping[str, int]) -> Tensor:
        spec = self.specs[self._spec_index[conv.indice_key]]
        num_out = x.shape[0] if spec.subm else sizes[spec.key]
        return sparse_conv(x, conv.weight, rules[spec.key], spec, num_out)
