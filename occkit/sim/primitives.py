"""The synthetic world's geometry at one instant: analytic solids on a flat, semantically painted ground.

Everything is in the **global** frame (x east, y north, z up, metres) with the ground plane at ``z = 0``.
Solids are structure-of-arrays numpy tables so that numba kernels (ray casting, voxel labelling) read them
without Python objects. Three kinds cover the world: yawed boxes (vehicles, buildings, walls, barriers,
signs), upright cylinders (poles, trunks, cones, pedestrians' bodies) and yawed ellipsoids (tree crowns, hedges).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BOX", "CYLINDER", "ELLIPSOID", "Texture", "Primitives", "GroundMap"]

#: Primitive kinds. ``half_size`` means: box (half length along the heading, half width, half height);
#: cylinder (radius, radius, half height); ellipsoid (semi-axes along the heading, across it, vertical).
BOX, CYLINDER, ELLIPSOID = 0, 1, 2


class Texture:
    """Procedural surface patterns, applied by the renderer on top of a primitive's albedo."""

    PLAIN = 0
    FACADE = 1  # building walls with a grid of darker windows
    FOLIAGE = 2  # high-frequency green noise
    STRIPES = 3  # alternating bands (barriers, traffic cones)
    VEHICLE = 4  # darker windows in the upper part of the body
    BARK = 5


@dataclass
class Primitives:
    """``P`` solids of the world at one instant (global frame).

    Attributes:
        kind: ``(P,)`` int8, one of ``BOX``, ``CYLINDER``, ``ELLIPSOID``.
        center: ``(P, 3)`` float64 centre of the solid (for a box standing on the ground, ``z = half height``).
        half_size: ``(P, 3)`` float64, see the kinds above.
        yaw: ``(P,)`` float64 heading in radians about +z (0 = along +x).
        semantic: ``(P,)`` uint8 Occ3D class id 0..16.
        instance: ``(P,)`` int32 object id; several solids of one object (a tree's trunk and crown) share it.
        color: ``(P, 3)`` float32 albedo in ``[0, 1]``.
        texture: ``(P,)`` uint8 :class:`Texture` code.
        reflectivity: ``(P,)`` float32 LiDAR reflectivity in ``[0, 1]``.
    """

    kind: np.ndarray
    center: np.ndarray
    half_size: np.ndarray
    yaw: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    color: np.ndarray
    texture: np.ndarray
    reflectivity: np.ndarray

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    @staticmethod
    def empty() -> Primitives:
        return Primitives(
            kind=np.zeros(0, np.int8),
            center=np.zeros((0, 3)),
            half_size=np.zeros((0, 3)),
            yaw=np.zeros(0),
            semantic=np.zeros(0, np.uint8),
            instance=np.zeros(0, np.int32),
            color=np.zeros((0, 3), np.float32),
            texture=np.zeros(0, np.uint8),
            reflectivity=np.zeros(0, np.float32),
        )

    @staticmethod
    def concatenate(parts: list[Primitives]) -> Primitives:
        if not parts:
            return Primitives.empty()
        return Primitives(
            **{name: np.concatenate([getattr(p, name) for p in parts]) for name in Primitives.__dataclass_fields__}
        )

    def select(self, mask: np.ndarray) -> Primitives:
        """The solids where the ``(P,)`` boolean ``mask`` (or index array) selects."""
        return Primitives(**{name: getattr(self, name)[mask] for name in Primitives.__dataclass_fields__})

    def radius_xy(self) -> np.ndarray:
        """``(P,)`` radius of a vertical cylinder around each solid's centre that contains it (for culling)."""
        return np.hypot(self.half_size[:, 0], self.half_size[:, 1])


@dataclass
class GroundMap:
    """The ground plane ``z = 0`` painted with flat classes, as a raster in the global frame.

    Cell ``[i, j]`` covers ``x in [origin[0] + i * resolution, ...)`` and ``y in [origin[1] + j * resolution, ...)``
    (x-major, like Occ3D's ``(X, Y)``). Outside the raster the ground is terrain.

    Attributes:
        semantics: ``(NX, NY)`` uint8 Occ3D flat classes: 11 driveable_surface, 12 other_flat, 13 sidewalk, 14 terrain.
        markings: ``(NX, NY)`` bool, white road paint (lane lines, stop lines, crossings) on driveable surface.
        origin: ``(2,)`` float64 global ``(x, y)`` of the raster's lower corner.
        resolution: cell size in metres.
    """

    semantics: np.ndarray
    markings: np.ndarray
    origin: np.ndarray
    resolution: float

    def lookup(self, xy: np.ndarray) -> np.ndarray:
        """``(N,)`` uint8 flat class under global points ``(N, 2)``; terrain outside the raster."""
        cells = np.floor((xy - self.origin) / self.resolution).astype(np.int64)
        nx, ny = self.semantics.shape
        inside = (cells[:, 0] >= 0) & (cells[:, 0] < nx) & (cells[:, 1] >= 0) & (cells[:, 1] < ny)
        out = np.full(xy.shape[0], 14, np.uint8)
        out[inside] = self.semantics[cells[inside, 0], cells[inside, 1]]
        return out
