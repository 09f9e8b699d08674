"""Training repeats bitwise on the CPU with several threads: the fixed-order gather and a guard over the tiny models.

The one CPU kernel of these models whose result followed thread scheduling was float ``index_put_(accumulate=True)``,
the backward of advanced indexing ``x[index]``: with more than one thread it adds repeated indices with racing atomic
additions. ``occkit.models.indexing.take`` replaces it; the guard below fails if any forward or backward of a tiny
model runs that kernel with repeated indices again.
"""

from __future__ import annotations

import pytest
import torch
from conftest import make_batch, torch_threads
from torch.utils._python_dispatch import TorchDispatchMode

from occkit import zoo
from occkit.models.indexing import take

ACCUMULATING_INDEX_PUT = {torch.ops.aten.index_put.default, torch.ops.aten.index_put_.default,
                          torch.ops.aten._index_put_impl_.default}  # fmt: skip
#: Each tiny model with a batch of the input size its config expects.
TINY_BATCHES = {
    "flashocc_tiny": dict(image_size=(64, 176)),
    "daocc_tiny": dict(image_size=(64, 176)),
    "da_occ_tiny": dict(image_size=(128, 352), depth_stride=16),
}


def _has_repeats(indices) -> bool:
    """Whether the index tensors of an ``index_put`` address some element twice (a bool mask never does)."""
    columns = [index.nonzero(as_tuple=True) if index.dtype == torch.bool else (index,)
               for index in indices if index is not None]  # fmt: skip
    flat = [c.reshape(-1) for c in torch.broadcast_tensors(*(c for group in columns for c in group))]
    keys = torch.stack(flat)
    return torch.unique(keys, dim=1).shape[1] < keys.shape[1]


class _RacingAccumulations(TorchDispatchMode):
    """Records every floating-point ``index_put`` with ``accumulate=True`` and repeated indices, whatever its size."""

    def __init__(self) -> None:
        super().__init__()
        self.found: list[tuple[int, ...]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in ACCUMULATING_INDEX_PUT:
            accumulate = args[3] if len(args) > 3 else kwargs.get("accumulate", False)
            if accumulate and args[0].is_floating_point() and _has_repeats(args[1]):
                self.found.append(tuple(args[0].shape))
        return func(*args, **kwargs)


def _gradients(model: torch.nn.Module, batch) -> list[torch.Tensor]:
    model.zero_grad(set_to_none=True)
    sum(model.loss(model(batch), batch).values()).backward()
    return [p.grad.clone() for p in model.parameters() if p.grad is not None]


# ------------------------------------------------------------------------------------------------------ take
@pytest.mark.parametrize("dim", [0, 1, -1])
def test_take_is_advanced_indexing_with_the_same_gradient(dim):
    source = torch.randn(7, 5, 6, dtype=torch.float64, requires_grad=True)
    index = torch.tensor([[0, 4, 4], [2, 0, 4]])
    expected = source[(slice(None),) * (dim % 3) + (index,)]
    assert torch.equal(take(source, index, dim), expected)
    torch.autograd.gradcheck(lambda s: take(s, index, dim), (source,))
    gradient = torch.randn_like(expected)
    (mine,) = torch.autograd.grad(take(source, index, dim), source, gradient)
    (reference,) = torch.autograd.grad(expected, source, gradient)
    torch.testing.assert_close(mine, reference)


def test_take_gradient_repeats_bitwise_with_twotorch_threads():
    """Sizes above the kernels' parallel grain (32768 elements), every row read about 60 times."""
    generator = torch.Generator().manual_seed(0)
    source = torch.randn(1000, 16, requires_grad=True)
    index = torch.randint(0, 1000, (60_000,), generator=generator)
    gradient = torch.randn(60_000, 16, generator=generator)
    with torch_threads(2):
        first = torch.autograd.grad(take(source, index), source, gradient)[0]
        for _ in range(5):
            assert torch.equal(torch.autograd.grad(take(source, index), source, gradient)[0], first)
    exact = torch.zeros(1000, 16, dtype=torch.float64).index_add_(0, index, gradient.double())
    torch.testing.assert_close(first, exact.float(), rtol=1e-5, atol=1e-5)


def test_the_guard_sees_advanced_indexing_with_repeated_indices():
    source = torch.randn(10, 3, requires_grad=True)
    with _RacingAccumulations() as guard:
        source[torch.tensor([1, 2, 3])].sum().backward()  # distinct: the racing kernel adds each element once
        source[source[:, 0] > 0].sum().backward()  # a mask: distinct too
    assert guard.found == []
    with _RacingAccumulations() as guard:
        source[torch.tensor([1, 2, 1])].sum().backward()
    assert guard.found == [(10, 3)]


# ------------------------------------------------------------------------------------------------------ models
@pytest.mark.parametrize("name", list(TINY_BATCHES))
def test_no_racing_accumulation_in_a_training_step_of_a_tiny_model(name):
    torch.manual_seed(0)
    model = zoo.build(name).train()
    batch = make_batch(batch_size=1, **TINY_BATCHES[name])
    with torch_threads(1), _RacingAccumulations() as guard:  # what runs, not how: one thread is enough, and quicker
        _gradients(model, batch)
    assert guard.found == [], f"index_put(accumulate=True) with repeated indices into tensors of shape {guard.found}"


def test_da_occ_tiny_gradients_repeat_bitwise_with_twotorch_threads():
    """The model whose gradients differed between two identical passes in 4 of 4 tries before the fix."""
    torch.manual_seed(0)
    model = zoo.build("da_occ_tiny").train()
    batch = make_batch(batch_size=1, **TINY_BATCHES["da_occ_tiny"])
    initial = {k: v.clone() for k, v in model.state_dict().items()}
    with torch_threads(2):
        first = _gradients(model, batch)
        model.load_state_dict(initial)  # the train-mode pass moved the BatchNorm statistics
        second = _gradients(model, batch)
    assert len(first) == len(second) and all(torch.equal(a, b) for a, b in zip(first, second, strict=True))
