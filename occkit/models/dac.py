"""Direction-Aware Convolution (DAC) of DA-Occ, and the DAC + BatchNorm + ReLU block.

**ParC, the static ancestor.** ParC-Net's position-aware circular convolution is a depthwise convolution whose kernel
spans the whole length ``L`` of one axis. A learned positional encoding is added to the input first (a full-length
kernel is otherwise translation invariant along its axis), and the input is concatenated with its own first ``L - 1``
entries along the axis, ``cat([F, F[:L-1]])`` (length ``2L - 1``), so that a "valid" sliding of the length-``L``
kernel returns ``L`` outputs: a circular convolution whose receptive field is the whole axis.

**DAC** (DA-Occ, DAC) makes the kernel a function of the input. For direction ``dir`` in ``{h, v}``:

    W_dir = g(P_dir(F_in))                   one length-L kernel per sample and channel, (B, C, L)
    F_out = DWConv_circ(F_in + PE_dir; W_dir) + b

- ``P_dir`` is directional average pooling: for ``"v"`` the mean over the width gives a per-channel profile of
  length ``H``; for ``"h"`` the mean over the height gives a profile of length ``W``. It pools the input *before*
  the positional encoding is added (``F_in`` in the equation).
- ``g`` turns the pooled profile into kernel weights (see below).
- ``PE_dir`` is a learnable positional encoding of shape ``(C, H, 1)`` for ``"v"`` and ``(C, 1, W)`` for ``"h"``.
- ``DWConv_circ`` is ParC's padding: the input is concatenated with its shifted copy along the direction and the
  full-length kernel slides over it "valid". With ``i`` the output index along the axis, ``K`` the kernel and ``x``
  the (position-encoded) input, both of length ``L``::

      padding="circular":  out[i] = sum_{k=0}^{L-1} K[k] * x[(i + k) mod L]
      padding="zeros":     out[i] = sum_{k=0}^{L-1-i} K[k] * x[i + k]

  (a cross-correlation, as ``torch.nn.functional.conv2d``: ``K[0]`` weighs the output's own position). The circular
  form wraps the far end of the grid onto the near end, which is what the paper specifies with the shifted
  concatenation, so it is the default. ``padding="zeros"`` concatenates ``L - 1`` zeros instead of the shifted copy,
  for users who dislike the wrap: nothing wraps, but the window is one-sided (position ``i`` sees ``i .. L - 1``:
  the first position sees the whole axis, the last only itself).

**Directions in occkit's layouts.** ``"v"`` (vertical) convolves along dim 2, ``"h"`` (horizontal) along dim 3. Image
feature maps are ``(B, C, H, W)`` with ``H`` the image rows, so ``"v"`` mixes along each image column and ``"h"`` along
each image row. BEV tensors are ``(B, C, X, Y)`` (dim 2 is x, forward; dim 3 is y, left), so there ``"v"`` mixes
along x (each line of constant y) and ``"h"`` along y. ``length`` is ``H`` (resp. ``X``) for ``"v"`` and ``W``
(resp. ``Y``) for ``"h"``, fixed at construction: the kernel, the encoding and ``g`` all have that length.

**Design of g.** A two-layer MLP along the length axis, shared by all channels:
``Linear(L, h) -> GELU -> Linear(h, L)`` with ``h = max(1, round(r L))`` (``r = mlp_ratio``), applied to each
channel's profile, plus a learnable static base kernel of shape ``(C, L)``: ``W = K_base + MLP(P(F))``. Sharing the
MLP across channels keeps it at ``2 h L + h + L`` weights whatever ``C`` (per-channel MLPs would cost ``C`` times
that), and its ``2 B C h L`` multiply-adds are a fraction ``2 h / (L M)`` of the convolution's ``B C L^2 M`` (``M`` the
size of the other axis); channels still get distinct kernels through their own profile and their own base kernel.
The base kernel starts like a static depthwise ``Conv2d`` of that size (uniform in ``+-1/sqrt(L)``) and the MLP's
last layer starts small (weights ``N(0, 0.01 / (L h))``, zero bias): for unit-scale pooled profiles the dynamic part
starts near a tenth of the base kernel, so an untrained DAC behaves almost like ParC's static circular convolution
and the input dependence grows as it is learned (small, not zero, so gradients reach the first layer from the first
step). The positional encoding starts small (truncated ``N(0, 0.02^2)``); the bias at zero.

**Implementation of the per-sample depthwise convolution.** A circular (or one-sided zero-padded) convolution along
an axis of length ``L`` is a product with an ``L x L`` circulant (resp. upper-triangular Toeplitz) matrix
``M[i, j] = K[(j - i) mod L]`` (resp. ``K[j - i]`` for ``j >= i``, else 0). DAC builds ``M`` per sample and channel
with one gather from a constant index buffer, ``(B, C, L, L)``, and applies it with one batched matrix product:
``M @ x`` for ``"v"`` and ``x @ M^T`` for ``"h"``. This is the same arithmetic as the grouped convolution over the
concatenated input (``L`` multiply-adds per output) but maps to GEMMs; on a 2-core CPU it trained (forward +
backward) faster than a ``groups=B*C`` conv2d over ``(1, B*C, 2L-1, W)`` in three of the four cases tried and much
faster than unfold + einsum, and in ONNX it is Gather + MatMul, which keeps the batch dimension free (a grouped
convolution bakes ``B * C`` into its ``group`` attribute, freezing the batch size of the exported graph).
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor, nn

from occkit.models.indexing import take

__all__ = ["DirectionAwareConv", "DACBlock", "direction_aware_conv", "band_index"]

Direction = Literal["h", "v"]
Padding = Literal["circular", "zeros"]
_DIRECTIONS = ("h", "v")
_PADDINGS = ("circular", "zeros")


def band_index(length: int, padding: Padding = "circular", device: torch.device | str | None = None) -> Tensor:
    """``(L, L)`` int64 index ``I`` with ``M = K_ext[..., I]`` the convolution matrix of a length-``L`` kernel ``K``.

    ``K_ext`` is ``K`` with one zero appended (``(..., L + 1)``). Circular: ``I[i, j] = (j - i) mod L``; zeros:
    ``I[i, j] = j - i`` for ``j >= i`` and ``L`` (the appended zero) below the diagonal. Then
    ``out[i] = sum_j M[i, j] x[j]`` is the convolution documented in this module.
    """
    if length < 1:
        raise ValueError(f"length must be positive, got {length}")
    if padding not in _PADDINGS:
        raise ValueError(f"padding must be one of {_PADDINGS}, got {padding!r}")
    positions = torch.arange(length, device=device)
    offset = positions[None, :] - positions[:, None]  # j - i
    if padding == "circular":
        return offset.remainder(length)
    return torch.where(offset >= 0, offset, torch.full_like(offset, length))


def _operand_index(
    length: int, padding: Padding, direction: Direction, device: torch.device | str | None = None
) -> Tensor:
    """The :func:`band_index` in the orientation the matrix product uses: as is for ``"v"`` (``M @ x``), transposed
    for ``"h"`` (``x @ M^T``), so that the gather writes ``M^T`` directly instead of transposing a large matrix."""
    index = band_index(length, padding, device)
    return index if direction == "v" else index.t().contiguous()


def _convolve(x: Tensor, kernel: Tensor, index: Tensor, direction: Direction) -> Tensor:
    """Per-sample depthwise convolution of ``x`` ``(B, C, H, W)`` with ``kernel`` ``(B, C, L)`` (or ``(C, L)``)
    along dim 2 (``"v"``, ``L = H``) or dim 3 (``"h"``, ``L = W``), given the ``(L, L)`` :func:`_operand_index`."""
    kernel = nn.functional.pad(kernel, (0, 1))  # (..., L + 1): the last entry is the zero of "zeros" padding
    # Every kernel tap appears L times in the band; take sums their gradients in a fixed order on the CPU, where
    # kernel[..., index] would add them with racing threads (see occkit.models.indexing).
    if torch.onnx.is_in_onnx_export():
        # The same values gathered as rows of the (L + 1, B, C) taps, then transposed: onnxruntime's CPU Gather along
        # the last axis copies one element at a time (9.5 ms for a 200 x 200 band of 32 channels, 2 threads), a row
        # gather and a Transpose take 0.7 ms. PyTorch is faster the other way (its matmul would copy the transpose).
        lead = kernel.dim() - 1  # (B, C) or (C,)
        rows = take(kernel.permute(lead, *range(lead)), index)  # (L, L, *lead)
        operand = rows.permute(*range(2, 2 + lead), 0, 1)
    else:
        operand = take(kernel, index, dim=-1)  # (B, C, L, L): M for "v", M^T for "h"
    if direction == "v":
        return operand @ x  # (B, C, H, H) @ (B, C, H, W): out[:, :, i, w] = sum_j M[i, j] x[:, :, j, w]
    return x @ operand  # (B, C, H, W) @ (B, C, W, W): out[:, :, h, i] = sum_j x[:, :, h, j] M[i, j]


def direction_aware_conv(x: Tensor, kernel: Tensor, direction: Direction, padding: Padding = "circular") -> Tensor:
    """Full-length depthwise convolution of ``x`` ``(B, C, H, W)`` along one axis, with per-sample kernels.

    ``kernel`` is ``(B, C, L)`` (one kernel per sample and channel) or ``(C, L)`` (shared by the batch), with ``L = H``
    for ``direction="v"`` (along dim 2) and ``L = W`` for ``"h"`` (along dim 3). Returns ``(B, C, H, W)``:
    ``out[i] = sum_k K[k] x[(i + k) mod L]`` for ``"circular"``, the same without the wrap (terms past ``L - 1``
    dropped) for ``"zeros"``. No positional encoding, no bias: the bare convolution of :class:`DirectionAwareConv`.
    """
    if direction not in _DIRECTIONS:
        raise ValueError(f"direction must be one of {_DIRECTIONS}, got {direction!r}")
    axis = 2 if direction == "v" else 3
    if x.dim() != 4 or kernel.shape[-1] != x.shape[axis] or kernel.shape[-2] != x.shape[1]:
        raise ValueError(
            f"direction {direction!r} needs x (B, C, H, W) and kernel (B, C, L) or (C, L) with L = x.shape[{axis}]; "
            f"got x {tuple(x.shape)} and kernel {tuple(kernel.shape)}"
        )
    return _convolve(x, kernel, _operand_index(kernel.shape[-1], padding, direction, x.device), direction)


class DirectionAwareConv(nn.Module):
    """DA-Occ's direction-aware convolution: ``(B, C, H, W) -> (B, C, H, W)``, see the module docstring.

    Args:
        channels: ``C``; the convolution is depthwise, so the output has the same channels.
        length: the size of the convolved axis: ``H`` (dim 2) for ``direction="v"``, ``W`` (dim 3) for ``"h"``.
        direction: ``"v"`` convolves along dim 2 (``H``: down each image column; x in BEV), ``"h"`` along dim 3
            (``W``: across each image row; y in BEV).
        padding: ``"circular"`` (the paper's shifted concatenation, wraps around) or ``"zeros"`` (no wrap).
        mlp_ratio: hidden width of the kernel generator ``g`` as a fraction of ``length`` (at least 1 unit).
        bias: add a learnable per-channel bias after the convolution.

    Parameters: ``kernel`` ``(C, L)`` (the static base kernel), ``pos_embed`` ``(C, L, 1)`` for ``"v"`` or ``(C, 1, L)``
    for ``"h"``, the generator ``mlp`` (``Linear(L, h) -> GELU -> Linear(h, L)``, ``h = max(1, round(mlp_ratio L))``)
    and ``bias`` ``(C,)``.
    """

    def __init__(
        self,
        channels: int,
        length: int,
        direction: Direction,
        padding: Padding = "circular",
        mlp_ratio: float = 0.5,
        bias: bool = True,
    ) -> None:
        super().__init__()
        if direction not in _DIRECTIONS:
            raise ValueError(f"direction must be one of {_DIRECTIONS}, got {direction!r}")
        if channels < 1 or length < 1:
            raise ValueError(f"channels and length must be positive, got channels={channels}, length={length}")
        if mlp_ratio <= 0:
            raise ValueError(f"mlp_ratio must be positive, got {mlp_ratio}")
        self.channels = channels
        self.length = length
        self.direction: Direction = direction
        self.padding: Padding = padding
        self.axis = 2 if direction == "v" else 3
        hidden = max(1, round(mlp_ratio * length))
        self.kernel = nn.Parameter(torch.empty(channels, length))
        pe_shape = (channels, length, 1) if direction == "v" else (channels, 1, length)
        self.pos_embed = nn.Parameter(torch.empty(pe_shape))
        self.mlp = nn.Sequential(nn.Linear(length, hidden), nn.GELU(), nn.Linear(hidden, length))
        self.bias = nn.Parameter(torch.zeros(channels)) if bias else None
        self.register_buffer("index", _operand_index(length, padding, direction), persistent=False)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Base kernel as a static depthwise conv of size ``L``, small last MLP layer, small encoding, zero bias."""
        bound = 1.0 / math.sqrt(self.length)
        nn.init.uniform_(self.kernel, -bound, bound)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        first, last = self.mlp[0], self.mlp[2]
        first.reset_parameters()
        nn.init.normal_(last.weight, std=0.1 * bound / math.sqrt(last.in_features))
        nn.init.zeros_(last.bias)
        if self.bias is not None:
            nn.init.zeros_(self.bias)

    def _check(self, x: Tensor) -> None:
        # Plain Python checks on static sizes: nothing enters an exported graph. The TorchScript tracer (legacy ONNX
        # exporter) records sizes as tensors and warns on such comparisons, so it skips them; the length is baked
        # into the traced graph through the index buffer anyway.
        if torch.jit.is_tracing():
            return
        if x.dim() != 4:
            raise ValueError(f"DirectionAwareConv expects (B, C, H, W), got shape {tuple(x.shape)}")
        if x.shape[1] != self.channels:
            raise ValueError(f"DirectionAwareConv expects {self.channels} channels, got {x.shape[1]}")
        if x.shape[self.axis] != self.length:
            name = "H (dim 2)" if self.direction == "v" else "W (dim 3)"
            raise ValueError(
                f"DirectionAwareConv(direction={self.direction!r}) expects {name} = length = {self.length}, "
                f"got {x.shape[self.axis]} (input shape {tuple(x.shape)})"
            )

    def pool(self, x: Tensor) -> Tensor:
        """``P_dir``: ``(B, C, H, W) -> (B, C, L)``, the mean over W for ``"v"`` (L = H), over H for ``"h"`` (L = W)."""
        return x.mean(dim=3 if self.direction == "v" else 2)

    def dynamic_kernel(self, x: Tensor) -> Tensor:
        """``W_dir = K_base + g(P_dir(x))``: ``(B, C, H, W) -> (B, C, L)``, one kernel per sample and channel."""
        return self.kernel + self.mlp(self.pool(x))

    def forward(self, x: Tensor) -> Tensor:
        """``(B, C, H, W) -> (B, C, H, W)``; the size along the direction must equal ``length``."""
        self._check(x)
        kernel = self.dynamic_kernel(x)  # (B, C, L), from the input before the positional encoding
        out = _convolve(x + self.pos_embed, kernel, self.index, self.direction)
        if self.bias is not None:
            out = out + self.bias[:, None, None]
        return out

    def extra_repr(self) -> str:
        return (
            f"channels={self.channels}, length={self.length}, direction={self.direction!r}, "
            f"padding={self.padding!r}, hidden={self.mlp[0].out_features}, bias={self.bias is not None}"
        )


class DACBlock(nn.Module):
    """``DirectionAwareConv`` (no bias) + ``BatchNorm2d`` + ``ReLU``: ``(B, C, H, W) -> (B, C, H, W)``.

    The unit DA-Occ puts in its HeightNet in place of a 3x3 conv-BN-ReLU block. Arguments as
    :class:`DirectionAwareConv`.
    """

    def __init__(
        self,
        channels: int,
        length: int,
        direction: Direction,
        padding: Padding = "circular",
        mlp_ratio: float = 0.5,
    ) -> None:
        super().__init__()
        self.conv = DirectionAwareConv(channels, length, direction, padding, mlp_ratio, bias=False)
        self.bn = nn.BatchNorm2d(channels)
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        """``(B, C, H, W) -> (B, C, H, W)``."""
        return self.act(self.bn(self.conv(x)))
