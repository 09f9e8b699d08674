"""A procedural, seeded driving world: roads, buildings, street furniture and traffic, as analytic solids.

One seed fixes everything. The ego drives a right-hand lane of a main road made of straights and circular arcs,
crossed every 60 to 150 m by a perpendicular-ish two-lane road. The ground is a raster of Occ3D flat classes with
road paint; everything above it is a :class:`~occkit.sim.primitives.Primitives` table of boxes, cylinders and
ellipsoids, each solid tagged with the Occ3D class and the instance id of the object it belongs to.

Every moving object follows a curve at constant speed (the ego with a gentle speed oscillation), so
:meth:`World.primitives` is an analytic function of time. Objects are proposed in priority order (the ego's sweep,
road works, bus stops, buildings, furniture, parked and moving vehicles, pedestrians) and a proposal is dropped when
any of its solids would come closer than a few centimetres to an accepted solid of another object at any time of
the scene: no two objects ever overlap, and nothing stands in the ego's way.

Lateral offsets ``l`` are measured to the left of a road's direction; the right-hand lanes of the main road have
``l < 0`` and carry traffic along the road's direction (``+s``), the left-hand lanes carry it the other way.

This module holds the public API and puts a world together from its parts: :mod:`~occkit.sim.roads` (road
geometry), :mod:`~occkit.sim.layout` (the scene's random layout), :mod:`~occkit.sim.ground` (the ground raster),
:mod:`~occkit.sim.objects` (the object catalogue), :mod:`~occkit.sim.placement` (where objects go),
:mod:`~occkit.sim.selection` (which of them are kept) and :mod:`~occkit.sim.motion` (how they move).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from occkit.sim.config import WorldConfig
from occkit.sim.ground import paint_ground
from occkit.sim.layout import Scene, draw_cross_section, draw_crossings, draw_ego_motion, draw_main_path, draw_plan
from occkit.sim.motion import EgoMotion, Tracks, wrap
from occkit.sim.objects import CATEGORY_SIZES, STYLES, Object, place_solids, solid_rows
from occkit.sim.placement import Placer
from occkit.sim.primitives import Primitives
from occkit.sim.selection import select

__all__ = ["CATEGORY_SIZES", "WorldConfig", "AnnotatedObject", "BoxState", "World", "generate_world"]


@dataclass(frozen=True)
class AnnotatedObject:
    """An object that gets nuScenes boxes (a ``sample_annotation`` per key frame)."""

    instance: int
    """Equals :attr:`Primitives.instance` of the object's solids."""
    category: str
    """nuScenes category, e.g. ``"vehicle.car"``."""


@dataclass(frozen=True)
class BoxState:
    """An annotated object's box at one instant, in the global frame.

    Attributes:
        instance: the object's instance id.
        category: nuScenes category.
        center: ``(3,)`` box centre; ``z`` is half the height (every object stands on the ground).
        size: ``(3,)`` nuScenes order width, length, height (m).
        yaw: heading (radians about +z) of the box's length axis.
        velocity: ``(2,)`` global ``vx, vy`` (m/s).
        attribute: nuScenes attribute name, ``""`` for objects without one (barriers, cones, debris, racks).
    """

    instance: int
    category: str
    center: np.ndarray
    size: np.ndarray
    yaw: float
    velocity: np.ndarray
    attribute: str


