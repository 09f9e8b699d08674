"""Scenes, labels and predictions as a rerun recording: one scene on a timeline, for an interactive 3D viewer.

`rerun <https://rerun.io>`_ records logged data into a file (``.rrd``) or streams it to its viewer (native, or a web
viewer served over HTTP). Every frame is logged at its ``frame`` (the key frame's position in its scene) and its
``timestamp`` (the sample's time), so the viewer scrubs through a scene. The entity tree mirrors occkit's frames:

=====================================  ========================================================================
``world``                              the global frame (z up); static: the class names and colours
``world/trajectory``                   the ego's path through the scene, a line strip (static)
``world/ego``                          the key frame's ego pose (``ego2global``)
``world/ego/vehicle``                  the ego car (static)
``world/ego/lidar``                    LiDAR -> ego (``lidar2ego``, the BEV augmentation undone)
``world/ego/lidar/points``             the LiDAR points, coloured by their height above the ego frame
``world/ego/lidar/boxes``              the ground-truth 3D boxes in their class colours
``world/ego/cameras/<CAM>``            camera -> ego, its pinhole and its image
``world/ego/occupancy``                label frame -> ego (the occupancy augmentation undone)
``.../occupancy/gt``, ``gt_camera``    occupied ground-truth voxels: all, and those of the camera mask
``.../prediction``, ``prediction_camera``  occupied predicted voxels: all, and those of the ground truth's camera mask
``.../occupancy/errors``               wrong class, missed and false-positive voxels (the metric's mask)
``scores/miou``, ``scores/iou``        the frame's scores (:func:`occkit.viz.errors.frame_scores`)
=====================================  ========================================================================

Voxels are solid boxes whose class ids index an annotation context of the label space's taxonomy, so the viewer
paints them in occkit's palette (:mod:`occkit.viz.palette`) and names their class on hover; free (and ignored)
voxels are left out. The ``log_*`` functions log at the recording's current time (:func:`set_frame`), on the
recording given or else rerun's global one (``rr.init``), so a notebook can log any :class:`~occkit.types.Batch` or
prediction; :func:`record_scene` logs a whole scene of a dataset split, as ``occkit view`` does.
"""

from __future__ import annotations

import dataclasses
import shutil
import sys
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch
from matplotlib import colormaps
from PIL import Image

from occkit.classes import DETECTION_CLASSES
from occkit.data.collate import collate
from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.data.labels import carry_instances
from occkit.label_space import OCC3D_SPACE, LabelSpace, label_space
from occkit.nuscenes import CAMERAS
from occkit.types import Batch
from occkit.viz.bev import EGO_BOX
from occkit.viz.errors import (
    FALSE_POSITIVE,
    MISSED,
    OUTCOME_COLORS,
    OUTCOME_NAMES,
    WRONG_CLASS,
    frame_scores,
    voxel_outcomes,
)
from occkit.viz.palette import instance_colors
from occkit.viz.run import Predicted, Predictor, folder_predictor
from occkit.viz.serving import ViewerServer

if TYPE_CHECKING:  # the engine (models, zoo) is imported only when a model predicts
    from occkit.model_source import ModelSource

__all__ = [
    "FRAME",
    "TIMESTAMP",
    "ENTITIES",
    "ERRORS",
    "set_frame",
    "log_setup",
    "log_trajectory",
    "occupied",
    "log_occupancy",
    "log_prediction",
    "log_batch",
    "scene_blueprint",
    "ViewConfig",
    "Scene",
    "open_scene",
    "start_sink",
    "new_recording",
    "record_scene",
]

#: The timelines: the key frame's position in its scene (a sequence) and the sample's time.
FRAME, TIMESTAMP = "frame", "timestamp"

