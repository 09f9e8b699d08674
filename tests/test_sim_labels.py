"""Ground truth of the synthetic world: exact voxels of solids, ground layer, priorities, masks, SurroundOcc rows."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from occkit.geometry.grid import OCC3D_GRID, SURROUNDOCC_GRID, VoxelGrid
from occkit.geometry.raycast import traverse_rays
from occkit.geometry.visibility import camera_visibility, lidar_visibility
from occkit.sim.labels import CLASS_PRIORITY, FREE, occupancy_labels, surroundocc_labels
from occkit.sim.primitives import BOX, CYLINDER, ELLIPSOID, GroundMap, Primitives
from occkit.sim.rig import LIDAR_TOP

CAR, PEDESTRIAN, TRAFFIC_CONE, MANMADE, VEGETATION = 4, 7, 8, 15, 16
DRIVEABLE, SIDEWALK, TERRAIN = 11, 13, 14
GROUND_LAYER = 2  # OCC3D_GRID's layer holding z = 0: [-0.2, 0.2)
HALF_DIAGONAL = 0.4 * math.sqrt(3) / 2


def solids(*rows) -> Primitives:
    """Primitives from rows ``(kind, centre (3,), half_size (3,), yaw, class)`` (global frame)."""
    n = len(rows)
    return Primitives(
        kind=np.array([r[0] for r in rows], np.int8),
        center=np.array([r[1] for r in rows], np.float64).reshape(n, 3),
        half_size=np.array([r[2] for r in rows], np.float64).reshape(n, 3),
        yaw=np.array([r[3] for r in rows], np.float64),
        semantic=np.array([r[4] for r in rows], np.uint8),
        instance=np.arange(n, dtype=np.int32),
        color=np.zeros((n, 3), np.float32),
        texture=np.zeros(n, np.uint8),
        reflectivity=np.zeros(n, np.float32),
    )


def pose(yaw: float = 0.0, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    matrix = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    matrix[:2, :2] = [[c, -s], [s, c]]
    matrix[:3, 3] = translation
    return matrix


def transform(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


# Terrain everywhere: an empty raster.
TERRAIN_ONLY = GroundMap(np.zeros((0, 0), np.uint8), np.zeros((0, 0), bool), np.zeros(2), 1.0)


def voxel_centre(i, j, k, grid=OCC3D_GRID) -> np.ndarray:
    return np.asarray(grid.lower) + (np.array([i, j, k]) + 0.5) * np.asarray(grid.voxel_size)


def cell(coordinate: float) -> int:
    """OCC3D_GRID index along x or y of a coordinate (m)."""
    return int(math.floor((coordinate + 40) / 0.4))


def index_of(points: np.ndarray, grid=OCC3D_GRID) -> tuple[np.ndarray, np.ndarray]:
    index, inside = grid.world_to_index(torch.as_tensor(points, dtype=torch.float64))
    return index.numpy(), inside.numpy()


# ------------------------------------------------------------------------------------------------ exact voxels
def test_single_solids_give_hand_computed_voxels():
    ego2global = pose(math.pi / 2, (10.0, 5.0, 0.0))
    ego_yaw = math.pi / 2

    def to_global(point):
        return transform(ego2global, np.asarray(point, float)[None])[0]

    scene = solids(
        # Ego-frame box x [2.1, 3.0], y [-0.5, 0.3], z [0.1, 1.3] (heading along ego x).
        (BOX, to_global([2.55, -0.1, 0.7]), [0.45, 0.4, 0.6], ego_yaw, CAR),
        # A 0.5 m square box at 45 deg, centred on voxel (110, 100, 4): reaches the 4 edge neighbours (0.354 m
        # from the centre along the axes, > 0.2) but not the diagonal ones (corner at 0.4 m L1 distance > 0.354).
        (BOX, to_global(voxel_centre(110, 100, 4)), [0.25, 0.25, 0.3], ego_yaw + math.pi / 4, TRAFFIC_CONE),
        # A cylinder of radius 0.25 centred on voxel (120, 90, 4): edge neighbours (0.2 < 0.25), not the diagonal
        # ones (0.283 > 0.25); half height 0.1 keeps it in layer 4.
        (CYLINDER, to_global(voxel_centre(120, 90, 4)), [0.25, 0.25, 0.1], 0.0, PEDESTRIAN),
        # An ellipsoid 1.4 m long along ego y, centred on voxel (90, 110, 4): j 108..112 only.
        (ELLIPSOID, to_global(voxel_centre(90, 110, 4)), [0.7, 0.15, 0.15], ego_yaw + math.pi / 2, VEGETATION),
        # A sphere of radius 0.25 on voxel (80, 80, 8): its 6 face neighbours, no more.
        (ELLIPSOID, to_global(voxel_centre(80, 80, 8)), [0.25, 0.25, 0.25], 0.3, MANMADE),
    )
    labels = occupancy_labels(scene, TERRAIN_ONLY, ego2global)
    expected = np.full(OCC3D_GRID.shape, FREE, np.uint8)
    expected[:, :, GROUND_LAYER] = TERRAIN
    expected[105:108, 98:101, 2:6] = CAR
    plus = [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)]
    for di, dj in plus:
        expected[110 + di, 100 + dj, 3:6] = TRAFFIC_CONE
        expected[120 + di, 90 + dj, 4] = PEDESTRIAN
    expected[90, 108:113, 4] = VEGETATION
    for offset in [(0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]:
        expected[80 + offset[0], 80 + offset[1], 8 + offset[2]] = MANMADE
    assert labels.dtype == np.uint8 and labels.shape == OCC3D_GRID.shape
    np.testing.assert_array_equal(labels, expected)


def test_touching_faces_follow_floor_semantics():
    # A box whose top face is exactly at a voxel boundary in index arithmetic reaches the voxel above: its top-face
    # points belong to that voxel, as world_to_index says; its bottom face on a boundary does not reach below.
    grid = VoxelGrid((0.0, 0.0, 0.5, 4.0, 4.0, 4.5), 1.0)  # the ground z = 0 lies below it
    scene = solids((BOX, [1.5, 1.5, 2.0], [0.3, 0.3, 0.5], 0.0, CAR))  # z [1.5, 2.5]: faces on layer boundaries
    labels = occupancy_labels(scene, TERRAIN_ONLY, pose(), grid)
    assert np.argwhere(labels != FREE).tolist() == [[1, 1, 1], [1, 1, 2]]


# ------------------------------------------------------------------------------------------------ sampling
def _surface_points(kind, half, count, rng) -> np.ndarray:
    """``(count, 3)`` points on the surface of a solid in its own frame (centre 0, heading +x)."""
    if kind == ELLIPSOID:
        n = rng.normal(size=(count, 3))
        return n / np.linalg.norm(n, axis=1, keepdims=True) * half
    if kind == BOX:
        # On faces mostly, on edges (two coordinates at +-1) and corners (three) for the rest.
        fixed_axes = rng.choice([1, 2, 3], count, p=[0.8, 0.15, 0.05])
        fixed = rng.random((count, 3)).argsort(axis=1).argsort(axis=1) < fixed_axes[:, None]
        p = np.where(fixed, rng.choice([-1.0, 1.0], (count, 3)), rng.uniform(-1, 1, (count, 3)))
        return p * half
    angle = rng.uniform(0, 2 * np.pi, count)
    radius = np.where(rng.random(count) < 0.6, 1.0, np.sqrt(rng.random(count)))
    z = np.where(radius == 1.0, rng.uniform(-1, 1, count), rng.choice([-1.0, 1.0], count))
    return np.stack((radius * np.cos(angle) * half[0], radius * np.sin(angle) * half[0], z * half[2]), axis=1)


def _to_world(local: np.ndarray, center, yaw) -> np.ndarray:
    return transform(pose(yaw, center), local)


def _random_solid(rng, kind):
    half = rng.uniform(0.05, 3.0, 3)
    if kind == CYLINDER:
        half[1] = half[0]
    center = np.array([rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(-0.5, 4.5)])
    return center, half, rng.uniform(-np.pi, np.pi)


@pytest.mark.parametrize("kind", [BOX, CYLINDER, ELLIPSOID])
def test_surface_and_inside_points_fall_in_occupied_voxels(kind):
    rng = np.random.default_rng(10 + kind)
    for _ in range(25):
        ego2global = pose(rng.uniform(-np.pi, np.pi), (rng.uniform(-20, 20), rng.uniform(-20, 20), 0.0))
        center_ego, half, yaw_ego = _random_solid(rng, kind)
        center = transform(ego2global, center_ego[None])[0]
        yaw = yaw_ego + math.atan2(ego2global[1, 0], ego2global[0, 0])
        labels = occupancy_labels(solids((kind, center, half, yaw, PEDESTRIAN)), TERRAIN_ONLY, ego2global)
        local = _surface_points(kind, half, 20000, rng)
        local = np.concatenate((local, local * rng.random((len(local), 1))))  # and points inside
        points = transform(np.linalg.inv(ego2global), _to_world(local, center, yaw))
        index, inside = index_of(points)
        assert inside.any()
        assert (labels[tuple(index[inside].T)] == PEDESTRIAN).all()


def _distance_to_solid(points, kind, half) -> np.ndarray:
    """Distance (m) from points in a solid's own frame to the solid; for ellipsoids, an upper bound."""
    if kind == BOX:
        return np.linalg.norm(np.maximum(np.abs(points) - half, 0.0), axis=1)
    if kind == CYLINDER:
        radial = np.maximum(np.hypot(points[:, 0], points[:, 1]) - half[0], 0.0)
        return np.hypot(radial, np.maximum(np.abs(points[:, 2]) - half[2], 0.0))
    # Exact is hard: inside -> 0, else the distance to the nearest of dense surface samples.
    inside = ((points / half) ** 2).sum(axis=1) <= 1.0
    n = np.random.default_rng(0).normal(size=(20000, 3))
    surface = n / np.linalg.norm(n, axis=1, keepdims=True) * half
    distance = np.zeros(len(points))
    for r in np.flatnonzero(~inside):
        distance[r] = np.linalg.norm(surface - points[r], axis=1).min()
    return distance


