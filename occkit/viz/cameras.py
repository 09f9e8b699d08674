"""The six surround cameras with projected LiDAR points (coloured by depth) or occupied voxels (coloured by class).

Projection uses the frame's own matrices and nothing else: a point ``p`` of the ego frame lands at
``img_aug @ K @ (inv(cam2ego) @ p)`` after the perspective division (docs/conventions.md), where ``img_aug`` maps the
original image to the displayed one, so overlays stay exact when images are shown resized. Overlays are drawn from
the farthest point to the nearest, so that near content covers what it hides.

Panels follow the nuScenes surround layout: CAM_FRONT_LEFT, CAM_FRONT, CAM_FRONT_RIGHT on top, CAM_BACK_LEFT,
CAM_BACK, CAM_BACK_RIGHT below, each titled with its camera name.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from torch import Tensor

from occkit.classes import IGNORE_INDEX
from occkit.figure import new_figure
from occkit.geometry.camera import project_points
from occkit.geometry.grid import OCC3D_GRID, VoxelGrid
from occkit.geometry.se3 import invert_transform, transform_points
from occkit.label_space import OCC3D_SPACE, LabelSpace
from occkit.nuscenes import CAMERAS
from occkit.types import Sample
from occkit.viz.palette import add_class_legend, class_colors

__all__ = [
    "SURROUND_LAYOUT",
    "CameraSet",
    "lidar_points_in_ego",
    "voxel_centres_in_ego",
    "camera_figure",
    "lidar_camera_figure",
    "occupancy_camera_figure",
]

#: Panel rows of the surround view: front cameras left to right on top, back cameras below.
SURROUND_LAYOUT = (CAMERAS[:3], CAMERAS[3:])
_PANEL_WIDTH = 4.0  # inches per camera panel
_GAP = 0.05  # inches between panels
_TITLE = 0.22  # inches above each panel for its title


@dataclass(frozen=True, eq=False)
class CameraSet:
    """The displayed images of one frame's cameras and the matrices that project ego points into them.

    Attributes:
        names: ``N`` camera channels.
        images: ``(N, H, W, 3)`` uint8, the displayed images.
        intrinsics: ``(N, 3, 3)`` pinhole matrices of the original images.
        cam2ego: ``(N, 4, 4)`` camera -> ego.
        img_aug: ``(N, 3, 3)`` original -> displayed pixels.
    """

    names: tuple[str, ...]
    images: np.ndarray
    intrinsics: Tensor
    cam2ego: Tensor
    img_aug: Tensor

    def __post_init__(self) -> None:
        count = len(self.names)
        shapes = {"images": (count, *self.images.shape[1:3], 3), "intrinsics": (count, 3, 3),
                  "cam2ego": (count, 4, 4), "img_aug": (count, 3, 3)}  # fmt: skip
        for name, shape in shapes.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"CameraSet.{name} has shape {tuple(getattr(self, name).shape)}, expected {shape}")

    @classmethod
    def from_sample(cls, sample: Sample, names: tuple[str, ...], images: np.ndarray) -> CameraSet:
        """The cameras of a loaded sample, shown as ``images``: ``(N, H, W, 3)`` uint8, the augmented images that
        ``sample.img_aug`` maps the original pixels to."""
        if sample.intrinsics is None:
            raise ValueError(f"sample {sample.token}: no cameras were loaded")
        return cls(tuple(names), images, sample.intrinsics.float(), sample.cam2ego.float(), sample.img_aug.float())

    @property
    def image_size(self) -> tuple[int, int]:
        """``(H, W)`` of the displayed images."""
        return self.images.shape[1], self.images.shape[2]

    def project(self, points_ego: Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project ego-frame points into every camera.

        Args:
            points_ego: ``(P, 3)`` points in the ego frame.

        Returns:
            uv: ``(N, P, 2)`` float32 displayed-image pixels; depth: ``(N, P)`` camera z; valid: ``(N, P)`` bool,
            in front of the camera and inside the image.
        """
        ego2cam = invert_transform(self.cam2ego)  # (N, 4, 4)
        points = points_ego.to(device=ego2cam.device, dtype=torch.float32)[None]  # (1, P, 3)
        uv, depth, valid = project_points(points, ego2cam, self.intrinsics, self.img_aug, self.image_size)
        return uv.cpu().numpy(), depth.cpu().numpy(), valid.cpu().numpy()

    def focal_scale(self) -> np.ndarray:
        """``(N,)`` displayed pixels per unit of ``x / z``: the focal length after the image augmentation."""
        linear = self.img_aug[:, :2, :2] @ self.intrinsics[:, :2, :2]  # (N, 2, 2)
        return torch.linalg.det(linear).abs().sqrt().cpu().numpy()


