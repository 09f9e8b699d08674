"""Render frames of a dataset split: ground truth, predictions and cameras as PNGs, a page and a JSON index.

Samples are loaded by :class:`~occkit.data.dataset.OccupancyDataset` with the test transform (no augmentation), so
every matrix is the one a model sees. Images are shown at their original size, or resized to ``display_width``
through the dataset's own deterministic test-time image transform; its matrix (``img_aug``) then carries the resize
into every projection.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
from matplotlib.figure import Figure
from PIL import Image

from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.data.index import FrameRecord
from occkit.data.labels import carry_instances
from occkit.data.names import path_under, safe_name
from occkit.data.transforms import ImageAugConfig, augment_image, sample_image_aug
from occkit.figure import MIN_PALETTE_COLORS, save_figure
from occkit.label_space import LabelSpace, label_space
from occkit.nuscenes import CAMERAS
from occkit.types import Sample
from occkit.viz.bev import bev_figure
from occkit.viz.cameras import CameraSet, lidar_camera_figure, lidar_points_in_ego, occupancy_camera_figure
from occkit.viz.errors import comparison_figure, format_scores, frame_scores
from occkit.viz.page import PageImage, Section, write_page
from occkit.viz.voxels import voxel_figure

if TYPE_CHECKING:  # the engine (models, zoo) is imported only when a model predicts
    from occkit.model_source import ModelSource

__all__ = ["VizConfig", "render_frames"]

class Predicted(NamedTuple):
    """One frame's prediction: class ids ``(X, Y, Z)`` and, from a panoptic model or file, instance ids."""

    semantics: np.ndarray
    instances: np.ndarray | None = None


Predictor = Callable[[str], Predicted]


#: An upper bound on the inches of one figure (the comparison and BEV figures are the widest, 13 in; the cameras
#: with a legend the tallest, about 6 in for 16:9 images), for the memory estimate of ``occkit viz --dpi``.
LARGEST_FIGURE_INCHES = (14.0, 8.0)


@dataclass(frozen=True)
class VizConfig:
    """What ``occkit viz`` renders."""

    data: str
    """Dataset root (nuScenes + Occ3D layout)."""
    out: str
    """Folder for the PNGs, ``index.md``, ``index.html`` and ``index.json``."""
    split: str = "val"
    """Scene split to take frames from."""
    version: str = "v1.0-synth"
    """Table folder under ``data``."""
    frames: int = 3
    """Frames spread evenly over the split (ignored when ``tokens`` are given)."""
    tokens: tuple[str, ...] = ()
    """Sample tokens to render instead of spread frames."""
    pred: str | None = None
    """Folder of ``<token>.npz`` predictions (as ``occkit predict`` writes them)."""
    model: ModelSource | None = None
    """A model to predict with on the fly instead of ``pred``: a checkpoint, or weights for a zoo entry."""
    label_space: str | None = None
    """Label space of the ground truth and predictions (:mod:`occkit.label_space`); None: the model's, or
    ``occ3d``. A model of another label space is refused."""
    device: str = "cpu"
    """Where the model runs."""
    sweeps: int = 0
    """Earlier LiDAR sweeps added to the key frame's points in the LiDAR overlay."""
    display_width: int = 800
    """Camera images wider than this are shown resized to this width (pixels)."""
    dpi: int = 100
    """Resolution of the PNGs."""
    colors: int | None = None
    """Store the PNGs with an adaptive palette of this many colours (at most 256): files several times smaller."""

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError(f"frames must be at least 1, got {self.frames}")
        if self.sweeps < 0:
            raise ValueError(f"sweeps must be >= 0, got {self.sweeps}")
        if self.display_width < 16:
            raise ValueError(f"display_width must be at least 16 pixels, got {self.display_width}")
        if self.colors is not None and not MIN_PALETTE_COLORS <= self.colors <= 256:
            raise ValueError(f"colors must lie in {MIN_PALETTE_COLORS}..256, got {self.colors}")
        if self.pred is not None and self.model is not None:
            raise ValueError("give predictions as a folder (pred) or a model to predict with, not both")