class World:
    """A generated scene: ground raster, sky and sun, the ego's drive, and every object's solids over time.

    Attributes:
        seed: the seed it was generated from.
        config: its settings.
        ground: the painted ground raster.
        sun_direction: ``(3,)`` unit vector toward the sun (elevation 15..70 degrees).
        sky_zenith, sky_horizon: ``(3,)`` float32 sRGB sky colours in ``[0, 1]``.
        location: nuScenes log location, ``"synth-city-<k>"``.
        objects: the annotated objects (those that get boxes), by instance id.
        categories: nuScenes category of every object, annotated or not, indexed by instance id.
        ego_path_length: metres the ego drives in ``config.duration`` seconds.
    """

    def __init__(
        self,
        seed: int,
        config: WorldConfig,
        scene: Scene,
        accepted: list[Object],
        sun_direction: np.ndarray,
        sky: tuple[np.ndarray, np.ndarray],
        location: str,
    ) -> None:
        self.seed, self.config, self.ground, self.location = seed, config, scene.ground, location
        self.sun_direction = sun_direction
        self.sky_zenith, self.sky_horizon = sky
        self._path, self._ego = scene.path, scene.ego
        self._paths = [scene.path] + [c.path for c in scene.crossings]
        self.ego_path_length = float(self._ego.s(config.duration) - self._ego.s(0.0))
        self._kinds = Counter(o.category if o.size is not None else f"{o.category}.{o.kind}" for o in accepted)
        self.objects = tuple(AnnotatedObject(i, o.category) for i, o in enumerate(accepted) if o.size is not None)
        self.categories = tuple(o.category for o in accepted)
        self._build_tables(accepted)

    def _build_tables(self, accepted: list[Object]) -> None:
        """Static solids in the global frame; moving objects as tracks plus solids in their own frame."""
        statics = [i for i, o in enumerate(accepted) if o.track is None]
        movers = [i for i, o in enumerate(accepted) if o.track is not None]
        rows, poses, ids = solid_rows(accepted, statics)
        self._static = place_solids(rows, *poses, ids)
        rows, _, ids = solid_rows(accepted, movers)
        self._mover_rows, self._mover_ids = rows, ids
        self._mover_owner = np.repeat(np.arange(len(movers)), [len(accepted[i].solids) for i in movers])
        self._tracks = Tracks.of([accepted[i].track for i in movers])
        self._static_boxes = [
            (i, o.category, np.array(o.size), o.pose, float(wrap(o.pose[2])), o.attribute)
            for i, o in enumerate(accepted)
            if o.size is not None and o.track is None
        ]
        self._mover_boxes = [
            (i, row, o.category, np.array(o.size), o.attribute)
            for row, i in enumerate(movers)
            if (o := accepted[i]).size is not None
        ]

    # ---------------------------------------------------------------------------------------------- ego
    def ego_pose(self, t: float) -> np.ndarray:
        """``(4, 4)`` float64 ego2global at time ``t`` (s): ego x forward, y left, z up, origin on the ground."""
        x, y, h = self._path.at_lane(self._ego.s(t), self._ego.l)
        c, s = math.cos(float(h)), math.sin(float(h))
        pose = np.eye(4)
        pose[:2, :2] = [[c, -s], [s, c]]
        pose[:2, 3] = float(x), float(y)
        return pose

    def ego_velocity(self, t: float) -> np.ndarray:
        """``(3,)`` global velocity (m/s) of the ego at time ``t``."""
        _, _, h = self._path.at_lane(self._ego.s(t), self._ego.l)
        speed = float(self._ego.speed(t))
        return np.array([speed * math.cos(float(h)), speed * math.sin(float(h)), 0.0])

    # ---------------------------------------------------------------------------------------------- objects
    def primitives(self, t: float) -> Primitives:
        """Every solid of the world at time ``t`` (s), global frame: static solids first, then moving ones."""
        x, y, yaw, _, _ = self._tracks.poses(self._paths, np.array([float(t)]))
        owner = self._mover_owner
        moving = place_solids(self._mover_rows, x[owner, 0], y[owner, 0], yaw[owner, 0], self._mover_ids)
        return Primitives.concatenate([self._static, moving])

    def primitive_velocities(self, t: float) -> np.ndarray:
        """``(P, 2)`` float64 global ``vx, vy`` (m/s) of every solid of :meth:`primitives` at time ``t``, row for row:
        zero for static solids, the object's box velocity (:meth:`boxes`) for a moving one."""
        _, _, _, vx, vy = self._tracks.poses(self._paths, np.array([float(t)]))
        owner = self._mover_owner
        moving = np.stack((vx[owner, 0], vy[owner, 0]), axis=-1).reshape(-1, 2)
        return np.concatenate((np.zeros((len(self._static), 2)), moving))

    def boxes(self, t: float) -> list[BoxState]:
        """Boxes of all annotated objects at time ``t`` (s), by instance id; culling by range is the caller's."""
        boxes = [
            BoxState(i, cat, np.array([pose[0], pose[1], size[2] / 2]), size.copy(), yaw, np.zeros(2), attr)
            for i, cat, size, pose, yaw, attr in self._static_boxes
        ]
        x, y, yaw, vx, vy = self._tracks.poses(self._paths, np.array([float(t)]))
        for i, row, cat, size, attr in self._mover_boxes:
            centre = np.array([x[row, 0], y[row, 0], size[2] / 2])
            velocity = np.array([vx[row, 0], vy[row, 0]])
            boxes.append(BoxState(i, cat, centre, size.copy(), float(wrap(yaw[row, 0])), velocity, attr))
        boxes.sort(key=lambda b: b.instance)
        return boxes

    def summary(self) -> dict[str, int]:
        """Object counts: annotated objects by nuScenes category, the rest by ``"<category>.<kind>"``."""
        return dict(sorted(self._kinds.items()))


