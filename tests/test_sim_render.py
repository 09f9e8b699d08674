"""Ray caster, cameras and LiDAR of the synthetic world, on small hand-made worlds.

The ray caster is checked against a brute-force numpy intersection of every ray with every solid, written
independently of the kernels; the sensors against projections and surface equations of known solids.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from occkit.sim.lidar import MIN_RANGE, scan_lidar
from occkit.sim.primitives import BOX, CYLINDER, ELLIPSOID, GroundMap, Primitives, Texture
from occkit.sim.raytrace import GROUND, NOTHING, cast_rays, hit_labels
from occkit.sim.render import CAMERA_RANGE, camera_rays, render_camera
from occkit.sim.rig import LIDAR_TOP, camera_rig

SKY = (np.array([0.4, -0.3, 0.85]), np.array([0.35, 0.55, 0.85]), np.array([0.8, 0.85, 0.92]))


def make_primitives(kind, center, half_size, yaw, semantic=None, instance=None, texture=None) -> Primitives:
    n = len(kind)
    return Primitives(
        kind=np.asarray(kind, np.int8),
        center=np.asarray(center, np.float64).reshape(n, 3),
        half_size=np.asarray(half_size, np.float64).reshape(n, 3),
        yaw=np.asarray(yaw, np.float64),
        semantic=np.asarray(semantic if semantic is not None else [4] * n, np.uint8),
        instance=np.asarray(instance if instance is not None else np.arange(n), np.int32),
        color=np.full((n, 3), 0.5, np.float32),
        texture=np.asarray(texture if texture is not None else [Texture.PLAIN] * n, np.uint8),
        reflectivity=np.full(n, 0.5, np.float32),
    )


def flat_ground(semantic: int = 11, half_extent: float = 100.0) -> GroundMap:
    n = int(2 * half_extent)
    markings = np.zeros((n, n), bool)
    markings[:, n // 2 - 1 : n // 2 + 1] = True  # a 2 m wide painted band along x at |y| < 1
    return GroundMap(np.full((n, n), semantic, np.uint8), markings, np.array([-half_extent, -half_extent]), 1.0)


def pose(x=0.0, y=0.0, z=0.0, yaw=0.0, pitch=0.0) -> np.ndarray:
    """``(4, 4)`` rotation by ``yaw`` about z after ``pitch`` about y, then translation."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    matrix = np.eye(4)
    matrix[:3, :3] = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    matrix[:3, 3] = (x, y, z)
    return matrix


def random_world(rng: np.random.Generator, n: int = 60, extent: float = 30.0) -> Primitives:
    kind = rng.integers(0, 3, n)
    half = rng.uniform(0.2, 4.0, (n, 3))
    half[kind == CYLINDER, 1] = half[kind == CYLINDER, 0]
    center = np.column_stack((rng.uniform(-extent, extent, (n, 2)), rng.uniform(0.0, 6.0, n)))
    return make_primitives(kind, center, half, rng.uniform(-np.pi, np.pi, n))


# --------------------------------------------------------------------------- brute force
def _local(origins, directions, primitives, p):
    c, s = math.cos(primitives.yaw[p]), math.sin(primitives.yaw[p])
    to_local = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return (origins - primitives.center[p]) @ to_local.T, directions @ to_local.T


def _slab_interval(o, d, half):
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (-half - o) / d, (half - o) / d
    return np.minimum(a, b).max(axis=1), np.maximum(a, b).min(axis=1)


def brute_force_entry(origins, directions, primitives, p):
    """``(R,)`` distance at which each ray enters solid ``p`` from outside (``inf`` otherwise)."""
    o, d = _local(origins, directions, primitives, p)
    h = primitives.half_size[p]
    if primitives.kind[p] == BOX:
        near, far = _slab_interval(o, d, h)
    elif primitives.kind[p] == CYLINDER:
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
        c = o[:, 0] ** 2 + o[:, 1] ** 2 - h[0] ** 2
        disc = b * b - a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        vertical = a == 0
        with np.errstate(divide="ignore", invalid="ignore"):
            near_side = np.where(vertical, np.where(c <= 0, -np.inf, np.inf), (-b - root) / a)
            far_side = np.where(vertical, np.where(c <= 0, np.inf, -np.inf), (-b + root) / a)
        near_z, far_z = _slab_interval(o[:, 2:], d[:, 2:], h[2:])
        near, far = np.maximum(near_side, near_z), np.minimum(far_side, far_z)
        near[disc < 0] = np.inf
    else:
        os_, ds = o / h, d / h
        a, b, c = (ds * ds).sum(1), (os_ * ds).sum(1), (os_ * os_).sum(1) - 1.0
        disc = b * b - a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        near, far = (-b - root) / a, (-b + root) / a
        near[disc < 0] = np.inf
    return np.where((near <= far) & (near > 0), near, np.inf)


