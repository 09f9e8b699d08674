"""A DataLoader whose worker errors reach the main process as the worker raised them.

PyTorch sends an error of a loader worker back as its type and formatted traceback, and raises
``type("Caught X in DataLoader worker process 0.\\nOriginal Traceback ...")`` in the main process: the one-line
message of a broken sample becomes kilobytes of someone else's traceback, and an error whose type cannot be rebuilt
from one string (``UnicodeDecodeError``, an error with required arguments) turns into a ``RuntimeError``, which the
command line reports as occkit's own bug. :func:`sample_loader` makes a worker hand its error over as a value
instead: the error itself (pickled), raised again in the main process with the same type and message as with no
workers; the worker's traceback is attached as its cause, so ``--debug`` still shows where in the worker it happened.
"""

from __future__ import annotations

import pickle
import traceback
from collections.abc import Callable, Iterator
from typing import Any

from torch.utils.data import DataLoader, Dataset, get_worker_info

from occkit.errors import InputError, is_input_error

__all__ = ["sample_loader", "WorkerFailure", "WorkerTraceback"]


class WorkerTraceback(Exception):
    """The traceback of an error in a loader worker, as text (the cause of the error raised again)."""

    def __str__(self) -> str:
        return f"\n{self.args[0]}" if self.args else ""


class WorkerFailure:
    """An error caught in a loader worker, on its way to the main process as a batch would go."""

    def __init__(self, error: BaseException) -> None:
        self.traceback = "".join(traceback.format_exception(error))
        self.type_name = type(error).__name__
        self.message = str(error)
        self.input_error = is_input_error(error)
        try:
            self.pickled: bytes | None = pickle.dumps(error)
            pickle.loads(self.pickled)  # some errors pickle but cannot be rebuilt (required arguments)
        except Exception:
            self.pickled = None

    def error(self) -> BaseException:
        """The worker's error, rebuilt in this process, with the worker's traceback as its cause."""
        if self.pickled is not None:
            error = pickle.loads(self.pickled)
        else:  # keep what the command line needs: the message and whether the user's input caused it
            kind = InputError if self.input_error else RuntimeError
            error = kind(f"{self.type_name}: {self.message}" if self.message else self.type_name)
        error.__cause__ = WorkerTraceback(self.traceback)
        return error


def _in_worker() -> bool:
    return get_worker_info() is not None


class _CatchingDataset(Dataset):
    """The dataset, whose errors in a worker process are returned as a :class:`WorkerFailure` (raised with none)."""

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def __getitem__(self, index: int) -> Any:
        if not _in_worker():
            return self.dataset[index]
        try:
            return self.dataset[index]
        except Exception as error:
            return WorkerFailure(error)


class _CatchingCollate:
    """The collate function, passing a sample's failure on as the batch (and catching its own in a worker)."""

    def __init__(self, collate_fn: Callable[[list], Any]) -> None:
        self.collate_fn = collate_fn

    def __call__(self, samples: list) -> Any:
        failure = next((s for s in samples if isinstance(s, WorkerFailure)), None)
        if failure is not None:
            return failure
        if not _in_worker():
            return self.collate_fn(samples)
        try:
            return self.collate_fn(samples)
        except Exception as error:
            return WorkerFailure(error)


class _SampleLoader(DataLoader):
    def __iter__(self) -> Iterator[Any]:  # type: ignore[override]
        for batch in super().__iter__():
            if isinstance(batch, WorkerFailure):
                raise batch.error()
            yield batch


def sample_loader(dataset: Dataset, *, collate_fn: Callable[[list], Any], **options: Any) -> DataLoader:
    """``torch.utils.data.DataLoader(dataset, collate_fn=collate_fn, **options)``, except that an error in a worker
    process is raised in the main process as the worker raised it (same type and message as with ``num_workers=0``).
    """
    return _SampleLoader(_CatchingDataset(dataset), collate_fn=_CatchingCollate(collate_fn), **options)