@pytest.mark.parametrize("kind", [BOX, CYLINDER, ELLIPSOID])
def test_no_fattening(kind):
    # Every marked voxel meets the solid, so its centre lies within half a diagonal of it.
    rng = np.random.default_rng(20 + kind)
    for _ in range(8):
        ego2global = pose(rng.uniform(-np.pi, np.pi), (rng.uniform(-20, 20), rng.uniform(-20, 20), 0.0))
        center_ego, half, yaw_ego = _random_solid(rng, kind)
        center = transform(ego2global, center_ego[None])[0]
        yaw = yaw_ego + math.atan2(ego2global[1, 0], ego2global[0, 0])
        labels = occupancy_labels(solids((kind, center, half, yaw, CAR)), TERRAIN_ONLY, ego2global)
        marked = np.argwhere(labels == CAR)
        centres = np.asarray(OCC3D_GRID.lower) + (marked + 0.5) * 0.4
        local = transform(np.linalg.inv(pose(yaw_ego, center_ego)), centres)
        # Ellipsoid distances come from surface samples under 0.1 m apart (semi-axes up to 3 m).
        slack = 0.06 if kind == ELLIPSOID else 1e-9
        assert (_distance_to_solid(local, kind, half) <= HALF_DIAGONAL + slack).all()


