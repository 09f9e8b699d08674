"""From a scene's aggregated points to one key frame's voxel labels: placement, majority vote, densification.

At a key frame the static points move into the label frame and every object annotated there gets its accumulated
points placed at its box (kept inside the enlarged box, as SurroundOcc does); static points inside those boxes
above the ground are stale (something else stood there before) and are dropped. Voxels take the class most of
their points have (ties to the lower class id).

Densification (``densify="poisson"``) follows SurroundOcc: normals from the 20 nearest neighbours, oriented
toward the key frame's sensor, Poisson surface reconstruction (octree depth 10) with the vertices of the lowest
10% density removed; the voxels the remaining vertices fall in are occupied too, with the class of the nearest
labelled point. It needs open3d (``pip install -e ".[labels]"``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occkit.errors import require_module
from occkit.geometry.grid import VoxelGrid
from occkit.labeling.aggregate import AggregateConfig, SceneCloud, object_membership, points_in_boxes
from occkit.labeling.sources import Boxes

__all__ = ["DENSIFY_METHODS", "DensifyConfig", "key_frame_points", "vote", "require_open3d", "densify_poisson"]

#: Densification methods: none, or SurroundOcc's Poisson surface reconstruction.
DENSIFY_METHODS = ("none", "poisson")


@dataclass(frozen=True)
class DensifyConfig:
    """SurroundOcc's Poisson settings (its ``config.yaml``), and a downsampling step before it."""

    depth: int = 10
    """Octree depth of the reconstruction."""
    min_density: float = 0.1
    """Share of vertices, those of lowest density (far from any point), removed from the mesh."""
    max_nn: int = 20
    """Neighbours of the normal estimate."""
    downsample: float = 0.1
    """Points are thinned to one per cube of this edge (m) before the reconstruction; 0 keeps all."""


