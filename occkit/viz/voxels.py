"""3D voxel renders: occupied voxels coloured by class, lit, seen from behind and above the ego car.

``Axes3D.voxels`` draws six faces per voxel and takes minutes on a 200 x 200 x 16 Occ3D grid. Here only the faces
that can be seen are built, as one ``Poly3DCollection``: a face is kept when the voxel behind it is not drawn
(interior faces never show) and when it faces the viewer (the view is orthographic, so one direction decides).
Neither loses anything of an opaque voxel surface, and a few thousand to a few tens of thousands of quads remain,
which matplotlib depth-sorts (by face centre) and draws in well under a second (docs/visualisation.md has timings).
Faces are shaded by a fixed directional light, so that the visible sides of a voxel differ in brightness and shapes
read as solids.
"""

from __future__ import annotations

import math

import numpy as np
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d import Axes3D
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from occkit.classes import IGNORE_INDEX
from occkit.figure import new_figure
from occkit.label_space import OCC3D_SPACE, LabelSpace
from occkit.viz.bev import EGO_BOX
from occkit.viz.palette import add_class_legend, class_colors, instance_colors

__all__ = ["EGO_COLOR", "voxel_faces", "view_direction", "draw_voxels", "voxel_figure"]

#: Outward unit normals of the six faces of a voxel, and for each its four corners as offsets in voxel units,
#: ordered around the face.
_FACES = {
    (-1, 0, 0): ((0, 0, 0), (0, 1, 0), (0, 1, 1), (0, 0, 1)),
    (1, 0, 0): ((1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1)),
    (0, -1, 0): ((0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)),
    (0, 1, 0): ((0, 1, 0), (1, 1, 0), (1, 1, 1), (0, 1, 1)),
    (0, 0, -1): ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)),
    (0, 0, 1): ((0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)),
}
#: Direction towards the light (ego frame): mostly from above, a little from behind and from the left.
_LIGHT = np.array((-0.35, 0.45, 0.82)) / np.linalg.norm((-0.35, 0.45, 0.82))
_AMBIENT = 0.45
#: RGB of the ego car's box.
EGO_COLOR = (25, 25, 25)


def view_direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """``(3,)`` unit vector from the scene towards an orthographic viewer placed as ``Axes3D.view_init`` does."""
    elevation, azimuth = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array((math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                     math.sin(elevation)))  # fmt: skip


