"""``occkit label``: labels built from the synthetic world's sensor data, checked against its exact labels."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from occkit.cli import main
from occkit.data.labels import read_occ3d_labels, read_surroundocc_labels
from occkit.data.tables import load_tables
from occkit.geometry.grid import OCC3D_GRID, VoxelGrid
from occkit.labeling.aggregate import AggregateConfig, object_membership, points_in_boxes
from occkit.labeling.pipeline import SUMMARY_FILE, LabelConfig, label_dataset
from occkit.labeling.sources import Boxes, LidarsegMissingError, _slerp, plan_scenes
from occkit.labeling.voxels import vote
from occkit.sim.generate import SimConfig, simulate_dataset
from occkit.sim.scene import _child_seed
from occkit.sim.world import WorldConfig, generate_world
from occkit.sim.writer import make_token

WORLD = SimConfig(scenes=1, frames=3, seed=11, image_size=(176, 64), cameras=("CAM_FRONT", "CAM_BACK"),
                  world=WorldConfig(density=0.5))  # fmt: skip
VERSION = WORLD.version


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("label") / "data"
    simulate_dataset(WORLD, root)
    return root


@pytest.fixture(scope="module")
def labelled(world, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("label") / "labels"
    return out, label_dataset(world, VERSION, out, LabelConfig(sweeps=3))


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*.npz"))}


def _geometry_iou(out: Path, world: Path) -> float:
    """Occupied-voxel IoU of generated against exact labels, under the exact camera mask, over all key frames."""
    hit = union = 0
    for path in sorted(out.glob("*/*/labels.npz")):
        generated = read_occ3d_labels(path)
        exact = read_occ3d_labels(world / "gts" / path.relative_to(out))
        a, b = generated.semantics[exact.mask_camera] != 17, exact.semantics[exact.mask_camera] != 17
        hit, union = hit + (a & b).sum(), union + (a | b).sum()
    return hit / union


def test_labels_agree_with_the_exact_ones_and_improve_with_sweeps(world, labelled, tmp_path):
    out, summary = labelled
    files = sorted(out.glob("*/*/labels.npz"))
    assert len(files) == WORLD.frames == summary["key_frames"]
    for path in files:
        generated = read_occ3d_labels(path)
        exact = read_occ3d_labels(world / "gts" / path.relative_to(out))
        # The same sweeps are cast, so the LiDAR masks differ only where the labels disagree on what is occupied.
        assert (generated.mask_lidar == exact.mask_lidar).mean() > 0.99
        assert generated.mask_camera.any()
    # Three key frames of a sparse world: most of the geometry; docs/labels.md measures full scenes.
    with_sweeps = _geometry_iou(out, world)
    label_dataset(world, VERSION, tmp_path / "keys", LabelConfig(sweeps=0))
    assert with_sweeps > 0.45 and with_sweeps > _geometry_iou(tmp_path / "keys", world) + 0.05
    scene = summary["scenes"][0]
    assert scene["points"]["static"] > 0 and scene["points"]["objects"] > 0 and scene["instances"] > 0
    assert json.loads((out / SUMMARY_FILE).read_text())["config"]["sweeps"] == 3


def test_the_same_input_gives_byte_identical_labels(world, labelled, tmp_path):
    out, _ = labelled
    label_dataset(world, VERSION, tmp_path / "again", LabelConfig(sweeps=3))
    assert _files(tmp_path / "again") == _files(out) and _files(out)


def test_surroundocc_output_is_readable(world, tmp_path):
    out = tmp_path / "so"
    label_dataset(world, VERSION, out, LabelConfig(label_space="surroundocc", sweeps=0))
    files = sorted((out / "samples").glob("*.pcd.bin.npy"))
    assert len(files) == WORLD.frames
    labels = read_surroundocc_labels(files[0])
    assert (labels.semantics != 0).sum() > 1000


def test_a_dataset_without_lidarseg_fails_naming_what_is_missing(world, tmp_path, capsys):
    bare = tmp_path / "bare"
    shutil.copytree(world, bare, ignore=shutil.ignore_patterns("lidarseg", "lidarseg.json"))
    with pytest.raises(LidarsegMissingError, match=r"lidarseg\.json not found"):
        label_dataset(bare, VERSION, tmp_path / "out")
    assert main(["label", "--root", str(bare), "--version", VERSION, "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "lidarseg.json not found" in error[0] and "nuScenes-lidarseg" in error[0]
    assert not (tmp_path / "out").exists()


def test_cli_writes_labels_and_a_summary_per_scene(world, tmp_path, capsys):
    out = tmp_path / "cli"
    assert main(["label", "--root", str(world), "--version", VERSION, "--out", str(out), "--sweeps", "0"]) == 0
    printed = capsys.readouterr()
    assert "scene-0001: 3 key frames, 3 sweeps" in printed.err + printed.out
    assert "data.label_root=" in printed.out
    assert main(["label", "--root", str(world), "--version", VERSION, "--out", str(out), "--sweeps", "0"]) == 2
    assert "--overwrite" in capsys.readouterr().err


def test_sweep_boxes_follow_the_objects_between_key_frames(world):
    """Interpolated boxes of each sweep against the world's exact boxes at the sweep's instant."""
    tables = load_tables(world, VERSION)
    plan = plan_scenes(tables)[0]
    exact_world = generate_world(_child_seed(WORLD.seed, 0), WORLD.world_config())
    instance_id = {make_token(VERSION, WORLD.seed, plan.name, "instance", b.instance): b.instance
                   for b in exact_world.boxes(0.0)}  # fmt: skip
    offset = -np.asarray(exact_world.ground.origin[:2])  # tables are shifted so the map starts at (0, 0)
    annotated = [{a["instance_token"] for a in tables["sample_annotation"] if a["sample_token"] == k.sample_token}
                 for k in plan.key_frames]  # fmt: skip
    key_of_sweep = np.searchsorted([k.sweep for k in plan.key_frames], np.arange(len(plan.sweeps)))
    errors = []
    for j, sweep in enumerate(plan.sweeps):
        k = key_of_sweep[j]
        exact = {b.instance: b for b in exact_world.boxes((sweep.timestamp - plan.sweeps[0].timestamp) / 1e6)}
        for b, local in enumerate(sweep.boxes.instance.tolist()):
            token = plan.instances[local]
            if not sweep.key and (k == 0 or token not in annotated[k - 1]):
                continue  # annotated at the next key frame alone: the devkit keeps that box as it is
            truth = exact[instance_id[token]]
            errors.append(np.linalg.norm(sweep.boxes.center[b, :2] - (truth.center[:2] + offset)))
    # Key frames are exact; sweeps interpolate smooth tracks linearly over 0.5 s: centimetres.
    assert len(errors) > 50 and np.median(errors) < 1e-6 and max(errors) < 0.1


def test_points_in_boxes_picks_the_smallest_box_and_turns_with_it():
    yaw = math.radians(30)
    rotation = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
    boxes = Boxes(
        instance=np.array([0, 1], np.int32),
        label=np.array([4, 7], np.uint8),
        center=np.array([[10.0, 5.0, 1.0], [10.5, 5.0, 1.0]]),
        size=np.array([[2.0, 4.0, 2.0], [0.6, 0.6, 1.8]]),  # (width, length, height): a car and a pedestrian
        rotation=np.stack([rotation, np.eye(3)]),
    )
    along = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    points = np.array([
        [10.0, 5.0, 1.0] + 1.9 * along,  # within the car's length along its heading
        [10.0, 5.0, 1.0] - 2.1 * along,  # just beyond it
        [10.5, 5.0, 1.0],  # in both: the pedestrian's
        [30.0, 0.0, 0.0],
    ])  # fmt: skip
    owner, local = points_in_boxes(points, boxes)
    assert owner.tolist() == [0, -1, 1, -1]
    assert np.allclose(local[0], [1.9, 0.0, 0.0])
    assert points_in_boxes(points, boxes, scale=1.1)[0].tolist() == [0, 0, 1, -1]


def test_ground_under_a_tall_box_stays_ground():
    """A sweep point just above the ground under a bus stays static however tall the box (the clearance is measured
    from the annotated box's bottom, not the enlarged one's, which lies 0.175 m below the ground for a 3.5 m bus)."""
    bus = Boxes(instance=np.array([0], np.int32), label=np.array([3], np.uint8), center=np.array([[0.0, 0.0, 1.75]]),
                size=np.array([[2.9, 11.0, 3.5]]), rotation=np.eye(3)[None])  # fmt: skip
    points = np.array([[1.0, 0.5, 0.01], [1.0, 0.5, 0.3], [3.0, -1.0, 2.0]])
    owner, local = points_in_boxes(points, bus, 1.1)
    assert owner.tolist() == [0, 0, 0]
    assert object_membership(owner, local, bus, None, AggregateConfig()).tolist() == [False, True, True]
    # A key frame's points go by their lidarseg class instead: the ground's is not the bus's.
    classes = np.array([11, 3, 3], np.uint8)
    assert object_membership(owner, local, bus, classes, AggregateConfig()).tolist() == [False, True, True]


def test_vote_takes_the_majority_and_ties_to_the_lower_class():
    grid = VoxelGrid((0, 0, 0, 2, 2, 2), 1.0)
    points = np.array([[0.5, 0.5, 0.5]] * 3 + [[1.5, 0.5, 0.5]] * 2 + [[5.0, 5.0, 5.0]])
    labels = np.array([4, 4, 11, 16, 15, 1], np.uint8)
    semantics = vote(points, labels, grid, empty=17)
    assert semantics[0, 0, 0] == 4 and semantics[1, 0, 0] == 15
    assert (semantics == 17).sum() == 6
    assert vote(np.zeros((0, 3)), np.zeros(0, np.uint8), OCC3D_GRID, 17).min() == 17


def test_slerp_interpolates_yaw_on_the_short_arc():
    def q(yaw):
        return np.array([math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)])

    middle = _slerp(q(math.radians(170)), q(math.radians(-170)), 0.5)
    assert abs(abs(2 * math.atan2(middle[3], middle[0])) - math.pi) < 1e-9
    assert np.allclose(_slerp(q(0.2), q(0.6), 0.25), q(0.3))


def test_poisson_fills_a_hole_in_a_plane():
    pytest.importorskip("open3d")
    from occkit.labeling.voxels import DensifyConfig, densify_poisson

    grid = VoxelGrid((-8, -8, -1, 8, 8, 1), 0.4)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-9, 9, (60_000, 2))
    xy = xy[np.hypot(*xy.T) > 1.5]  # a hole of 1.5 m radius around the sensor
    points = np.concatenate((xy, np.full((len(xy), 1), 0.05)), axis=1)
    labels = np.full(len(points), 11, np.uint8)
    voted = vote(points, labels, grid, 17)
    assert (voted[19:21, 19:21, 2] == 17).all()
    # SurroundOcc trims the 10% of vertices of lowest density, which are those of the hole: keep them all here.
    dense = densify_poisson(points, labels, np.array([0.0, 0.0, 1.8]), voted, grid, 17, DensifyConfig(min_density=0))
    assert (dense[18:22, 18:22, 2] == 11).all()
    assert ((dense != 17) & (voted == 17)).sum() >= 4 and (dense[voted != 17] == voted[voted != 17]).all()
    assert (dense[:, :, 4] == 17).all()  # nothing above the plane