# ------------------------------------------------------------------------------------------------ ground
def test_ground_layer_classes():
    # Road from x = -20 m to 20 m (global), a sidewalk stripe at x in [4, 6), terrain outside the raster.
    semantics = np.full((80, 160), DRIVEABLE, np.uint8)
    semantics[48:52, :] = SIDEWALK
    ground = GroundMap(semantics, np.zeros_like(semantics, bool), np.array([-20.0, -40.0]), 0.5)
    labels = occupancy_labels(Primitives.empty(), ground, pose())
    layer = labels[:, :, GROUND_LAYER]
    assert (layer[cell(4.0) : cell(6.0)] == SIDEWALK).all()
    assert (layer[cell(-20.0) : cell(4.0)] == DRIVEABLE).all()
    assert (layer[cell(6.0) : cell(20.0)] == DRIVEABLE).all()
    assert (layer[: cell(-20.0)] == TERRAIN).all() and (layer[cell(20.0) :] == TERRAIN).all()
    assert (np.delete(labels, GROUND_LAYER, axis=2) == FREE).all()
    # Yawed by 90 deg, the stripe x_global in [4, 6) lies at ego y in (-6, -4].
    rotated = occupancy_labels(Primitives.empty(), ground, pose(math.pi / 2))[:, :, GROUND_LAYER]
    assert (rotated[:, cell(-6.0) + 1 : cell(-4.0)] == SIDEWALK)[50:150].all()
    assert (rotated[:, cell(-4.0) + 1 :] == DRIVEABLE)[50:150, :50].all()


