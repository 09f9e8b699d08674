"""torch.distributed for ``torchrun``: process group setup, sharded samplers and rank-0 helpers.

``torchrun --nproc-per-node N -m occkit train ...`` starts N processes with ``RANK``, ``WORLD_SIZE`` and
``LOCAL_RANK`` set; :func:`setup` joins them into one group (NCCL on CUDA, gloo on CPU). A plain ``occkit train``
runs as a group of one without initialising anything.
"""

from __future__ import annotations

import operator
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist

__all__ = ["Context", "setup", "teardown", "EpochSampler", "StreamSampler", "barrier", "broadcast_object",
           "broadcast_tensors", "all_reduce_mean", "all_reduce_sum"]


@dataclass(frozen=True)
class Context:
    """Where this process stands in the run."""

    rank: int
    world_size: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def setup(device: str | None = None) -> Context:
    """Join the process group when launched by torchrun; choose the device (``cuda:LOCAL_RANK`` when CUDA exists)."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if device is None:
        device = f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu"
    target = torch.device(device)
    if target.type == "cuda":
        if target.index is None:  # plain "cuda": this process's GPU (set_device needs an index)
            target = torch.device("cuda", local_rank)
        torch.cuda.set_device(target)
    else:
        # Subnormal floats (gradients and activations decaying towards zero) run an order of magnitude slower on
        # x86 CPUs; flushing them to zero, as GPUs do by default, changes no result above 1e-38. Process-wide, so
        # teardown() restores PyTorch's default.
        torch.set_flush_denormal(True)
    if world_size > 1 and not dist.is_initialized():
        dist.init_process_group(backend="nccl" if target.type == "cuda" else "gloo")
    return Context(rank=rank, world_size=world_size, device=target)


def teardown() -> None:
    """Leave the process group and restore the float mode :func:`setup` changed."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()
    torch.set_flush_denormal(False)


def barrier() -> None:
    if dist.is_available() and dist.is_initialized():
        dist.barrier()


def broadcast_object(value, src: int = 0):
    """``value`` of rank ``src`` on every rank (itself when not distributed)."""
    if not (dist.is_available() and dist.is_initialized()):
        return value
    holder = [value]
    dist.broadcast_object_list(holder, src=src)
    return holder[0]


def broadcast_tensors(tensors: list[torch.Tensor], src: int = 0) -> None:
    """Overwrite ``tensors`` in place with rank ``src``'s values (one flat broadcast per dtype and device)."""
    if not (dist.is_available() and dist.is_initialized()) or not tensors:
        return
    groups: dict[tuple[torch.dtype, torch.device], list[torch.Tensor]] = {}
    for tensor in tensors:
        groups.setdefault((tensor.dtype, tensor.device), []).append(tensor)
    for group in groups.values():
        flat = torch.cat([t.detach().reshape(-1) for t in group])
        dist.broadcast(flat, src=src)
        offset = 0
        for tensor in group:
            tensor.detach().copy_(flat[offset : offset + tensor.numel()].view_as(tensor))
            offset += tensor.numel()


def all_reduce_sum(array: np.ndarray) -> np.ndarray:
    """Counts or sums ``array`` summed over the ranks (itself outside a process group): integers as int64, anything
    else as float64."""
    if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return array
    device = "cuda" if torch.distributed.get_backend() == "nccl" else "cpu"
    dtype = np.int64 if np.asarray(array).dtype.kind in "iub" else np.float64
    counts = torch.from_numpy(np.ascontiguousarray(array, dtype=dtype)).to(device)
    torch.distributed.all_reduce(counts)
    return counts.cpu().numpy()


def all_reduce_mean(values: dict[str, float], device: torch.device) -> dict[str, float]:
    """The mean of each value over the ranks (the values themselves when not distributed); every rank must call it
    with the same keys."""
    if not (dist.is_available() and dist.is_initialized()) or not values:
        return values
    stacked = torch.tensor(list(values.values()), dtype=torch.float64, device=device)
    dist.all_reduce(stacked)
    stacked /= dist.get_world_size()
    return dict(zip(values, stacked.tolist(), strict=True))


