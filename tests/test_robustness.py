"""Corruptions (occkit.data.corruptions) checked on the data they produce, and occkit robustness end to end."""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import shutil

import numpy as np
import pytest
import torch

from occkit import zoo
from occkit.data.collate import collate
from occkit.data.corruptions import CORRUPTIONS, SampleCorruption
from occkit.data.dataset import DatasetConfig, OccupancyDataset, read_points
from occkit.data.transforms import ImageAugConfig
from occkit.engine.checkpoint import FORMAT, atomic_save
from occkit.engine.evaluate import evaluate_model
from occkit.geometry.camera import project_points
from occkit.label_space import OCC3D_SPACE
from occkit.robustness import SUITES, Case, parse_suite, run_robustness
from occkit.robustness.report import corruption_error, resilience, score_summary
from occkit.robustness.suite import model_inputs, not_applicable
from occkit.sim.generate import SimConfig, simulate_dataset

CAMERAS = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_BACK")
IMAGE_AUG = ImageAugConfig(final_size=(96, 176))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """1 scene x 3 key frames (the later ones with 9 sweeps before them), three cameras at 352 x 198."""
    root = tmp_path_factory.mktemp("robustness") / "data"
    simulate_dataset(SimConfig(scenes=1, frames=3, seed=5, image_size=(352, 198), cameras=CAMERAS), root)
    return root


def _dataset(root, corruption=None, severity=1, **options) -> OccupancyDataset:
    config = {"root": str(root), "split": "all", "cameras": CAMERAS, "image_aug": IMAGE_AUG, "sweeps": 9,
              "corruption": corruption, "corruption_severity": severity, **options}  # fmt: skip
    return OccupancyDataset(DatasetConfig(**config))


# ------------------------------------------------------------------------------------------------- the registry
def test_every_corruption_is_well_formed_and_unknown_ones_are_named():
    families = {"cameras", "images", "lidar", "geometry", "temporal"}
    for name, corruption in CORRUPTIONS.items():
        assert corruption.name == name and corruption.family in families
        assert len(corruption.levels) == len(corruption.labels) >= 1
        assert set(corruption.needs) <= {"cameras", "lidar", "temporal"}
        assert not corruption.ordered or len(corruption.levels) <= 3
    with pytest.raises(ValueError, match="unknown corruption 'rain'; the corruptions are missing_camera"):
        SampleCorruption("rain", 1)
    with pytest.raises(ValueError, match="fog has levels 1 to 3, got 4"):
        SampleCorruption("fog", 4)
    with pytest.raises(ValueError, match="unknown corruption"):
        _dataset("unused", corruption="rain")


def test_image_corruptions_change_pixels_by_a_severity_ordered_amount_and_repeat_exactly(world):
    pytest.importorskip("albumentations")
    dataset = _dataset(world)
    record = dataset.records[1]
    clean = np.asarray(dataset._read_camera(record, "CAM_FRONT", record.token), dtype=np.float64)
    for name in (n for n, c in CORRUPTIONS.items() if c.family == "images"):
        changes = []
        for severity in CORRUPTIONS[name].severities:
            corrupted = _dataset(world, name, severity)
            pixels = np.asarray(corrupted._read_camera(record, "CAM_FRONT", record.token))
            again = np.asarray(_dataset(world, name, severity)._read_camera(record, "CAM_FRONT", record.token))
            np.testing.assert_array_equal(pixels, again)  # a pure function of seed, frame, name and level
            changes.append(float(np.abs(pixels - clean).mean()))
        assert 0 < changes[0] < changes[1] < changes[2], (name, changes)


def test_draws_depend_on_the_frame_and_the_seed_only():
    pytest.importorskip("albumentations")
    noise = SampleCorruption("gaussian_noise", 2, seed=0)
    image = np.full((20, 30, 3), 128, np.uint8)
    first = noise.image(image, "token-a", "CAM_FRONT")
    assert not np.array_equal(first, noise.image(image, "token-b", "CAM_FRONT"))
    assert not np.array_equal(first, SampleCorruption("gaussian_noise", 2, seed=1).image(image, "token-a", "CAM_FRONT"))
    np.testing.assert_array_equal(first, SampleCorruption("gaussian_noise", 2, seed=0).image(image, "token-a",
                                                                                           "CAM_FRONT"))
    drop = SampleCorruption("missing_cameras", 2)
    assert len(drop.failed_cameras("token-a", CAMERAS + ("CAM_BACK_LEFT", "CAM_BACK_RIGHT", "CAM_FRONT_RIGHT"))) == 3


