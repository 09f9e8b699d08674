"""``occkit convert``: official FlashOcc / BEVDet and DAOcc state dicts onto occkit's models.

The reference state dicts below are built key by key from the reference code, with random tensors of the shapes
those modules create; no reference code runs. Where each name comes from:

FlashOcc (Yzichen/FlashOCC, model ``BEVDetOCC``, configs ``projects/configs/flashocc/flashocc-r50-M0.py`` for M0 and
``flashocc-r50.py`` for M1; modules under ``projects/mmdet3d_plugin/models``):

* ``img_backbone``: mmdet's ``ResNet`` (depth 50, all four stages built whatever ``out_indices``): ``conv1``,
  ``bn1``, ``layerN.M.{conv1,bn1,conv2,bn2,conv3,bn3}``, ``layerN.0.downsample.{0,1}`` (torchvision's names);
* ``img_neck``: ``necks/fpn.py`` ``CustomFPN`` (in [1024, 2048], out 256, ``out_ids=[0]``): ConvModules without
  norm, so ``lateral_convs.I.conv.{weight,bias}`` and one ``fpn_convs.0.conv``;
* ``img_view_transformer``: ``necks/view_transformer.py`` ``LSSViewTransformer``: ``depth_net`` =
  ``Conv2d(256, D + 64, 1)``, D = the depth bins of ``grid_config['depth']`` (M0: [1, 45, 1] -> 44; M1: 0.5 m -> 88);
  its frustum and grid are plain attributes, not buffers;
* ``img_bev_encoder_backbone``: ``backbones/resnet.py`` ``CustomResNet`` (64 in, [128, 256, 512], strides 2, 2, 2,
  two mmdet ``BasicBlock`` per stage): ``layers.I.J.{conv1,bn1,conv2,bn2}``, ``layers.I.0.downsample`` a plain
  ``Conv2d(3, stride, 1)`` with bias;
* ``img_bev_encoder_neck``: ``necks/lss_fpn.py`` ``FPN_LSS`` (in 640, M0 out 128, ``extra_upsample=2``):
  ``conv.{0,1,3,4}`` (conv3x3, BN, ReLU, conv3x3, BN, ReLU at twice the output width), ``up2.{1,2,4}`` (Upsample,
  conv3x3, BN, ReLU, conv1x1 with bias);
* ``occ_head``: ``dense_heads/bev_occ_head.py`` ``BEVOCCHead2D`` (M0 in 128, out 128, Dz 16, 18 classes):
  ``final_conv.conv`` (ConvModule with bias, no norm), ``predicter.{0,2}`` (Linear 128 -> 256 -> 16 x 18).

BEVDet's detection model ``bevdet-r50-cbgs`` (what FlashOcc's configs ``load_from``; HuangJunJie2017/BEVDet,
``configs/bevdet/bevdet-r50-cbgs.py``) has the same modules with other sizes: ``grid_config['depth']`` [1, 60, 1],
so 59 depth bins and a ``depth_net`` of 59 + 64 = 123 outputs; its FPN_LSS outputs 256 (as FlashOcc's M1); and
``pts_bbox_head``, mmdet3d's ``CenterHead`` (``mmdet3d/models/dense_heads/centerpoint_head.py``) with one task of
all ten classes: ``shared_conv.{conv,bn}`` and per task ``task_heads.T.<head>.0`` a ConvModule (``conv``, ``bn``)
and ``<head>.1`` the output conv, common heads as DAOcc's below.

DAOcc (AlphaPlusTT/DAOcc, config ``configs/nuscenes/occ3d/daocc_occ3d_nus_w_mask.yaml``, model ``BEVFusion`` in
``mmdet3d/models/fusion_models/bevfusion.py``):

* ``encoders.camera.backbone``: mmdet ``ResNet`` 50, as above;
* ``encoders.camera.neck``: ``necks/generalized_lss.py`` ``GeneralizedLSSFPN`` (in [512, 1024, 2048], out 256, BN2d):
  ``lateral_convs.I`` and ``fpn_convs.I`` for I = 0, 1, ConvModules ``conv`` (no bias) + ``bn``; lateral 0 takes
  512 + 256 channels, lateral 1 1024 + 2048;
* ``encoders.camera.vtransform``: ``vtransforms/bev_ss.py`` ``BEVTransformV2``: ``transfer_conv`` (1x1, 256 -> 128)
  and the registered buffer ``ref_3d`` (180 x 180 x 10 voxel centres, 3);
* ``encoders.lidar.backbone``: ``backbones/sparse_encoder.py`` ``SparseEncoder`` (block_type basicblock) built from
  ``mmdet3d/ops/sparse_block.py``: ``conv_input.{0,1}``, ``encoder_layers.encoder_layerN.J.{conv1,bn1,conv2,bn2}``
  (SparseBasicBlock = mmdet BasicBlock), ``encoder_layerN.2.{0,1}`` (stride-2 conv + BN1d), ``conv_out.{0,1}``
  (kernel (1, 1, 3)). Its spconv is the bundled ``mmdet3d/ops/spconv`` (spconv 1.x; docs/install.md installs no
  other), whose ``SparseConvolution.weight`` is ``(*kernel_size, in, out)``;
* ``fuser``: ``fusers/conv.py`` ``ConvFuser``, an ``nn.Sequential(conv3x3 1536 -> 512, BN, ReLU)``: ``fuser.{0,1}``;
* ``decoder.backbone`` / ``decoder.neck``: ``backbones/second.py`` ``CustomResNet`` (512 in, strides 1, 1, 2) and
  ``necks/second.py`` ``FPN_LSS`` (640 -> 512, ``extra_upsample: null``, so ``conv`` only);
* ``heads.object``: ``heads/bbox/centerpoint.py`` ``CenterHead`` (512 in, share 64, six tasks, common heads reg 2,
  height 1, dim 3, rot 2, vel 2, then heatmap);
* ``heads.occ``: ``heads/occ/bev_occ_head.py`` ``BEVOCCHead2D`` (128 -> 128) with ``coordinate_transform``,
  ``customs/cross_coordinate_sample.py`` ``CrossCoordinateSample``: ``transfer_conv`` (1x1, 512 -> 128) and the
  buffer ``ref_points`` (200 x 200 x 1 column centres, 3).

Every BatchNorm brings ``weight, bias, running_mean, running_var`` and an int64 ``num_batches_tracked``.
"""