def key_frame_points(
    cloud: SceneCloud,
    boxes: Boxes,
    frame2global: np.ndarray,
    grid: VoxelGrid,
    config: AggregateConfig,
    margin: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The scene's points as they stand at one key frame, in its label frame.

    Args:
        cloud: the aggregated scene.
        boxes: the boxes annotated at the key frame.
        frame2global: ``(4, 4)`` the label frame (ego or LiDAR at the key frame) to global.
        grid: the label grid; points outside it (grown by ``margin`` metres) are left out.
        config: the aggregation settings (box enlargement, ground clearance).
        margin: metres around the grid kept as well (densification needs context beyond the edge).

    Returns:
        ``(M, 3)`` float64 points in the label frame and ``(M,)`` uint8 their classes.
    """
    global2frame = np.linalg.inv(frame2global)
    lower = np.asarray(grid.lower) - margin
    upper = np.asarray(grid.upper) + margin
    # A cheap cut by distance, on the stored float32 offsets from the scene origin, before anything is converted or
    # transformed: the grid's circumscribed radius around the frame's origin.
    radius = np.linalg.norm(np.maximum(np.abs(lower[:2]), np.abs(upper[:2])))
    centre = (frame2global[:2, 3] - cloud.origin[:2]).astype(np.float32)
    near = np.abs(cloud.static_xyz[:, :2] - centre).max(axis=1) <= radius
    static = cloud.static_xyz[near].astype(np.float64) + cloud.origin
    static_label = cloud.static_label[near]
    # Static points inside a box at this instant that stand above its ground belong to the object, not the scene.
    owner, local = points_in_boxes(static, boxes, config.box_scale)
    stale = object_membership(owner, local, boxes, None, config)
    xyz, labels = [static[~stale]], [static_label[~stale]]
    box2global = boxes.box2global()
    half = boxes.size[:, [1, 0, 2]] * (config.box_scale / 2)
    for b, instance in enumerate(boxes.instance.tolist()):
        if instance not in cloud.objects:
            continue
        points, classes = cloud.objects[instance]
        inside = (np.abs(points) <= half[b]).all(axis=1)
        xyz.append(points[inside].astype(np.float64) @ box2global[b, :3, :3].T + box2global[b, :3, 3])
        labels.append(classes[inside])
    xyz = np.concatenate(xyz) @ global2frame[:3, :3].T + global2frame[:3, 3]
    labels = np.concatenate(labels)
    keep = ((xyz >= lower) & (xyz < upper)).all(axis=1)
    return xyz[keep], labels[keep]


def vote(points: np.ndarray, labels: np.ndarray, grid: VoxelGrid, empty: int) -> np.ndarray:
    """``(X, Y, Z)`` uint8 labels: each voxel the class most of its points have (ties to the lower id), else
    ``empty``. Points outside the grid are ignored."""
    index = np.floor((points - np.asarray(grid.lower)) / np.asarray(grid.voxel_size)).astype(np.int64)
    inside = ((index >= 0) & (index < np.asarray(grid.shape))).all(axis=1)
    flat = np.ravel_multi_index(tuple(index[inside].T), grid.shape)
    keys, counts = np.unique(flat * 256 + labels[inside].astype(np.int64), return_counts=True)
    voxel, label = keys // 256, keys % 256
    order = np.lexsort((label, -counts, voxel))
    first = np.ones(len(order), bool)
    first[1:] = voxel[order][1:] != voxel[order][:-1]
    semantics = np.full(grid.num_voxels, empty, np.uint8)
    semantics[voxel[order][first]] = label[order][first]
    return semantics.reshape(grid.shape)


def require_open3d():
    """The open3d module; a :class:`~occkit.errors.MissingDependencyError` (exit code 2 on the command line: the
    user can install it) with the install command where it is missing."""
    open3d = require_module("open3d", "densify=poisson", 'pip install -e ".[labels]" (on Linux open3d also needs '
                            "the system library libusb-1.0, e.g. apt-get install libusb-1.0-0)")  # fmt: skip
    # Poisson's solver warns about numerical corner cases on every frame; errors still show.
    open3d.utility.set_verbosity_level(open3d.utility.VerbosityLevel.Error)
    return open3d


def densify_poisson(
    points: np.ndarray,
    labels: np.ndarray,
    sensor: np.ndarray,
    semantics: np.ndarray,
    grid: VoxelGrid,
    empty: int,
    config: DensifyConfig = DensifyConfig(),  # noqa: B008 - frozen
) -> np.ndarray:
    """Occupy the voxels of the Poisson surface of ``points`` too (module doc); returns new ``(X, Y, Z)`` labels.

    Args:
        points: ``(M, 3)`` float64 labelled points in the label frame (a margin around the grid helps the surface).
        labels: ``(M,)`` uint8 their classes.
        sensor: ``(3,)`` the key frame's sensor position in the label frame (normals face it).
        semantics: ``(X, Y, Z)`` the voted labels; voxels that hold points keep their class.
        grid: the label grid.
        empty: the empty label.
        config: Poisson settings.
    """
    o3d = require_open3d()
    from scipy.spatial import cKDTree

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(points)
    if config.downsample > 0:
        cloud = cloud.voxel_down_sample(config.downsample)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(config.max_nn))
    cloud.orient_normals_towards_camera_location(np.asarray(sensor, np.float64))
    # One thread: the reconstruction is then the same bytes on every run.
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=config.depth, n_threads=1)
    density = np.asarray(density)
    vertices = np.asarray(mesh.vertices)[density >= np.quantile(density, config.min_density)]
    index = np.floor((vertices - np.asarray(grid.lower)) / np.asarray(grid.voxel_size)).astype(np.int64)
    inside = ((index >= 0) & (index < np.asarray(grid.shape))).all(axis=1)
    voxels = np.unique(np.ravel_multi_index(tuple(index[inside].T), grid.shape))
    dense = semantics.reshape(-1).copy()
    new = voxels[dense[voxels] == empty]
    if len(new):
        centres = np.asarray(grid.lower) + (np.stack(np.unravel_index(new, grid.shape), axis=1) + 0.5) * np.asarray(
            grid.voxel_size
        )
        _, nearest = cKDTree(points).query(centres, k=1)
        dense[new] = labels[nearest]
    return dense.reshape(grid.shape)
