"""Crash-safe checkpoints: atomic writes, rolling retention, a best model, and loading without unpickling code.

A run folder holds ``step-00000120.pt`` files (the last ``keep_last``), ``best.pt`` (the best validation mIoU) and
``last.json`` naming the newest complete checkpoint. Every file is written to a temporary name in the same folder,
flushed to disk and renamed over the target, so a run killed at any moment (SIGKILL included) leaves either the
previous file or the new one, never a truncated one; ``last.json`` is only updated after its checkpoint is complete.

Checkpoints are plain dicts of tensors, numbers and strings, loaded with ``torch.load(weights_only=True)`` after
their declared sizes were checked (:func:`occkit.weight_files.load_torch_file`, which convert and the pretrained
backbones read through too).
"""

from __future__ import annotations

import json
import os
import random
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from occkit.config import MISSING, leaf_differences, to_dict
from occkit.data.dataset import DatasetConfig
from occkit.experiment import TrainConfig
from occkit.models.heads.center import DECODING_FIELDS
from occkit.outputs import fsync_folder, write_atomic
from occkit.weight_files import check_finite, load_torch_file
from occkit.zoo import config_class

__all__ = [
    "FORMAT",
    "atomic_save",
    "save_checkpoint",
    "load_checkpoint",
    "latest_checkpoint",
    "rng_state",
    "set_rng_state",
    "check_compatible",
    "check_resumable",
    "BOOKKEEPING_KEYS",
    "ensure_writable",
]

FORMAT = "occkit-checkpoint/1"


