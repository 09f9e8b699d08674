"""The training loop: AdamW, warm-up + cosine schedule, clipping, accumulation, AMP, EMA, validation, resume.

``train(experiment, out)`` runs one experiment into a run folder (``occkit train`` is a thin wrapper). Single-process
CPU runs are bitwise deterministic at a fixed thread count (any count, but the same one: runs with other counts differ
in the last bits): a run killed at any moment and resumed with ``resume="auto"`` ends with the same weights as one
never interrupted, because a checkpoint holds the model, optimizer, schedule, EMA, every random generator and the data
position, the data order and augmentations are pure functions of (seed, epoch, index), and the models sum gradients
in a fixed order (``occkit.models.indexing``). CUDA runs are not bitwise deterministic. Under torchrun
every rank holds one and the same model at every step (BatchNorm running statistics are rank 0's), so the sharded
validation scores exactly the weights that are saved.
"""

from __future__ import annotations

import copy
import random
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from occkit import zoo
from occkit.classes import DETECTION_CLASSES
from occkit.config import ConfigError
from occkit.convert import load_partial
from occkit.data.collate import collate
from occkit.data.dataset import OccupancyDataset
from occkit.data.loader import sample_loader
from occkit.data.sampling import cbgs_indices
from occkit.engine import distributed
from occkit.engine.checkpoint import (
    atomic_save,
    check_resumable,
    ensure_writable,
    latest_checkpoint,
    load_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from occkit.engine.evaluate import score_model
from occkit.engine.run_log import RunLog, plot_losses
from occkit.engine.schedule import Schedule
from occkit.experiment import Experiment, TrainConfig, check_label_space, experiment_yaml
from occkit.metrics.evaluate import plot_per_class_iou
from occkit.models import pretrained
from occkit.models.temporal import StreamMemory
from occkit.outputs import OutputLock
from occkit.types import Batch

__all__ = ["train", "ModelEMA", "TrainResult", "check_output_folder", "check_initial_weights", "accumulation"]


@dataclass
class TrainResult:
    """What a finished run reports."""

    out: Path
    steps: int
    metrics: dict | None
    best_miou: float | None
    seconds: float


class ModelEMA:
    """Exponential moving average of a model's parameters (buffers copied), the weights validated and exported."""

    def __init__(self, model: nn.Module) -> None:
        self.module = copy.deepcopy(model).eval()
        for p in self.module.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def update(self, model: nn.Module, decay: float) -> None:
        for ema, current in zip(self.module.state_dict().values(), model.state_dict().values(), strict=True):
            if ema.dtype.is_floating_point:
                ema.lerp_(current.detach(), 1.0 - decay)
            else:
                ema.copy_(current)


def accumulation(train: TrainConfig, world_size: int) -> int:
    """Forward/backward passes per optimizer step: ``train.accumulate``, or what ``train.global_batch`` needs with
    ``world_size`` processes of ``train.batch_size`` samples (the references' 8 GPUs x 4 samples on one GPU: 8)."""
    if not train.global_batch:
        return train.accumulate
    per_pass = train.batch_size * world_size
    if train.global_batch % per_pass:
        raise ConfigError(f"train.global_batch {train.global_batch} is not a multiple of batch_size x processes = "
                          f"{train.batch_size} x {world_size}: change the batch size or the number of processes")
    return train.global_batch // per_pass


def check_initial_weights(experiment: Experiment) -> None:
    """Fail now, with one line naming the file and the setting, if a fresh run cannot get its initial weights: a
    backbone's ``pretrained`` source (downloaded into its cache here when there is a network) or ``train.load_from``.
    """
    pretrained.ensure_available(experiment.model)
    load_from = experiment.train.load_from
    if load_from is not None and not Path(load_from).is_file():
        raise FileNotFoundError(f"train.load_from = {load_from}: no such file (the whole-model weights this run "
                                "starts from; set train.load_from=PATH, or null to start without them)")


def check_output_folder(out: Path, resume: str | None) -> Path | None:
    """The checkpoint to resume from (None for a fresh run); refuses to mix a fresh run into an old folder."""
    if resume not in (None, "auto"):
        checkpoint = Path(resume)
        if out.is_dir() and any(out.iterdir()) and checkpoint.resolve().parent != out.resolve():
            raise FileExistsError(f"--out {out} already holds another run: resume {checkpoint} into its own folder "
                                  "or a new one (nothing was overwritten)")  # fmt: skip
        return checkpoint
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} exists and is not a folder")
    previous = latest_checkpoint(out) if out.is_dir() else None
    if resume == "auto":
        return previous
    if out.is_dir() and any(out.iterdir()):
        raise FileExistsError(f"--out {out} already holds a run: pass --resume auto to continue it or choose a new "
                              "folder (nothing was overwritten)")
    return None