def test_ground_majority_and_solid_over_ground():
    # 0.2 m raster cells: voxel (100 + n, 100) holds cells x 200 + 2n .. 201 + 2n, y 200 .. 201, one per sub-cell.
    semantics = np.full((400, 400), DRIVEABLE, np.uint8)
    semantics[200:202, 200:202] = SIDEWALK
    semantics[201, 201] = DRIVEABLE  # voxel 100: three sidewalk sub-cells of four
    semantics[202, 200] = SIDEWALK  # voxel 101: one of four
    semantics[204, 200] = semantics[205, 201] = SIDEWALK  # voxel 102: two of four, a tie to the lower id
    ground = GroundMap(semantics, np.zeros_like(semantics, bool), np.array([-40.0, -40.0]), 0.2)
    layer = occupancy_labels(Primitives.empty(), ground, pose())[:, :, GROUND_LAYER]
    assert layer[100:103, 100].tolist() == [SIDEWALK, DRIVEABLE, DRIVEABLE]
    # One sample per voxel reads the cell under the centre: (0.2, 0.2) is cell (201, 201), road.
    assert occupancy_labels(Primitives.empty(), ground, pose(), supersample=1)[100, 100, GROUND_LAYER] == DRIVEABLE
    scene = solids((BOX, [0.2, 0.2, 0.1], [0.1, 0.1, 0.1], 0.0, CAR))
    assert occupancy_labels(scene, ground, pose())[100, 100, GROUND_LAYER] == CAR


# ------------------------------------------------------------------------------------------------ priority
def test_priority_order_and_overlaps():
    assert sorted(CLASS_PRIORITY) == list(range(17))
    assert CLASS_PRIORITY[0] == PEDESTRIAN and CLASS_PRIORITY[-1] == TERRAIN
    assert CLASS_PRIORITY.index(CAR) < CLASS_PRIORITY.index(MANMADE) < CLASS_PRIORITY.index(VEGETATION)
    rows = [
        (BOX, [5.0, 0.0, 0.9], [2.2, 0.9, 0.9], 0.3, CAR),
        (CYLINDER, [5.0, 0.0, 0.9], [0.3, 0.3, 0.9], 0.0, PEDESTRIAN),  # inside the car
        (BOX, [7.0, 0.0, 3.0], [1.0, 3.0, 3.0], 0.0, MANMADE),  # overlaps the car's front
        (ELLIPSOID, [8.0, 2.0, 3.0], [2.0, 2.0, 2.0], 0.0, VEGETATION),  # overlaps the building
    ]
    for order in (rows, rows[::-1]):
        labels = occupancy_labels(solids(*order), TERRAIN_ONLY, pose())
        alone = {row[4]: occupancy_labels(solids(row), TERRAIN_ONLY, pose()) == row[4] for row in rows}
        assert (labels[alone[PEDESTRIAN]] == PEDESTRIAN).all()
        assert (labels[alone[CAR] & ~alone[PEDESTRIAN]] == CAR).all()
        assert (labels[alone[MANMADE] & ~alone[CAR]] == MANMADE).all()
        assert (labels[alone[VEGETATION] & ~alone[MANMADE]] == VEGETATION).all()
        assert (alone[CAR] & alone[MANMADE]).any() and (alone[MANMADE] & alone[VEGETATION]).any()