from __future__ import annotations

import json
import zipfile
from collections import Counter

import pytest
import torch
import torch.nn.functional as F

from occkit import zoo
from occkit.cli import main
from occkit.config import ConfigError
from occkit.convert import (
    convert_checkpoint,
    convert_state_dict,
    detect_source,
    format_report,
    load_partial,
    load_weights,
    read_checkpoint,
    report_path,
)

# ----------------------------------------------------------------------------------------------------- builders
_GENERATOR = torch.Generator().manual_seed(0)


def _t(*shape: int) -> torch.Tensor:
    return torch.randn(*shape, generator=_GENERATOR)


def _w(*shape: int, out_axis: int = 0) -> torch.Tensor:
    """A conv / linear weight scaled by 1 / sqrt(fan-in), so that activations keep their size through the layers."""
    return _t(*shape) * (torch.Size(shape).numel() / shape[out_axis]) ** -0.5


def _bn(state: dict, prefix: str, channels: int) -> None:
    state[f"{prefix}.weight"] = _t(channels).abs() + 0.5
    state[f"{prefix}.bias"] = _t(channels)
    state[f"{prefix}.running_mean"] = _t(channels)
    state[f"{prefix}.running_var"] = _t(channels).abs() + 0.5
    state[f"{prefix}.num_batches_tracked"] = torch.tensor(1234, dtype=torch.int64)


def _resnet(state: dict, prefix: str, blocks=(3, 4, 6, 3), bottleneck: bool = True) -> None:
    """mmdet's ResNet (pytorch style): torchvision's parameter names."""
    state[f"{prefix}conv1.weight"] = _w(64, 3, 7, 7)
    _bn(state, f"{prefix}bn1", 64)
    expansion = 4 if bottleneck else 1
    inplanes = 64
    for stage, (count, planes) in enumerate(zip(blocks, (64, 128, 256, 512), strict=True), start=1):
        for j in range(count):
            block = f"{prefix}layer{stage}.{j}"
            if bottleneck:
                convs = [(planes, inplanes, 1), (planes, planes, 3), (planes * expansion, planes, 1)]
            else:
                convs = [(planes, inplanes, 3), (planes, planes, 3)]
            for index, (out, inp, k) in enumerate(convs, start=1):
                state[f"{block}.conv{index}.weight"] = _w(out, inp, k, k)
                _bn(state, f"{block}.bn{index}", out)
            if j == 0 and (stage > 1 or inplanes != planes * expansion):
                state[f"{block}.downsample.0.weight"] = _w(planes * expansion, inplanes, 1, 1)
                _bn(state, f"{block}.downsample.1", planes * expansion)
            inplanes = planes * expansion


def _custom_resnet(state: dict, prefix: str, numc_input: int, channels, strides, layers=(2, 2, 2)) -> None:
    """BEVDet's / DAOcc's CustomResNet of mmdet BasicBlocks; the first block's downsample is a strided conv3x3."""
    current = numc_input
    for i, (width, _stride, count) in enumerate(zip(channels, strides, layers, strict=True)):
        for j in range(count):
            block = f"{prefix}layers.{i}.{j}"
            state[f"{block}.conv1.weight"] = _w(width, current if j == 0 else width, 3, 3)
            _bn(state, f"{block}.bn1", width)
            state[f"{block}.conv2.weight"] = _w(width, width, 3, 3)
            _bn(state, f"{block}.bn2", width)
            if j == 0:
                state[f"{block}.downsample.weight"] = _w(width, current, 3, 3)
                state[f"{block}.downsample.bias"] = _t(width)
        current = width


def _fpn_lss(state: dict, prefix: str, in_channels: int, out_channels: int, extra_upsample: bool) -> None:
    mid = out_channels * (2 if extra_upsample else 1)
    state[f"{prefix}conv.0.weight"] = _w(mid, in_channels, 3, 3)
    _bn(state, f"{prefix}conv.1", mid)
    state[f"{prefix}conv.3.weight"] = _w(mid, mid, 3, 3)
    _bn(state, f"{prefix}conv.4", mid)
    if extra_upsample:
        state[f"{prefix}up2.1.weight"] = _w(out_channels, mid, 3, 3)
        _bn(state, f"{prefix}up2.2", out_channels)
        state[f"{prefix}up2.4.weight"] = _w(out_channels, out_channels, 1, 1)
        state[f"{prefix}up2.4.bias"] = _t(out_channels)