def _pick(records: list[FrameRecord], config: VizConfig) -> list[int]:
    """Indices of the frames to render: the requested tokens, or ``frames`` spread over the split."""
    if config.tokens:
        position = {record.token: i for i, record in enumerate(records)}
        unknown = [token for token in config.tokens if token not in position]
        if unknown:
            raise ValueError(f"{config.data}: split {config.split!r} has no sample token {unknown[0]!r}"
                             + (f" (and {len(unknown) - 1} more unknown)" if len(unknown) > 1 else ""))  # fmt: skip
        return [position[token] for token in dict.fromkeys(config.tokens)]
    count = min(config.frames, len(records))
    return sorted({int(i) for i in np.linspace(0, len(records) - 1, count).round()})


def _display_transform(image_path: Path, width: int) -> ImageAugConfig:
    """The test-time image transform that shows the original image, resized to at most ``width`` pixels wide."""
    with Image.open(image_path) as image:
        original_w, original_h = image.size
    shown_w = min(original_w, width)
    # The test transform crops ``final_size`` from the bottom of the resized image: taking the whole resized height
    # (as the transform rounds it) makes that crop the entire image.
    shown_h = int(np.floor(original_h * shown_w / original_w + 1e-6))
    return ImageAugConfig(final_size=(shown_h, shown_w), bottom_crop=True)


def _camera_set(dataset: OccupancyDataset, record: FrameRecord, sample: Sample) -> CameraSet:
    """The cameras of ``sample`` with their images at the dataset's test-time transform, as uint8 pixels."""
    images = []
    for i, name in enumerate(dataset.config.cameras):
        with Image.open(dataset.root / record.cameras[name].path) as image:
            image = image.convert("RGB")
        params = sample_image_aug(dataset.config.image_aug, image.size, False, np.random.default_rng(0))
        # The pixels shown must be the ones the sample's matrix describes, or every overlay would be off.
        if not torch.allclose(params.matrix(), sample.img_aug[i], atol=1e-4):
            raise RuntimeError(f"sample {sample.token} {name}: displayed image transform differs from img_aug")
        images.append(augment_image(image, params))
    return CameraSet.from_sample(sample, dataset.config.cameras, np.stack(images))


def folder_predictor(folder: Path, tokens: Sequence[str], space: LabelSpace) -> Predictor:
    """Predictions read from ``folder/<token>.npz``; every frame's file is checked before anything is drawn or
    recorded (``occkit viz`` and ``occkit view``)."""
    from occkit.metrics.evaluate import read_prediction, read_prediction_instances

    if not folder.is_dir():
        raise FileNotFoundError(f"prediction folder {folder} does not exist")
    files = {token: path_under(folder, safe_name(token, "sample token") + ".npz", f"--pred {folder}")
             for token in tokens}  # fmt: skip
    for token, path in files.items():
        if not path.is_file():
            raise FileNotFoundError(f"no prediction for sample {token}: {path} not found")
    return lambda token: Predicted(read_prediction(files[token], space), read_prediction_instances(files[token], space))


def _model_predictor(config: VizConfig) -> tuple[Predictor, LabelSpace]:
    """The model's predictions by token, and its label space."""
    from occkit.data.collate import collate
    from occkit.engine.evaluate import evaluation_dataset

    model, experiment, space = config.model.load_predicting(config.label_space, config.device)
    experiment = dataclasses.replace(experiment, data=dataclasses.replace(experiment.data, version=config.version))
    dataset = evaluation_dataset(experiment, config.data, config.split, labels=False)
    position = {record.token: i for i, record in enumerate(dataset.records)}

    @torch.no_grad()
    def predict(token: str) -> Predicted:
        prediction = model.predict(collate([dataset[position[token]]]).to(config.device))
        instances = None if prediction.instances is None else prediction.instances[0].cpu().numpy()
        return Predicted(prediction.semantics[0].cpu().numpy(), instances)

    return predict, space