class _Trainer:
    """State and steps of one run; :func:`train` drives it."""

    def __init__(self, experiment: Experiment, out: Path, context: distributed.Context) -> None:
        self.experiment, self.out, self.context = experiment, out, context
        check_label_space(experiment.model, experiment.data.label_space)  # the model predicts what the data holds
        cfg = experiment.train
        # Every generator a checkpoint saves starts from the seed: numpy's and Python's global ones are otherwise
        # seeded from the OS, so a draw from them (a user's augmentation or model) would differ from run to run.
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        random.seed(cfg.seed)
        model = zoo.build_from_config(experiment.architecture, experiment.model).to(context.device)
        self.model = model
        self.ddp = (torch.nn.parallel.DistributedDataParallel(model, device_ids=None if context.device.type == "cpu"
                    else [context.device]) if context.distributed else None)  # fmt: skip
        trainable = [p for p in model.parameters() if p.requires_grad]
        self.optimizer = torch.optim.AdamW(trainable, lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)
        self.ema = ModelEMA(model) if cfg.ema_decay > 0 else None
        self.autocast = context.device.type == "cuda" and cfg.precision != "fp32"
        self.amp_dtype = torch.bfloat16 if cfg.precision == "bf16" else torch.float16
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.autocast and cfg.precision == "fp16")

        self.accumulate = accumulation(cfg, context.world_size)
        self.dataset = OccupancyDataset(experiment.data)
        # A recurrent temporal model trains as it runs: each scene's frames in order, its memory carried along.
        self.memory = _stream_memory(model, experiment)
        if cfg.sampler == "streams":  # any model may train in that order (a control for the temporal ones)
            self.sampler: distributed.EpochSampler | distributed.StreamSampler = distributed.StreamSampler(
                self.dataset.scene_indices(), cfg.batch_size, context.rank, context.world_size, seed=cfg.seed)
        else:
            population = None
            if cfg.sampler == "cbgs":
                population = cbgs_indices(self.dataset.sample_classes(), DETECTION_CLASSES, cfg.seed)
            self.sampler = distributed.EpochSampler(len(self.dataset), cfg.batch_size, context.rank,
                                                    context.world_size, shuffle=True, seed=cfg.seed,
                                                    population=population)  # fmt: skip
        per_epoch = self.sampler.batches_per_epoch() // self.accumulate
        if per_epoch < 1:
            raise ValueError(f"the training split has {len(self.dataset)} samples, fewer than one optimizer step of "
                             f"{cfg.batch_size * context.world_size * self.accumulate}")
        self.steps_per_epoch = per_epoch
        self.total_steps = min(cfg.epochs * per_epoch, cfg.max_steps or cfg.epochs * per_epoch)
        self.schedule = Schedule(cfg, self.total_steps, per_epoch)
        self.step, self.epoch, self.best_miou = 0, 0, None
        # Loss terms of the steps since the last log row: saved too, so a resumed run logs the same means.
        self.log_window: list[dict[str, float]] = []

    def initialise(self) -> None:
        """Initial weights of a fresh run: the backbones' pretrained weights, then ``train.load_from``."""
        cfg = self.experiment.train
        loaded = pretrained.initialise(self.model, whole_model_weights=cfg.load_from is not None)
        if cfg.load_from is not None:
            report = load_partial(self.model, cfg.load_from, self.experiment)
            if self.context.is_main:
                print(report)
        if self.context.is_main and loaded:
            print(f"initialised the image backbone from {', '.join(loaded)}")
        if self.ema is not None:
            self.ema.module.load_state_dict(self.model.state_dict())

    # ------------------------------------------------------------------------------------------ state
    def state(self) -> dict[str, Any]:
        return {
            "architecture": self.experiment.architecture,
            "experiment": self.experiment.to_dict(),
            "config_yaml": experiment_yaml(self.experiment),
            "model": self.model.state_dict(),
            "ema": self.ema.module.state_dict() if self.ema else None,
            "optimizer": self.optimizer.state_dict(),
            "scaler": self.scaler.state_dict(),
            "step": self.step,
            "epoch": self.epoch,
            "best_miou": self.best_miou,
            "log_window": list(self.log_window),
            "rng": rng_state(),
            "stream_memory": self.memory.state_dict() if self.memory is not None else None,
        }

    def restore(self, path: Path, allow_changes: Sequence[str] = ()) -> list[str]:
        """Load a checkpoint of this experiment; returns the allowed differences (see ``check_resumable``)."""
        payload = load_checkpoint(path, map_location=self.context.device)
        changes = check_resumable(payload, self.experiment.to_dict(), path, allow_changes)
        self.model.load_state_dict(payload["model"])
        if self.ema is not None and payload["ema"] is not None:
            self.ema.module.load_state_dict(payload["ema"])
        if payload["optimizer"] is not None:
            self.optimizer.load_state_dict(payload["optimizer"])
        elif self.context.is_main:
            # A run moved between machines under a size limit may travel without AdamW's moments: they then start
            # afresh (bias-corrected, they settle within a few hundred steps), which the run log says.
            print(f"{path} holds no optimizer state: AdamW's moments start afresh at step {payload['step']}")
        self.scaler.load_state_dict(payload["scaler"])
        self.step, self.epoch, self.best_miou = payload["step"], payload["epoch"], payload["best_miou"]
        self.log_window = list(payload.get("log_window") or [])
        if self.memory is not None and payload.get("stream_memory") is not None:
            self.memory.load_state_dict(payload["stream_memory"])
        set_rng_state(payload["rng"])
        if self.context.distributed:  # one saved state, distinct per-rank draws from here on
            torch.manual_seed(self.experiment.train.seed + 7919 * self.step + self.context.rank)
        return changes

    def save(self, log: RunLog | None) -> None:
        if self.context.is_main:
            save_checkpoint(self.out, self.state(), self.step, self.experiment.train.keep_last)
        distributed.barrier()

    # ------------------------------------------------------------------------------------------ steps
    def set_lr(self) -> float:
        lr = self.schedule.lr(self.step)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        return lr

    def forward_backward(self, batch: Batch) -> dict[str, float]:
        network = self.ddp or self.model
        with torch.autocast(self.context.device.type, dtype=self.amp_dtype, enabled=self.autocast):
            output = network(batch) if self.memory is None else network(batch, memory=self.memory)
            losses = self.model.loss(output, batch)
        total = sum(losses.values())
        self.scaler.scale(total / self.accumulate).backward()
        values = {f"loss/{k}": float(v.detach()) for k, v in losses.items()}
        values["loss"] = float(total.detach())
        return values

    def optimizer_step(self) -> None:
        cfg = self.experiment.train
        self.scaler.unscale_(self.optimizer)
        if cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.grad_clip)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.optimizer.zero_grad(set_to_none=True)
        if self.context.distributed:
            # Gradients are averaged, so parameters agree on every rank, but each rank's BatchNorm updated its
            # running statistics from its own samples: make them rank 0's (which the checkpoints hold), so the
            # EMA, the sharded validation and the saved weights are one and the same model on every rank.
            distributed.broadcast_tensors(list(self.model.buffers()))
        if self.ema is not None:
            self.ema.update(self.model, self.schedule.ema_decay(self.step))
        self.step += 1

    def loader(self, skip_batches: int) -> torch.utils.data.DataLoader:
        self.dataset.set_epoch(self.epoch)
        self.dataset.refill = True  # on_error=skip: a sample that fails is replaced, so every batch stays full
        self.sampler.set_epoch(self.epoch, skip_batches)
        if self.memory is not None and skip_batches == 0:
            self.memory.reset()  # a new deal of scenes: a stream may begin with the scene the last epoch ended on
        workers = self.experiment.train.workers
        # A private generator: creating the iterator must not draw from the global RNG, or a resumed run would
        # draw at another moment than the uninterrupted one.
        return sample_loader(
            self.dataset, batch_size=self.experiment.train.batch_size, sampler=self.sampler, num_workers=workers,
            collate_fn=collate, drop_last=True, generator=torch.Generator().manual_seed(self.epoch),
            persistent_workers=False, pin_memory=self.context.device.type == "cuda",
        )  # fmt: skip

    def validate(self) -> dict:
        weights = self.ema.module if self.ema is not None else self.model
        val_data = replace(self.experiment.data, split=self.experiment.train.val_split, augment=False, history=0)
        train = self.experiment.train
        return score_model(weights, OccupancyDataset(val_data), rayiou=False, batch_size=train.batch_size,
                           workers=train.workers, context=self.context)  # fmt: skip