def test_the_docs_name_every_corruption_with_its_parameters_per_level():
    from pathlib import Path

    text = (Path(__file__).parents[1] / "docs" / "robustness.md").read_text()
    rows: dict[str, str] = {}  # the first row of each name: the corruption table's (the comparison's come after)
    for line in text.splitlines():
        if line.startswith("| `"):
            rows.setdefault(line.split("|")[1].strip(), line)
    for name, corruption in CORRUPTIONS.items():
        assert f"`{name}`" in rows, name
        if name == "missing_camera":
            assert all(f"{i}: `{camera}`" in text for i, camera in enumerate(corruption.labels, 1))
            continue
        for label, params in zip(corruption.labels, corruption.levels, strict=True):
            assert label in rows[f"`{name}`"], (name, label)
            for key, value in params.items():
                assert f"`{key}={value}`" in rows[f"`{name}`"], (name, key, value)


# ------------------------------------------------------------------------------------------------------ cameras
def test_failed_cameras_are_black_and_masked(world):
    clean = _dataset(world)[1]
    sample = _dataset(world, "missing_camera", 2)[1]  # CAM_FRONT
    assert sample.camera_mask.tolist() == [True, False, True]
    assert sample.images[1].abs().max() == 0
    torch.testing.assert_close(sample.images[[0, 2]], clean.images[[0, 2]], rtol=0, atol=0)
    assert not _dataset(world, "no_cameras")[1].camera_mask.any()


@pytest.mark.parametrize("entry", ["flashocc_tiny", "da_occ_tiny", "daocc_tiny"])
def test_a_missing_cameras_features_never_reach_the_bev(world, entry):
    """Whatever the failed camera's image holds, the prediction is bitwise the same; a working camera's does
    change it (so the comparison can fail)."""
    experiment = zoo.experiment(entry)
    config = dataclasses.replace(experiment.data, root=str(world), split="all", cameras=CAMERAS, augment=False,
                                 history=0, depth_downsample=0, corruption="missing_camera", corruption_severity=2)
    batch = collate([OccupancyDataset(config)[2]])
    torch.manual_seed(0)
    model = zoo.build_from_config(experiment.architecture, experiment.model).eval()

    def logits(images):
        with torch.no_grad():
            return model(dataclasses.replace(batch, images=images)).occupancy

    reference = logits(batch.images)
    for camera, expect_change in ((1, False), (0, True)):
        noisy = batch.images.clone()
        noisy[0, camera] = torch.randn_like(noisy[0, camera]) * 3
        changed = not torch.equal(logits(noisy), reference)
        assert changed == expect_change, (entry, camera)


# -------------------------------------------------------------------------------------------------------- LiDAR
def test_beam_reduction_keeps_every_kth_ring(world):
    record = _dataset(world).records[1]
    raw = read_points(world / record.lidar_path, record.token)
    rings = np.round(raw[:, 4]).astype(int)
    assert set(rings) == set(range(32))
    for severity, every in ((1, 2), (2, 4), (3, 8)):
        kept = SampleCorruption("lidar_beams", severity).points(torch.from_numpy(raw.copy()), record.token, 0,
                                                                record.lidar2ego)  # fmt: skip
        kept_rings = set(np.round(kept[:, 4].numpy()).astype(int))
        assert kept_rings == set(range(0, 32, every)) and len(kept_rings) == 32 // every
        assert len(kept) == int((rings % every == 0).sum())
        # Through the dataset: the key frame's points (time lag 0) are exactly those rows.
        sample = _dataset(world, "lidar_beams", severity, sweeps=0)[1]
        assert len(sample.points) == len(kept)


