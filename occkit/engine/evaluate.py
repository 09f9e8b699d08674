"""Evaluation of a trained model: Occ3D mIoU / IoU (camera mask) and RayIoU over a dataset split.

It runs over the split in order, sharded over ranks under torchrun; confusion matrices and RayIoU counts are
summed over ranks, so any number of processes gives the same scores. A temporal model is streamed
(:func:`stream_memory`): each rank runs whole scenes, frame by frame in time order, every frame's BEV computed once
and its history kept in a :class:`~occkit.models.temporal.StreamMemory` that a new scene resets.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from occkit import zoo
from occkit.data.collate import collate
from occkit.data.dataset import OccupancyDataset
from occkit.data.loader import sample_loader
from occkit.engine import distributed
from occkit.engine.checkpoint import check_compatible, load_checkpoint
from occkit.experiment import Experiment
from occkit.metrics.confusion import OccupancyMetric
from occkit.metrics.evaluate import write_prediction
from occkit.metrics.origins import records_ray_origins
from occkit.metrics.rayiou import RayCounts, cast_frame
from occkit.metrics.raypq import RayPQCounts
from occkit.models.temporal import StreamMemory
from occkit.zoo import experiment_from_dict

__all__ = [
    "score_model",
    "evaluate_model",
    "load_trained",
    "evaluation_dataset",
    "split_loader",
    "stream_memory",
    "dataset_ray_origins",
]

log = logging.getLogger(__name__)


def split_loader(dataset: OccupancyDataset, batch_size: int, workers: int, context: distributed.Context | None,
                 by_scene: bool = False):  # fmt: skip
    """Every sample once, in order, this rank's share. With ``on_error="skip"`` a batch holds the samples that
    loaded, possibly none (``len(batch) == 0``): pass over those.

    ``by_scene`` (streaming): each rank takes whole scenes (every ``world``-th scene of the split), their frames in
    the split's order, which is each scene's frames in time order."""
    rank, world = (context.rank, context.world_size) if context is not None else (0, 1)
    if by_scene:
        population = [index for scene in dataset.scene_indices()[rank::world] for index in scene]
        sampler = distributed.EpochSampler(len(dataset), batch_size, shuffle=False, population=population)
    else:
        sampler = distributed.EpochSampler(len(dataset), batch_size, rank, world, shuffle=False)
    # sample_loader: a worker's error arrives as the worker raised it (one line naming the sample), not as torch's
    # "Caught X in DataLoader worker process" with the worker's traceback in its message.
    return sample_loader(dataset, batch_size=batch_size, sampler=sampler, num_workers=workers, collate_fn=collate,
                         generator=torch.Generator())  # fmt: skip


def stream_memory(model: nn.Module, batch_size: int) -> tuple[StreamMemory | None, int]:
    """The memory to stream a temporal model with and the batch size to do it at (one frame per step: a frame
    needs the one before it); ``(None, batch_size)`` for a single-frame model."""
    if getattr(model, "temporal", None) is None:
        return None, batch_size
    if batch_size != 1:
        log.info("%s is temporal: streaming one frame at a time (batch size %d ignored)", type(model).__name__,
                 batch_size)  # fmt: skip
    return model.stream(), 1


def _predict(model: nn.Module, batch, memory: StreamMemory | None):
    return model.predict(batch) if memory is None else model.predict(batch, memory=memory)


def dataset_ray_origins(dataset: OccupancyDataset) -> dict[str, np.ndarray]:
    """RayIoU origins (ego positions along each scene) of every key frame of the dataset."""
    return records_ray_origins(dataset.records)


def score_model(
    model: nn.Module,
    dataset: OccupancyDataset,
    *,
    rayiou: bool = True,
    ray_origins: dict[str, np.ndarray] | None = None,
    mask: str | None = "default",
    batch_size: int = 1,
    workers: int = 0,
    context: distributed.Context | None = None,
    predictions: Path | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Score ``model`` on ``dataset``: every command, benchmark and the training loop's validation score through here.

    RayIoU (and for a flow model mAVE and OccScore) is computed when ``rayiou`` is set and the dataset's label space
    defines it, on ``ray_origins`` or, by default, the origins of the dataset's own key-frame poses; the other
    arguments and the result are :func:`evaluate_model`'s.
    """
    if not rayiou or not dataset.space.rayiou:
        ray_origins = None
    elif ray_origins is None:
        ray_origins = dataset_ray_origins(dataset)
    return evaluate_model(model, dataset, batch_size, workers, context, predictions=predictions,
                          ray_origins=ray_origins, progress=progress, mask=mask)  # fmt: skip


