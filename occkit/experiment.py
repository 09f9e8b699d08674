"""An experiment: which model, which data, how to train. One YAML file, four sections.

    architecture: daocc        # which model family reads the ``model`` section
    model: {...}               # e.g. DAOccConfig
    data: {...}                # occkit.data.dataset.DatasetConfig (the training split's settings)
    train: {...}               # TrainConfig below

``configs/NAME.yaml`` holds one per zoo entry (``occkit.zoo.experiment(NAME)``); ``occkit train --config FILE
--set train.lr=2e-4`` reads one (``occkit.zoo.load_experiment``, which knows the architectures). Every key is
checked: a typo is an error naming the file and the valid keys. This module holds settings only, no model code, so
that every layer above it (models, zoo, engine) can speak of experiments.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
import yaml

from occkit.config import ConfigError, check_magnitudes, check_ranges, dump_yaml, from_dict, override_dict, to_dict
from occkit.data.dataset import DatasetConfig
from occkit.data.transforms import ImageAugConfig
from occkit.label_space import LabelSpace, label_space

__all__ = ["TrainConfig", "Experiment", "PaperRow", "reproduces", "check_label_space", "experiment_from_dict",
           "read_experiment_file", "experiment_yaml", "replace_train", "CPU_ROOT", "CPU_TRAIN", "cpu_data"]


Preset = TypeVar("Preset", bound=Callable[[], "Experiment"])


#: Inclusive bounds of every numeric training setting: practical limits far beyond any paper's schedule (DAOcc: 24
#: epochs, 8 x 4 samples per step), so that a typo is refused before a run instead of training nothing or forever.
_STEPS = 100_000_000
_TRAIN_RANGES = {
    "epochs": (1, 100_000), "max_steps": (0, _STEPS), "batch_size": (1, 4096), "accumulate": (1, 4096),
    "global_batch": (0, 65_536), "lr": (0.0, 10.0), "weight_decay": (0.0, 10.0), "betas": (0.0, 1.0),
    "warmup_steps": (0, _STEPS), "warmup_ratio": (0.0, 1.0), "min_lr_ratio": (0.0, 1.0), "lr_steps": (0, 100_000),
    "lr_gamma": (0.0, 10.0), "grad_clip": (0.0, 1e6), "ema_decay": (0.0, 1.0), "ema_ramp": (0.0, 1e9),
    "ema_initial_updates": (0, 1_000_000_000), "seed": (0, 2**63 - 1), "workers": (0, 256), "val_every": (-1, _STEPS),
    "log_every": (1, _STEPS), "checkpoint_every": (0, _STEPS), "keep_last": (1, 10_000),
}  # fmt: skip

#: Bound of every number of a model section, whose fields have no ranges of their own: ten times past the largest
#: of any zoo entry (DAOcc's LiDAR encoder keeps 160 000 voxels), far below a size whose allocation fails.
_MODEL_LIMIT = 10_000_000


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation, schedule, precision, validation and checkpointing."""

    epochs: int = 24
    """Passes over the training split."""
    max_steps: int = 0
    """Stop after this many optimizer steps (0: run every epoch); the schedule spans min(epochs, max_steps)."""
    batch_size: int = 4
    """Samples per process per forward pass; the global batch is batch_size x processes x accumulate."""
    accumulate: int = 1
    """Forward/backward passes per optimizer step (gradient accumulation)."""
    global_batch: int = 0
    """The reference's samples per optimizer step over all processes; when set, accumulate is derived as
    global_batch / (batch_size x processes), which must divide it (8 GPUs x 4 = 32 is 4 x 8 on one GPU); 0 uses
    accumulate as given."""
    sampler: Literal["random", "cbgs", "streams"] = "random"
    """Training order: every sample once per epoch in random order; CBGS (class-balanced grouping and sampling,
    mmdetection3d's ``CBGSDataset``): samples duplicated per detection class so that every class is seen as often; or
    ``streams``, the scenes in random order dealt to ``batch_size`` streams per process, each scene's frames in time
    order (what a recurrent temporal model trains on, its memory carried from step to step; a single-frame model
    trained in that order is the control that separates the order from the history)."""
    load_from: str | None = None
    """Whole-model weights loaded before training (an occkit checkpoint or ``.safetensors``, or a reference
    checkpoint that ``occkit convert`` reads): partial and shape-checked, what is skipped is listed (FlashOcc starts
    from BEVDet's detection checkpoint this way). Not used when resuming."""
    lr: float = 1e-4
    """Peak learning rate of AdamW."""
    weight_decay: float = 0.01
    """AdamW weight decay."""
    betas: tuple[float, float] = (0.9, 0.999)
    """AdamW betas."""
    warmup_steps: int = 500
    """Linear warm-up steps, from warmup_ratio x lr to lr."""
    warmup_ratio: float = 1.0 / 3.0
    """Learning rate at step 0 as a fraction of lr (mmcv's warmup_ratio)."""
    lr_policy: Literal["cosine", "step"] = "cosine"
    """After the warm-up: ``cosine`` anneals to min_lr_ratio x lr (DAOcc); ``step`` multiplies the rate by lr_gamma
    at each epoch of lr_steps (mmcv's step policy: FlashOcc's ``step=[24]`` over 24 epochs keeps it constant)."""
    lr_by_epoch: bool = False
    """The schedule (not the warm-up) changes the rate once per epoch, as mmcv's runners do by default (DAOcc's
    cosine over 6 epochs); False: every optimizer step."""
    min_lr_ratio: float = 1e-3
    """Cosine annealing ends at min_lr_ratio x lr."""
    lr_steps: tuple[int, ...] = ()
    """Step policy: epochs at whose start the rate is multiplied by lr_gamma."""
    lr_gamma: float = 0.1
    """Step policy: the factor applied at each of lr_steps."""
    grad_clip: float = 5.0
    """Maximum global gradient norm (0: no clipping)."""
    precision: Literal["fp32", "bf16", "fp16"] = "fp32"
    """Autocast precision on CUDA (fp16 adds loss scaling); CPU always trains in fp32."""
    ema_decay: float = 0.999
    """Decay of the exponential moving average of the weights, used for validation and saved (0: none)."""
    ema_ramp: float = 0.0
    """Ramp of the decay over the EMA's updates t, ``ema_decay x (1 - exp(-t / ema_ramp))`` (BEVDepth's MEGVII EMA,
    which DAOcc and FlashOcc use with 2000); 0: the constant ema_decay."""
    ema_initial_updates: int = 0
    """t before the first update (the references' ``init_updates``: 10560, which starts the ramp near its end)."""
    seed: int = 0
    """Seed of the weights, the data order, the augmentations and every other random draw."""
    workers: int = 2
    """DataLoader worker processes per training process."""
    val_split: str = "val"
    """Split scored during training and by default by ``occkit eval``."""
    val_every: int = 1
    """Validate every this many epochs, and at the end (0: only at the end; -1: never)."""
    log_every: int = 10
    """Write the loss terms and learning rate every this many steps."""
    checkpoint_every: int = 0
    """Save a checkpoint every this many steps (0: at the end of every epoch)."""
    keep_last: int = 2
    """Rolling checkpoints kept besides ``best.pt`` and ``last.pt``."""

    def __post_init__(self) -> None:
        check_ranges("train", self, _TRAIN_RANGES)
        if self.lr <= 0 or self.ema_decay >= 1 or self.warmup_ratio <= 0 or self.lr_gamma <= 0:
            raise ValueError("train.lr, warmup_ratio and lr_gamma must be > 0 and train.ema_decay < 1, got "
                             f"{self.lr}, {self.warmup_ratio}, {self.lr_gamma} and {self.ema_decay}")
        if self.global_batch and self.accumulate != 1:
            raise ValueError("set train.global_batch or train.accumulate, not both: global_batch derives accumulate")
        if self.global_batch and self.global_batch % self.batch_size:
            raise ValueError(f"train.global_batch {self.global_batch} is not a multiple of train.batch_size "
                             f"{self.batch_size}")
        if self.lr_steps and self.lr_policy != "step":
            raise ValueError("train.lr_steps is used by lr_policy: step only")


