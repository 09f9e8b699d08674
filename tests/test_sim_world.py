"""The procedural world: determinism, the ego's drive, ground layout, no overlapping objects, boxes, coverage."""

from __future__ import annotations

import numpy as np
import pytest

from occkit.classes import occ3d_id
from occkit.sim.primitives import BOX, CYLINDER, Primitives
from occkit.sim.world import CATEGORY_SIZES, World, WorldConfig, generate_world

SHORT = WorldConfig(duration=4.0, density=0.5)
STEP = 0.05  # s, twice as fine as the generator's own check


@pytest.fixture(scope="module")
def worlds() -> list[World]:
    return [generate_world(seed, SHORT) for seed in range(3)]


def sample_times(world: World, step: float = STEP) -> np.ndarray:
    return np.arange(0.0, world.config.duration + 1e-9, step)


def ego_track(world: World, times: np.ndarray) -> np.ndarray:
    """``(T, 4, 4)`` ego poses."""
    return np.stack([world.ego_pose(t) for t in times])


# ------------------------------------------------------------------------------------------ 2D footprint overlap
def footprints(p: Primitives):
    """Centre ``(P, 2)``, axes ``(P, 2, 2)`` (heading, left), half sizes ``(P, 2)``, circle flag, heights."""
    c, s = np.cos(p.yaw), np.sin(p.yaw)
    axes = np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], 1)
    z0, z1 = p.center[:, 2] - p.half_size[:, 2], p.center[:, 2] + p.half_size[:, 2]
    return p.center[:, :2], axes, p.half_size[:, :2], p.kind == CYLINDER, z0, z1