def _stream_memory(model: torch.nn.Module, experiment: Experiment) -> StreamMemory | None:
    """The memory a streamed-training model carries from step to step, after checking that the settings stream it;
    None for other models."""
    temporal = getattr(model, "temporal", None)
    streamed = temporal is not None and temporal.cfg.streamed_training
    sampler = experiment.train.sampler
    if streamed and sampler != "streams":
        raise ValueError(f"{experiment.architecture} with a recurrent history trains on streams of frames: set "
                         f"train.sampler: streams (got {sampler})")
    if streamed and experiment.data.history:
        raise ValueError(f"a streamed model takes its history from the stream: set data.history: 0 (got "
                         f"{experiment.data.history})")
    return model.stream() if streamed else None


def _progress(context: distributed.Context, total: int, initial: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit="step", desc="train", dynamic_ncols=True,
                disable=not (enabled and context.is_main))  # fmt: skip


def train(
    experiment: Experiment,
    out: str | Path,
    resume: str | None = None,
    progress: bool = True,
    device: str | None = None,
    on_step: Callable[[int], None] | None = None,
    allow_changes: Sequence[str] = (),
) -> TrainResult:
    """Train ``experiment`` into the run folder ``out``.

    Args:
        experiment: model, data and training settings.
        out: run folder (checkpoints, logs, plots, ``config.yaml``); must be new or empty unless resuming.
        resume: ``"auto"`` continues from the newest checkpoint in ``out`` (a fresh start if there is none), or a
            checkpoint path; None starts fresh.
        progress: show a progress bar (loss, samples/s, ETA) on rank 0.
        device: ``cpu``, ``cuda``, ``cuda:1``...; None picks CUDA when available.
        on_step: called with the step number after every optimizer step (tests use it to interrupt).
        allow_changes: experiment keys (``train.lr``) or sections (``train``) that may differ from the checkpoint
            a run resumes; any other difference is refused before anything is written, naming the keys.
    """
    started = time.perf_counter()
    out = Path(out)
    context = distributed.setup(device)
    # One run at a time per run folder, refused before anything is read; rank 0 holds it for the whole group.
    lock = OutputLock(out, "occkit train", enabled=context.is_main)
    try:
        lock.acquire()
        if resume is None:  # a missing weights file fails before any data is read or anything written
            if context.is_main:  # rank 0 downloads into the cache; the others read it there
                check_initial_weights(experiment)
            distributed.barrier()
        start_from = check_output_folder(out, resume) if context.is_main else None
        start_from = distributed.broadcast_object(start_from)
        if context.is_main:
            ensure_writable(out)
        distributed.barrier()
        trainer = _Trainer(experiment, out, context)
        if start_from is None:
            trainer.initialise()  # a missing pretrained file fails here, before the first step
        else:
            # A checkpoint of another experiment fails here, before anything is written.
            changes = trainer.restore(start_from, allow_changes)
            if changes and context.is_main:
                print(f"resuming {start_from} at step {trainer.step} with changed settings: {'; '.join(changes)}")
        if context.is_main:
            (out / "config.yaml").write_text(experiment_yaml(experiment, "# written by occkit train"))
        distributed.barrier()
        # Resuming (or "auto" starting afresh after a run killed before its first checkpoint) drops the log rows
        # past the checkpoint's step.
        resume_step = trainer.step if start_from is not None or resume == "auto" else None
        log = RunLog(out, resume_step=resume_step) if context.is_main else None
        metrics = _run(trainer, log, progress, on_step)
        return TrainResult(out, trainer.step, metrics, trainer.best_miou, time.perf_counter() - started)
    finally:
        lock.release()
        distributed.teardown()