def brute_force(origins, directions, max_distance, primitives, with_ground):
    best = np.full(len(directions), np.inf)
    index = np.full(len(directions), NOTHING)
    if with_ground:
        with np.errstate(divide="ignore"):
            t = np.where((directions[:, 2] < 0) & (origins[:, 2] > 0), -origins[:, 2] / directions[:, 2], np.inf)
        best, index = np.where(t < max_distance, t, np.inf), np.where(t < max_distance, GROUND, NOTHING)
    for p in range(len(primitives)):
        t = brute_force_entry(origins, directions, primitives, p)
        closer = (t < best) & (t < max_distance)
        best[closer], index[closer] = t[closer], p
    return best, index


def surface_residual(points, primitives, p):
    """``(N,)`` signed distance (m) of points to solid ``p`` (exact for boxes and cylinders, for spheres)."""
    local, _ = _local(points, points, primitives, p)
    h = primitives.half_size[p]
    if primitives.kind[p] == CYLINDER:
        q = np.column_stack((np.hypot(local[:, 0], local[:, 1]) - h[0], np.abs(local[:, 2]) - h[2]))
    elif primitives.kind[p] == BOX:
        q = np.abs(local) - h
    else:
        assert np.allclose(h, h[0]), "only spheres have a simple exact distance"
        return np.linalg.norm(local, axis=1) - h[0]
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# --------------------------------------------------------------------------- ray caster
@pytest.mark.parametrize("shared_origin", [False, True])
def test_cast_rays_matches_brute_force(shared_origin):
    rng = np.random.default_rng(0)
    primitives = random_world(rng)
    n = 20000
    if shared_origin:
        origins = np.array([[3.0, -2.0, 1.6]])
    else:
        origins = np.column_stack((rng.uniform(-40, 40, (n, 2)), rng.uniform(0.2, 12.0, n)))
    directions = unit(rng.normal(size=(n, 3)))
    axis_aligned = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [0.6, 0.8, 0], [0, 0.6, -0.8]]
    directions[: len(axis_aligned)] = axis_aligned
    if not shared_origin:  # straight down onto every solid, and axis-aligned rays level with their centres
        count = len(primitives)
        down, level = slice(8, 8 + count), slice(8 + count, 8 + 2 * count)
        origins[down], directions[down] = primitives.center + [0.0, 0.0, 20.0], [0.0, 0.0, -1.0]
        origins[level], directions[level] = primitives.center - [45.0, 0.0, 0.0], [1.0, 0.0, 0.0]
    for max_distance, with_ground in ((1e9, True), (25.0, True), (60.0, False)):
        ground = flat_ground() if with_ground else None
        hits = cast_rays(origins, directions, max_distance, primitives, ground)
        full_origins = np.broadcast_to(origins, directions.shape)
        expected, index = brute_force(full_origins, directions, max_distance, primitives, with_ground)
        np.testing.assert_array_equal(hits.primitive, index)
        hit = np.isfinite(expected)
        assert (index >= 0).mean() > 0.1
        np.testing.assert_allclose(hits.distance[hit], expected[hit], rtol=0, atol=1e-9)
        assert np.all(np.isinf(hits.distance[~hit]))
        assert np.all(np.isnan(hits.point[~hit])) and np.all(hits.normal[~hit] == 0)
        np.testing.assert_allclose(
            hits.point[hit], full_origins[hit] + expected[hit, None] * directions[hit], atol=1e-9
        )
        # Normals: unit, facing the ray, and along the surface's gradient (checked on boxes and cylinders).
        normals = hits.normal[hit].astype(np.float64)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
        assert np.all((normals * directions[hit]).sum(1) <= 1e-6)
        for p in range(len(primitives)):
            on_p = hits.primitive == p
            if on_p.any() and primitives.kind[p] != ELLIPSOID:
                assert np.abs(surface_residual(hits.point[on_p], primitives, p)).max() < 1e-9
                step = hits.point[on_p] + 1e-4 * hits.normal[on_p]
                assert surface_residual(step, primitives, p).min() > 0.5e-4  # the normal points outward


