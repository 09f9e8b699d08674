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
"""

from __future__ import annotations

import bisect
import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from occkit.classes import occ3d_id
from occkit.sim.primitives import BOX, CYLINDER, ELLIPSOID, GroundMap, Primitives, Texture

__all__ = ["CATEGORY_SIZES", "WorldConfig", "AnnotatedObject", "BoxState", "World", "generate_world"]

LANE_WIDTH = 3.5
_DRIVEABLE, _OTHER_FLAT, _SIDEWALK, _TERRAIN = 11, 12, 13, 14

#: nuScenes mean box size (width, length, height) in metres of the categories the world annotates.
CATEGORY_SIZES: dict[str, tuple[float, float, float]] = {
    "vehicle.car": (1.95, 4.62, 1.73),
    "vehicle.truck": (2.52, 6.93, 2.84),
    "vehicle.bus.rigid": (2.94, 11.19, 3.47),
    "vehicle.trailer": (2.90, 12.28, 3.87),
    "vehicle.construction": (2.82, 6.44, 3.21),
    "vehicle.motorcycle": (0.77, 2.11, 1.47),
    "vehicle.bicycle": (0.61, 1.70, 1.30),
    "human.pedestrian.adult": (0.67, 0.73, 1.77),
    "human.pedestrian.construction_worker": (0.67, 0.73, 1.77),
    "movable_object.barrier": (2.53, 0.50, 0.98),
    "movable_object.trafficcone": (0.41, 0.41, 0.85),
}

# Generator's overlap check: time step (s), clearance kept between objects (m), and the share of the relative
# velocity times the step that covers motion between two checked instants (half a step, with 20 % slack).
_CHECK_DT = 0.1
_CHECK_MARGIN = 0.1
_CHECK_SLACK = 0.6 * _CHECK_DT

# Space kept free around the ego: box centre ahead of the rear axle, half length, half width, height (m). It covers
# a 4.1 x 1.8 m car whether its centre sits at the rear axle or 1 m ahead of it.
_EGO_RESERVE = (1.0, 3.4, 1.0, 2.0)

_BAY_DEPTH = 3.2  # bus bays: driveable from the road edge this far out (m)
_DRIVEWAY_DEPTH = 1.5  # driveways: other_flat from the kerb to this far beyond the sidewalk (m)
_TALL_VEHICLE = 4.6  # no vehicle is taller (m); street-tree crowns start above it

_VEHICLE_COLORS = np.array(
    [
        (0.90, 0.90, 0.88),  # white
        (0.05, 0.05, 0.06),  # black
        (0.24, 0.25, 0.27),  # dark grey
        (0.48, 0.49, 0.51),  # grey
        (0.70, 0.71, 0.73),  # silver
        (0.58, 0.07, 0.06),  # red
        (0.10, 0.20, 0.50),  # blue
        (0.09, 0.28, 0.16),  # dark green
        (0.76, 0.68, 0.52),  # beige
        (0.86, 0.70, 0.10),  # yellow
        (0.85, 0.40, 0.08),  # orange
        (0.35, 0.22, 0.14),  # brown
    ]
)
_VEHICLE_COLOR_WEIGHTS = np.array([24, 15, 11, 10, 12, 7, 7, 3, 3, 4, 2, 2], float)
_CLOTHES = np.array(
    [(0.1, 0.1, 0.12), (0.85, 0.85, 0.82), (0.2, 0.25, 0.45), (0.55, 0.1, 0.1), (0.35, 0.35, 0.35), (0.6, 0.5, 0.3)]
)
_SKIN = np.array([(0.87, 0.72, 0.6), (0.65, 0.48, 0.36), (0.42, 0.3, 0.22), (0.95, 0.8, 0.7)])
_HI_VIS = (0.95, 0.55, 0.05)
# Facade materials: albedo and LiDAR reflectivity.
_MATERIALS = {
    "concrete": ((0.62, 0.61, 0.58), 0.3),
    "brick": ((0.55, 0.28, 0.19), 0.3),
    "glass": ((0.26, 0.34, 0.42), 0.2),
    "plaster": ((0.84, 0.79, 0.68), 0.3),
}


@dataclass(frozen=True)
class _Style:
    """Look of a city: facade material weights (concrete, brick, glass, plaster) and building heights (m)."""

    materials: tuple[float, float, float, float]
    height: tuple[float, float]
    trees: float  # relative density of trees and hedges


_STYLES = (
    _Style((0.5, 0.1, 0.3, 0.1), (10.0, 25.0), 0.7),  # downtown
    _Style((0.2, 0.6, 0.0, 0.2), (6.0, 14.0), 1.2),  # brick terraces
    _Style((0.3, 0.0, 0.6, 0.1), (12.0, 25.0), 0.8),  # business park
    _Style((0.2, 0.2, 0.0, 0.6), (6.0, 10.0), 1.5),  # suburb
)


# ============================================================================================ public types
@dataclass(frozen=True)
class WorldConfig:
    """Settings of the procedural world."""

    duration: float = 20.0
    """Seconds the ego drives (the scene length)."""
    ego_speed: tuple[float, float] = (4.0, 10.0)
    """Range (m/s) of the ego's mean speed, drawn per scene."""
    ground_resolution: float = 0.1
    """Cell size (m) of the ground raster."""
    margin: float = 60.0
    """The world extends this far (m) beyond the ego path; the sensors see about 55 m."""
    density: float = 1.0
    """Scales the number of objects: traffic, pedestrians, furniture (less makes faster tests)."""

    def __post_init__(self) -> None:
        lo, hi = self.ego_speed
        if not 0.0 < lo <= hi:
            raise ValueError(f"ego_speed must be a range 0 < lo <= hi, got {self.ego_speed}")
        for name in ("duration", "ground_resolution", "density"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.margin < 0:
            raise ValueError(f"margin must be non-negative, got {self.margin}")


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


# ============================================================================================ road geometry
class _Path:
    """A planar curve of straight pieces and circular arcs, parameterised by arc length ``s`` (m).

    Piece ``i`` starts at arc length ``start[i]`` at ``(x0[i], y0[i])`` with heading ``h0[i]`` and has curvature
    ``k[i]`` (1/m, positive turning left) and length ``length[i]``. Before its start and after its end the curve
    goes on along its first and last piece, which are straight.

    A lateral offset ``l`` gives a parallel curve (a lane, a sidewalk line) with its own arc length ``s_lane``,
    equal to ``s`` at the start; along piece ``i`` it grows by ``1 - k[i] * l`` per metre of ``s``.
    """

    def __init__(self, x0: float, y0: float, heading: float, pieces: list[tuple[float, float]]) -> None:
        """Chain ``pieces`` of ``(curvature, length)`` from ``(x0, y0)`` heading ``heading`` (radians)."""
        xs, ys, hs = [], [], []
        x, y, h = x0, y0, heading
        for k, length in pieces:
            xs.append(x)
            ys.append(y)
            hs.append(h)
            x, y, h = _advance(x, y, h, k, length)
        self.x0, self.y0, self.h0 = np.array(xs), np.array(ys), np.array(hs)
        self.k = np.array([p[0] for p in pieces], float)
        self.length = np.array([p[1] for p in pieces], float)
        self.start = np.concatenate(([0.0], np.cumsum(self.length)[:-1]))
        self.turn = self.h0 - self.h0[0]  # heading gained before each piece (rad)
        self._starts = self.start.tolist()

    def _piece(self, s: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.start, s, side="right") - 1, 0, len(self.k) - 1)

    def frame(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position ``x, y`` and heading of the curve at arc lengths ``s`` (any shape)."""
        s = np.asarray(s, float)
        i = self._piece(s)
        ds, k, h0 = s - self.start[i], self.k[i], self.h0[i]
        h = h0 + k * ds
        straight = k == 0.0
        k_safe = np.where(straight, 1.0, k)
        x = self.x0[i] + np.where(straight, ds * np.cos(h0), (np.sin(h) - np.sin(h0)) / k_safe)
        y = self.y0[i] + np.where(straight, ds * np.sin(h0), (np.cos(h0) - np.cos(h)) / k_safe)
        return x, y, h

    def point(self, s: float, l: float) -> tuple[float, float, float]:
        """Scalar ``x, y, heading`` at arc length ``s`` and lateral offset ``l`` (plain floats, no numpy)."""
        i = min(max(bisect.bisect_right(self._starts, s) - 1, 0), len(self._starts) - 1)
        x, y, h = _advance(
            float(self.x0[i]), float(self.y0[i]), float(self.h0[i]), float(self.k[i]), s - self._starts[i]
        )
        return x - l * math.sin(h), y + l * math.cos(h), h

    def lane_to_centre(self, s_lane: np.ndarray, l: np.ndarray) -> np.ndarray:
        """Arc length ``s`` of the curve at arc lengths ``s_lane`` of its parallels at offsets ``l`` (same shapes)."""
        s_lane, l = np.broadcast_arrays(np.asarray(s_lane, float), np.asarray(l, float))
        flat_s, flat_l = s_lane.reshape(-1), l.reshape(-1)
        lane_start = self.start[None, :] - flat_l[:, None] * self.turn[None, :]
        i = np.maximum((lane_start <= flat_s[:, None]).sum(axis=1) - 1, 0)
        rows = np.arange(len(flat_s))
        s = self.start[i] + (flat_s - lane_start[rows, i]) / (1.0 - self.k[i] * flat_l)
        return s.reshape(s_lane.shape)

    def centre_to_lane(self, s, l) -> np.ndarray:
        """Arc length along the parallel at offset ``l`` of the point at arc length ``s`` of the curve."""
        s, l = np.asarray(s, float), np.asarray(l, float)
        i = self._piece(s)
        return self.start[i] - l * self.turn[i] + (s - self.start[i]) * (1.0 - self.k[i] * l)

    def at_lane(self, s_lane: np.ndarray, l: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``x, y, heading`` at arc lengths ``s_lane`` of the parallels at offsets ``l``; the heading is the curve's."""
        x, y, h = self.frame(self.lane_to_centre(s_lane, l))
        return x - l * np.sin(h), y + l * np.cos(h), h

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Arc length ``s`` and lateral offset ``l`` of the nearest curve point of each of the points ``(N, 2)``."""
        xy = np.ascontiguousarray(xy, dtype=np.float64)
        return _project_points(xy[:, 0], xy[:, 1], *self.pieces())

    def pieces(self) -> tuple[np.ndarray, ...]:
        """The piece table ``x0, y0, h0, k, length, start`` for the numba kernels."""
        return self.x0, self.y0, self.h0, self.k, self.length, self.start


def _advance(x: float, y: float, h: float, k: float, ds: float) -> tuple[float, float, float]:
    """Pose after ``ds`` metres along a piece of curvature ``k`` from ``(x, y)`` heading ``h``."""
    if k == 0.0:
        return x + ds * math.cos(h), y + ds * math.sin(h), h
    h1 = h + k * ds
    return x + (math.sin(h1) - math.sin(h)) / k, y + (math.cos(h) - math.cos(h1)) / k, h1


@njit(cache=True)
def _piece_coords(px, py, x0, y0, h0, k, length, first, last):
    """Arc length from the start of one piece, signed lateral offset, and whether the point projects onto it."""
    c, s = math.cos(h0), math.sin(h0)
    if k == 0.0:
        dx, dy = px - x0, py - y0
        u = dx * c + dy * s
        l = -dx * s + dy * c
    else:
        r = 1.0 / k
        cx, cy = x0 - s * r, y0 + c * r  # centre of the arc, on the left for k > 0
        dx, dy = px - cx, py - cy
        ax, ay = x0 - cx, y0 - cy
        u = math.atan2(ax * dy - ay * dx, ax * dx + ay * dy) * r
        radius = math.sqrt(dx * dx + dy * dy)
        l = abs(r) - radius if k > 0 else radius - abs(r)
    valid = (u >= -1e-6 or first) and (u <= length + 1e-6 or last)
    return u, l, valid


@njit(cache=True)
def _project_points(px, py, x0, y0, h0, k, length, start):
    """Nearest-piece ``(s, l)`` of points ``(N,)``; the tables are :meth:`_Path.pieces`."""
    n, num = px.shape[0], k.shape[0]
    s_out, l_out = np.zeros(n), np.full(n, np.inf)
    for q in range(n):
        for p in range(num):
            u, l, valid = _piece_coords(px[q], py[q], x0[p], y0[p], h0[p], k[p], length[p], p == 0, p == num - 1)
            if valid and abs(l) < abs(l_out[q]):
                s_out[q], l_out[q] = start[p] + u, l
    return s_out, l_out


@njit(cache=True)
def _road_coordinates(x0, y0, h0, k, length, start, ox, oy, res, nx, ny, half_width):
    """``(s, l)`` of the main road for raster cells within ``half_width`` of it (others: ``l = inf``).

    Each piece only visits the cells of its bounding box (the end pieces reach to the raster's edge).
    """
    s_map = np.full((nx, ny), np.nan, np.float32)
    l_map = np.full((nx, ny), np.inf, np.float32)
    num = k.shape[0]
    reach = (nx + ny) * res  # longer than the raster's diagonal
    for p in range(num):
        lo_u = -reach if p == 0 else 0.0
        hi_u = length[p] + reach if p == num - 1 else length[p]
        xmin, ymin, xmax, ymax = np.inf, np.inf, -np.inf, -np.inf
        for q in range(33):
            u = lo_u + (hi_u - lo_u) * q / 32.0
            h = h0[p] + k[p] * u
            if k[p] == 0.0:
                x, y = x0[p] + u * math.cos(h0[p]), y0[p] + u * math.sin(h0[p])
            else:
                x = x0[p] + (math.sin(h) - math.sin(h0[p])) / k[p]
                y = y0[p] + (math.cos(h0[p]) - math.cos(h)) / k[p]
            xmin, xmax, ymin, ymax = min(xmin, x), max(xmax, x), min(ymin, y), max(ymax, y)
        i0 = max(int((xmin - half_width - ox) / res), 0)
        i1 = min(int((xmax + half_width - ox) / res) + 1, nx)
        j0 = max(int((ymin - half_width - oy) / res), 0)
        j1 = min(int((ymax + half_width - oy) / res) + 1, ny)
        for i in range(i0, i1):
            px = ox + (i + 0.5) * res
            for j in range(j0, j1):
                py = oy + (j + 0.5) * res
                u, l, valid = _piece_coords(px, py, x0[p], y0[p], h0[p], k[p], length[p], p == 0, p == num - 1)
                if valid and abs(l) < half_width and abs(l) < abs(l_map[i, j]):
                    s_map[i, j], l_map[i, j] = start[p] + u, l
    return s_map, l_map


@dataclass(frozen=True)
class _CrossSection:
    """Lateral layout of the main road; index 0 is the right side (``l < 0``), 1 the left.

    Attributes:
        median: half width (m) of the median island, 0 for none.
        lanes: lanes per side.
        parking: width (m) of the parking strip per side, 0 for none.
        sidewalk: width (m) of the sidewalk per side.
    """

    median: float
    lanes: tuple[int, int]
    parking: tuple[float, float]
    sidewalk: tuple[float, float]

    def edge(self, side: int) -> float:
        """Distance (m) from the centreline to the outer edge of the carriageway."""
        return self.median + self.lanes[side] * LANE_WIDTH

    def kerb(self, side: int) -> float:
        """Distance (m) to the kerb: the inner edge of the sidewalk."""
        return self.edge(side) + self.parking[side]

    def outer(self, side: int) -> float:
        """Distance (m) to the outer edge of the sidewalk."""
        return self.kerb(side) + self.sidewalk[side]

    def lane(self, side: int, j: int) -> float:
        """Signed offset ``l`` of the centre of lane ``j`` (0 next to the centre) of a side."""
        return _SIGN[side] * (self.median + LANE_WIDTH * (j + 0.5))

    def profile(self) -> np.ndarray:
        """``(7,)`` median, then edge, kerb, outer of the right and of the left side, for the numba painters."""
        return np.array([self.median] + [f(side) for side in (0, 1) for f in (self.edge, self.kerb, self.outer)])


_SIGN = (-1.0, 1.0)  # sign of l per side


@dataclass
class _Crossing:
    """A straight two-lane road through the main road at main arc length ``s_main``.

    Its own arc length ``sc`` is 0 at the main road's centreline and runs along ``u`` (pointing to the main
    road's left); it spans ``[-minus, plus]``. Its path starts at ``sc = -minus``.
    """

    s_main: float
    point: np.ndarray
    u: np.ndarray
    tangent: np.ndarray  # the main road's direction at the crossing
    minus: float
    plus: float
    sidewalk: float
    half_width: float = LANE_WIDTH
    path: _Path = field(init=False)

    def __post_init__(self) -> None:
        start = self.point - self.minus * self.u
        heading = math.atan2(self.u[1], self.u[0])
        self.path = _Path(float(start[0]), float(start[1]), heading, [(0.0, self.minus + self.plus)])

    def xy(self, sc: np.ndarray, lc: np.ndarray) -> np.ndarray:
        """Global points ``(..., 2)`` at crossing arc lengths ``sc`` and lateral offsets ``lc``."""
        sc, lc = np.asarray(sc, float), np.asarray(lc, float)
        n = np.array([-self.u[1], self.u[0]])
        return self.point + sc[..., None] * self.u + lc[..., None] * n

    def geometry(self) -> np.ndarray:
        """``(10,)`` point, u, tangent, minus, plus, half width, sidewalk, for the numba painter."""
        values = [*self.point, *self.u, *self.tangent, self.minus, self.plus, self.half_width, self.sidewalk]
        return np.array(values, float)


@dataclass
class _Plan:
    """Where the main road's features go, as main arc-length intervals per side.

    ``bays``, ``driveways``: rows ``(side, s0, s1)``; ``works``: ``(side, s0, s1, closes_lane)``;
    ``bus_stops``: ``(side, s, in_bay)``.
    """

    bays: list[tuple[int, float, float]] = field(default_factory=list)
    driveways: list[tuple[int, float, float]] = field(default_factory=list)
    works: list[tuple[int, float, float, bool]] = field(default_factory=list)
    bus_stops: list[tuple[int, float, bool]] = field(default_factory=list)


@dataclass
class _Scene:
    """Everything the object placement needs: road, ego motion, crossings, plan, ground and the view."""

    rng: np.random.Generator
    config: WorldConfig
    path: _Path
    xsec: _CrossSection
    ego_side_lane: int
    ego: _EgoMotion
    crossings: list[_Crossing]
    plan: _Plan
    ground: GroundMap
    view: tuple[float, float]  # main arc-length range (m) that the sensors can see during the scene
    bbox: np.ndarray  # (4,) xmin, ymin, xmax, ymax of the world that matters
    style: _Style


# ============================================================================================ ego motion
@dataclass(frozen=True)
class _EgoMotion:
    """The ego's lane arc length ``s(t) = s0 + v t + (a v / w) (sin(w t + phase) - sin(phase))`` on offset ``l``.

    Its speed ``v (1 + a cos(w t + phase))`` oscillates gently around the scene's mean speed ``v``.
    """

    l: float
    s0: float
    v: float
    a: float
    w: float
    phase: float

    def s(self, t):
        t = np.asarray(t, float)
        return (
            self.s0 + self.v * t + self.a * self.v / self.w * (np.sin(self.w * t + self.phase) - math.sin(self.phase))
        )

    def speed(self, t):
        return self.v * (1.0 + self.a * np.cos(self.w * np.asarray(t, float) + self.phase))

    def deviation(self) -> float:
        """Largest distance (m) between the ego and a car driving at its mean speed from the same start."""
        return 2.0 * self.a * self.v / self.w


# ============================================================================================ the world
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
        ego_path_length: metres the ego drives in ``config.duration`` seconds.
    """

    def __init__(
        self,
        seed: int,
        config: WorldConfig,
        scene: _Scene,
        accepted: list[_Object],
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
        self._build_tables(accepted)

    def _build_tables(self, accepted: list[_Object]) -> None:
        """Static solids in the global frame; moving objects as tracks plus solids in their own frame."""
        statics = [i for i, o in enumerate(accepted) if o.track is None]
        movers = [i for i, o in enumerate(accepted) if o.track is not None]
        rows, poses, ids = _solid_rows(accepted, statics)
        self._static = _place_solids(rows, *poses, ids)
        rows, _, ids = _solid_rows(accepted, movers)
        self._mover_rows, self._mover_ids = rows, ids
        self._mover_owner = np.repeat(np.arange(len(movers)), [len(accepted[i].solids) for i in movers])
        self._tracks = _Tracks.of([accepted[i].track for i in movers])
        self._static_boxes = [
            (i, o.category, np.array(o.size), o.pose, float(_wrap(o.pose[2])), o.attribute)
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
        moving = _place_solids(self._mover_rows, x[owner, 0], y[owner, 0], yaw[owner, 0], self._mover_ids)
        return Primitives.concatenate([self._static, moving])

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
            boxes.append(BoxState(i, cat, centre, size.copy(), float(_wrap(yaw[row, 0])), velocity, attr))
        boxes.sort(key=lambda b: b.instance)
        return boxes

    def summary(self) -> dict[str, int]:
        """Object counts: annotated objects by nuScenes category, the rest by ``"<category>.<kind>"``."""
        return dict(sorted(self._kinds.items()))


def _wrap(angle):
    """Angles folded into ``[-pi, pi)``."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


# ============================================================================================ objects
# A solid in its object's frame (x along the object's heading, y to its left, z up, origin on the ground under
# the object's centre): kind, dx, dy, z centre, half sizes (3), albedo (3), texture, reflectivity. Solids share
# their object's yaw.
_Solid = tuple


def _solid(kind, dx, dy, z0, z1, hx, hy, color, texture=Texture.PLAIN, reflectivity=0.3) -> _Solid:
    """A solid spanning heights ``z0..z1`` (m) with horizontal half sizes ``hx, hy``, centred at ``(dx, dy)``."""
    return (kind, dx, dy, (z0 + z1) / 2, hx, hy, (z1 - z0) / 2, *color, texture, reflectivity)


@dataclass
class _Object:
    """A proposed object: what it is, its solids, and where it is (static pose or a track).

    Attributes:
        category: nuScenes category (``static.manmade``, ``static.vegetation`` for unannotated scenery).
        kind: finer name for the summary (``building``, ``tree``, ...).
        solids: its solids in its own frame.
        size: ``(w, l, h)`` of its box, or None for unannotated objects.
        attribute: nuScenes attribute ("" for none).
        pose: ``(x, y, yaw)`` of a static object.
        track: ``(path, l, s0, v, reverse)`` of a moving one: on path ``path`` (0 is the main road, ``1 + c`` is
            crossing ``c``) at offset ``l`` it is at lane arc length ``s0 + v t``; ``reverse`` turns it around.
        ground: flat classes a static object may stand on (checked under its footprint), or None for anywhere.
    """

    category: str
    kind: str
    solids: list[_Solid]
    size: tuple[float, float, float] | None = None
    attribute: str = ""
    pose: tuple[float, float, float] | None = None
    track: tuple[int, float, float, float, bool] | None = None
    ground: tuple[int, ...] | None = None


def _solid_rows(objects: list[_Object], indices: list[int]):
    """Solid table ``(S, 13)`` (a solid's 12 values, then its Occ3D class) of the listed objects, each solid's
    object pose as three ``(S,)`` arrays, and each solid's instance id (the object's index)."""
    counts = [len(objects[i].solids) for i in indices]
    rows = np.array([s for i in indices for s in objects[i].solids], float).reshape(-1, 12)
    semantic = np.repeat(np.array([occ3d_id(objects[i].category) for i in indices], float), counts)
    rows = np.concatenate([rows, semantic[:, None]], axis=1)
    pose = np.array([objects[i].pose or (0.0, 0.0, 0.0) for i in indices], float).reshape(-1, 3)
    pose = np.repeat(pose, counts, axis=0)
    ids = np.repeat(np.array(indices, np.int64), counts)
    return rows, (pose[:, 0], pose[:, 1], pose[:, 2]), ids


def _place_solids(rows: np.ndarray, x, y, yaw, instance) -> Primitives:
    """Solids ``rows`` of objects at poses ``x, y, yaw`` (one per row) as global :class:`Primitives`."""
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = rows[:, 1], rows[:, 2]
    center = np.stack([x + c * dx - s * dy, y + s * dx + c * dy, rows[:, 3]], axis=1)
    return Primitives(
        kind=rows[:, 0].astype(np.int8),
        center=center,
        half_size=rows[:, 4:7].copy(),
        yaw=np.asarray(_wrap(yaw), float),
        semantic=rows[:, 12].astype(np.uint8),
        instance=np.asarray(instance, np.int32),
        color=rows[:, 7:10].astype(np.float32),
        texture=rows[:, 10].astype(np.uint8),
        reflectivity=rows[:, 11].astype(np.float32),
    )


@dataclass(frozen=True)
class _Tracks:
    """Tracks of ``M`` moving objects as arrays ``(M,)``, fields as in :attr:`_Object.track`."""

    path: np.ndarray
    l: np.ndarray
    s0: np.ndarray
    v: np.ndarray
    reverse: np.ndarray

    @staticmethod
    def of(tracks: list[tuple[int, float, float, float, bool]]) -> _Tracks:
        table = np.array(tracks, float).reshape(-1, 5)
        return _Tracks(table[:, 0].astype(np.int64), table[:, 1], table[:, 2], table[:, 3], table[:, 4] > 0)

    def poses(self, paths: list[_Path], t: np.ndarray) -> tuple[np.ndarray, ...]:
        """``x, y, yaw, vx, vy``, each ``(M, T)``, at times ``t`` ``(T,)``."""
        s_lane = self.s0[:, None] + self.v[:, None] * t[None, :]
        x, y, h = (np.zeros(s_lane.shape) for _ in range(3))
        for p in np.unique(self.path):
            rows = self.path == p
            x[rows], y[rows], h[rows] = paths[p].at_lane(s_lane[rows], self.l[rows, None])
        vx, vy = self.v[:, None] * np.cos(h), self.v[:, None] * np.sin(h)
        return x, y, h + np.pi * self.reverse[:, None], vx, vy


# ============================================================================================ ground raster
@njit(cache=True)
def _frac(v):
    return v - math.floor(v)


@njit(cache=True)
def _lane_paint(a, s, median, edge, lanes):
    """Main-road paint at distance ``a`` from the centreline: edge lines, median or centre lines, dashed dividers."""
    if edge - 0.3 <= a < edge - 0.15:
        return True
    if median > 0.0:
        if median + 0.15 <= a < median + 0.3:
            return True
    elif 0.05 <= a < 0.2:  # double solid centre line
        return True
    divider = round((a - median) / LANE_WIDTH)  # nearest line between two lanes of one side: 3 m dash, 6 m gap
    return 1 <= divider < lanes and abs(a - median - LANE_WIDTH * divider) < 0.075 and _frac(s / 9.0) < 1.0 / 3.0


@njit(cache=True)
def _paint_main(sem, marks, s_map, l_map, profile, lanes, bays, driveways):
    """Flat classes and paint of the main road's corridor; ``bays``/``driveways`` rows are ``(side, s0, s1)``."""
    nx, ny = sem.shape
    median = profile[0]
    for i in range(nx):
        for j in range(ny):
            l = l_map[i, j]
            if math.isinf(l):
                continue
            side = 0 if l < 0.0 else 1
            a, s = abs(l), s_map[i, j]
            edge, kerb, outer = profile[1 + 3 * side], profile[2 + 3 * side], profile[3 + 3 * side]
            c = _TERRAIN
            if a < median:
                c = _OTHER_FLAT
            elif a < edge:
                c = _DRIVEABLE
            elif a < kerb:
                c = _OTHER_FLAT
            elif a < outer:
                c = _SIDEWALK
            for b in range(bays.shape[0]):
                if bays[b, 0] == side and bays[b, 1] <= s < bays[b, 2] and edge <= a < edge + _BAY_DEPTH:
                    c = _DRIVEABLE
            if kerb <= a < outer + _DRIVEWAY_DEPTH:
                for d in range(driveways.shape[0]):
                    if driveways[d, 0] == side and driveways[d, 1] <= s < driveways[d, 2]:
                        c = _OTHER_FLAT
            sem[i, j] = c
            marks[i, j] = c == _DRIVEABLE and median <= a < edge and _lane_paint(a, s, median, edge, lanes[side])


@njit(cache=True)
def _paint_crossing(sem, marks, l_map, window, ox, oy, res, geometry, profile):
    """Paint a crossing road over the raster ``window`` ``(i0, i1, j0, j1)``: its carriageway and sidewalks,
    zebra crossings and stop lines on both roads, its centre and edge lines. ``geometry`` is
    :meth:`_Crossing.geometry`, ``profile`` :meth:`_CrossSection.profile`."""
    px, py, ux, uy, tx, ty, minus, plus, hw, sw = geometry
    median = profile[0]
    for i in range(window[0], window[1]):
        x = ox + (i + 0.5) * res
        for j in range(window[2], window[3]):
            y = oy + (j + 0.5) * res
            dx, dy = x - px, y - py
            sc, lc = dx * ux + dy * uy, -dx * uy + dy * ux
            a = abs(lc)
            if sc < -minus or sc > plus or a >= hw + sw + 1.0:
                continue
            lm = l_map[i, j]
            side = 0 if lm < 0.0 else 1
            am = abs(lm)  # inf away from the main road
            edge, kerb, outer = profile[1 + 3 * side], profile[2 + 3 * side], profile[3 + 3 * side]
            on_main = am < edge
            if a < hw:
                sem[i, j] = _DRIVEABLE
                if on_main:
                    marks[i, j] = False  # no main-road lines inside the junction
                elif kerb <= am < outer:  # zebra continuing the main road's sidewalk
                    marks[i, j] = a < hw - 0.15 and _frac(lc + hw) < 0.5
                elif outer + 0.5 <= am < outer + 0.9:  # stop line of the lane heading to the junction
                    marks[i, j] = lc * sc < 0.0
                elif am >= outer + 1.0:
                    marks[i, j] = (a < 0.075 and _frac(sc / 6.0) < 0.5) or hw - 0.3 <= a < hw - 0.15
                else:
                    marks[i, j] = False
            elif a < hw + sw:
                if sem[i, j] != _DRIVEABLE:
                    sem[i, j] = _SIDEWALK
                    marks[i, j] = False
                elif on_main:  # zebra across the main road, continuing this road's sidewalks
                    marks[i, j] = hw + 0.3 <= a < hw + sw - 0.3 and _frac(lm) < 0.5
            elif on_main and am >= median and hw + sw + 0.4 <= a < hw + sw + 0.8:
                # stop lines of the main road, upstream of the zebra: right-hand lanes drive along the tangent
                upstream = dx * tx + dy * ty
                if (side == 0 and upstream < 0.0) or (side == 1 and upstream > 0.0):
                    marks[i, j] = True


def _paint_ground(scene_path: _Path, xsec: _CrossSection, crossings, plan: _Plan, bbox, res: float) -> GroundMap:
    """Rasterise the ground over ``bbox`` (xmin, ymin, xmax, ymax) at ``res`` metres per cell."""
    origin = np.floor(np.asarray(bbox[:2]) / res) * res
    nx, ny = (int(math.ceil((bbox[2 + d] - origin[d]) / res)) for d in range(2))
    half_width = max(xsec.outer(0), xsec.outer(1)) + _DRIVEWAY_DEPTH + 1.0
    s_map, l_map = _road_coordinates(*scene_path.pieces(), origin[0], origin[1], res, nx, ny, half_width)
    sem = np.full((nx, ny), _TERRAIN, np.uint8)
    marks = np.zeros((nx, ny), np.bool_)
    rows = lambda items: np.array(items, float).reshape(-1, 3)  # noqa: E731 - tiny local table builder
    profile = xsec.profile()
    _paint_main(sem, marks, s_map, l_map, profile, np.array(xsec.lanes), rows(plan.bays), rows(plan.driveways))
    for c in crossings:
        n = np.array([-c.u[1], c.u[0]])
        reach = c.half_width + c.sidewalk + 1.0
        corners = np.array([c.point + a * c.u + b * n for a in (-c.minus, c.plus) for b in (-reach, reach)])
        lo = np.clip(np.floor((corners.min(0) - origin) / res).astype(int), 0, [nx, ny])
        hi = np.clip(np.ceil((corners.max(0) - origin) / res).astype(int) + 1, 0, [nx, ny])
        window = np.array([lo[0], hi[0], lo[1], hi[1]])
        _paint_crossing(sem, marks, l_map, window, origin[0], origin[1], res, c.geometry(), profile)
    marks &= sem == _DRIVEABLE
    return GroundMap(semantics=sem, markings=marks, origin=origin, resolution=res)


# ============================================================================================ scene layout
def _main_path(rng: np.random.Generator, length: float) -> _Path:
    """Alternating straights and arcs (radius 40..200 m) of at least ``length`` metres, straight at both ends.

    The heading stays within 0.6 rad of the initial one, so the road never comes back toward itself and the
    perpendicular-ish crossings never meet it twice.
    """
    pieces = [(0.0, float(rng.uniform(40, 90)))]
    heading, total = 0.0, pieces[0][1]
    while total < length:
        if pieces[-1][0] != 0.0 or rng.random() < 0.4:
            piece = (0.0, float(rng.uniform(30, 120)))
        else:
            radius, turn = float(rng.uniform(40, 200)), float(rng.uniform(0.15, 0.6))
            sign = 1.0 if rng.random() < 0.5 else -1.0
            if abs(heading + sign * turn) > 0.6:
                sign = -sign
            heading += sign * turn
            piece = (sign / radius, radius * turn)
        pieces.append(piece)
        total += piece[1]
    pieces.append((0.0, 100.0))
    return _Path(0.0, 0.0, float(rng.uniform(-np.pi, np.pi)), pieces)


def _cross_section(rng: np.random.Generator) -> _CrossSection:
    lanes = int(rng.integers(2, 5))
    multi = 0.6 if lanes >= 3 else 0.25
    median = float(rng.uniform(0.5, 1.5)) if rng.random() < multi else 0.0
    parking = tuple(float(rng.uniform(2.3, 2.8)) if rng.random() < 0.5 else 0.0 for _ in range(2))
    sidewalk = tuple(float(rng.uniform(2.0, 4.0)) for _ in range(2))
    return _CrossSection(median, ((lanes + 1) // 2, lanes // 2), parking, sidewalk)  # type: ignore[arg-type]


def _ego_motion(rng: np.random.Generator, config: WorldConfig, l: float) -> _EgoMotion:
    lo, hi = config.ego_speed
    a = min(0.05, (hi - lo) / (hi + lo))  # speed wobble, kept inside the configured range
    v = float(rng.uniform(lo / (1 - a), hi / (1 + a)))
    return _EgoMotion(l, 0.0, v, a, 2 * np.pi / float(rng.uniform(8, 16)), float(rng.uniform(0, 2 * np.pi)))


def _crossings(rng, path: _Path, xsec: _CrossSection, view: tuple[float, float], arm: float) -> list[_Crossing]:
    """Crossings every 60..150 m of main arc length over ``view``, arms ``arm`` metres long.

    An arm that would run into an earlier crossing's road stops short of it; a crossing whose arm would then be
    too short to reach beyond the main road's sidewalks is left out.
    """
    crossings: list[_Crossing] = []
    pad = 14.0
    s = view[0] + float(rng.uniform(10, 70))
    while s < view[1]:
        x, y, h = path.point(s, 0.0)
        angle = h + np.pi / 2 + float(rng.uniform(-0.26, 0.26))
        u = np.array([math.cos(angle), math.sin(angle)])
        arms = {-1: arm, 1: arm}
        for c in crossings:
            # point + a u = c.point + b c.u
            matrix = np.array([u, -c.u]).T
            if abs(np.linalg.det(matrix)) < 1e-6:
                continue
            a, b = np.linalg.solve(matrix, c.point - np.array([x, y]))
            if -c.minus - pad <= b <= c.plus + pad and abs(a) <= arms[int(np.sign(a)) or 1] + pad:
                arms[int(np.sign(a)) or 1] = abs(a) - pad
        shortest = min(arms[-1] - xsec.outer(0), arms[1] - xsec.outer(1))
        if shortest > 25.0:
            tangent = np.array([math.cos(h), math.sin(h)])
            sidewalk = float(rng.uniform(2.0, 4.0))
            crossings.append(_Crossing(s, np.array([x, y]), u, tangent, arms[-1], arms[1], sidewalk))
        s += float(rng.uniform(60, 150))
    return crossings


def _first_free(blocked: list[tuple[float, float]], s: float, length: float, limit: float) -> float | None:
    """Smallest start ``>= s`` (moved at most ``limit``) of an interval of ``length`` clear of ``blocked``."""
    start = s
    for _ in range(len(blocked) + 1):
        hit = [b for a, b in blocked if a < start + length and start < b]
        if not hit:
            return start if start - s <= limit else None
        start = max(hit)
    return None


def _plan(rng, xsec: _CrossSection, ego_lane: int, crossings, view, ego_s: float, density: float) -> _Plan:
    """Lay out road works (every 50..75 m), bus stops (every 65..100 m) and driveways along the main road.

    Road works and bus stops start near the ego so that they are in view; a bus stands in a bay where there is a
    parking strip, otherwise in the outermost lane, which must then not be the ego's.
    """
    plan = _Plan()
    blocked: dict[int, list[tuple[float, float]]] = {0: [], 1: []}
    for c in crossings:
        skew = abs(float(np.dot(c.u, c.tangent)))
        half = (c.half_width + c.sidewalk + 1.5) / math.sqrt(max(1.0 - skew**2, 0.5)) + 6.0
        for side in (0, 1):
            blocked[side].append((c.s_main - half, c.s_main + half))
    s = ego_s + float(rng.uniform(-35, 0))
    while s < view[1] - 20:
        length, first = float(rng.uniform(14, 24)), int(rng.integers(2))
        for side in (first, 1 - first):
            # cones taper in over 14 m upstream: below the zone on the right, above it on the left
            before, after = (14.0, 3.0) if side == 0 else (3.0, 14.0)
            start = _first_free(blocked[side], s - before, before + length + after, 30)
            if start is not None:
                break
        if start is None:
            s += 15
            continue
        closes = xsec.lanes[side] >= 2 and not (side == 0 and ego_lane == xsec.lanes[0] - 1) and rng.random() < 0.4
        plan.works.append((side, start + before, start + before + length, bool(closes)))
        blocked[side].append((start, start + before + length + after))
        s = start + before + float(rng.uniform(50, 75))
    s = ego_s + float(rng.uniform(-30, 10))
    while s < view[1] - 20:
        sides = [side for side in (0, 1) if xsec.parking[side] > 0 or side == 1 or ego_lane != xsec.lanes[0] - 1]
        if len(sides) == 2 and rng.random() < 0.5:
            sides.reverse()
        for side in sides:
            start = _first_free(blocked[side], s - 12, 24, 30)
            if start is not None:
                break
        if start is None:
            s += 15
            continue
        in_bay = xsec.parking[side] > 0
        plan.bus_stops.append((side, start + 12, in_bay))
        if in_bay:
            plan.bays.append((side, start + 2, start + 22))
        blocked[side].append((start, start + 24))
        s = start + 12 + float(rng.uniform(65, 100))
    for side in (0, 1):
        s = view[0] + float(rng.uniform(0, 30))
        while s < view[1]:
            width = float(rng.uniform(3, 5))
            if _first_free(blocked[side], s, width, 0) is not None:
                plan.driveways.append((side, s, s + width))
                blocked[side].append((s - 1, s + width + 1))
            s += float(rng.uniform(25, 60)) / math.sqrt(density)
    return plan


# ============================================================================================ object builders
def _draw_size(rng, category: str, max_width: float = 3.1) -> tuple[float, float, float]:
    """A box size around the category's nuScenes mean (about 10 % spread, clipped to +-15 %)."""
    scale = np.clip(1.0 + 0.1 * rng.standard_normal(3), 0.85, 1.15)
    w, l, h = (float(m * f) for m, f in zip(CATEGORY_SIZES[category], scale, strict=True))
    return min(w, max_width), l, h


def _jitter(rng, color, amount: float = 0.04) -> tuple[float, float, float]:
    return tuple(float(c) for c in np.clip(np.asarray(color) + rng.uniform(-amount, amount, 3), 0.0, 1.0))


def _vehicle_color(rng) -> tuple[float, float, float]:
    """One palette for every vehicle class, so colour never tells the class."""
    index = rng.choice(len(_VEHICLE_COLORS), p=_VEHICLE_COLOR_WEIGHTS / _VEHICLE_COLOR_WEIGHTS.sum())
    return _jitter(rng, _VEHICLE_COLORS[index], 0.03)


def _vehicle_solids(category: str, w: float, l: float, h: float, color) -> list[_Solid]:
    """Solids of a vehicle filling its box: body and cabin boxes (one tall box plus a cab for buses and trucks)."""
    paint = dict(texture=Texture.VEHICLE, reflectivity=0.5)
    if category == "vehicle.car":
        return [
            _solid(BOX, 0.0, 0.0, 0.0, 0.55 * h, l / 2, w / 2, color, **paint),
            _solid(BOX, -0.05 * l, 0.0, 0.55 * h, h, 0.27 * l, 0.45 * w, color, **paint),
        ]
    if category == "vehicle.truck":
        return [
            _solid(BOX, -0.14 * l, 0.0, 0.0, h, 0.36 * l, w / 2, color, **paint),
            _solid(BOX, 0.375 * l, 0.0, 0.0, 0.82 * h, 0.125 * l, 0.48 * w, color, **paint),
        ]
    if category == "vehicle.bus.rigid":
        return [
            _solid(BOX, 0.0, 0.0, 0.0, 0.93 * h, l / 2, w / 2, color, **paint),
            _solid(BOX, -0.1 * l, 0.0, 0.93 * h, h, 0.2 * l, 0.35 * w, color, **paint),
        ]
    if category == "vehicle.trailer":
        return [
            _solid(BOX, 0.0, 0.0, 0.9, h, l / 2, w / 2, color, **paint),
            _solid(BOX, -0.3 * l, 0.0, 0.0, 0.9, 0.18 * l, 0.45 * w, (0.08, 0.08, 0.08), reflectivity=0.3),
        ]
    if category == "vehicle.construction":
        return [
            _solid(BOX, -0.2 * l, 0.0, 0.0, 0.5 * h, 0.3 * l, w / 2, color, **paint),
            _solid(BOX, -0.25 * l, 0.0, 0.5 * h, h, 0.17 * l, 0.33 * w, color, **paint),
            _solid(BOX, 0.25 * l, 0.0, 0.35 * h, 0.8 * h, 0.18 * l, 0.12 * w, color, **paint),
            _solid(BOX, 0.4 * l, 0.0, 0.0, 0.35 * h, 0.1 * l, 0.45 * w, (0.3, 0.3, 0.3), reflectivity=0.5),
        ]
    raise KeyError(category)


def _vehicle(rng, category: str, attribute: str) -> _Object:
    w, l, h = _draw_size(rng, category)
    solids = _vehicle_solids(category, w, l, h, _vehicle_color(rng))
    return _Object(category, "vehicle", solids, (w, l, h), attribute)


def _rider(rng, dx: float, z0: float, top: float, radius: float) -> list[_Solid]:
    """Torso cylinder and head of a person from height ``z0`` to ``top`` (m), ``dx`` along the object."""
    clothes = _jitter(rng, _CLOTHES[rng.integers(len(_CLOTHES))])
    skin = _jitter(rng, _SKIN[rng.integers(len(_SKIN))], 0.03)
    return [
        _solid(CYLINDER, dx, 0.0, z0, top - 0.24, radius, radius, clothes, reflectivity=0.25),
        _solid(ELLIPSOID, dx, 0.0, top - 0.24, top, 0.1, 0.09, skin, reflectivity=0.25),
    ]


def _cycle(rng, category: str, ridden: bool) -> _Object:
    """A bicycle or motorcycle; a rider (part of the same object, as in nuScenes' labels) when ``ridden``."""
    w, l, h = _draw_size(rng, category)
    motor = category == "vehicle.motorcycle"
    if not ridden:
        h *= 0.75
    frame = 0.62 * h if ridden else 0.9 * h
    color = _vehicle_color(rng) if motor else _jitter(rng, _CLOTHES[rng.integers(len(_CLOTHES))])
    body = 0.45 * w if motor else 0.2 * w
    solids = [
        _solid(BOX, 0.0, 0.0, 0.0, frame, l / 2, body, color, texture=Texture.PLAIN, reflectivity=0.5),
        _solid(BOX, 0.36 * l, 0.0, frame - 0.08, frame, 0.04, w / 2, (0.1, 0.1, 0.1), reflectivity=0.5),
    ]
    if ridden:
        solids += _rider(rng, -0.1 * l, frame, h, min(0.2, 0.4 * w))
    attribute = "cycle.with_rider" if ridden else "cycle.without_rider"
    return _Object(category, "cycle", solids, (w, l, h), attribute)


def _pedestrian(rng, moving: bool, category: str = "human.pedestrian.adult") -> _Object:
    w, l, h = _draw_size(rng, category)
    radius = float(rng.uniform(0.2, 0.28))
    solids = _rider(rng, 0.0, 0.0, h, radius)
    if category == "human.pedestrian.construction_worker":
        solids[0] = solids[0][:7] + (*_HI_VIS, Texture.PLAIN, 0.9)  # retro-reflective vest
    attribute = "pedestrian.moving" if moving else "pedestrian.standing"
    return _Object(category, "pedestrian", solids, (w, l, h), attribute)


def _barrier(rng) -> _Object:
    """A barrier; its 2.5 m width lies across its heading (nuScenes' convention), so yaw it across the road."""
    w, l, h = _draw_size(rng, "movable_object.barrier")
    color = ((0.8, 0.1, 0.08), (0.95, 0.45, 0.05), (0.9, 0.9, 0.88))[int(rng.integers(3))]
    solid = _solid(BOX, 0.0, 0.0, 0.0, h, l / 2, w / 2, color, texture=Texture.STRIPES, reflectivity=0.9)
    return _Object("movable_object.barrier", "barrier", [solid], (w, l, h))


def _cone(rng) -> _Object:
    h = float(rng.uniform(0.7, 1.0))
    solid = _solid(CYLINDER, 0.0, 0.0, 0.0, h, 0.2, 0.2, (0.95, 0.4, 0.05), texture=Texture.STRIPES, reflectivity=0.9)
    return _Object("movable_object.trafficcone", "cone", [solid], (0.41, 0.41, h))


def _debris(rng) -> _Object:
    l = float(rng.uniform(0.3, 1.2))
    w, h = float(rng.uniform(0.3, l)), float(rng.uniform(0.2, 0.8))
    color = _jitter(rng, ((0.45, 0.4, 0.35), (0.3, 0.28, 0.25), (0.6, 0.55, 0.45))[int(rng.integers(3))])
    return _Object("movable_object.debris", "debris", [_solid(BOX, 0.0, 0.0, 0.0, h, l / 2, w / 2, color)], (w, l, h))


def _building(rng, style: _Style, width: float, depth: float) -> _Object:
    """A facade box ``width`` along its heading and ``depth`` across, sometimes with a plant room on the roof."""
    material = list(_MATERIALS)[rng.choice(4, p=np.array(style.materials) / sum(style.materials))]
    color, reflectivity = _MATERIALS[material]
    color = _jitter(rng, color, 0.06)
    height = float(rng.uniform(*style.height))
    solids = [_solid(BOX, 0.0, 0.0, 0.0, height, width / 2, depth / 2, color, Texture.FACADE, reflectivity)]
    if rng.random() < 0.3:
        top = height + float(rng.uniform(2, 4))
        solids.append(_solid(BOX, 0.0, 0.0, height, top, width / 6, depth / 6, _jitter(rng, (0.6, 0.6, 0.58))))
    return _Object("static.manmade", "building", solids, ground=(_TERRAIN,))


def _wall(rng, length: float) -> _Object:
    fence = rng.random() < 0.5
    thickness, height = (0.1, float(rng.uniform(1.2, 2.0))) if fence else (0.3, float(rng.uniform(1.0, 2.5)))
    color = _jitter(rng, (0.35, 0.36, 0.35) if fence else (0.68, 0.66, 0.6), 0.05)
    solid = _solid(BOX, 0.0, 0.0, 0.0, height, length / 2, thickness / 2, color)
    return _Object("static.manmade", "fence" if fence else "wall", [solid], ground=(_TERRAIN, _SIDEWALK))


_FURNITURE_GROUND = (_SIDEWALK, _TERRAIN, _OTHER_FLAT)


def _pole(rng, kind: str, toward_road: float) -> _Object:
    """A pole; a sign plate, lamp arm or signal head on top. ``toward_road`` (+-1) is the local y of the road."""
    metal = (0.45, 0.46, 0.48)
    if kind == "street_light":
        r, h, arm = float(rng.uniform(0.12, 0.18)), float(rng.uniform(6, 9)), float(rng.uniform(1.5, 2.5))
        top = _solid(BOX, 0.0, toward_road * arm / 2, h - 0.2, h, 0.12, arm / 2, metal, reflectivity=0.5)
    elif kind == "sign":
        r, h = 0.1, float(rng.uniform(2.2, 2.8))
        color = ((0.8, 0.1, 0.1), (0.1, 0.25, 0.7), (0.95, 0.95, 0.95), (0.95, 0.8, 0.1))[int(rng.integers(4))]
        top = _solid(BOX, 0.0, 0.0, h, h + 0.7, 0.03, 0.35, color, reflectivity=0.9)
        h += 0.05
    elif kind == "traffic_light":
        r, h = 0.12, float(rng.uniform(3.0, 3.6))
        top = _solid(BOX, 0.0, 0.0, h, h + 1.0, 0.18, 0.18, (0.08, 0.08, 0.08), reflectivity=0.5)
    else:
        r, h = float(rng.uniform(0.1, 0.2)), float(rng.uniform(3, 8))
        pole = _solid(CYLINDER, 0.0, 0.0, 0.0, h, r, r, metal, reflectivity=0.5)
        return _Object("static.manmade", "pole", [pole], ground=_FURNITURE_GROUND)
    pole = _solid(CYLINDER, 0.0, 0.0, 0.0, h, r, r, metal, reflectivity=0.5)
    return _Object("static.manmade", kind, [pole, top], ground=_FURNITURE_GROUND)


def _tree(rng, street: bool) -> _Object:
    """A trunk and an ellipsoid crown; street trees carry their crowns above the tallest vehicle."""
    radius = float(rng.uniform(1.2, 3.0 if street else 3.5))
    vertical = float(rng.uniform(1.2, 3.0))
    bottom = float(rng.uniform(_TALL_VEHICLE + 0.1, 5.5)) if street else float(rng.uniform(1.5, 3.5))
    trunk_r = float(rng.uniform(0.12, 0.25))
    bark = _jitter(rng, (0.3, 0.22, 0.15), 0.03)
    leaves = _jitter(rng, (0.2, 0.4, 0.14), 0.07)
    solids = [
        _solid(CYLINDER, 0.0, 0.0, 0.0, bottom + vertical, trunk_r, trunk_r, bark, Texture.BARK, 0.15),
        _solid(ELLIPSOID, 0.0, 0.0, bottom, bottom + 2 * vertical, radius, radius, leaves, Texture.FOLIAGE, 0.15),
    ]
    return _Object("static.vegetation", "tree", solids, ground=(_SIDEWALK, _TERRAIN))


def _hedge(rng) -> _Object:
    length, width, height = float(rng.uniform(2, 8)), float(rng.uniform(0.8, 1.5)), float(rng.uniform(0.8, 1.8))
    kind = ELLIPSOID if rng.random() < 0.5 else BOX
    leaves = _jitter(rng, (0.18, 0.36, 0.12), 0.05)
    solid = _solid(kind, 0.0, 0.0, 0.0, height, length / 2, width / 2, leaves, Texture.FOLIAGE, 0.15)
    return _Object("static.vegetation", "hedge", [solid], ground=(_TERRAIN,))


def _bus_shelter(rng) -> _Object:
    frame = _jitter(rng, (0.5, 0.52, 0.55))
    solids = [
        _solid(BOX, 0.0, -0.6, 0.0, 2.5, 2.0, 0.05, (0.3, 0.38, 0.45), reflectivity=0.2),  # glass back wall
        _solid(BOX, 0.0, 0.0, 2.5, 2.65, 2.1, 0.7, frame, reflectivity=0.5),  # roof
    ]
    return _Object("static.manmade", "bus_shelter", solids, ground=(_SIDEWALK, _TERRAIN))


def _bicycle_rack(rng, length: float) -> _Object:
    solid = _solid(BOX, 0.0, 0.0, 0.0, 0.8, length / 2, 0.05, (0.55, 0.56, 0.58), reflectivity=0.5)
    return _Object("static_object.bicycle_rack", "rack", [solid], (0.1, length, 0.8), ground=(_SIDEWALK, _TERRAIN))


# ============================================================================================ placement
_TRAFFIC = {"car": 0.67, "truck": 0.12, "bus": 0.06, "truck_trailer": 0.07, "construction": 0.03, "motorcycle": 0.05}
_LEAD = {"car": 0.4, "truck_trailer": 0.3, "bus": 0.15, "truck": 0.15}
_FOLLOW = {"car": 0.5, "bus": 0.3, "truck": 0.2}
_UNITS = {
    "car": ("vehicle.car",),
    "truck": ("vehicle.truck",),
    "bus": ("vehicle.bus.rigid",),
    "truck_trailer": ("vehicle.truck", "vehicle.trailer"),
    "construction": ("vehicle.construction",),
    "motorcycle": ("vehicle.motorcycle",),
}
_HITCH = 0.8  # gap (m) between a truck and its trailer


def _unit_length(unit: list[_Object]) -> float:
    """Bumper-to-bumper length (m) of a traffic unit."""
    return sum(o.size[1] for o in unit) + _HITCH * (len(unit) - 1)


class _Placer:
    """Proposes the scene's objects, group by group, in priority order (earlier groups win conflicts)."""

    def __init__(self, scene: _Scene) -> None:
        self.scene, self.rng, self.groups = scene, scene.rng, []
        self.paths = [scene.path] + [c.path for c in scene.crossings]
        self.density = scene.config.density
        ego = scene.ego
        self.ego_centre = tuple(float(scene.path.lane_to_centre(ego.s(t), ego.l)) for t in (0.0, scene.config.duration))

    def add(self, *objects: _Object) -> None:
        """Propose ``objects`` as one group: kept or dropped together."""
        self.groups.append(list(objects))

    def uniform(self, lo: float, hi: float) -> float:
        """A float drawn uniformly from ``[lo, hi)``."""
        return float(self.rng.uniform(lo, hi))

    def choice(self, weights: dict[str, float]) -> str:
        """A key of ``weights`` drawn with probability proportional to its value."""
        names = list(weights)
        p = np.array([weights[n] for n in names])
        return names[int(self.rng.choice(len(names), p=p / p.sum()))]

    # ------------------------------------------------------------------------------------------ poses
    def on_main(self, obj: _Object, s: float, l: float, turn: float = 0.0) -> _Object:
        """Stand ``obj`` at main arc length ``s``, offset ``l``, yawed ``turn`` from the road's heading."""
        x, y, h = self.scene.path.point(s, l)
        obj.pose = (x, y, h + turn)
        return obj

    def on_crossing(self, obj: _Object, c: _Crossing, sc: float, lc: float, turn: float = 0.0) -> _Object:
        """Stand ``obj`` at arc length ``sc``, offset ``lc`` of crossing ``c``, yawed ``turn`` from its heading."""
        x, y = c.xy(np.array(sc), np.array(lc))
        obj.pose = (float(x), float(y), math.atan2(c.u[1], c.u[0]) + turn)
        return obj

    def on_lane(self, obj: _Object, path: int, l: float, s_lane: float, speed: float, direction: int) -> _Object:
        """Put ``obj`` at lane arc length ``s_lane`` of path ``path`` at offset ``l``, heading ``direction`` (+-1)
        along it at ``speed`` m/s; a standing object gets a static pose."""
        if speed > 0.0:
            obj.track = (path, l, s_lane, direction * speed, direction < 0)
        else:
            x, y, h = self.paths[path].at_lane(np.array(s_lane), np.array(l))
            obj.pose = (float(x), float(y), float(h) + (np.pi if direction < 0 else 0.0))
        return obj

    def unit(self, kind: str, attribute: str) -> list[_Object]:
        """The vehicles of one traffic unit (``_UNITS``), front first; motorcycles come with their riders."""
        return [
            _cycle(self.rng, c, True) if c == "vehicle.motorcycle" else _vehicle(self.rng, c, attribute)
            for c in _UNITS[kind]
        ]

    def drive(self, unit: list[_Object], path: int, l: float, head: float, direction: int, speed: float):
        """Put a unit in a lane, its front end at lane arc length ``head``, its trailer behind it; returns it."""
        offset = 0.0
        for obj in unit:
            self.on_lane(obj, path, l, head - direction * (offset + obj.size[1] / 2), speed, direction)
            offset += obj.size[1] + _HITCH
        return unit

    def stream(self, path: int, l: float, direction: int, speed: float, lo: float, hi: float, limit: int = -1):
        """Up to ``limit`` (-1: any number of) units at one speed along a lane, at random gaps, spanning at most
        ``[lo, hi]`` of lane arc length at ``t = 0``."""
        attribute = "vehicle.moving" if speed > 0 else "vehicle.stopped"
        cursor = lo + self.uniform(0, 10) / self.density
        while limit != 0:
            unit = self.unit(self.choice(_TRAFFIC), attribute)
            length = _unit_length(unit)
            if cursor + length > hi:
                break
            head = cursor + length if direction > 0 else cursor
            self.add(*self.drive(unit, path, l + self.uniform(-0.15, 0.15), head, direction, speed))
            cursor += length + self.uniform(5, 35) / self.density
            limit -= 1

    def main_lane(self, s_centre, l):
        """Lane arc length at offset ``l`` of main arc length ``s_centre``."""
        return float(self.scene.path.centre_to_lane(s_centre, l))

    def view_lane(self, l: float, extra: float = 10.0) -> tuple[float, float]:
        """The scene's visible main arc-length range, widened by ``extra``, in lane arc length at offset ``l``."""
        lo, hi = self.scene.view
        return self.main_lane(lo - extra, l), self.main_lane(hi + extra, l)

    # ------------------------------------------------------------------------------------------ features
    def companions(self) -> None:
        """A lead vehicle and a follower in the ego's lane at the ego's mean speed: always in view."""
        ego = self.scene.ego
        reserve = _EGO_RESERVE[1] + ego.deviation() + 2 * _CHECK_MARGIN
        if self.rng.random() < 0.85:
            unit = self.unit(self.choice(_LEAD), "vehicle.moving")
            head = ego.s0 + _EGO_RESERVE[0] + reserve + self.uniform(4, 16) + _unit_length(unit)
            self.add(*self.drive(unit, 0, ego.l, head, 1, ego.v))
        if self.rng.random() < 0.75:
            unit = self.unit(self.choice(_FOLLOW), "vehicle.moving")
            head = ego.s0 + _EGO_RESERVE[0] - reserve - self.uniform(4, 14)
            self.add(*self.drive(unit, 0, ego.l, head, 1, ego.v))

    def works(self, side: int, s0: float, s1: float, closes_lane: bool) -> None:
        """Road works: a construction vehicle (often a trailer, sometimes a truck) fenced by barriers, cones
        tapering in from upstream, workers and debris. The zone takes the parking strip, sidewalk and terrain,
        and on multi-lane sides sometimes the outermost lane."""
        xsec, sign, rng = self.scene.xsec, _SIGN[side], self.rng
        edge, kerb, outer = xsec.edge(side), xsec.kerb(side), xsec.outer(side)
        inner = edge - LANE_WIDTH + 0.4 if closes_lane else (edge + 0.3 if xsec.parking[side] > 0 else kerb + 0.2)
        far = outer + self.uniform(8, 12)
        mid = (s0 + s1) / 2
        turn = self.uniform(-0.3, 0.3)
        machine = _vehicle(rng, "vehicle.construction", "vehicle.parked")
        w, l, _ = machine.size
        reach = l / 2 * abs(math.sin(turn)) + w / 2 * math.cos(turn)  # half extent across the road
        turn += np.pi if rng.random() < 0.5 else 0.0
        self.add(self.on_main(machine, mid + self.uniform(-2, 2), sign * (inner + 0.5 + reach), turn))
        if rng.random() < 0.85:
            trailer = _vehicle(rng, "vehicle.trailer", "vehicle.parked")
            self.add(self.on_main(trailer, mid, sign * (far - 0.4 - trailer.size[0] / 2)))
        if rng.random() < 0.5:  # a truck parked behind the sidewalk just past the zone
            truck = _vehicle(rng, "vehicle.truck", "vehicle.parked")
            past = s1 + 1.0 + truck.size[1] / 2 if side == 0 else s0 - 1.0 - truck.size[1] / 2
            self.add(self.on_main(truck, past, sign * (outer + 1.0 + truck.size[0] / 2), turn))
        for k in range(int((s1 - s0) / 2.6)):
            self.add(self.on_main(_barrier(rng), s0 + 1.3 + 2.6 * k, sign * (inner + 0.3), np.pi / 2))
        for s_end in (s0, s1):
            lateral = inner + 1.6
            while lateral + 1.3 < far:
                self.add(self.on_main(_barrier(rng), s_end, sign * lateral))
                lateral += 2.6
        upstream, start = (-1.0, s0) if side == 0 else (1.0, s1)
        target = edge - 0.3 if closes_lane else inner + 0.1
        count = int(rng.integers(4, 8))
        for q in range(1, count + 1):
            lateral = inner + 0.1 + (target - inner - 0.1) * q / count
            self.add(self.on_main(_cone(rng), start + upstream * 2.0 * q, sign * lateral))
        for _ in range(int(rng.integers(2, 5))):
            self.add(self.on_main(_cone(rng), self.uniform(s0 + 1, s1 - 1), sign * self.uniform(inner + 1, far - 1)))
        for _ in range(int(rng.integers(1, 4))):
            worker = _pedestrian(rng, False, "human.pedestrian.construction_worker")
            s, lat = self.uniform(s0 + 1, s1 - 1), self.uniform(inner + 1, far - 1)
            self.add(self.on_main(worker, s, sign * lat, self.uniform(-np.pi, np.pi)))
        for _ in range(int(rng.integers(1, 4))):
            s, lat = self.uniform(s0 + 1, s1 - 1), self.uniform(inner + 1, far - 1)
            self.add(self.on_main(_debris(rng), s, sign * lat, self.uniform(-np.pi, np.pi)))

    def bus_stop(self, side: int, s: float, in_bay: bool) -> None:
        """A shelter behind the sidewalk, people waiting, and usually a bus at the kerb (in its bay if any)."""
        xsec, sign, rng = self.scene.xsec, _SIGN[side], self.rng
        turn = 0.0 if side == 0 else np.pi
        if rng.random() < 0.9:
            bus = _vehicle(rng, "vehicle.bus.rigid", "vehicle.stopped")
            w = bus.size[0]
            lateral = xsec.edge(side) + _BAY_DEPTH - 0.25 - w / 2 if in_bay else xsec.edge(side) - 0.35 - w / 2
            self.add(self.on_main(bus, s, sign * lateral, turn))
        self.add(self.on_main(_bus_shelter(rng), s, sign * (xsec.outer(side) + 0.9), turn))
        for _ in range(int(rng.integers(1, 5))):
            person = _pedestrian(rng, False)
            lateral = xsec.outer(side) - self.uniform(0.4, 1.2)
            self.add(self.on_main(person, s + self.uniform(-4, 4), sign * lateral, self.uniform(-np.pi, np.pi)))

    def junctions(self) -> None:
        """Traffic lights on the corners of each junction; barriers closing crossing roads that end."""
        xsec, rng, lo, hi = self.scene.xsec, self.rng, self.scene.bbox[:2], self.scene.bbox[2:]
        for c in self.scene.crossings:
            skew = math.sqrt(max(1.0 - float(np.dot(c.u, c.tangent)) ** 2, 0.5))
            for side in (0, 1):
                sc = _SIGN[side] * (xsec.kerb(side) + 0.4) / skew
                for lc in (-1.0, 1.0):
                    light = _pole(rng, "traffic_light", 0.0)
                    self.add(self.on_crossing(light, c, sc, lc * (c.half_width + c.sidewalk + 0.6)))
            for end in (-c.minus + 0.6, c.plus - 0.6):
                point = c.xy(np.array(end), np.array(0.0))
                if np.all((point > lo) & (point < hi)):
                    for lc in (-2.6, 0.0, 2.6):
                        self.add(self.on_crossing(_barrier(rng), c, end, lc))

    def buildings(self) -> None:
        """Rows of buildings set back behind the sidewalks of the main road and of the crossing arms."""
        scene, rng = self.scene, self.rng
        for side in (0, 1):
            s = scene.view[0] - 10 + self.uniform(0, 10)
            while s < scene.view[1] + 10:
                width, depth = self.uniform(8, 30), self.uniform(8, 20)
                lateral = scene.xsec.outer(side) + self.uniform(2, 10) + depth / 2
                self.add(self.on_main(_building(rng, scene.style, width, depth), s + width / 2, _SIGN[side] * lateral))
                s += width + self.uniform(1, 10)
        for c in scene.crossings:
            for arm, side, length in ((-1.0, 0, c.minus), (1.0, 1, c.plus)):
                for lc_sign in (-1.0, 1.0):
                    s = scene.xsec.outer(side) + self.uniform(6, 12)
                    while s < length:
                        width, depth = self.uniform(8, 30), self.uniform(8, 20)
                        lc = lc_sign * (c.half_width + c.sidewalk + self.uniform(2, 10) + depth / 2)
                        self.add(
                            self.on_crossing(_building(rng, scene.style, width, depth), c, arm * (s + width / 2), lc)
                        )
                        s += width + self.uniform(1, 10)

    def furniture(self) -> None:
        """Street trees, lights, signs and poles at the kerb; hedges, trees, walls, bicycle racks, parked
        motorcycles and debris beyond the sidewalks; barriers on a stretch of median; the same on crossing arms."""
        scene, rng, xsec = self.scene, self.rng, self.scene.xsec
        lo, hi = scene.view
        green, dens = scene.style.trees, self.density
        for side in (0, 1):
            sign, kerb, outer = _SIGN[side], xsec.kerb(side), xsec.outer(side)
            turn = 0.0 if side == 0 else np.pi
            road = 1.0 if side == 0 else -1.0  # local y of the road seen from a pole, in the road's frame
            for s in self.steps(lo, hi, 8, 18, green * dens):
                if rng.random() < 0.6:
                    self.add(self.on_main(_tree(rng, True), s, sign * (kerb + 0.55)))
            for s in self.steps(lo, hi, 25, 40, 1.0):
                self.add(self.on_main(_pole(rng, "street_light", road), s, sign * (kerb + 0.35)))
            for s in self.steps(lo, hi, 15, 45, 1.0):
                kind = "sign" if rng.random() < 0.6 else "pole"
                self.add(self.on_main(_pole(rng, kind, road), s, sign * (kerb + 0.3)))
            for s in self.steps(lo, hi, 6, 16, green * dens):
                lateral = outer + self.uniform(1.0, 4.5)
                item = _tree(rng, False) if rng.random() < 0.5 else _hedge(rng)
                self.add(self.on_main(item, s, sign * lateral))
            for s in self.steps(lo, hi, 15, 40, 1.0):
                if rng.random() < 0.4:
                    self.add(self.on_main(_wall(rng, self.uniform(5, 15)), s, sign * (outer + self.uniform(0.3, 1.0))))
            for s in self.steps(lo, hi, 12, 35, dens):
                lateral = kerb + self.uniform(0.2, 0.6) if rng.random() < 0.5 else outer + self.uniform(0.3, 3.0)
                self.add(self.on_main(_debris(rng), s, sign * lateral, self.uniform(-np.pi, np.pi)))
            for s in self.steps(lo, hi, 35, 70, 1.0):
                self.bicycle_rack(side, s, turn)
            for s in self.steps(lo, hi, 40, 80, 1.0):
                self.motorcycle_row(side, s)
        if xsec.median > 0 and rng.random() < 0.5:
            start = self.ego_centre[0] + self.uniform(-20, 60)
            for k in range(int(self.uniform(15, 40) / 2.6)):
                self.add(self.on_main(_barrier(rng), start + 2.6 * k, 0.0, np.pi / 2))
        for c in scene.crossings:
            for arm, side, length in ((-1.0, 0, c.minus), (1.0, 1, c.plus)):
                for lc_sign in (-1.0, 1.0):
                    for s in self.steps(xsec.outer(side) + 4, length, 10, 25, green * dens):
                        self.add(self.on_crossing(_tree(rng, True), c, arm * s, lc_sign * (c.half_width + 0.5)))
                    for s in self.steps(xsec.outer(side) + 4, length, 25, 40, 1.0):
                        light = _pole(rng, "street_light", -lc_sign)
                        self.add(self.on_crossing(light, c, arm * s, lc_sign * (c.half_width + 0.35)))

    def steps(self, lo: float, hi: float, step_lo: float, step_hi: float, density: float) -> list[float]:
        """Positions from ``lo`` to ``hi`` at random steps in ``[step_lo, step_hi] / density``."""
        out, s = [], lo + self.uniform(0, step_lo)
        while s < hi:
            out.append(s)
            s += self.uniform(step_lo, step_hi) / density
        return out

    def bicycle_rack(self, side: int, s: float, turn: float) -> None:
        """A rack on the terrain behind the sidewalk with bicycles parked across it."""
        sign, outer, rng = _SIGN[side], self.scene.xsec.outer(side), self.rng
        length = self.uniform(2.0, 4.0)
        self.add(self.on_main(_bicycle_rack(rng, length), s, sign * (outer + 2.0), turn))
        bikes = []
        for k in range(int(rng.integers(1, int(length / 0.8) + 1))):
            bike = _cycle(rng, "vehicle.bicycle", False)
            bikes.append(self.on_main(bike, s - length / 2 + 0.4 + 0.8 * k, sign * (outer + 0.95), np.pi / 2))
        self.add(*bikes)

    def motorcycle_row(self, side: int, s: float) -> None:
        """Parked motorcycles: in a row along the parking strip, or side by side behind the sidewalk."""
        xsec, sign, rng = self.scene.xsec, _SIGN[side], self.rng
        for k in range(int(rng.integers(1, 5))):
            moto = _cycle(rng, "vehicle.motorcycle", False)
            if xsec.parking[side] > 0 and rng.random() < 0.5:
                moto.ground = (_OTHER_FLAT,)
                self.add(self.on_main(moto, s + 2.6 * k, sign * (xsec.edge(side) + xsec.parking[side] / 2)))
            else:
                moto.ground = (_SIDEWALK, _TERRAIN)
                self.add(self.on_main(moto, s + 1.1 * k, sign * (xsec.outer(side) + 1.3), np.pi / 2))

    def parked(self) -> None:
        """Cars parked along the parking strips, facing the traffic of their side."""
        scene = self.scene
        for side in (0, 1):
            width = scene.xsec.parking[side]
            if width == 0:
                continue
            lateral = _SIGN[side] * (scene.xsec.edge(side) + width / 2)
            s = scene.view[0] + self.uniform(0, 5)
            while s < scene.view[1]:
                car = _vehicle(self.rng, "vehicle.car", "vehicle.parked")
                car.ground = (_OTHER_FLAT,)
                length = car.size[1]
                self.add(self.on_main(car, s + length / 2, lateral, 0.0 if side == 0 else np.pi))
                s += length + self.uniform(0.8, 8.0) / self.density

    def riders(self) -> None:
        """Cyclists and motorcyclists riding near the road edge, with their side's traffic."""
        xsec, rng = self.scene.xsec, self.rng
        for side in (0, 1):
            direction = 1 if side == 0 else -1
            for category, speeds in (("vehicle.bicycle", (3, 7)), ("vehicle.motorcycle", (6, 13))):
                for _ in range(int(rng.poisson(1.0 * self.density))):
                    cycle = _cycle(rng, category, True)
                    l = _SIGN[side] * (xsec.edge(side) - 0.45 - cycle.size[0] / 2)
                    s = self.main_lane(self.uniform(*self.scene.view), l)
                    self.add(self.on_lane(cycle, 0, l, s, self.uniform(*speeds), direction))

    def main_traffic(self) -> None:
        """Every lane of the main road: a stream at one speed per lane (the ego's speed in its lane), or a queue
        stopped at a junction; only vehicles that get into view at some instant."""
        scene, xsec = self.scene, self.scene.xsec
        ego, duration = scene.ego, scene.config.duration
        for side in (0, 1):
            direction = 1 if side == 0 else -1
            for j in range(xsec.lanes[side]):
                l = xsec.lane(side, j)
                if side == 0 and j == scene.ego_side_lane:
                    speed = ego.v
                elif self.rng.random() < 0.2 and self.queue(side, l, direction):
                    continue
                else:
                    speed = self.uniform(3, 14)
                a, b = self.view_lane(l)
                travel = direction * speed * duration
                self.stream(0, l, direction, speed, min(a, a - travel), max(b, b - travel))

    def queue(self, side: int, l: float, direction: int) -> bool:
        """Stop a queue of 2..6 vehicles at the junction nearest the ego's path; False if none is in view."""
        scene = self.scene
        middle = sum(self.ego_centre) / 2
        near = [c for c in scene.crossings if scene.view[0] + 30 < c.s_main < scene.view[1] - 30]
        if not near:
            return False
        c = min(near, key=lambda c: abs(c.s_main - middle))
        skew = math.sqrt(max(1.0 - float(np.dot(c.u, c.tangent)) ** 2, 0.5))
        head = self.main_lane(c.s_main - direction * ((c.half_width + c.sidewalk + 1.5) / skew + 1.0), l)
        for _ in range(int(self.rng.integers(2, 7))):
            unit = self.drive(self.unit(self.choice(_TRAFFIC), "vehicle.stopped"), 0, l, head, direction, 0.0)
            self.add(*unit)
            head -= direction * (_unit_length(unit) + self.uniform(1.5, 3.0))
        return True

    def arm_limits(self, c: _Crossing, lc: float, limits: tuple[float, float]) -> tuple[float, float]:
        """Where a line of the crossing at offset ``lc`` comes within ``limits[side]`` of the main road's centreline:
        ``(sc`` where it enters, ``sc`` where it leaves``)``."""
        sc = np.arange(-c.minus, c.plus, 0.25)
        _, l = self.scene.path.project(c.xy(sc, np.full_like(sc, lc)))
        inside = np.flatnonzero(np.abs(l) <= np.where(l < 0, limits[0], limits[1]))
        return float(sc[inside[0]]) - 0.25, float(sc[inside[-1]]) + 0.25

    def crossing_traffic(self) -> None:
        """Per crossing lane: a queue waiting at the stop line of the arm heading to the junction, vehicles
        leaving on the other arm; none of them enters the junction during the scene."""
        xsec, duration, rng = self.scene.xsec, self.scene.config.duration, self.rng
        for index, c in enumerate(self.scene.crossings):
            path = index + 1
            for lc in (-LANE_WIDTH / 2, LANE_WIDTH / 2):
                direction = 1 if lc < 0 else -1
                stop_minus, stop_plus = self.arm_limits(c, lc, (xsec.outer(0) + 1.0, xsec.outer(1) + 1.0))
                head = (stop_minus - 0.3 if direction > 0 else stop_plus + 0.3) + c.minus
                for _ in range(int(rng.integers(0, 4))):
                    unit = self.unit(self.choice(_TRAFFIC), "vehicle.stopped")
                    self.add(*self.drive(unit, path, lc, head, direction, 0.0))
                    head -= direction * (_unit_length(unit) + self.uniform(1.5, 3.0))
                speed = self.uniform(3, 12)
                lo, hi = (stop_plus, c.plus) if direction > 0 else (-c.minus, stop_minus)
                lo, hi = (lo, hi - speed * duration) if direction > 0 else (lo + speed * duration, hi)
                self.stream(path, lc, direction, speed, lo + c.minus, hi + c.minus, limit=int(rng.integers(0, 4)))

    def pedestrians(self) -> None:
        """People walking (0.5..1.8 m/s) or standing on the sidewalks, and crossing on the zebras."""
        scene, xsec, rng = self.scene, self.scene.xsec, self.rng
        duration = scene.config.duration
        for side in (0, 1):
            kerb, outer = xsec.kerb(side), xsec.outer(side)
            walk = kerb + 0.9  # the kerb side of the sidewalk holds the street furniture
            lines = [walk + 0.45, outer - 0.45] if outer - walk >= 1.9 else [(walk + outer) / 2]
            for lateral in lines:
                l = _SIGN[side] * lateral
                a, b = self.view_lane(l)
                for s in self.steps(a, b, 5, 25, self.density):
                    self.walker(0, l, s)
        for index, c in enumerate(scene.crossings):
            for lc_sign in (-1.0, 1.0):
                lc = lc_sign * (c.half_width + 0.7 + (c.sidewalk - 0.7) / 2)
                enter, leave = self.arm_limits(c, lc, (xsec.edge(0) + 0.5, xsec.edge(1) + 0.5))
                for lo, hi in ((-c.minus, enter), (leave, c.plus)):
                    for s in self.steps(lo, hi, 8, 25, self.density):
                        speed, direction = self.uniform(0.5, 1.8), 1 if rng.random() < 0.5 else -1
                        end = s + direction * speed * duration
                        if lo + 0.5 < min(s, end) and max(s, end) < hi - 0.5:
                            self.add(self.on_lane(_pedestrian(rng, True), index + 1, lc, s + c.minus, speed, direction))
                zebra = lc_sign * (c.half_width + c.sidewalk / 2)
                enter, leave = self.arm_limits(c, zebra, (xsec.edge(0), xsec.edge(1)))
                for _ in range(int(rng.integers(0, 3))):
                    speed, direction = self.uniform(1.0, 1.6), 1 if rng.random() < 0.5 else -1
                    s = self.uniform(enter, leave) + c.minus
                    self.add(self.on_lane(_pedestrian(rng, True), index + 1, zebra, s, speed, direction))

    def walker(self, path: int, l: float, s: float) -> None:
        """Someone at lane arc length ``s`` of a sidewalk line: mostly walking either way, sometimes standing."""
        rng = self.rng
        if rng.random() < 0.15:
            person = self.on_lane(_pedestrian(rng, False), path, l, s, 0.0, 1)
            person.pose = (*person.pose[:2], self.uniform(-np.pi, np.pi))
        else:
            person = self.on_lane(
                _pedestrian(rng, True), path, l, s, self.uniform(0.5, 1.8), 1 if rng.random() < 0.5 else -1
            )
        self.add(person)


# ============================================================================================ overlap check
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


def _ego_object(scene: _Scene) -> _Object:
    """The space the ego needs, as an object moving with it (only used by the overlap check)."""
    ahead, half_length, half_width, height = _EGO_RESERVE
    solid = _solid(BOX, ahead, 0.0, 0.0, height, half_length, half_width, (0.0, 0.0, 0.0))
    ego = scene.ego
    return _Object("vehicle.ego", "ego", [solid], track=(0, ego.l, ego.s0, ego.v, False))


def _object_poses(scene: _Scene, objects: list[_Object], times: np.ndarray) -> tuple[np.ndarray, ...]:
    """``x, y, yaw, vx, vy`` of every object at ``times``, each ``(N, T)``; object 0 is the ego."""
    n, num_times = len(objects), len(times)
    x, y, yaw, vx, vy = (np.zeros((n, num_times)) for _ in range(5))
    statics = [i for i, o in enumerate(objects) if o.track is None]
    pose = np.array([objects[i].pose for i in statics]).reshape(-1, 3)
    x[statics], y[statics], yaw[statics] = pose[:, :1], pose[:, 1:2], pose[:, 2:]
    movers = [i for i, o in enumerate(objects) if o.track is not None and i > 0]
    if movers:
        paths = [scene.path] + [c.path for c in scene.crossings]
        poses = _Tracks.of([objects[i].track for i in movers]).poses(paths, times)
        x[movers], y[movers], yaw[movers], vx[movers], vy[movers] = poses
    ego = scene.ego
    ex, ey, eh = scene.path.at_lane(ego.s(times), ego.l)
    speed = ego.speed(times)
    x[0], y[0], yaw[0], vx[0], vy[0] = ex, ey, eh, speed * np.cos(eh), speed * np.sin(eh)
    return x, y, yaw, vx, vy


def _ground_ok(scene: _Scene, objects: list[_Object]) -> np.ndarray:
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


def _plausible(scene: _Scene, objects: list[_Object], group_of: np.ndarray, x, y) -> np.ndarray:
    """``(N,)`` whether each object's group is worth checking: some object of it comes into view (the world's
    bounding box) at some instant, and none of its static objects stands on forbidden ground."""
    lo, hi = scene.bbox[:2] - 5.0, scene.bbox[2:] + 5.0
    seen = ((x > lo[0]) & (x < hi[0]) & (y > lo[1]) & (y < hi[1])).any(axis=1)
    group_seen = np.zeros(group_of.max() + 1, bool)
    np.logical_or.at(group_seen, group_of, seen)
    group_bad = np.zeros(group_of.max() + 1, bool)
    np.logical_or.at(group_bad, group_of, ~_ground_ok(scene, objects))
    return (group_seen & ~group_bad)[group_of]


def _clear_groups(objects: list[_Object], group_of: np.ndarray, x, y, yaw, vx, vy) -> np.ndarray:
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
    grow = np.hypot(hx, hy) + _CHECK_MARGIN + speed * _CHECK_SLACK
    box = np.stack([cx.min(1) - grow, cy.min(1) - grow, cx.max(1) + grow, cy.max(1) + grow], axis=1)
    _, first = np.unique(group_of[owner], return_index=True)
    group_start = np.append(first, len(rows)).astype(np.int64)
    return _select_groups(
        group_start, owner, moving, cx, cy, c, s, vx[owner], vy[owner], hx, hy, z0, z1, box, _CHECK_SLACK, _CHECK_MARGIN
    )


def _select(scene: _Scene, groups: list[list[_Object]]) -> list[_Object]:
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


# ============================================================================================ generation
def generate_world(seed: int, config: WorldConfig = WorldConfig()) -> World:  # noqa: B008 - frozen, immutable
    """Generate the world of ``seed``: road layout, ground raster, ego drive and all objects.

    Deterministic: the same seed and config give identical arrays. Independent random streams for the layout,
    the objects and the sky keep a change in one from reshuffling the others.
    """
    layout_rng, object_rng, sky_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    city = int(layout_rng.integers(len(_STYLES)))
    xsec = _cross_section(layout_rng)
    ego_lane = int(layout_rng.integers(xsec.lanes[0]))
    ego = _ego_motion(layout_rng, config, xsec.lane(0, ego_lane))
    start = config.margin + float(layout_rng.uniform(5, 25))
    drive = ego.v * (1 + ego.a) * config.duration
    path = _main_path(layout_rng, start + 1.3 * drive + config.margin + 40.0)
    ego = _EgoMotion(ego.l, float(path.centre_to_lane(start, ego.l)), ego.v, ego.a, ego.w, ego.phase)
    ends = path.lane_to_centre(ego.s(np.array([0.0, config.duration])), ego.l)
    view = (float(ends[0]) - config.margin, float(ends[1]) + config.margin)
    ex, ey, _ = path.at_lane(ego.s(np.linspace(0.0, config.duration, 64)), ego.l)
    bbox = np.array([ex.min(), ey.min(), ex.max(), ey.max()]) + np.array([-1, -1, 1, 1]) * config.margin
    crossings = _crossings(layout_rng, path, xsec, view, 1.5 * config.margin + 30.0)
    plan = _plan(layout_rng, xsec, ego_lane, crossings, view, float(ends[0]), config.density)
    ground = _paint_ground(path, xsec, crossings, plan, bbox, config.ground_resolution)
    scene = _Scene(object_rng, config, path, xsec, ego_lane, ego, crossings, plan, ground, view, bbox, _STYLES[city])

    placer = _Placer(scene)
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
    accepted = _select(scene, placer.groups)

    elevation, azimuth = np.radians(sky_rng.uniform(15, 70)), sky_rng.uniform(-np.pi, np.pi)
    sun = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    zenith = np.clip(np.array([0.22, 0.42, 0.78]) + sky_rng.uniform(-0.05, 0.05, 3), 0, 1).astype(np.float32)
    horizon = np.clip(np.array([0.72, 0.8, 0.88]) + sky_rng.uniform(-0.05, 0.05, 3), 0, 1).astype(np.float32)
    return World(seed, config, scene, accepted, sun, (zenith, horizon), f"synth-city-{city}")
