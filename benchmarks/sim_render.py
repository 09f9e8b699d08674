"""Speed of the simulator's sensors on one CPU core: six cameras at 800x450 and one LiDAR sweep.

The scene is synthetic and self-contained: a street crossing on a painted ground map, lined with buildings, trees,
poles and hedges, with cars, pedestrians, barriers and cones, about 400 solids within 80 m of the ego vehicle.
Each stage is timed over a few repetitions after a warm-up call that compiles the numba kernels:

* camera rays: pixel rays and the ray cast of the six cameras;
* shading: labels and colours of the six cameras' hits;
* lidar: one full sweep (ray cast, labels, intensities);
* render_camera: the six cameras end to end (rays + shading + depth).

    python benchmarks/sim_render.py [--repeats 5] [--out benchmarks/results/sim_render.json] [--images DIR]
"""

from __future__ import annotations

import os

# One core: set before numpy/numba/torch start their thread pools.
for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[variable] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from occkit.sim.lidar import scan_lidar  # noqa: E402
from occkit.sim.primitives import BOX, CYLINDER, ELLIPSOID, GroundMap, Primitives, Texture  # noqa: E402
from occkit.sim.raytrace import cast_rays, hit_labels  # noqa: E402
from occkit.sim.render import CAMERA_RANGE, camera_rays, render_camera, shade  # noqa: E402
from occkit.sim.rig import LIDAR_TOP, camera_rig  # noqa: E402

SUN = np.array([0.45, -0.35, 0.82])
SKY_ZENITH = np.array([0.36, 0.55, 0.86])
SKY_HORIZON = np.array([0.78, 0.85, 0.93])


class _SceneBuilder:
    """Collects solids row by row; :meth:`build` stacks them into :class:`Primitives`."""

    def __init__(self) -> None:
        self.rows: list[tuple] = []

    def add(self, kind, center, half_size, yaw, semantic, color, texture, reflectivity, instance=None) -> int:
        instance = len(self.rows) if instance is None else instance
        self.rows.append((kind, center, half_size, yaw, semantic, instance, color, texture, reflectivity))
        return instance

    def build(self) -> Primitives:
        columns = list(zip(*self.rows, strict=True))
        dtypes = (np.int8, np.float64, np.float64, np.float64, np.uint8, np.int32, np.float32, np.uint8, np.float32)
        return Primitives(*(np.asarray(column, dtype) for column, dtype in zip(columns, dtypes, strict=True)))


def street_ground(half_extent: float = 100.0, resolution: float = 0.2) -> GroundMap:
    """A road along x (|y| < 7 m) crossed by one along y (x in [30, 44]), sidewalks, lawns; lane and zebra paint."""
    n = int(2 * half_extent / resolution)
    centres = -half_extent + (np.arange(n) + 0.5) * resolution
    x, y = np.meshgrid(centres, centres, indexing="ij")
    road = (np.abs(y) < 7.0) | ((x > 30.0) & (x < 44.0))
    sidewalk = ~road & ((np.abs(y) < 11.0) | ((x > 26.0) & (x < 48.0)))
    semantics = np.full((n, n), 14, np.uint8)
    semantics[(np.abs(y) > 40.0) & (x < 0.0)] = 12
    semantics[sidewalk] = 13
    semantics[road] = 11
    along_x = (np.abs(y) < 7.0) & ~((x > 30.0) & (x < 44.0))
    centre_line = along_x & (np.abs(y) < 0.12) & (np.mod(x, 9.0) < 3.0)
    edge_lines = along_x & (np.abs(np.abs(y) - 6.6) < 0.12)
    zebra = (x > 26.0) & (x < 30.0) & (np.abs(y) < 7.0) & (np.mod(y, 1.0) < 0.5)
    return GroundMap(semantics, centre_line | edge_lines | zebra, np.array([-half_extent, -half_extent]), resolution)