def overlapping_pairs(p: Primitives, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Mask over pairs ``(i, j)`` whose solids overlap: yawed rectangles (boxes, and ellipsoids by their bounding
    rectangle) by the separating-axis test, cylinders as circles, and their height intervals intersect."""
    centre, axes, half, circle, z0, z1 = footprints(p)

    def rect_rect():
        d = centre[j] - centre[i]
        apart = np.zeros(len(i), bool)
        for a, k in ((i, 0), (i, 1), (j, 0), (j, 1)):
            u = axes[a, k]
            ri = half[i, 0] * np.abs((axes[i, 0] * u).sum(1)) + half[i, 1] * np.abs((axes[i, 1] * u).sum(1))
            rj = half[j, 0] * np.abs((axes[j, 0] * u).sum(1)) + half[j, 1] * np.abs((axes[j, 1] * u).sum(1))
            apart |= np.abs((d * u).sum(1)) > ri + rj
        return ~apart

    def circle_rect(c, r):
        diff = centre[c] - centre[r]
        local = np.stack([(diff * axes[r, k]).sum(1) for k in (0, 1)], 1)
        return np.hypot(*(local - np.clip(local, -half[r], half[r])).T) < half[c, 0]

    out = rect_rect()
    out = np.where(circle[j] & ~circle[i], circle_rect(j, i), out)
    out = np.where(circle[i] & ~circle[j], circle_rect(i, j), out)
    out = np.where(circle[i] & circle[j], np.hypot(*(centre[j] - centre[i]).T) < half[i, 0] + half[j, 0], out)
    return out & (z0[i] < z1[j]) & (z0[j] < z1[i])


def clashes(p: Primitives) -> list[tuple[int, int]]:
    """Instance pairs of different objects whose solids overlap."""
    radius = p.radius_xy()
    centre = p.center[:, :2]
    dist = np.linalg.norm(centre[:, None] - centre[None], axis=-1)
    near = (dist < radius[:, None] + radius[None]) & (p.instance[:, None] != p.instance[None])
    i, j = np.nonzero(np.triu(near, 1))
    bad = overlapping_pairs(p, i, j)
    return sorted({(int(p.instance[a]), int(p.instance[b])) for a, b in zip(i[bad], j[bad], strict=True)})


# ------------------------------------------------------------------------------------------ tests
def test_overlap_helper_on_known_shapes():
    def prims(kinds, centres, halves, yaws):
        n = len(kinds)
        return Primitives(
            kind=np.array(kinds, np.int8),
            center=np.array([(x, y, 1.0) for x, y in centres], float),
            half_size=np.array([(a, b, 1.0) for a, b in halves], float),
            yaw=np.array(yaws, float),
            semantic=np.zeros(n, np.uint8),
            instance=np.arange(n, dtype=np.int32),
            color=np.zeros((n, 3), np.float32),
            texture=np.zeros(n, np.uint8),
            reflectivity=np.zeros(n, np.float32),
        )

    # a rotated square reaching toward a box, just short of it and just into it
    d = np.sqrt(2)
    assert clashes(prims([BOX, BOX], [(0, 0), (d + 1.05, 0)], [(1, 1), (1, 1)], [np.pi / 4, 0])) == []
    assert clashes(prims([BOX, BOX], [(0, 0), (d + 0.95, 0)], [(1, 1), (1, 1)], [np.pi / 4, 0])) == [(0, 1)]
    # a circle near a box's corner: inside the bounding square but outside the box
    assert clashes(prims([BOX, CYLINDER], [(0, 0), (1.5, 1.5)], [(1, 1), (0.6, 0.6)], [0, 0])) == []
    assert clashes(prims([CYLINDER, BOX], [(1.3, 1.3), (0, 0)], [(0.6, 0.6), (1, 1)], [0, 0])) == [(0, 1)]
    assert clashes(prims([CYLINDER, CYLINDER], [(0, 0), (1.1, 0)], [(0.5, 0.5), (0.5, 0.5)], [0, 0])) == []


def test_same_seed_same_world_other_seed_other_world():
    a, b, c = generate_world(7, SHORT), generate_world(7, SHORT), generate_world(8, SHORT)
    assert np.array_equal(a.ground.semantics, b.ground.semantics)
    assert np.array_equal(a.ground.markings, b.ground.markings)
    for t in (0.0, 1.37, SHORT.duration):
        pa, pb = a.primitives(t), b.primitives(t)
        for name in Primitives.__dataclass_fields__:
            assert np.array_equal(getattr(pa, name), getattr(pb, name)), name
        assert np.array_equal(a.ego_pose(t), b.ego_pose(t))
        assert [(x.instance, x.category, x.attribute) for x in a.boxes(t)] == [
            (x.instance, x.category, x.attribute) for x in b.boxes(t)
        ]
    assert a.location == b.location and np.array_equal(a.sun_direction, b.sun_direction)
    assert a.summary() == b.summary()
    ga, gc = a.ground.semantics, c.ground.semantics
    assert not (ga.shape == gc.shape and np.array_equal(ga, gc))
    assert not np.allclose(a.ego_pose(0.0), c.ego_pose(0.0))


def test_primitives_are_a_pure_function_of_time(worlds):
    world = worlds[0]
    first = world.primitives(2.5)
    world.primitives(0.3), world.boxes(3.9), world.ego_pose(1.0)
    again = world.primitives(2.5)
    for name in Primitives.__dataclass_fields__:
        assert np.array_equal(getattr(first, name), getattr(again, name))


def test_primitive_tables_are_well_formed(worlds):
    for world in worlds:
        p = world.primitives(1.0)
        n = len(p)
        assert n > 100
        assert p.kind.dtype == np.int8 and p.semantic.dtype == np.uint8 and p.instance.dtype == np.int32
        assert p.color.dtype == np.float32 and p.texture.dtype == np.uint8 and p.reflectivity.dtype == np.float32
        assert p.center.shape == (n, 3) and p.half_size.shape == (n, 3)
        assert (p.half_size > 0).all() and (p.semantic <= 16).all()
        assert (p.center[:, 2] - p.half_size[:, 2] >= -1e-9).all()  # nothing below the ground
        assert ((p.color >= 0) & (p.color <= 1)).all() and ((p.reflectivity >= 0) & (p.reflectivity <= 1)).all()
        # one class per object, and the annotated objects' classes follow their categories
        for instance in np.unique(p.instance):
            assert len(np.unique(p.semantic[p.instance == instance])) == 1
        semantic_of = dict(zip(p.instance.tolist(), p.semantic.tolist(), strict=True))
        for obj in world.objects:
            assert semantic_of[obj.instance] == occ3d_id(obj.category)


def test_ego_pose_is_rigid_smooth_and_within_speed_range(worlds):
    for world in worlds:
        times = sample_times(world)
        poses = ego_track(world, times)
        rotation = poses[:, :3, :3]
        assert np.allclose(rotation @ rotation.transpose(0, 2, 1), np.eye(3), atol=1e-12)
        assert np.allclose(np.linalg.det(rotation), 1.0)
        assert np.allclose(poses[:, 3], [0, 0, 0, 1]) and np.allclose(poses[:, 2, 3], 0.0)
        assert np.allclose(rotation[:, 2], [0, 0, 1])  # yaw only
        step = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1) / STEP
        lo, hi = world.config.ego_speed
        assert (step > lo * 0.99).all() and (step < hi * 1.01).all()
        yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
        assert np.abs(np.diff(yaw)).max() < 0.05  # heading turns smoothly (>= 40 m radius)
        # the heading follows the direction of travel, and the velocity is the pose's derivative
        travel = np.diff(poses[:, :2, 3], axis=0)
        assert np.allclose(np.arctan2(travel[:, 1], travel[:, 0]), (yaw[1:] + yaw[:-1]) / 2, atol=1e-3)
        for t in (0.7, 2.2):
            numeric = (world.ego_pose(t + 1e-4)[:3, 3] - world.ego_pose(t - 1e-4)[:3, 3]) / 2e-4
            assert np.allclose(world.ego_velocity(t), numeric, atol=1e-5)
        assert world.ego_path_length == pytest.approx(step.sum() * STEP, rel=1e-3)


def test_ego_drives_on_driveable_surface_inside_the_raster(worlds):
    for world in worlds:
        poses = ego_track(world, sample_times(world))
        corners = np.array([[-1.0, 0.9], [-1.0, -0.9], [3.1, 0.9], [3.1, -0.9], [0.0, 0.0]])
        points = np.einsum("tij,kj->tki", poses[:, :2, :2], corners) + poses[:, None, :2, 3]
        assert (world.ground.lookup(points.reshape(-1, 2)) == 11).all()
        g = world.ground
        size = np.array(g.semantics.shape) * g.resolution
        xy = poses[:, :2, 3]
        assert (xy - world.config.margin >= g.origin - g.resolution).all()
        assert (xy + world.config.margin <= g.origin + size + g.resolution).all()


def test_ground_classes_and_paint(worlds):
    for world in worlds:
        g = world.ground
        classes = set(np.unique(g.semantics).tolist())
        assert classes <= {11, 12, 13, 14} and {11, 13, 14} <= classes
        assert not (g.markings & (g.semantics != 11)).any()
        painted = g.markings[g.semantics == 11].mean()
        assert 0.02 < painted < 0.3


def test_objects_never_overlap(worlds):
    for world in worlds:
        # halfway between the instants the generator checks (every 0.1 s): the worst case
        for t in np.arange(0.05, world.config.duration, 0.1):
            assert clashes(world.primitives(t)) == [], t


def test_nothing_in_the_egos_way(worlds):
    for world in worlds:
        for t in sample_times(world):
            pose = world.ego_pose(t)
            p = world.primitives(t)
            low = p.center[:, 2] - p.half_size[:, 2] < 2.0
            # the ego as a 4.1 x 1.8 m box centred 1 m ahead of the rear axle, tested as one more solid
            ego_centre = pose[:2, 3] + pose[:2, 0] * 1.0
            yaw = np.arctan2(pose[1, 0], pose[0, 0])
            probe = Primitives.concatenate([_subset(p, low), _box(ego_centre, (2.05, 0.9), yaw, -1)])
            assert not any(-1 in pair for pair in clashes(probe)), t


def _subset(p: Primitives, mask: np.ndarray) -> Primitives:
    return Primitives(**{name: getattr(p, name)[mask] for name in Primitives.__dataclass_fields__})


def _box(centre, half, yaw, instance) -> Primitives:
    return Primitives(
        kind=np.array([BOX], np.int8),
        center=np.array([[centre[0], centre[1], 0.8]]),
        half_size=np.array([[half[0], half[1], 0.8]]),
        yaw=np.array([yaw]),
        semantic=np.zeros(1, np.uint8),
        instance=np.array([instance], np.int32),
        color=np.zeros((1, 3), np.float32),
        texture=np.zeros(1, np.uint8),
        reflectivity=np.zeros(1, np.float32),
    )


def test_static_scenery_stands_off_roads_and_sidewalks(worlds):
    for world in worlds:
        p = world.primitives(0.0)
        buildings = p.texture == 1
        under = world.ground.lookup(p.center[buildings, :2])
        assert (under == 14).all()


def test_boxes_match_solids_categories_and_motion(worlds):
    for world in worlds:
        boxes = world.boxes(1.0)
        assert [b.instance for b in boxes] == [o.instance for o in world.objects]
        p = world.primitives(1.0)
        for box in boxes:
            assert box.center.shape == (3,) and box.size.shape == (3,) and box.velocity.shape == (2,)
            assert box.center[2] == pytest.approx(box.size[2] / 2)
            solids = p.instance == box.instance
            assert solids.any()
            # every solid's centre lies inside its box (footprint and height)
            c, s = np.cos(box.yaw), np.sin(box.yaw)
            d = p.center[solids, :2] - box.center[:2]
            along, across = d @ [c, s], d @ [-s, c]
            assert (np.abs(along) <= box.size[1] / 2 + 1e-6).all() and (np.abs(across) <= box.size[0] / 2 + 1e-6).all()
            assert (p.center[solids, 2] + p.half_size[solids, 2] <= box.size[2] + 1e-6).all()
            if box.category.startswith("vehicle.") and box.category not in ("vehicle.bicycle", "vehicle.motorcycle"):
                assert box.attribute in ("vehicle.moving", "vehicle.stopped", "vehicle.parked")
                assert (box.attribute == "vehicle.moving") == bool(np.hypot(*box.velocity) > 0)
            elif box.category.startswith("human."):
                assert (box.attribute == "pedestrian.moving") == bool(np.hypot(*box.velocity) > 0)
            elif box.category in ("vehicle.bicycle", "vehicle.motorcycle"):
                assert box.attribute in ("cycle.with_rider", "cycle.without_rider")
            else:
                assert box.attribute == ""


def test_box_sizes_follow_nuscenes_statistics():
    world = generate_world(11)
    sizes: dict[str, list[np.ndarray]] = {}
    for box in world.boxes(0.0):
        if box.category in CATEGORY_SIZES and box.attribute != "cycle.without_rider":
            sizes.setdefault(box.category, []).append(box.size)
    assert len(sizes) >= 8
    for category, values in sizes.items():
        mean = np.array(CATEGORY_SIZES[category])
        ratio = np.array(values) / mean
        assert ((ratio > 0.8) & (ratio < 1.2)).all(), category
        if len(values) >= 10:
            assert np.allclose(ratio.mean(axis=0), 1.0, atol=0.08), category


def test_velocity_is_the_derivative_of_the_centre(worlds):
    world = worlds[1]
    t, h = 1.5, 1e-3
    before, now, after = world.boxes(t - h), world.boxes(t), world.boxes(t + h)
    moving = 0
    for b0, b1, b2 in zip(before, now, after, strict=True):
        numeric = (b2.center[:2] - b0.center[:2]) / (2 * h)
        assert np.allclose(b1.velocity, numeric, atol=1e-4), b1.category
        moving += np.hypot(*b1.velocity) > 0
        # boxes move along their heading (forward or backward)
        if np.hypot(*b1.velocity) > 0:
            heading = np.array([np.cos(b1.yaw), np.sin(b1.yaw)])
            assert abs(abs(heading @ b1.velocity) - np.hypot(*b1.velocity)) < 1e-6
    assert moving > 5


def test_summary_counts_objects(worlds):
    world = worlds[2]
    summary = world.summary()
    annotated = {}
    for obj in world.objects:
        annotated[obj.category] = annotated.get(obj.category, 0) + 1
    assert {k: v for k, v in summary.items() if k in annotated} == annotated
    assert sum(summary.values()) == len(np.unique(world.primitives(0.0).instance))
    assert summary.get("static.manmade.building", 0) > 5 and summary.get("vehicle.car", 0) > 5


def test_config_is_validated():
    with pytest.raises(ValueError, match="ego_speed"):
        WorldConfig(ego_speed=(5.0, 2.0))
    with pytest.raises(ValueError, match="duration"):
        WorldConfig(duration=0.0)
    with pytest.raises(ValueError, match="density"):
        WorldConfig(density=-1.0)
    fixed = generate_world(3, WorldConfig(duration=2.0, ego_speed=(6.0, 6.0), density=0.3))
    assert fixed.ego_path_length == pytest.approx(12.0)


def test_every_class_is_near_the_ego_most_of_the_time():
    """With the default settings each Occ3D class 0..16 is within 40 m (ego axes) at 60 % of key frames."""
    hits = np.zeros(17)
    trials = 0
    grid = np.stack(np.meshgrid(np.arange(-39.5, 40, 1.0), np.arange(-39.5, 40, 1.0)), -1).reshape(-1, 2)
    for seed in range(8):
        world = generate_world(100 + seed)
        for t in np.linspace(0.0, world.config.duration, 5):
            pose = world.ego_pose(t)
            p = world.primitives(t)
            local = (p.center[:, :2] - pose[:2, 3]) @ pose[:2, :2]
            near = (np.abs(local) < 40).all(axis=1)
            present = set(p.semantic[near].tolist())
            present |= set(world.ground.lookup(grid @ pose[:2, :2].T + pose[:2, 3]).tolist())
            hits[list(present)] += 1
            trials += 1
    share = hits / trials
    assert (share >= 0.6).all(), {i: round(float(s), 2) for i, s in enumerate(share) if s < 0.6}
