"""Reference state dicts -> occkit's keys: the family a checkpoint is of, its tensors renamed, re-laid and checked.

:func:`convert_state_dict` maps every tensor of a reference state dict onto the parameter of the target model (a zoo
entry's, or a built model) that plays its part, with the rules of the checkpoint's family
(:mod:`occkit.convert.flashocc`, :mod:`occkit.convert.daocc`; occkit's own names map onto themselves), and says in a
:class:`Conversion` what it placed, dropped with a reason, could not place, or left unfilled.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from occkit import zoo
from occkit.config import ConfigError
from occkit.convert import daocc, flashocc
from occkit.convert.rules import BEV_YX, SAME, SPARSE, Drop, Rule, Source, _rule
from occkit.weight_files import ReferenceCheckpoint, strip_wrappers

# ----------------------------------------------------------------------------------------------------- sources
SOURCES: dict[str, Source] = {
    source.kind: source
    for source in (
        flashocc.SOURCE,
        daocc.SOURCE,
        # occkit's top-level module names over its architectures; "fuser.mix." keeps DAOcc's "fuser.0." apart.
        Source("occkit", "occkit weights", None,
               ("image_encoder.", "view_transform.", "lidar_encoder.", "fuser.mix.", "bev_encoder.", "range_extension.",
                "occupancy_head.", "detection_head.", "depth_net.", "height_net.", "bev_horizontal.",
                "bev_vertical.", "height_vertical.", "height_reduce.", "fuse."), None),
    )
}  # fmt: skip


def detect_source(keys: Sequence[str], where: str = "the checkpoint") -> Source:
    """The family whose prefixes cover most of ``keys``.

    Raises:
        ConfigError: no family claims any key (the message shows a few of them).
    """
    claimed = {kind: sum(key.startswith(source.prefixes) for key in keys) for kind, source in SOURCES.items()}
    best = max(claimed, key=claimed.get)
    if claimed[best] == 0:
        sample = ", ".join(list(keys)[:5]) or "no keys at all"
        raise ConfigError(f"{where} is neither a FlashOcc / BEVDet, a DAOcc nor an occkit checkpoint (keys: {sample})")
    return SOURCES[best]


def _describe(source: Source, keys: Sequence[str]) -> str:
    """The source's description, told more precisely where the keys allow (BEVDet's detection model)."""
    if (
        source.kind == "flashocc"
        and any(k.startswith("pts_bbox_head.") for k in keys)
        and not any(k.startswith("occ_head.") for k in keys)
    ):
        return "BEVDet detection (mmdet3d BEVDet with a CenterHead, no occupancy head)"
    return source.description


def default_entry(source: Source) -> str:
    """The zoo entry a checkpoint of ``source`` converts to when none is named.

    Raises:
        ConfigError: the source fits several entries equally (occkit weights).
    """
    if source.default_entry is None:
        raise ConfigError(f"{source.description} fit any zoo entry of their architecture: name one with --model")
    return source.default_entry


# ----------------------------------------------------------------------------------------------------- key tables
#: Per source: its rules, its drops, and occkit prefixes whose tensors the target model may lack on purpose.
_TABLES: dict[str, tuple[list[Rule], list[Drop], dict[str, str]]] = {
    "flashocc": (flashocc.RULES, flashocc.DROPS, {}),
    "daocc": (daocc.RULES, daocc.DROPS, daocc.OPTIONAL),
    "occkit": ([_rule(r"(.+)", r"\1")], [], {}),
}

_NO_BATCH_COUNTER = "BatchNorm step counter: the occkit module keeps none"
_LAYOUT_NOTES = {
    BEV_YX: "with the kernel transposed (the reference runs the conv on (Y, X) BEV maps, occkit on (X, Y))",
    "rsck": "permuted from spconv 1.x's (kx, ky, kz, in, out) to spconv 2.x's (out, kx, ky, kz, in)",
}


# ----------------------------------------------------------------------------------------------------- conversion
class ShapeMismatch(NamedTuple):
    """A tensor whose shape does not fit (shapes as stored, before any layout change)."""

    key: str
    """The occkit key."""
    reference_shape: tuple[int, ...]
    occkit_shape: tuple[int, ...]
    reference_key: str


@dataclass
class Conversion:
    """What :func:`convert_state_dict` made of a reference state dict."""

    target: str
    """The zoo entry converted to (``the model`` for :func:`load_partial`)."""
    architecture: str
    source: str
    """``flashocc``, ``daocc`` or ``occkit``."""
    source_description: str
    strict: bool
    state: dict[str, Tensor] = field(default_factory=dict, repr=False)
    """occkit key -> tensor, in occkit's layout and dtype."""
    mapped: dict[str, str] = field(default_factory=dict)
    """Reference key -> occkit key, for every tensor in :attr:`state`."""
    dropped: dict[str, str] = field(default_factory=dict)
    """Reference key -> why occkit does not keep it."""
    unmapped: dict[str, str] = field(default_factory=dict)
    """Reference key -> why it found no place (no rule, or the rule's target is not in this model)."""
    missing: list[str] = field(default_factory=list)
    """occkit keys left unfilled."""
    shape_mismatches: list[ShapeMismatch] = field(default_factory=list)
    transforms: dict[str, str] = field(default_factory=dict)
    """occkit key -> the layout change applied to its tensor."""
    defaulted: dict[str, str] = field(default_factory=dict)
    """occkit key -> the value given without a reference tensor (BatchNorm counters a checkpoint lacks)."""
    notes: list[str] = field(default_factory=list)
    source_file: str | None = None
    """The checkpoint's file name, when converted from a file."""
    ignored: dict[str, str] = field(default_factory=dict)
    """The file's top-level entries besides the weights -> what they are."""
    files: dict[str, str] = field(default_factory=dict)
    """What :func:`convert_checkpoint` wrote: ``weights`` and ``report`` paths."""

    @property
    def complete(self) -> bool:
        """Every reference tensor placed or dropped with a reason, every occkit tensor filled, every shape right."""
        return not (self.unmapped or self.missing or self.shape_mismatches)

    def problems(self, limit: int = 4) -> str:
        """One line naming the keys that keep the conversion from being complete ('' when it is)."""

        def listed(items: Sequence[str]) -> str:
            more = f", and {len(items) - limit} more" if len(items) > limit else ""
            return ", ".join(items[:limit]) + more

        parts = []
        if self.unmapped:
            parts.append(f"{len(self.unmapped)} reference key(s) without an occkit counterpart: "
                         + listed([f"{k} ({why})" for k, why in self.unmapped.items()]))  # fmt: skip
        if self.shape_mismatches:
            parts.append(f"{len(self.shape_mismatches)} shape mismatch(es): " + listed(
                [f"{m.reference_key} {m.reference_shape} -> {m.key} needs {m.occkit_shape}"
                 for m in self.shape_mismatches]))  # fmt: skip
        if self.missing:
            parts.append(f"{len(self.missing)} occkit key(s) left unfilled: {listed(self.missing)}")
        return "; ".join(parts)

    def report(self) -> dict[str, Any]:
        """Plain-data summary: counts, drops grouped by reason, layout changes, and every problem key."""
        counts = {
            "reference_tensors": len(self.mapped) + len(self.dropped) + len(self.unmapped)
            + len({m.reference_key for m in self.shape_mismatches}),
            "mapped": len(self.mapped),
            "dropped": len(self.dropped),
            "unmapped": len(self.unmapped),
            "shape_mismatches": len(self.shape_mismatches),
            "occkit_tensors": len(self.state) + len(self.missing) + len(self.shape_mismatches),
            "filled": len(self.state),
            "defaulted": len(self.defaulted),
            "missing": len(self.missing),
        }  # fmt: skip
        return {
            "source_file": self.source_file,
            "source": self.source,
            "source_description": self.source_description,
            "target": self.target,
            "architecture": self.architecture,
            "strict": self.strict,
            "complete": self.complete,
            "counts": counts,
            "dropped_by_reason": dict(Counter(self.dropped.values())),
            "layout_changes": dict(Counter(self.transforms.values())),
            "ignored_entries": dict(self.ignored),
            "files": dict(self.files),
            "notes": list(self.notes),
            "unmapped": dict(self.unmapped),
            "shape_mismatches": [m._asdict() for m in self.shape_mismatches],
            "missing": list(self.missing),
            "defaulted": dict(self.defaulted),
            "dropped": dict(self.dropped),
            "mapped": dict(self.mapped),
        }