def street_scene(seed: int = 0) -> tuple[Primitives, GroundMap]:
    """About 400 solids along the streets of :func:`street_ground`, within 80 m of the origin."""
    rng = np.random.default_rng(seed)
    scene = _SceneBuilder()
    facade_colours = [(0.72, 0.66, 0.58), (0.62, 0.42, 0.34), (0.78, 0.78, 0.76), (0.55, 0.57, 0.6)]
    for side in (-1.0, 1.0):
        x = -80.0
        while x < 80.0:  # two rows of buildings behind the sidewalks
            length = rng.uniform(8.0, 18.0)
            for row_offset in (0.0, 16.0):
                depth, height = rng.uniform(5.0, 8.0), rng.uniform(3.5, 10.0) * (1.0 + row_offset / 32.0)
                y = side * (12.5 + row_offset + depth)
                colour = facade_colours[rng.integers(len(facade_colours))]
                if not 26.0 < x + length / 2 < 48.0 or row_offset > 0.0:
                    scene.add(BOX, (x + length / 2, y, height), (length / 2 - 0.4, depth, height), 0.0, 15,
                              colour, Texture.FACADE, 0.3)  # fmt: skip
            x += length
        for x in np.arange(-78.0, 80.0, 9.0):  # trees and poles on the sidewalks
            tree = scene.add(CYLINDER, (x, side * 9.8, 1.5), (0.18, 0.18, 1.5), 0.0, 16, (0.35, 0.26, 0.18),
                             Texture.BARK, 0.2)  # fmt: skip
            scene.add(ELLIPSOID, (x, side * 9.8, 4.2), (rng.uniform(1.6, 2.4), rng.uniform(1.6, 2.4), 1.8),
                      rng.uniform(0, np.pi), 16, (0.22, 0.42, 0.16), Texture.FOLIAGE, 0.15, tree)  # fmt: skip
            scene.add(CYLINDER, (x + 4.5, side * 7.6, 3.0), (0.08, 0.08, 3.0), 0.0, 15, (0.5, 0.5, 0.52),
                      Texture.PLAIN, 0.5)  # fmt: skip
        for x in np.arange(-76.0, 80.0, 13.0):  # hedges in the lawns between buildings
            scene.add(ELLIPSOID, (x, side * 11.6, 0.5), (2.5, 0.45, 0.6), 0.0, 16, (0.18, 0.36, 0.14),
                      Texture.FOLIAGE, 0.15)  # fmt: skip
    car_colours = [(0.8, 0.1, 0.1), (0.1, 0.2, 0.6), (0.85, 0.85, 0.85), (0.1, 0.1, 0.1), (0.5, 0.5, 0.55)]
    for lane_y, heading in ((-3.3, 0.0), (3.3, np.pi), (-5.6, 0.0), (5.6, np.pi)):
        for x in np.arange(-75.0, 80.0, 8.5):
            if rng.random() < 0.55 and not 24.0 < x < 50.0:
                length = rng.uniform(2.0, 2.5)
                scene.add(BOX, (x, lane_y + rng.uniform(-0.3, 0.3), 0.78), (length, 0.95, 0.78),
                          heading + rng.uniform(-0.08, 0.08), 4, car_colours[rng.integers(len(car_colours))],
                          Texture.VEHICLE, 0.5)  # fmt: skip
    for x in np.arange(-70.0, 80.0, 6.0):  # pedestrians on the sidewalks
        side = 1.0 if rng.random() < 0.5 else -1.0
        clothes = tuple(rng.uniform(0.1, 0.6, 3))
        scene.add(CYLINDER, (x + rng.uniform(-2, 2), side * rng.uniform(7.5, 10.5), 0.87), (0.25, 0.25, 0.87), 0.0, 7,
                  clothes, Texture.PLAIN, 0.3)  # fmt: skip
    for i in range(10):  # road works: barriers and cones on the crossing road
        scene.add(BOX, (33.0 + 0.9 * (i % 5), 9.0 + 8.0 * (i // 5), 0.5), (0.9, 0.15, 0.5), 0.0, 1,
                  (0.85, 0.1, 0.1), Texture.STRIPES, 0.6)  # fmt: skip
        scene.add(CYLINDER, (40.0, -12.0 - 1.5 * i, 0.35), (0.15, 0.15, 0.35), 0.0, 8, (0.95, 0.45, 0.05),
                  Texture.STRIPES, 0.7)  # fmt: skip
    while len(scene.rows) < 420:  # clutter: random small solids in the lawns and the other_flat lot
        x, y = rng.uniform(-78.0, 78.0), rng.choice((-1.0, 1.0)) * rng.uniform(40.0, 75.0)
        kind = int(rng.integers(3))
        half = (rng.uniform(0.3, 2.0), rng.uniform(0.3, 2.0), rng.uniform(0.3, 1.5))
        if kind == CYLINDER:
            half = (half[0], half[0], half[2])
        scene.add(kind, (x, y, half[2]), half, rng.uniform(0, np.pi), 0, tuple(rng.uniform(0.2, 0.8, 3)),
                  Texture.PLAIN, 0.3)  # fmt: skip
    return scene.build(), street_ground()


def _ego_pose() -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = (2.0, -3.3, 0.0)
    return pose


def _time(function, repeats: int) -> list[float]:
    function()  # warm-up: JIT compilation (or a cache load) and first-touch allocations
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        seconds.append(time.perf_counter() - start)
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/sim_render.json"))
    parser.add_argument("--images", type=Path, default=None, help="also write the six camera images here (PNG)")
    args = parser.parse_args()

    primitives, ground = street_scene()
    ego2global = _ego_pose()
    cameras = camera_rig(800, 450)
    sky = (SUN, SKY_ZENITH, SKY_HORIZON)
    hits_of = {}

    def camera_casts():
        for camera in cameras:
            origin, directions, _ = camera_rays(camera, ego2global)
            hits_of[camera.name] = (directions, cast_rays(origin, directions, CAMERA_RANGE, primitives, ground))

    def shading():
        for directions, hits in hits_of.values():
            semantic, _, marking = hit_labels(hits, primitives, ground)
            shade(directions, hits, semantic, marking, primitives, *sky, 0)

    def lidar():
        scan_lidar(LIDAR_TOP, ego2global, primitives, ground, 0)

    def cameras_end_to_end():
        return [render_camera(camera, ego2global, primitives, ground, *sky, 0) for camera in cameras]

    stages = {
        "camera_rays": _time(camera_casts, args.repeats),
        "shading": _time(shading, args.repeats),
        "lidar": _time(lidar, args.repeats),
        "render_camera_x6": _time(cameras_end_to_end, args.repeats),
    }
    near = np.hypot(*(primitives.center[:, :2] - ego2global[:2, 3]).T) < 80.0
    scan = scan_lidar(LIDAR_TOP, ego2global, primitives, ground, 0)
    results = {
        "scene": {"primitives": len(primitives), "within_80m": int(near.sum()), "lidar_points": len(scan)},
        "rays": {"cameras": 6 * 800 * 450, "lidar": LIDAR_TOP.azimuth_steps * len(LIDAR_TOP.elevations_deg)},
        "seconds_median": {name: round(statistics.median(s), 4) for name, s in stages.items()},
        "seconds_best": {name: round(min(s), 4) for name, s in stages.items()},
    }
    total = sum(results["seconds_median"][name] for name in ("camera_rays", "shading", "lidar"))
    results["seconds_median"]["total_cameras_and_lidar"] = round(total, 4)
    print(f"{'stage':<26}{'median s':>10}{'best s':>10}")
    for name in stages:
        print(f"{name:<26}{results['seconds_median'][name]:>10.4f}{results['seconds_best'][name]:>10.4f}")
    print(f"{'total (rays+shading+lidar)':<26}{total:>10.4f}")
    print(f"scene: {results['scene']}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out}")
    if args.images is not None:
        from PIL import Image

        args.images.mkdir(parents=True, exist_ok=True)
        for camera, render in zip(cameras, cameras_end_to_end(), strict=True):
            Image.fromarray(render.image).save(args.images / f"{camera.name}.png")
        print(f"wrote camera images to {args.images}")


if __name__ == "__main__":
    main()
