"""Official checkpoints -> occkit weights: FlashOcc / BEVDet and DAOcc state dicts renamed, re-laid and checked.

``occkit convert CKPT --model ENTRY --out FILE.safetensors`` reads a checkpoint of a reference implementation,
maps every tensor onto the parameter of the zoo entry's model that plays its part, and writes them with a report::

    conversion = convert_checkpoint("epoch_24_ema.pth", "daocc", "daocc.safetensors")   # + daocc.report.json
    model = load_weights("daocc.safetensors", "daocc")                                   # strict, shape-checked

Sources (told apart by their key prefixes, :func:`detect_source`):

* ``flashocc``: FlashOcc's ``BEVDetOCC`` (Yzichen/FlashOCC, an mmdet3d 1.0 plugin), and BEVDet's detection model
  (``bevdet-r50-cbgs.pth``, which FlashOcc's configs start from with ``load_from``): ``img_backbone`` (mmdet's
  ResNet, torchvision's parameter names), ``img_neck`` (``CustomFPN``), ``img_view_transformer.depth_net``,
  ``img_bev_encoder_backbone`` (``CustomResNet``), ``img_bev_encoder_neck`` (``FPN_LSS``), ``occ_head``
  (``BEVOCCHead2D``), and in BEVDet's file ``pts_bbox_head`` (a ``CenterHead`` the occupancy model does not have).
* ``daocc``: DAOcc's ``BEVFusion`` (AlphaPlusTT/DAOcc): ``encoders.camera.{backbone,neck,vtransform}``,
  ``encoders.lidar.backbone`` (mmdet3d's ``SparseEncoder``), ``fuser``, ``decoder.{backbone,neck}``,
  ``heads.object`` (``CenterHead``) and ``heads.occ`` (``BEVOCCHead2D`` with its ``CrossCoordinateSample``).
* ``occkit``: weights already in occkit's names (a converted ``.safetensors``, an occkit checkpoint).

Layouts that differ, and why the tensors are changed rather than only renamed:

* **BEV axes.** occkit keeps every BEV map as ``(B, C, X, Y)``. BEVDet/FlashOcc run their BEV encoder and occupancy
  head on ``(B, C, Y, X)``, and DAOcc's occupancy head swaps its ``(X, Y)`` input to ``(Y, X)`` before its
  ``final_conv``. Convolving the transposed map with the transposed kernel gives the transposed result, so the
  kernels of exactly those convolutions are transposed (``weight.transpose(-1, -2)``, a no-op for 1 x 1 kernels);
  all else in those modules (BatchNorm, biases, linear layers) is unchanged.
* **Sparse convolutions.** DAOcc's ``SparseEncoder`` uses the spconv 1.x bundled in its ``mmdet3d/ops/spconv``
  (its docs/install.md installs no spconv package), whose weights are ``(kx, ky, kz, in, out)``; spconv 2.x, which
  occkit uses, stores ``(out, kx, ky, kz, in)``. The kernel axes are in the same order on both sides: BEVFusion's
  voxelizer writes ``(x, y, z)`` coordinates (not mmdet3d's usual ``(z, y, x)``) for its ``[1440, 1440, 41]`` sparse
  shape, as occkit does, so the permutation is ``(4, 0, 1, 2, 3)`` and nothing else. A checkpoint re-saved from
  spconv 2.x already has occkit's layout; the layout is read off the shapes, once per checkpoint, and reported.

Everything else maps key for key. Keys a reference keeps that occkit does not need are dropped with a reason
(sampling-point buffers occkit computes from the config, BEVDet's detection head, ``num_batches_tracked`` where
occkit's module has none); any other difference (a key without counterpart, an occkit tensor left unfilled, a shape
that differs) is an error in strict mode, naming the keys. Non-strict mode (``train.load_from``, :func:`load_partial`)
loads what fits and lists the rest.

Files are read with ``torch.load(weights_only=True)`` (numpy scalars and arrays in mmcv's ``meta`` are allowed; they
rebuild plain data), never by unpickling code.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from occkit import zoo
from occkit.config import ConfigError
from occkit.outputs import check_report_file, write_atomic, write_report
from occkit.weight_files import WEIGHTS_FORMAT, check_finite, load_torch_file, read_safetensors

__all__ = [
    "WEIGHTS_FORMAT",
    "Source",
    "SOURCES",
    "ShapeMismatch",
    "Conversion",
    "ReferenceCheckpoint",
    "PartialLoad",
    "read_checkpoint",
    "detect_source",
    "default_entry",
    "convert_state_dict",
    "convert_checkpoint",
    "report_path",
    "format_report",
    "load_weights",
    "load_partial",
]


#: How the ``format`` marker of occkit's run checkpoints (``occkit.engine.checkpoint.FORMAT``) begins. Matched by
#: prefix, not imported: the engine loads reference weights through this module (``train.load_from``), so this
#: module sits below it.
_CHECKPOINT_FORMAT_PREFIX = "occkit-checkpoint/"


# ----------------------------------------------------------------------------------------------------- sources
@dataclass(frozen=True)
class Source:
    """A family of checkpoints, recognised by the prefixes of its keys."""

    kind: str
    """``flashocc``, ``daocc`` or ``occkit``."""
    description: str
    """What such a checkpoint is, for messages."""
    architecture: str | None
    """The occkit architecture its weights belong to (None: any, the names are occkit's own)."""
    prefixes: tuple[str, ...]
    """Key prefixes only this family uses."""
    default_entry: str | None
    """The zoo entry a conversion targets when none is named."""


SOURCES: dict[str, Source] = {
    source.kind: source
    for source in (
        Source("flashocc", "FlashOcc / BEVDet (mmdet3d BEVDetOCC)", "flashocc",
               ("img_backbone.", "img_neck.", "img_view_transformer.", "img_bev_encoder_backbone.",
                "img_bev_encoder_neck.", "occ_head.", "pts_bbox_head."), "flashocc_m0"),
        Source("daocc", "DAOcc (BEVFusion-style)", "daocc",
               ("encoders.camera.", "encoders.lidar.", "fuser.0.", "fuser.1.", "decoder.backbone.", "decoder.neck.",
                "heads.occ.", "heads.object."), "daocc"),
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
    if source.kind == "flashocc" and any(k.startswith("pts_bbox_head.") for k in keys) and not any(
        k.startswith("occ_head.") for k in keys
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
#: Layout changes (see the module docstring). ``same``: renamed only.
SAME, BEV_YX, SPARSE = "same", "bev_yx", "sparse"

#: BatchNorm's tensors, one regex group.
_BN = r"(weight|bias|running_mean|running_var|num_batches_tracked)"

Target = Callable[[re.Match], "str | None"]


@dataclass(frozen=True)
class Rule:
    """A reference key pattern (full match) and its occkit name; ``layout`` says how the tensor is re-laid."""

    pattern: re.Pattern
    target: Target
    layout: str = SAME


@dataclass(frozen=True)
class Drop:
    """Reference keys occkit does not keep, and why."""

    pattern: re.Pattern
    reason: str


def _rule(pattern: str, target: str | Target, layout: str = SAME) -> Rule:
    """``target``: a ``re`` template (``\\1``) or a function of the match returning the name (None: no mapping)."""
    expand = (lambda m: m.expand(target)) if isinstance(target, str) else target
    return Rule(re.compile(pattern), expand, layout)


def _drop(pattern: str, reason: str) -> Drop:
    return Drop(re.compile(pattern), reason)


def _resnet(prefix: str, target: str) -> list[Rule]:
    """mmdet's ResNet (torchvision's names: conv1, bn1, layerN.M.*) -> ``ResNetBackbone`` (stem.0/1, stages.N-1)."""
    p = re.escape(prefix)
    return [
        _rule(rf"{p}conv1\.weight", f"{target}stem.0.weight"),
        _rule(rf"{p}bn1\.{_BN}", rf"{target}stem.1.\1"),
        _rule(rf"{p}layer(\d+)\.(.+)", lambda m: f"{target}stages.{int(m[1]) - 1}.{m[2]}"),
    ]


#: ``FPN_LSS`` (BEVDet, DAOcc): ``conv`` = Sequential(conv3x3, BN, ReLU, conv3x3, BN, ReLU), ``up2`` =
#: Sequential(Upsample, conv3x3, BN, ReLU, conv1x1) -> occkit's ``FPNLSS`` ``fuse`` (two conv-BN-ReLU) and
#: ``project`` (conv-BN-ReLU, conv1x1).
_FPN_LSS = {
    ("conv", 0): "fuse.0.0", ("conv", 1): "fuse.0.1", ("conv", 3): "fuse.1.0", ("conv", 4): "fuse.1.1",
    ("up2", 1): "project.0.0", ("up2", 2): "project.0.1", ("up2", 4): "project.1",
}  # fmt: skip


def _bev_encoder(backbone: str, neck: str, target: str, layout: str) -> list[Rule]:
    """``CustomResNet`` (``layers.N.M`` BasicBlocks, ``downsample`` a plain strided conv) and ``FPN_LSS`` ->
    occkit's ``BevEncoder``; ``layout`` is BEV_YX where the reference runs them on ``(Y, X)`` maps."""

    def neck_target(m: re.Match) -> str | None:
        name = _FPN_LSS.get((m[1], int(m[2])))
        return None if name is None else f"{target}neck.{name}.{m[3]}"

    return [
        _rule(rf"{re.escape(backbone)}layers\.(\d+)\.(\d+)\.(.+)", rf"{target}backbone.stages.\1.\2.\3", layout),
        _rule(rf"{re.escape(neck)}(conv|up2)\.(\d+)\.(.+)", neck_target, layout),
    ]


def _center_head(prefix: str, target: str) -> list[Rule]:
    """mmdet3d's ``CenterHead``: ``shared_conv`` and every ``SeparateHead`` branch are ConvModules (``conv``, ``bn``)
    then a plain output conv; occkit flattens each into one Sequential, index ``i`` of the reference at ``3 i``."""
    p = re.escape(prefix)
    branch = rf"{p}task_heads\.(\d+)\.(\w+)\.(\d+)\."

    def name(m: re.Match, offset: int, rest: str) -> str:
        return f"{target}task_heads.{m[1]}.branches.{m[2]}.{3 * int(m[3]) + offset}.{rest}"

    return [
        _rule(rf"{p}shared_conv\.conv\.weight", f"{target}shared_conv.0.weight"),
        _rule(rf"{p}shared_conv\.bn\.{_BN}", rf"{target}shared_conv.1.\1"),
        _rule(rf"{branch}conv\.weight", lambda m: name(m, 0, "weight")),
        _rule(rf"{branch}bn\.{_BN}", lambda m: name(m, 1, m[4])),
        _rule(rf"{branch}(weight|bias)", lambda m: name(m, 0, m[4])),
    ]


#: FlashOcc ``BEVDetOCC`` (projects/mmdet3d_plugin/models/detectors/bevdet_occ.py) -> occkit ``FlashOcc``.
_FLASHOCC_RULES: list[Rule] = [
    *_resnet("img_backbone.", "image_encoder.backbone."),
    # CustomFPN: ConvModules without norm (conv with bias); one output conv, fpn_convs.0, on the finest level.
    _rule(r"img_neck\.lateral_convs\.(\d+)\.conv\.(weight|bias)", r"image_encoder.neck.lateral.\1.\2"),
    _rule(r"img_neck\.fpn_convs\.0\.conv\.(weight|bias)", r"image_encoder.neck.output.\1"),
    # LSSViewTransformer: one 1x1 conv, depth bins first, then context channels (occkit's order too).
    _rule(r"img_view_transformer\.depth_net\.(weight|bias)", r"view_transform.depth_net.\1"),
    *_bev_encoder("img_bev_encoder_backbone.", "img_bev_encoder_neck.", "bev_encoder.", BEV_YX),
    # BEVOCCHead2D: final_conv (ConvModule, conv with bias + ReLU) on (Y, X), then predicter Linear-Softplus-Linear.
    _rule(r"occ_head\.final_conv\.conv\.(weight|bias)", r"occupancy_head.conv.0.\1", BEV_YX),
    _rule(r"occ_head\.predicter\.(0|2)\.(weight|bias)", r"occupancy_head.predictor.\1.\2"),
]

_FLASHOCC_DROPS: list[Drop] = [
    _drop(r"pts_bbox_head\..+", "BEVDet's detection head (CenterHead): FlashOcc's occupancy model has none"),
]

#: DAOcc ``BEVFusion`` (mmdet3d/models/fusion_models/bevfusion.py and the modules its config names) -> ``DAOcc``.
_DAOCC_RULES: list[Rule] = [
    *_resnet("encoders.camera.backbone.", "image_encoder.backbone."),
    # GeneralizedLSSFPN: ConvModules with BN2d (conv without bias, "bn") -> conv_bn_relu Sequentials.
    _rule(r"encoders\.camera\.neck\.lateral_convs\.(\d+)\.conv\.weight", r"image_encoder.neck.lateral.\1.0.weight"),
    _rule(rf"encoders\.camera\.neck\.lateral_convs\.(\d+)\.bn\.{_BN}", r"image_encoder.neck.lateral.\1.1.\2"),
    _rule(r"encoders\.camera\.neck\.fpn_convs\.(\d+)\.conv\.weight", r"image_encoder.neck.output.\1.0.weight"),
    _rule(rf"encoders\.camera\.neck\.fpn_convs\.(\d+)\.bn\.{_BN}", r"image_encoder.neck.output.\1.1.\2"),
    # BEVTransformV2: the 1x1 transfer_conv before sampling; its (X, Y) output with channel z * C + c is occkit's.
    _rule(r"encoders\.camera\.vtransform\.transfer_conv\.(weight|bias)", r"view_transform.reduce.\1"),
    # SparseEncoder: occkit's LidarEncoder.encoder keeps its module names (conv_input, encoder_layers, conv_out).
    _rule(r"encoders\.lidar\.backbone\.(.+)", r"lidar_encoder.encoder.\1", SPARSE),
    # ConvFuser is an nn.Sequential(conv, BN, ReLU); occkit's ConvFuser holds the same as `mix`.
    _rule(r"fuser\.0\.weight", "fuser.mix.0.weight"),
    _rule(rf"fuser\.1\.{_BN}", r"fuser.mix.1.\1"),
    *_bev_encoder("decoder.backbone.", "decoder.neck.", "bev_encoder.", SAME),
    # BEVOCCHead2D: CrossCoordinateSample's 1x1 transfer_conv is occkit's RangeExtension.reduce; final_conv runs on
    # the (Y, X) map the head swaps to.
    _rule(r"heads\.occ\.coordinate_transform\.transfer_conv\.(weight|bias)", r"range_extension.reduce.\1"),
    _rule(r"heads\.occ\.final_conv\.conv\.(weight|bias)", r"occupancy_head.conv.0.\1", BEV_YX),
    _rule(r"heads\.occ\.predicter\.(0|2)\.(weight|bias)", r"occupancy_head.predictor.\1.\2"),
    *_center_head("heads.object.", "detection_head."),
]

_DAOCC_DROPS: list[Drop] = [
    _drop(r"encoders\.camera\.vtransform\.ref_3d",
          "BEVTransformV2's voxel-centre buffer, a function of the config (occkit computes it, unsaved)"),
    _drop(r"heads\.occ\.coordinate_transform\.ref_points",
          "CrossCoordinateSample's column-centre buffer, a function of the config (occkit computes it, unsaved)"),
]  # fmt: skip

#: Per source: its rules, its drops, and occkit prefixes whose tensors the target model may lack on purpose.
_TABLES: dict[str, tuple[list[Rule], list[Drop], dict[str, str]]] = {
    "flashocc": (_FLASHOCC_RULES, _FLASHOCC_DROPS, {}),
    "daocc": (_DAOCC_RULES, _DAOCC_DROPS,
              {"detection_head.": "the auxiliary detection head (heads.object, training only): this model has none"}),
    "occkit": ([_rule(r"(.+)", r"\1")], [], {}),
}  # fmt: skip

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
    arch = zoo.ARCHITECTURES.get(architecture) if architecture is not None else None
    return sorted(arch.presets) if arch is not None else []


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
    reference_state = _strip_wrappers(reference_state)
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
        if conversion.shape_mismatches else []
    hint = f" (the checkpoint fits {', '.join(fits)})" if fits else ""
    return ConfigError(f"{conversion.source_description} checkpoint does not convert to {conversion.target}{hint}: "
                       f"{conversion.problems()}")


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


# ----------------------------------------------------------------------------------------------------- files
@dataclass
class ReferenceCheckpoint:
    """The tensors of a checkpoint file and what else it held."""

    path: Path
    state: dict[str, Tensor]
    """The model's state dict, ``module.`` prefixes stripped."""
    ignored: dict[str, str]
    """Top-level entries besides the weights (mmcv's ``meta``, ``optimizer``, ...) -> what they are."""
    metadata: dict[str, str]
    """A ``.safetensors`` file's metadata (empty otherwise)."""
    occkit: bool
    """An occkit checkpoint or converted weights (occkit's names)."""
    architecture: str | None = None
    """The architecture an occkit file says its weights are of (None: not said)."""


#: What the top-level entries of mmcv / occkit checkpoints besides the weights hold.
_TOP_LEVEL = {
    "meta": "mmcv run metadata: config text, versions, epoch",
    "optimizer": "optimizer state, for training only",
    "updates": "EMA update count, for training only",
    "epoch": "epoch counter",
    "iter": "iteration counter",
    "lr_scheduler": "scheduler state, for training only",
    "scaler": "mixed-precision loss scale, for training only",
}

def _strip_wrappers(state: Mapping[str, Any]) -> dict[str, Any]:
    """Keys without DistributedDataParallel's ``module.`` prefix."""
    return {key.removeprefix("module."): value for key, value in state.items()}


def _tensor_dict(state: Any, path: Path, what: str) -> dict[str, Tensor]:
    if not isinstance(state, Mapping) or not state:
        raise ValueError(f"{path}: {what} is not a non-empty dict of tensors")
    wrong = [key for key, value in state.items() if not isinstance(value, Tensor)]
    if wrong:
        raise ValueError(f"{path}: {what} holds non-tensor entries ({', '.join(map(str, wrong[:4]))})")
    return _strip_wrappers(state)


def read_checkpoint(path: str | Path) -> ReferenceCheckpoint:
    """The state dict of a checkpoint file, read without unpickling code.

    Reads ``.safetensors`` files, occkit checkpoints (their EMA weights when they have them), mmcv checkpoints
    (``{'meta', 'state_dict', 'optimizer'}``, the EMA hook's ``epoch_N_ema.pth`` too) and bare state dicts. Weights
    that are NaN or infinite are refused (:func:`~occkit.weight_files.check_finite`): converted or loaded, they
    would score an mIoU of 0 without any error.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file cannot be read safely, holds no state dict, or weights that are not finite (the message
            names the file and why).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    checkpoint = _read_state(path)
    check_finite(checkpoint.state, path)
    return checkpoint


def _read_state(path: Path) -> ReferenceCheckpoint:
    """:func:`read_checkpoint` without its checks of the values."""
    if path.suffix == ".safetensors":
        state, metadata = read_safetensors(path)
        return ReferenceCheckpoint(path, state, {}, metadata, occkit=metadata.get("format") == WEIGHTS_FORMAT,
                                   architecture=metadata.get("architecture"))
    payload = load_torch_file(path)
    if isinstance(payload, Mapping) and str(payload.get("format", "")).startswith(_CHECKPOINT_FORMAT_PREFIX):
        key = "ema" if payload.get("ema") is not None else "model"
        ignored = {k: "occkit run state" for k in payload if k != key}
        return ReferenceCheckpoint(path, _tensor_dict(payload[key], path, f"its '{key}'"), ignored, {}, occkit=True,
                                   architecture=payload.get("architecture"))
    if isinstance(payload, Mapping):
        for key in ("state_dict", "model"):
            if isinstance(payload.get(key), Mapping):
                ignored = {k: _TOP_LEVEL.get(k, "not model weights") for k in payload if k != key}
                state = _tensor_dict(payload[key], path, f"its '{key}'")
                return ReferenceCheckpoint(path, state, ignored, {}, occkit=False)
        if payload and all(isinstance(v, Tensor) for v in payload.values()):
            return ReferenceCheckpoint(path, _tensor_dict(payload, path, "the file"), {}, {}, occkit=False)
        top = ", ".join(map(str, list(payload)[:6]))
        raise ValueError(f"{path} holds no state dict (top-level keys: {top}; expected 'state_dict' or tensors)")
    raise ValueError(f"{path} holds a {type(payload).__name__}, not a checkpoint dict")


def _check_architecture(checkpoint: ReferenceCheckpoint, architecture: str, target: str) -> None:
    """Refuse an occkit file whose weights are of another architecture than ``target``'s."""
    if checkpoint.architecture is not None and checkpoint.architecture != architecture:
        entry = checkpoint.metadata.get("entry")
        held = f"{entry} ({checkpoint.architecture})" if entry else f"a {checkpoint.architecture} model"
        raise ConfigError(f"{checkpoint.path} holds the weights of {held}, but {target} is a {architecture} model")


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


def _architecture_of(model: nn.Module) -> str:
    for name, arch in zoo.ARCHITECTURES.items():
        if isinstance(model, arch.model):
            return name
    raise ConfigError(f"{type(model).__name__} is not a model of the zoo's architectures")


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
