"""The ground raster: Occ3D flat classes and road paint of the main road, its crossings and roadside features.

The main road's corridor is painted from the ``(s, l)`` road coordinates of each cell: median, carriageway with
edge, centre and dashed divider lines, parking strips, sidewalks, bus bays and driveways; everything else is
terrain. Each crossing then paints its carriageway and sidewalks over it, with zebra crossings and stop lines.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from occkit.sim.primitives import GroundMap
from occkit.sim.roads import LANE_WIDTH, CrossSection, Path, Plan, road_coordinates

__all__ = ["DRIVEABLE", "OTHER_FLAT", "SIDEWALK", "TERRAIN", "BAY_DEPTH", "paint_ground"]

#: Occ3D flat classes of the ground.
DRIVEABLE, OTHER_FLAT, SIDEWALK, TERRAIN = 11, 12, 13, 14

BAY_DEPTH = 3.2  # bus bays: driveable from the road edge this far out (m)
_DRIVEWAY_DEPTH = 1.5  # driveways: other_flat from the kerb to this far beyond the sidewalk (m)


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
            c = TERRAIN
            if a < median:
                c = OTHER_FLAT
            elif a < edge:
                c = DRIVEABLE
            elif a < kerb:
                c = OTHER_FLAT
            elif a < outer:
                c = SIDEWALK
            for b in range(bays.shape[0]):
                if bays[b, 0] == side and bays[b, 1] <= s < bays[b, 2] and edge <= a < edge + BAY_DEPTH:
                    c = DRIVEABLE
            if kerb <= a < outer + _DRIVEWAY_DEPTH:
                for d in range(driveways.shape[0]):
                    if driveways[d, 0] == side and driveways[d, 1] <= s < driveways[d, 2]:
                        c = OTHER_FLAT
            sem[i, j] = c
            marks[i, j] = c == DRIVEABLE and median <= a < edge and _lane_paint(a, s, median, edge, lanes[side])


@njit(cache=True)
def _paint_crossing(sem, marks, l_map, window, ox, oy, res, geometry, profile):
    """Paint a crossing road over the raster ``window`` ``(i0, i1, j0, j1)``: its carriageway and sidewalks,
    zebra crossings and stop lines on both roads, its centre and edge lines. ``geometry`` is
    :meth:`Crossing.geometry`, ``profile`` :meth:`CrossSection.profile`."""
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
                sem[i, j] = DRIVEABLE
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
                if sem[i, j] != DRIVEABLE:
                    sem[i, j] = SIDEWALK
                    marks[i, j] = False
                elif on_main:  # zebra across the main road, continuing this road's sidewalks
                    marks[i, j] = hw + 0.3 <= a < hw + sw - 0.3 and _frac(lm) < 0.5
            elif on_main and am >= median and hw + sw + 0.4 <= a < hw + sw + 0.8:
                # stop lines of the main road, upstream of the zebra: right-hand lanes drive along the tangent
                upstream = dx * tx + dy * ty
                if (side == 0 and upstream < 0.0) or (side == 1 and upstream > 0.0):
                    marks[i, j] = True


def paint_ground(scene_path: Path, xsec: CrossSection, crossings, plan: Plan, bbox, res: float) -> GroundMap:
    """Rasterise the ground over ``bbox`` (xmin, ymin, xmax, ymax) at ``res`` metres per cell."""
    origin = np.floor(np.asarray(bbox[:2]) / res) * res
    nx, ny = (int(math.ceil((bbox[2 + d] - origin[d]) / res)) for d in range(2))
    half_width = max(xsec.outer(0), xsec.outer(1)) + _DRIVEWAY_DEPTH + 1.0
    s_map, l_map = road_coordinates(*scene_path.pieces(), origin[0], origin[1], res, nx, ny, half_width)
    sem = np.full((nx, ny), TERRAIN, np.uint8)
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
    marks &= sem == DRIVEABLE
    return GroundMap(semantics=sem, markings=marks, origin=origin, resolution=res)
