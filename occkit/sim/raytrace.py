"""Exact ray casting against the world's solids and the ground plane, shared by the cameras and the LiDAR.

Rays live in the global frame. Intersections are analytic: a slab test in a box's local frame, the side and caps of
an upright cylinder, a yawed ellipsoid scaled to the unit sphere, and the plane ``z = 0`` for rays going down.
A solid is seen from outside only: a ray that starts inside a solid passes through it.

Acceleration: the solids' xy footprints are binned into a uniform 2D grid (one per call, over the region the rays
can reach); each ray walks the grid cells it crosses with a 2D DDA, tests the solids listed in each cell once
(a per-ray mailbox skips repeats), and stops as soon as its best hit lies before the exit of the current cell.
The ground hit, the range limit and the solids' height range bound the walk, so rays to the ground or the sky cost
a handful of cells.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from occkit.sim.primitives import BOX, CYLINDER, ELLIPSOID, GroundMap, Primitives

__all__ = ["GROUND", "NOTHING", "Hits", "cast_rays", "solid_table", "hit_labels"]

#: ``Hits.primitive`` values that are not primitive indices.
GROUND, NOTHING = -1, -2

#: Grid cell size (m): a car covers one or two cells, a building a few dozen.
CELL_SIZE = 3.0
# The grid never exceeds this many cells; wider regions get coarser cells.
_MAX_CELLS = 1 << 18
# Footprints and cell tops are padded by this much (m) so that round-off in the walk never skips a solid.
_PAD = 1e-3


@dataclass
class Hits:
    """First hit of each of ``R`` rays.

    Attributes:
        distance: ``(R,)`` float64 distance along the unit ray (m); ``inf`` where nothing lies within range.
        primitive: ``(R,)`` int32 index of the solid hit, :data:`GROUND` for the plane ``z = 0``, :data:`NOTHING`.
        normal: ``(R, 3)`` float32 unit surface normal facing the ray; zero where nothing was hit.
        point: ``(R, 3)`` float64 global hit point ``origin + distance * direction``; ``nan`` where nothing was hit.
    """

    distance: np.ndarray
    primitive: np.ndarray
    normal: np.ndarray
    point: np.ndarray

    def __len__(self) -> int:
        return int(self.distance.shape[0])


def solid_table(primitives: Primitives) -> np.ndarray:
    """``(P, 8)`` float64 rows ``(cx, cy, cz, hx, hy, hz, cos yaw, sin yaw)``: what the kernels read of each solid."""
    return np.ascontiguousarray(
        np.concatenate(
            (
                primitives.center,
                primitives.half_size,
                np.cos(primitives.yaw)[:, None],
                np.sin(primitives.yaw)[:, None],
            ),
            axis=1,
        ),
        dtype=np.float64,
    )


def cast_rays(
    origins: np.ndarray,
    directions: np.ndarray,
    max_distance: float,
    primitives: Primitives,
    ground: GroundMap | None,
) -> Hits:
    """First hit of each ray among the solids and (when ``ground`` is given) the ground plane.

    Args:
        origins: ``(R, 3)`` global ray origins (m); a single origin ``(3,)`` or ``(1, 3)`` is shared by all rays.
        directions: ``(R, 3)`` unit directions, global frame.
        max_distance: hits at this distance (m) or farther are not reported.
        primitives: the world's solids.
        ground: the ground map; only its presence matters here (every ground point is a hit, the map gives its
            class later, see :func:`hit_labels`). ``None`` leaves out the ground plane.

    Returns:
        :class:`Hits` for the ``R`` rays.
    """
    directions = np.ascontiguousarray(directions, dtype=np.float64)
    origins = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
    if directions.ndim != 2 or directions.shape[1] != 3:
        raise ValueError(f"directions must have shape (R, 3), got {directions.shape}")
    if origins.shape[0] not in (1, directions.shape[0]):
        raise ValueError(f"origins must have shape (3,), (1, 3) or (R, 3), got {origins.shape}")
    table = solid_table(primitives)
    kind = np.ascontiguousarray(primitives.kind, dtype=np.int8)
    x0, y0, cell, nx, ny, start, items, cell_top = _build_grid(origins, max_distance, kind, table)
    z_range = _height_range(kind, table)
    rays = directions.shape[0]
    distance = np.empty(rays)
    primitive = np.empty(rays, np.int32)
    normal = np.empty((rays, 3), np.float32)
    point = np.empty((rays, 3))
    _cast_kernel(
        origins, directions, float(max_distance), ground is not None, kind, table,
        x0, y0, cell, nx, ny, z_range[0], z_range[1], start, items, cell_top,
        distance, primitive, normal, point,
    )  # fmt: skip
    return Hits(distance, primitive, normal, point)


def hit_labels(
    hits: Hits, primitives: Primitives, ground: GroundMap | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Labels of what each ray hit.

    Returns:
        semantic: ``(R,)`` uint8 Occ3D class: the solid's class, the ground map's flat class (terrain outside the
            map), 255 where nothing was hit.
        instance: ``(R,)`` int32 the solid's instance id, -1 for the ground and for nothing.
        marking: ``(R,)`` bool, the ground hit lies on road paint.
    """
    semantic = np.full(len(hits), 255, np.uint8)
    instance = np.full(len(hits), -1, np.int32)
    marking = np.zeros(len(hits), bool)
    solid = hits.primitive >= 0
    semantic[solid] = primitives.semantic[hits.primitive[solid]]
    instance[solid] = primitives.instance[hits.primitive[solid]]
    on_ground = hits.primitive == GROUND
    if ground is not None and on_ground.any():
        xy = hits.point[on_ground, :2]
        semantic[on_ground] = ground.lookup(xy)
        cells = np.floor((xy - ground.origin) / ground.resolution).astype(np.int64)
        nx, ny = ground.markings.shape
        inside = (cells[:, 0] >= 0) & (cells[:, 0] < nx) & (cells[:, 1] >= 0) & (cells[:, 1] < ny)
        painted = np.zeros(len(xy), bool)
        painted[inside] = ground.markings[cells[inside, 0], cells[inside, 1]]
        marking[on_ground] = painted
    return semantic, instance, marking