def lidar_points_in_ego(sample: Sample) -> Tensor:
    """``(P, 3)`` LiDAR points of a sample in the (un-augmented) ego frame: undo ``bev_aug``, apply ``lidar2ego``."""
    if sample.points is None:
        raise ValueError(f"sample {sample.token}: no LiDAR points were loaded")
    lidar = transform_points(torch.linalg.inv(sample.bev_aug.double()), sample.points[:, :3].double())
    return transform_points(sample.lidar2ego.double(), lidar).float()


def voxel_centres_in_ego(index: np.ndarray, occ_aug: Tensor | None = None, grid: VoxelGrid = OCC3D_GRID,
                         label2ego: Tensor | None = None) -> Tensor:
    """``(V, 3)`` float32 CPU ego-frame centres of voxels ``index`` (``(V, 3)`` int) of ``grid``: ``occ_aug`` (the
    augmentation in the labels' frame) undone if given, then ``label2ego`` ``(4, 4)`` applied if the labels live in
    another frame than the ego frame (SurroundOcc: the sample's ``lidar2ego``)."""
    lower, size = grid.lower_tensor(dtype=torch.float64), grid.size_tensor(dtype=torch.float64)
    centres = (torch.from_numpy(np.asarray(index)).double() + 0.5) * size + lower  # (V, 3)
    if occ_aug is not None:
        centres = transform_points(torch.linalg.inv(occ_aug.detach().cpu().double()), centres)
    if label2ego is not None:
        centres = transform_points(label2ego.detach().cpu().double(), centres)
    return centres.float()


def camera_figure(cameras: CameraSet, title: str = "", legend_height: float = 0.0) -> tuple[Figure, dict[str, Axes]]:
    """The surround layout with each camera's image, titled with its name; cameras the set lacks stay blank.

    Axes positions are fixed (no layout engine), so that overlays can size markers in image pixels.

    Args:
        cameras: the images to show.
        title: figure title.
        legend_height: inches kept free below the panels (for a legend or colour bar).

    Returns:
        the figure and its axes by camera name (only the cameras of the set).
    """
    height, width = cameras.image_size
    panel_h = _PANEL_WIDTH * height / width
    rows, columns = len(SURROUND_LAYOUT), len(SURROUND_LAYOUT[0])
    top = 0.3 if title else 0.0
    fig_w = columns * _PANEL_WIDTH + (columns - 1) * _GAP
    fig_h = top + rows * (panel_h + _TITLE) + (rows - 1) * _GAP + legend_height
    figure = new_figure(fig_w, fig_h)
    axes = {}
    for row, names in enumerate(SURROUND_LAYOUT):
        for column, name in enumerate(names):
            left = column * (_PANEL_WIDTH + _GAP)
            bottom = fig_h - top - (row + 1) * (panel_h + _TITLE) - row * _GAP
            axis = figure.add_axes((left / fig_w, bottom / fig_h, _PANEL_WIDTH / fig_w, panel_h / fig_h))
            axis.set_axis_off()
            if name not in cameras.names:
                axis.set_title(f"{name} (not loaded)", fontsize=8, color="0.5")
                continue
            axis.imshow(cameras.images[cameras.names.index(name)], interpolation="bilinear")
            axis.set_xlim(0, width)
            axis.set_ylim(height, 0)
            axis.set_title(name, fontsize=8)
            axes[name] = axis
    if title:
        figure.suptitle(title, fontsize=9, y=1 - 0.08 / fig_h)
    return figure, axes


def _points_per_pixel(cameras: CameraSet) -> float:
    """Typographic points per displayed image pixel in :func:`camera_figure` panels (marker sizes are in points)."""
    return _PANEL_WIDTH * 72.0 / cameras.image_size[1]


def _draw_far_to_near(axis: Axes, uv: np.ndarray, depth: np.ndarray, colors: np.ndarray, sizes: np.ndarray,
                      alpha: float, marker: str) -> None:  # fmt: skip
    order = np.argsort(-depth, kind="stable")  # farthest first: nearer points are drawn over what they hide
    axis.scatter(uv[order, 0], uv[order, 1], s=sizes[order], c=colors[order], marker=marker, alpha=alpha,
                 linewidths=0, rasterized=True)  # fmt: skip


