"""Model-side parity with the reference code: the reference's weights, converted by occkit, give its outputs.

The goldens (``tests/golden/reference_parity/*_model/``) were written by ``benchmarks/reference_parity/*_model.py``
from the reference repositories at pinned commits (docs/reproducing.md): a reduced-width reference model with random
weights (an mmcv checkpoint), a fixed input batch, the reference's output at each stage and its loss terms. Here
occkit builds the same reduced model from its own config, converts the checkpoint with ``occkit.convert`` (the code
behind ``occkit convert``), runs the inputs and compares: each stage to 1e-4 of that stage's largest magnitude, each
loss to 1e-5 relative. No reference code is needed.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import benchmark_module

from occkit.convert import convert_state_dict, read_checkpoint
from occkit.models.bev_encoder import BevEncoderConfig
from occkit.models.daocc import DAOcc, DAOccConfig
from occkit.models.flashocc import FlashOcc, FlashOccConfig
from occkit.models.heads.center import CenterHeadConfig
from occkit.models.heads.occupancy import OccupancyHeadConfig
from occkit.models.image_encoder import ImageEncoderConfig
from occkit.models.lidar_encoder import LidarEncoderConfig
from occkit.models.range_extension import RangeExtensionConfig
from occkit.models.view_transform.lss import LSSConfig
from occkit.models.view_transform.projection import ProjectionConfig
from occkit.types import Batch

GOLDEN = Path(__file__).parent / "golden" / "reference_parity"
FLASHOCC = GOLDEN / "flashocc_model"
STAGE_TOLERANCE = 1e-4  # max |occkit - reference| / max |reference|, per stage
LOSS_TOLERANCE = 1e-5  # relative


def scaled_difference(ours: torch.Tensor, reference: np.ndarray) -> float:
    reference = torch.from_numpy(reference).double()
    assert tuple(ours.shape) == tuple(reference.shape)
    return float((ours.double() - reference).abs().max() / reference.abs().max().clamp_min(1e-12))


# ------------------------------------------------------------------------------------------------------ FlashOcc
def flashocc_config(meta: dict, name: str) -> FlashOccConfig:
    """occkit's FlashOcc of the golden's reduced reference config (``meta["models"][name]["model"]``)."""
    model = meta["models"][name]["model"]
    backbone, neck, view = model["img_backbone"], model["img_neck"], model["img_view_transformer"]
    grid = view["grid_config"]
    bev_backbone, bev_neck, head = model["img_bev_encoder_backbone"], model["img_bev_encoder_neck"], model["occ_head"]
    return FlashOccConfig(
        image=ImageEncoderConfig(depth=backbone["depth"], base_channels=backbone["base_channels"],
                                 out_stages=tuple(i + 1 for i in backbone["out_indices"]), norm_eval=False,
                                 neck="fpn", neck_channels=neck["out_channels"]),
        lss=LSSConfig(image_size=tuple(view["input_size"]), feature_stride=view["downsample"],
                      depth_range=tuple(grid["depth"]),
                      point_cloud_range=(grid["x"][0], grid["y"][0], grid["z"][0], grid["x"][1], grid["y"][1],
                                         grid["z"][1]),
                      grid_size=tuple(round((grid[a][1] - grid[a][0]) / grid[a][2]) for a in "xyz"),
                      in_channels=view["in_channels"], context_channels=view["out_channels"],
                      truncate_indices=True),
        bev=BevEncoderConfig(in_channels=bev_backbone["numC_input"], strides=(2, 2, 2),
                             channels=tuple(bev_backbone["num_channels"]), neck_channels=bev_neck["out_channels"],
                             neck_extra_upsample=2),
        occupancy=OccupancyHeadConfig(in_channels=head["in_dim"], hidden_channels=head["out_dim"], height=head["Dz"],
                                      num_classes=head["num_classes"], use_mask=head["use_mask"]),
    )  # fmt: skip


def flashocc_batch(inputs: dict[str, np.ndarray]) -> Batch:
    """The reference's ``img_inputs`` as occkit's batch: ``cam2ego`` is BEVDet's ``prepare_inputs`` camera -> key
    ego (computed as it does, in float64), ``img_aug`` the 3 x 3 of ``post_rots`` / ``post_trans``, ``occ_aug`` the
    4 x 4 of ``bda``."""
    t = {name: torch.from_numpy(value) for name, value in inputs.items()}
    ego2globals = t["ego2globals"].double()
    cam2ego = (torch.linalg.inv(ego2globals[:, :1]) @ ego2globals @ t["sensor2egos"].double()).float()
    img_aug = t["post_rots"].clone()
    img_aug[..., :2, 2] = t["post_trans"][..., :2]
    occ_aug = torch.eye(4).repeat(t["bda"].shape[0], 1, 1)
    occ_aug[:, :3, :3] = t["bda"]
    return Batch(tokens=["golden"], scenes=["golden"], images=t["images"], intrinsics=t["intrins"], cam2ego=cam2ego,
                 img_aug=img_aug, occ_aug=occ_aug, voxel_semantics=t["voxel_semantics"].long(),
                 mask_camera=t["mask_camera"].bool())  # fmt: skip


def run_flashocc(model: FlashOcc, batch: Batch) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
    """occkit's outputs at the reference's stages, in the reference's shapes and axis order."""
    captured: dict[str, torch.Tensor] = {}
    hooks = [model.image_encoder.register_forward_hook(lambda m, a, out: captured.__setitem__("image_features", out)),
             model.view_transform.register_forward_hook(lambda m, a, out: captured.__setitem__("bev", out[0])),
             model.bev_encoder.register_forward_hook(lambda m, a, out: captured.__setitem__("bev_encoded", out))]
    model.eval()
    with torch.no_grad():
        output = model(batch)
        losses = model.loss(output, batch)
    for hook in hooks:
        hook.remove()
    return {
        "image_features": captured["image_features"].flatten(0, 1),  # (B*N, C, h, w)
        "depth": output.depth.flatten(0, 1),  # (B*N, D, h, w)
        "bev": captured["bev"].transpose(-1, -2),  # (B, C, X, Y) -> the reference's (B, C, Y, X)
        "bev_encoded": captured["bev_encoded"].transpose(-1, -2),
        "logits": output.occupancy.permute(0, 2, 3, 4, 1),  # (B, K, X, Y, Z) -> (B, X, Y, Z, K)
    }, {"loss_occ": float(losses["occupancy"])}