@torch.no_grad()
def evaluate_model(
    model: nn.Module,
    dataset: OccupancyDataset,
    batch_size: int = 1,
    workers: int = 0,
    context: distributed.Context | None = None,
    predictions: Path | None = None,
    ray_origins: dict[str, np.ndarray] | None = None,
    progress: Callable[[int], None] | None = None,
    mask: str | None = "default",
) -> dict[str, Any]:
    """Score a model on a labelled dataset split with the protocol of the dataset's label space (Occ3D: the camera
    mask, the official setting; SurroundOcc: every voxel). Callers use :func:`score_model`, which chooses the rays.

    Args:
        model: a zoo model; put in eval mode here.
        dataset: the split, with ``occupancy=True`` and no augmentation; a temporal model streams it scene by scene
            (:func:`stream_memory`), and under the dataset's ``history_dropped`` corruption its memory forgets the
            frames the corruption drops.
        predictions: folder to also write ``<token>.npz`` predictions into.
        ray_origins: token -> origins; when given, RayIoU is computed too (no mask, as SparseOcc); Occ3D's grid only.
        progress: called with the number of samples after each batch (skipped ones included).
        mask: ``camera``, ``lidar``, None (every voxel), or ``default``: the label space's.

    Returns:
        ``miou``, ``iou``, ``per_class_iou``, ``label_space``, ``mask``, ``frames`` (scored), ``skipped`` (frames that
        failed to load under ``on_error="skip"``, not scored) and with origins ``rayiou``, ``rayiou@1/2/4``, and
        for a model with a flow head ``mave`` and ``occ_score`` (the CVPR 2024 challenge's, on the same rays), and for
        a model with an instance head on labels with instance ids (``data.instances``) ``raypq``, ``raypq@1/2/4``.
    """
    space = dataset.space
    if ray_origins is not None and not space.rayiou:
        raise ValueError(f"RayIoU is not defined for {space.name} labels (only on Occ3D's grid); leave it out")
    mask = space.check_mask(space.default_mask if mask == "default" else mask)
    was_training = model.training
    model.eval()
    device = next(model.parameters()).device
    metric = OccupancyMetric.for_space(space, mask)
    ray_counts = RayCounts(space) if ray_origins is not None else None
    panoptic = RayPQCounts()  # a model with an instance head, on labels with instance ids
    panoptic_frames = frames = 0
    memory, batch_size = stream_memory(model, batch_size)
    loader = split_loader(dataset, batch_size, workers, context, by_scene=memory is not None)
    share = len(loader.sampler)
    for index, batch in enumerate(loader):
        if len(batch) > 0:  # else every frame of the batch failed to load (on_error="skip")
            before = memory.state_dict() if memory is not None and dataset.corruption is not None else None
            prediction = _predict(model, batch.to(device), memory)
            semantics = prediction.semantics.cpu().numpy()
            # Flow is scored where the data has it (data.flow); without it, the model is scored as any other.
            scored_flow = prediction.flow is not None and batch.voxel_flow is not None
            flows = prediction.flow.float().cpu().numpy() if scored_flow else None
            scored_instances = prediction.instances is not None and batch.voxel_instances is not None
            instances = prediction.instances.cpu().numpy() if prediction.instances is not None else None
            if before is not None and dataset.corruption.forget(batch.tokens[0]):
                memory.load_state_dict(before)  # the frame is lost to the frames after it (history_dropped)
            labels = batch.voxel_semantics.numpy()
            masks = {name: None if value is None else value.numpy()
                     for name, value in (("mask_camera", batch.mask_camera), ("mask_lidar", batch.mask_lidar))}
            metric.update(labels, semantics, **masks)
            for i, token in enumerate(batch.tokens):
                flow = None if flows is None else flows[i]
                if predictions is not None:
                    write_prediction(predictions, token, semantics[i], flow,
                                     None if instances is None else instances[i])  # fmt: skip
                if ray_origins is not None:
                    rays = cast_frame(labels[i], semantics[i], ray_origins[token], space)
                    ray_counts.add_frame(rays, *(() if flow is None else (batch.voxel_flow[i].numpy(), flow)))
                    if scored_instances:
                        panoptic.add_cast(rays, batch.voxel_instances[i].numpy(), instances[i])
                        panoptic_frames += 1
            frames += len(batch)
        if progress is not None:
            progress(min(batch_size, share - index * batch_size))
    model.train(was_training)
    metric.confusion = distributed.all_reduce_sum(metric.confusion)
    frames, skipped = (int(n) for n in distributed.all_reduce_sum(np.array([frames, share - frames])))
    if skipped:
        log.warning("%d of %d frames failed to load and were skipped (on_error=skip): not scored", skipped,
                    frames + skipped)  # fmt: skip
    result = {**metric.compute(), "label_space": space.name, "mask": mask, "frames": frames, "skipped": skipped}
    if ray_origins is not None:
        ray_counts.reduce(distributed.all_reduce_sum)  # a rank may hold no frame at all: its counts are zeros
        result.update(ray_counts.scores())
        if int(distributed.all_reduce_sum(np.array([panoptic_frames]))[0]):
            panoptic.reduce(distributed.all_reduce_sum)
            scores = panoptic.compute()
            result.update({key: scores[key] for key in ("raypq", "raypq@1", "raypq@2", "raypq@4")})
    return result


