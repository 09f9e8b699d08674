"""spconv, with its CPU backward fixed: the one module in occkit that imports spconv.

Import sparse convolutions from here, never from ``spconv`` directly, so the fix below is always in place.

The fix (spconv 2.3.8, CPU PyPI build): forward runs on CPU, but the backward of every native sparse convolution
(``SubMConv3d``, ``SparseConv3d``, ``SparseInverseConv3d``) goes through ``spconv.pytorch.ops.indice_conv_backward``,
which calls ``get_current_stream()`` unconditionally, before it branches to its CPU gather-matmul-scatter path.
Every other call site in ``ops.py`` asks for the stream only for CUDA tensors. ``get_current_stream``
(``spconv.pytorch.cppcore``) returns ``torch.cuda.current_stream().cuda_stream``, so without CUDA the backward dies
in ``torch.cuda._lazy_init`` with ``RuntimeError: Found no NVIDIA driver on your system``. The CPU path never uses
the stream, so we rebind the name ``get_current_stream`` inside ``spconv.pytorch.ops`` (the only reference that
function sees) to one returning the null stream ``0``, the value ``ops.py`` itself uses for CPU tensors.
The rebinding happens once, at import, and only when CUDA is unavailable: with CUDA the original getter works for
CPU tensors too, and spconv is left untouched. No file of spconv is modified.

A second CPU bug, fixed here too: the CPU kernel ``scatter_add_cpu`` (``spconv/csrc/sparse/gather.py``) runs its
rows in parallel threads but shares its two row pointers between the threads (declared outside the parallel
lambda), so with more than one thread rows are added to the wrong outputs: wrong forward features and wrong input
gradients, more often the larger the layer or the busier the machine. ``spconv.pytorch.ops`` calls it only for CPU
tensors; we give that module a ``SpconvOps`` whose ``scatter_add_cpu`` is ``torch.index_add_`` on the same memory,
everything else delegating to spconv's own class. CUDA tensors never reach it.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence

# Two messages spconv 2.3.8 triggers on every run that are not the user's to act on: its dense scatter indexes with
# a list (a PyTorch deprecation warning from spconv's own code), and a torch.fx note about is_fx_tracing that its
# import path prints. Silenced narrowly: only that message, only that logger's warnings.
warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing",
                        category=UserWarning)
logging.getLogger("torch.fx._symbolic_trace").setLevel(logging.ERROR)

import spconv.pytorch as spconv  # noqa: E402
import spconv.pytorch.ops as _spconv_ops  # noqa: E402
import torch  # noqa: E402
from spconv.pytorch import SparseConv3d, SparseConvTensor, SparseSequential, SubMConv3d  # noqa: E402
from torch import Tensor  # noqa: E402

__all__ = [
    "spconv",
    "SparseConvTensor",
    "SubMConv3d",
    "SparseConv3d",
    "SparseSequential",
    "SPCONV_CPU_BACKWARD_PATCHED",
    "sparse_tensor_from_voxels",
]


def _null_stream() -> int:
    """The CUDA null stream, for a process without CUDA where only CPU tensors can reach spconv."""
    return 0


_null_stream.occkit_patch = True  # type: ignore[attr-defined]


def _patch_cpu_backward() -> bool:
    """Rebind ``spconv.pytorch.ops.get_current_stream`` when CUDA is unavailable; return whether it is rebound."""
    if torch.cuda.is_available():
        return False
    # Checking a marker rather than identity keeps this idempotent across a reload of this module.
    if not getattr(_spconv_ops.get_current_stream, "occkit_patch", False):
        _spconv_ops.get_current_stream = _null_stream
    return True


#: True when spconv's stream getter is rebound so that CPU backward works (always on a machine without CUDA).
SPCONV_CPU_BACKWARD_PATCHED: bool = _patch_cpu_backward()


class _RaceFreeSpconvOps:
    """spconv's ``SpconvOps`` with a thread-safe ``scatter_add_cpu``; every other attribute is spconv's own."""

    occkit_patch = True

    def __init__(self, ops: type) -> None:
        self._ops = ops

    def __getattr__(self, name: str):
        return getattr(self._ops, name)

    @staticmethod
    def scatter_add_cpu(out, inp, inds) -> None:
        """``out[inds[i]] += inp[i]`` for ``i < len(inds)``, on spconv (tensorview) CPU tensors, in place."""
        indices = torch.from_numpy(inds.numpy_view()).long()
        rows = torch.from_numpy(inp.numpy_view())[: indices.numel()]
        torch.from_numpy(out.numpy_view()).index_add_(0, indices, rows)


def _patch_cpu_scatter_add() -> None:
    if not getattr(_spconv_ops.SpconvOps, "occkit_patch", False):
        _spconv_ops.SpconvOps = _RaceFreeSpconvOps(_spconv_ops.SpconvOps)


_patch_cpu_scatter_add()


def sparse_tensor_from_voxels(
    features: Tensor,
    coords: Tensor,
    spatial_shape: Sequence[int],
    batch_size: int,
) -> SparseConvTensor:
    """Wrap voxel features in a spconv tensor: the one place occkit coordinates meet spconv's.

    spconv indices are int32 ``(batch, d0, d1, d2)`` with ``d*`` in the order of ``spatial_shape``. occkit keeps its
    ``(x, y, z)`` order throughout, so ``spatial_shape`` is ``(X, Y, Z)``, ``.dense()`` is ``(B, C, X, Y, Z)`` and
    per-axis kernel sizes and strides are given as ``(x, y, z)``; mmdet3d configs, written for ``(z, y, x)``, need
    their per-axis tuples reversed.

    Args:
        features: ``(V, C)`` voxel features.
        coords: ``(V, 4)`` integer ``(batch, x, y, z)``, as from ``occkit.geometry.voxelize.voxelize_batch``; each
            row must be unique and inside ``[0, batch_size) x [0, X) x [0, Y) x [0, Z)``.
        spatial_shape: ``(X, Y, Z)`` grid size, usually ``VoxelGrid.shape``.
        batch_size: ``B``.

    Returns:
        ``SparseConvTensor`` on the features' device.
    """
    if features.dim() != 2:
        raise ValueError(f"features must have shape (V, C), got {tuple(features.shape)}")
    if coords.dim() != 2 or coords.shape[1] != 4 or coords.shape[0] != features.shape[0]:
        raise ValueError(
            f"coords must have shape (V, 4) = ({features.shape[0]}, 4) as (batch, x, y, z), got {tuple(coords.shape)}"
        )
    if coords.is_floating_point():
        raise TypeError(f"coords must be an integer tensor, got {coords.dtype}")
    if coords.device != features.device:
        raise ValueError(f"coords are on {coords.device} but features are on {features.device}")
    if len(spatial_shape) != 3 or any(int(s) < 1 for s in spatial_shape):
        raise ValueError(f"spatial_shape must be three positive sizes (X, Y, Z), got {tuple(spatial_shape)}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    indices = coords.to(torch.int32).contiguous()
    return SparseConvTensor(features.contiguous(), indices, [int(s) for s in spatial_shape], batch_size)