class EpochSampler(torch.utils.data.Sampler[int]):
    """Deterministic per-epoch order, sharded over ranks, that can start part-way through an epoch.

    Training: a permutation of the population (the dataset's indices ``0..size-1``, or a resampled list of them
    such as CBGS's, :func:`occkit.data.sampling.cbgs_indices`) seeded by ``(seed, epoch)``, cut to a whole number
    of global batches (every rank takes the same number of steps), rank ``r`` taking every ``world``-th item from
    ``r``; ``skip_batches`` drops the first batches of this rank's share, so a resumed run continues exactly where it
    stopped. Evaluation (``shuffle=False``): every item of the population once, in order, split over ranks without
    padding.
    """

    def __init__(self, size: int, batch_size: int, rank: int = 0, world_size: int = 1, shuffle: bool = True,
                 seed: int = 0, population: Sequence[int] | None = None) -> None:  # fmt: skip
        """
        Args:
            size: samples in the dataset.
            batch_size: samples per batch on each rank.
            rank, world_size: this process and the number of processes.
            shuffle: a new order every epoch (training), or the population in order (evaluation).
            seed: seed of the orders.
            population: the dataset indices an epoch runs over, repeats allowed (CBGS draws a sample once per class
                it holds and more for rare classes); None: ``range(size)``, each sample once.

        Raises:
            ValueError: an item of ``population`` is not an index of the dataset.
        """
        self.size, self.batch_size, self.rank, self.world_size = size, batch_size, rank, world_size
        self.shuffle, self.seed = shuffle, seed
        self.population: list[int] | None = None
        if population is not None:
            items = [operator.index(i) for i in population]
            outside = [i for i in items if not 0 <= i < size]
            if outside:
                raise ValueError(f"population holds {outside[0]}, not an index of a dataset of {size} samples")
            self.population = items
        self.epoch, self.skip_batches = 0, 0

    def set_epoch(self, epoch: int, skip_batches: int = 0) -> None:
        self.epoch, self.skip_batches = epoch, skip_batches

    def _count(self) -> int:
        """Items in one epoch's population."""
        return self.size if self.population is None else len(self.population)

    def _indices(self) -> list[int]:
        if not self.shuffle:
            if self.population is None:
                return list(range(self.rank, self.size, self.world_size))
            return self.population[self.rank :: self.world_size]
        generator = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        order = torch.randperm(self._count(), generator=generator).tolist()
        if self.population is not None:
            # The same permutation as without a population, applied to its items: an epoch of CBGS is its
            # resampled list shuffled, sharded and resumed as a plain epoch is.
            order = [self.population[i] for i in order]
        global_batch = self.batch_size * self.world_size
        order = order[: len(order) // global_batch * global_batch]
        return order[self.rank :: self.world_size][self.skip_batches * self.batch_size :]

    def batches_per_epoch(self) -> int:
        """Full batches of one epoch on this rank (training order)."""
        return self._count() // (self.batch_size * self.world_size)

    def __iter__(self) -> Iterator[int]:
        return iter(self._indices())

    def __len__(self) -> int:
        return len(self._indices())


class StreamSampler(torch.utils.data.Sampler[int]):
    """Streams of whole scenes, for a model that carries a memory from step to step (streamed training).

    Per epoch the scenes are shuffled, seeded by ``(seed, epoch)``, and dealt one by one to the shortest of
    ``batch_size x world_size`` streams; a stream is its scenes' frames in time order, one scene after the other.
    Batch ``j`` of rank ``r`` holds frame ``j`` of streams ``r B .. r B + B - 1``. Every stream is cut to the
    shortest one's length, so that all batches are full and every rank takes the same number of steps; the frames
    cut off are dealt again, in another order, the next epoch. ``skip_batches`` drops the first batches of the
    epoch, as :class:`EpochSampler`'s, so a resumed run continues where it stopped.
    """

    def __init__(self, scenes: Sequence[Sequence[int]], batch_size: int, rank: int = 0, world_size: int = 1,
                 seed: int = 0) -> None:  # fmt: skip
        """
        Args:
            scenes: the dataset indices of each scene's frames, in time order.
            batch_size: streams per rank (samples per batch); rank, world_size: this process and their number.
            seed: seed of the deals.

        Raises:
            ValueError: fewer scenes than streams (some stream would stay empty).
        """
        streams = batch_size * world_size
        if len(scenes) < streams:
            raise ValueError(f"streamed training needs a scene per stream: {len(scenes)} scenes for {batch_size} "
                             f"samples per batch x {world_size} processes")
        self.scenes = [list(scene) for scene in scenes]
        self.batch_size, self.rank, self.world_size, self.seed = batch_size, rank, world_size, seed
        self.epoch, self.skip_batches = 0, 0

    def set_epoch(self, epoch: int, skip_batches: int = 0) -> None:
        self.epoch, self.skip_batches = epoch, skip_batches

    def streams(self) -> list[list[int]]:
        """Every stream of this epoch (all ranks'), cut to the same length."""
        generator = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        streams: list[list[int]] = [[] for _ in range(self.batch_size * self.world_size)]
        for scene in torch.randperm(len(self.scenes), generator=generator).tolist():
            min(streams, key=len).extend(self.scenes[scene])
        length = min(len(stream) for stream in streams)
        return [stream[:length] for stream in streams]

    def batches_per_epoch(self) -> int:
        """Full batches of one epoch on this rank."""
        return len(self.streams()[0])

    def _indices(self) -> list[int]:
        mine = self.streams()[self.rank * self.batch_size : (self.rank + 1) * self.batch_size]
        order = [stream[j] for j in range(len(mine[0])) for stream in mine]
        return order[self.skip_batches * self.batch_size :]

    def __iter__(self) -> Iterator[int]:
        return iter(self._indices())

    def __len__(self) -> int:
        return len(self._indices())

