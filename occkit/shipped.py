"""Weights occkit ships for its CPU-sized zoo entries, trained on the synthetic world, each with its card.

``occkit/weights/NAME.safetensors`` holds the weights of zoo entry ``NAME`` in float16 (occkit's weights format, so
``occkit eval --weights FILE`` reads it too) and ``NAME.card.json`` says what they are: the world they were trained on
(a seed other than the demo's), the steps, time and device of the run, the command that reproduces it
(``scripts/train_shipped_weights.py``), their scores on the demo world's held-out scenes, the occkit version, and the
file's SHA-256, which every load checks::

    model = zoo.build("daocc_tiny", weights="synthetic")      # or: occkit predict --weights synthetic --model ...
    card("daocc_tiny").scores["miou"]

The weights are stored at half precision (the files stay small enough for the repository) and load into the model's
own float32 parameters; the card's scores are those of the stored half-precision weights.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from occkit.config import ConfigError

__all__ = ["SYNTHETIC", "WeightsCard", "weights_folder", "shipped_entries", "card", "weights_path", "load_shipped",
           "write_shipped", "write_card"]  # fmt: skip

#: The name that stands for the shipped weights wherever a weights file is asked for (``--weights synthetic``).
SYNTHETIC = "synthetic"
#: The precision the weights are stored at (a torch dtype's name).
STORED_DTYPE = "float16"


@dataclass(frozen=True)
class WeightsCard:
    """What a shipped weights file is, where it came from and what it scores."""

    entry: str
    """The zoo entry whose model the weights fill."""
    sha256: str
    """SHA-256 of the ``.safetensors`` file; a file that does not match is refused."""
    world: dict[str, Any]
    """The synthetic world trained on: ``seed``, ``scenes``, ``frames``, ``image_size`` (not the demo world's
    seed)."""
    steps: int
    """Optimizer steps of the training run."""
    train_seconds: float
    """Wall time of the training run."""
    device: str
    """Where it trained (e.g. ``cpu, 2 threads``, ``NVIDIA H100``)."""
    command: str
    """The command that reproduces the run and this card."""
    scores: dict[str, Any]
    """Scores of the stored weights on the demo world's held-out scenes: ``miou``, ``iou``, ``rayiou`` (fractions)
    and ``per_class`` IoU by class name."""
    occkit_version: str
    """The occkit version that wrote the card."""
    curve: list[dict[str, float]] = field(default_factory=list)
    """Held-out mIoU over the run on its own world's validation scenes: ``{"step", "miou", "iou"}`` rows."""
    notes: str = ""
    """Anything a user should know (e.g. where a family converged below its target)."""


def weights_folder() -> Path:
    """The folder of the shipped files inside the installed package."""
    return Path(str(resources.files("occkit") / "weights"))


def shipped_entries(folder: Path | None = None) -> list[str]:
    """Zoo entries with shipped weights (those with a card)."""
    folder = weights_folder() if folder is None else folder
    return sorted(path.name.removesuffix(".card.json") for path in folder.glob("*.card.json"))


def card(entry: str, folder: Path | None = None) -> WeightsCard:
    """The card of ``entry``'s shipped weights.

    Raises:
        ConfigError: none are shipped for ``entry`` (the message lists those that are), or the card is unreadable.
    """
    folder = weights_folder() if folder is None else folder
    path = folder / f"{entry}.card.json"
    if not path.is_file():
        shipped = ", ".join(shipped_entries(folder)) or "none yet"
        raise ConfigError(f"occkit ships no trained weights for {entry} (--weights {SYNTHETIC} has: {shipped})")
    try:
        return WeightsCard(**json.loads(path.read_text()))
    except (OSError, ValueError, TypeError) as error:
        raise ConfigError(f"{path}: not a weights card ({error})") from error


def weights_path(entry: str, folder: Path | None = None) -> Path:
    """The shipped ``.safetensors`` of ``entry``, checked against its card's SHA-256.

    Raises:
        ConfigError: no weights are shipped for ``entry``, or the file is missing or not the one the card describes.
    """
    described = card(entry, folder)
    path = (weights_folder() if folder is None else folder) / f"{entry}.safetensors"
    if not path.is_file():
        raise ConfigError(f"the weights of {entry}'s card are missing: {path} (reinstall occkit)")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    if digest != described.sha256:
        raise ConfigError(f"{path} is not the file its card describes (SHA-256 {digest[:12]}..., the card says "
                          f"{described.sha256[:12]}...): reinstall occkit")  # fmt: skip
    return path


def load_shipped(model: Any, entry: str, folder: Path | None = None) -> Any:
    """Load ``entry``'s shipped weights strictly into ``model`` (a model of ``entry``'s architecture and shapes).

    Raises:
        ConfigError: no weights are shipped for ``entry``, the file is not its card's, or it does not fit ``model``
            (the message names the first keys that differ).
    """
    from occkit.weight_files import WEIGHTS_FORMAT, read_safetensors

    path = weights_path(entry, folder)
    state, metadata = read_safetensors(path)
    if metadata.get("format") != WEIGHTS_FORMAT or metadata.get("entry") != entry:
        raise ConfigError(f"{path} is not occkit's weights of {entry} (metadata {metadata}): reinstall occkit")
    expected = {key: tuple(value.shape) for key, value in model.state_dict().items()}
    missing, unexpected = sorted(expected.keys() - state.keys()), sorted(state.keys() - expected.keys())
    wrong = sorted(key for key in expected.keys() & state.keys() if tuple(state[key].shape) != expected[key])
    if missing or unexpected or wrong:
        raise ConfigError(f"{path} does not fit this {entry} model: missing {missing[:3]}, unexpected "
                          f"{unexpected[:3]}, other shapes {wrong[:3]}")  # fmt: skip
    model.load_state_dict(state, strict=True)
    return model


def write_shipped(model: Any, architecture: str, card_fields: dict[str, Any], folder: Path) -> WeightsCard:
    """Write ``model``'s weights (of zoo architecture ``architecture``) at half precision and their card into
    ``folder``; returns the card.

    ``card_fields`` holds every :class:`WeightsCard` field but ``sha256`` (computed here). Integer buffers (BatchNorm's
    step counters) keep their dtype.
    """
    import torch
    from safetensors.torch import save

    from occkit import __version__
    from occkit.outputs import write_atomic
    from occkit.weight_files import WEIGHTS_FORMAT

    entry = card_fields["entry"]
    # Copies: safetensors stores each tensor on its own, and a state dict may hold views of one storage.
    half = getattr(torch, STORED_DTYPE)
    state = {key: (value.to(half) if value.is_floating_point() else value).detach().cpu().clone()
             for key, value in model.state_dict().items()}  # fmt: skip
    metadata = {"format": WEIGHTS_FORMAT, "entry": entry, "architecture": architecture,
                "source": "occkit", "source_file": "synthetic world", "complete": "true"}  # fmt: skip
    data = save(state, metadata)
    folder.mkdir(parents=True, exist_ok=True)
    write_atomic(folder / f"{entry}.safetensors", data)
    written = WeightsCard(**{"occkit_version": __version__, **card_fields, "sha256": hashlib.sha256(data).hexdigest()})
    write_card(written, folder)
    return written


def write_card(written: WeightsCard, folder: Path) -> None:
    """Write ``written`` as ``folder/ENTRY.card.json``, atomically."""
    from occkit.outputs import write_atomic

    write_atomic(folder / f"{written.entry}.card.json", json.dumps(dataclasses.asdict(written), indent=1) + "\n")
