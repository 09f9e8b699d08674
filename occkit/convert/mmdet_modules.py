"""Rename rules of the mmdet / mmdet3d modules both references are built of: ResNet, BEVDet's BEV encoder
(``CustomResNet`` and ``FPN_LSS``) and mmdet3d's ``CenterHead``; each returns the rules for one instance of the
module, under the reference's prefix and occkit's."""

from __future__ import annotations

import re

from occkit.convert.rules import _BN, Rule, _rule


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