#: Entity paths by role (see the module doc).
ENTITIES = {
    "world": "world",
    "trajectory": "world/trajectory",
    "ego": "world/ego",
    "vehicle": "world/ego/vehicle",
    "lidar": "world/ego/lidar",
    "points": "world/ego/lidar/points",
    "boxes": "world/ego/lidar/boxes",
    "cameras": "world/ego/cameras",
    "occupancy": "world/ego/occupancy",
    "gt": "world/ego/occupancy/gt",
    "gt_camera": "world/ego/occupancy/gt_camera",
    "gt_instances": "world/ego/occupancy/gt_instances",
    "prediction": "world/ego/occupancy/prediction",
    "prediction_camera": "world/ego/occupancy/prediction_camera",
    "prediction_instances": "world/ego/occupancy/prediction_instances",
    "errors": "world/ego/occupancy/errors",
    "scores": "scores",
}

#: The errors the error layer shows, by name, as :func:`~occkit.viz.errors.voxel_outcomes` codes.
ERRORS = {"wrong_class": WRONG_CLASS, "missed": MISSED, "false_positive": FALSE_POSITIVE}

#: On-screen size of LiDAR points, box edges and the trajectory: a size in UI points keeps them readable at any zoom.
SCREEN_RADIUS = rr.Radius.ui_points(1.5)



def set_frame(frame: int, timestamp_us: int | None = None, recording: rr.RecordingStream | None = None) -> None:
    """Log what follows at key frame ``frame`` of the scene and, when given, at the sample's time (microseconds
    since the epoch, as nuScenes stores it)."""
    rr.set_time(FRAME, sequence=frame, recording=recording)
    if timestamp_us is not None:
        rr.set_time(TIMESTAMP, timestamp=np.datetime64(int(timestamp_us), "us"), recording=recording)


def _transform(matrix: torch.Tensor | np.ndarray) -> rr.Transform3D:
    """A 4x4 child -> parent matrix as a rerun transform (the linear part may hold flips and scales)."""
    matrix = np.asarray(torch.as_tensor(matrix).detach().cpu().double())
    return rr.Transform3D(translation=matrix[:3, 3], mat3x3=matrix[:3, :3])


def log_setup(space: LabelSpace | str = OCC3D_SPACE, recording: rr.RecordingStream | None = None) -> None:
    """The static part of a recording: z up, the class names and colours of ``space`` (voxels and boxes take them
    by class id), the error layer's colours and the ego car."""
    space = label_space(space)
    taxonomy = space.taxonomy
    rr.log(ENTITIES["world"], rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True, recording=recording)
    classes = [rr.AnnotationInfo(id=i, label=name, color=color)
               for i, (name, color) in enumerate(zip(taxonomy.classes, taxonomy.colors, strict=True))]  # fmt: skip
    rr.log(ENTITIES["world"], rr.AnnotationContext(classes), static=True, recording=recording)
    outcomes = [rr.AnnotationInfo(id=code, label=OUTCOME_NAMES[code], color=OUTCOME_COLORS[code])
                for code in ERRORS.values()]  # fmt: skip
    rr.log(ENTITIES["errors"], rr.AnnotationContext(outcomes), static=True, recording=recording)
    lower, upper = np.array(EGO_BOX[:3]), np.array(EGO_BOX[3:])
    vehicle = rr.Boxes3D(mins=[lower], sizes=[upper - lower], colors=[(40, 40, 40)], fill_mode="solid")
    rr.log(ENTITIES["vehicle"], vehicle, static=True, recording=recording)


def log_trajectory(ego2global: np.ndarray | torch.Tensor, recording: rr.RecordingStream | None = None) -> None:
    """The ego's path through a scene as one static line strip in the global frame.

    Args:
        ego2global: ``(T, 4, 4)`` ego poses of the scene's key frames in time order.
    """
    positions = np.asarray(torch.as_tensor(ego2global).detach().cpu().double())[:, :3, 3]
    rr.log(ENTITIES["trajectory"], rr.LineStrips3D([positions], colors=[(255, 255, 255)], radii=SCREEN_RADIUS),
           static=True, recording=recording)  # fmt: skip


