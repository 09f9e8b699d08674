"""Road geometry: the main road's path, its cross section, the crossing roads, and the plan of roadside features.

A :class:`Path` is a chain of straights and circular arcs parameterised by arc length ``s``; lateral offsets ``l``
are measured to the left of its direction, so the right-hand side of a road has ``l < 0``. The numba kernels here
turn global points and ground-raster cells into ``(s, l)`` road coordinates.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

__all__ = ["LANE_WIDTH", "SIGN", "Path", "road_coordinates", "CrossSection", "Crossing", "Plan"]

LANE_WIDTH = 3.5
SIGN = (-1.0, 1.0)  # sign of l per side: index 0 is the right side, 1 the left


class Path:
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
    """Nearest-piece ``(s, l)`` of points ``(N,)``; the tables are :meth:`Path.pieces`."""
    n, num = px.shape[0], k.shape[0]
    s_out, l_out = np.zeros(n), np.full(n, np.inf)
    for q in range(n):
        for p in range(num):
            u, l, valid = _piece_coords(px[q], py[q], x0[p], y0[p], h0[p], k[p], length[p], p == 0, p == num - 1)
            if valid and abs(l) < abs(l_out[q]):
                s_out[q], l_out[q] = start[p] + u, l
    return s_out, l_out


@njit(cache=True)
def road_coordinates(x0, y0, h0, k, length, start, ox, oy, res, nx, ny, half_width):
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
class CrossSection:
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
        return SIGN[side] * (self.median + LANE_WIDTH * (j + 0.5))

    def profile(self) -> np.ndarray:
        """``(7,)`` median, then edge, kerb, outer of the right and of the left side, for the numba painters."""
        return np.array([self.median] + [f(side) for side in (0, 1) for f in (self.edge, self.kerb, self.outer)])


@dataclass
class Crossing:
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
    path: Path = field(init=False)

    def __post_init__(self) -> None:
        start = self.point - self.minus * self.u
        heading = math.atan2(self.u[1], self.u[0])
        self.path = Path(float(start[0]), float(start[1]), heading, [(0.0, self.minus + self.plus)])

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
class Plan:
    """Where the main road's features go, as main arc-length intervals per side.

    ``bays``, ``driveways``: rows ``(side, s0, s1)``; ``works``: ``(side, s0, s1, closes_lane)``;
    ``bus_stops``: ``(side, s, in_bay)``.
    """

    bays: list[tuple[int, float, float]] = field(default_factory=list)
    driveways: list[tuple[int, float, float]] = field(default_factory=list)
    works: list[tuple[int, float, float, bool]] = field(default_factory=list)
    bus_stops: list[tuple[int, float, bool]] = field(default_factory=list)