def load_trained(
    path: str | Path,
    device: str | torch.device = "cpu",
    experiment: Experiment | None = None,
    overrides: Sequence[str] = (),
) -> tuple[nn.Module, Experiment]:
    """The model of a checkpoint (its EMA weights when it has them) and the experiment to run it with.

    Args:
        path: an occkit checkpoint.
        device: where to put the model.
        experiment: the experiment to use instead of the one saved in the checkpoint (e.g. other data settings);
            its model must be the checkpoint's (a ``ValueError`` names the first difference).
        overrides: ``section.key=value`` changes applied to the saved experiment (when ``experiment`` is None).
    """
    payload = load_checkpoint(path, map_location=device)
    if experiment is None:
        try:
            experiment = experiment_from_dict(payload["experiment"], f"{path} (saved config)")
        except (KeyError, ValueError) as error:
            raise ValueError(f"{path}: its saved experiment no longer loads ({error})") from error
        if overrides:
            experiment = experiment_from_dict(experiment.to_dict(), f"{path} (saved config)", overrides)
    check_compatible(payload, experiment.architecture, experiment.to_dict()["model"], path)
    model = zoo.build_from_config(experiment.architecture, experiment.model).to(device)
    weights = payload["ema"] if payload.get("ema") is not None else payload["model"]
    try:
        model.load_state_dict(weights)
    except RuntimeError as error:
        raise ValueError(f"{path}: weights do not fit the {experiment.architecture} model ({error})") from error
    return model.eval(), experiment


def evaluation_dataset(experiment: Experiment, root: str | Path | None, split: str, labels: bool = True):
    """The experiment's data settings on another root/split, without augmentation (and without history frames: a
    temporal model is streamed, :func:`stream_memory`)."""
    changes: dict[str, Any] = {"split": split, "augment": False, "occupancy": labels, "history": 0}
    if root is not None:
        changes.update(root=str(root), index=None)
    return OccupancyDataset(dataclasses.replace(experiment.data, **changes))