@dataclass(frozen=True)
class Experiment:
    """The four sections of an experiment file."""

    architecture: str
    model: Any
    data: DatasetConfig
    train: TrainConfig

    def to_dict(self) -> dict:
        return {"architecture": self.architecture, "model": to_dict(self.model), "data": to_dict(self.data),
                "train": to_dict(self.train)}  # fmt: skip


@dataclass(frozen=True)
class PaperRow:
    """The published number a zoo entry's recipe reproduces on the real data."""

    paper: str
    """Paper and table, e.g. ``DAOcc (Yang et al., TCSVT 2025), Table I``."""
    row: str
    """The row as the table names it, with what distinguishes it (mask, frames, ablation arm)."""
    result: str
    """The number, metric and split, e.g. ``53.82 mIoU, Occ3D-nuScenes val (camera mask)``."""

    def __str__(self) -> str:
        return f"{self.paper}, {self.row}: {self.result}"


def reproduces(paper: str, row: str, result: str) -> Callable[[Preset], Preset]:
    """Mark a zoo preset with the paper row its recipe reproduces (``occkit.zoo.paper_row``, the config headers and
    docs/reproducing.md read it)."""

    def mark(preset: Preset) -> Preset:
        preset.paper_row = PaperRow(paper, row, result)  # type: ignore[attr-defined]
        return preset

    return mark