def test_point_dropout_fov_sweeps_and_no_lidar(world):
    clean = _dataset(world)[1]
    lags = clean.points[:, 4]
    assert (lags > 0).any()
    half = _dataset(world, "point_dropout", 2)[1]
    assert abs(len(half.points) - len(clean.points) / 2) <= 10  # round(0.5 * P) of every sweep kept
    assert len(torch.unique(_dataset(world, "fewer_sweeps", 1)[2].points[:, 4])) == 1 + 4  # 9 sweeps -> 4
    key_only = _dataset(world, "fewer_sweeps", 3)[1]
    assert len(key_only.points) == int((lags == 0).sum()) and (key_only.points[:, 4] == 0).all()
    # 60 degrees around the ego's heading, each sweep in its own frame (the key frame's here).
    narrow = _dataset(world, "lidar_fov", 3, sweeps=0)[1]
    lidar2ego = torch.tensor(np.asarray(_dataset(world).records[1].lidar2ego), dtype=torch.float32)
    ego = narrow.points[:, :3] @ lidar2ego[:3, :3].T
    azimuth = torch.rad2deg(torch.atan2(ego[:, 1], ego[:, 0]))
    assert len(narrow.points) > 0 and azimuth.abs().max() <= 30 + 1e-3
    assert len(narrow.points) < (lags == 0).sum() / 4
    empty = _dataset(world, "no_lidar")[1]
    assert empty.points.shape == (0, 5)


def test_a_delayed_lidar_hands_the_older_sweep_in_as_the_key_frame(world):
    record = _dataset(world, "lidar_delay", 2).records[2]
    stand_in = record.sweeps[1]  # two sweeps (100 ms) before the key frame
    sample = _dataset(world, "lidar_delay", 2, sweeps=0)[2]
    raw = read_points(world / stand_in.path, record.token)
    np.testing.assert_array_equal(sample.points[:, :4].numpy(), raw[:, :4])  # in its own frame, as if current
    assert (sample.points[:, 4] == 0).all()
    full = _dataset(world, "lidar_delay", 2)[2]
    assert full.points[:, 4].max() == pytest.approx(record.sweeps[10].time_lag - stand_in.time_lag, abs=1e-6)


# ----------------------------------------------------------------------------------------------------- geometry
def test_extrinsic_noise_moves_projected_points_by_the_expected_pixels(world):
    clean = _dataset(world)[1]
    for severity in CORRUPTIONS["camera_extrinsics"].severities:
        params = CORRUPTIONS["camera_extrinsics"].levels[severity - 1]
        sample = _dataset(world, "camera_extrinsics", severity)[1]
        for camera in range(len(CAMERAS)):
            true, told = clean.cam2ego[camera].double(), sample.cam2ego[camera].double()
            delta = torch.linalg.inv(true) @ told
            angle = math.degrees(math.acos(min(1.0, (torch.trace(delta[:3, :3]).item() - 1) / 2)))
            assert angle == pytest.approx(params["degrees"], abs=1e-3)
            assert delta[:3, 3].norm().item() == pytest.approx(params["metres"], abs=1e-5)
            # A point far along the optical axis lands at the principal point under the true extrinsics; told the
            # wrong ones, the model looks for it f * tan(phi) pixels away, phi the angle the axis turned by.
            intrinsics = clean.intrinsics[camera].double()
            far = (true @ torch.tensor([0.0, 0.0, 1e5, 1.0], dtype=torch.float64))[:3]
            uv_true = project_points(far[None], torch.linalg.inv(true), intrinsics, None, (198, 352))[0][0]
            uv_told = project_points(far[None], torch.linalg.inv(told), intrinsics, None, (198, 352))[0][0]
            axis = delta[:3, :3].T @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
            phi = math.acos(axis[2].item())
            focal = intrinsics[0, 0].item()
            assert intrinsics[1, 1].item() == pytest.approx(focal)
            torch.testing.assert_close(uv_true, intrinsics[:2, 2], rtol=0, atol=1e-6)
            assert (uv_told - uv_true).norm().item() == pytest.approx(focal * math.tan(phi), rel=1e-3, abs=0.01)


