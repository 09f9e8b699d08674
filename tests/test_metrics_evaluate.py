"""Scoring a folder of predictions against a gts/ tree reproduces the official mIoU and SparseOcc RayIoU."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from occkit.cli import main
from occkit.metrics.evaluate import evaluate_predictions, write_report

GOLDEN = Path(__file__).parent / "golden" / "occ3d_metrics"
MODES = {"camera": "camera_mask", "lidar": "lidar_mask", "none": "no_mask"}


@pytest.fixture(scope="module")
def trees(tmp_path_factory):
    """The 20 golden frames as an Occ3D gts/ tree, two prediction folders (key semantics / pred) and origins."""
    root = tmp_path_factory.mktemp("eval")
    frames = np.load(GOLDEN / "all_frames.npz")
    scenes = {info["token"]: info["scene_name"] for info in json.loads((GOLDEN / "infos.json").read_text())}
    tokens = [str(t) for t in frames["tokens"]]
    for kind in ("semantics", "pred"):
        (root / f"preds_{kind}").mkdir()
    for i, token in enumerate(tokens):
        folder = root / "gts" / scenes[token] / token
        folder.mkdir(parents=True)
        np.savez(
            folder / "labels.npz",
            semantics=frames["semantics"][i],
            mask_lidar=frames["mask_lidar"][i],
            mask_camera=frames["mask_camera"][i],
        )
        for kind in ("semantics", "pred"):
            np.savez(root / f"preds_{kind}" / f"{token}.npz", **{kind: frames["pred"][i]})
    lidar = np.load(GOLDEN / "lidar_origins.npz")
    origins = {str(t): lidar["origins"][i, : lidar["n_origins"][i]] for i, t in enumerate(lidar["tokens"])}
    np.savez(root / "origins.npz", **origins)
    return {"root": root, "gts": root / "gts", "tokens": tokens, "origins": root / "origins.npz"}


@pytest.fixture(scope="module")
def official():
    return json.loads((GOLDEN / "miou_official.json").read_text())["modes"]


def _copy_preds(trees, tmp_path) -> Path:
    preds = tmp_path / "preds"
    shutil.copytree(trees["root"] / "preds_semantics", preds)
    return preds


def _assert_miou(result, reference):
    assert result["miou"] == pytest.approx(reference["mIoU"], abs=1e-12)
    names = list(result["per_class_iou"])
    assert len(names) == 18
    for name, expected in zip(names, reference["per_class_iou"], strict=True):
        value = result["per_class_iou"][name]
        assert (value is None) == (expected is None), name
        if expected is not None:
            assert value == pytest.approx(expected, abs=1e-12), name
    assert result["iou"] == pytest.approx(reference["geometry_iou"]["IoU_occupied"], abs=1e-12)


def test_camera_mask_and_rayiou_match_references(trees, official):
    result = evaluate_predictions(
        trees["gts"], trees["root"] / "preds_semantics", ray_origins=trees["origins"], compute_rayiou=True
    )
    _assert_miou(result, official["camera_mask"])
    assert result["mask"] == "camera" and result["frames"] == 20 and result["missing_predictions"] == 0
    main_return = json.loads((GOLDEN / "rayiou_sparseocc.json").read_text())["main_rayiou_return"]
    assert result["rayiou"] == pytest.approx(main_return["RayIoU"], abs=1e-6)
    for t in (1, 2, 4):
        assert result[f"rayiou@{t}"] == pytest.approx(main_return[f"RayIoU@{t}"], abs=1e-6)


@pytest.mark.parametrize("mask", ["lidar", "none"])
def test_other_masks_and_pred_key(trees, official, mask):
    result = evaluate_predictions(trees["gts"], trees["root"] / "preds_pred", mask=mask, workers=2)
    _assert_miou(result, official[MODES[mask]])
    assert result["mask"] == mask and "rayiou" not in result


def test_missing_prediction_is_listed_or_scored_as_free(trees, tmp_path):
    preds = _copy_preds(trees, tmp_path)
    gone = trees["tokens"][3]
    (preds / f"{gone}.npz").unlink()
    with pytest.raises(ValueError, match=f"no prediction for 1 of 20 frames: {gone}"):
        evaluate_predictions(trees["gts"], preds)
    result = evaluate_predictions(trees["gts"], preds, allow_missing=True)
    assert result["missing_predictions"] == 1 and result["frames"] == 20
    assert 0 <= result["miou"] <= 1


def test_bad_predictions_name_the_file(trees, tmp_path):
    preds = _copy_preds(trees, tmp_path)
    bad = preds / f"{trees['tokens'][0]}.npz"
    np.savez(bad, semantics=np.zeros((200, 200, 8), np.uint8))
    with pytest.raises(ValueError, match=rf"{bad.name}.*shape \(200, 200, 8\)"):
        evaluate_predictions(trees["gts"], preds)
    grid = np.zeros((200, 200, 16), np.uint8)
    grid[0, 0, 0] = 40
    np.savez(bad, semantics=grid)
    with pytest.raises(ValueError, match=rf"{bad.name}.*\[40\]"):
        evaluate_predictions(trees["gts"], preds)
    bad.write_bytes(b"not an npz")
    with pytest.raises(ValueError, match=f"{bad.name}: cannot read prediction"):
        evaluate_predictions(trees["gts"], preds)


def test_rayiou_needs_origins(trees, tmp_path):
    with pytest.raises(ValueError, match="ray origins"):
        evaluate_predictions(trees["gts"], trees["root"] / "preds_semantics", compute_rayiou=True)
    partial = tmp_path / "origins.npz"
    np.savez(partial, **{trees["tokens"][0]: np.zeros((1, 3))})
    with pytest.raises(ValueError, match="no ray origins for 19 of 20 frames"):
        evaluate_predictions(trees["gts"], trees["root"] / "preds_semantics", ray_origins=partial, compute_rayiou=True)


def test_report_files(trees, tmp_path):
    result = evaluate_predictions(trees["gts"], trees["root"] / "preds_semantics", mask="none")
    paths = write_report(result, tmp_path)
    assert json.loads(paths["json"].read_text()) == result
    table = paths["markdown"].read_text()
    assert f"| {100 * result['miou']:.2f} |" in table and "| free |" not in table
    assert paths["plot"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_end_to_end(trees, official, tmp_path, capsys):
    out = tmp_path / "report"
    args = ["--gt", str(trees["gts"]), "--preds", str(trees["root"] / "preds_pred"), "--out", str(out)]
    assert main(["eval-preds", *args, "--rayiou", "--ray-origins", str(trees["origins"]), "--workers", "3"]) == 0
    printed = capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["miou"] == pytest.approx(official["camera_mask"]["mIoU"], abs=1e-12)
    assert "rayiou@4" in metrics
    assert (out / "metrics.md").read_text() in printed
    assert (out / "per_class_iou.png").stat().st_size > 0

    assert main(["eval-preds", *args, "--rayiou"]) == 2
    assert "--ray-origins" in capsys.readouterr().err


def test_ray_origins_from_the_dataset_tables(tmp_path, capsys):
    # A perfect prediction of a synthetic dataset scores 1 everywhere, with origins derived from its tables.
    from occkit.sim.generate import SimConfig, simulate_dataset

    root = tmp_path / "synth"
    simulate_dataset(SimConfig(scenes=1, frames=2, image_size=(176, 64), cameras=("CAM_FRONT",)), root)
    predictions = tmp_path / "preds"
    predictions.mkdir()
    for labels in (root / "gts").glob("*/*/labels.npz"):
        with np.load(labels) as gt:
            np.savez(predictions / f"{labels.parent.name}.npz", semantics=gt["semantics"])
    arguments = ["eval-preds", "--gt", str(root / "gts"), "--preds", str(predictions), "--out", str(tmp_path / "out")]
    assert main([*arguments, "--rayiou", "--nuscenes", str(root), "--version", "v1.0-synth"]) == 0
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["miou"] == 1.0 and metrics["rayiou"] == 1.0
    assert main([*arguments, "--rayiou"]) == 2
    assert "--nuscenes ROOT" in capsys.readouterr().err