def experiment_from_dict(
    data: Any, config_classes: Mapping[str, type], where: str = "experiment", overrides: Sequence[str] = ()
) -> Experiment:
    """Check and build an experiment from plain data; ``overrides`` are ``section.key=value`` strings.

    ``config_classes`` maps each architecture name to its model config dataclass (``occkit.zoo`` passes the zoo's).
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping with architecture, model, data and train")
    unknown = set(data) - {"architecture", "model", "data", "train"}
    if unknown or "architecture" not in data:
        raise ConfigError(f"{where}: an experiment has the keys architecture, model, data, train; got {sorted(data)}")
    architecture = data["architecture"]
    if architecture not in config_classes:
        raise ConfigError(f"{where}: unknown architecture {architecture!r}; known: {', '.join(sorted(config_classes))}")
    parsed = Experiment(
        architecture=architecture,
        model=from_dict(config_classes[architecture], data.get("model") or {}, f"{where}: model"),
        data=from_dict(DatasetConfig, data.get("data") or {}, f"{where}: data"),
        train=from_dict(TrainConfig, data.get("train") or {}, f"{where}: train"),
    )
    try:
        check_magnitudes("model", parsed.model, _MODEL_LIMIT)
    except ConfigError as error:
        raise ConfigError(f"{where}: {error}") from None
    if not overrides:
        check_label_space(parsed.model, parsed.data.label_space, where)
        return parsed
    if any(o.split("=", 1)[0].strip() == "architecture" for o in overrides):
        raise ConfigError("the architecture cannot be overridden with --set: use another config file")
    return experiment_from_dict(override_dict(parsed.to_dict(), overrides), config_classes, f"{where} (after --set)")


def read_experiment_file(path: str | Path) -> Any:
    """The plain data of an experiment YAML file; errors name the file."""
    path = Path(path)
    try:
        return yaml.safe_load(path.read_text())
    except OSError as error:
        raise ConfigError(f"cannot read config {path}: {error.strerror}") from error
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {error}") from error


def check_label_space(model: Any, name: str, where: str = "experiment") -> LabelSpace:
    """The label space ``name`` (``data.label_space``), checked against what the model predicts: its occupancy
    head's classes and free / empty id, the frame its range extension places the grid in, and whether its loss needs
    a visibility mask the labels carry. A model and labels of different label spaces are an error naming both."""
    try:
        space = label_space(name)
    except ValueError as error:
        raise ConfigError(f"{where}: data.label_space: {error}") from None
    head = getattr(model, "occupancy", None)
    if head is not None and (head.num_classes, head.free_index) != (space.num_classes, space.free_index):
        raise ConfigError(f"{where}: the model predicts {head.num_classes} classes with free / empty id "
                          f"{head.free_index}, but data.label_space {space.name} has {space.num_classes} with "
                          f"{space.free_index}: a model of one label space cannot train on or score another")
    if head is not None and head.use_mask and "camera" not in space.masks:
        raise ConfigError(f"{where}: model.occupancy.use_mask needs camera visibility masks, which "
                          f"{space.name} labels do not have")  # fmt: skip
    grid = model.output_grid  # every architecture's config says where it predicts
    if grid.shape != space.grid.shape or not np.allclose(grid.point_cloud_range, space.grid.point_cloud_range):
        raise ConfigError(f"{where}: the model predicts on {grid!r} but {space.name} labels are on {space.grid!r}")
    extension = getattr(model, "range_extension", None)
    if extension is not None and extension.label_frame != space.frame:
        raise ConfigError(f"{where}: model.range_extension.label_frame is {extension.label_frame} but "
                          f"{space.name} labels live in the {space.frame} frame")  # fmt: skip
    return space


def experiment_yaml(experiment: Experiment, header: str = "") -> str:
    """Commented YAML of an experiment (each field's docstring above it)."""

    def section(name: str, cfg: Any) -> str:
        body = dump_yaml(cfg).rstrip("\n")
        return f"{name}:\n" + "\n".join(("  " + line) if line else line for line in body.splitlines())

    parts = [header.rstrip("\n")] if header else []
    parts.append(f"architecture: {experiment.architecture}")
    parts += [section("model", experiment.model), section("data", experiment.data), section("train", experiment.train)]
    return "\n".join(parts) + "\n"


def replace_train(experiment: Experiment, **changes: Any) -> Experiment:
    """A copy with some training settings changed."""
    return dataclasses.replace(experiment, train=dataclasses.replace(experiment.train, **changes))


# ------------------------------------------------------------------------------------ CPU-sized zoo entries
#: Where the CPU-sized (``_tiny``) zoo entries read their data: the demo's synthetic world.
CPU_ROOT = "data/demo"

#: The short CPU schedule of every ``_tiny`` zoo entry: 5 epochs of single samples at 2e-3, no EMA.
CPU_TRAIN = TrainConfig(epochs=5, batch_size=1, lr=2e-3, warmup_steps=50, grad_clip=35.0, ema_decay=0.0, workers=1,
                        val_every=0, log_every=10)  # fmt: skip


def cpu_data(paper: DatasetConfig) -> DatasetConfig:
    """A paper entry's data settings at CPU size: the demo world, 128 x 352 images without rotation, at most 4
    previous sweeps."""
    return dataclasses.replace(paper, root=CPU_ROOT, sweeps=min(paper.sweeps, 4),
                               image_aug=ImageAugConfig(final_size=(128, 352), rotate_deg=(0.0, 0.0)))  # fmt: skip