def test_tilted_pose_is_rejected():
    tilted = pose()
    tilted[:3, :3] = [[1, 0, 0], [0, math.cos(0.1), -math.sin(0.1)], [0, math.sin(0.1), math.cos(0.1)]]
    with pytest.raises(ValueError, match="rotation about z"):
        occupancy_labels(Primitives.empty(), TERRAIN_ONLY, tilted)


# ------------------------------------------------------------------------------------------------ masks
def test_lidar_mask_marks_the_rays():
    labels = occupancy_labels(Primitives.empty(), TERRAIN_ONLY, pose())
    origin = np.array([0.94, 0.0, 1.84])
    points = np.array([[10.3, 3.1, 0.05, 7.0], [-5.2, -20.7, 0.1, 3.0]])  # an intensity column, ignored
    second = (np.array([2.1, 1.1, 1.84]), np.array([[2.1, 1.1, -0.1]]))  # straight down in column (105, 102)
    mask = lidar_visibility(labels, OCC3D_GRID, [(origin, points), second])
    assert mask.dtype == np.uint8
    segments = [(origin, points[0, :3]), (origin, points[1, :3]), (second[0], second[1][0])]
    sampled = set()
    for start, end in segments:
        steps = int(np.linalg.norm(end - start) / 1e-4) + 1
        index, inside = index_of(start + np.linspace(0, 1, steps + 1)[:, None] * (end - start))
        sampled |= {tuple(v) for v in index[inside].tolist()}
    # Dense sampling finds every voxel but those cut by a corner thinner than 1e-4 m.
    marked = {tuple(v) for v in np.argwhere(mask).tolist()}
    assert sampled <= marked and len(marked - sampled) <= 3
    # The returns' voxels, the vertical ray down to the ground included.
    assert mask[tuple(index_of(points[:, :3])[0].T)].all()
    # z from 1.84 (layer 7) down to -0.1 (layer 2, [-0.2, 0.2)), nothing below.
    assert mask[105, 102].tolist() == [0, 0, 1, 1, 1, 1, 1, 1] + [0] * 8


