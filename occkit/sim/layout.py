"""A scene's layout, drawn from the world's layout stream: the main road, its cross section, the ego's drive,
the crossing roads and the plan of road works, bus stops and driveways; and :class:`Scene`, the bundle of all of
it (with the painted ground) that object placement works from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from occkit.sim.motion import EgoMotion
from occkit.sim.objects import Style
from occkit.sim.primitives import GroundMap
from occkit.sim.roads import Crossing, CrossSection, Path, Plan

if TYPE_CHECKING:
    from occkit.sim.config import WorldConfig

__all__ = ["Scene", "draw_main_path", "draw_cross_section", "draw_ego_motion", "draw_crossings", "draw_plan"]


@dataclass
class Scene:
    """Everything the object placement needs: road, ego motion, crossings, ground and the view."""

    rng: np.random.Generator
    config: WorldConfig
    path: Path
    xsec: CrossSection
    ego_side_lane: int
    ego: EgoMotion
    crossings: list[Crossing]
    ground: GroundMap
    view: tuple[float, float]  # main arc-length range (m) that the sensors can see during the scene
    bbox: np.ndarray  # (4,) xmin, ymin, xmax, ymax of the world that matters
    style: Style


def draw_main_path(rng: np.random.Generator, length: float) -> Path:
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
    return Path(0.0, 0.0, float(rng.uniform(-np.pi, np.pi)), pieces)


def draw_cross_section(rng: np.random.Generator) -> CrossSection:
    lanes = int(rng.integers(2, 5))
    multi = 0.6 if lanes >= 3 else 0.25
    median = float(rng.uniform(0.5, 1.5)) if rng.random() < multi else 0.0
    parking = tuple(float(rng.uniform(2.3, 2.8)) if rng.random() < 0.5 else 0.0 for _ in range(2))
    sidewalk = tuple(float(rng.uniform(2.0, 4.0)) for _ in range(2))
    return CrossSection(median, ((lanes + 1) // 2, lanes // 2), parking, sidewalk)  # type: ignore[arg-type]


def draw_ego_motion(rng: np.random.Generator, config: WorldConfig, l: float) -> EgoMotion:
    lo, hi = config.ego_speed
    a = min(0.05, (hi - lo) / (hi + lo))  # speed wobble, kept inside the configured range
    v = float(rng.uniform(lo / (1 - a), hi / (1 + a)))
    return EgoMotion(l, 0.0, v, a, 2 * np.pi / float(rng.uniform(8, 16)), float(rng.uniform(0, 2 * np.pi)))


def draw_crossings(rng, path: Path, xsec: CrossSection, view: tuple[float, float], arm: float) -> list[Crossing]:
    """Crossings every 60..150 m of main arc length over ``view``, arms ``arm`` metres long.

    An arm that would run into an earlier crossing's road stops short of it; a crossing whose arm would then be
    too short to reach beyond the main road's sidewalks is left out.
    """
    crossings: list[Crossing] = []
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
            crossings.append(Crossing(s, np.array([x, y]), u, tangent, arms[-1], arms[1], sidewalk))
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


def draw_plan(rng, xsec: CrossSection, ego_lane: int, crossings, view, ego_s: float, density: float) -> Plan:
    """Lay out road works (every 50..75 m), bus stops (every 65..100 m) and driveways along the main road.

    Road works and bus stops start near the ego so that they are in view; a bus stands in a bay where there is a
    parking strip, otherwise in the outermost lane, which must then not be the ego's.
    """
    plan = Plan()
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