@pytest.fixture(scope="module")
def flashocc_golden() -> dict:
    meta = json.loads((FLASHOCC / "meta.json").read_text())
    with np.load(FLASHOCC / "inputs.npz") as inputs:
        return {"meta": meta, "inputs": dict(inputs)}


@pytest.mark.parametrize("name", ["flashocc_m0", "flashocc_m1"])
def test_flashocc_gives_the_reference_outputs_on_converted_reference_weights(flashocc_golden, name):
    meta = flashocc_golden["meta"]
    assert meta["repository"] == "Yzichen/FlashOCC" and len(meta["commit"]) == 40
    checkpoint = read_checkpoint(FLASHOCC / f"{name}.pth")
    model = FlashOcc(flashocc_config(meta, name))
    conversion = convert_state_dict(checkpoint.state, model)
    assert conversion.complete and not conversion.unmapped and not conversion.dropped
    model.load_state_dict(conversion.state, strict=True)

    stages, losses = run_flashocc(model, flashocc_batch(flashocc_golden["inputs"]))
    with np.load(FLASHOCC / f"{name}_stages.npz") as reference:
        differences = {stage: scaled_difference(stages[stage], reference[stage]) for stage in reference.files}
    assert set(differences) == set(stages)
    assert max(differences.values()) <= STAGE_TOLERANCE, differences
    for term, value in meta["models"][name]["losses"].items():
        assert losses[term] == pytest.approx(value, rel=LOSS_TOLERANCE), term


# ------------------------------------------------------------------------------------------ paper-size key lists
def test_every_paper_size_reference_key_is_mapped_or_dropped_with_a_reason():
    """The reference models' full key lists (docs/results/parity/) convert completely to their zoo entries, and the
    committed coverage files are what the conversion gives today."""
    key_coverage = benchmark_module("reference_parity/key_coverage.py")
    key_lists = key_coverage.key_lists()
    assert {path.stem for path in key_lists} == {"daocc", "daocc_no_detection", "flashocc_m0", "flashocc_m1"}
    for key_list in key_lists:
        report = key_coverage.coverage(key_list)
        assert report["keys"] == report["mapped"] + report["dropped"] and report["covered"] == "100.0%", key_list
        assert report["unmapped"] == report["shape_mismatches"] == 0 and not report["occkit_unfilled"], key_list
        assert all(entry.get("occkit") or entry.get("dropped") for entry in report["by_key"].values())
        committed = json.loads(key_coverage.coverage_path(key_list).read_text())
        assert committed == report, f"{key_list.stem}.coverage.json is stale: rerun key_coverage.py"