Expected = dict[str, tuple[tuple[int, ...], torch.dtype]]


def _expected_state(model: nn.Module) -> Expected:
    return {key: (tuple(value.shape), value.dtype) for key, value in model.state_dict().items()}


def _entry_expected(entry: str) -> tuple[str, Expected]:
    """``(architecture, occkit key -> (shape, dtype))`` of a zoo entry's model, built on the meta device (no memory,
    no initialisation) or, if a module refuses that, on the CPU."""
    architecture, cfg = zoo.model_config(entry)
    try:
        with torch.device("meta"):
            model = zoo.build_from_config(architecture, cfg)
    except (RuntimeError, NotImplementedError):
        model = zoo.build_from_config(architecture, cfg)
    return architecture, _expected_state(model)


def _map_key(key: str, rules: Sequence[Rule]) -> tuple[str | None, str]:
    for rule in rules:
        match = rule.pattern.fullmatch(key)
        if match is not None:
            return rule.target(match), rule.layout
    return None, SAME


def _sparse_layout(candidates: list[tuple[str, Tensor, tuple[int, ...]]]) -> str:
    """``rsck`` (spconv 1.x, DAOcc's bundled spconv) or ``krsc`` (spconv 2.x, occkit's) for all 5-D sparse conv
    weights of a checkpoint: the one every shape fits; spconv 1.x when both or neither fit (the reference's own)."""
    krsc = all(tuple(t.shape) == shape for _, t, shape in candidates)
    rsck = all(tuple(t.permute(4, 0, 1, 2, 3).shape) == shape for _, t, shape in candidates)
    return "krsc" if krsc and not rsck else "rsck"