def test_cast_rays_known_distances_and_inside_origin():
    primitives = make_primitives(
        [BOX, CYLINDER, ELLIPSOID],
        [[10.0, 0.0, 1.0], [0.0, 10.0, 1.0], [-10.0, 0.0, 1.0]],
        [[1.0, 2.0, 1.0], [0.5, 0.5, 1.0], [2.0, 1.0, 3.0]],
        [math.pi / 2, 0.0, 0.3],
    )
    directions = np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, 0, -1.0], [0, 0, 1.0]])
    hits = cast_rays(np.array([0.0, 0.0, 1.0]), directions, 100.0, primitives, flat_ground())
    # The box is yawed by 90 degrees, so its half width (2 m) faces the ray along x.
    c, s = math.cos(0.3), math.sin(0.3)
    ellipsoid_x = 1.0 / math.sqrt((c / 2.0) ** 2 + (s / 1.0) ** 2)  # semi-axis of the yawed ellipse along x
    np.testing.assert_allclose(hits.distance, [8.0, 9.5, 10.0 - ellipsoid_x, 1.0, np.inf], atol=1e-12)
    np.testing.assert_array_equal(hits.primitive, [0, 1, 2, GROUND, NOTHING])
    # The ellipse's normal where it crosses the x axis is its gradient there, rotated back by the yaw.
    lx, ly = c * ellipsoid_x, -s * ellipsoid_x
    gx, gy = lx / 4.0, ly / 1.0
    ellipse_normal = np.array([c * gx - s * gy, s * gx + c * gy, 0.0]) / math.hypot(gx, gy)
    expected_normals = [[-1, 0, 0], [0, -1, 0], ellipse_normal, [0, 0, 1]]
    np.testing.assert_allclose(hits.normal[:4], expected_normals, atol=1e-6)
    # A ray that starts inside a solid does not see it; from outside it does.
    inside = cast_rays(np.array([10.0, 0.0, 1.0]), np.array([[1.0, 0.0, 0.0]]), 100.0, primitives, None)
    assert inside.primitive[0] == NOTHING
    far = cast_rays(np.array([20.0, 0.0, 1.0]), np.array([[-1.0, 0.0, 0.0]]), 100.0, primitives, None)
    assert far.primitive[0] == 0 and far.distance[0] == pytest.approx(8.0)


def test_cast_rays_empty_world_and_labels():
    ground = flat_ground(semantic=13)
    directions = unit(np.array([[1.0, 0.0, -0.1], [0.0, 1.0, -0.5], [1.0, 0.0, 0.1], [1.0, 0.0, -0.001]]))
    hits = cast_rays(np.array([0.0, 0.0, 2.0]), directions, 200.0, Primitives.empty(), ground)
    np.testing.assert_array_equal(hits.primitive, [GROUND, GROUND, NOTHING, NOTHING])
    semantic, instance, marking = hit_labels(hits, Primitives.empty(), ground)
    np.testing.assert_array_equal(semantic, [13, 13, 255, 255])
    np.testing.assert_array_equal(instance, [-1, -1, -1, -1])
    np.testing.assert_array_equal(marking, [True, False, False, False])  # paint at |y| < 1 only


# --------------------------------------------------------------------------- cameras
def _project(camera, ego2global, point):
    """Pixel ``(u, v)`` and camera depth of a global point."""
    global2cam = np.linalg.inv(ego2global @ camera.cam2ego)
    p = global2cam[:3, :3] @ point + global2cam[:3, 3]
    uvw = camera.K @ p
    return uvw[:2] / uvw[2], p[2]


