"""occkit.viz: BEV orientation and colours, error maps, 3D faces, camera layout and exact projections, the CLI."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from occkit.classes import OCC3D_COLORS
from occkit.cli import main
from occkit.figure import new_figure, save_figure
from occkit.geometry.camera import image_aug_matrix
from occkit.geometry.grid import VoxelGrid
from occkit.geometry.se3 import invert_transform, make_transform, rotation_about_z
from occkit.label_space import OCC3D_SPACE
from occkit.types import Sample
from occkit.viz.bev import bev_extent, bev_figure, bev_image, top_occupied
from occkit.viz.cameras import (
    SURROUND_LAYOUT,
    CameraSet,
    camera_figure,
    lidar_camera_figure,
    lidar_points_in_ego,
    occupancy_camera_figure,
    voxel_centres_in_ego,
)
from occkit.viz.errors import (
    CORRECT,
    FALSE_POSITIVE,
    MISSED,
    NOT_EVALUATED,
    OUTCOME_COLORS,
    TRUE_FREE,
    WRONG_CLASS,
    column_outcomes,
    comparison_figure,
    error_image,
    frame_scores,
    voxel_outcomes,
)
from occkit.viz.palette import EMPTY_COLOR, UNOBSERVED_COLOR
from occkit.viz.voxels import draw_voxels, view_direction, voxel_faces

FREE, CAR, ROAD, TRUCK = 17, 4, 11, 10
#: A small grid: 8 x 6 x 4 voxels of 0.5 m, x in [-2, 2), y in [-1.5, 1.5), z in [-1, 1).
GRID = VoxelGrid((-2.0, -1.5, -1.0, 2.0, 1.5, 1.0), 0.5)
#: Occ3D's classes on that grid.
SPACE = dataclasses.replace(OCC3D_SPACE, grid=GRID)


def _labels() -> np.ndarray:
    labels = np.full(GRID.shape, FREE, dtype=np.uint8)
    labels[:, :, 0] = ROAD
    return labels


def _color(class_id: int) -> tuple[int, ...]:
    return tuple(OCC3D_COLORS[class_id])


# ------------------------------------------------------------------------------------------------------ BEV
def test_bev_puts_forward_up_and_left_on_the_left():
    labels = _labels()
    labels[6, 1, 3] = CAR  # ahead (x index 6 of 8) and to the right (y index 1 of 6: y < 0)
    image = bev_image(labels, shade=0.0)
    assert image.shape == (8, 6, 3)
    # Row 0 is the front edge (x index 7) and column 0 the left edge (y index 5).
    assert tuple(image[8 - 1 - 6, 6 - 1 - 1]) == _color(CAR)
    assert tuple(image[0, 0]) == _color(ROAD) and tuple(image[7, 5]) == _color(ROAD)
    assert (image == _color(CAR)).all(-1).sum() == 1
    # The top voxel keeps its exact palette colour under the default height shading.
    assert tuple(bev_image(labels)[1, 4]) == _color(CAR)
    # imshow extent in metres: y from +y_max on the left to y_min on the right, x from x_min up to x_max.
    assert bev_extent(GRID) == (1.5, -1.5, -2.0, 2.0)


def test_top_occupied_skips_ignored_and_masked_voxels():
    labels = _labels()
    labels[2, 2, 3] = CAR
    labels[3, 3, 2] = 255
    mask = np.ones(GRID.shape, dtype=bool)
    mask[2, 2, 3] = False
    top_class, top_z = top_occupied(labels, mask)
    assert (top_class[2, 2], top_z[2, 2]) == (ROAD, 0)  # the car voxel is hidden: the road below shows
    assert (top_class[3, 3], top_z[3, 3]) == (ROAD, 0)  # 255 is not a class
    assert top_occupied(labels)[0][2, 2] == CAR


def test_bev_marks_unobserved_and_empty_columns():
    labels = _labels()
    labels[4, 4, 0] = FREE  # a hole: the column holds free space only
    mask = np.ones(GRID.shape, dtype=bool)
    mask[1, 2] = False  # nothing of this column is observed
    image = bev_image(labels, mask)
    assert tuple(image[8 - 1 - 1, 6 - 1 - 2]) == UNOBSERVED_COLOR
    assert tuple(image[8 - 1 - 4, 6 - 1 - 4]) == EMPTY_COLOR
    assert tuple(bev_image(labels)[8 - 1 - 1, 6 - 1 - 2]) != UNOBSERVED_COLOR


def test_bev_figure_has_legend_and_both_panels():
    labels = _labels()
    labels[6, 1, 1:3] = CAR
    figure = bev_figure(labels, np.ones(GRID.shape, dtype=bool), SPACE, title="frame")
    axes = figure.axes
    assert [axis.get_title() for axis in axes] == ["all labels", "camera-visible voxels (mask_camera)"]
    legend = [text.get_text() for text in axes[-1].get_legend().get_texts()]
    assert legend[:2] == ["car", "driveable_surface"] and "free" not in legend


# ------------------------------------------------------------------------------------------------------ errors
def _error_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    gt, pred = _labels(), _labels()
    gt[1, 1, 1], pred[1, 1, 1] = CAR, CAR  # correct
    gt[2, 1, 1], pred[2, 1, 1] = CAR, TRUCK  # wrong class
    gt[3, 1, 1] = CAR  # missed
    pred[4, 1, 1] = CAR  # false positive
    pred[5, 1, 1] = CAR  # a false positive in a column the mask hides
    gt[6, 1, 1] = 255  # ignored
    pred[6, 1, 1] = CAR
    mask = np.ones(GRID.shape, dtype=bool)
    mask[5, 1] = False
    return gt, pred, mask


def test_voxel_outcomes_classify_the_four_cases():
    gt, pred, mask = _error_pair()
    outcomes = voxel_outcomes(gt, pred, mask)
    assert [outcomes[x, 1, 1] for x in range(1, 7)] == [CORRECT, WRONG_CLASS, MISSED, FALSE_POSITIVE,
                                                        NOT_EVALUATED, NOT_EVALUATED]  # fmt: skip
    assert outcomes[0, 0, 0] == CORRECT and outcomes[0, 0, 3] == TRUE_FREE


def test_column_outcomes_and_error_image_orientation():
    gt, pred, mask = _error_pair()
    gt[7, 4, 0] = pred[7, 4, 0] = FREE  # a column of free voxels only
    columns = column_outcomes(voxel_outcomes(gt, pred, mask))
    assert [columns[x, 1] for x in range(1, 7)] == [CORRECT, WRONG_CLASS, MISSED, FALSE_POSITIVE, NOT_EVALUATED,
                                                    CORRECT]  # fmt: skip
    assert columns[7, 4] == TRUE_FREE
    image = error_image(columns)
    assert tuple(image[8 - 1 - 3, 6 - 1 - 1]) == OUTCOME_COLORS[MISSED]
    assert tuple(image[8 - 1 - 4, 6 - 1 - 1]) == OUTCOME_COLORS[FALSE_POSITIVE]


def test_comparison_title_carries_the_frame_scores():
    gt, pred, mask = _error_pair()
    scores = frame_scores(gt, pred, mask)
    # Road: all correct (IoU 1); car: 1 voxel right, GT 3 (evaluated), predicted 2 -> 1 / 4; truck: 0 / 1.
    assert scores["miou"] == pytest.approx((1.0 + 0.25 + 0.0) / 3)
    figure = comparison_figure(gt, pred, mask, SPACE, title="frame")
    title = figure.get_suptitle()
    assert f"mIoU {100 * scores['miou']:.1f}" in title and f"IoU {100 * scores['iou']:.1f}" in title
    assert [axis.get_title() for axis in figure.axes] == ["ground truth", "prediction", "errors (per column)"]


# ------------------------------------------------------------------------------------------------------ 3D
def test_voxel_faces_hide_shared_and_back_faces():
    drawn = np.zeros((3, 3, 3), dtype=bool)
    drawn[1, 1, 1] = True
    assert len(voxel_faces(drawn)[0]) == 6
    towards = view_direction(30.0, 200.0)  # from behind (-x), the right (-y) and above (+z)
    _, _, normals = voxel_faces(drawn, towards)
    assert sorted(map(tuple, normals.astype(int))) == [(-1, 0, 0), (0, -1, 0), (0, 0, 1)]
    drawn[2, 1, 1] = True
    voxels, corners, _ = voxel_faces(drawn)
    assert len(voxels) == 10  # the touching faces are interior
    assert corners.shape == (10, 4, 3) and corners.min() == 1 and corners.max() == 3


def test_draw_voxels_adds_one_collection_with_the_ego_car():
    labels = _labels()
    figure = new_figure(4, 3)
    axis = figure.add_subplot(projection="3d")
    faces = draw_voxels(axis, labels, space=SPACE)
    # Road layer seen from above-behind-right: 48 tops, 6 back faces (x = -2) and 8 right faces (y = -1.5), + car.
    assert faces == 48 + 6 + 8 + 6
    assert len(axis.collections) == 1


# ------------------------------------------------------------------------------------------------------ cameras
def _camera(yaw_deg: float, position=(1.0, 0.0, 1.5)) -> torch.Tensor:
    """cam2ego of a camera at ``position`` looking along ego yaw ``yaw_deg`` (x right, y down, z forward)."""
    optical = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return make_transform(rotation_about_z(torch.tensor(math.radians(yaw_deg))) @ optical, torch.tensor(position))


_YAWS = {"CAM_FRONT": 0.0, "CAM_FRONT_RIGHT": -55.0, "CAM_FRONT_LEFT": 55.0, "CAM_BACK": 180.0,
         "CAM_BACK_LEFT": 110.0, "CAM_BACK_RIGHT": -110.0}  # fmt: skip


def _cameras(names, width=96, height=54, resize=0.5) -> CameraSet:
    """Cameras of ``width x height`` original images (principal point off centre), shown resized by ``resize``."""
    intrinsics = torch.tensor([[60.0, 0.0, 40.0], [0.0, 60.0, 30.0], [0.0, 0.0, 1.0]])
    shown = (round(height * resize), round(width * resize))
    aug = image_aug_matrix(resize, (0, 0, shown[1], shown[0]))
    images = np.zeros((len(names), *shown, 3), dtype=np.uint8)
    return CameraSet(tuple(names), images, intrinsics.expand(len(names), 3, 3), torch.stack([_camera(_YAWS[n])
                     for n in names]), aug.expand(len(names), 3, 3))  # fmt: skip


def _axes_by_title(figure) -> dict[str, object]:
    return {axis.get_title(): axis for axis in figure.axes if axis.get_title()}


def test_camera_panels_follow_the_surround_layout():
    scrambled = ("CAM_BACK", "CAM_FRONT_RIGHT", "CAM_FRONT", "CAM_BACK_LEFT", "CAM_BACK_RIGHT", "CAM_FRONT_LEFT")
    figure, axes = camera_figure(_cameras(scrambled))
    # Reading order (top to bottom, then left to right) of the panels' positions.
    ordered = sorted(figure.axes, key=lambda a: (-round(a.get_position().y0, 3), a.get_position().x0))
    assert [axis.get_title() for axis in ordered] == [name for row in SURROUND_LAYOUT for name in row]
    assert set(axes) == set(scrambled)
    figure, axes = camera_figure(_cameras(("CAM_FRONT",)))
    assert list(axes) == ["CAM_FRONT"] and "CAM_BACK (not loaded)" in [a.get_title() for a in figure.axes]


def test_lidar_point_on_the_optical_axis_lands_at_the_principal_point():
    cameras = _cameras(("CAM_FRONT", "CAM_BACK", "CAM_FRONT_LEFT"))
    front = cameras.cam2ego[0]
    on_axis = front[:3, 3] + 12.0 * front[:3, 2]  # 12 m along the front camera's optical axis (its z)
    lidar2ego = make_transform(rotation_about_z(torch.tensor(math.pi / 2)), torch.tensor([0.9, 0.0, 1.8]))
    flip_y = torch.diag(torch.tensor([1.0, -1.0, 1.0, 1.0]))  # a BEV augmentation of the LiDAR frame
    lidar = (invert_transform(lidar2ego) @ torch.cat((on_axis, torch.ones(1))))[:3]
    sample = Sample(token="t", scene="s", lidar2ego=lidar2ego, bev_aug=flip_y,
                    points=torch.cat(((flip_y[:3, :3] @ lidar)[None], torch.zeros(1, 2)), dim=1))  # fmt: skip
    points = lidar_points_in_ego(sample)
    torch.testing.assert_close(points[0], on_axis, atol=1e-5, rtol=0)
    figure = lidar_camera_figure(cameras, points)
    panels = _axes_by_title(figure)
    principal = (cameras.img_aug[0] @ torch.tensor([40.0, 30.0, 1.0]))[:2].numpy()  # shown at half size
    np.testing.assert_allclose(panels["CAM_FRONT"].collections[0].get_offsets(), [principal], atol=1e-4)
    assert len(panels["CAM_BACK"].collections[0].get_offsets()) == 0  # behind that camera


def test_voxel_on_the_optical_axis_lands_at_the_principal_point_in_its_class_colour():
    grid = VoxelGrid((-4.0, -4.0, -1.0, 4.0, 4.0, 2.2), 0.4)
    labels = np.full(grid.shape, FREE, dtype=np.uint8)
    labels[15, 10, 5] = CAR  # centre (2.2, 0.2, 1.2)
    cameras = _cameras(("CAM_FRONT",))
    cameras = CameraSet(cameras.names, cameras.images, cameras.intrinsics, _camera(0.0, (0.5, 0.2, 1.2))[None],
                        cameras.img_aug)  # fmt: skip
    figure = occupancy_camera_figure(cameras, labels, space=dataclasses.replace(OCC3D_SPACE, grid=grid))
    scatter = _axes_by_title(figure)["CAM_FRONT"].collections[0]
    principal = (cameras.img_aug[0] @ torch.tensor([40.0, 30.0, 1.0]))[:2].numpy()
    np.testing.assert_allclose(scatter.get_offsets(), [principal], atol=1e-4)
    np.testing.assert_allclose(scatter.get_facecolors()[0, :3], np.array(_color(CAR)) / 255, atol=1e-6)
    # A flipped occupancy frame (BEV augmentation) is undone before projecting.
    flip_x = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
    torch.testing.assert_close(voxel_centres_in_ego(np.array([[4, 10, 5]]), flip_x, grid),
                               torch.tensor([[2.2, 0.2, 1.2]]), atol=1e-5, rtol=0)  # fmt: skip


def test_palette_png_keeps_class_colours_exact(tmp_path):
    figure = new_figure(1.0, 1.0, dpi=40)
    axis = figure.add_axes((0, 0, 1, 1))
    axis.imshow(np.array(OCC3D_COLORS[:16], dtype=np.uint8).reshape(4, 4, 3), interpolation="nearest")
    axis.set_axis_off()
    with Image.open(save_figure(figure, tmp_path / "p.png", colors=64)) as image:
        assert image.mode == "P"
        pixels = np.asarray(image.convert("RGB"))
    # 10 x 10 pixels per cell: (row, column) of the cell is (v // 10, u // 10).
    assert tuple(pixels[5, 5]) == _color(0) and tuple(pixels[35, 35]) == _color(15)
    assert tuple(pixels[25, 5]) == _color(8)


# ------------------------------------------------------------------------------------------------------ CLI
@pytest.fixture(scope="module")
def data(small_world) -> Path:
    """2 scenes x 2 key frames, 2 cameras at 176 x 99: scene-0002 is the val split."""
    return small_world


def _val_gts(root: Path) -> dict[str, Path]:
    return {path.parent.name: path for path in sorted((root / "gts" / "scene-0002").glob("*/labels.npz"))}


def test_cli_renders_ground_truth_predictions_and_page(data, tmp_path, capsys):
    from occkit.metrics.evaluate import write_prediction

    predictions = tmp_path / "pred"
    predictions.mkdir()
    for token, path in _val_gts(data).items():
        with np.load(path) as labels:
            semantics, instances = labels["semantics"].copy(), labels["instances"]
        semantics[semantics == ROAD] = 12  # the road becomes other_flat: a wrong class in every frame
        write_prediction(predictions, token, semantics, instances=instances)  # panoptic: each object its colour
    out = tmp_path / "viz"
    assert main(["viz", "--data", str(data), "--frames", "2", "--pred", str(predictions), "--out", str(out),
                 "--colors", "128"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "[viz] 2/2" in printed and str(out / "index.html") in printed
    index = json.loads((out / "index.json").read_text())
    assert [frame["token"] for frame in index["frames"]] == list(_val_gts(data))
    expected = {"bev_gt", "voxels_gt", "compare", "voxels_pred", "cameras_lidar", "cameras_gt", "cameras_pred",
                "instances_gt", "instances_pred"}  # the world's labels and these predictions carry instances
    page = (out / "index.md").read_text()
    for frame in index["frames"]:
        assert set(frame["files"]) == expected
        assert 0.0 <= frame["scores"]["miou"] < 1.0 and frame["scores"]["iou"] == pytest.approx(1.0)
        for relative in frame["files"].values():
            assert (out / relative).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
            assert f"]({relative})" in page
    assert (out / "index.html").read_text().count("<img ") == 2 * len(expected)


def test_cli_predicts_with_a_checkpoint(data, tmp_path):
    from occkit import zoo
    from occkit.engine.checkpoint import FORMAT, atomic_save
    from occkit.zoo import experiment_from_dict

    overrides = ["data.cameras=[CAM_FRONT, CAM_BACK]", "data.image_aug.final_size=[64, 176]",
                 "model.lss.image_size=[64, 176]", "model.image.out_stages=[3]", "model.bev.channels=[16, 32, 64]",
                 "model.bev.neck_channels=16", "model.occupancy.in_channels=16",
                 "model.occupancy.hidden_channels=16"]  # fmt: skip
    experiment = experiment_from_dict(zoo.experiment("flashocc_tiny").to_dict(), "test", overrides)
    torch.manual_seed(0)
    model = zoo.build_from_config(experiment.architecture, experiment.model)
    (tmp_path / "run").mkdir()
    checkpoint = atomic_save({"format": FORMAT, "architecture": experiment.architecture,
                              "experiment": experiment.to_dict(), "model": model.state_dict(), "ema": None},
                             tmp_path / "run" / "model.pt")  # fmt: skip
    token = next(iter(_val_gts(data)))
    out = tmp_path / "viz"
    assert main(["viz", "--data", str(data), "--token", token, "--ckpt", str(checkpoint), "--out", str(out)]) == 0
    frame = json.loads((out / "index.json").read_text())["frames"][0]
    assert frame["token"] == token and {"compare", "cameras_pred"} <= set(frame["files"])


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--data", "{missing}"], "missing does not exist"),
        (["--token", "nosuchtoken"], "no sample token 'nosuchtoken'"),
        (["--pred", "{empty}"], ".npz not found"),
        (["--pred", "{missing}"], "--pred "),
        (["--frames", "0"], "argument --frames: must be between 1 and 10000, got 0"),
    ],
)
def test_cli_bad_input_is_one_error_line(data, tmp_path, capsys, arguments, message):
    (tmp_path / "empty").mkdir()
    filled = [a.format(missing=tmp_path / "missing", empty=tmp_path / "empty") for a in arguments]
    options = {"--data": str(data)} | dict(zip(filled[::2], filled[1::2], strict=True))
    argv = ["viz", *[part for item in options.items() for part in item], "--out", str(tmp_path / "out")]
    try:
        code = main(argv)
    except SystemExit as exit_info:  # argparse refuses an out-of-range option while parsing
        code = exit_info.code
    assert code == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("occkit viz: error:") and message in error and "\n" not in error
    assert not (tmp_path / "out" / "index.json").exists()