def _relayout(tensor: Tensor, layout: str, sparse: str) -> tuple[Tensor, str | None]:
    """The tensor in occkit's layout, and the note of the change made (None: none)."""
    if layout == BEV_YX and tensor.ndim == 4:
        changed = tensor.shape[-1] * tensor.shape[-2] > 1
        return tensor.transpose(-1, -2).contiguous(), (_LAYOUT_NOTES[BEV_YX] if changed else None)
    if layout == SPARSE and tensor.ndim == 5 and sparse == "rsck":
        return tensor.permute(4, 0, 1, 2, 3).contiguous(), _LAYOUT_NOTES["rsck"]
    return tensor, None


def _entries_of(architecture: str | None) -> list[str]:
    """The zoo entries of an architecture (from its declaration: no preset is run)."""
    return zoo.names(architecture) if architecture in zoo.ARCHITECTURES else []


def _check_entry(entry: str) -> None:
    if entry not in zoo.names():
        raise ConfigError(f"unknown zoo entry {entry!r}; the zoo has: {', '.join(zoo.names())}")


def _wrong_model(source: Source, description: str, architecture: str, target: str) -> ConfigError:
    entries = _entries_of(source.architecture)
    hint = (f"it fits the {source.architecture} entries ({', '.join(entries)})" if entries
            else "occkit has no model of that architecture")  # fmt: skip
    return ConfigError(f"the checkpoint is a {description} checkpoint, but {target} is a {architecture} model: "
                       f"{hint}")  # fmt: skip


def _convert(
    reference_state: Mapping[str, Tensor],
    architecture: str,
    expected: Expected,
    target: str,
    strict: bool,
    source: Source | None = None,
) -> Conversion:
    """Map ``reference_state`` onto the occkit keys and shapes ``expected``; see :func:`convert_state_dict`."""
    reference_state = strip_wrappers(reference_state)
    keys = list(reference_state)
    source = source or detect_source(keys)
    description = _describe(source, keys)
    if source.architecture is not None and source.architecture != architecture:
        raise _wrong_model(source, description, architecture, target)
    if source.kind not in _TABLES:
        raise ConfigError(f"no conversion table for {description} checkpoints")
    rules, drops, optional = _TABLES[source.kind]
    result = Conversion(target=target, architecture=architecture, source=source.kind, source_description=description,
                        strict=strict)  # fmt: skip

    # First pass: names. The sparse layout is decided over all sparse weights together (it is one per checkpoint).
    placed: list[tuple[str, Tensor, str, str]] = []
    for key, tensor in reference_state.items():
        reason = next((drop.reason for drop in drops if drop.pattern.fullmatch(key)), None)
        if reason is not None:
            result.dropped[key] = reason
            continue
        name, layout = _map_key(key, rules)
        if name is None:
            result.unmapped[key] = "no rule maps it"
        elif name not in expected:
            lacking = next((why for prefix, why in optional.items() if name.startswith(prefix)), None)
            if lacking is not None:
                result.dropped[key] = lacking
            elif key.endswith(".num_batches_tracked"):
                result.dropped[key] = _NO_BATCH_COUNTER
            else:
                result.unmapped[key] = f"maps to {name}, which {target} does not have"
        else:
            placed.append((key, tensor, name, layout))
    sparse_weights = [(k, t, expected[n][0]) for k, t, n, lay in placed if lay == SPARSE and t.ndim == 5]
    sparse = _sparse_layout(sparse_weights)
    if sparse_weights and sparse == "krsc":  # the usual spconv 1.x case shows in the layout changes
        result.notes.append(f"{len(sparse_weights)} sparse convolution weights already in spconv 2.x's layout "
                            "(out, kx, ky, kz, in): kept as they are")  # fmt: skip

    # Second pass: tensors, in occkit's layout, shape and dtype.
    owners: dict[str, str] = {}
    casts: Counter[str] = Counter()
    for key, tensor, name, layout in placed:
        if name in owners:
            result.unmapped[key] = f"maps to {name}, already filled from {owners[name]}"
            continue
        shape, dtype = expected[name]
        if tensor.dtype.is_floating_point != dtype.is_floating_point:
            result.unmapped[key] = f"maps to {name}, but holds {tensor.dtype} where occkit keeps {dtype}"
            continue
        value, note = _relayout(tensor, layout, sparse)
        if tuple(value.shape) != shape:
            result.shape_mismatches.append(ShapeMismatch(name, tuple(tensor.shape), shape, key))
            continue
        if value.dtype != dtype:
            casts[f"{value.dtype} -> {dtype}".replace("torch.", "")] += 1
            value = value.to(dtype)
        owners[name] = key
        result.state[name] = value
        result.mapped[key] = name
        if note is not None:
            result.transforms[name] = note
    result.notes.extend(f"{count} tensor(s) cast {cast}" for cast, count in sorted(casts.items()))

    mismatched = {m.key for m in result.shape_mismatches}
    for name, (shape, dtype) in expected.items():
        if name in result.state or name in mismatched:
            continue
        if name.endswith(".num_batches_tracked"):
            # Only read when BatchNorm's momentum is None (never in these models); checkpoints written before
            # PyTorch 0.4.1 lack it.
            result.state[name] = torch.zeros(shape, dtype=dtype)
            result.defaulted[name] = "0 (BatchNorm step counter, not in the checkpoint)"
        else:
            result.missing.append(name)
    return result