def occupied(semantics: np.ndarray, space: LabelSpace | str = OCC3D_SPACE,
             mask: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """``(X, Y, Z)`` bool: voxels that are neither free nor ignored, within ``mask`` when given."""
    space = label_space(space)
    semantics = np.asarray(semantics)
    keep = (semantics != space.free_index) & (semantics != space.ignore_index)
    return keep if mask is None else keep & np.asarray(mask, dtype=bool)


def _log_voxels(entity: str, keep: np.ndarray, class_ids: np.ndarray, space: LabelSpace,
                recording: rr.RecordingStream | None, instances: np.ndarray | None = None) -> int:  # fmt: skip
    """Voxels ``keep`` (``(X, Y, Z)`` bool) of ``space``'s grid as solid boxes with ``class_ids`` (``(X, Y, Z)``),
    coloured by class, or with ``instances`` (``(X, Y, Z)``) each object its own colour (the class still on hover)."""
    grid = space.grid
    if keep.shape != grid.shape:
        raise ValueError(f"{entity}: the grid is {keep.shape}, but {space.name} labels are {grid.shape}")
    index = np.argwhere(keep)
    size = np.asarray(grid.voxel_size, dtype=np.float32)
    centres = (index.astype(np.float32) + 0.5) * size + np.asarray(grid.lower, dtype=np.float32)
    # One half size for all voxels: rerun repeats the last half size for the remaining centres (and would draw a
    # box at the origin for a half size without a centre). Class names show on hover: as labels on every voxel they
    # would hide the scene.
    half_sizes = (size / 2)[None] if len(index) else np.zeros((0, 3), np.float32)
    colors = None if instances is None else instance_colors(class_ids[keep], instances[keep], space.taxonomy)
    rr.log(entity, rr.Boxes3D(centers=centres, half_sizes=half_sizes, class_ids=class_ids[keep].astype(np.uint16),
                              colors=colors, fill_mode="solid", show_labels=False), recording=recording)  # fmt: skip
    return len(index)


def log_occupancy(entity: str, semantics: np.ndarray, space: LabelSpace | str = OCC3D_SPACE,
                  mask: np.ndarray | None = None, recording: rr.RecordingStream | None = None,
                  instances: np.ndarray | None = None) -> int:  # fmt: skip
    """Occupied voxels of a label grid at ``entity``, in the label frame (log it under ``world/ego/occupancy``, whose
    transform :func:`log_batch` sets, to place them around the ego).

    Args:
        entity: entity path, e.g. ``ENTITIES["gt"]``.
        semantics: ``(X, Y, Z)`` integer class ids of ``space`` (255 = ignored).
        mask: optional ``(X, Y, Z)`` bool; only voxels it keeps are logged.
        instances: optional ``(X, Y, Z)`` panoptic instance ids: each object its own colour, stuff (0) by class.

    Returns:
        the number of voxels logged.
    """
    space = label_space(space)
    semantics = np.asarray(semantics)
    ids = None if instances is None else np.asarray(instances)
    return _log_voxels(entity, occupied(semantics, space, mask), semantics, space, recording, ids)


def log_prediction(prediction: np.ndarray | torch.Tensor, gt: np.ndarray | torch.Tensor | None = None,
                   mask: np.ndarray | torch.Tensor | None = None, space: LabelSpace | str = OCC3D_SPACE,
                   recording: rr.RecordingStream | None = None) -> dict[str, int]:  # fmt: skip
    """A predicted grid and, against the ground truth, its errors and scores.

    Logs the occupied predicted voxels (``prediction``), those of the camera ``mask`` (``prediction_camera``), and
    with ``gt`` the error layer (``errors``: wrong class, missed, false positive; voxels the mask keeps, or all
    without one, as the metric scores them) and the frame's mIoU and IoU (``scores``).

    Args:
        prediction: ``(X, Y, Z)`` class ids of ``space``.
        gt: optional ``(X, Y, Z)`` ground-truth class ids (255 = ignored).
        mask: optional ``(X, Y, Z)`` bool camera mask of the ground truth.

    Returns:
        voxel counts by entity role (``prediction``, ``prediction_camera``) and by error (``wrong_class``,
        ``missed``, ``false_positive``).
    """
    space = label_space(space)
    prediction, gt, mask = (None if a is None else np.asarray(torch.as_tensor(a).cpu()) for a in (prediction, gt, mask))
    counts = {"prediction": log_occupancy(ENTITIES["prediction"], prediction, space, recording=recording)}
    if mask is not None:
        counts["prediction_camera"] = log_occupancy(ENTITIES["prediction_camera"], prediction, space, mask, recording)
    if gt is None:
        return counts
    outcomes = voxel_outcomes(gt, prediction, mask, space.free_index)
    _log_voxels(ENTITIES["errors"], np.isin(outcomes, list(ERRORS.values())), outcomes, space, recording)
    counts.update({name: int(np.count_nonzero(outcomes == code)) for name, code in ERRORS.items()})
    for name, value in frame_scores(gt, prediction, mask, space).items():
        if value is not None:  # undefined: no class in the ground truth or the prediction
            rr.log(f"{ENTITIES['scores']}/{name}", rr.Scalars(value), recording=recording)
    return counts


def _height_colors(heights: np.ndarray, space: LabelSpace) -> np.ndarray:
    """``(P, 3)`` uint8 colours of points at ``heights`` (m, ego frame) over the label grid's height range."""
    low, high = space.grid.lower[2], space.grid.upper[2]
    return (colormaps["turbo"](np.clip((heights - low) / (high - low), 0.0, 1.0))[:, :3] * 255).astype(np.uint8)


def _log_cameras(batch: Batch, index: int, cameras: Sequence[str], image_files: Sequence[str | Path] | None,
                 recording: rr.RecordingStream | None) -> int:  # fmt: skip
    """Each camera's pose, pinhole and (from ``image_files``) image; returns the number of images logged."""
    count = batch.intrinsics.shape[1]
    if len(cameras) != count or (image_files is not None and len(image_files) != count):
        raise ValueError(f"the batch has {count} cameras, but {len(cameras)} camera names and "
                         f"{'no' if image_files is None else len(image_files)} image files were given")  # fmt: skip
    for i, name in enumerate(cameras):
        entity = f"{ENTITIES['cameras']}/{name}"
        rr.log(entity, _transform(batch.cam2ego[index, i]), recording=recording)
        intrinsics = batch.intrinsics[index, i].double()
        if image_files is None:
            # The pinhole of the augmented image the network sees (its normalised pixels are not drawn).
            height, width = batch.images.shape[-2:]
            intrinsics = batch.img_aug[index, i].double() @ intrinsics
        else:
            with Image.open(image_files[i]) as image:  # the header only: the file is logged as it is
                width, height = image.size
        rr.log(entity, rr.Pinhole(image_from_camera=intrinsics.cpu().numpy(), resolution=[width, height],
                                  camera_xyz=rr.ViewCoordinates.RDF), recording=recording)  # fmt: skip
        if image_files is not None:
            rr.log(entity, rr.EncodedImage(path=image_files[i]), recording=recording)
    return 0 if image_files is None else count


def log_batch(batch: Batch, index: int = 0, space: LabelSpace | str = OCC3D_SPACE, cameras: Sequence[str] = CAMERAS,
              image_files: Sequence[str | Path] | None = None,
              recording: rr.RecordingStream | None = None) -> dict[str, int]:  # fmt: skip
    """One sample of a batch at the recording's current time: ego pose, cameras, LiDAR points, boxes and the
    ground-truth occupancy (whatever the batch holds).

    The batch's tensors are drawn in their own (augmented) frames under transforms that undo the augmentation, so
    everything lands in the un-augmented ego frame: points and boxes under ``lidar2ego @ inv(bev_aug)``, labels
    under ``inv(occ_aug)`` (SurroundOcc's LiDAR-frame labels: ``lidar2ego @ inv(bev_aug)``).

    The points are all the batch holds for the sample (the key frame and the sweeps the dataset added), coloured by
    their height in the ego frame.

    Args:
        batch: a collated batch (:func:`occkit.data.collate.collate`).
        index: which sample of the batch.
        space: the label space of ``batch.voxel_semantics``.
        cameras: the names of the batch's ``N`` cameras, in its order (the dataset's ``cameras``).
        image_files: the ``N`` original image files of the frame (``dataset.root / record.cameras[name].path``),
            logged as they are with the original intrinsics. The batch's own images are normalised for the network
            and are not drawn; without files each camera gets its pose and the pinhole of the augmented image.

    Returns:
        counts by entity role: ``points``, ``boxes``, ``images``, ``gt``, ``gt_camera`` and ``gt_instances`` (voxels).
    """
    space = label_space(space)
    counts = {}
    rr.log(ENTITIES["ego"], _transform(batch.ego2global[index]), recording=recording)
    lidar_to_ego = batch.lidar2ego[index].double() @ torch.linalg.inv(batch.bev_aug[index].double())
    rr.log(ENTITIES["lidar"], _transform(lidar_to_ego), recording=recording)
    if batch.intrinsics is not None:
        counts["images"] = _log_cameras(batch, index, cameras, image_files, recording)
    if batch.points is not None:
        points = batch.points[index, : int(batch.num_points[index]), :3].double().cpu()
        heights = (points @ lidar_to_ego[2, :3].cpu() + lidar_to_ego[2, 3].cpu()).numpy()
        rr.log(ENTITIES["points"], rr.Points3D(points.float().numpy(), colors=_height_colors(heights, space),
                                               radii=SCREEN_RADIUS), recording=recording)  # fmt: skip
        counts["points"] = len(points)
    if batch.boxes is not None:
        boxes = batch.boxes[index].double().cpu().numpy()
        names = [DETECTION_CLASSES[int(label)] for label in batch.box_labels[index]]
        rr.log(ENTITIES["boxes"], rr.Boxes3D(
            centers=boxes[:, :3], half_sizes=boxes[:, 3:6] / 2,
            rotation_axis_angles=[rr.RotationAxisAngle(axis=(0, 0, 1), radians=yaw) for yaw in boxes[:, 6]],
            class_ids=[space.taxonomy.index(name) for name in names], radii=SCREEN_RADIUS, show_labels=False,
        ), recording=recording)  # fmt: skip
        counts["boxes"] = len(boxes)
    if batch.voxel_semantics is not None:
        label_to_ego = torch.linalg.inv(batch.occ_aug[index].double()) if space.frame == "ego" else lidar_to_ego
        rr.log(ENTITIES["occupancy"], _transform(label_to_ego), recording=recording)
        semantics = batch.voxel_semantics[index].cpu().numpy()
        counts["gt"] = log_occupancy(ENTITIES["gt"], semantics, space, recording=recording)
        mask = None if batch.mask_camera is None else batch.mask_camera[index].cpu().numpy()
        if mask is not None:
            counts["gt_camera"] = log_occupancy(ENTITIES["gt_camera"], semantics, space, mask, recording)
        if batch.voxel_instances is not None:
            counts["gt_instances"] = log_occupancy(ENTITIES["gt_instances"], semantics, space, mask, recording,
                                                   batch.voxel_instances[index].cpu().numpy())  # fmt: skip
    return counts


# ------------------------------------------------------------------------------------------------------ layout
def _view_3d(name: str, shown: Sequence[str], hidden: Sequence[str] = ()) -> rrb.Spatial3DView:
    """A 3D view around the ego (it follows the car) of the trajectory, the ego car, ``shown`` and ``hidden`` (in
    the view's entity list, switched off), seen from behind and above."""
    roles = ("trajectory", "vehicle", *shown, *hidden)
    return rrb.Spatial3DView(
        name=name, origin=ENTITIES["ego"], contents=[f"+ /{ENTITIES[role]}" for role in roles],
        overrides={f"/{ENTITIES[role]}": rrb.EntityBehavior(visible=False) for role in hidden},
        eye_controls=rrb.EyeControls3D(position=(-32.0, 0.0, 28.0), look_target=(8.0, 0.0, 0.0), eye_up=(0, 0, 1)),
    )  # fmt: skip


def scene_blueprint(cameras: Sequence[str], masked: bool, labelled: bool, prediction_name: str | None,
                    panoptic: bool = False) -> rrb.Blueprint:  # fmt: skip
    """The viewer's layout: 3D views of the ground truth, the prediction and its errors side by side, the cameras
    below, and the frame's scores with predictions.

    Args:
        cameras: the camera names, one 2D view each.
        masked: the labels carry a camera mask: the 3D views show the voxels it keeps (the ones the metric scores),
            and list the full grids switched off.
        labelled: the recording holds ground-truth occupancy.
        prediction_name: the predictions' name for the view titles; None without predictions.
        panoptic: the recording holds instance layers (``gt_instances``, ``prediction_instances``): listed in their
            views, switched off.
    """

    def layers(role: str) -> tuple[list[str], list[str]]:
        """The occupancy entities of ``role`` shown and listed switched off."""
        shown, hidden = ([f"{role}_camera"], [role]) if masked else ([role], [])
        return shown, hidden + ([f"{role}_instances"] if panoptic else [])

    if labelled:
        shown, hidden = layers("gt")
        views = [_view_3d("ground truth", ["boxes", *shown], [*hidden, "points"])]
    else:
        views = [_view_3d("LiDAR and boxes", ["boxes", "points"])]
    if prediction_name is not None:
        shown, hidden = layers("prediction")
        views.append(_view_3d(prediction_name, shown, [*hidden, "boxes"]))
        if labelled:
            views.append(_view_3d("errors" + (" (camera mask)" if masked else ""), ["errors"], ["boxes"]))
    rows: list = [rrb.Horizontal(*views)]
    shares = [3.0]
    if cameras:
        camera_views = [rrb.Spatial2DView(name=name, origin=f"{ENTITIES['cameras']}/{name}") for name in cameras]
        rows.append(rrb.Grid(*camera_views, grid_columns=min(3, len(cameras))))
        shares.append(2.0)
    if prediction_name is not None and labelled:
        rows.append(rrb.TimeSeriesView(name="frame scores", origin=f"/{ENTITIES['scores']}"))
        shares.append(0.8)
    # The entity tree stays open (it switches layers on and off); selection details and the full time panel are a
    # click away, so the views get the room.
    return rrb.Blueprint(rrb.Vertical(*rows, row_shares=shares), rrb.BlueprintPanel(state="expanded"),
                         rrb.SelectionPanel(state="collapsed"), rrb.TimePanel(timeline=FRAME, state="collapsed"))


# ------------------------------------------------------------------------------------------------------ scenes
@dataclass(frozen=True)
class ViewConfig:
    """What ``occkit view`` records."""

    data: str
    """Dataset root (nuScenes layout, labels in the label space's layout)."""
    split: str = "val"
    """Split whose first scene is shown when ``scene`` is None (a named scene is found in any split)."""
    version: str = "v1.0-synth"
    """Table folder under ``data``."""
    scene: str | None = None
    """Scene name, found in whichever split holds it (names are unique); None: the first scene of ``split``."""
    frames: int | None = None
    """Record the scene's first ``frames`` key frames; None: all."""
    pred: str | None = None
    """Folder of ``<token>.npz`` predictions (as ``occkit predict`` writes them)."""
    model: ModelSource | None = None
    """A model to predict with instead of ``pred``: a checkpoint, or weights for a zoo entry."""
    label_space: str | None = None
    """Label space of the ground truth and predictions; None: the model's, or ``occ3d``."""
    device: str = "cpu"
    """Where the model runs."""

    def __post_init__(self) -> None:
        if self.frames is not None and self.frames < 1:
            raise ValueError(f"frames must be at least 1, got {self.frames}")
        if self.pred is not None and self.model is not None:
            raise ValueError("give predictions as a folder (pred) or a model to predict with, not both")


@dataclass(frozen=True, eq=False)
class Scene:
    """A scene ready to record: its frames in time order and, optionally, where its predictions come from."""

    name: str
    dataset: OccupancyDataset
    """The split, loaded with the test transform: cameras, key-frame LiDAR points, boxes and (when every frame of
    the scene has them) labels."""
    indices: tuple[int, ...]
    """Dataset indices of the frames to record, in time order."""
    predict: Predictor | None = None
    """Token -> the predicted classes ``(X, Y, Z)`` (and instances); called for the frames in time order (a temporal
    model streams)."""
    prediction_name: str | None = None
    """The predictions' name: their folder's, or the checkpoint's run folder's."""

    @property
    def labelled(self) -> bool:
        return self.dataset.config.occupancy

    @property
    def masked(self) -> bool:
        """Whether the labels carry a camera mask."""
        return self.labelled and "camera" in self.dataset.space.masks

    def blueprint(self) -> rrb.Blueprint:
        return scene_blueprint(self.dataset.config.cameras, self.masked, self.labelled, self.prediction_name,
                               self.dataset.config.instances)  # fmt: skip


def _name_list(names: Sequence[str], limit: int = 12) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f", ... ({len(names) - limit} more)" if len(names) > limit else "")