def _run(trainer: _Trainer, log: RunLog | None, progress: bool, on_step: Callable[[int], None] | None) -> dict | None:
    cfg = trainer.experiment.train
    bar = _progress(trainer.context, trainer.total_steps, trainer.step, progress)
    metrics = None
    accumulate = trainer.accumulate
    samples_per_step = cfg.batch_size * accumulate * trainer.context.world_size
    try:
        while trainer.step < trainer.total_steps:
            done_in_epoch = trainer.step - trainer.epoch * trainer.steps_per_epoch
            trainer.model.train()
            tick, window = time.perf_counter(), trainer.log_window
            for index, batch in enumerate(trainer.loader(done_in_epoch * accumulate)):
                if index // accumulate >= trainer.steps_per_epoch - done_in_epoch:
                    break
                lr = trainer.set_lr()
                window.append(trainer.forward_backward(batch.to(trainer.context.device)))
                if (index + 1) % accumulate:
                    continue
                trainer.optimizer_step()
                rate = samples_per_step / max(time.perf_counter() - tick, 1e-9)
                tick = time.perf_counter()
                bar.update(1)
                bar.set_postfix(loss=f"{window[-1]['loss']:.3f}", samples_s=f"{rate:.2f}", epoch=trainer.epoch)
                if trainer.step % cfg.log_every == 0 or trainer.step == trainer.total_steps:
                    mean = {k: sum(w[k] for w in window) / len(window) for k in window[0]}
                    mean = distributed.all_reduce_mean(mean, trainer.context.device)  # the global batch's losses
                    if log is not None:
                        log.train({"step": trainer.step, "epoch": trainer.epoch, "lr": lr, **mean,
                                   "samples_per_s": rate})  # fmt: skip
                    window.clear()
                end_of_epoch = trainer.step % trainer.steps_per_epoch == 0
                if end_of_epoch:
                    trainer.epoch += 1
                if trainer.step == trainer.total_steps or (end_of_epoch and cfg.val_every > 0
                                                           and trainer.epoch % cfg.val_every == 0):
                    metrics = _validate(trainer, log, bar) if cfg.val_every >= 0 else None
                if (cfg.checkpoint_every and trainer.step % cfg.checkpoint_every == 0) or end_of_epoch or (
                        trainer.step == trainer.total_steps):
                    trainer.save(log)
                if on_step is not None:
                    on_step(trainer.step)
                if trainer.step >= trainer.total_steps:
                    break
    finally:
        bar.close()
        if log is not None:
            _finish(trainer, log, metrics)
    return metrics