def _center_head(state: dict, prefix: str, in_channels: int, tasks: tuple[int, ...] = (1, 2, 2, 1, 2, 2)) -> None:
    """mmdet3d's CenterHead with the common heads of DAOcc and BEVDet; ``tasks``, the classes per task, are
    DAOcc's six by default (BEVDet's bevdet-r50-cbgs has one task of ten)."""
    state[f"{prefix}shared_conv.conv.weight"] = _w(64, in_channels, 3, 3)
    _bn(state, f"{prefix}shared_conv.bn", 64)
    for t, classes in enumerate(tasks):
        for head, out in (("reg", 2), ("height", 1), ("dim", 3), ("rot", 2), ("vel", 2), ("heatmap", classes)):
            branch = f"{prefix}task_heads.{t}.{head}"
            state[f"{branch}.0.conv.weight"] = _w(64, 64, 3, 3)
            _bn(state, f"{branch}.0.bn", 64)
            state[f"{branch}.1.weight"] = _w(out, 64, 3, 3)
            state[f"{branch}.1.bias"] = _t(out)


def flashocc_state(depth_bins: int = 44, bev_out: int = 128, occ_head: bool = True, tiny: bool = False) -> dict:
    """BEVDetOCC's state dict: M0 by default; ``depth_bins=88, bev_out=256`` is M1 (flashocc-r50.py); ``tiny``
    gives flashocc_tiny's sizes (ResNet-18 one block per stage, 64-channel FPN, 22 depth bins (2 m), 16 context
    channels, a narrow BEV encoder with a 32-channel FPN_LSS)."""
    state: dict = {}
    if tiny:
        depth_bins, bev_out = 22, 32
        _resnet(state, "img_backbone.", blocks=(1, 1, 1, 1), bottleneck=False)
        neck_in, neck, context, bev = (256, 512), 64, 16, (32, 64, 128)
    else:
        _resnet(state, "img_backbone.")
        neck_in, neck, context, bev = (1024, 2048), 256, 64, (128, 256, 512)
    for i, channels in enumerate(neck_in):
        state[f"img_neck.lateral_convs.{i}.conv.weight"] = _w(neck, channels, 1, 1)
        state[f"img_neck.lateral_convs.{i}.conv.bias"] = _t(neck)
    state["img_neck.fpn_convs.0.conv.weight"] = _w(neck, neck, 3, 3)
    state["img_neck.fpn_convs.0.conv.bias"] = _t(neck)
    state["img_view_transformer.depth_net.weight"] = _w(depth_bins + context, neck, 1, 1)
    state["img_view_transformer.depth_net.bias"] = _t(depth_bins + context)
    _custom_resnet(state, "img_bev_encoder_backbone.", context, bev, (2, 2, 2), (1, 1, 1) if tiny else (2, 2, 2))
    _fpn_lss(state, "img_bev_encoder_neck.", bev[0] + bev[2], bev_out, extra_upsample=True)
    if occ_head:
        state["occ_head.final_conv.conv.weight"] = _w(bev_out, bev_out, 3, 3)
        state["occ_head.final_conv.conv.bias"] = _t(bev_out)
        state["occ_head.predicter.0.weight"] = _w(2 * bev_out, bev_out)
        state["occ_head.predicter.0.bias"] = _t(2 * bev_out)
        state["occ_head.predicter.2.weight"] = _w(16 * 18, 2 * bev_out)
        state["occ_head.predicter.2.bias"] = _t(16 * 18)
    return state


def bevdet_detection_state() -> dict:
    """``bevdet-r50-cbgs``: FlashOcc's image and BEV modules with 59 depth bins and FPN_LSS to 256, a CenterHead of
    one ten-class task, no occ_head."""
    state = flashocc_state(depth_bins=59, bev_out=256, occ_head=False)
    _center_head(state, "pts_bbox_head.", 256, tasks=(10,))
    return state


def daocc_state() -> dict:
    """DAOcc's BEVFusion state dict for daocc_occ3d_nus_w_mask.yaml; sparse weights in spconv 1.x layout."""
    state: dict = {}
    _resnet(state, "encoders.camera.backbone.")
    neck = "encoders.camera.neck."
    for i, channels in enumerate((512 + 256, 1024 + 2048)):
        state[f"{neck}lateral_convs.{i}.conv.weight"] = _w(256, channels, 1, 1)
        _bn(state, f"{neck}lateral_convs.{i}.bn", 256)
        state[f"{neck}fpn_convs.{i}.conv.weight"] = _w(256, 256, 3, 3)
        _bn(state, f"{neck}fpn_convs.{i}.bn", 256)
    state["encoders.camera.vtransform.ref_3d"] = _t(180 * 180 * 10, 3)
    state["encoders.camera.vtransform.transfer_conv.weight"] = _w(128, 256, 1, 1)
    state["encoders.camera.vtransform.transfer_conv.bias"] = _t(128)
    lidar = "encoders.lidar.backbone."
    state[f"{lidar}conv_input.0.weight"] = _w(3, 3, 3, 5, 16, out_axis=-1)  # (*kernel, in, out)
    _bn(state, f"{lidar}conv_input.1", 16)
    channels = 16
    for n, stage in enumerate(((16, 16, 32), (32, 32, 64), (64, 64, 128), (128, 128)), start=1):
        for j, out in enumerate(stage):
            block = f"{lidar}encoder_layers.encoder_layer{n}.{j}"
            if j == len(stage) - 1 and n != 4:
                state[f"{block}.0.weight"] = _w(3, 3, 3, channels, out, out_axis=-1)
                _bn(state, f"{block}.1", out)
            else:
                for conv in (1, 2):
                    state[f"{block}.conv{conv}.weight"] = _w(3, 3, 3, out, out, out_axis=-1)
                    _bn(state, f"{block}.bn{conv}", out)
            channels = out
    state[f"{lidar}conv_out.0.weight"] = _w(1, 1, 3, 128, 128, out_axis=-1)
    _bn(state, f"{lidar}conv_out.1", 128)
    state["fuser.0.weight"] = _w(512, 1280 + 256, 3, 3)
    _bn(state, "fuser.1", 512)
    _custom_resnet(state, "decoder.backbone.", 512, (128, 256, 512), (1, 1, 2))
    _fpn_lss(state, "decoder.neck.", 640, 512, extra_upsample=False)
    _center_head(state, "heads.object.", 512)
    state["heads.occ.final_conv.conv.weight"] = _w(128, 128, 3, 3)
    state["heads.occ.final_conv.conv.bias"] = _t(128)
    state["heads.occ.predicter.0.weight"] = _w(256, 128)
    state["heads.occ.predicter.0.bias"] = _t(256)
    state["heads.occ.predicter.2.weight"] = _w(16 * 18, 256)
    state["heads.occ.predicter.2.bias"] = _t(16 * 18)
    state["heads.occ.coordinate_transform.ref_points"] = _t(200 * 200 * 1, 3)
    state["heads.occ.coordinate_transform.transfer_conv.weight"] = _w(128, 512, 1, 1)
    state["heads.occ.coordinate_transform.transfer_conv.bias"] = _t(128)
    return state


