"""Model zoo: one line per architecture, and the entries each family registers in ``occkit/zoo/<family>.py``.

    >>> from occkit import zoo
    >>> zoo.names()[:3]
    ['da_occ', 'da_occ_tiny', 'daocc']
    >>> model = zoo.build("daocc_tiny")

Each architecture's model file declares an :class:`~occkit.models.base.Architecture`: its config and model classes
and its benchmark stages. Its zoo entries are functions named after them, returning the whole experiment, in
``occkit/zoo/<family>.py``, registered with :func:`occkit.zoo.registry.preset`; the model files know nothing of
datasets or schedules.
Every entry has a YAML twin in ``configs/NAME.yaml``: the whole experiment (``architecture``, ``model``, ``data``,
``train``), written by :func:`config_yaml` and kept equal to :func:`experiment` by a test, so a config file read with
:func:`load_experiment` and a name given to :func:`build` mean the same model.
"""

from __future__ import annotations

import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from occkit import experiment as _experiment
from occkit.config import ConfigError, leaf_differences
from occkit.experiment import Experiment, PaperRow, experiment_yaml
from occkit.models import pretrained
from occkit.models.base import Architecture, OccupancyModel
from occkit.models.da_occ import ARCHITECTURE as DA_OCC
from occkit.models.daocc import ARCHITECTURE as DAOCC
from occkit.models.flashocc import ARCHITECTURE as FLASHOCC
from occkit.shipped import SYNTHETIC, load_shipped
from occkit.zoo import da_occ as _da_occ_entries  # noqa: F401 -- each family module registers its entries
from occkit.zoo import daocc as _daocc_entries  # noqa: F401
from occkit.zoo import flashocc as _flashocc_entries  # noqa: F401
from occkit.zoo.registry import ENTRIES

__all__ = ["ARCHITECTURES", "names", "description", "paper_row", "needed_files", "architecture", "diff", "model_config",
           "experiment", "build", "build_from_config", "config_yaml", "config_class", "experiment_from_dict",
           "load_experiment"]

#: Architecture name -> its declaration; adding an architecture is one line here.
ARCHITECTURES: dict[str, Architecture] = {
    arch.name: arch
    for arch in (
        DAOCC,
        FLASHOCC,
        DA_OCC,
    )
}


def names(architecture: str | None = None) -> list[str]:
    """Zoo entry names, sorted; with ``architecture``, only that architecture's (no preset is run)."""
    return sorted(name for name, entry in ENTRIES.items() if architecture in (None, entry.architecture))


def _entry(name: str) -> Callable[[], Experiment]:
    if name not in ENTRIES:
        raise KeyError(f"unknown model {name!r}; the zoo has: {', '.join(names())}")
    return ENTRIES[name].make


def description(name: str) -> str:
    """One paragraph on what the entry is."""
    return " ".join((_entry(name).__doc__ or "").split())


def paper_row(name: str) -> PaperRow | None:
    """The published row the entry's recipe reproduces on the real data (None for the CPU-sized entries)."""
    return getattr(_entry(name), "paper_row", None)


def needed_files(experiment: Experiment) -> list[str]:
    """The weight files an experiment starts from: its backbones' pretrained files and its ``train.load_from``."""
    files = []
    for setting, depth in pretrained.backbone_settings(experiment.model):
        file = pretrained.needed_file(setting, depth)
        files.append(f"{pretrained.SETTING} = {setting}" + ("" if setting.endswith(file) else f" ({file})"))
    if experiment.train.load_from:
        files.append(f"train.load_from = {experiment.train.load_from}")
    return files


def experiment(name: str) -> Experiment:
    """The full experiment (model, data, training) of a zoo entry, as ``configs/NAME.yaml`` holds it."""
    return _entry(name)()


def diff(first: str, second: str) -> list[tuple[str, Any, Any]]:
    """How entry ``second`` differs from entry ``first``: ``(setting, first's value, second's value)`` for every
    setting of their experiments that differs (``model.bev.neck_channels``, ``data.sweeps``, ``train.epochs``; the
    architecture as ``architecture``), in key order; :data:`occkit.config.MISSING` where a side lacks the setting."""
    return leaf_differences(experiment(first).to_dict(), experiment(second).to_dict())


def model_config(name: str) -> tuple[str, Any]:
    """``(architecture, model config)`` of a zoo entry."""
    entry = experiment(name)
    return entry.architecture, entry.model


def architecture(name: str) -> Architecture:
    """The declaration of architecture ``name``.

    Raises:
        ConfigError: no such architecture.
    """
    if name not in ARCHITECTURES:
        raise ConfigError(f"architecture: unknown {name!r}; known: {', '.join(sorted(ARCHITECTURES))}")
    return ARCHITECTURES[name]


def config_class(name: str) -> type:
    """The model config dataclass of architecture ``name``."""
    return architecture(name).config


def build_from_config(name: str, cfg: Any) -> OccupancyModel:
    """The model of architecture ``name`` built from ``cfg``."""
    return architecture(name).build(cfg)


def build(name: str, weights: str | None = None) -> OccupancyModel:
    """The model of the zoo entry ``name``: freshly initialised, or with ``weights="synthetic"`` the weights occkit
    ships for it (:mod:`occkit.shipped`, checked against their card). A weights file loads with
    :func:`occkit.convert.load_weights`."""
    model = build_from_config(*model_config(name))
    if weights is None:
        return model
    if weights != SYNTHETIC:
        raise ValueError(f"weights must be None or {SYNTHETIC!r}, got {weights!r} (a weights file loads with "
                         "occkit.convert.load_weights)")
    return load_shipped(model, name)


def experiment_from_dict(data: Any, where: str = "experiment", overrides: Sequence[str] = ()) -> Experiment:
    """Check and build an experiment of any zoo architecture from plain data (a checkpoint's, a YAML file's);
    ``overrides`` are ``section.key=value`` strings. Errors name ``where`` and the key."""
    classes = {name: arch.config for name, arch in ARCHITECTURES.items()}
    return _experiment.experiment_from_dict(data, classes, where, overrides)


def load_experiment(source: str | Path, overrides: Sequence[str] = ()) -> Experiment:
    """The experiment of a YAML file, or of the zoo entry of that name when no such file exists, with overrides.

    Raises:
        ConfigError: the file or an override is invalid (the message names the file and the key).
        FileNotFoundError: neither a file nor a zoo name.
    """
    path = Path(source)
    if not path.exists() and str(source) in ENTRIES:
        return experiment_from_dict(experiment(str(source)).to_dict(), f"zoo entry {source}", overrides)
    if not path.exists():
        raise FileNotFoundError(f"config {source} does not exist (zoo names: {', '.join(names())})")
    return experiment_from_dict(_experiment.read_experiment_file(path), str(path), overrides)


def config_yaml(name: str) -> str:
    """The text of ``configs/NAME.yaml``: a description, then the commented experiment."""
    entry = experiment(name)
    lines = [f"{name}: {description(name)}"]
    if (row := paper_row(name)) is not None:
        lines.append(f"Reproduces {row}.")
    needed = needed_files(entry)
    lines.append("Starts from " + "; ".join(needed) + "." if needed else "Starts from random weights.")
    lines.append(f"occkit train --config configs/{name}.yaml --out runs/{name}")
    header = "\n".join(textwrap.fill(line, 116, initial_indent="# ", subsequent_indent="#   ", break_long_words=False,
                                      break_on_hyphens=False) for line in lines)  # fmt: skip
    return experiment_yaml(entry, header)
