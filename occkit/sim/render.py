"""Camera images of the synthetic world: one exact ray per pixel, simple shading, labels per pixel.

Each pixel's ray goes through its centre ``(u + 0.5, v + 0.5)`` (``K^-1``, then ``cam2global``) and stops at the
first solid or ground point (:func:`occkit.sim.raytrace.cast_rays`). Colours follow a small physically-flavoured
recipe computed in linear RGB and encoded to sRGB at the end:

* Lambertian surfaces, ``albedo * (ambient + diffuse * max(0, n . sun))``, the ambient term tinted by the sky;
* procedural textures in each solid's own frame (facade windows, foliage, stripes, vehicle glass, bark) and on the
  ground (asphalt, paving, grass and soil, road paint), from value noise on integer lattices hashed without any
  random state, so renders are byte-identical across runs and machines;
* a sky gradient from the horizon colour to the zenith colour for rays that hit nothing, and a light distance
  haze toward the horizon colour;
* a one-level dither of sensor noise, a hash of the pixel index and ``seed``.

Colours given by callers (albedos, sky colours) are sRGB-encoded values in ``[0, 1]``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from occkit.sim.primitives import BOX, CYLINDER, GroundMap, Primitives, Texture
from occkit.sim.raytrace import GROUND, NOTHING, Hits, cast_rays, hit_labels, solid_table
from occkit.sim.rig import CameraSpec

__all__ = ["CAMERA_RANGE", "CameraRender", "render_camera", "camera_rays", "shade"]

#: Farthest hit a camera reports (m): the ground then reaches to within a pixel of the geometric horizon.
CAMERA_RANGE = 1000.0

AMBIENT = 0.35
DIFFUSE = 0.8
# Share of the ambient light that takes the zenith's colour rather than white.
SKY_TINT = 0.25
# Distance (m) over which haze replaces 63% of a surface's colour with the horizon's.
HAZE_DISTANCE = 600.0
# Peak sensor noise, in 8-bit sRGB levels.
SENSOR_NOISE = 1.0

# Ground and texture colours (sRGB), indexed by the constants below; converted to linear once.
_ASPHALT, _OTHER_FLAT, _PAVING, _GRASS, _SOIL, _PAINT, _GLASS, _TYRE, _BAND, _WINDOW = range(10)
_PALETTE_SRGB = np.array(
    [
        (0.30, 0.30, 0.31),  # asphalt (driveable_surface)
        (0.47, 0.46, 0.44),  # concrete (other_flat)
        (0.64, 0.61, 0.57),  # paving (sidewalk)
        (0.33, 0.45, 0.19),  # grass (terrain)
        (0.46, 0.38, 0.26),  # soil (terrain)
        (0.92, 0.92, 0.90),  # road paint
        (0.10, 0.12, 0.15),  # vehicle glass
        (0.06, 0.06, 0.06),  # tyres and sills
        (0.93, 0.93, 0.93),  # white band of stripes
        (0.16, 0.19, 0.24),  # window glass
    ]
)
_SRGB_LUT_SIZE = 16384
# Texture codes as plain module constants, which compiled kernels read as literals.
_PLAIN, _FACADE, _FOLIAGE, _STRIPES, _VEHICLE, _BARK = (
    Texture.PLAIN,
    Texture.FACADE,
    Texture.FOLIAGE,
    Texture.STRIPES,
    Texture.VEHICLE,
    Texture.BARK,
)
_SUN_COLOUR = (1.0, 0.97, 0.92)
# Facade layout (m): window columns every 2.4 m, floors every 3 m, windows 1.2 m wide and 1.5 m tall from a
# 0.9 m sill, none closer than 0.6 m to a corner.
_WINDOW_PITCH, _WINDOW_WIDTH, _FLOOR_HEIGHT, _WINDOW_HEIGHT, _SILL, _CORNER = 2.4, 1.2, 3.0, 1.5, 0.9, 0.6


@dataclass
class CameraRender:
    """One camera's image and per-pixel ground truth.

    Attributes:
        image: ``(H, W, 3)`` uint8 sRGB.
        depth: ``(H, W)`` float32 camera z (m) of the surface seen; 0 for sky.
        semantic: ``(H, W)`` uint8 Occ3D class of the surface seen; 255 for sky.
        instance: ``(H, W)`` int32 instance id of the solid seen; -1 for ground and sky.
    """

    image: np.ndarray
    depth: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """Decode sRGB values in ``[0, 1]`` to linear RGB."""
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


@functools.cache
def _srgb_lut() -> np.ndarray:
    """``(_SRGB_LUT_SIZE,)`` float32 8-bit sRGB level of evenly spaced linear values in ``[0, 1]``."""
    c = np.linspace(0.0, 1.0, _SRGB_LUT_SIZE)
    encoded = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return (255.0 * encoded).astype(np.float32)


@functools.cache
def _palette() -> np.ndarray:
    return _srgb_to_linear(_PALETTE_SRGB)


@functools.lru_cache(maxsize=16)
def _camera_directions(camera: CameraSpec) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions ``(H * W, 3)`` in the camera frame (row-major pixels) and their z components."""
    u = np.arange(camera.width) + 0.5
    v = np.arange(camera.height) + 0.5
    uu, vv = np.meshgrid(u, v, indexing="xy")
    pixels = np.stack((uu, vv, np.ones_like(uu)), axis=-1)
    rays = pixels.reshape(-1, 3) @ np.linalg.inv(camera.K).T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rays.flags.writeable = False
    forward = rays[:, 2].copy()
    forward.flags.writeable = False
    return rays, forward