@pytest.fixture(scope="module")
def flashocc_m0():
    state = flashocc_state()
    return state, convert_state_dict(state, "flashocc_m0")


@pytest.fixture(scope="module")
def daocc():
    state = daocc_state()
    return state, convert_state_dict(state, "daocc")


# ----------------------------------------------------------------------------------------------------- strict
def test_flashocc_m0_converts_completely_and_loads_strictly(flashocc_m0):
    state, conversion = flashocc_m0
    model = zoo.build("flashocc_m0")
    assert conversion.complete and not conversion.unmapped and not conversion.missing
    assert len(conversion.mapped) == len(state) == len(model.state_dict()) and not conversion.dropped
    model.load_state_dict(conversion.state, strict=True)
    # The 3x3 convs that run on (Y, X) maps in the reference: 15 of CustomResNet (3 stages x (conv1, conv2,
    # downsample + conv1, conv2)), 3 of FPN_LSS (conv.0, conv.3, up2.1) and the occupancy head's final_conv.
    assert len(conversion.transforms) == 19


def test_flashocc_tensors_land_in_place(flashocc_m0):
    state, conversion = flashocc_m0
    out = conversion.state
    same = {
        "img_backbone.conv1.weight": "image_encoder.backbone.stem.0.weight",
        "img_backbone.bn1.running_var": "image_encoder.backbone.stem.1.running_var",
        "img_backbone.layer3.5.conv2.weight": "image_encoder.backbone.stages.2.5.conv2.weight",
        "img_backbone.layer4.0.downsample.1.num_batches_tracked":
            "image_encoder.backbone.stages.3.0.downsample.1.num_batches_tracked",
        "img_neck.lateral_convs.1.conv.weight": "image_encoder.neck.lateral.1.weight",
        "img_neck.fpn_convs.0.conv.weight": "image_encoder.neck.output.weight",
        "img_view_transformer.depth_net.bias": "view_transform.depth_net.bias",
        "img_bev_encoder_neck.up2.2.running_mean": "bev_encoder.neck.project.0.1.running_mean",
        "occ_head.predicter.2.weight": "occupancy_head.predictor.2.weight",
    }  # fmt: skip
    for reference, occkit in same.items():
        assert conversion.mapped[reference] == occkit
        assert torch.equal(out[occkit], state[reference]), reference
    # The BEV runs as (Y, X) in BEVDet and (X, Y) in occkit: its 3x3 kernels are transposed.
    transposed = {
        "img_bev_encoder_backbone.layers.1.0.conv1.weight": "bev_encoder.backbone.stages.1.0.conv1.weight",
        "img_bev_encoder_backbone.layers.2.0.downsample.weight": "bev_encoder.backbone.stages.2.0.downsample.weight",
        "img_bev_encoder_neck.conv.3.weight": "bev_encoder.neck.fuse.1.0.weight",
        "occ_head.final_conv.conv.weight": "occupancy_head.conv.0.weight",
    }  # fmt: skip
    for reference, occkit in transposed.items():
        assert torch.equal(out[occkit], state[reference].transpose(-1, -2)), reference
        assert not torch.equal(out[occkit], state[reference])
    assert torch.equal(out["bev_encoder.neck.project.1.weight"], state["img_bev_encoder_neck.up2.4.weight"])