def generate_world(seed: int, config: WorldConfig = WorldConfig()) -> World:  # noqa: B008 - frozen, immutable
    """Generate the world of ``seed``: road layout, ground raster, ego drive and all objects.

    Deterministic: the same seed and config give identical arrays. Independent random streams for the layout,
    the objects and the sky keep a change in one from reshuffling the others.
    """
    layout_rng, object_rng, sky_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    city = int(layout_rng.integers(len(STYLES)))
    xsec = draw_cross_section(layout_rng)
    ego_lane = int(layout_rng.integers(xsec.lanes[0]))
    ego = draw_ego_motion(layout_rng, config, xsec.lane(0, ego_lane))
    start = config.margin + float(layout_rng.uniform(5, 25))
    drive = ego.v * (1 + ego.a) * config.duration
    path = draw_main_path(layout_rng, start + 1.3 * drive + config.margin + 40.0)
    ego = EgoMotion(ego.l, float(path.centre_to_lane(start, ego.l)), ego.v, ego.a, ego.w, ego.phase)
    ends = path.lane_to_centre(ego.s(np.array([0.0, config.duration])), ego.l)
    view = (float(ends[0]) - config.margin, float(ends[1]) + config.margin)
    ex, ey, _ = path.at_lane(ego.s(np.linspace(0.0, config.duration, 64)), ego.l)
    bbox = np.array([ex.min(), ey.min(), ex.max(), ey.max()]) + np.array([-1, -1, 1, 1]) * config.margin
    crossings = draw_crossings(layout_rng, path, xsec, view, 1.5 * config.margin + 30.0)
    plan = draw_plan(layout_rng, xsec, ego_lane, crossings, view, float(ends[0]), config.density)
    ground = paint_ground(path, xsec, crossings, plan, bbox, config.ground_resolution)
    scene = Scene(object_rng, config, path, xsec, ego_lane, ego, crossings, ground, view, bbox, STYLES[city])

    placer = Placer(scene)
    placer.companions()
    for side, s0, s1, closes in plan.works:
        placer.works(side, s0, s1, closes)
    for side, s, in_bay in plan.bus_stops:
        placer.bus_stop(side, s, in_bay)
    placer.junctions()
    placer.buildings()
    placer.furniture()
    placer.parked()
    placer.riders()
    placer.main_traffic()
    placer.crossing_traffic()
    placer.pedestrians()
    accepted = select(scene, placer.groups)

    elevation, azimuth = np.radians(sky_rng.uniform(15, 70)), sky_rng.uniform(-np.pi, np.pi)
    sun = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    zenith = np.clip(np.array([0.22, 0.42, 0.78]) + sky_rng.uniform(-0.05, 0.05, 3), 0, 1).astype(np.float32)
    horizon = np.clip(np.array([0.72, 0.8, 0.88]) + sky_rng.uniform(-0.05, 0.05, 3), 0, 1).astype(np.float32)
    return World(seed, config, scene, accepted, sun, (zenith, horizon), f"synth-city-{city}")