# ----------------------------------------------------------------------------------------------------- temporal
def test_a_dropped_history_is_forgotten_by_the_stream(world, tmp_path, monkeypatch):
    """history_dropped at 100%: every frame is predicted with an empty memory, as if it opened its scene; clean, the
    later frames of the scene find the earlier ones in it."""
    from occkit.metrics.evaluate import read_prediction

    experiment = zoo.experiment("da_occ_tiny_temporal")
    config = dataclasses.replace(experiment.data, root=str(world), split="all", cameras=CAMERAS, augment=False,
                                 history=0, depth_downsample=0, image_aug=ImageAugConfig(final_size=(128, 352)))
    torch.manual_seed(0)
    model = zoo.build_from_config(experiment.architecture, experiment.model).eval()
    remembered: list[bool] = []  # per predicted frame: whether the memory held an earlier frame
    predict = model.predict

    def spying_predict(batch, memory=None):
        remembered.append(memory.states is not None and bool(memory.filled.any()))
        return predict(batch, memory=memory)

    monkeypatch.setattr(model, "predict", spying_predict)
    dropped = OccupancyDataset(dataclasses.replace(config, corruption="history_dropped", corruption_severity=3))
    (tmp_path / "dropped").mkdir()
    evaluate_model(model, dropped, predictions=tmp_path / "dropped")
    assert remembered == [False, False, False]
    remembered.clear()
    evaluate_model(model, OccupancyDataset(config))
    assert remembered == [False, True, True]
    for index, record in enumerate(dropped.records):
        expected = predict(collate([dropped[index]]), memory=model.stream()).semantics[0].numpy()
        np.testing.assert_array_equal(read_prediction(tmp_path / "dropped" / f"{record.token}.npz"), expected)


# -------------------------------------------------------------------------------------------------------- suites
def test_suites_parse_names_levels_and_labels():
    assert len(SUITES["default"]) == sum(len(c.levels) for c in CORRUPTIONS.values())
    assert parse_suite("quick") == SUITES["quick"]
    assert parse_suite("fog, missing_camera:CAM_FRONT,fog:2") == (Case("fog", 1), Case("fog", 2), Case("fog", 3),
                                                                   Case("missing_camera", 2))  # fmt: skip
    with pytest.raises(ValueError, match="'rain' is neither a suite"):
        parse_suite("fog,rain")
    with pytest.raises(ValueError, match=r"lidar_beams has levels 1 \(16 beams\), 2 \(8 beams\), 3 \(4 beams\)"):
        parse_suite("lidar_beams:32 beams")
    camera_only = model_inputs(cameras=True, lidar=False, temporal=False)
    assert not_applicable(Case("fog", 1), camera_only) is None
    assert not_applicable(Case("no_lidar", 1), camera_only) == "needs a model that takes cameras and lidar"
    assert not_applicable(Case("history_dropped", 1), camera_only) == "needs a model that takes temporal"


def test_resilience_and_corruption_error_follow_robobev():
    clean = {"miou": 0.4, "iou": 0.8, "rayiou": None}
    levels = [{"miou": 0.3, "iou": 0.6, "rayiou": None}, {"miou": 0.2, "iou": 0.4, "rayiou": None}]
    rr = resilience(levels, clean)
    assert rr["miou"] == pytest.approx((0.3 + 0.2) / (2 * 0.4)) and rr["iou"] == pytest.approx(0.625)
    assert rr["rayiou"] is None
    baseline = [{"miou": 0.1, "iou": 0.5, "rayiou": None}, {"miou": 0.0, "iou": 0.5, "rayiou": None}]
    ce = corruption_error(levels, baseline)
    assert ce["miou"] == pytest.approx((0.7 + 0.8) / (0.9 + 1.0)) and ce["iou"] == pytest.approx(1.0)
    ours = [{"name": "fog", "levels": [dict(level, severity=i + 1) for i, level in enumerate(levels)]},
            {"name": "jpeg", "levels": [dict(levels[0], severity=1)]}]
    theirs = {"corruptions": [{"name": "fog", "levels": [dict(level, severity=i + 1)
                                                         for i, level in enumerate(baseline)]}]}  # fmt: skip
    summary = score_summary(ours, clean, theirs)
    assert summary["mce"]["miou"] == pytest.approx(ce["miou"]) and summary["mce_corruptions"] == ["fog"]
    assert summary["mrr"]["miou"] == pytest.approx((rr["miou"] + 0.3 / 0.4) / 2)
    assert ours[1]["ce"] is None


