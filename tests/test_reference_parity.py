"""occkit against the reference code's own numbers: the goldens under ``tests/golden/reference_parity`` were written
by ``benchmarks/reference_parity/*.py`` running the reference repository at the commit each golden names; no
reference code runs here.

The data side: for the reference's augmentation draws, occkit's sampling gives the same parameters and occkit's
image and BEV augmentation matrices equal the ones FlashOcc's ``PrepareImageInputs.img_transform`` and
``LoadAnnotationsBEVDepth.bev_transform`` computed; occkit's LSS frustum is ``LSSViewTransformer.create_frustum``'s.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from occkit import zoo
from occkit.data.transforms import BevAugConfig, ImageAugConfig, sample_bev_aug, sample_image_aug
from occkit.models.view_transform.lss import frustum

GOLDENS = Path(__file__).parent / "golden" / "reference_parity"


@pytest.fixture(scope="module")
def golden() -> dict:
    return json.loads((GOLDENS / "flashocc_data_side.json").read_text())


@pytest.fixture(scope="module")
def daocc_golden() -> dict:
    return json.loads((GOLDENS / "daocc_data_side.json").read_text())


class _Scripted:
    """A random source that returns given values in order: occkit's sampling, fed the reference's draws."""

    def __init__(self, uniforms: list[float], randoms: list[float]) -> None:
        self.uniforms, self.randoms = list(uniforms), list(randoms)

    def uniform(self, low: float = 0.0, high: float = 1.0) -> float:
        value = self.uniforms.pop(0)
        assert low <= value <= high or math.isclose(value, low) or math.isclose(value, high), (low, value, high)
        return value

    def random(self) -> float:
        return self.randoms.pop(0)


def _image_config(golden: dict) -> ImageAugConfig:
    config = golden["data_config"]
    return ImageAugConfig(final_size=tuple(config["input_size"]), resize_range=tuple(config["resize"]),
                          bottom_crop=True, flip=config["flip"], rotate_deg=tuple(config["rot"]))  # fmt: skip


def test_the_golden_names_the_reference_and_its_commit(golden):
    assert golden["repository"] == "Yzichen/FlashOCC" and len(golden["commit"]) == 40
    assert [Path(f).name for f in golden["files"]] == ["loading.py", "view_transformer.py"]


def test_image_augmentation_parameters_and_matrices_equal_flashoccs(golden):
    config = _image_config(golden)
    height, width = golden["data_config"]["src_size"]
    base = config.final_size[1] / width
    for draw in golden["image"]:
        rng = _Scripted([draw["resize"] - base, draw["crop"][0], draw["rotate_deg"]], [0.0 if draw["flip"] else 0.9])
        params = sample_image_aug(config, (width, height), draw["train"], rng)
        assert params.resize == pytest.approx(draw["resize"], abs=1e-12), draw["seed"]
        # The crop follows from int() of the resized size, as the reference truncates it.
        assert list(params.crop) == draw["crop"] and params.flip == draw["flip"], draw["seed"]
        assert params.rotate_deg == pytest.approx(draw["rotate_deg"], abs=1e-12)
        matrix = params.matrix().to(torch.float64)
        reference = torch.tensor(draw["post_rot"], dtype=torch.float64)
        translation = torch.tensor(draw["post_tran"], dtype=torch.float64)
        # The reference computes in float32: its matrix is exact to float32 rounding of pixel-sized values.
        torch.testing.assert_close(matrix[:2, :2], reference, rtol=0, atol=1e-6)
        torch.testing.assert_close(matrix[:2, 2], translation, rtol=0, atol=1e-4)


@pytest.mark.parametrize("key", ["bev", "bev_bevdet"])
def test_bev_augmentation_matrices_equal_flashoccs(golden, key):
    conf = golden["bda_aug_conf" if key == "bev" else "bda_aug_conf_bevdet"]
    config = BevAugConfig(flip_x=conf["flip_dx_ratio"], flip_y=conf["flip_dy_ratio"],
                          rotate_deg=tuple(conf["rot_lim"]), scale=tuple(conf["scale_lim"]))  # fmt: skip
    for draw in golden[key]:
        rng = _Scripted([draw["rotate_deg"], draw["scale"]], [0.0 if draw["flip_dx"] else 0.9,
                                                              0.0 if draw["flip_dy"] else 0.9])  # fmt: skip
        occ_aug = sample_bev_aug(config, rng, train=True)
        reference = torch.tensor(draw["rot_mat"], dtype=torch.float64)
        torch.testing.assert_close(occ_aug[:3, :3], reference, rtol=0, atol=1e-6)
        assert torch.equal(occ_aug[3], torch.tensor([0.0, 0, 0, 1], dtype=torch.float64)), draw["seed"]
    assert {draw["flip_dx"] for draw in golden[key]} == {True, False}  # both branches are in the goldens


def test_the_draws_cover_every_branch(golden):
    draws = golden["image"]
    assert {d["flip"] for d in draws if d["train"]} == {True, False}
    assert any(not d["train"] for d in draws)
    assert np.ptp([d["rotate_deg"] for d in golden["bev_bevdet"]]) > 10


@pytest.mark.parametrize("name", ["flashocc_m0", "flashocc_m1", "bevdet_r50_cbgs"])
def test_the_lss_frustum_is_flashoccs(golden, name):
    reference = golden["frustum"][name]
    points = frustum(reference["image_size"], reference["stride"], reference["depth"])
    assert list(points.shape) == reference["shape"]
    u, v, d = (torch.tensor(reference[axis]) for axis in ("u", "v", "d"))
    expected = torch.stack(torch.broadcast_tensors(u[None, None, :], v[None, :, None], d[:, None, None]), dim=-1)
    torch.testing.assert_close(points, expected, rtol=0, atol=1e-6)


def test_the_paper_presets_augment_as_their_references(golden, daocc_golden):
    """FlashOcc M0 and DAOcc train with the reference configs' augmentation settings (FlashOcc's data_config and
    bda_aug_conf; DAOcc's augment2d, ImageAug3D's bottom crop and flips, and an identity GlobalRotScaleTrans)."""
    flashocc, daocc = zoo.experiment("flashocc_m0").data, zoo.experiment("daocc").data
    assert flashocc.image_aug == _image_config(golden)
    conf = golden["bda_aug_conf"]
    assert flashocc.bev_aug == BevAugConfig(flip_x=conf["flip_dx_ratio"], flip_y=conf["flip_dy_ratio"],
                                            rotate_deg=tuple(conf["rot_lim"]), scale=tuple(conf["scale_lim"]))
    reference = daocc_golden["image_aug"]
    assert daocc.image_aug == ImageAugConfig(final_size=tuple(reference["final_dim"]),
                                             resize_range=tuple(reference["resize_lim"]),
                                             bottom_crop=reference["bot_pct_lim"] == [0.0, 0.0],
                                             flip=reference["rand_flip"], rotate_deg=tuple(reference["rot_lim"]))
    # RandomFlip3D flips each axis with probability one half; the 3D rotation and scale are off in the occ3d config.
    assert daocc.bev_aug == BevAugConfig(flip_x=0.5, flip_y=0.5, rotate_deg=(0.0, 0.0), scale=(1.0, 1.0))


def test_daoccs_image_augmentation_equals_its_reference(daocc_golden):
    reference = daocc_golden["image_aug"]
    config = ImageAugConfig(final_size=tuple(reference["final_dim"]), resize_range=tuple(reference["resize_lim"]),
                            bottom_crop=True, flip=True, rotate_deg=tuple(reference["rot_lim"]))  # fmt: skip
    width, height = daocc_golden["original_size"]
    base = config.final_size[1] / width
    for draw in daocc_golden["image"]:
        rng = _Scripted([draw["resize"] - base, draw["crop"][0], draw["rotate_deg"]], [0.0 if draw["flip"] else 0.9])
        params = sample_image_aug(config, (width, height), draw["train"], rng)
        assert list(params.crop) == draw["crop"] and params.flip == draw["flip"], draw["seed"]
        matrix = params.matrix().to(torch.float64)
        torch.testing.assert_close(matrix[:2, :2], torch.tensor(draw["rotation"], dtype=torch.float64), rtol=0,
                                   atol=1e-6)  # fmt: skip
        torch.testing.assert_close(matrix[:2, 2], torch.tensor(draw["translation"], dtype=torch.float64), rtol=0,
                                   atol=1e-4)  # fmt: skip


def test_daoccs_bev_flips_equal_its_reference(daocc_golden):
    config = BevAugConfig(flip_x=0.5, flip_y=0.5)
    for draw in daocc_golden["flip"]:
        rng = _Scripted([0.0, 1.0], [0.0 if draw["flip_x"] else 0.9, 0.0 if draw["flip_y"] else 0.9])
        occ_aug = sample_bev_aug(config, rng, train=True)
        for key in ("lidar_aug_matrix", "occ_aug_matrix"):
            torch.testing.assert_close(occ_aug, torch.tensor(draw[key], dtype=torch.float64), rtol=0, atol=0)
    assert {(d["flip_x"], d["flip_y"]) for d in daocc_golden["flip"]} == {(a, b) for a in (0, 1) for b in (0, 1)}