def test_box_projects_to_its_pixel_with_labels_and_depth():
    cameras = camera_rig(176, 99)
    front, back = cameras[1], cameras[4]
    assert front.name == "CAM_FRONT" and back.name == "CAM_BACK"
    ego2global = pose(120.0, -40.0, 0.0, yaw=0.7)
    # Boxes ahead-left, ahead-right-high and behind the ego vehicle (ego coordinates), of distinct instances.
    ego_centres = np.array([[14.0, 3.0, 1.0], [20.0, -4.0, 4.0], [-14.0, 0.0, 1.0]])
    centres = ego_centres @ ego2global[:3, :3].T + ego2global[:3, 3]
    primitives = make_primitives(
        [BOX] * 3, centres, [[0.6, 0.6, 0.6]] * 3, [0.2, 1.0, 0.0], semantic=[4, 10, 7], instance=[7, 8, 9]
    )
    ground = flat_ground(half_extent=300.0)
    render = render_camera(front, ego2global, primitives, ground, *SKY, seed=0)
    assert render.image.shape == (99, 176, 3) and render.image.dtype == np.uint8
    for centre, semantic, instance in zip(centres[:2], (4, 10), (7, 8), strict=True):
        (u, v), _ = _project(front, ego2global, centre)
        assert render.semantic[int(v), int(u)] == semantic and render.instance[int(v), int(u)] == instance
    (u_left, _), _ = _project(front, ego2global, centres[0])
    (u_right, v_high), _ = _project(front, ego2global, centres[1])
    assert u_left < 88 < u_right and v_high < 49  # left is left, up is up
    assert not (render.instance == 9).any()
    back_render = render_camera(back, ego2global, primitives, ground, *SKY, seed=0)
    (u, v), _ = _project(back, ego2global, centres[2])
    assert back_render.instance[int(v), int(u)] == 9

    # Depth is the camera z of the surface point each pixel sees; semantic and instance follow the hit.
    origin, directions, _ = camera_rays(front, ego2global)
    hits = cast_rays(origin, directions, CAMERA_RANGE, primitives, ground)
    global2cam = np.linalg.inv(ego2global @ front.cam2ego)
    seen = hits.primitive != NOTHING
    z = (hits.point[seen] @ global2cam[:3, :3].T + global2cam[:3, 3])[:, 2]
    np.testing.assert_allclose(render.depth.reshape(-1)[seen], z, rtol=1e-6)
    assert np.all(render.depth.reshape(-1)[~seen] == 0)
    np.testing.assert_array_equal(render.semantic.reshape(-1)[~seen], 255)
    on_ground = hits.primitive == GROUND
    np.testing.assert_array_equal(render.semantic.reshape(-1)[on_ground], ground.lookup(hits.point[on_ground, :2]))
    assert set(np.unique(render.semantic.reshape(-1)[on_ground])) == {11, 14}  # terrain beyond the map
    np.testing.assert_array_equal(render.instance.reshape(-1)[hits.primitive < 0], -1)


def test_nearer_box_hides_farther_one():
    front = camera_rig(176, 99)[1]
    ego2global = pose(5.0, 5.0)
    centres = np.array([[12.0, 0.0, 1.5], [25.0, 0.0, 1.5]]) + ego2global[:3, 3]
    primitives = make_primitives([BOX, BOX], centres, [[0.5, 0.5, 0.5], [0.5, 3.0, 1.5]], [0.0, 0.0], instance=[1, 2])
    render = render_camera(front, ego2global, primitives, flat_ground(), *SKY, seed=0)
    (u, v), depth = _project(front, ego2global, centres[0])
    assert render.instance[int(v), int(u)] == 1
    assert render.depth[int(v), int(u)] == pytest.approx(depth - 0.5, abs=1e-3)
    assert (render.instance == 2).sum() > (render.instance == 1).sum() > 0  # the big far box shows around it