def ensure_writable(out: Path) -> None:
    """Create ``out`` and prove a file can be written there, or raise ``PermissionError`` naming it."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as error:
        raise PermissionError(f"cannot write to --out {out}: {error.strerror}") from error


def atomic_save(payload: Any, path: str | Path) -> Path:
    """``torch.save`` to ``path`` through a temporary file and a rename: the target is never seen half written."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(temporary, "wb") as handle:
            torch.save(payload, handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    fsync_folder(path.parent)
    return path


def rng_state() -> dict[str, Any]:
    """Every random generator a training step may draw from, as tensors and lists (``weights_only``-loadable)."""
    kind, keys, position, has_gauss, cached = np.random.get_state()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {"kind": kind, "keys": torch.from_numpy(keys.astype(np.int64)), "position": int(position),
                  "has_gauss": int(has_gauss), "cached": float(cached)},
        "python": [list(part) if isinstance(part, tuple) else part for part in random.getstate()],
    }  # fmt: skip
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` captured, from any device: a checkpoint loaded with ``map_location`` on a GPU
    holds its generator states there, and PyTorch takes them only as CPU byte tensors."""
    torch.set_rng_state(state["torch"].cpu())
    numpy = state["numpy"]
    np.random.set_state((numpy["kind"], numpy["keys"].cpu().numpy().astype(np.uint32), numpy["position"],
                         numpy["has_gauss"], numpy["cached"]))  # fmt: skip
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([generator.cpu() for generator in state["cuda"]])


def save_checkpoint(folder: str | Path, payload: dict[str, Any], step: int, keep_last: int) -> Path:
    """Write ``step-XXXXXXXX.pt``, point ``last.json`` at it, then delete rolling checkpoints beyond ``keep_last``."""
    folder = Path(folder)
    path = atomic_save({"format": FORMAT, **payload}, folder / f"step-{step:08d}.pt")
    write_atomic(folder / "last.json", json.dumps({"checkpoint": path.name, "step": step}) + "\n")
    rolling = sorted(folder.glob("step-*.pt"))
    for old in rolling[:-keep_last]:
        old.unlink(missing_ok=True)
    return path


def checkpoint_step(path: str | Path) -> int:
    """The training step a ``step-XXXXXXXX.pt`` checkpoint was written at, read from its name."""
    name = Path(path).stem
    digits = name.removeprefix("step-")
    if name == digits or not digits.isdigit():
        raise ValueError(f"{path} is not named like a checkpoint (step-XXXXXXXX.pt)")
    return int(digits)


def latest_checkpoint(folder: str | Path) -> Path | None:
    """The checkpoint ``last.json`` names, or None for a folder without one."""
    pointer = Path(folder) / "last.json"
    if not pointer.is_file():
        return None
    try:
        name = json.loads(pointer.read_text())["checkpoint"]
    except (ValueError, KeyError) as error:
        raise ValueError(f"{pointer} is not a checkpoint pointer ({error})") from error
    path = Path(folder) / name
    if not path.is_file():
        raise FileNotFoundError(f"{pointer} names {name}, which does not exist")
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint through :func:`~occkit.weight_files.load_torch_file` (sizes checked first, weights-only,
    refusals on one line); anything that is not an occkit checkpoint, or whose model weights are NaN or infinite,
    is a clear error."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    payload = load_torch_file(path, map_location)
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"{path} is not an occkit checkpoint (no '{FORMAT}' format marker)")
    for key in ("model", "ema"):
        weights = payload.get(key)
        if isinstance(weights, Mapping) and all(isinstance(value, torch.Tensor) for value in weights.values()):
            check_finite(weights, path, f"'{key}' weights")
    return payload


#: Experiment keys that change no weight, so a resumed run may change them without ``allow``.
BOOKKEEPING_KEYS = ("train.workers", "train.log_every", "train.keep_last", "train.checkpoint_every")

#: Model keys that change what the same weights predict, not the weights (DAOcc's panoptic output from its detection
#: head, the centre heads' decoding thresholds): a checkpoint is loaded under any value of them.
PREDICTION_KEYS = ("model.panoptic",) + tuple(f"model.{head}.{name}" for head in ("detection", "instances")
                                              for name in DECODING_FIELDS)


def check_compatible(payload: dict[str, Any], architecture: str, model_config: dict, path: str | Path) -> None:
    """Raise ``ValueError`` naming the first difference when a checkpoint holds another model or config."""
    if payload["architecture"] != architecture:
        raise ValueError(f"{path} holds a {payload['architecture']} model, not {architecture}")
    saved = _fill(payload["experiment"]["model"], _defaults(architecture)["model"])
    differences = [d for d in leaf_differences(saved, model_config, "model") if d[0] not in PREDICTION_KEYS]
    if differences:
        raise ValueError(f"{path} was trained with another model config: {_describe(differences[0])}"
                         + (f" (and {len(differences) - 1} more differences)" if len(differences) > 1 else ""))


def check_resumable(payload: dict[str, Any], experiment: dict, path: str | Path,
                    allow: Sequence[str] = ()) -> list[str]:  # fmt: skip
    """Refuse to resume a checkpoint under another experiment than the one it was trained with.

    Args:
        payload: the checkpoint.
        experiment: the requested experiment, as ``Experiment.to_dict()``.
        path: the checkpoint's file, for the messages.
        allow: keys (``train.lr``) or sections (``train``) that may differ; :data:`BOOKKEEPING_KEYS` always may.

    Returns:
        The allowed differences, described (``train.lr: 0.001 -> 0.0005``), for the run to report.

    Raises:
        ValueError: another architecture, or differences outside ``allow``, every key named.
    """
    architecture = experiment["architecture"]
    if payload["architecture"] != architecture:
        raise ValueError(f"{path} holds a {payload['architecture']} model, not {architecture}")
    saved = _fill(payload["experiment"], _defaults(architecture))
    differences = leaf_differences(saved, experiment, "")
    allowed = [*BOOKKEEPING_KEYS, *allow]
    refused = [d for d in differences if not any(d[0] == key or d[0].startswith(key + ".") for key in allowed)]
    if refused:
        keys = " ".join(f"--allow-change {key}" for key, _, _ in refused)
        raise ValueError(f"{path} was trained with another experiment: "
                         + "; ".join(_describe(d) for d in refused)
                         + f". Resume with the saved settings, or pass {keys} to change them (nothing was written)")
    return [f"{key}: {saved_value!r} -> {value!r}" for key, saved_value, value in differences]


def _defaults(architecture: str) -> dict:
    """The experiment of ``architecture`` with every option at its default (sections model, data, train)."""
    return {"architecture": architecture, "model": to_dict(config_class(architecture)()),
            "data": to_dict(DatasetConfig()), "train": to_dict(TrainConfig())}  # fmt: skip


def _fill(saved: Any, defaults: Any) -> Any:
    """``saved`` with the options added since it was written filled in at their defaults, so that a new option left
    at its default is no difference (a removed option stays, and is named)."""
    if not (isinstance(saved, dict) and isinstance(defaults, dict)):
        return saved
    filled = {name: value for name, value in defaults.items() if name not in saved}
    filled.update({name: _fill(value, defaults.get(name)) for name, value in saved.items()})
    return filled


def _describe(difference: tuple[str, Any, Any]) -> str:
    key, saved, current = difference
    show = lambda value: "absent" if value is MISSING else repr(value)  # noqa: E731
    return f"{key} is {show(saved)} in the checkpoint but {show(current)} here"
