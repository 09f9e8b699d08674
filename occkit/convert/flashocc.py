"""FlashOcc / BEVDet checkpoints -> occkit's ``flashocc`` architecture.

FlashOcc's ``BEVDetOCC`` (Yzichen/FlashOCC, an mmdet3d 1.0 plugin), and BEVDet's detection model
(``bevdet-r50-cbgs.pth``, which FlashOcc's configs start from with ``load_from``): ``img_backbone`` (mmdet's ResNet,
torchvision's parameter names), ``img_neck`` (``CustomFPN``), ``img_view_transformer.depth_net``,
``img_bev_encoder_backbone`` (``CustomResNet``), ``img_bev_encoder_neck`` (``FPN_LSS``), ``occ_head``
(``BEVOCCHead2D``), and in BEVDet's file ``pts_bbox_head`` (a ``CenterHead`` the occupancy model does not have).
The BEV encoder and the occupancy head run on ``(Y, X)`` maps: their kernels are transposed
(:mod:`occkit.convert.rules`).
"""

from __future__ import annotations

from occkit.convert.mmdet_modules import _bev_encoder, _resnet
from occkit.convert.rules import BEV_YX, Drop, Rule, Source, _drop, _rule

SOURCE = Source("flashocc", "FlashOcc / BEVDet (mmdet3d BEVDetOCC)", "flashocc",
                ("img_backbone.", "img_neck.", "img_view_transformer.", "img_bev_encoder_backbone.",
                 "img_bev_encoder_neck.", "occ_head.", "pts_bbox_head."), "flashocc_m0")  # fmt: skip

#: FlashOcc ``BEVDetOCC`` (projects/mmdet3d_plugin/models/detectors/bevdet_occ.py) -> occkit ``FlashOcc``.
RULES: list[Rule] = [
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

DROPS: list[Drop] = [
    _drop(r"pts_bbox_head\..+", "BEVDet's detection head (CenterHead): FlashOcc's occupancy model has none"),
]