def test_camera_mask_stops_at_the_first_occupied_voxel():
    # A wall 10 m ahead, wider and taller than a narrow forward camera sees at that range.
    wall = solids((BOX, [10.5, 0.0, 2.5], [0.3, 8.0, 2.5], 0.0, MANMADE))
    labels = occupancy_labels(wall, TERRAIN_ONLY, pose())
    cam2ego = np.eye(4)
    cam2ego[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
    cam2ego[:3, 3] = [1.7, 0.0, 1.5]
    intrinsics = np.array([[200.0, 0.0, 100.0], [0.0, 200.0, 50.0], [0.0, 0.0, 1.0]])
    mask = camera_visibility(labels, OCC3D_GRID, [(cam2ego, intrinsics, 200, 100)])
    assert mask.dtype == np.uint8
    front = int(math.floor((10.2 + 40) / 0.4))  # the wall's first voxel layer along x
    assert mask[front:].any() and not mask[front + 1 :].any()  # nothing inside or behind the wall
    assert (labels[front][mask[front] == 1] == MANMADE).all()
    assert mask[front - 5 : front, 100, 6].all()  # free space on the optical axis is seen
    assert not mask[: int(math.floor((1.7 + 40) / 0.4))].any()  # nothing behind the camera
    # Without the wall the ground far ahead is seen, all of it within the view (grazing angles included).
    empty = occupancy_labels(Primitives.empty(), TERRAIN_ONLY, pose())
    seen = camera_visibility(empty, OCC3D_GRID, [(cam2ego, intrinsics, 200, 100)])
    assert seen[front + 5 :].any()
    # Ground from just past the image's lower edge (1.5 m / tan(14 deg) = 6 m ahead of the camera) to the grid's end.
    ahead = slice(int(math.floor((1.7 + 6.5 + 40) / 0.4)), 199)
    assert seen[ahead, 100, 2].all()


# ------------------------------------------------------------------------------------------------ SurroundOcc
def _agreeing(rows, grid_from, grid_to, from2to, target, radius=2):
    """Agreement of voxel rows ``(i, j, k, label)`` of ``grid_from`` with the labels ``target`` of ``grid_to``.

    Returns:
        The number of rows whose centre, mapped into ``grid_to``, has a voxel of the same label within ``radius``
        voxels in ``target``, and the number of centres inside ``grid_to``.
    """
    centres = np.asarray(grid_from.lower) + (rows[:, :3] + 0.5) * np.asarray(grid_from.voxel_size)
    index, inside = index_of(transform(from2to, centres), grid_to)
    hits = 0
    for (i, j, k), label in zip(index[inside], rows[inside, 3], strict=True):
        lo = np.maximum(np.array([i, j, k]) - radius, 0)
        window = target[lo[0] : i + radius + 1, lo[1] : j + radius + 1, lo[2] : k + radius + 1]
        hits += bool((window == label).any())
    return hits, int(inside.sum())


def test_surroundocc_matches_occ3d_up_to_resolution():
    rng = np.random.default_rng(5)
    rows = [(BOX, [12.0, 3.0, 0.8], [2.2, 0.9, 0.8], 0.4, CAR), (CYLINDER, [6.0, -4.0, 1.5], [0.2, 0.2, 1.5], 0, 0)]
    for _ in range(12):
        # Solids within the height range of both grids (ego z [-1, 5.4], LiDAR z [-5, 3] = ego z [-3.16, 4.84]).
        kind = int(rng.integers(0, 3))
        half = rng.uniform(0.1, [3.0, 3.0, 1.5])
        half[1] = half[0] if kind == CYLINDER else half[1]
        center = [rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(-0.5 + half[2], 4.3 - half[2])]
        rows.append((kind, center, half, rng.uniform(-np.pi, np.pi), int(rng.choice([CAR, MANMADE, VEGETATION]))))
    ego2global = pose(0.7, (100.0, -50.0, 0.0))
    # Solids are given in the ego frame above; the world holds them in the global frame.
    scene = solids(
        *[(k, transform(ego2global, np.asarray(c, float)[None])[0], h, y + 0.7, l) for k, c, h, y, l in rows]
    )
    lidar2global = ego2global @ LIDAR_TOP.lidar2ego
    sparse = surroundocc_labels(scene, TERRAIN_ONLY, lidar2global)
    assert sparse.dtype == np.int64 and sparse.ndim == 2 and sparse.shape[1] == 4
    flat = np.ravel_multi_index(tuple(sparse[:, :3].T), SURROUNDOCC_GRID.shape)
    assert (np.diff(flat) > 0).all()
    assert set(np.unique(sparse[:, 3]).tolist()) <= set(range(17)) and (sparse[:, 3] == 0).any()  # "others" is 0
    # The ground plane sits 1.84 m below the sensor: layer floor((-1.84 + 5) / 0.5) = 6.
    ground = sparse[sparse[:, 3] == TERRAIN]
    assert set(ground[:, 2].tolist()) == {6} and len(ground) > 0.9 * 200 * 200
    # The car 12 m ahead of the ego is ahead (+y) of the LiDAR, whose x points right: y (11 +- 2.5 + 50) / 0.5.
    cars = sparse[sparse[:, 3] == CAR]
    assert cars.size and (np.abs(cars[:, 1] - 122) <= 6).any()
    dense = occupancy_labels(scene, TERRAIN_ONLY, ego2global)
    solid_rows = sparse[sparse[:, 3] != TERRAIN]
    hits, total = _agreeing(solid_rows, SURROUNDOCC_GRID, OCC3D_GRID, LIDAR_TOP.lidar2ego, dense)
    assert total > 100 and hits == total
    dense_rows = np.argwhere((dense != FREE) & (dense != TERRAIN))
    dense_rows = np.concatenate((dense_rows, dense[tuple(dense_rows.T)][:, None]), axis=1)
    target = np.full(SURROUNDOCC_GRID.shape, FREE, np.uint8)
    target[tuple(sparse[:, :3].T)] = sparse[:, 3]
    hits, total = _agreeing(dense_rows, OCC3D_GRID, SURROUNDOCC_GRID, np.linalg.inv(LIDAR_TOP.lidar2ego), target)
    assert total > 100 and hits == total


def test_mask_inputs_are_checked():
    with pytest.raises(ValueError, match="shape"):
        lidar_visibility(np.zeros((4, 4, 4), np.uint8), OCC3D_GRID, [])
    labels = np.full(OCC3D_GRID.shape, FREE, np.uint8)
    assert not lidar_visibility(labels, OCC3D_GRID, []).any()
    assert traverse_rays(labels != FREE, OCC3D_GRID, np.zeros((0, 3)), np.zeros((0, 3))).sum() == 0


def test_panoptic_instance_ids_follow_objects_over_time_and_name_their_instance_token(tmp_path):
    """labels.npz carries each voxel's object (the world's id + 1) for thing classes, 0 elsewhere, the same id in
    every frame, and the nuScenes instance token of each id that the sample annotates (empty for the others)."""
    import json

    from occkit.classes import OCC3D, THING_CLASSES
    from occkit.sim.generate import SimConfig, simulate_dataset

    root = tmp_path / "world"
    simulate_dataset(SimConfig(scenes=1, frames=2, seed=3, image_size=(176, 99), cameras=("CAM_FRONT",)), root)
    samples = {r["token"]: r for r in json.loads((root / "v1.0-synth" / "sample.json").read_text())}
    annotations = json.loads((root / "v1.0-synth" / "sample_annotation.json").read_text())
    frames = []
    for path in sorted(root.glob("gts/*/*/labels.npz"), key=lambda p: samples[p.parent.name]["timestamp"]):
        with np.load(path) as archive:
            frames.append({key: archive[key] for key in archive.files})
    things = [OCC3D.index(name) for name in THING_CLASSES]
    for frame in frames:
        instances, semantics = frame["instances"], frame["semantics"]
        assert instances.dtype == np.int32 and instances.shape == semantics.shape
        assert np.isin(semantics[instances > 0], things).all()
        assert (instances[np.isin(semantics, things)] > 0).mean() > 0.9
        assert set(np.unique(instances[instances > 0])) == set(frame["instance_ids"].tolist())
    # The same object keeps its id: the ids two frames share hold the same class in both.
    first, second = frames
    shared = set(first["instance_ids"].tolist()) & set(second["instance_ids"].tolist())
    assert shared
    tokens = [dict(zip(f["instance_ids"].tolist(), f["instance_tokens"].tolist(), strict=True)) for f in frames]
    for instance in shared:
        assert tokens[0][instance] == tokens[1][instance] or "" in (tokens[0][instance], tokens[1][instance])
        classes = [np.bincount(f["semantics"][f["instances"] == instance]).argmax() for f in frames]
        assert classes[0] == classes[1]
    # A token names the object's annotation in that very sample; an object the sample does not annotate has none.
    tokens_of = [path.parent.name for path in sorted(root.glob("gts/*/*/labels.npz"),
                                                     key=lambda p: samples[p.parent.name]["timestamp"])]  # fmt: skip
    for sample_token, named in zip(tokens_of, tokens, strict=True):
        annotated = {a["instance_token"] for a in annotations if a["sample_token"] == sample_token}
        assert set(named.values()) - {""} == annotated & set(named.values()) and annotated & set(named.values())
    assert any("" in named.values() for named in tokens)  # unseen objects: voxels, but no annotation