def _model_predictor(config: ViewConfig, model: torch.nn.Module, experiment) -> Predictor:
    """The model's predictions by token on its own data settings; a temporal model keeps its stream's memory
    across calls, so the frames must come in time order."""
    from occkit.engine.evaluate import evaluation_dataset, stream_memory

    experiment = dataclasses.replace(experiment, data=dataclasses.replace(experiment.data, version=config.version))
    dataset = evaluation_dataset(experiment, config.data, config.split, labels=False)
    position = {record.token: i for i, record in enumerate(dataset.records)}
    memory, _ = stream_memory(model, 1)

    @torch.no_grad()
    def predict(token: str) -> Predicted:
        batch = collate([dataset[position[token]]]).to(config.device)
        prediction = model.predict(batch) if memory is None else model.predict(batch, memory=memory)
        instances = None if prediction.instances is None else prediction.instances[0].cpu().numpy()
        return Predicted(prediction.semantics[0].cpu().numpy(), instances)

    return predict


def open_scene(config: ViewConfig) -> Scene:
    """Check everything ``config`` names and load the scene's dataset (and model): nothing is logged here, so a
    recording is only started for a scene that can be recorded.

    Raises:
        FileNotFoundError: missing data root, prediction folder, prediction file or checkpoint.
        ValueError: unknown split, a scene in no split (the message lists some of the data's scenes), a checkpoint
            of another label space than ``config.label_space``.
    """
    root = Path(config.data)
    if not root.is_dir():
        raise FileNotFoundError(f"data root {root} does not exist")
    model = experiment = None
    space = label_space(config.label_space or "occ3d")
    if config.model is not None:
        model, experiment, space = config.model.load_predicting(config.label_space, config.device)
    # A scene name is unique across the splits: a named scene is looked up in all of them ("all"), so that it needs
    # no --split, and the split only picks the default scene.
    if config.scene is not None:
        config = dataclasses.replace(config, split="all")
    common = {"root": str(root), "version": config.version, "split": config.split, "label_space": space.name}
    listing = OccupancyDataset(DatasetConfig(**common, cameras=(), sweeps=-1, occupancy=False, boxes=False))
    scenes = {listing.records[indices[0]].scene: indices for indices in listing.scene_indices()}
    name = config.scene if config.scene is not None else next(iter(scenes))
    if name not in scenes:
        raise ValueError(f"{root}: no scene {name!r} in {config.version} (in no split); its scenes: "
                         f"{_name_list(sorted(scenes), limit=8)}")  # fmt: skip
    indices = tuple(scenes[name][: config.frames])
    records = [listing.records[i] for i in indices]
    cameras = tuple(camera for camera in CAMERAS if camera in records[0].cameras)
    labelled = all(listing.label_path(record).is_file() for record in records)
    panoptic = labelled and carry_instances(space, (listing.label_path(record) for record in records))
    # The key frame's points only (sweeps=0): what the LiDAR saw at the frame's time.
    dataset = OccupancyDataset(DatasetConfig(**common, cameras=cameras, sweeps=0, occupancy=labelled, boxes=True,
                                             instances=panoptic))  # fmt: skip
    predict, prediction_name = None, None
    if config.pred is not None:
        predict = folder_predictor(Path(config.pred), [record.token for record in records], space)
        prediction_name = f"prediction ({Path(config.pred).name})"
    elif model is not None:
        predict = _model_predictor(config, model, experiment)
        prediction_name = f"prediction ({config.model.label})"
    return Scene(name, dataset, indices, predict, prediction_name)