def test_flashocc_bev_encoder_and_head_compute_the_reference_function(flashocc_m0):
    """The converted BEV encoder + head on the (X, Y) map equal the reference's computation on the (Y, X) map."""
    state, conversion = flashocc_m0
    model = zoo.build("flashocc_m0").eval()
    model.load_state_dict(conversion.state)
    # The reference's BEV encoder: occkit's module with the reference's tensors as they are, fed (Y, X) maps (the
    # same operator sequence: CustomResNet's BasicBlocks and FPN_LSS; the key table pairs them module for module).
    reference_encoder = zoo.build("flashocc_m0").eval().bev_encoder
    untransposed = {name[len("bev_encoder."):]: state[ref] for ref, name in conversion.mapped.items()
                    if name.startswith("bev_encoder.")}  # fmt: skip
    reference_encoder.load_state_dict(untransposed)
    bev_yx = torch.randn(1, 64, 16, 24, generator=_GENERATOR)  # a non-square map keeps the axes apart
    with torch.no_grad():
        features_yx = reference_encoder(bev_yx)  # (1, 128, Y, X)
        features_xy = model.bev_encoder(bev_yx.transpose(-1, -2))  # (1, 128, X, Y)
        torch.testing.assert_close(features_xy, features_yx.transpose(-1, -2), rtol=1e-4, atol=1e-4)
        # BEVOCCHead2D.forward: final_conv (conv + ReLU) on (Y, X), permute to (B, X, Y, C), predicter, view.
        hidden = F.relu(F.conv2d(features_yx, state["occ_head.final_conv.conv.weight"],
                                 state["occ_head.final_conv.conv.bias"], padding=1)).permute(0, 3, 2, 1)
        hidden = F.softplus(F.linear(hidden, state["occ_head.predicter.0.weight"], state["occ_head.predicter.0.bias"]))
        logits = F.linear(hidden, state["occ_head.predicter.2.weight"], state["occ_head.predicter.2.bias"])
        reference = logits.view(1, 24, 16, 16, 18)  # (B, Dx, Dy, Dz, classes)
        ours = model.occupancy_head(features_xy)  # (B, classes, X, Y, Z)
    torch.testing.assert_close(ours.permute(0, 2, 3, 4, 1), reference, rtol=1e-4, atol=1e-4)


def test_flashocc_m1_checkpoints_convert_for_flashocc_m1_only():
    state = flashocc_state(depth_bins=88, bev_out=256)
    model = zoo.build("flashocc_m1")
    model.load_state_dict(convert_state_dict(state, "flashocc_m1").state, strict=True)
    with pytest.raises(ConfigError) as info:
        convert_state_dict(state, "flashocc_m0")
    message = str(info.value)
    assert "fits flashocc_m1" in message and "img_view_transformer.depth_net.weight (152, 256, 1, 1)" in message


def test_daocc_converts_completely_and_loads_strictly(daocc):
    state, conversion = daocc
    model = zoo.build("daocc")
    assert conversion.complete and not conversion.unmapped and not conversion.missing
    assert conversion.dropped == {
        "encoders.camera.vtransform.ref_3d":
            "BEVTransformV2's voxel-centre buffer, a function of the config (occkit computes it, unsaved)",
        "heads.occ.coordinate_transform.ref_points":
            "CrossCoordinateSample's column-centre buffer, a function of the config (occkit computes it, unsaved)",
    }  # fmt: skip
    assert len(conversion.mapped) == len(state) - 2 == len(model.state_dict())
    model.load_state_dict(conversion.state, strict=True)
    # 21 sparse convolution weights permuted (conv_input, 3 x (4 in basic blocks + 1 strided), 4 in the last stage,
    # conv_out), one occupancy-head kernel transposed.
    changes = Counter(conversion.transforms.values())
    assert sorted(changes.values()) == [1, 21] and any("from spconv 1.x" in change for change in changes)
    assert not conversion.notes


def test_daocc_tensors_land_in_place(daocc):
    state, conversion = daocc
    out = conversion.state
    same = {
        "encoders.camera.backbone.layer2.3.bn3.weight": "image_encoder.backbone.stages.1.3.bn3.weight",
        "encoders.camera.neck.lateral_convs.1.conv.weight": "image_encoder.neck.lateral.1.0.weight",
        "encoders.camera.neck.fpn_convs.0.bn.running_mean": "image_encoder.neck.output.0.1.running_mean",
        "encoders.camera.vtransform.transfer_conv.weight": "view_transform.reduce.weight",
        "encoders.lidar.backbone.encoder_layers.encoder_layer3.1.bn2.bias":
            "lidar_encoder.encoder.encoder_layers.encoder_layer3.1.bn2.bias",
        "fuser.0.weight": "fuser.mix.0.weight",
        "fuser.1.running_var": "fuser.mix.1.running_var",
        # BEVFusion's fuser, decoder and CenterHead run on (X, Y) maps, as occkit's: kernels as they are.
        "decoder.backbone.layers.2.0.downsample.weight": "bev_encoder.backbone.stages.2.0.downsample.weight",
        "decoder.neck.conv.4.num_batches_tracked": "bev_encoder.neck.fuse.1.1.num_batches_tracked",
        "heads.object.shared_conv.conv.weight": "detection_head.shared_conv.0.weight",
        "heads.object.task_heads.0.heatmap.0.bn.running_var":
            "detection_head.task_heads.0.branches.heatmap.1.running_var",
        "heads.object.task_heads.4.vel.0.conv.weight": "detection_head.task_heads.4.branches.vel.0.weight",
        "heads.object.task_heads.5.heatmap.1.weight": "detection_head.task_heads.5.branches.heatmap.3.weight",
        "heads.occ.coordinate_transform.transfer_conv.bias": "range_extension.reduce.bias",
        "heads.occ.predicter.0.weight": "occupancy_head.predictor.0.weight",
    }  # fmt: skip
    for reference, occkit in same.items():
        assert conversion.mapped[reference] == occkit
        assert torch.equal(out[occkit], state[reference]), reference
    # spconv 1.x (kx, ky, kz, in, out) -> spconv 2.x (out, kx, ky, kz, in).
    for reference, occkit in {
        "encoders.lidar.backbone.conv_input.0.weight": "lidar_encoder.encoder.conv_input.0.weight",
        "encoders.lidar.backbone.encoder_layers.encoder_layer2.2.0.weight":
            "lidar_encoder.encoder.encoder_layers.encoder_layer2.2.0.weight",
        "encoders.lidar.backbone.conv_out.0.weight": "lidar_encoder.encoder.conv_out.0.weight",
    }.items():  # fmt: skip
        assert torch.equal(out[occkit], state[reference].permute(4, 0, 1, 2, 3)), reference
    assert tuple(out["lidar_encoder.encoder.conv_out.0.weight"].shape) == (128, 1, 1, 3, 128)
    # BEVOCCHead2D swaps its input to (Y, X) before final_conv.
    assert torch.equal(out["occupancy_head.conv.0.weight"], state["heads.occ.final_conv.conv.weight"].transpose(-1, -2))


