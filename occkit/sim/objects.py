"""The object catalogue: vehicles, riders, pedestrians, road-works gear, buildings, street furniture and plants.

Each builder draws one object's size and look from a random generator and returns an :class:`Object` made of
solids in its own frame; placing it (a static pose or a track along a lane) is the placer's job. A city's
:class:`Style` sets its facade materials, building heights and greenery.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occkit.classes import occ3d_id
from occkit.sim.ground import OTHER_FLAT, SIDEWALK, TERRAIN
from occkit.sim.motion import wrap
from occkit.sim.primitives import BOX, CYLINDER, ELLIPSOID, Primitives, Texture

__all__ = [
    "CATEGORY_SIZES",
    "Style",
    "STYLES",
    "Solid",
    "solid",
    "Object",
    "solid_rows",
    "place_solids",
    "vehicle",
    "cycle",
    "pedestrian",
    "barrier",
    "cone",
    "debris",
    "building",
    "wall",
    "pole",
    "tree",
    "hedge",
    "bus_shelter",
    "bicycle_rack",
]

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
class Style:
    """Look of a city: facade material weights (concrete, brick, glass, plaster) and building heights (m)."""

    materials: tuple[float, float, float, float]
    height: tuple[float, float]
    trees: float  # relative density of trees and hedges


STYLES = (
    Style((0.5, 0.1, 0.3, 0.1), (10.0, 25.0), 0.7),  # downtown
    Style((0.2, 0.6, 0.0, 0.2), (6.0, 14.0), 1.2),  # brick terraces
    Style((0.3, 0.0, 0.6, 0.1), (12.0, 25.0), 0.8),  # business park
    Style((0.2, 0.2, 0.0, 0.6), (6.0, 10.0), 1.5),  # suburb
)


# A solid in its object's frame (x along the object's heading, y to its left, z up, origin on the ground under
# the object's centre): kind, dx, dy, z centre, half sizes (3), albedo (3), texture, reflectivity. Solids share
# their object's yaw.
Solid = tuple


def solid(kind, dx, dy, z0, z1, hx, hy, color, texture=Texture.PLAIN, reflectivity=0.3) -> Solid:
    """A solid spanning heights ``z0..z1`` (m) with horizontal half sizes ``hx, hy``, centred at ``(dx, dy)``."""
    return (kind, dx, dy, (z0 + z1) / 2, hx, hy, (z1 - z0) / 2, *color, texture, reflectivity)


@dataclass
class Object:
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
    solids: list[Solid]
    size: tuple[float, float, float] | None = None
    attribute: str = ""
    pose: tuple[float, float, float] | None = None
    track: tuple[int, float, float, float, bool] | None = None
    ground: tuple[int, ...] | None = None


def solid_rows(objects: list[Object], indices: list[int]):
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


def place_solids(rows: np.ndarray, x, y, yaw, instance) -> Primitives:
    """Solids ``rows`` of objects at poses ``x, y, yaw`` (one per row) as global :class:`Primitives`."""
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = rows[:, 1], rows[:, 2]
    center = np.stack([x + c * dx - s * dy, y + s * dx + c * dy, rows[:, 3]], axis=1)
    return Primitives(
        kind=rows[:, 0].astype(np.int8),
        center=center,
        half_size=rows[:, 4:7].copy(),
        yaw=np.asarray(wrap(yaw), float),
        semantic=rows[:, 12].astype(np.uint8),
        instance=np.asarray(instance, np.int32),
        color=rows[:, 7:10].astype(np.float32),
        texture=rows[:, 10].astype(np.uint8),
        reflectivity=rows[:, 11].astype(np.float32),
    )


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


def _vehicle_solids(category: str, w: float, l: float, h: float, color) -> list[Solid]:
    """Solids of a vehicle filling its box: body and cabin boxes (one tall box plus a cab for buses and trucks)."""
    paint = dict(texture=Texture.VEHICLE, reflectivity=0.5)
    if category == "vehicle.car":
        return [
            solid(BOX, 0.0, 0.0, 0.0, 0.55 * h, l / 2, w / 2, color, **paint),
            solid(BOX, -0.05 * l, 0.0, 0.55 * h, h, 0.27 * l, 0.45 * w, color, **paint),
        ]
    if category == "vehicle.truck":
        return [
            solid(BOX, -0.14 * l, 0.0, 0.0, h, 0.36 * l, w / 2, color, **paint),
            solid(BOX, 0.375 * l, 0.0, 0.0, 0.82 * h, 0.125 * l, 0.48 * w, color, **paint),
        ]
    if category == "vehicle.bus.rigid":
        return [
            solid(BOX, 0.0, 0.0, 0.0, 0.93 * h, l / 2, w / 2, color, **paint),
            solid(BOX, -0.1 * l, 0.0, 0.93 * h, h, 0.2 * l, 0.35 * w, color, **paint),
        ]
    if category == "vehicle.trailer":
        return [
            solid(BOX, 0.0, 0.0, 0.9, h, l / 2, w / 2, color, **paint),
            solid(BOX, -0.3 * l, 0.0, 0.0, 0.9, 0.18 * l, 0.45 * w, (0.08, 0.08, 0.08), reflectivity=0.3),
        ]
    if category == "vehicle.construction":
        return [
            solid(BOX, -0.2 * l, 0.0, 0.0, 0.5 * h, 0.3 * l, w / 2, color, **paint),
            solid(BOX, -0.25 * l, 0.0, 0.5 * h, h, 0.17 * l, 0.33 * w, color, **paint),
            solid(BOX, 0.25 * l, 0.0, 0.35 * h, 0.8 * h, 0.18 * l, 0.12 * w, color, **paint),
            solid(BOX, 0.4 * l, 0.0, 0.0, 0.35 * h, 0.1 * l, 0.45 * w, (0.3, 0.3, 0.3), reflectivity=0.5),
        ]
    raise KeyError(category)


def vehicle(rng, category: str, attribute: str) -> Object:
    w, l, h = _draw_size(rng, category)
    solids = _vehicle_solids(category, w, l, h, _vehicle_color(rng))
    return Object(category, "vehicle", solids, (w, l, h), attribute)


def _rider(rng, dx: float, z0: float, top: float, radius: float) -> list[Solid]:
    """Torso cylinder and head of a person from height ``z0`` to ``top`` (m), ``dx`` along the object."""
    clothes = _jitter(rng, _CLOTHES[rng.integers(len(_CLOTHES))])
    skin = _jitter(rng, _SKIN[rng.integers(len(_SKIN))], 0.03)
    return [
        solid(CYLINDER, dx, 0.0, z0, top - 0.24, radius, radius, clothes, reflectivity=0.25),
        solid(ELLIPSOID, dx, 0.0, top - 0.24, top, 0.1, 0.09, skin, reflectivity=0.25),
    ]


def cycle(rng, category: str, ridden: bool) -> Object:
    """A bicycle or motorcycle; a rider (part of the same object, as in nuScenes' labels) when ``ridden``."""
    w, l, h = _draw_size(rng, category)
    motor = category == "vehicle.motorcycle"
    if not ridden:
        h *= 0.75
    frame = 0.62 * h if ridden else 0.9 * h
    color = _vehicle_color(rng) if motor else _jitter(rng, _CLOTHES[rng.integers(len(_CLOTHES))])
    body = 0.45 * w if motor else 0.2 * w
    solids = [
        solid(BOX, 0.0, 0.0, 0.0, frame, l / 2, body, color, texture=Texture.PLAIN, reflectivity=0.5),
        solid(BOX, 0.36 * l, 0.0, frame - 0.08, frame, 0.04, w / 2, (0.1, 0.1, 0.1), reflectivity=0.5),
    ]
    if ridden:
        solids += _rider(rng, -0.1 * l, frame, h, min(0.2, 0.4 * w))
    attribute = "cycle.with_rider" if ridden else "cycle.without_rider"
    return Object(category, "cycle", solids, (w, l, h), attribute)


def pedestrian(rng, moving: bool, category: str = "human.pedestrian.adult") -> Object:
    w, l, h = _draw_size(rng, category)
    radius = float(rng.uniform(0.2, 0.28))
    solids = _rider(rng, 0.0, 0.0, h, radius)
    if category == "human.pedestrian.construction_worker":
        solids[0] = solids[0][:7] + (*_HI_VIS, Texture.PLAIN, 0.9)  # retro-reflective vest
    attribute = "pedestrian.moving" if moving else "pedestrian.standing"
    return Object(category, "pedestrian", solids, (w, l, h), attribute)


def barrier(rng) -> Object:
    """A barrier; its 2.5 m width lies across its heading (nuScenes' convention), so yaw it across the road."""
    w, l, h = _draw_size(rng, "movable_object.barrier")
    color = ((0.8, 0.1, 0.08), (0.95, 0.45, 0.05), (0.9, 0.9, 0.88))[int(rng.integers(3))]
    shape = solid(BOX, 0.0, 0.0, 0.0, h, l / 2, w / 2, color, texture=Texture.STRIPES, reflectivity=0.9)
    return Object("movable_object.barrier", "barrier", [shape], (w, l, h))


def cone(rng) -> Object:
    h = float(rng.uniform(0.7, 1.0))
    shape = solid(CYLINDER, 0.0, 0.0, 0.0, h, 0.2, 0.2, (0.95, 0.4, 0.05), texture=Texture.STRIPES, reflectivity=0.9)
    return Object("movable_object.trafficcone", "cone", [shape], (0.41, 0.41, h))


def debris(rng) -> Object:
    l = float(rng.uniform(0.3, 1.2))
    w, h = float(rng.uniform(0.3, l)), float(rng.uniform(0.2, 0.8))
    color = _jitter(rng, ((0.45, 0.4, 0.35), (0.3, 0.28, 0.25), (0.6, 0.55, 0.45))[int(rng.integers(3))])
    return Object("movable_object.debris", "debris", [solid(BOX, 0.0, 0.0, 0.0, h, l / 2, w / 2, color)], (w, l, h))


def building(rng, style: Style, width: float, depth: float) -> Object:
    """A facade box ``width`` along its heading and ``depth`` across, sometimes with a plant room on the roof."""
    material = list(_MATERIALS)[rng.choice(4, p=np.array(style.materials) / sum(style.materials))]
    color, reflectivity = _MATERIALS[material]
    color = _jitter(rng, color, 0.06)
    height = float(rng.uniform(*style.height))
    solids = [solid(BOX, 0.0, 0.0, 0.0, height, width / 2, depth / 2, color, Texture.FACADE, reflectivity)]
    if rng.random() < 0.3:
        top = height + float(rng.uniform(2, 4))
        solids.append(solid(BOX, 0.0, 0.0, height, top, width / 6, depth / 6, _jitter(rng, (0.6, 0.6, 0.58))))
    return Object("static.manmade", "building", solids, ground=(TERRAIN,))


def wall(rng, length: float) -> Object:
    fence = rng.random() < 0.5
    thickness, height = (0.1, float(rng.uniform(1.2, 2.0))) if fence else (0.3, float(rng.uniform(1.0, 2.5)))
    color = _jitter(rng, (0.35, 0.36, 0.35) if fence else (0.68, 0.66, 0.6), 0.05)
    shape = solid(BOX, 0.0, 0.0, 0.0, height, length / 2, thickness / 2, color)
    return Object("static.manmade", "fence" if fence else "wall", [shape], ground=(TERRAIN, SIDEWALK))


_FURNITURE_GROUND = (SIDEWALK, TERRAIN, OTHER_FLAT)


def pole(rng, kind: str, toward_road: float) -> Object:
    """A pole; a sign plate, lamp arm or signal head on top. ``toward_road`` (+-1) is the local y of the road."""
    metal = (0.45, 0.46, 0.48)
    if kind == "street_light":
        r, h, arm = float(rng.uniform(0.12, 0.18)), float(rng.uniform(6, 9)), float(rng.uniform(1.5, 2.5))
        top = solid(BOX, 0.0, toward_road * arm / 2, h - 0.2, h, 0.12, arm / 2, metal, reflectivity=0.5)
    elif kind == "sign":
        r, h = 0.1, float(rng.uniform(2.2, 2.8))
        color = ((0.8, 0.1, 0.1), (0.1, 0.25, 0.7), (0.95, 0.95, 0.95), (0.95, 0.8, 0.1))[int(rng.integers(4))]
        top = solid(BOX, 0.0, 0.0, h, h + 0.7, 0.03, 0.35, color, reflectivity=0.9)
        h += 0.05
    elif kind == "traffic_light":
        r, h = 0.12, float(rng.uniform(3.0, 3.6))
        top = solid(BOX, 0.0, 0.0, h, h + 1.0, 0.18, 0.18, (0.08, 0.08, 0.08), reflectivity=0.5)
    else:
        r, h = float(rng.uniform(0.1, 0.2)), float(rng.uniform(3, 8))
        mast = solid(CYLINDER, 0.0, 0.0, 0.0, h, r, r, metal, reflectivity=0.5)
        return Object("static.manmade", "pole", [mast], ground=_FURNITURE_GROUND)
    mast = solid(CYLINDER, 0.0, 0.0, 0.0, h, r, r, metal, reflectivity=0.5)
    return Object("static.manmade", kind, [mast, top], ground=_FURNITURE_GROUND)


def tree(rng, street: bool) -> Object:
    """A trunk and an ellipsoid crown; street trees carry their crowns above the tallest vehicle."""
    radius = float(rng.uniform(1.2, 3.0 if street else 3.5))
    vertical = float(rng.uniform(1.2, 3.0))
    bottom = float(rng.uniform(_TALL_VEHICLE + 0.1, 5.5)) if street else float(rng.uniform(1.5, 3.5))
    trunk_r = float(rng.uniform(0.12, 0.25))
    bark = _jitter(rng, (0.3, 0.22, 0.15), 0.03)
    leaves = _jitter(rng, (0.2, 0.4, 0.14), 0.07)
    solids = [
        solid(CYLINDER, 0.0, 0.0, 0.0, bottom + vertical, trunk_r, trunk_r, bark, Texture.BARK, 0.15),
        solid(ELLIPSOID, 0.0, 0.0, bottom, bottom + 2 * vertical, radius, radius, leaves, Texture.FOLIAGE, 0.15),
    ]
    return Object("static.vegetation", "tree", solids, ground=(SIDEWALK, TERRAIN))


def hedge(rng) -> Object:
    length, width, height = float(rng.uniform(2, 8)), float(rng.uniform(0.8, 1.5)), float(rng.uniform(0.8, 1.8))
    kind = ELLIPSOID if rng.random() < 0.5 else BOX
    leaves = _jitter(rng, (0.18, 0.36, 0.12), 0.05)
    shape = solid(kind, 0.0, 0.0, 0.0, height, length / 2, width / 2, leaves, Texture.FOLIAGE, 0.15)
    return Object("static.vegetation", "hedge", [shape], ground=(TERRAIN,))


def bus_shelter(rng) -> Object:
    frame = _jitter(rng, (0.5, 0.52, 0.55))
    solids = [
        solid(BOX, 0.0, -0.6, 0.0, 2.5, 2.0, 0.05, (0.3, 0.38, 0.45), reflectivity=0.2),  # glass back wall
        solid(BOX, 0.0, 0.0, 2.5, 2.65, 2.1, 0.7, frame, reflectivity=0.5),  # roof
    ]
    return Object("static.manmade", "bus_shelter", solids, ground=(SIDEWALK, TERRAIN))


def bicycle_rack(rng, length: float) -> Object:
    shape = solid(BOX, 0.0, 0.0, 0.0, 0.8, length / 2, 0.05, (0.55, 0.56, 0.58), reflectivity=0.5)
    return Object("static_object.bicycle_rack", "rack", [shape], (0.1, length, 0.8), ground=(SIDEWALK, TERRAIN))