# ---------------------------------------------------------------------------------------------- occkit robustness
def _checkpoint(world, path, entry="daocc_tiny", seed=0, image_aug=IMAGE_AUG):
    experiment = zoo.experiment(entry)
    experiment = dataclasses.replace(experiment, data=dataclasses.replace(
        experiment.data, root=str(world), split="all", cameras=CAMERAS, image_aug=image_aug))
    experiment = dataclasses.replace(experiment, train=dataclasses.replace(experiment.train, val_split="all"))
    torch.manual_seed(seed)
    model = zoo.build_from_config(experiment.architecture, experiment.model)
    atomic_save({"format": FORMAT, "architecture": experiment.architecture, "experiment": experiment.to_dict(),
                 "model": model.state_dict()}, path)  # fmt: skip
    return path


def test_robustness_writes_its_report_and_resumes_from_the_finished_cases(world, tmp_path, capsys):
    from occkit.cli import main

    checkpoint = _checkpoint(world, tmp_path / "model.pt")
    out = tmp_path / "robustness"
    suite = "lidar_beams:2,lidar_beams:3,missing_camera:CAM_FRONT,history_dropped"
    lines: list[str] = []
    first = run_robustness(checkpoint, out, suite=suite, rayiou=False, workers=0, log=lines.append)
    assert [c["name"] for c in first["corruptions"]] == ["missing_camera", "lidar_beams"]
    assert first["not_applicable"] == [{"name": "history_dropped", "levels": [1, 2, 3],
                                        "reason": "needs a model that takes temporal"}]  # fmt: skip
    assert "not applicable (needs a model that takes temporal): history_dropped" in lines
    assert first["frames"] == 3 and not any(level["cached"] for c in first["corruptions"] for level in c["levels"])
    for name in ("robustness.json", "robustness.md", "resilience.png", "severity.png"):
        assert (out / name).is_file(), name
    assert sorted(p.name for p in (out / "cases").iterdir()) == ["clean.json", "lidar_beams-2.json",
                                                                 "lidar_beams-3.json", "missing_camera-2.json"]
    beams = first["corruptions"][1]
    mean = np.mean([level["miou"] for level in beams["levels"]])
    assert beams["rr"]["miou"] == pytest.approx(mean / first["clean"]["miou"])
    assert "| `lidar_beams` | lidar |" in (out / "robustness.md").read_text()

    (tmp_path / "robustness.json").write_text((out / "robustness.json").read_text())  # the baseline, below

    # A case lost mid-run (its file never written) is computed again; the others come from the cache.
    (out / "cases" / "lidar_beams-3.json").unlink()
    lines.clear()
    second = run_robustness(checkpoint, out, suite=suite, rayiou=False, workers=0, log=lines.append)
    cached = {level["label"]: level["cached"] for c in second["corruptions"] for level in c["levels"]}
    assert cached == {"CAM_FRONT": True, "8 beams": True, "4 beams": False}
    assert sum("(cached" in line for line in lines) == 3  # clean, CAM_FRONT, 8 beams
    assert second["corruptions"][1]["levels"][1]["miou"] == first["corruptions"][1]["levels"][1]["miou"]

    # Other weights: nothing is reused. The baseline adds CE.
    other = _checkpoint(world, tmp_path / "other.pt", seed=1)
    lines.clear()
    third = run_robustness(other, out, suite="lidar_beams:2,lidar_beams:3", rayiou=False, workers=0, log=lines.append,
                           baseline=tmp_path / "robustness.json")  # fmt: skip
    assert not any("cached" in line for line in lines)
    assert third["mce"] is not None and third["mce_corruptions"] == ["lidar_beams"]

    # The command: one line per case, the table, the files; a bad suite is a usage error.
    assert main(["robustness", "--ckpt", str(checkpoint), "--out", str(tmp_path / "cli"), "--suite",
                 "missing_camera:CAM_BACK", "--no-rayiou", "--workers", "0", "--device", "cpu"]) == 0  # fmt: skip
    printed = capsys.readouterr()
    assert "missing_camera CAM_BACK: mIoU" in printed.out and "| `missing_camera` | cameras |" in printed.out
    assert json.loads((tmp_path / "cli" / "robustness.json").read_text())["suite"] == "missing_camera:CAM_BACK"
    assert not (tmp_path / "cli" / "severity.png").exists()  # the cameras are variants, not severities
    assert main(["robustness", "--ckpt", str(checkpoint), "--out", str(tmp_path / "x"), "--suite", "rain"]) == 2
    assert "'rain' is neither a suite" in capsys.readouterr().err
    assert main(["robustness", "--list"]) == 0
    assert "lidar_beams (lidar; needs lidar)" in capsys.readouterr().out