def _dense_sites(shape: tuple[int, int, int]) -> torch.Tensor:
    grid = torch.stack(torch.meshgrid(*(torch.arange(n) for n in shape), indexing="ij"), dim=-1).reshape(-1, 3)
    return torch.cat([torch.zeros(len(grid), 1, dtype=torch.long), grid], dim=1)  # (V, 4) (batch, x, y, z)


@pytest.mark.parametrize(
    ("reference_key", "occkit_key", "shape", "stride", "padding"),
    [
        ("encoders.lidar.backbone.conv_input.0.weight", "lidar_encoder.encoder.conv_input.0.weight", (4, 5, 6), 1, 1),
        ("encoders.lidar.backbone.conv_out.0.weight", "lidar_encoder.encoder.conv_out.0.weight", (2, 3, 7),
         (1, 1, 2), 0),
    ],
)  # fmt: skip
def test_converted_sparse_weights_compute_spconv_1x_convolutions(daocc, reference_key, occkit_key, shape, stride,
                                                                  padding):  # fmt: skip
    """With every site active a sparse conv is a dense one. spconv 1.x computes
    ``out[p, o] = sum_k,i W[k, i, o] x[p * stride - padding + k, i]``, a ``conv3d`` with ``W.permute(4, 3, 0, 1, 2)``;
    occkit's spconv 2.x layers with the converted weights must compute the same (the asymmetric (1, 1, 3) conv_out
    pins the kernel's axis order)."""
    from occkit.models.sparse import SparseConv3d, SubMConv3d, sparse_tensor_from_voxels

    state, conversion = daocc
    weight = conversion.state[occkit_key]
    out_channels, *kernel, in_channels = weight.shape
    if stride == 1:
        conv = SubMConv3d(in_channels, out_channels, tuple(kernel), padding=padding, bias=False)
    else:
        conv = SparseConv3d(in_channels, out_channels, tuple(kernel), stride=stride, padding=padding, bias=False)
    with torch.no_grad():
        conv.weight.copy_(weight)
        dense = torch.randn(1, in_channels, *shape, generator=_GENERATOR)
        coords = _dense_sites(shape)
        features = dense[0].permute(1, 2, 3, 0).reshape(-1, in_channels)
        ours = conv(sparse_tensor_from_voxels(features, coords, shape, 1)).dense()
        reference = F.conv3d(dense, state[reference_key].permute(4, 3, 0, 1, 2), stride=stride, padding=padding)
    torch.testing.assert_close(ours, reference, rtol=1e-4, atol=1e-4)


def test_sparse_weights_already_in_spconv_2x_layout_are_kept(daocc):
    state, _ = daocc
    resaved = {k: (v.permute(4, 0, 1, 2, 3).contiguous() if k.startswith("encoders.lidar.") and v.ndim == 5 else v)
               for k, v in state.items()}  # fmt: skip
    conversion = convert_state_dict(resaved, "daocc")
    key = "encoders.lidar.backbone.encoder_layers.encoder_layer1.0.conv1.weight"
    assert torch.equal(conversion.state["lidar_encoder.encoder.encoder_layers.encoder_layer1.0.conv1.weight"],
                       resaved[key])  # fmt: skip
    assert any("already in spconv 2.x's layout" in note for note in conversion.notes)
    assert not any("spconv" in change for change in conversion.transforms.values())


def test_detection_keys_are_dropped_for_an_entry_without_the_detection_head(daocc):
    state, _ = daocc
    entry = "daocc_no_detection" if "daocc_no_detection" in zoo.names() else None
    if entry is None:
        pytest.skip("the zoo has no DAOcc entry without a detection head")
    conversion = convert_state_dict(state, entry)
    head = [k for k in state if k.startswith("heads.object.")]
    assert all("auxiliary detection head" in conversion.dropped[k] for k in head)
    zoo.build(entry).load_state_dict(conversion.state, strict=True)


# ----------------------------------------------------------------------------------------------------- refusals
def test_a_checkpoint_of_the_other_model_is_refused(flashocc_m0, daocc):
    with pytest.raises(ConfigError, match=r"DAOcc \(BEVFusion-style\) checkpoint, but flashocc_m0 is a flashocc"):
        convert_state_dict(daocc[0], "flashocc_m0")
    with pytest.raises(ConfigError, match=r"FlashOcc / BEVDet .* checkpoint, but daocc is a daocc model"):
        convert_state_dict(flashocc_m0[0], "daocc")
    with pytest.raises(ConfigError, match="not convert|but daocc_tiny"):  # same architecture, other sizes
        convert_state_dict(daocc[0], "daocc_tiny")


