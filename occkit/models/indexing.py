"""Indexing whose gradient is summed in a fixed order on the CPU, so that training with several threads repeats bitwise.

``source[index]`` with an integer tensor (advanced indexing) differentiates through ``index_put_(accumulate=True)``.
On the CPU, for float32 with more than one thread and at least 32768 elements, that kernel adds the gradient rows
in parallel with atomic float additions: where an index repeats (a context row feeding several depth bins, a kernel
tap read by every row of a band matrix), the order of the additions, and so the rounding of the sum, follows thread
scheduling. Two identical runs then drift apart from the first backward pass.

:func:`take` gives the same values through ``index_select``, whose backward is ``index_add_``: on the CPU it adds in
the order of the index, either serially or (rows of a 2-D tensor) after a stable sort by destination, each destination
row summed by one thread, so the result depends neither on scheduling nor on the thread count. On CUDA ``index_add_``
adds atomically, unless ``torch.use_deterministic_algorithms(True)`` is set; occkit promises no bitwise repeatability
there. That switch would also make the CPU kernel of ``x[index]`` serial, but it is process-wide and changes or
forbids CUDA kernels, so occkit leaves it to the user.
"""

from __future__ import annotations

from torch import Tensor

__all__ = ["take"]


def take(source: Tensor, index: Tensor, dim: int = 0) -> Tensor:
    """``source`` indexed along ``dim`` by an integer tensor of any shape, e.g. ``take(x, i) == x[i]``.

    Args:
        source: any tensor.
        index: integer tensor of any shape; entries may repeat.
        dim: the dimension of ``source`` that ``index`` selects from.

    Returns:
        ``source`` with dimension ``dim`` replaced by ``index.shape``.
    """
    dim = dim % source.dim()
    if index.dim() == 1:
        return source.index_select(dim, index)
    return source.index_select(dim, index.reshape(-1)).unflatten(dim, index.shape)