def lidar_camera_figure(cameras: CameraSet, points_ego: Tensor, max_depth: float = 60.0, point_px: float = 2.0,
                        title: str = "") -> Figure:  # fmt: skip
    """The surround cameras with LiDAR points projected and coloured by their depth along each camera's axis.

    Args:
        cameras: images and matrices.
        points_ego: ``(P, 3)`` points in the ego frame (see :func:`lidar_points_in_ego`).
        max_depth: depth (m) at the end of the colour map.
        point_px: marker side in displayed image pixels.
        title: figure title.
    """
    figure, axes = camera_figure(cameras, title, legend_height=0.7)
    uv, depth, valid = cameras.project(points_ego)
    cmap, norm = colormaps["turbo"], Normalize(0.0, max_depth)
    size = (point_px * _points_per_pixel(cameras)) ** 2
    for name, axis in axes.items():
        i = cameras.names.index(name)
        keep = valid[i]
        colors = cmap(norm(depth[i, keep]))  # (M, 4)
        _draw_far_to_near(axis, uv[i, keep], depth[i, keep], colors, np.full(int(keep.sum()), size), 1.0, "o")
    bar = figure.add_axes((0.3, 0.42 / figure.get_figheight(), 0.4, 0.12 / figure.get_figheight()))
    figure.colorbar(ScalarMappable(norm, cmap), cax=bar, orientation="horizontal")
    bar.set_xlabel("depth along the camera axis (m)", fontsize=7)
    bar.tick_params(labelsize=6)
    return figure


def occupancy_camera_figure(
    cameras: CameraSet,
    semantics: np.ndarray,
    mask: np.ndarray | None = None,
    occ_aug: Tensor | None = None,
    space: LabelSpace = OCC3D_SPACE,
    label2ego: Tensor | None = None,
    alpha: float = 0.5,
    marker_scale: float = 0.75,
    title: str = "",
) -> Figure:
    """The surround cameras with the centres of occupied voxels projected and coloured by class.

    Each voxel centre is a half-transparent square, ``marker_scale`` times as wide as the voxel appears at its depth
    (voxel size times focal length over depth; at most an eighth of the image width, since the square stands for a
    cube only far from the camera), drawn from the farthest to the nearest so that near voxels cover what they hide.

    Args:
        cameras: images and matrices.
        semantics: ``(X, Y, Z)`` labels of ``space`` (ground truth or prediction) in the occupancy frame.
        mask: optional ``(X, Y, Z)`` visibility mask; only the voxels it keeps are drawn.
        occ_aug: the sample's augmentation in the labels' frame, undone before projecting (identity if None).
        space: the label space of ``semantics`` (grid, free class, colours).
        label2ego: ``(4, 4)`` labels' frame -> ego frame when ``space`` is not in the ego frame (SurroundOcc's
            LiDAR frame: the sample's ``lidar2ego``).
        alpha: marker opacity.
        marker_scale: marker width over the voxel's apparent width.
        title: figure title.
    """
    semantics = np.asarray(semantics)
    if (space.frame == "ego") != (label2ego is None):
        raise ValueError(f"{space.name} labels live in the {space.frame} frame: give label2ego exactly when that is "
                         "not the ego frame")  # fmt: skip
    grid = space.grid
    drawn = (semantics != space.free_index) & (semantics != IGNORE_INDEX)
    if mask is not None:
        drawn &= np.asarray(mask, dtype=bool)
    index = np.argwhere(drawn)  # (V, 3)
    classes = semantics[tuple(index.T)]
    figure, axes = camera_figure(cameras, title, legend_height=0.5)
    uv, depth, valid = cameras.project(voxel_centres_in_ego(index, occ_aug, grid, label2ego))
    colors = class_colors(classes, space.taxonomy) / 255.0  # (V, 3)
    voxel = float(np.mean(grid.voxel_size))
    focal, per_pixel = cameras.focal_scale(), _points_per_pixel(cameras)
    largest = cameras.image_size[1] / 8
    for name, axis in axes.items():
        i = cameras.names.index(name)
        keep = valid[i]
        side_px = np.clip(marker_scale * focal[i] * voxel / depth[i, keep], 1.0, largest)  # displayed pixels
        _draw_far_to_near(axis, uv[i, keep], depth[i, keep], colors[keep], (side_px * per_pixel) ** 2, alpha, "s")
    legend_axis = next(iter(axes.values()), None)
    if legend_axis is not None:
        add_class_legend(legend_axis, np.unique(classes), taxonomy=space.taxonomy, loc="lower center", ncol=9,
                         fontsize=7, bbox_to_anchor=(0.5, 0.02), bbox_transform=figure.transFigure)  # fmt: skip
    return figure