def _validate(trainer: _Trainer, log: RunLog | None, bar) -> dict:
    metrics = trainer.validate()
    if trainer.context.is_main:
        bar.write(f"step {trainer.step}: val mIoU {100 * metrics['miou']:.2f}  IoU {100 * metrics['iou']:.2f}")
        log.validation(trainer.step, metrics)
        if trainer.best_miou is None or metrics["miou"] > trainer.best_miou:
            trainer.best_miou = metrics["miou"]
            weights = trainer.ema.module if trainer.ema is not None else trainer.model
            atomic_save({"format": "occkit-checkpoint/1", "architecture": trainer.experiment.architecture,
                         "experiment": trainer.experiment.to_dict(), "config_yaml": experiment_yaml(trainer.experiment),
                         "model": weights.state_dict(), "ema": None, "step": trainer.step, "metrics": metrics},
                        trainer.out / "best.pt")  # fmt: skip
    return metrics


def _finish(trainer: _Trainer, log: RunLog, metrics: dict | None) -> None:
    rows = log.rows("log.jsonl")
    if rows:
        plot_losses(rows, trainer.out / "loss.png")
    if metrics is not None:
        plot_per_class_iou(metrics, trainer.out / "per_class_iou.png",
                           f"validation at step {trainer.step}: mIoU {100 * metrics['miou']:.1f}")  # fmt: skip
    log.close()
