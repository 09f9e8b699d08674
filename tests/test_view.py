"""occkit view and occkit.viz.recording: recordings read back with rerun's own reader and counted against the files."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from occkit.classes import OCC3D
from occkit.cli import main
from occkit.nuscenes import CAMERAS

FREE, IGNORE = OCC3D.empty_index, OCC3D.ignore_index
ROAD, OTHER_FLAT, CAR = OCC3D.index("driveable_surface"), OCC3D.index("other_flat"), OCC3D.index("car")
EGO = "/world/ego"

needs_rerun = pytest.mark.skipif(importlib.util.find_spec("rerun") is None, reason='needs pip install -e ".[viewer]"')


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """One scene of 2 key frames, the six cameras at 176 x 99: scene-0001, the train split."""
    from occkit.sim.generate import SimConfig, simulate_dataset

    root = tmp_path_factory.mktemp("view") / "data"
    simulate_dataset(SimConfig(scenes=1, frames=2, seed=3, image_size=(176, 99)), root)
    return root


def _scene_labels(root: Path) -> dict[str, dict[str, np.ndarray]]:
    """token -> the label file's ``semantics`` and ``mask_camera``, for the scene's frames in time order."""
    from occkit.data.dataset import DatasetConfig, OccupancyDataset

    listing = OccupancyDataset(DatasetConfig(root=str(root), split="train", cameras=(), sweeps=-1, boxes=False))
    frames = {}
    for record in sorted(listing.records, key=lambda record: record.index_in_scene):
        with np.load(listing.label_path(record)) as labels:
            frames[record.token] = {"semantics": labels["semantics"], "mask_camera": labels["mask_camera"].astype(bool)}
    return frames


def _read(path: Path) -> dict[str, dict[str, dict[int, pa.ListScalar]]]:
    """entity -> component column -> frame -> the logged values (an Arrow list: ``len``, ``.values``, ``.as_py()``),
    read back from the recording file."""
    from rerun.chunk import RrdReader

    found: dict = defaultdict(lambda: defaultdict(dict))
    for chunk in RrdReader(path).stream().to_chunks():
        table = chunk.to_record_batch()
        if "frame" not in table.schema.names:  # static data
            continue
        frames = table.column("frame").to_pylist()
        for name in table.schema.names:
            if ":" in name:  # a component column, "Archetype:field"
                for row, frame in enumerate(frames):
                    found[chunk.entity_path][name][frame] = table.column(name)[row]
    return dict(found)


def _occupied(semantics: np.ndarray, mask: np.ndarray | None = None) -> int:
    keep = (semantics != FREE) & (semantics != IGNORE)
    return int(np.count_nonzero(keep if mask is None else keep & mask))


def _write_predictions(labels: dict, folder: Path) -> dict[str, dict[str, int]]:
    """Predictions that are the ground truth with known changes; returns each frame's error counts.

    Per frame: the road becomes other_flat (wrong class), the first car voxel of the camera mask becomes free
    (missed) and its first free voxel a car (false positive)."""
    from occkit.metrics.evaluate import write_prediction

    folder.mkdir()
    expected = {}
    for token, frame in labels.items():
        semantics, mask = frame["semantics"].copy(), frame["mask_camera"]
        semantics[semantics == ROAD] = OTHER_FLAT
        semantics[tuple(np.argwhere((semantics == CAR) & mask)[0])] = FREE
        semantics[tuple(np.argwhere((frame["semantics"] == FREE) & mask)[0])] = CAR
        write_prediction(folder, token, semantics)
        wrong = int(np.count_nonzero((frame["semantics"] == ROAD) & mask))
        expected[token] = {"wrong_class": wrong, "missed": 1, "false_positive": 1}
    return expected


@needs_rerun
def test_the_recording_holds_every_layer_counted_as_the_files(data, tmp_path, capsys):
    from occkit.viz.recording import ERRORS

    labels = _scene_labels(data)
    errors = _write_predictions(labels, tmp_path / "pred")
    path = tmp_path / "view" / "scene.rrd"
    assert main(["view", "--data", str(data), "--split", "train", "--pred", str(tmp_path / "pred"), "--save",
                 str(path)]) == 0  # fmt: skip
    assert f"wrote 2 frames of scene-0001 to {path}" in capsys.readouterr().out
    found = _read(path)
    cameras = [f"{EGO}/cameras/{camera}" for camera in CAMERAS]
    layers = {role: f"{EGO}/occupancy/{role}" for role in ("gt", "gt_camera", "prediction", "prediction_camera",
                                                            "errors")}  # fmt: skip
    entities = [EGO, f"{EGO}/lidar", f"{EGO}/lidar/points", f"{EGO}/lidar/boxes", f"{EGO}/occupancy", *cameras,
                *layers.values(), "/scores/miou", "/scores/iou"]  # fmt: skip
    assert set(entities) <= set(found)
    for frame, (token, truth) in enumerate(labels.items()):
        semantics, mask = truth["semantics"], truth["mask_camera"]
        voxels = {role: len(found[entity]["Boxes3D:centers"][frame]) for role, entity in layers.items()}
        assert voxels["gt"] == _occupied(semantics) and voxels["gt_camera"] == _occupied(semantics, mask)
        # One car voxel freed, one free voxel filled: as many occupied voxels as in the ground truth.
        assert voxels["prediction"] == voxels["gt"] and voxels["prediction_camera"] == voxels["gt_camera"]
        codes = found[layers["errors"]]["Boxes3D:class_ids"][frame].values.to_numpy()
        assert {name: int(np.count_nonzero(codes == code)) for name, code in ERRORS.items()} == errors[token]
        assert voxels["errors"] == sum(errors[token].values())
        classes = found[layers["gt_camera"]]["Boxes3D:class_ids"][frame].values.to_numpy()
        assert np.array_equal(np.sort(classes), np.sort(semantics[(semantics != FREE) & mask]))
        for camera in cameras:  # one image per camera and frame, with its pinhole
            logged = found[camera]
            assert len(logged["EncodedImage:blob"][frame]) == len(logged["Pinhole:image_from_camera"][frame]) == 1
        assert len(found[f"{EGO}/lidar/points"]["Points3D:positions"][frame]) > 1000
        assert 0.0 <= found["/scores/miou"]["Scalars:scalars"][frame].as_py()[0] < 1.0


@needs_rerun
def test_a_batch_logs_without_image_files_as_the_network_sees_it(data, tmp_path):
    from occkit.data.collate import collate
    from occkit.data.dataset import DatasetConfig, OccupancyDataset
    from occkit.viz.recording import log_batch, log_prediction, log_setup, new_recording, set_frame

    dataset = OccupancyDataset(DatasetConfig(root=str(data), sweeps=0))
    batch = collate([dataset[0], dataset[1]])
    recording = new_recording()
    path = tmp_path / "batch.rrd"
    recording.save(path)
    log_setup(recording=recording)
    set_frame(0, recording=recording)
    counts = log_batch(batch, 1, recording=recording)
    semantics, mask = batch.voxel_semantics[1], batch.mask_camera[1]
    errors = log_prediction(semantics, semantics, mask, recording=recording)
    recording.disconnect()
    with np.load(dataset.label_path(dataset.records[1])) as labels:
        assert counts["gt"] == _occupied(labels["semantics"])
    found = _read(path)
    # A perfect prediction: an empty error layer, without the half size that would draw a box at the origin.
    assert errors["wrong_class"] == errors["missed"] == errors["false_positive"] == 0
    assert len(found[f"{EGO}/occupancy/errors"]["Boxes3D:half_sizes"][0]) == 0
    assert counts["images"] == 0 and len(found[f"{EGO}/occupancy/gt"]["Boxes3D:centers"][0]) == counts["gt"]
    camera = found[f"{EGO}/cameras/CAM_FRONT"]
    # Without image files a camera is the pinhole of the augmented image the network sees.
    assert "EncodedImage:blob" not in camera
    assert camera["Pinhole:resolution"][0].as_py() == [[batch.images.shape[-1], batch.images.shape[-2]]]


def _small_checkpoint(folder: Path) -> Path:
    """A freshly initialised FlashOcc, small enough to predict a frame in a second."""
    import torch

    from occkit import zoo
    from occkit.engine.checkpoint import FORMAT, atomic_save
    from occkit.zoo import experiment_from_dict

    overrides = ["data.image_aug.final_size=[64, 176]", "model.lss.image_size=[64, 176]", "model.image.out_stages=[3]",
                 "model.bev.channels=[16, 32, 64]", "model.bev.neck_channels=16", "model.occupancy.in_channels=16",
                 "model.occupancy.hidden_channels=16"]  # fmt: skip
    experiment = experiment_from_dict(zoo.experiment("flashocc_tiny").to_dict(), "test", overrides)
    torch.manual_seed(0)
    model = zoo.build_from_config(experiment.architecture, experiment.model)
    folder.mkdir()
    return atomic_save({"format": FORMAT, "architecture": experiment.architecture, "experiment": experiment.to_dict(),
                        "model": model.state_dict(), "ema": None}, folder / "model.pt")  # fmt: skip


@needs_rerun
def test_a_checkpoint_predicts_the_frames_in_order(data, tmp_path):
    checkpoint = _small_checkpoint(tmp_path / "run")
    path = tmp_path / "ckpt.rrd"
    assert main(["view", "--data", str(data), "--split", "train", "--ckpt", str(checkpoint), "--frames", "1", "--save",
                 str(path)]) == 0  # fmt: skip
    found = _read(path)
    assert set(found[f"{EGO}/occupancy/prediction"]["Boxes3D:centers"]) == {0}
    assert f"{EGO}/occupancy/errors" in found


def test_an_unknown_scene_is_one_line_naming_the_scenes(data, tmp_path, capsys):
    pytest.importorskip("rerun")
    argv = ["view", "--data", str(data), "--split", "train", "--scene", "scene-0002", "--save", str(tmp_path / "x.rrd")]
    assert main(argv) == 2
    error = capsys.readouterr().err
    assert error.startswith("occkit view: error:") and error.count("\n") == 1
    assert "no scene 'scene-0002' in v1.0-synth (in no split)" in error and "its scenes: scene-0001" in error
    assert not (tmp_path / "x.rrd").exists()


@needs_rerun
def test_a_named_scene_is_found_in_any_split(data, tmp_path, capsys):
    """The world's one scene is in train; --split is left at val (which has no scene here): the name finds it, with
    the dataset and the checkpoint's predictions of that scene."""
    path = tmp_path / "scene.rrd"
    assert main(["view", "--data", str(data), "--scene", "scene-0001", "--frames", "1", "--save", str(path)]) == 0
    assert f"wrote 1 frames of scene-0001 to {path}" in capsys.readouterr().out
    checkpoint = _small_checkpoint(tmp_path / "run")
    assert main(["view", "--data", str(data), "--scene", "scene-0001", "--ckpt", str(checkpoint), "--frames", "1",
                 "--save", str(path)]) == 0  # fmt: skip
    assert set(_read(path)[f"{EGO}/occupancy/prediction"]["Boxes3D:centers"]) == {0}