# --------------------------------------------------------------------------------------------------------- DAOcc
DAOCC = GOLDEN / "daocc_model"


#: The reference's two view transforms -> occkit's projection settings, golden stages and losses. ``BEVTransform``
#: (the paper's, V1, which the ``daocc`` entries run) averages the cameras that see a voxel; ``BEVTransformV2`` (the
#: public code's current config) takes the first and samples with ``align_corners=True``.
DAOCC_VIEW_TRANSFORMS = {
    "BEVTransform": ({"mode": "average", "align_corners": False}, "stages_paper.npz"),
    "BEVTransformV2": ({"mode": "first", "align_corners": True}, "stages.npz"),
}


def daocc_losses(meta: dict, view_transform: str) -> dict[str, float]:
    return meta["paper_view_transform"]["losses"] if view_transform == "BEVTransform" else meta["losses"]


def daocc_config(meta: dict, view_transform: str) -> DAOccConfig:
    """occkit's DAOcc of the golden's reduced reference config (the paper config with ``meta["overrides"]``) and the
    reference's ``view_transform``."""
    reduced = meta["overrides"]
    model = reduced["model"]
    camera, lidar = model["encoders"]["camera"], model["encoders"]["lidar"]["backbone"]
    view, decoder, heads = camera["vtransform"], model["decoder"], model["heads"]
    pc_range = tuple(reduced["point_cloud_range"])
    occ = heads["occ"]["coordinate_transform"]
    x0, x1, y0, y1 = occ["point_range"][:4]
    return DAOccConfig(
        occ_range=(x0, y0, -1.0, x1, y1, 5.4),
        occ_voxel_size=((x1 - x0) / occ["point_num"][0], (y1 - y0) / occ["point_num"][1], 0.4),
        image=ImageEncoderConfig(depth=50, base_channels=camera["backbone"]["base_channels"], out_stages=(2, 3, 4),
                                 neck="lss_fpn", neck_channels=camera["neck"]["out_channels"], norm_eval=False),
        view=ProjectionConfig(point_cloud_range=(view["x"][0], view["y"][0], -5.0, view["x"][1], view["y"][1], 3.0),
                              grid_size=(view["xs"], view["ys"], 10), in_channels=view["in_channels"],
                              out_channels=view["out_channels"], **DAOCC_VIEW_TRANSFORMS[view_transform][0]),
        lidar=LidarEncoderConfig(point_cloud_range=pc_range, remove_close=0.0, base_channels=lidar["base_channels"],
                                 encoder_channels=tuple(tuple(stage) for stage in lidar["encoder_channels"]),
                                 output_channels=lidar["output_channels"]),
        fusion_channels=model["fuser"]["out_channels"],
        bev=BevEncoderConfig(in_channels=decoder["backbone"]["numC_input"], strides=(1, 1, 2),
                             channels=tuple(decoder["backbone"]["num_channels"]),
                             neck_channels=decoder["neck"]["out_channels"]),
        range_extension=RangeExtensionConfig(bev_range=(view["x"][0], view["y"][0], view["x"][1], view["y"][1]),
                                             in_channels=occ["in_dim"], out_channels=occ["out_dim"]),
        occupancy=OccupancyHeadConfig(in_channels=heads["occ"]["in_dim"], hidden_channels=heads["occ"]["out_dim"]),
        detection=CenterHeadConfig(in_channels=heads["object"]["in_channels"],
                                   share_conv_channels=heads["object"]["share_conv_channel"],
                                   head_conv_channels=heads["object"]["separate_head"]["head_conv"],
                                   point_cloud_range=pc_range),
    )  # fmt: skip


def daocc_batch(inputs: dict[str, np.ndarray]) -> Batch:
    """The reference's inputs as occkit's batch: 3 x 3 intrinsics and image augmentations from the 4 x 4 ones, and
    the boxes' z at their centre (LiDARInstance3DBoxes hold the bottom)."""
    t = {name: torch.from_numpy(value) for name, value in inputs.items()}
    img_aug = torch.eye(3).repeat(*t["img_aug_matrix"].shape[:2], 1, 1)
    img_aug[..., :2, :2] = t["img_aug_matrix"][..., :2, :2]
    img_aug[..., :2, 2] = t["img_aug_matrix"][..., :2, 3]
    boxes = t["gt_bboxes_3d"].clone()
    boxes[..., 2] += boxes[..., 5] / 2
    points = t["points"]
    return Batch(tokens=["golden"], scenes=["golden"], images=t["img"], intrinsics=t["camera_intrinsics"][..., :3, :3],
                 cam2ego=t["camera2ego"], img_aug=img_aug, lidar2ego=t["lidar2ego"], bev_aug=t["lidar_aug_matrix"],
                 occ_aug=t["occ_aug_matrix"], points=points, num_points=torch.tensor([points.shape[1]]),
                 boxes=list(boxes), box_labels=list(t["gt_labels_3d"]), voxel_semantics=t["voxel_semantics"].long(),
                 mask_camera=t["mask_camera"].bool())  # fmt: skip


