"""DAOcc checkpoints -> occkit's ``daocc`` architecture.

DAOcc's ``BEVFusion`` (AlphaPlusTT/DAOcc): ``encoders.camera.{backbone,neck,vtransform}``, ``encoders.lidar.backbone``
(mmdet3d's ``SparseEncoder``; its spconv 1.x kernels are permuted, :mod:`occkit.convert.rules`), ``fuser``,
``decoder.{backbone,neck}``, ``heads.object`` (``CenterHead``) and ``heads.occ`` (``BEVOCCHead2D`` with its
``CrossCoordinateSample``; its ``final_conv`` runs on the ``(Y, X)`` map the head swaps to: kernel transposed).
"""

from __future__ import annotations

from occkit.convert.mmdet_modules import _bev_encoder, _center_head, _resnet
from occkit.convert.rules import _BN, BEV_YX, SAME, SPARSE, Drop, Rule, Source, _drop, _rule

SOURCE = Source("daocc", "DAOcc (BEVFusion-style)", "daocc",
                ("encoders.camera.", "encoders.lidar.", "fuser.0.", "fuser.1.", "decoder.backbone.", "decoder.neck.",
                 "heads.occ.", "heads.object."), "daocc")  # fmt: skip

#: DAOcc ``BEVFusion`` (mmdet3d/models/fusion_models/bevfusion.py and the modules its config names) -> ``DAOcc``.
RULES: list[Rule] = [
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

DROPS: list[Drop] = [
    _drop(r"encoders\.camera\.vtransform\.ref_3d",
          "BEVTransformV2's voxel-centre buffer, a function of the config (occkit computes it, unsaved)"),
    _drop(r"heads\.occ\.coordinate_transform\.ref_points",
          "CrossCoordinateSample's column-centre buffer, a function of the config (occkit computes it, unsaved)"),
]  # fmt: skip

#: occkit prefixes a target model may lack on purpose -> why; the reference keys that map there are dropped so.
OPTIONAL = {"detection_head.": "the auxiliary detection head (heads.object, training only): this model has none"}
