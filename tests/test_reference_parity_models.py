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
from occkit.models.flashocc import FlashOcc, FlashOccConfig
from occkit.models.heads.occupancy import OccupancyHeadConfig
from occkit.models.image_encoder import ImageEncoderConfig
from occkit.models.view_transform.lss import LSSConfig
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
    assert {path.stem for path in key_lists} >= {"flashocc_m0", "flashocc_m1"}
    for key_list in key_lists:
        report = key_coverage.coverage(key_list)
        assert report["keys"] == report["mapped"] + report["dropped"] and report["covered"] == "100.0%", key_list
        assert report["unmapped"] == report["shape_mismatches"] == 0 and not report["occkit_unfilled"], key_list
        assert all(entry.get("occkit") or entry.get("dropped") for entry in report["by_key"].values())
        committed = json.loads(key_coverage.coverage_path(key_list).read_text())
        assert committed == report, f"{key_list.stem}.coverage.json is stale: rerun key_coverage.py"
