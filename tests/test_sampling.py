"""CBGS (mmdetection3d's class-balanced resampling) and the epoch sampler's population: counts worked out by hand,
the reference's draws, determinism, a class without samples, sharding and resuming."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
import torch

from occkit.data import sampling
from occkit.data.sampling import cbgs_indices, class_samples
from occkit.engine.distributed import EpochSampler

#: Six samples and the classes of their boxes; "x" is no class being balanced, sample 5 holds none of them.
SAMPLES = [{"a", "b", "c"}, {"a", "b"}, {"a", "c"}, {"a", "b"}, {"a", "b", "c"}, {"x"}]
CLASSES = ("a", "b", "c")


def _blocks(indices: list[int], counts: list[int]) -> list[list[int]]:
    """``indices`` cut into consecutive runs of ``counts`` (the per-class draws, in class order)."""
    starts = np.cumsum([0, *counts]).tolist()
    assert starts[-1] == len(indices)
    return [indices[start:stop] for start, stop in zip(starts[:-1], starts[1:], strict=True)]


def test_class_samples_lists_each_sample_once_per_class_it_holds():
    assert class_samples(SAMPLES, CLASSES) == [[0, 1, 2, 3, 4], [0, 1, 3, 4], [0, 2, 4]]
    # Repeats in a sample count once; names outside the classes are ignored.
    assert class_samples([["a", "a", "x"], []], ("a", "x", "b")) == [[0], [0], []]


@pytest.fixture()
def draws(monkeypatch) -> list[tuple[list[int], int]]:
    """The ``(samples, count)`` of each ``choice`` call of the generator CBGS draws from, in call order."""
    calls = []

    class Recording(np.random.RandomState):
        def choice(self, a, size=None, *args, **kwargs):
            calls.append((list(a), size))
            return super().choice(a, size, *args, **kwargs)

    monkeypatch.setattr(sampling.np.random, "RandomState", Recording)
    return calls


def test_hand_computed_counts_round_as_mmdetection3d(draws):
    # |S_a| = 5, |S_b| = 4, |S_c| = 3, D = 12, K = 3. ratio_c = (1/3) / (|S_c| / 12), count = int(|S_c| * ratio_c):
    #   a: 5 * ((1/3) / (5/12)) = 3.9999999999999996 in floats -> 3 (exactly 4 on paper: mmdetection3d draws 3)
    #   b: 4 * ((1/3) / (4/12)) = 4.0 -> 4
    #   c: 3 * ((1/3) / (3/12)) = 4.0 -> 4
    indices = cbgs_indices(SAMPLES, CLASSES, seed=0)
    assert draws == [([0, 1, 2, 3, 4], 3), ([0, 1, 3, 4], 4), ([0, 2, 4], 4)]
    assert len(indices) == 3 + 4 + 4
    for name, block in zip(CLASSES, _blocks(indices, [3, 4, 4]), strict=True):
        assert all(name in SAMPLES[i] for i in block), (name, block)
    assert 5 not in indices  # a sample of no balanced class is never drawn


def test_draws_are_the_references_and_deterministic():
    """mmdetection3d seeds numpy's global legacy generator and calls np.random.choice once per class."""
    per_class = [[0, 1, 2, 3, 4], [0, 1, 3, 4], [0, 2, 4]]
    reference = []
    state = np.random.get_state()  # the global generator is the test process's too
    try:
        np.random.seed(7)
        for samples in per_class:
            reference += np.random.choice(samples, int(len(samples) * ((1.0 / 3) / (len(samples) / 12)))).tolist()
    finally:
        np.random.set_state(state)
    assert cbgs_indices(SAMPLES, CLASSES, seed=7) == reference
    assert cbgs_indices(SAMPLES, CLASSES, seed=7) == cbgs_indices(SAMPLES, CLASSES, seed=7)
    draws = {tuple(cbgs_indices(SAMPLES, CLASSES, seed)) for seed in range(20)}
    assert len(draws) > 10  # the seed matters
    assert all(type(i) is int for i in reference)


def test_a_class_without_samples_is_left_out(draws):
    # K = 4 with "d" in no sample (mmdetection3d divides by zero): D = 12, each other class int(|S_c| * (1/4) /
    # (|S_c| / 12)) = 3.0 -> 3 draws, "d" none.
    indices = cbgs_indices(SAMPLES, ("d", *CLASSES), seed=1)
    assert draws == [([0, 1, 2, 3, 4], 3), ([0, 1, 3, 4], 3), ([0, 2, 4], 3)]
    for name, block in zip(CLASSES, _blocks(indices, [3, 3, 3]), strict=True):
        assert all(name in SAMPLES[i] for i in block)