def voxel_faces(
    drawn: np.ndarray, towards_viewer: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The visible faces of a set of voxels.

    Args:
        drawn: ``(X, Y, Z)`` bool, the voxels to draw.
        towards_viewer: optional ``(3,)`` direction to an orthographic viewer; faces turned away from it are
            dropped (back-face culling).

    Returns:
        voxels: ``(F, 3)`` int64 index of the voxel each face belongs to.
        corners: ``(F, 4, 3)`` float64 face corners in voxel units (voxel ``(i, j, k)`` spans ``[i, i + 1]``...).
        normals: ``(F, 3)`` float64 outward unit normals.
    """
    drawn = np.asarray(drawn, dtype=bool)
    if drawn.ndim != 3:
        raise ValueError(f"drawn must be (X, Y, Z), got shape {drawn.shape}")
    voxels, corners, normals = [], [], []
    padded = np.pad(drawn, 1)  # (X + 2, Y + 2, Z + 2): voxels beyond the grid count as not drawn
    inner = tuple(slice(1, -1) for _ in range(3))
    for normal, offsets in _FACES.items():
        if towards_viewer is not None and np.dot(normal, towards_viewer) <= 0:
            continue
        neighbour = padded[tuple(slice(1 + n, padded.shape[a] - 1 + n) for a, n in enumerate(normal))]
        index = np.argwhere(padded[inner] & ~neighbour)  # (F_n, 3): drawn voxels whose neighbour is not drawn
        voxels.append(index)
        corners.append(index[:, None, :] + np.array(offsets, dtype=np.float64)[None])  # (F_n, 4, 3)
        normals.append(np.broadcast_to(np.array(normal, dtype=np.float64), index.shape))
    if not voxels:
        return np.zeros((0, 3), np.int64), np.zeros((0, 4, 3)), np.zeros((0, 3))
    return np.concatenate(voxels), np.concatenate(corners), np.concatenate(normals)


def _lit(colors: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``(F, 3)`` uint8 colours -> ``(F, 3)`` float in [0, 1], lit by an ambient and a directional light."""
    brightness = _AMBIENT + (1 - _AMBIENT) * np.clip(normals @ _LIGHT, 0.0, None)
    return np.clip(colors / 255.0 * brightness[:, None], 0.0, 1.0)


def _ego_faces() -> np.ndarray:
    """``(6, 4, 3)`` corners of the ego car's box in metres."""
    low, high = np.array(EGO_BOX[:3]), np.array(EGO_BOX[3:])
    return np.stack([low + np.array(offsets) * (high - low) for offsets in _FACES.values()])


def draw_voxels(
    axis: Axes3D,
    semantics: np.ndarray,
    mask: np.ndarray | None = None,
    space: LabelSpace = OCC3D_SPACE,
    elevation_deg: float = 32.0,
    azimuth_deg: float = 195.0,
    zoom: float = 1.5,
    instances: np.ndarray | None = None,
) -> int:
    """Draw the occupied voxels of a label grid on a 3D axis, lit, with the ego car as a black box.

    Args:
        axis: a ``projection="3d"`` axis; its view is set here (orthographic, ``view_init(elevation, azimuth)``;
            azimuth 180 looks forward from straight behind the car).
        semantics: ``(X, Y, Z)`` labels of ``space``.
        mask: optional ``(X, Y, Z)`` visibility mask; only the voxels it keeps are drawn.
        space: the label space of ``semantics`` (voxel size and origin in metres, classes, colours); the ego car is
            drawn when its frame is the ego frame.
        zoom: scale of the grid's box in the axes.
        instances: optional ``(X, Y, Z)`` panoptic instance ids: each object its own colour, stuff (0) its class's
            (:func:`~occkit.viz.palette.instance_colors`).

    Returns:
        the number of faces drawn (the car's six included when drawn).
    """
    grid = space.grid
    semantics = np.asarray(semantics)
    drawn = (semantics != space.free_index) & (semantics != IGNORE_INDEX)
    if mask is not None:
        drawn &= np.asarray(mask, dtype=bool)
    towards_viewer = view_direction(elevation_deg, azimuth_deg)
    voxels, corners, normals = voxel_faces(drawn, towards_viewer)
    size, lower = np.array(grid.voxel_size), np.array(grid.lower)
    faces = tuple(voxels.T)
    base = class_colors(semantics[faces], space.taxonomy) if instances is None else \
        instance_colors(semantics[faces], np.asarray(instances)[faces], space.taxonomy)  # fmt: skip
    colors = _lit(base.astype(np.float64), normals)  # (F, 3)
    corners, edges = corners * size + lower, colors * 0.8  # (F, 4, 3) metres; darker voxel edges
    if space.frame == "ego":
        ego_normals = np.array(list(_FACES), dtype=np.float64)  # (6, 3)
        ego_colors = _lit(np.full((6, 3), EGO_COLOR, dtype=np.float64), ego_normals)
        # One collection, so that matplotlib depth-sorts the ego car's faces among the voxels' faces (separate
        # collections are only sorted as wholes, which would hide the car under the road or draw it over objects).
        corners = np.concatenate((corners, _ego_faces()))  # (F + 6, 4, 3)
        colors = np.concatenate((colors, ego_colors))
        edges = np.concatenate((edges, np.ones((6, 3))))  # white car edges
    axis.add_collection3d(Poly3DCollection(corners, facecolors=colors, edgecolors=edges, linewidths=0.1))
    (x_min, y_min, z_min), (x_max, y_max, z_max) = grid.lower, grid.upper
    axis.set(xlim=(x_min, x_max), ylim=(y_min, y_max), zlim=(z_min, z_max))
    # Metres are metres on every axis; the zoom fills the axes with the flat 80 x 80 x 6.4 m box.
    axis.set_box_aspect((x_max - x_min, y_max - y_min, z_max - z_min), zoom=zoom)
    axis.set_proj_type("ortho")
    axis.view_init(elev=elevation_deg, azim=azimuth_deg)
    axis.set_axis_off()
    return len(corners)


def voxel_figure(
    semantics: np.ndarray,
    mask: np.ndarray | None = None,
    space: LabelSpace = OCC3D_SPACE,
    title: str = "",
    elevation_deg: float = 32.0,
    azimuth_deg: float = 195.0,
    instances: np.ndarray | None = None,
) -> Figure:
    """One frame's occupied voxels in 3D with a class legend; see :func:`draw_voxels`. With ``instances``, every
    object has its own colour and the legend lists the stuff classes and the number of objects."""
    figure = new_figure(8.0, 4.6)
    axis = figure.add_axes((-0.02, -0.05, 0.82, 1.0), projection="3d")
    draw_voxels(axis, semantics, mask, space, elevation_deg, azimuth_deg, instances=instances)
    keep = np.ones(np.shape(semantics), bool) if mask is None else np.asarray(mask, dtype=bool)
    drawn = np.asarray(semantics)[keep]
    extra = [("ego car", EGO_COLOR)] if space.frame == "ego" else []
    if instances is not None:
        ids = np.asarray(instances)[keep]
        drawn = drawn[ids == 0]  # the classes of objects are told by the objects' own colours
        objects = np.unique(ids[ids > 0])
        swatch = instance_colors(np.zeros(1, np.uint8), np.ones(1, np.int32), space.taxonomy)[0]  # object 1's
        extra.append((f"{len(objects)} objects, one colour each", tuple(int(c) for c in swatch)))
    add_class_legend(axis, np.unique(drawn), extra, space.taxonomy, bbox_to_anchor=(1.0, 0.85))
    if title:
        figure.suptitle(title, fontsize=9)
    return figure