@pytest.mark.parametrize("pitch_deg", [0.0, 4.0, -3.0])
def test_horizon_row_in_empty_world(pitch_deg):
    """Sky above the horizon, ground below; a nose-down pitch moves the horizon up by f tan(pitch)."""
    front = camera_rig(176, 99)[1]
    pitch = math.radians(pitch_deg)
    ego2global = pose(30.0, -20.0, 0.0, yaw=-1.2, pitch=pitch)
    render = render_camera(front, ego2global, Primitives.empty(), flat_ground(semantic=14), *SKY, seed=0)
    fy, cy = front.K[1, 1], front.K[1, 2]
    horizon_v = cy - fy * math.tan(pitch)
    rows = np.arange(front.height) + 0.5
    sky_rows = rows < horizon_v - 1.0
    ground_rows = rows > horizon_v + 2.0  # the ground stops at CAMERA_RANGE, within a pixel of the horizon
    assert sky_rows.any() and ground_rows.any()
    assert np.all(render.semantic[sky_rows] == 255) and np.all(render.depth[sky_rows] == 0)
    assert np.all(render.semantic[ground_rows] == 14) and np.all(render.depth[ground_rows] > 0)
    # Sky is brighter than the grass and the image is not upside down.
    assert render.image[0].mean() > render.image[-1].mean()
    # The depth of a ground pixel is where its ray meets the plane, seen from the camera's height.
    height = (ego2global @ front.cam2ego)[2, 3]
    v = front.height - 1
    ray = np.linalg.inv(front.K) @ np.array([88.5, v + 0.5, 1.0])
    cam2global = ego2global @ front.cam2ego
    direction = cam2global[:3, :3] @ ray
    assert render.depth[v, 88] == pytest.approx(ray[2] * height / -direction[2], rel=1e-5)


def test_render_is_deterministic_and_textured():
    rng = np.random.default_rng(3)
    textures = [Texture.PLAIN, Texture.FACADE, Texture.FOLIAGE, Texture.STRIPES, Texture.VEHICLE, Texture.BARK]
    n = 18
    primitives = make_primitives(
        [BOX, CYLINDER, ELLIPSOID] * 6,
        np.column_stack((rng.uniform(6, 30, n), rng.uniform(-12, 12, n), rng.uniform(0.5, 3.0, n))),
        np.column_stack((np.full(n, 1.2), np.full(n, 1.2), rng.uniform(0.5, 3.0, n))),
        rng.uniform(-np.pi, np.pi, n),
        texture=np.repeat(textures, 3),
    )
    cameras = camera_rig(176, 99)
    renders = [render_camera(cameras[1], pose(), primitives, flat_ground(), *SKY, seed=5) for _ in range(2)]
    for name in ("image", "depth", "semantic", "instance"):
        assert getattr(renders[0], name).tobytes() == getattr(renders[1], name).tobytes()
    other_seed = render_camera(cameras[1], pose(), primitives, flat_ground(), *SKY, seed=6)
    assert other_seed.image.tobytes() != renders[0].image.tobytes()
    np.testing.assert_array_equal(other_seed.semantic, renders[0].semantic)
    assert np.abs(other_seed.image.astype(int) - renders[0].image.astype(int)).max() <= 2  # noise is a dither
    # Every textured solid in view shows more than one colour.
    image, instance = renders[0].image.reshape(-1, 3), renders[0].instance.reshape(-1)
    for p in np.unique(instance[instance >= 0]):
        if (instance == p).sum() > 40 and primitives.texture[p] != Texture.PLAIN:
            assert len(np.unique(image[instance == p], axis=0)) > 3


# --------------------------------------------------------------------------- LiDAR
def lidar_world():
    """A wall 20 m ahead of the ego vehicle, a pole and a sphere to its sides, on painted asphalt."""
    primitives = make_primitives(
        [BOX, CYLINDER, ELLIPSOID],
        [[20.5, 0.0, 5.0], [0.0, 8.0, 3.0], [-6.0, -7.0, 2.0]],
        [[0.5, 40.0, 5.0], [0.4, 0.4, 3.0], [1.5, 1.5, 1.5]],
        [0.0, 0.0, 0.4],
        semantic=[15, 15, 16],
        instance=[3, 4, 5],
    )
    return primitives, flat_ground()


