"""What a robustness run evaluates: cases (a corruption at a level, or the clean data) and the named suites.

A suite is ``default`` (every corruption at every level), ``quick`` (one level of each kind of failure, for a
check in minutes) or a comma-separated list of ``NAME`` (every level) and ``NAME:LEVEL`` (a level by number or by
label, e.g. ``missing_camera:CAM_FRONT``, ``fog:3``). A case applies when the model takes what the corruption
needs (:attr:`~occkit.data.corruptions.Corruption.needs`); the others are reported as not applicable.
"""

from __future__ import annotations

from dataclasses import dataclass

from occkit.data.corruptions import CORRUPTIONS, Corruption

__all__ = ["Case", "SUITES", "CLEAN", "parse_suite", "model_inputs", "not_applicable"]


@dataclass(frozen=True, order=True)
class Case:
    """One evaluation: ``corruption`` at ``severity``; ``corruption=None`` is the clean data."""

    corruption: str | None
    severity: int = 0

    @property
    def key(self) -> str:
        """File-name-safe id: ``clean`` or ``<name>-<severity>``."""
        return "clean" if self.corruption is None else f"{self.corruption}-{self.severity}"

    @property
    def label(self) -> str:
        if self.corruption is None:
            return "clean"
        return f"{self.corruption} {CORRUPTIONS[self.corruption].labels[self.severity - 1]}"


CLEAN = Case(None)

#: Suite name -> its cases (before the model's inputs leave some out).
SUITES: dict[str, tuple[Case, ...]] = {
    "default": tuple(Case(name, level) for name, c in CORRUPTIONS.items() for level in c.severities),
    # One level of each kind of failure: the front camera, half the rig, each sensor alone, weather and light, a
    # sparser LiDAR, calibration and timing, a lost history.
    "quick": (
        Case("missing_camera", 2),  # CAM_FRONT
        Case("missing_cameras", 2),
        Case("no_cameras", 1),
        Case("low_light", 2),
        Case("fog", 2),
        Case("motion_blur", 2),
        Case("lidar_beams", 2),
        Case("no_lidar", 1),
        Case("camera_extrinsics", 2),
        Case("lidar_delay", 2),
        Case("history_dropped", 2),
    ),
}


def _level(corruption: Corruption, text: str, item: str) -> int:
    if text.isdigit() and int(text) in corruption.severities:
        return int(text)
    if text in corruption.labels:
        return corruption.labels.index(text) + 1
    levels = ", ".join(f"{i} ({label})" for i, label in zip(corruption.severities, corruption.labels, strict=True))
    raise ValueError(f"--suite item {item!r}: {corruption.name} has levels {levels}")


def parse_suite(text: str) -> tuple[Case, ...]:
    """The cases of a suite name or of a comma-separated list of ``NAME`` / ``NAME:LEVEL``, in the order given,
    each once."""
    if text in SUITES:
        return SUITES[text]
    cases: list[Case] = []
    for item in (part.strip() for part in text.split(",")):
        name, _, level = item.partition(":")
        if name not in CORRUPTIONS:
            raise ValueError(f"--suite {text!r}: {name!r} is neither a suite ({', '.join(SUITES)}) nor a corruption "
                             f"({', '.join(CORRUPTIONS)})")  # fmt: skip
        corruption = CORRUPTIONS[name]
        levels = [_level(corruption, level, item)] if level else list(corruption.severities)
        cases += [Case(name, s) for s in levels if Case(name, s) not in cases]
    return tuple(cases)


def model_inputs(cameras: bool, lidar: bool, temporal: bool) -> frozenset[str]:
    """What a model takes, in the terms of :attr:`~occkit.data.corruptions.Corruption.needs`."""
    return frozenset(name for name, used in (("cameras", cameras), ("lidar", lidar), ("temporal", temporal)) if used)


def not_applicable(case: Case, inputs: frozenset[str]) -> str | None:
    """Why the case does not apply to a model with ``inputs``; None when it does."""
    if case.corruption is None:
        return None
    needs = CORRUPTIONS[case.corruption].needs
    if all(need in inputs for need in needs):
        return None
    return f"needs a model that takes {' and '.join(needs)}"
