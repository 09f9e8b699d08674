"""Which proposed objects make it into the world: in view, on allowed ground, and clear of everything else.

Proposals come in groups (a truck and its trailer, a bus stop's shelter and people) that are kept or dropped
together, in priority order. A group survives when it comes into view at some instant, none of its static objects
stands on forbidden ground, and none of its solids comes within a few centimetres of the ego's reserved space or
of an accepted solid of another object at any checked instant of the scene. The pairwise test is a numba
separating-axis check of yawed footprints, padded by the relative motion between two checked instants.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from occkit.sim.layout import Scene
from occkit.sim.motion import Tracks
from occkit.sim.objects import Object, solid
from occkit.sim.primitives import BOX

__all__ = ["CHECK_MARGIN", "EGO_RESERVE", "select"]

# Overlap check: time step (s), clearance kept between objects (m), and the share of the relative
# velocity times the step that covers motion between two checked instants (half a step, with 20 % slack).
_CHECK_DT = 0.1
CHECK_MARGIN = 0.1
_CHECK_SLACK = 0.6 * _CHECK_DT

# Space kept free around the ego: box centre ahead of the rear axle, half length, half width, height (m). It covers
# a 4.1 x 1.8 m car whether its centre sits at the rear axle or 1 m ahead of it.
EGO_RESERVE = (1.0, 3.4, 1.0, 2.0)


@njit(cache=True)
def _separated(ax, ay, ac, as_, ahx, ahy, bx, by, bc, bs, bhx, bhy, dvx, dvy, slack, margin):
    """Whether two yawed rectangles (centre, cos/sin of yaw, half sizes) are apart by more than ``margin`` plus
    ``slack`` times their relative velocity ``(dvx, dvy)``, along one of their four edge normals."""
    dx, dy = bx - ax, by - ay
    for axis in range(4):
        if axis == 0:
            ux, uy = ac, as_
        elif axis == 1:
            ux, uy = -as_, ac
        elif axis == 2:
            ux, uy = bc, bs
        else:
            ux, uy = -bs, bc
        ra = ahx * abs(ac * ux + as_ * uy) + ahy * abs(-as_ * ux + ac * uy)
        rb = bhx * abs(bc * ux + bs * uy) + bhy * abs(-bs * ux + bc * uy)
        if abs(dx * ux + dy * uy) - ra - rb > margin + abs(dvx * ux + dvy * uy) * slack:
            return True
    return False


@njit(cache=True)
def _conflict(i, j, moving, cx, cy, cos_, sin_, vx, vy, hx, hy, z0, z1, box, slack, margin):
    """Whether solids ``i`` and ``j`` come too close at any checked instant (static solids use column 0)."""
    if z0[i] >= z1[j] or z0[j] >= z1[i]:
        return False
    if box[i, 0] > box[j, 2] or box[j, 0] > box[i, 2] or box[i, 1] > box[j, 3] or box[j, 1] > box[i, 3]:
        return False
    times = cx.shape[1] if moving[i] or moving[j] else 1
    reach0 = math.sqrt(hx[i] ** 2 + hy[i] ** 2) + math.sqrt(hx[j] ** 2 + hy[j] ** 2) + margin
    for t in range(times):
        ti = t if moving[i] else 0
        tj = t if moving[j] else 0
        dvx, dvy = vx[i, ti] - vx[j, tj], vy[i, ti] - vy[j, tj]
        reach = reach0 + math.sqrt(dvx * dvx + dvy * dvy) * slack
        dx, dy = cx[j, tj] - cx[i, ti], cy[j, tj] - cy[i, ti]
        if dx * dx + dy * dy >= reach * reach:
            continue
        if not _separated(
            cx[i, ti], cy[i, ti], cos_[i, ti], sin_[i, ti], hx[i], hy[i],
            cx[j, tj], cy[j, tj], cos_[j, tj], sin_[j, tj], hx[j], hy[j], dvx, dvy, slack, margin,
        ):  # fmt: skip
            return True
    return False


@njit(cache=True)
def _select_groups(group_start, owner, moving, cx, cy, cos_, sin_, vx, vy, hx, hy, z0, z1, box, slack, margin):
    """Accept groups of solids in order unless a solid conflicts with an accepted one of another object (or with
    another object of its own group). Solids are sorted by group; returns ``(G,)`` bool."""
    num_groups = group_start.shape[0] - 1
    keep = np.zeros(num_groups, np.bool_)
    accepted = np.empty(owner.shape[0], np.int64)
    count = 0
    for g in range(num_groups):
        ok = True
        for i in range(group_start[g], group_start[g + 1]):
            for a in range(count + i - group_start[g]):
                j = accepted[a] if a < count else group_start[g] + a - count
                if owner[j] != owner[i] and _conflict(
                    i, j, moving, cx, cy, cos_, sin_, vx, vy, hx, hy, z0, z1, box, slack, margin
                ):
                    ok = False
                    break
            if not ok:
                break
        if ok:
            keep[g] = True
            for i in range(group_start[g], group_start[g + 1]):
                accepted[count] = i
                count += 1
    return keep


def _ego_object(scene: Scene) -> Object:
    """The space the ego needs, as an object moving with it (only used by the overlap check)."""
    ahead, half_length, half_width, height = EGO_RESERVE
    space = solid(BOX, ahead, 0.0, 0.0, height, half_length, half_width, (0.0, 0.0, 0.0))
    ego = scene.ego
    return Object("vehicle.ego", "ego", [space], track=(0, ego.l, ego.s0, ego.v, False))


def _object_poses(scene: Scene, objects: list[Object], times: np.ndarray) -> tuple[np.ndarray, ...]:
    """``x, y, yaw, vx, vy`` of every object at ``times``, each ``(N, T)``; object 0 is the ego."""
    n, num_times = len(objects), len(times)
    x, y, yaw, vx, vy = (np.zeros((n, num_times)) for _ in range(5))
    statics = [i for i, o in enumerate(objects) if o.track is None]
    pose = np.array([objects[i].pose for i in statics]).reshape(-1, 3)
    x[statics], y[statics], yaw[statics] = pose[:, :1], pose[:, 1:2], pose[:, 2:]
    movers = [i for i, o in enumerate(objects) if o.track is not None and i > 0]
    if movers:
        paths = [scene.path] + [c.path for c in scene.crossings]
        poses = Tracks.of([objects[i].track for i in movers]).poses(paths, times)
        x[movers], y[movers], yaw[movers], vx[movers], vy[movers] = poses
    ego = scene.ego
    ex, ey, eh = scene.path.at_lane(ego.s(times), ego.l)
    speed = ego.speed(times)
    x[0], y[0], yaw[0], vx[0], vy[0] = ex, ey, eh, speed * np.cos(eh), speed * np.sin(eh)
    return x, y, yaw, vx, vy


def _ground_ok(scene: Scene, objects: list[Object]) -> np.ndarray:
    """``(N,)`` whether each static object with a ground rule has only allowed flat classes under its base
    (the solids that touch the ground; 3 x 3 points over their extent, 0.1 m inside it)."""
    ok = np.ones(len(objects), bool)
    ruled = [i for i, o in enumerate(objects) if o.ground is not None and o.track is None]
    if not ruled:
        return ok
    grid = np.array([-1.0, 0.0, 1.0])
    points, masks = [], []
    for i in ruled:
        o = objects[i]
        base = np.array([s[1:7] for s in o.solids if s[3] - s[6] < 0.3])  # dx, dy, zc, hx, hy, hz
        lo = np.min(base[:, :2] - base[:, 3:5], axis=0) + 0.1
        hi = np.max(base[:, :2] + base[:, 3:5], axis=0) - 0.1
        centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 0.0)
        local = np.stack(np.meshgrid(centre[0] + grid * half[0], centre[1] + grid * half[1]), -1).reshape(-1, 2)
        x, y, yaw = o.pose
        c, s = math.cos(yaw), math.sin(yaw)
        points.append(np.stack([x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1]], 1))
        masks.append(sum(1 << g for g in o.ground))
    classes = scene.ground.lookup(np.concatenate(points)).reshape(len(ruled), -1).astype(np.int64)
    allowed = (np.array(masks)[:, None] >> classes) & 1
    ok[ruled] = allowed.all(axis=1)
    return ok


def _plausible(scene: Scene, objects: list[Object], group_of: np.ndarray, x, y) -> np.ndarray:
    """``(N,)`` whether each object's group is worth checking: some object of it comes into view (the world's
    bounding box) at some instant, and none of its static objects stands on forbidden ground."""
    lo, hi = scene.bbox[:2] - 5.0, scene.bbox[2:] + 5.0
    seen = ((x > lo[0]) & (x < hi[0]) & (y > lo[1]) & (y < hi[1])).any(axis=1)
    group_seen = np.zeros(group_of.max() + 1, bool)
    np.logical_or.at(group_seen, group_of, seen)
    group_bad = np.zeros(group_of.max() + 1, bool)
    np.logical_or.at(group_bad, group_of, ~_ground_ok(scene, objects))
    return (group_seen & ~group_bad)[group_of]


def _clear_groups(objects: list[Object], group_of: np.ndarray, x, y, yaw, vx, vy) -> np.ndarray:
    """Run the overlap check over the objects' solids (object poses ``(N, T)``); ``(G,)`` kept flags in the order
    of ``np.unique(group_of)``."""
    rows = np.array([s for o in objects for s in o.solids], float)
    owner = np.repeat(np.arange(len(objects)), [len(o.solids) for o in objects])
    moving = np.array([o.track is not None for o in objects])[owner]
    c, s = np.cos(yaw[owner]), np.sin(yaw[owner])
    dx, dy = rows[:, 1:2], rows[:, 2:3]
    cx, cy = x[owner] + c * dx - s * dy, y[owner] + s * dx + c * dy
    hx, hy = rows[:, 4].copy(), rows[:, 5].copy()
    z0, z1 = rows[:, 3] - rows[:, 6], rows[:, 3] + rows[:, 6]
    speed = np.hypot(vx, vy).max(axis=1)[owner]
    grow = np.hypot(hx, hy) + CHECK_MARGIN + speed * _CHECK_SLACK
    box = np.stack([cx.min(1) - grow, cy.min(1) - grow, cx.max(1) + grow, cy.max(1) + grow], axis=1)
    _, first = np.unique(group_of[owner], return_index=True)
    group_start = np.append(first, len(rows)).astype(np.int64)
    return _select_groups(
        group_start, owner, moving, cx, cy, c, s, vx[owner], vy[owner], hx, hy, z0, z1, box, _CHECK_SLACK, CHECK_MARGIN
    )


def select(scene: Scene, groups: list[list[Object]]) -> list[Object]:
    """The proposals that survive, in order: in view at some instant, standing on allowed ground, and clear of
    the ego and of every earlier accepted object at every instant of the scene (checked every ``_CHECK_DT``)."""
    duration = scene.config.duration
    times = np.linspace(0.0, duration, int(math.ceil(duration / _CHECK_DT)) + 1)
    objects = [_ego_object(scene)] + [o for g in groups for o in g]
    group_of = np.repeat(np.arange(len(groups) + 1), [1] + [len(g) for g in groups])
    poses = _object_poses(scene, objects, times)
    keep = _plausible(scene, objects, group_of, poses[0], poses[1])
    keep[0] = True  # the ego
    objects, group_of = [o for o, k in zip(objects, keep, strict=True) if k], group_of[keep]
    kept = np.unique(group_of)[_clear_groups(objects, group_of, *(p[keep] for p in poses))]
    return [o for o, g in zip(objects[1:], group_of[1:], strict=True) if g in set(kept.tolist())]
