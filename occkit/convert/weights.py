"""Converted weights on disk: ``occkit convert``'s ``.safetensors`` file and report, and loading weights into models.

:func:`convert_checkpoint` writes what :func:`~occkit.convert.conversion.convert_state_dict` made of a checkpoint
file, with its report; :func:`load_weights` loads occkit weights strictly (``occkit eval --weights``), and
:func:`load_partial` whatever of any checkpoint fits (``train.load_from``).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torch import Tensor, nn

from occkit import zoo
from occkit.config import ConfigError
from occkit.convert.conversion import (
    SOURCES,
    Conversion,
    _architecture_of,
    _check_architecture,
    _check_entry,
    _convert,
    _describe,
    _expected_state,
    _incomplete,
    convert_state_dict,
    default_entry,
    detect_source,
)
from occkit.outputs import check_report_file, write_atomic, write_report
from occkit.weight_files import WEIGHTS_FORMAT, read_checkpoint

# ----------------------------------------------------------------------------------------------------- writing
#: The command named in the reports :func:`convert_checkpoint` writes (an earlier one of them may be replaced).
_COMMAND = "occkit convert"


def report_path(out_path: str | Path) -> Path:
    """Where :func:`convert_checkpoint` writes its report: ``FILE.report.json`` beside ``FILE.safetensors``."""
    out_path = Path(out_path)
    return out_path.with_name(out_path.stem + ".report.json")


def convert_checkpoint(path: str | Path, entry: str | None, out_path: str | Path, strict: bool = True) -> Conversion:
    """Convert a checkpoint file for zoo entry ``entry`` and write ``out_path`` (.safetensors) and its report.

    Args:
        path: the reference checkpoint (see :func:`read_checkpoint`).
        entry: zoo entry; None takes the source's default (FlashOcc / BEVDet -> ``flashocc_m0``, DAOcc -> ``daocc``).
        out_path: the weights file; its metadata holds ``format``, ``entry``, ``architecture``, ``source``,
            ``source_file`` and ``complete``. The report goes to :func:`report_path` (``FILE.report.json``).
        strict: refuse an incomplete conversion; non-strict writes what maps (e.g. BEVDet's detection checkpoint
            as a start for FlashOcc) and marks the file incomplete.

    Returns:
        The conversion; ``conversion.report()`` is what the report file holds, ``conversion.files`` where it went.

    Raises:
        ConfigError: wrong model, or in strict mode an incomplete conversion (the report is written first and the
            message names it; no weights are written).
    """
    check_report(out_path)
    checkpoint = read_checkpoint(path)
    source = detect_source(list(checkpoint.state), str(checkpoint.path))
    entry = entry or checkpoint.metadata.get("entry") or default_entry(source)
    _check_entry(entry)
    _check_architecture(checkpoint, zoo.model_config(entry)[0], entry)
    try:
        conversion = convert_state_dict(checkpoint.state, entry, strict=False)
    except ConfigError as error:
        raise ConfigError(f"{checkpoint.path}: {error}") from error
    conversion.strict = strict
    conversion.source_file = checkpoint.path.name
    conversion.ignored = dict(checkpoint.ignored)
    out_path = Path(out_path)
    conversion.files = {"report": str(report_path(out_path))}
    if strict and not conversion.complete:
        _write_report(conversion)
        raise ConfigError(f"{checkpoint.path}: {_incomplete(conversion, checkpoint.state)} (full lists in "
                          f"{conversion.files['report']})")  # fmt: skip
    from safetensors.torch import save

    metadata = {"format": WEIGHTS_FORMAT, "entry": entry, "architecture": conversion.architecture,
                "source": conversion.source, "source_file": checkpoint.path.name,
                "complete": str(conversion.complete).lower()}  # fmt: skip
    # safetensors stores each tensor on its own: copies, so that views of one storage (possible in any state dict)
    # are written independently.
    state = {k: v.detach().contiguous().clone() for k, v in conversion.state.items()}
    # Through a temporary file and a rename: a full disk or a folder that cannot be written leaves the previous file
    # (or none), never a truncated one.
    write_atomic(out_path, save(state, metadata))
    conversion.files["weights"] = str(out_path)
    _write_report(conversion)
    return conversion


def check_report(out_path: str | Path) -> None:
    """Refuse, before any work, a ``FILE.report.json`` beside ``out_path`` that is not an earlier convert report."""
    check_report_file(report_path(out_path), _COMMAND, earlier_keys=("source_file", "counts", "mapped"))


def _write_report(conversion: Conversion) -> None:
    write_report(Path(conversion.files["report"]), conversion.report(), _COMMAND)


def format_report(report: Mapping[str, Any]) -> str:
    """The report as a few lines for a terminal."""
    counts = report["counts"]
    lines = [
        f"{report['source_file'] or 'state dict'}: {report['source_description']} checkpoint, "
        f"{counts['reference_tensors']} tensors -> {report['target']} ({counts['occkit_tensors']} tensors)",
        f"  mapped   {counts['mapped']}"
        + "".join(f"; {count} {note}" for note, count in report["layout_changes"].items()),
    ]
    if report["dropped_by_reason"]:
        lines.append(f"  dropped  {counts['dropped']}: "
                     + "; ".join(f"{n} {why}" for why, n in report["dropped_by_reason"].items()))  # fmt: skip
    if report["ignored_entries"]:
        ignored = report["ignored_entries"].items()
        lines.append("  ignored  top-level " + ", ".join(f"{k} ({why})" for k, why in ignored))
    lines.extend(f"  note     {note}" for note in report["notes"])
    if counts["defaulted"]:
        lines.append(f"  defaulted {counts['defaulted']} BatchNorm step counters the checkpoint lacks (set to 0)")
    for name, label in (("unmapped", "without counterpart"), ("shape_mismatches", "shape mismatches"),
                        ("missing", "occkit tensors unfilled")):  # fmt: skip
        if counts[name]:
            items = report[name]
            shown = [f"{m['reference_key']} {tuple(m['reference_shape'])} -> {m['key']} {tuple(m['occkit_shape'])}"
                     for m in items] if name == "shape_mismatches" else list(items)  # fmt: skip
            lines.append(f"  {label}: {counts[name]} ({', '.join(shown[:4])}{', ...' if len(shown) > 4 else ''})")
    if report["complete"]:
        verdict = "complete: every occkit tensor comes from the checkpoint, every reference tensor is placed or dropped"
    else:
        verdict = f"incomplete ({'refused, strict' if report['strict'] else 'partial, non-strict'})"
    lines.append(f"  {verdict}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------------- loading
def _check_fit(state: Mapping[str, Tensor], model: nn.Module, path: Path, note: str) -> None:
    """Raise ``ConfigError`` naming the first keys that keep ``state`` from loading strictly into ``model``."""
    expected = _expected_state(model)
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    wrong = [f"{k} is {tuple(state[k].shape)}, the model's {expected[k][0]}" for k in expected
             if k in state and tuple(state[k].shape) != expected[k][0]]  # fmt: skip
    problems = [f"{label} {', '.join(items[:3])}{' ...' if len(items) > 3 else ''} ({len(items)})"
                for label, items in (("shape:", wrong), ("missing:", missing), ("unexpected:", unexpected))
                if items]  # fmt: skip
    if problems:
        raise ConfigError(f"{path} does not fit the model{note}: {'; '.join(problems)}")


def load_weights(path: str | Path, entry_or_model: str | nn.Module) -> nn.Module:
    """Load converted weights (``.safetensors`` from :func:`convert_checkpoint`, an occkit checkpoint's weights, or a
    state dict in occkit's names) strictly into a model.

    Args:
        path: the weights file.
        entry_or_model: a zoo entry (the model is built) or a built model (loaded in place).

    Returns:
        The model, in its previous mode, on its previous device.

    Raises:
        ConfigError: the file holds a reference checkpoint (convert it first), or a key is missing, unexpected or of
            another shape (the message names it).
    """
    checkpoint = read_checkpoint(path)
    keys = list(checkpoint.state)
    if not checkpoint.occkit:
        source = detect_source(keys, str(checkpoint.path))
        if source.kind != "occkit":
            raise ConfigError(f"{checkpoint.path} is a {_describe(source, keys)} checkpoint: convert it first "
                              f"(occkit convert {checkpoint.path} --out FILE.safetensors)")  # fmt: skip
    if isinstance(entry_or_model, str):
        _check_entry(entry_or_model)
        _check_architecture(checkpoint, zoo.model_config(entry_or_model)[0], entry_or_model)
        model = zoo.build(entry_or_model)
    else:
        model = entry_or_model
        _check_architecture(checkpoint, _architecture_of(model), "the model")
    converted_for = checkpoint.metadata.get("entry")
    note = f" (converted for {converted_for})" if converted_for and converted_for != entry_or_model else ""
    if checkpoint.metadata.get("complete") == "false":
        note += " (a partial conversion: use it with train.load_from)"
    _check_fit(checkpoint.state, model, checkpoint.path, note)
    model.load_state_dict(checkpoint.state, strict=True)
    return model


@dataclass
class PartialLoad:
    """What :func:`load_partial` loaded; ``str()`` is the summary a training run prints."""

    path: Path
    conversion: Conversion
    ignored: dict[str, str]
    loaded: int
    total: int

    def __str__(self) -> str:
        c = self.conversion
        lines = [f"load_from {self.path} ({c.source_description}): {self.loaded} of the model's {self.total} "
                 f"tensors loaded"]  # fmt: skip
        left = sorted(set(c.missing) | {m.key for m in c.shape_mismatches})
        if left:
            lines.append(f"  kept at their initialisation: {len(left)} ({', '.join(left[:4])}"
                         f"{', ...' if len(left) > 4 else ''})")  # fmt: skip
        for why, count in Counter(c.dropped.values()).items():
            lines.append(f"  skipped {count}: {why}")
        if c.shape_mismatches:
            lines.append(f"  skipped {len(c.shape_mismatches)} of another shape: " + ", ".join(
                f"{m.reference_key} {m.reference_shape} (model {m.occkit_shape})" for m in c.shape_mismatches[:4])
                + (", ..." if len(c.shape_mismatches) > 4 else ""))  # fmt: skip
        if c.unmapped:
            lines.append(f"  skipped {len(c.unmapped)} without counterpart: {', '.join(list(c.unmapped)[:4])}"
                         f"{', ...' if len(c.unmapped) > 4 else ''}")  # fmt: skip
        return "\n".join(lines)


def load_partial(model: nn.Module, path: str | Path, experiment: Any = None) -> PartialLoad:
    """Load whatever of a checkpoint fits ``model`` (``train.load_from``): occkit weights or checkpoints, or a
    reference checkpoint converted on the fly; tensors of another shape and keys without counterpart are skipped
    and listed.

    Args:
        model: the built model, loaded in place.
        path: the weights (see :func:`read_checkpoint`).
        experiment: the model's experiment (its ``architecture`` is used); None finds the architecture from the model.

    Raises:
        ConfigError: a checkpoint of another architecture, or nothing of it fits the model.
    """
    checkpoint = read_checkpoint(path)
    architecture = experiment.architecture if experiment is not None else _architecture_of(model)
    _check_architecture(checkpoint, architecture, "the model")
    keys = list(checkpoint.state)
    source = SOURCES["occkit"] if checkpoint.occkit else detect_source(keys, str(checkpoint.path))
    expected = _expected_state(model)
    try:
        conversion = _convert(checkpoint.state, architecture, expected, "the model", False, source)
    except ConfigError as error:
        raise ConfigError(f"{checkpoint.path}: {error}") from error
    loaded = {k: v for k, v in conversion.state.items() if k not in conversion.defaulted}
    if not loaded:
        raise ConfigError(f"{checkpoint.path}: none of its tensors fits this {architecture} model "
                          f"({conversion.problems()})")  # fmt: skip
    model.load_state_dict(loaded, strict=False)
    return PartialLoad(checkpoint.path, conversion, checkpoint.ignored, len(loaded), len(expected))