def _views(
    sample: Sample, cameras: CameraSet | None, predicted: Predicted | None, pred_name: str, title: str,
    space: LabelSpace,
) -> list[tuple[str, str, Callable[[], Figure]]]:
    """``(file stem, caption, figure factory)`` of every view the frame has data for."""
    pred = None if predicted is None else predicted.semantics
    gt = None if sample.voxel_semantics is None else sample.voxel_semantics.numpy()
    mask = None if sample.mask_camera is None else sample.mask_camera.numpy()
    orientation = "forward up, left on the left" if space.frame == "ego" else f"the {space.frame} frame's x up"
    visible, under = ("camera-visible voxels", "under the camera mask") if mask is not None else ("all voxels", "")
    views = []
    if gt is not None:
        panels = "; left panel all labels, right panel the camera-visible voxels" if mask is not None else ""
        views.append(("bev_gt", f"Ground truth, bird's-eye view: class of the top-most occupied voxel, "
                      f"{orientation}{panels}.",
                      partial(bev_figure, gt, mask, space, title=f"{title}: ground truth")))  # fmt: skip
        car = ", seen from behind and above the ego car (black box)" if space.frame == "ego" else ""
        views.append(("voxels_gt", f"Ground truth in 3D ({visible}){car}.",
                      partial(voxel_figure, gt, mask, space, title=f"{title}: ground truth")))  # fmt: skip
    if pred is not None and gt is not None:
        views.append(("compare", f"Ground truth, {pred_name} and the error map {under}, with the frame's mIoU and "
                      "IoU.", partial(comparison_figure, gt, pred, mask, space, title=title,
                                      pred_name=pred_name)))  # fmt: skip
    if pred is not None:
        seen = " (the voxels the cameras see in the ground truth)" if mask is not None else ""
        views.append(("voxels_pred", f"{pred_name} in 3D{seen}.",
                      partial(voxel_figure, pred, mask, space, title=f"{title}: {pred_name}")))  # fmt: skip
    # Panoptic: every object its own colour, the same in every frame where its id holds (the synthetic world's do).
    for stem, grid, ids, what in (("instances_gt", gt, sample.voxel_instances, "Ground truth"),
                                  ("instances_pred", pred, None if predicted is None else predicted.instances,
                                   pred_name)):  # fmt: skip
        if grid is not None and ids is not None:
            views.append((stem, f"{what}'s instances in 3D{' (camera-visible voxels)' if mask is not None else ''}: "
                          "each object its own colour, stuff by class.",
                          partial(voxel_figure, grid, mask, space, title=f"{title}: {what} instances",
                                  instances=np.asarray(ids))))  # fmt: skip
    if cameras is None:
        return views
    if sample.points is not None:
        points = lidar_points_in_ego(sample)
        views.append(("cameras_lidar", "Surround cameras with the LiDAR points projected, coloured by depth.",
                      partial(lidar_camera_figure, cameras, points, title=f"{title}: LiDAR")))  # fmt: skip
    # The labels' own augmentation and frame: ego (Occ3D: occ_aug) or LiDAR (SurroundOcc: bev_aug, then lidar2ego).
    label_frame = (sample.occ_aug, space, None) if space.frame == "ego" else (sample.bev_aug, space, sample.lidar2ego)
    for stem, grid, what in (("cameras_gt", gt, "ground truth"), ("cameras_pred", pred, pred_name)):
        if grid is not None:
            views.append((stem, f"Surround cameras with the {what}'s occupied voxels projected, coloured by class.",
                          partial(occupancy_camera_figure, cameras, grid, mask, *label_frame,
                                  title=f"{title}: {what} voxels")))  # fmt: skip
    return views