def record_scene(scene: Scene, recording: rr.RecordingStream | None = None,
                 progress: Callable[[str], None] | None = None) -> list[dict]:  # fmt: skip
    """Log every frame of ``scene`` (its static part first) on the ``frame`` and ``timestamp`` timelines.

    Returns:
        one entry per frame: ``token``, ``frame`` and the counts of :func:`log_batch` and :func:`log_prediction`.
    """
    dataset = scene.dataset
    space = dataset.space
    records = [dataset.records[i] for i in scene.indices]
    rr.send_recording_name(scene.name, recording=recording)
    log_setup(space, recording)
    log_trajectory(np.stack([record.ego2global for record in records]), recording)
    frames = []
    for number, (index, record) in enumerate(zip(scene.indices, records, strict=True), start=1):
        set_frame(record.index_in_scene, record.timestamp, recording)
        batch = collate([dataset[index]])
        files = [dataset.root / record.cameras[camera].path for camera in dataset.config.cameras]
        entry = {"token": record.token, "frame": record.index_in_scene,
                 **log_batch(batch, 0, space, dataset.config.cameras, files, recording)}  # fmt: skip
        if scene.predict is not None:
            gt = None if batch.voxel_semantics is None else batch.voxel_semantics[0]
            mask = None if batch.mask_camera is None else batch.mask_camera[0]
            predicted = scene.predict(record.token)
            entry.update(log_prediction(predicted.semantics, gt, mask, space, recording))
            if predicted.instances is not None:
                entry["prediction_instances"] = log_occupancy(ENTITIES["prediction_instances"], predicted.semantics,
                                                              space, mask, recording, predicted.instances)  # fmt: skip
        frames.append(entry)
        if progress is not None:
            progress(f"[view] {number}/{len(records)} {record.token}")
    return frames


