"""The runs behind ``occkit eval`` and ``occkit predict``: a model from its source scored on a split, or its predictions
written to a folder, on one process or as a ``torchrun`` group.

Under ``torchrun`` every rank loads the model, takes its share of the frames and scores or writes them; the counts are
summed across ranks and rank 0 alone writes the report. The output folder is checked (and, for predictions, locked)
before the model is loaded, so a wrong folder costs nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from occkit.engine import distributed
from occkit.engine.checkpoint import ensure_writable
from occkit.engine.evaluate import evaluation_dataset, score_model
from occkit.engine.predict import predict_to_folder
from occkit.metrics.evaluate import write_report
from occkit.model_source import ModelSource
from occkit.outputs import OutputLock

__all__ = ["evaluate_source", "predict_source"]


def evaluate_source(
    source: ModelSource,
    out: Path,
    *,
    data: str | Path | None = None,
    split: str | None = None,
    overrides: Sequence[str] = (),
    mask: str | None = "default",
    rayiou: bool = True,
    save_predictions: bool = False,
    batch_size: int = 1,
    workers: int = 2,
    device: str | None = None,
    progress: bool = True,
) -> tuple[dict[str, Any], dict[str, Path]] | None:
    """Score ``source``'s model on ``split`` of ``data`` and write ``metrics.json``, ``metrics.md`` and the per-class
    plot into ``out``.

    Args:
        data, split: the dataset root and split (default: the experiment's own root and validation split).
        overrides: ``section.key=value`` changes of the model's experiment.
        mask: ``camera``, ``lidar``, None (every voxel) or ``default`` (the label space's).
        rayiou: also RayIoU (and mAVE and OccScore for a flow model) where the label space defines it.
        save_predictions: also write ``<token>.npz`` predictions into ``out/predictions``.
        device: ``cpu``, ``cuda``, ... (default: CUDA when available; under ``torchrun`` each rank's own GPU).

    Returns:
        On rank 0, the scores (with eval-preds' report keys: ``missing_predictions``, ``checkpoint``, ``split``,
        ``root``) and the report's paths; on the other ranks None.
    """
    context = distributed.setup(device)
    try:
        model, experiment = source.load(context.device, overrides)
        dataset = evaluation_dataset(experiment, data, split or experiment.train.val_split)
        predictions = out / "predictions" if save_predictions else None
        if context.is_main:
            ensure_writable(out)
            if predictions is not None:
                predictions.mkdir(exist_ok=True)
        distributed.barrier()
        share = len(range(context.rank, len(dataset), context.world_size))
        with tqdm(total=share, unit="frame", desc="eval", disable=not (progress and context.is_main)) as bar:
            result = score_model(model, dataset, rayiou=rayiou, mask=mask, batch_size=batch_size, workers=workers,
                                 context=context, predictions=predictions, progress=bar.update)  # fmt: skip
        paths = None
        if context.is_main:
            # Every frame has its prediction here; the keys make the report read like eval-preds' one.
            result.update(missing_predictions=0, checkpoint=str(source), split=dataset.config.split,
                          root=dataset.config.root)  # fmt: skip
            paths = write_report(result, out)
        distributed.barrier()  # every rank leaves the group together, none while another still uses it
    finally:
        distributed.teardown()
    return (result, paths) if context.is_main else None


def predict_source(
    source: ModelSource,
    data: str | Path,
    split: str,
    out: Path,
    *,
    overrides: Sequence[str] = (),
    batch_size: int = 1,
    workers: int = 2,
    device: str | None = None,
    progress: bool = True,
) -> dict[str, int] | None:
    """Write ``source``'s predictions of ``split`` of ``data`` to ``out`` as Occ3D ``<token>.npz`` files; one run per
    folder (a second one is refused while the first holds the folder's lock).

    Returns:
        On rank 0, ``written`` and ``skipped`` (frames that failed to load under ``data.on_error=skip``) summed over
        the ranks; on the other ranks None.
    """
    context = distributed.setup(device)
    lock = OutputLock(out, "occkit predict", enabled=context.is_main)  # rank 0 holds it for the whole group
    try:
        lock.acquire()
        model, experiment = source.load(context.device, overrides)
        dataset = evaluation_dataset(experiment, data, split, labels=False)
        if context.is_main:
            ensure_writable(out)
        distributed.barrier()
        share = len(range(context.rank, len(dataset), context.world_size))
        with tqdm(total=share, unit="frame", desc="predict", disable=not (progress and context.is_main)) as bar:
            counts = predict_to_folder(model, dataset, out, batch_size, workers, context, bar.update)
        distributed.barrier()
    finally:
        lock.release()
        distributed.teardown()
    return counts if context.is_main else None