def test_missing_extra_and_misshapen_keys_are_named(flashocc_m0):
    state = dict(flashocc_m0[0])
    del state["occ_head.predicter.2.bias"]
    with pytest.raises(ConfigError, match=r"left unfilled: occupancy_head\.predictor\.2\.bias"):
        convert_state_dict(state, "flashocc_m0")
    state = dict(flashocc_m0[0], **{"img_neck.fpn_convs.1.conv.weight": torch.zeros(1)})
    with pytest.raises(ConfigError, match=r"img_neck\.fpn_convs\.1\.conv\.weight \(no rule maps it\)"):
        convert_state_dict(state, "flashocc_m0")
    state = dict(flashocc_m0[0], **{"occ_head.predicter.0.weight": torch.zeros(256, 64)})
    with pytest.raises(ConfigError, match=r"occ_head\.predicter\.0\.weight \(256, 64\) -> "
                                          r"occupancy_head\.predictor\.0\.weight needs \(256, 128\)"):
        convert_state_dict(state, "flashocc_m0")
    with pytest.raises(ConfigError, match=r"neither .* \(keys: backbone\.conv1\.weight\)"):
        detect_source(["backbone.conv1.weight"])


def test_non_strict_returns_the_part_of_bevdets_detection_checkpoint_that_fits():
    state = bevdet_detection_state()
    assert detect_source(list(state)).kind == "flashocc"
    with pytest.raises(ConfigError):
        convert_state_dict(state, "flashocc_m0")
    conversion = convert_state_dict(state, "flashocc_m0", strict=False)
    assert not conversion.complete
    head = [k for k in state if k.startswith("pts_bbox_head.")]
    # shared_conv (conv + 5 BatchNorm tensors), then 1 task x 6 heads x (conv + 5 BatchNorm + output weight, bias).
    assert len(head) == 6 + 1 * 6 * 8 and all(conversion.dropped[k].startswith("BEVDet's detection head") for k in head)
    assert "BEVDet detection" in conversion.source_description
    # BEVDet's depth net (59 bins: 123 outputs) and FPN_LSS (256 out) do not fit M0; the image and BEV backbones do.
    mismatched = {m.reference_key for m in conversion.shape_mismatches}
    assert "img_view_transformer.depth_net.weight" in mismatched and "img_bev_encoder_neck.up2.1.weight" in mismatched
    assert "image_encoder.backbone.stages.3.2.conv3.weight" in conversion.state
    assert "bev_encoder.backbone.stages.2.1.conv2.weight" in conversion.state
    assert len(conversion.state) == 405  # docs/reproducing.md
    # M1's BEV neck is BEVDet's width: only the depth net (88 bins against 59) and the heads stay out.
    m1 = convert_state_dict(state, "flashocc_m1", strict=False)
    assert {m.reference_key.rsplit(".", 2)[0] for m in m1.shape_mismatches} == {"img_view_transformer"}
    assert len(m1.state) == 422
    head_keys = {k for k in zoo.build("flashocc_m0").state_dict() if k.startswith("occupancy_head.")}
    assert set(conversion.missing) == head_keys
    report = conversion.report()
    assert report["counts"]["dropped"] == len(head) and not report["complete"]


def test_load_partial_starts_flashocc_from_bevdet(tmp_path):
    path = tmp_path / "bevdet-r50-cbgs.pth"
    torch.save({"meta": {"epoch": 20}, "state_dict": bevdet_detection_state()}, path)
    model = zoo.build("flashocc_m0")
    before = model.occupancy_head.predictor[0].weight.clone()
    loaded = load_partial(model, path, zoo.experiment("flashocc_m0"))
    reference = read_checkpoint(path).state
    assert torch.equal(model.image_encoder.backbone.stem[0].weight, reference["img_backbone.conv1.weight"])
    assert torch.equal(model.occupancy_head.predictor[0].weight, before)
    text = str(loaded)
    assert f"{loaded.loaded} of the model's" in text and "BEVDet's detection head" in text
    assert "img_view_transformer.depth_net.weight (123, 256, 1, 1)" in text
    with pytest.raises(ConfigError, match=r"but the model is a daocc model: it fits the flashocc entries"):
        load_partial(zoo.build("daocc_tiny"), path)


# ----------------------------------------------------------------------------------------------------- files
class _NotData:
    """A class a weights-only load must refuse to rebuild."""


def test_reading_mmcv_ema_and_ddp_checkpoints(tmp_path):
    import numpy as np

    state = flashocc_state(tiny=True)
    mmcv = tmp_path / "epoch_24.pth"
    torch.save({"meta": {"epoch": 24, "hook_msgs": {"best_score": np.float64(0.3195)}, "CLASSES": ("car",)},
                "state_dict": {f"module.{k}": v for k, v in state.items()}, "optimizer": {"state": {}}}, mmcv)
    checkpoint = read_checkpoint(mmcv)
    assert list(checkpoint.state) == list(state) and set(checkpoint.ignored) == {"meta", "optimizer"}
    # The references' environments pickle numpy 1, whose scalars live in numpy.core: the same file spelled so.
    numpy1 = tmp_path / "numpy1.pth"
    with zipfile.ZipFile(mmcv) as source, zipfile.ZipFile(numpy1, "w") as target:
        for info in source.infolist():
            data = source.read(info.filename)
            if info.filename.endswith("data.pkl"):
                assert b"numpy._core.multiarray" in data
                data = data.replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
            target.writestr(info, data)
    assert list(read_checkpoint(numpy1).state) == list(state)
    ema = tmp_path / "epoch_24_ema.pth"
    torch.save({"epoch": 24, "state_dict": state, "updates": 10560}, ema)
    assert set(read_checkpoint(ema).ignored) == {"epoch", "updates"}
    unsafe = tmp_path / "unsafe.pth"
    torch.save({"state_dict": state, "meta": _NotData()}, unsafe)
    with pytest.raises(ValueError, match=rf"{unsafe} cannot be read as a checkpoint: it pickles .*_NotData"):
        read_checkpoint(unsafe)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_checkpoint(tmp_path / "absent.pth")