def convert_state_dict(
    reference_state: Mapping[str, Tensor], entry: str | nn.Module, strict: bool = True
) -> Conversion:
    """Map a reference state dict onto the model of zoo entry ``entry``, or onto a model built from a config.

    Args:
        reference_state: reference key -> tensor (``module.`` prefixes already stripped, see :func:`read_checkpoint`).
        entry: zoo entry, e.g. ``flashocc_m0``, ``flashocc_m1``, ``daocc``; any entry whose model has the
            reference's module structure converts when the shapes fit. Or an occkit model (e.g. one of a reference
            config's reduced width, as the parity tests build).
        strict: raise unless the conversion is complete.

    Returns:
        The :class:`Conversion`; its ``state`` loads into ``zoo.build(entry)`` (or the model) with ``strict=True``
        when complete.

    Raises:
        ConfigError: the checkpoint is of another model (the message names both), or, in strict mode, a reference key
            without counterpart, an unfilled occkit key or a shape mismatch (the message names them, and other
            entries of the architecture the checkpoint fits).
    """
    if isinstance(entry, nn.Module):
        architecture, expected = _architecture_of(entry), _expected_state(entry)
        entry = f"the given {architecture} model"
    else:
        _check_entry(entry)
        architecture, expected = _entry_expected(entry)
    conversion = _convert(reference_state, architecture, expected, entry, strict)
    if strict and not conversion.complete:
        raise _incomplete(conversion, reference_state)
    return conversion


def _incomplete(conversion: Conversion, reference_state: Mapping[str, Tensor]) -> ConfigError:
    """The strict-mode error: the problem keys, and other entries the checkpoint fits when shapes are the issue."""
    fits = _fitting_entries(reference_state, conversion.architecture, conversion.target) \
        if conversion.shape_mismatches else []  # fmt: skip
    hint = f" (the checkpoint fits {', '.join(fits)})" if fits else ""
    return ConfigError(f"{conversion.source_description} checkpoint does not convert to {conversion.target}{hint}: "
                       f"{conversion.problems()}")  # fmt: skip


def _fitting_entries(reference_state: Mapping[str, Tensor], architecture: str, entry: str, limit: int = 3) -> list[str]:
    """Other zoo entries of ``architecture`` the state converts to completely (to suggest on a shape mismatch)."""
    fits = []
    for name in _entries_of(architecture):
        if name == entry:
            continue
        try:
            if _convert(reference_state, architecture, _entry_expected(name)[1], name, strict=False).complete:
                fits.append(name)
        except (ConfigError, ValueError):  # an entry that does not build right now suggests nothing
            continue
        if len(fits) == limit:
            break
    return fits


def _check_architecture(checkpoint: ReferenceCheckpoint, architecture: str, target: str) -> None:
    """Refuse an occkit file whose weights are of another architecture than ``target``'s."""
    if checkpoint.architecture is not None and checkpoint.architecture != architecture:
        entry = checkpoint.metadata.get("entry")
        held = f"{entry} ({checkpoint.architecture})" if entry else f"a {checkpoint.architecture} model"
        raise ConfigError(f"{checkpoint.path} holds the weights of {held}, but {target} is a {architecture} model")


def _architecture_of(model: nn.Module) -> str:
    for name, arch in zoo.ARCHITECTURES.items():
        if isinstance(model, arch.model):
            return name
    raise ConfigError(f"{type(model).__name__} is not a model of the zoo's architectures")