# ------------------------------------------------------------------------------------------------------ the cache
def _rewrite_keeping_size_and_time(path, change):
    """Change a file's bytes in place (``change(bytes) -> bytes`` of the same length), then give it back its
    modification time: what ``cp -p`` or ``rsync -a`` of another version of the file leaves."""
    stat = path.stat()
    data = path.read_bytes()
    changed = change(data)
    assert len(changed) == len(data) and changed != data
    path.write_bytes(changed)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size and path.stat().st_mtime_ns == stat.st_mtime_ns


def _uncompressed_labels(labels_file, free=False):
    """The bytes of ``labels_file`` (an Occ3D labels.npz) stored uncompressed: their size is the grid's whatever
    the classes; with ``free``, every voxel is free space."""
    with np.load(labels_file) as arrays:
        content = {name: arrays[name] for name in arrays.files}
    if free:
        content["semantics"] = np.full_like(content["semantics"], OCC3D_SPACE.free_index)
    buffer = io.BytesIO()
    np.savez(buffer, **content)
    return buffer.getvalue()


def test_the_cache_misses_when_any_input_of_a_case_changes(world, tmp_path, monkeypatch):
    """Each input a case's scores depend on is changed in turn, the others kept: every change is a miss, and the
    unchanged inputs are a hit (so a miss is not a broken key)."""
    from occkit.robustness import cache

    labels = tmp_path / "gts"
    shutil.copytree(world / "gts", labels)
    labels_file = sorted(labels.rglob("labels.npz"))[1]
    labels_file.write_bytes(_uncompressed_labels(labels_file))
    checkpoint = _checkpoint(world, tmp_path / "model.pt")

    def dataset(**changes):
        return _dataset(world, **{"label_root": str(labels), **changes})

    beams = Case("lidar_beams", 2)

    def key(case=beams, data=None, seed=0, rayiou=False):
        return cache.case_fingerprint(cache.cache_context(checkpoint, data or dataset(), seed, rayiou), case)

    path = tmp_path / "case.json"
    cache.write_case(path, key(), {"miou": 0.16, "iou": 0.5, "seconds": 3.0})
    assert cache.read_cached(path, key()) == {"miou": 0.16, "iou": 0.5, "seconds": 3.0}

    changes = {
        "the severity": lambda: key(case=Case("lidar_beams", 3)),
        "the case": lambda: key(case=Case("point_dropout", 2)),
        "the seed": lambda: key(seed=1),
        "the metrics (RayIoU)": lambda: key(rayiou=True),
        "the data settings": lambda: key(data=dataset(sweeps=4)),
        "the image transform": lambda: key(data=dataset(image_aug=ImageAugConfig(final_size=(128, 352)))),
        "the split": lambda: key(data=dataset(split="train")),  # the world's one scene: the same frames as "all"
    }
    for what, changed_key in changes.items():
        assert cache.read_cached(path, changed_key()) is None, what

    # The occkit version, the checkpoint's bytes (same path) and the labels' content (same size and time).
    monkeypatch.setattr(cache, "__version__", "0.0.0+other")
    assert cache.read_cached(path, key()) is None, "the occkit version"
    monkeypatch.undo()
    assert cache.read_cached(path, key()) is not None
    _checkpoint(world, checkpoint, seed=1)
    assert cache.read_cached(path, key()) is None, "the checkpoint"
    cache.write_case(path, key(), {"miou": 0.16, "iou": 0.5, "seconds": 3.0})
    _rewrite_keeping_size_and_time(labels_file, lambda _: _uncompressed_labels(labels_file, free=True))
    assert cache.read_cached(path, key()) is None, "the ground truth"