def run_daocc(model: DAOcc, batch: Batch) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
    """occkit's outputs at the reference's stages, in the reference's shapes and axis order, and its loss terms under
    the reference's names (the detection terms per task, times the detection loss weight as ``loss_scale``)."""
    captured: dict[str, torch.Tensor] = {}

    def keep(name, pick=lambda out: out):
        return lambda module, args, out: captured.__setitem__(name, pick(out))

    modules = {"camera_neck": model.image_encoder, "camera_bev": model.view_transform,
               "lidar_bev": model.lidar_encoder, "fused_bev": model.fuser, "decoder_bev": model.bev_encoder,
               "occ_sampled": model.range_extension, "occ_final_conv": model.occupancy_head.conv,
               "object_shared": model.detection_head.shared_conv}  # fmt: skip
    hooks = [module.register_forward_hook(keep(name)) for name, module in modules.items()]
    model.eval()
    with torch.no_grad():
        output = model(batch, detect=True)
        occupancy = model.occupancy_head.loss(output.occupancy, batch.voxel_semantics, batch.mask_camera)
        detection = model.detection_head.loss(output.detection, batch.boxes, batch.box_labels)
    for hook in hooks:
        hook.remove()
    stages = {
        "camera_neck": captured["camera_neck"].flatten(0, 1),
        **{name: captured[name] for name in ("camera_bev", "lidar_bev", "fused_bev", "decoder_bev", "object_shared")},
        "occ_sampled": captured["occ_sampled"].transpose(-1, -2),  # (B, C, X, Y) -> the reference's (B, C, Y, X)
        "occ_final_conv": captured["occ_final_conv"].transpose(-1, -2),
        "occ_logits": output.occupancy.permute(0, 2, 3, 4, 1),  # (B, K, X, Y, Z) -> (B, X, Y, Z, K)
    }
    for t, task in enumerate(output.detection):
        stages.update({f"object_task{t}_{name}": value for name, value in task.items()})
    weight = model.cfg.detection_loss_weight
    losses = {"loss/occ/loss_occ": float(occupancy["occupancy"])}
    for t in range(len(output.detection)):
        losses[f"loss/object/heatmap/task{t}"] = weight * float(detection[f"det_heatmap/task{t}"])
        losses[f"loss/object/bbox/task{t}"] = weight * float(detection[f"det_bbox/task{t}"])
    return stages, losses


@pytest.mark.parametrize("view_transform", list(DAOCC_VIEW_TRANSFORMS))
def test_daocc_gives_the_reference_outputs_on_converted_reference_weights(view_transform):
    meta = json.loads((DAOCC / "meta.json").read_text())
    assert meta["reference"]["repository"] == "AlphaPlusTT/DAOcc" and len(meta["reference"]["commit"]) == 40
    checkpoint = read_checkpoint(DAOCC / "reference.pth")
    model = DAOcc(daocc_config(meta, view_transform))
    conversion = convert_state_dict(checkpoint.state, model)
    assert conversion.complete and not conversion.unmapped
    assert set(conversion.dropped) == {"encoders.camera.vtransform.ref_3d", "heads.occ.coordinate_transform.ref_points"}
    model.load_state_dict(conversion.state, strict=True)

    with np.load(DAOCC / "inputs.npz") as inputs:
        stages, losses = run_daocc(model, daocc_batch(dict(inputs)))
    with np.load(DAOCC / DAOCC_VIEW_TRANSFORMS[view_transform][1]) as reference:
        differences = {stage: scaled_difference(ours, reference[stage]) for stage, ours in stages.items()}
    assert max(differences.values()) <= STAGE_TOLERANCE, differences
    for term, value in daocc_losses(meta, view_transform).items():
        assert losses[term] == pytest.approx(value, rel=LOSS_TOLERANCE, abs=1e-12), term
