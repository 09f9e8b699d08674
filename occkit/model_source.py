"""Where a command's model comes from: an occkit checkpoint, a weights file for a zoo entry, or the shipped weights.

``occkit eval``, ``predict``, ``robustness``, ``viz`` and ``view`` take ``--ckpt FILE`` or ``--weights FILE|synthetic``
(with ``--model ENTRY``); each becomes a :class:`ModelSource`, which names the file to hash and loads the model with
its experiment. Importing this module costs nothing: torch and the models load with :meth:`ModelSource.load`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from occkit.shipped import SYNTHETIC, shipped_entries, weights_path

if TYPE_CHECKING:
    from occkit.experiment import Experiment
    from occkit.label_space import LabelSpace

__all__ = ["ModelSource"]


@dataclass(frozen=True)
class ModelSource:
    """Where a command's model comes from: an occkit checkpoint, or a weights file for a zoo entry, or the weights
    occkit ships for one (``weights="synthetic"``)."""

    ckpt: str | None = None
    """An occkit checkpoint (best.pt, step-*.pt): it names its own model and experiment."""
    weights: str | None = None
    """A weights file in occkit's names (``.safetensors``, e.g. from ``occkit convert``), or ``synthetic``."""
    entry: str | None = None
    """With ``weights``: the zoo entry (or experiment YAML) whose model and experiment run them; for a file, default
    the entry it was converted for."""
    config: str | None = None
    """With ``ckpt``: a zoo entry or experiment YAML to run the checkpoint with instead of its saved experiment (other
    data settings); its model must be the checkpoint's."""

    def __post_init__(self) -> None:
        if (self.ckpt is None) == (self.weights is None):
            raise ValueError("a model comes from a checkpoint or from weights: give exactly one")
        if self.ckpt is not None and self.entry is not None:
            raise ValueError("a checkpoint names its own model; a zoo entry goes with weights")
        if self.weights is not None and self.config is not None:
            raise ValueError("weights run with their zoo entry's experiment: name it as the entry, not as a config")
        if self.weights == SYNTHETIC and self.entry is None:
            raise ValueError(f"the {SYNTHETIC} weights are per zoo entry: name it (shipped: "
                             f"{', '.join(shipped_entries()) or 'none yet'})")  # fmt: skip

    @property
    def file(self) -> Path:
        """The file the weights are read from (the shipped file for ``synthetic``, checked against its card)."""
        if self.ckpt is not None:
            return Path(self.ckpt)
        return weights_path(self.entry) if self.weights == SYNTHETIC else Path(self.weights)

    @property
    def label(self) -> str:
        """A short name for legends: a checkpoint's run folder, else the entry and where its weights are from."""
        if self.ckpt is not None:
            return Path(self.ckpt).resolve().parent.name
        if self.weights == SYNTHETIC:
            return f"{self.entry}, {SYNTHETIC} weights"
        return f"{self.entry}, {Path(self.weights).name}" if self.entry else Path(self.weights).name

    def __str__(self) -> str:
        if self.ckpt is not None:
            return self.ckpt
        return f"{self.weights} ({self.entry})" if self.entry else self.weights

    def load_predicting(self, space: str | None, device: Any = "cpu") -> tuple[Any, Experiment, LabelSpace]:
        """:meth:`load`, for drawing predictions beside labels of label space ``space`` (None: the model's own):
        the model, its experiment and its label space; a missing file, or a model of another label space, is an
        error naming it."""
        from occkit.label_space import label_space

        if not self.file.is_file():
            raise FileNotFoundError(f"{self.file} does not exist")
        model, experiment = self.load(device)
        own = label_space(experiment.data.label_space)
        if space is not None and space != own.name:
            raise ValueError(f"{self} predicts {own.name} labels, not {space}")
        return model, experiment, own

    def load(self, device: Any = "cpu", overrides: Sequence[str] = ()) -> tuple[Any, Experiment]:
        """The model (an ``nn.Module``), in eval mode on ``device``, and the experiment to run it with
        (``overrides`` applied)."""
        from occkit import zoo
        from occkit.convert import load_weights, read_checkpoint
        from occkit.engine.evaluate import load_trained
        from occkit.shipped import load_shipped

        if self.ckpt is not None and self.config is not None:
            return load_trained(self.ckpt, device, experiment=zoo.load_experiment(self.config, overrides))
        if self.ckpt is not None:
            return load_trained(self.ckpt, device, overrides=overrides)
        entry = self.entry
        if entry is None:
            entry = read_checkpoint(self.weights).metadata.get("entry")
            if entry is None:
                raise ValueError(f"{self.weights} does not say which model it is: name its zoo entry")
        experiment = zoo.load_experiment(entry, overrides)
        model = zoo.build_from_config(experiment.architecture, experiment.model)
        if self.weights == SYNTHETIC:
            return load_shipped(model, entry).to(device).eval(), experiment
        return load_weights(self.weights, model).to(device).eval(), experiment