@pytest.mark.parametrize(("arguments", "message"), [(["--save", "{tmp}/x.txt"], "must be a .rrd file"),
                                                    (["--pred", "{tmp}/none"], "--pred "),
                                                    (["--data", "{tmp}/none"], "--data ")])  # fmt: skip
def test_options_are_checked_before_any_work(data, tmp_path, capsys, arguments, message):
    options = {"--data": str(data), "--split": "train", "--save": str(tmp_path / "x.rrd")}
    options |= dict(zip(arguments[::2], [a.format(tmp=tmp_path) for a in arguments[1::2]], strict=True))
    assert main(["view", *[part for item in options.items() for part in item]]) == 2
    error = capsys.readouterr().err
    assert message in error and error.count("\n") == 1


def test_without_rerun_the_command_names_the_extra(data, tmp_path, capsys, monkeypatch):
    loaded = [name for name in sys.modules if name.split(".")[0] == "rerun" or name == "occkit.viz.recording"]
    for name in loaded:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` fails as if it were not installed
    assert main(["view", "--data", str(data), "--split", "train", "--save", str(tmp_path / "x.rrd")]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and 'pip install -e ".[viewer]"' in error


def test_importing_occkit_imports_no_rerun():
    code = "import sys, occkit, occkit.cli, occkit.viz; print('rerun' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_serve_refuses_a_taken_port_before_rerun_torch_or_the_scene_load(data):
    """In a fresh interpreter: the one error line, and neither rerun nor torch imported by then."""
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code = ("import sys; from occkit.cli import main; "
                f"code = main(['view', '--data', {str(data)!r}, '--serve', '--grpc-port', '{port}']); "
                "print(code, 'rerun' in sys.modules, 'torch' in sys.modules)")  # fmt: skip
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.split() == ["2", "False", "False"]
    assert run.stderr == (f"occkit view: error: --grpc-port {port} is already in use on 127.0.0.1: choose another port "
                          "with --grpc-port\n")  # fmt: skip
    assert main(["view", "--data", str(data), "--serve", "--web-port", "9100", "--grpc-port", "9100"]) == 2