def test_a_changed_ground_truth_is_scored_again_not_taken_from_the_cache(world, tmp_path):
    """The probe's case: gts/ replaced after a run; the rerun printed the old mIoU as cached."""
    data = tmp_path / "data"
    shutil.copytree(world, data)
    for labels_file in data.glob("gts/*/*/labels.npz"):
        labels_file.write_bytes(_uncompressed_labels(labels_file))
    checkpoint = _checkpoint(world, tmp_path / "model.pt")
    out = tmp_path / "robustness"
    first = run_robustness(checkpoint, out, data=data, suite="no_lidar", rayiou=False, workers=0, log=print)
    assert first["clean"]["miou"] > 0
    for labels_file in data.glob("gts/*/*/labels.npz"):  # every frame is free space now
        _rewrite_keeping_size_and_time(labels_file, lambda _, f=labels_file: _uncompressed_labels(f, free=True))
    lines: list[str] = []
    second = run_robustness(checkpoint, out, data=data, suite="no_lidar", rayiou=False, workers=0, log=lines.append)
    assert not any("cached" in line for line in lines), lines
    assert not second["clean"]["cached"] and second["clean"]["miou"] != first["clean"]["miou"]


def test_a_cached_case_file_of_another_shape_is_computed_again(tmp_path):
    from occkit.robustness import cache

    path = tmp_path / "clean.json"
    for text in ("[]", '{"fingerprint": {}, "result": []}', '{"fingerprint": {}}', "not json"):
        path.write_text(text)
        assert cache.read_cached(path, {}) is None, text


def test_a_folder_where_a_case_file_goes_is_one_error_line_before_any_work(world, tmp_path, capsys, monkeypatch):
    from occkit.cli import main
    from occkit.model_source import ModelSource

    monkeypatch.setattr(ModelSource, "load", lambda *_: pytest.fail("the paths are checked before the model loads"))
    checkpoint = _checkpoint(world, tmp_path / "model.pt")
    out = tmp_path / "robustness"
    command = ["robustness", "--ckpt", str(checkpoint), "--out", str(out), "--suite", "fog:2", "--no-rayiou",
               "--workers", "0", "--device", "cpu"]  # fmt: skip
    blockers = {out / "cases" / "fog-2.json": "is a folder, where occkit robustness writes the scores of case fog",
                out / "robustness.md": "is not a file, where occkit robustness writes its robustness.md"}
    for blocker, message in blockers.items():
        blocker.mkdir(parents=True)
        assert main(command) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"occkit robustness: error: {blocker} {message}" in err, err
        assert "choose another --out" in err
        blocker.rmdir()
    (out / "cases").rmdir()
    (out / "cases").write_text("")
    assert main(command) == 2
    assert f"{out / 'cases'} is a file where occkit robustness keeps its per-case cache" in capsys.readouterr().err


# -------------------------------------------------------------------------------------------------- applicability
@pytest.mark.parametrize(("entry", "inputs"), [
    ("flashocc_tiny", {"cameras"}),
    ("da_occ_tiny", {"cameras"}),  # LiDAR is loaded in training as the depth target only
    ("da_occ_tiny_temporal", {"cameras", "temporal"}),
    ("daocc_tiny", {"cameras", "lidar"}),
])  # fmt: skip
def test_what_a_model_takes_is_what_its_forward_reads_not_what_its_data_loads(entry, inputs):
    from occkit.robustness.run import inference_inputs

    experiment = zoo.experiment(entry)
    model = zoo.build_from_config(experiment.architecture, experiment.model)
    assert inference_inputs(model, experiment.model) == inputs


def test_lidar_cases_are_not_applicable_to_camera_only_da_occ_and_stay_out_of_mrr(world, tmp_path):
    checkpoint = _checkpoint(world, tmp_path / "da_occ.pt", entry="da_occ_tiny",
                             image_aug=ImageAugConfig(final_size=(128, 352)))
    assert zoo.experiment("da_occ_tiny").data.sweeps >= 0  # its data loads LiDAR (the depth target)
    report = run_robustness(checkpoint, tmp_path / "out", suite="lidar_beams:2,no_lidar,no_cameras,missing_camera:2",
                            rayiou=False, workers=0, log=lambda _: None)  # fmt: skip
    assert report["inputs"] == ["cameras"]
    assert [c["name"] for c in report["corruptions"]] == ["missing_camera"]
    assert {item["name"]: item["reason"] for item in report["not_applicable"]} == {
        "lidar_beams": "needs a model that takes lidar",
        "no_lidar": "needs a model that takes cameras and lidar",
        "no_cameras": "needs a model that takes cameras and lidar",
    }
    assert report["mrr"]["miou"] == pytest.approx(report["corruptions"][0]["rr"]["miou"])
    assert "Not applicable to this model: `lidar_beams`" in (tmp_path / "out" / "robustness.md").read_text()