def test_convert_checkpoint_writes_weights_and_report(tmp_path):
    path = tmp_path / "flashocc_tiny.pth"
    torch.save({"meta": {"epoch": 1}, "state_dict": flashocc_state(tiny=True)}, path)
    out = tmp_path / "weights" / "flashocc_tiny.safetensors"
    conversion = convert_checkpoint(path, "flashocc_tiny", out)
    report = json.loads(report_path(out).read_text())
    assert report.pop("written_by") == "occkit convert"  # so that a later conversion may replace it, and only it
    assert report == json.loads(json.dumps(conversion.report()))
    assert report["complete"] and report["counts"]["mapped"] == len(flashocc_state(tiny=True))
    assert report["ignored_entries"] == {"meta": "mmcv run metadata: config text, versions, epoch"}
    assert "complete: every occkit tensor" in format_report(report)
    model = load_weights(out, "flashocc_tiny")
    assert torch.equal(model.occupancy_head.predictor[2].bias, conversion.state["occupancy_head.predictor.2.bias"])
    with pytest.raises(ConfigError, match=r"flashocc_tiny \(flashocc\), but daocc_tiny is a daocc model"):
        load_weights(out, "daocc_tiny")
    with pytest.raises(ConfigError, match="convert it first"):
        load_weights(path, "flashocc_tiny")


def test_load_weights_names_the_key_of_another_shape(tmp_path):
    from safetensors.torch import save_file

    state = {k: v.clone() for k, v in zoo.build("flashocc_tiny").state_dict().items()}
    state["occupancy_head.conv.0.weight"] = torch.zeros(32, 32, 1, 1)
    path = tmp_path / "broken.safetensors"
    save_file(state, str(path))
    with pytest.raises(ConfigError, match=r"shape: occupancy_head\.conv\.0\.weight is \(32, 32, 1, 1\)"):
        load_weights(path, "flashocc_tiny")


# ----------------------------------------------------------------------------------------------------- CLI
def test_cli_convert_end_to_end(tmp_path, capsys):
    path = tmp_path / "epoch_24_ema.pth"
    torch.save({"state_dict": flashocc_state(tiny=True), "updates": 5}, path)
    out = tmp_path / "tiny.safetensors"
    assert main(["convert", str(path), "--model", "flashocc_tiny", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "FlashOcc / BEVDet (mmdet3d BEVDetOCC) checkpoint" in printed and f"wrote {out}" in printed
    model = load_weights(out, "flashocc_tiny")
    model.load_state_dict(model.state_dict(), strict=True)
    assert json.loads(report_path(out).read_text())["target"] == "flashocc_tiny"
    # Without --model the source's default entry (flashocc_m0) is taken: the tiny checkpoint does not fit it.
    assert main(["convert", str(path), "--out", str(tmp_path / "m0.safetensors")]) == 2
    err = capsys.readouterr().err
    assert "does not convert to flashocc_m0 (the checkpoint fits flashocc_tiny)" in err and "report.json" in err
    assert not (tmp_path / "m0.safetensors").exists() and (tmp_path / "m0.report.json").exists()
    assert main(["convert", str(tmp_path), "--out", str(out)]) == 2
    assert "is a folder" in capsys.readouterr().err


def test_cli_eval_scores_converted_weights_with_the_entrys_experiment(tmp_path, capsys, synthetic_world):
    world = synthetic_world(scenes=1, frames=2, image_size=(176, 99))
    reference = tmp_path / "flashocc_tiny.pth"
    torch.save({"state_dict": flashocc_state(tiny=True)}, reference)
    weights = tmp_path / "flashocc_tiny.safetensors"
    convert_checkpoint(reference, "flashocc_tiny", weights)
    common = ["--data", str(world), "--split", "all", "--no-rayiou", "--workers", "0", "--device", "cpu"]
    # The entry comes from the file's metadata when neither --model nor --config names it.
    assert main(["eval", "--weights", str(weights), *common, "--out", str(tmp_path / "eval")]) == 0
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert metrics["checkpoint"] == str(weights) and metrics["frames"] == 2 and 0 <= metrics["miou"] <= 1
    capsys.readouterr()
    for argv, needle in [
        (["--weights", str(weights), "--model", "daocc_tiny"], "holds the weights of flashocc_tiny (flashocc)"),
        (["--weights", str(weights), "--model", "flashocc_tiny", "--config", "flashocc_tiny"], "give one"),
        (["--weights", str(reference), "--model", "flashocc_tiny"], "convert it first"),
        (["--ckpt", str(reference), "--model", "flashocc_tiny"], "--model goes with --weights"),
    ]:
        assert main(["eval", *argv, *common, "--out", str(tmp_path / "refused")]) == 2
        assert needle in capsys.readouterr().err


def test_convert_never_writes_its_report_over_a_users_file(tmp_path):
    path = tmp_path / "flashocc_tiny.pth"
    torch.save({"state_dict": flashocc_state(tiny=True)}, path)
    out = tmp_path / "flashocc_tiny.safetensors"
    report_path(out).write_text('{"my": "notes"}\n')
    with pytest.raises(FileExistsError, match="flashocc_tiny.report.json, which exists and is not a report of occkit"):
        convert_checkpoint(path, "flashocc_tiny", out)
    assert report_path(out).read_text() == '{"my": "notes"}\n' and not out.exists()
    report_path(out).unlink()
    convert_checkpoint(path, "flashocc_tiny", out)
    convert_checkpoint(path, "flashocc_tiny", out)  # an earlier report of its own is replaced