def test_rare_classes_are_drawn_about_as_often_as_common_ones():
    rng = np.random.default_rng(0)
    # 2000 samples: "common" in nearly all, "rare" in 2 %.
    samples = [{"common"} | ({"rare"} if rng.random() < 0.02 else set()) for _ in range(2000)]
    per_class = class_samples(samples, ("common", "rare"))
    duplicated = sum(map(len, per_class))
    counts = [int(len(members) * (0.5 / (len(members) / duplicated))) for members in per_class]
    indices = cbgs_indices(samples, ("common", "rare"), seed=0)
    common_draws, rare_draws = _blocks(indices, counts)
    assert all("rare" in samples[i] for i in rare_draws) and len(set(rare_draws)) <= len(per_class[1])
    assert abs(len(rare_draws) - duplicated / 2) <= 1 and abs(len(common_draws) - duplicated / 2) <= 1
    share = sum("rare" in samples[i] for i in indices) / len(indices)
    assert 0.49 < share < 0.53  # half the draws hold the rare class, against 2 % of the samples


@pytest.mark.parametrize(
    "classes, samples, message",
    [
        ((), SAMPLES, "at least one class"),
        (("a", "b", "a"), SAMPLES, r"distinct; 'a' repeated"),
        (("d",), SAMPLES, "no sample of 6 holds a box of the classes d"),
    ],
)
def test_nothing_to_balance_is_an_error(classes, samples, message):
    with pytest.raises(ValueError, match=message):
        cbgs_indices(samples, classes, seed=0)


# ----------------------------------------------------------------------------------------------------- EpochSampler
def _permutation(count: int, seed: int, epoch: int) -> list[int]:
    """The epoch's permutation of ``count`` items, as EpochSampler has always drawn it."""
    return torch.randperm(count, generator=torch.Generator().manual_seed(seed * 1_000_003 + epoch)).tolist()


def test_without_a_population_the_order_is_unchanged():
    for size, batch, world in ((10, 2, 1), (23, 3, 2)):
        for rank in range(world):
            sampler = EpochSampler(size, batch, rank, world, seed=5)
            sampler.set_epoch(3, skip_batches=1)
            order = _permutation(size, 5, 3)
            order = order[: len(order) // (batch * world) * (batch * world)]
            assert list(sampler) == order[rank::world][batch:]
            explicit = EpochSampler(size, batch, rank, world, seed=5, population=range(size))
            explicit.set_epoch(3, skip_batches=1)
            assert list(explicit) == list(sampler)
            assert explicit.batches_per_epoch() == sampler.batches_per_epoch() == size // (batch * world)


def test_a_population_is_shuffled_sharded_and_resumed_as_an_epoch():
    population = cbgs_indices(SAMPLES * 4, CLASSES, seed=3)  # 24 samples, 47 draws with repeats
    assert len(population) > 24 and len(set(population)) < len(population)
    batch, world = 2, 3
    global_batch = batch * world
    epochs = []
    for epoch in range(2):
        shares = []
        for rank in range(world):
            sampler = EpochSampler(24, batch, rank, world, seed=9, population=population)
            sampler.set_epoch(epoch)
            shares.append(list(sampler))
            assert sampler.batches_per_epoch() == len(population) // global_batch == len(shares[-1]) // batch
            # Resuming after k batches continues with this rank's (k + 1)-th batch.
            sampler.set_epoch(epoch, skip_batches=2)
            assert list(sampler) == shares[-1][2 * batch :] and len(sampler) == len(shares[-1]) - 2 * batch
        expected = [population[i] for i in _permutation(len(population), 9, epoch)]
        expected = expected[: len(expected) // global_batch * global_batch]
        assert shares == [expected[rank::world] for rank in range(world)]
        # The ranks together take the population's draws, each as often as it was drawn (less the cut tail).
        taken = Counter(i for share in shares for i in share)
        assert taken <= Counter(population) and sum(taken.values()) == len(population) // global_batch * global_batch
        epochs.append(shares)
    assert epochs[0] != epochs[1]


def test_evaluation_order_runs_over_the_population_in_order():
    population = [4, 4, 0, 2, 1]
    shares = [list(EpochSampler(5, 2, rank, 2, shuffle=False, population=population)) for rank in range(2)]
    assert shares == [[4, 0, 1], [4, 2]]
    assert list(EpochSampler(5, 2, 1, 2, shuffle=False)) == [1, 3]


def test_a_population_outside_the_dataset_is_an_error():
    with pytest.raises(ValueError, match="population holds 5, not an index of a dataset of 5 samples"):
        EpochSampler(5, 2, population=[0, 5])
    with pytest.raises(TypeError):
        EpochSampler(5, 2, population=[0, 1.5])