def test_lidar_points_lie_on_surfaces_in_the_lidar_frame():
    primitives, ground = lidar_world()
    ego2global = pose(50.0, 30.0, 0.0, yaw=0.0)
    primitives.center[:, :2] += ego2global[:2, 3]
    scan = scan_lidar(LIDAR_TOP, ego2global, primitives, ground, seed=0)
    assert scan.points.shape == (len(scan), 5) and scan.points.dtype == np.float32
    assert 20000 < len(scan) < 35000
    lidar2global = ego2global @ LIDAR_TOP.lidar2ego
    world = scan.points[:, :3].astype(np.float64) @ lidar2global[:3, :3].T + lidar2global[:3, 3]
    on_ground = scan.instance == -1
    assert np.all(np.abs(world[on_ground, 2]) < 0.03)
    assert set(np.unique(scan.semantic[on_ground])) == {11}
    for p in range(len(primitives)):
        mine = scan.instance == primitives.instance[p]
        assert mine.sum() > 20
        assert np.all(np.abs(surface_residual(world[mine], primitives, p)) < 0.03)
        assert np.all(scan.semantic[mine] == primitives.semantic[p])
    # Wall points: the range is the distance to the plane x = 20 (ego) along the beam, within the noise.
    wall = scan.instance == 3
    directions = scan.points[wall, :3] / np.linalg.norm(scan.points[wall, :3], axis=1, keepdims=True)
    along_x = (directions.astype(np.float64) @ LIDAR_TOP.lidar2ego[:3, :3].T)[:, 0]
    expected = (20.0 - LIDAR_TOP.lidar2ego[0, 3]) / along_x
    assert np.abs(scan.distance[wall] - expected).max() < 0.026
    assert 0.003 < np.abs(scan.distance[wall] - expected).mean() < 0.015
    np.testing.assert_allclose(np.linalg.norm(scan.points[:, :3], axis=1), scan.distance, rtol=1e-5)
    assert np.all(scan.distance > MIN_RANGE) and np.all(scan.distance <= LIDAR_TOP.max_range + 0.03)


def test_lidar_rings_intensity_and_dropout():
    primitives, ground = lidar_world()
    scan = scan_lidar(LIDAR_TOP, pose(), primitives, ground, seed=1, dropout=0.0)
    rings = scan.points[:, 4]
    assert np.all(rings == np.round(rings)) and rings.min() >= 0 and rings.max() <= 31
    elevation = np.degrees(np.arcsin(scan.points[:, 2] / np.linalg.norm(scan.points[:, :3], axis=1)))
    np.testing.assert_allclose(elevation, np.asarray(LIDAR_TOP.elevations_deg)[rings.astype(int)], atol=1e-3)
    intensity = scan.points[:, 3]
    assert np.all((intensity >= 0) & (intensity <= 255)) and np.all(intensity == np.round(intensity))
    # Road paint returns more light than asphalt (the painted band lies at |y| < 1 m, straight ahead and behind).
    lidar2ego = LIDAR_TOP.lidar2ego
    ego = scan.points[:, :3].astype(np.float64) @ lidar2ego[:3, :3].T + lidar2ego[:3, 3]
    on_ground = scan.instance == -1
    paint = on_ground & (np.abs(ego[:, 1]) < 0.9) & (np.abs(ego[:, 0]) < 15)
    asphalt = on_ground & (np.abs(ego[:, 1]) > 1.1) & (np.hypot(ego[:, 0], ego[:, 1]) < 15)
    assert intensity[paint].mean() > 3 * intensity[asphalt].mean() > 0

    # Without dropout every return within range is kept; with it, the expected fraction goes, reproducibly.
    directions, _ = LIDAR_TOP.ray_directions()
    hits = cast_rays(lidar2ego[:3, 3], directions @ lidar2ego[:3, :3].T, LIDAR_TOP.max_range, primitives, ground)
    assert len(scan) == ((hits.distance > MIN_RANGE) & (hits.distance <= LIDAR_TOP.max_range)).sum()
    dropped = scan_lidar(LIDAR_TOP, pose(), primitives, ground, seed=1, dropout=0.3)
    assert abs(len(dropped) / len(scan) - 0.7) < 0.02
    again = scan_lidar(LIDAR_TOP, pose(), primitives, ground, seed=1, dropout=0.3)
    assert again.points.tobytes() == dropped.points.tobytes()
    with pytest.raises(ValueError):
        scan_lidar(LIDAR_TOP, pose(), primitives, ground, seed=1, dropout=1.5)