def _render_frame(
    dataset: OccupancyDataset, index: int, predict: Predictor | None, pred_name: str, config: VizConfig
) -> tuple[list[PageImage], dict]:
    """Every view of one frame into ``out/<token>/``; the page's images and the frame's JSON entry."""
    record = dataset.records[index]
    sample = dataset[index]
    predicted = None if predict is None else predict(record.token)
    pred = None if predicted is None else predicted.semantics
    cameras = _camera_set(dataset, record, sample) if dataset.config.cameras else None
    images, files = [], {}
    title = f"{record.scene} / {record.token}"
    for stem, caption, draw in _views(sample, cameras, predicted, pred_name, title, dataset.space):
        folder = path_under(config.out, safe_name(record.token, "sample token"), f"--out {config.out}")
        path = save_figure(draw(), folder / f"{stem}.png", config.dpi, config.colors)
        files[stem] = f"{record.token}/{path.name}"
        images.append(PageImage(files[stem], caption))
    entry = {"token": record.token, "scene": record.scene, "files": files}
    if pred is not None and sample.voxel_semantics is not None:
        mask = None if sample.mask_camera is None else sample.mask_camera.numpy()
        entry["scores"] = frame_scores(sample.voxel_semantics.numpy(), pred, mask, dataset.space)
        entry["scored_under"] = "camera mask" if mask is not None else "every voxel"
    return images, entry


def render_frames(config: VizConfig, progress: Callable[[str], None] = print) -> dict:
    """Render the frames of ``config`` and write the page and ``index.json``.

    Raises:
        FileNotFoundError: missing data root, prediction folder, prediction file or checkpoint.
        ValueError: unknown split or token, or nothing to show (no labels and no predictions).

    Returns:
        the index written to ``index.json``: the frames with their files (relative to ``out``) and scores, and
        the pages.
    """
    root = Path(config.data)
    if not root.is_dir():
        raise FileNotFoundError(f"data root {root} does not exist")
    # Predictions are named after their folder, or the model (a checkpoint's run folder, e.g. runs/demo/daocc_tiny).
    predict, pred_name, space = None, "prediction", label_space(config.label_space or "occ3d")
    if config.model is not None:
        (predict, space), pred_name = _model_predictor(config), f"prediction ({config.model.label})"
    common = {"root": str(root), "version": config.version, "split": config.split, "boxes": False,
              "label_space": space.name}  # fmt: skip
    listing = OccupancyDataset(DatasetConfig(**common, cameras=(), sweeps=-1, occupancy=False))
    records = listing.records
    picks = _pick(records, config)
    cameras = tuple(name for name in CAMERAS if name in records[0].cameras)
    image_aug = _display_transform(root / records[0].cameras[cameras[0]].path, config.display_width) if cameras \
        else ImageAugConfig()  # fmt: skip
    labelled = all(listing.label_path(records[i]).is_file() for i in picks)
    panoptic = labelled and carry_instances(space, (listing.label_path(records[i]) for i in picks))
    dataset = OccupancyDataset(DatasetConfig(**common, cameras=cameras, sweeps=config.sweeps, occupancy=labelled,
                                             instances=panoptic, image_aug=image_aug))  # fmt: skip
    if config.pred is not None:
        tokens = [records[i].token for i in picks]
        predict = folder_predictor(Path(config.pred), tokens, space)
        pred_name = f"prediction ({Path(config.pred).name})"
    if not labelled and predict is None:
        raise ValueError(f"{root}: the chosen frames of split {config.split!r} have no {space.name} labels; give "
                         "predictions")  # fmt: skip
    sections, frames = [], []
    for number, index in enumerate(picks, start=1):
        images, entry = _render_frame(dataset, index, predict, pred_name, config)
        scores = entry.get("scores")
        text = "" if scores is None else f"This frame: {format_scores(scores)} ({entry['scored_under']})."
        sections.append(Section(f"{entry['scene']} / {entry['token']}", text, tuple(images)))
        frames.append(entry)
        progress(f"[viz] {number}/{len(picks)} {entry['token']}: {len(images)} images")
    source = config.pred or (None if config.model is None else str(config.model))
    intro = (f"{len(frames)} frame(s) of split {config.split} of {root} ({config.version})"
             + (f", predictions from {source}" if source else "") + ".")  # fmt: skip
    pages = write_page(config.out, "occkit viz", intro, sections)
    index = {"data": str(root), "version": config.version, "split": config.split, "predictions": source,
             "pages": {kind: path.name for kind, path in pages.items()}, "frames": frames}  # fmt: skip
    (Path(config.out) / "index.json").write_text(json.dumps(index, indent=2) + "\n")
    progress(f"[viz] page: {pages['html']} (and {pages['markdown'].name}), index: {Path(config.out) / 'index.json'}")
    return index