# --------------------------------------------------------------------------- grid construction
def _footprints(kind: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(P, 2)`` lower and upper xy corners of each solid's axis-aligned footprint, padded by ``_PAD``."""
    cos, sin = np.abs(table[:, 6]), np.abs(table[:, 7])
    hx, hy = table[:, 3], table[:, 4]
    extent = np.stack((cos * hx + sin * hy, sin * hx + cos * hy), axis=1)  # a yawed rectangle
    ellipse = kind == ELLIPSOID
    extent[ellipse] = np.stack((np.hypot(cos * hx, sin * hy)[ellipse], np.hypot(sin * hx, cos * hy)[ellipse]), axis=1)
    disc = kind == CYLINDER
    extent[disc] = hx[disc, None]
    return table[:, :2] - extent - _PAD, table[:, :2] + extent + _PAD


def _height_range(kind: np.ndarray, table: np.ndarray) -> tuple[float, float]:
    """Lowest bottom and highest top (m) over all solids; an empty range when there are none."""
    if len(kind) == 0:
        return 1.0, 0.0
    return float((table[:, 2] - table[:, 5]).min() - _PAD), float((table[:, 2] + table[:, 5]).max() + _PAD)


def _build_grid(origins: np.ndarray, max_distance: float, kind: np.ndarray, table: np.ndarray):
    """Uniform grid over the solids' footprints within ``max_distance`` of the origins; CSR lists per cell."""
    lower, upper = _footprints(kind, table)
    if len(kind):
        lo = np.maximum(origins[:, :2].min(axis=0) - max_distance, lower.min(axis=0))
        hi = np.minimum(origins[:, :2].max(axis=0) + max_distance, upper.max(axis=0))
    if len(kind) == 0 or np.any(hi <= lo):
        return 0.0, 0.0, CELL_SIZE, 1, 1, np.zeros(2, np.int64), np.zeros(0, np.int32), np.full(1, -np.inf)
    span = hi - lo
    cell = max(CELL_SIZE, math.sqrt(span[0] * span[1] / _MAX_CELLS))
    nx, ny = (int(n) for n in np.maximum(np.ceil(span / cell), 1))
    top = table[:, 2] + table[:, 5] + _PAD
    start, items, cell_top = _bin_footprints(lower, upper, top, lo[0], lo[1], cell, nx, ny)
    return float(lo[0]), float(lo[1]), cell, nx, ny, start, items, cell_top


@njit(cache=True)
def _bin_footprints(lower, upper, top, x0, y0, cell, nx, ny):
    """CSR lists of the solids overlapping each cell (cell ``c = ix * ny + iy``) and each cell's highest top."""
    counts = np.zeros(nx * ny + 1, np.int64)
    cell_top = np.full(nx * ny, -np.inf)
    for p in range(lower.shape[0]):
        i0, i1, j0, j1 = _cell_span(lower, upper, p, x0, y0, cell, nx, ny)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                counts[i * ny + j + 1] += 1
                cell_top[i * ny + j] = max(cell_top[i * ny + j], top[p])
    start = np.cumsum(counts)
    items = np.empty(start[-1], np.int32)
    fill = start[:-1].copy()
    for p in range(lower.shape[0]):
        i0, i1, j0, j1 = _cell_span(lower, upper, p, x0, y0, cell, nx, ny)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                items[fill[i * ny + j]] = p
                fill[i * ny + j] += 1
    return start, items, cell_top


@njit(cache=True)
def _cell_span(lower, upper, p, x0, y0, cell, nx, ny):
    """Inclusive cell index ranges ``i0, i1, j0, j1`` covered by footprint ``p`` (empty ranges when outside)."""
    i0 = max(int(math.floor((lower[p, 0] - x0) / cell)), 0)
    i1 = min(int(math.floor((upper[p, 0] - x0) / cell)), nx - 1)
    j0 = max(int(math.floor((lower[p, 1] - y0) / cell)), 0)
    j1 = min(int(math.floor((upper[p, 1] - y0) / cell)), ny - 1)
    return i0, i1, j0, j1


# --------------------------------------------------------------------------- intersections
@njit(cache=True)
def _slab(o, d, half, t_near, t_far):
    """Narrow ``[t_near, t_far]`` to where ``o + t d`` lies in ``[-half, half]``."""
    if d == 0.0:
        if abs(o) > half:
            return np.inf, -np.inf
        return t_near, t_far
    inv = 1.0 / d
    ta = (-half - o) * inv
    tb = (half - o) * inv
    if ta > tb:
        ta, tb = tb, ta
    return max(t_near, ta), min(t_far, tb)


@njit(cache=True)
def _entry(t_near, t_far):
    """The entering distance of an interval, or ``inf`` when the ray misses or starts inside."""
    if t_near > t_far or t_near <= 0.0:
        return np.inf
    return t_near


@njit(cache=True)
def _intersect(kind, table, p, ox, oy, oz, dx, dy, dz):
    """Distance at which the ray enters solid ``p``; ``inf`` if it does not."""
    rx, ry, rz = ox - table[p, 0], oy - table[p, 1], oz - table[p, 2]
    hx, hy, hz = table[p, 3], table[p, 4], table[p, 5]
    if kind[p] == CYLINDER:
        a = dx * dx + dy * dy
        c = rx * rx + ry * ry - hx * hx
        if a == 0.0:
            if c > 0.0:
                return np.inf
            t_near, t_far = -np.inf, np.inf
        else:
            b = rx * dx + ry * dy
            disc = b * b - a * c
            if disc < 0.0:
                return np.inf
            root = math.sqrt(disc)
            t_near, t_far = (-b - root) / a, (-b + root) / a
        t_near, t_far = _slab(rz, dz, hz, t_near, t_far)
        return _entry(t_near, t_far)
    # Boxes and ellipsoids: rotate by -yaw into the solid's frame.
    cos, sin = table[p, 6], table[p, 7]
    lx, ly = cos * rx + sin * ry, -sin * rx + cos * ry
    ldx, ldy = cos * dx + sin * dy, -sin * dx + cos * dy
    if kind[p] == BOX:
        t_near, t_far = _slab(lx, ldx, hx, -np.inf, np.inf)
        t_near, t_far = _slab(ly, ldy, hy, t_near, t_far)
        t_near, t_far = _slab(rz, dz, hz, t_near, t_far)
        return _entry(t_near, t_far)
    sx, sy, sz = lx / hx, ly / hy, rz / hz
    sdx, sdy, sdz = ldx / hx, ldy / hy, dz / hz
    a = sdx * sdx + sdy * sdy + sdz * sdz
    b = sx * sdx + sy * sdy + sz * sdz
    c = sx * sx + sy * sy + sz * sz - 1.0
    disc = b * b - a * c
    if disc < 0.0:
        return np.inf
    root = math.sqrt(disc)
    return _entry((-b - root) / a, (-b + root) / a)


@njit(cache=True)
def _normal(kind, table, p, x, y, z):
    """Outward unit normal of solid ``p`` at its surface point ``(x, y, z)``, global frame."""
    rx, ry, rz = x - table[p, 0], y - table[p, 1], z - table[p, 2]
    hx, hy, hz = table[p, 3], table[p, 4], table[p, 5]
    cos, sin = table[p, 6], table[p, 7]
    if kind[p] == CYLINDER:
        radial = math.sqrt(rx * rx + ry * ry)
        if abs(abs(rz) - hz) < abs(radial - hx) or radial == 0.0:
            return 0.0, 0.0, math.copysign(1.0, rz)
        return rx / radial, ry / radial, 0.0
    lx, ly = cos * rx + sin * ry, -sin * rx + cos * ry
    if kind[p] == BOX:
        ax, ay, az = abs(lx) / hx, abs(ly) / hy, abs(rz) / hz
        nx, ny, nz = 0.0, 0.0, 0.0
        if ax >= ay and ax >= az:
            nx = math.copysign(1.0, lx)
        elif ay >= az:
            ny = math.copysign(1.0, ly)
        else:
            nz = math.copysign(1.0, rz)
    else:
        nx, ny, nz = lx / (hx * hx), ly / (hy * hy), rz / (hz * hz)
        norm = math.sqrt(nx * nx + ny * ny + nz * nz)
        nx, ny, nz = nx / norm, ny / norm, nz / norm
    return cos * nx - sin * ny, sin * nx + cos * ny, nz


# --------------------------------------------------------------------------- traversal
@njit(cache=True)
def _walk(ray, ox, oy, oz, dx, dy, dz, best, best_p, kind, table, x0, y0, cell, nx, ny, z_lo, z_hi,
          start, items, cell_top, mailbox):  # fmt: skip
    """Nearest solid hit closer than ``best`` along one ray: 2D DDA over the grid cells the ray crosses."""
    # Only the part of the ray inside the grid and within the solids' height range can hit a solid.
    t0, t1 = _slab(ox - x0 - 0.5 * nx * cell, dx, 0.5 * nx * cell, 0.0, best)
    t0, t1 = _slab(oy - y0 - 0.5 * ny * cell, dy, 0.5 * ny * cell, t0, t1)
    t0, t1 = _slab(oz - 0.5 * (z_lo + z_hi), dz, 0.5 * (z_hi - z_lo), t0, t1)
    if t0 > t1:
        return best, best_p
    ix = min(max(int(math.floor((ox + t0 * dx - x0) / cell)), 0), nx - 1)
    iy = min(max(int(math.floor((oy + t0 * dy - y0) / cell)), 0), ny - 1)
    step_x, next_x, delta_x = _dda_axis(ox, dx, x0, cell, ix)
    step_y, next_y, delta_y = _dda_axis(oy, dy, y0, cell, iy)
    t_in = t0
    while True:
        t_out = min(next_x, next_y, t1)
        c = ix * ny + iy
        # Lowest height of the ray inside this cell: skip the cell when even that is above every solid there.
        if oz + dz * (t_in if dz >= 0.0 else t_out) <= cell_top[c]:
            for k in range(start[c], start[c + 1]):
                p = items[k]
                if mailbox[p] != ray:
                    mailbox[p] = ray
                    t = _intersect(kind, table, p, ox, oy, oz, dx, dy, dz)
                    if t < best:
                        best, best_p = t, p
        # A hit before the cell's exit cannot be beaten by solids in later cells.
        if best <= t_out or t_out >= t1:
            return best, best_p
        if next_x < next_y:
            ix += step_x
            if ix < 0 or ix >= nx:
                return best, best_p
            t_in = next_x
            next_x += delta_x
        else:
            iy += step_y
            if iy < 0 or iy >= ny:
                return best, best_p
            t_in = next_y
            next_y += delta_y


@njit(cache=True)
def _dda_axis(o, d, lo, cell, index):
    """Cell step, distance to the first cell border and distance between borders along one grid axis."""
    if d > 0.0:
        return 1, (lo + (index + 1) * cell - o) / d, cell / d
    if d < 0.0:
        return -1, (lo + index * cell - o) / d, -cell / d
    return 0, np.inf, np.inf


@njit(cache=True)
def _cast_kernel(origins, directions, max_distance, with_ground, kind, table, x0, y0, cell, nx, ny, z_lo, z_hi,
                 start, items, cell_top, distance, primitive, normal, point):  # fmt: skip
    """Fill ``distance``, ``primitive``, ``normal``, ``point`` (see :class:`Hits`) for every ray."""
    mailbox = np.full(kind.shape[0], -1, np.int64)
    shared_origin = origins.shape[0] == 1
    for r in range(directions.shape[0]):
        o = 0 if shared_origin else r
        ox, oy, oz = origins[o, 0], origins[o, 1], origins[o, 2]
        dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
        best, best_p = max_distance, NOTHING
        if with_ground and dz < 0.0 and oz > 0.0 and -oz / dz < best:
            best, best_p = -oz / dz, GROUND
        if items.shape[0] > 0:
            best, best_p = _walk(r, ox, oy, oz, dx, dy, dz, best, best_p, kind, table, x0, y0, cell, nx, ny,
                                 z_lo, z_hi, start, items, cell_top, mailbox)  # fmt: skip
        primitive[r] = best_p
        if best_p == NOTHING:
            distance[r] = np.inf
            normal[r] = 0.0
            point[r] = np.nan
            continue
        distance[r] = best
        x, y, z = ox + best * dx, oy + best * dy, oz + best * dz
        point[r, 0], point[r, 1], point[r, 2] = x, y, z
        if best_p == GROUND:
            n0, n1, n2 = 0.0, 0.0, 1.0
        else:
            n0, n1, n2 = _normal(kind, table, best_p, x, y, z)
            if n0 * dx + n1 * dy + n2 * dz > 0.0:  # grazing hits on edges: keep the normal facing the ray
                n0, n1, n2 = -n0, -n1, -n2
        normal[r, 0], normal[r, 1], normal[r, 2] = n0, n1, n2