def start_sink(recording: rr.RecordingStream, blueprint: rrb.Blueprint, save: str | Path | None = None,
               server: ViewerServer | None = None) -> None:  # fmt: skip
    """Send a recording where it is seen, before anything is logged: to a file (``save``), to a running web viewer
    server (``server``, :func:`occkit.viz.serving.start_server`: it buffers the data for viewers that connect later),
    or else to a native viewer it spawns. ``blueprint`` becomes the recording's default layout."""
    if save is not None:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        recording.save(save, default_blueprint=blueprint)
        return
    if server is not None:
        recording.connect_grpc(server.grpc_url, default_blueprint=blueprint)
        return
    # The viewer the SDK installed beside this interpreter, also when its environment is not on PATH (rerun looks
    # on PATH only).
    viewer = shutil.which("rerun", path=str(Path(sys.executable).parent))
    rr.spawn(default_blueprint=blueprint, executable_path=viewer, recording=recording)


def new_recording() -> rr.RecordingStream:
    """A recording of application ``occkit`` with a recording id of its own (rerun's default id is the process's,
    shared by every recording it makes)."""
    return rr.RecordingStream("occkit", recording_id=uuid.uuid4())


def view_scene(config: ViewConfig, save: Path | None = None, server: ViewerServer | None = None,
               log: Callable[[str], None] = print) -> None:  # fmt: skip
    """Record ``config``'s scene and show it: in a spawned viewer, into the ``.rrd`` file ``save``, or through the
    running ``server`` (a web viewer, until it stops: an ``OSError`` with its last words, or Ctrl-C)."""
    scene = open_scene(config)
    recording = new_recording()
    start_sink(recording, scene.blueprint(), save=save, server=server)
    start = time.perf_counter()
    frames = record_scene(scene, recording, progress=log)
    recording.flush()
    seconds = time.perf_counter() - start
    if save is not None:
        recording.disconnect()  # closes the file
        log(f"wrote {len(frames)} frames of {scene.name} to {save} ({save.stat().st_size / 1e6:.1f} MB, "
            f"{seconds:.1f} s); open it with: rerun {save}")
    elif server is None:
        log(f"sent {len(frames)} frames of {scene.name} to the viewer ({seconds:.1f} s)")
    else:
        log(f"serving {len(frames)} frames of {scene.name} on {server.bind}: open {server.web_url} in a browser "
            "(Ctrl-C stops the server)")
        while server.process.poll() is None:
            time.sleep(1)
        raise OSError(f"the rerun server stopped: {server.last_words()}")