def camera_rays(camera: CameraSpec, ego2global: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays through the pixel centres of ``camera`` on the ego vehicle at ``ego2global``.

    Returns:
        origin: ``(3,)`` global camera centre.
        directions: ``(H * W, 3)`` global unit directions, pixels in row-major order (``v`` then ``u``).
        forward: ``(H * W,)`` camera z of each unit direction (depth = distance * forward).
    """
    cam2global = np.asarray(ego2global, np.float64) @ camera.cam2ego
    rays, forward = _camera_directions(camera)
    return cam2global[:3, 3].copy(), rays @ cam2global[:3, :3].T, forward


def render_camera(
    camera: CameraSpec,
    ego2global: np.ndarray,
    primitives: Primitives,
    ground: GroundMap | None,
    sun_direction: np.ndarray,
    sky_zenith: np.ndarray,
    sky_horizon: np.ndarray,
    seed: int,
) -> CameraRender:
    """Render one camera of the ego vehicle at ``ego2global`` (``(4, 4)``, ego to global).

    Args:
        camera: the camera's pose in ego and intrinsics.
        ego2global: ``(4, 4)`` pose of the ego vehicle.
        primitives, ground: the world at the camera's timestamp; ``ground=None`` leaves out the ground plane.
        sun_direction: ``(3,)`` global direction toward the sun (normalised here).
        sky_zenith, sky_horizon: ``(3,)`` sRGB sky colours straight up and at the horizon.
        seed: seed of the sensor noise.
    """
    origin, directions, forward = camera_rays(camera, ego2global)
    hits = cast_rays(origin, directions, CAMERA_RANGE, primitives, ground)
    semantic, instance, marking = hit_labels(hits, primitives, ground)
    image = shade(directions, hits, semantic, marking, primitives, sun_direction, sky_zenith, sky_horizon, seed)
    depth = np.where(hits.primitive != NOTHING, hits.distance * forward, 0.0).astype(np.float32)
    shape = (camera.height, camera.width)
    return CameraRender(
        image.reshape(*shape, 3), depth.reshape(shape), semantic.reshape(shape), instance.reshape(shape)
    )


def shade(
    directions: np.ndarray,
    hits: Hits,
    semantic: np.ndarray,
    marking: np.ndarray,
    primitives: Primitives,
    sun_direction: np.ndarray,
    sky_zenith: np.ndarray,
    sky_horizon: np.ndarray,
    seed: int,
) -> np.ndarray:
    """``(R, 3)`` uint8 sRGB colour of each ray from its hit, the hit's class and road paint flag (``hit_labels``)."""
    sun = np.asarray(sun_direction, np.float64)
    sun = sun / np.linalg.norm(sun)
    zenith, horizon = _srgb_to_linear(sky_zenith), _srgb_to_linear(sky_horizon)
    tint = zenith / max(float(zenith @ np.array([0.2126, 0.7152, 0.0722])), 1e-6)
    ambient = AMBIENT * ((1.0 - SKY_TINT) + SKY_TINT * tint)
    image = np.empty((len(hits), 3), np.uint8)
    _shade_kernel(
        np.ascontiguousarray(directions, np.float64), hits.distance, hits.primitive, hits.normal, hits.point,
        semantic, marking, np.ascontiguousarray(primitives.kind, np.int8), solid_table(primitives),
        _srgb_to_linear(primitives.color), np.ascontiguousarray(primitives.texture, np.uint8),
        np.ascontiguousarray(primitives.instance, np.int32), _palette(), sun, ambient,
        DIFFUSE * np.asarray(_SUN_COLOUR), zenith, horizon, np.int64(int(seed) & 0xFFFFFFFF), _srgb_lut(), image,
    )  # fmt: skip
    return image


# --------------------------------------------------------------------------- procedural noise
@njit(cache=True)
def _hash(a, b, c):
    """Uniform value in ``[0, 1)`` from three integers (a 32-bit integer hash; no random state)."""
    h = ((a * 73856093) ^ (b * 19349663) ^ (c * 83492791)) & 0xFFFFFFFF
    h = (((h >> 16) ^ h) * 0x45D9F3B) & 0xFFFFFFFF
    h = (((h >> 16) ^ h) * 0x45D9F3B) & 0xFFFFFFFF
    return ((h >> 16) ^ h) / 4294967296.0


@njit(cache=True)
def _smooth(t):
    return t * t * (3.0 - 2.0 * t)


@njit(cache=True)
def _value_noise(x, y, z, salt):
    """Smooth value noise in ``[0, 1)`` with unit lattice spacing: trilinear blend of hashed lattice values."""
    fx, fy, fz = math.floor(x), math.floor(y), math.floor(z)
    ix, iy, iz = int(fx), int(fy), int(fz) + salt * 7919
    tx, ty, tz = _smooth(x - fx), _smooth(y - fy), _smooth(z - fz)
    value = 0.0
    for cz in range(2):
        for cy in range(2):
            for cx in range(2):
                weight = (tx if cx else 1.0 - tx) * (ty if cy else 1.0 - ty) * (tz if cz else 1.0 - tz)
                value += weight * _hash(ix + cx, iy + cy, iz + cz)
    return value


# --------------------------------------------------------------------------- materials
@njit(cache=True)
def _ground_albedo(semantic, marking, x, y, distance, palette):
    """Linear albedo of the ground at ``(x, y)``; fine detail fades with distance, where it would only alias."""
    if marking:
        base = _PAINT
    elif semantic == 11:
        base = _ASPHALT
    elif semantic == 13:
        base = _PAVING
    elif semantic == 14:
        base = _GRASS
    else:
        base = _OTHER_FLAT
    r, g, b = palette[base, 0], palette[base, 1], palette[base, 2]
    if semantic == 14 and not marking:  # patches of soil in the grass
        mix = min(max(2.5 * (_value_noise(0.25 * x, 0.25 * y, 0.0, 1) - 0.35), 0.0), 1.0)
        r = r + mix * (palette[_SOIL, 0] - r)
        g = g + mix * (palette[_SOIL, 1] - g)
        b = b + mix * (palette[_SOIL, 2] - b)
    fine = max(0.0, 1.0 - distance / 40.0)
    shade = 0.85 + 0.3 * _value_noise(0.5 * x, 0.5 * y, 0.0, 2)
    shade += fine * 0.35 * (_value_noise(6.0 * x, 6.0 * y, 0.0, 3) - 0.5)
    if base == _PAVING:  # joints between 0.6 m slabs
        jx, jy = x / 0.6 - math.floor(x / 0.6), y / 0.6 - math.floor(y / 0.6)
        if fine > 0.0 and (jx < 0.04 or jy < 0.04):
            shade *= 1.0 - 0.35 * fine
    return r * shade, g * shade, b * shade


@njit(cache=True)
def _solid_albedo(p, x, y, z, n0, n1, kind, table, albedo, texture, instance, palette):
    """Linear albedo of solid ``p`` at its surface point ``(x, y, z)`` with world normal ``(n0, n1, ...)``."""
    r, g, b = albedo[p, 0], albedo[p, 1], albedo[p, 2]
    code = texture[p]
    if code == _PLAIN:
        return r, g, b
    # The point and the normal in the solid's frame (x along its heading, z up from its centre).
    cos, sin = table[p, 6], table[p, 7]
    rx, ry, lz = x - table[p, 0], y - table[p, 1], z - table[p, 2]
    lx, ly = cos * rx + sin * ry, -sin * rx + cos * ry
    nlx = cos * n0 + sin * n1
    hx, hy, hz = table[p, 3], table[p, 4], table[p, 5]
    # Horizontal coordinate along the face (m): across the heading on end faces, along it on side faces.
    if kind[p] == BOX:
        along, length = (ly + hy, 2.0 * hy) if abs(nlx) > 0.5 else (lx + hx, 2.0 * hx)
    else:
        along, length = (math.atan2(ly, lx) + math.pi) * hx, 2.0 * math.pi * hx
    height = lz + hz  # above the solid's base
    salt = instance[p]
    if code == _FACADE:
        column = math.floor(along / _WINDOW_PITCH)
        floor = math.floor(height / _FLOOR_HEIGHT)
        across = along - column * _WINDOW_PITCH - 0.5 * (_WINDOW_PITCH - _WINDOW_WIDTH)
        up = height - floor * _FLOOR_HEIGHT - _SILL
        inside_face = _CORNER < along < length - _CORNER and height < 2.0 * hz - 0.5
        if inside_face and 0.0 <= across < _WINDOW_WIDTH and 0.0 <= up < _WINDOW_HEIGHT and kind[p] != CYLINDER:
            glow = 0.6 + 0.9 * _hash(int(column), int(floor), salt)  # some windows reflect more sky than others
            return palette[_WINDOW, 0] * glow, palette[_WINDOW, 1] * glow, palette[_WINDOW, 2] * glow
        grime = 0.9 + 0.2 * _value_noise(0.7 * along, 0.7 * height, 0.0, salt)
        return r * grime, g * grime, b * grime
    if code == _FOLIAGE:
        leaves = 0.45 * _value_noise(3.0 * x, 3.0 * y, 3.0 * z, salt) + 0.55 * _value_noise(x, y, z, salt + 1)
        shade = 0.45 + 1.0 * leaves
        return r * shade, g * shade, b * shade
    if code == _STRIPES:
        if int(math.floor(2.5 * height / hz)) % 2 == 1:  # five bands over the height
            return palette[_BAND, 0], palette[_BAND, 1], palette[_BAND, 2]
        return r, g, b
    if code == _VEHICLE:
        f = lz / hz
        if f < -0.7:
            return palette[_TYRE, 0], palette[_TYRE, 1], palette[_TYRE, 2]
        if 0.2 < f < 0.85:  # a glass band round the upper body, below the roof
            return palette[_GLASS, 0], palette[_GLASS, 1], palette[_GLASS, 2]
        return r, g, b
    if code == _BARK:
        streak = 0.6 + 0.6 * _value_noise(4.0 * along, 0.8 * height, 0.0, salt)
        return r * streak, g * streak, b * streak
    return r, g, b


@njit(cache=True)
def _shade_kernel(directions, distance, primitive, normal, point, semantic, marking, kind, table, albedo, texture,
                  instance, palette, sun, ambient, sunlight, zenith, horizon, seed, lut, image):  # fmt: skip
    """Fill ``image`` (``(R, 3)`` uint8) with each ray's shaded, hazed, dithered sRGB colour."""
    scale = lut.shape[0] - 1
    for i in range(directions.shape[0]):
        dz = directions[i, 2]
        p = primitive[i]
        if p == NOTHING:
            t = math.sqrt(min(max(dz, 0.0), 1.0))
            r = horizon[0] + t * (zenith[0] - horizon[0])
            g = horizon[1] + t * (zenith[1] - horizon[1])
            b = horizon[2] + t * (zenith[2] - horizon[2])
        else:
            x, y, z = point[i, 0], point[i, 1], point[i, 2]
            n0, n1, n2 = normal[i, 0], normal[i, 1], normal[i, 2]
            if p == GROUND:
                r, g, b = _ground_albedo(semantic[i], marking[i], x, y, distance[i], palette)
            else:
                r, g, b = _solid_albedo(p, x, y, z, n0, n1, kind, table, albedo, texture, instance, palette)
            lit = max(0.0, n0 * sun[0] + n1 * sun[1] + n2 * sun[2])
            r *= ambient[0] + lit * sunlight[0]
            g *= ambient[1] + lit * sunlight[1]
            b *= ambient[2] + lit * sunlight[2]
            haze = 1.0 - math.exp(-distance[i] / HAZE_DISTANCE)
            r += haze * (horizon[0] - r)
            g += haze * (horizon[1] - g)
            b += haze * (horizon[2] - b)
        dither = SENSOR_NOISE * (2.0 * _hash(i, seed, 17) - 1.0)
        image[i, 0] = _encode(r, dither, lut, scale)
        image[i, 1] = _encode(g, dither, lut, scale)
        image[i, 2] = _encode(b, dither, lut, scale)


@njit(cache=True)
def _encode(c, dither, lut, scale):
    """8-bit sRGB level of linear value ``c`` plus ``dither`` levels."""
    level = lut[int(min(max(c, 0.0), 1.0) * scale + 0.5)] + dither
    return np.uint8(min(max(level + 0.5, 0.0), 255.0))
