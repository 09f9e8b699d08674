"""Speed of the synthetic world: seconds per key frame on one CPU core, stage by stage.

A key frame is six cameras at 800x450, one LiDAR sweep, the Occ3D labels and both visibility masks (the writing
of JPEGs, point files and labels included). A warm-up run compiles the numba kernels first. A second measurement
simulates a longer scene, where each key frame also carries its share of the nine sweeps between key frames and
mask_lidar accumulates the sweeps around it.

    python benchmarks/sim_frame.py [--repeats 3] [--out benchmarks/results/sim_frame.json]
"""

from __future__ import annotations

import os

# One core: set before numpy/numba/torch start their thread pools.
for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[variable] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from occkit.environment import environment_report  # noqa: E402
from occkit.sim.generate import SimConfig, simulate_dataset  # noqa: E402


def run_once(config: SimConfig) -> tuple[float, dict[str, float]]:
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        summary = simulate_dataset(config, Path(folder) / "data")
        return time.perf_counter() - start, summary["timings"]


def measure(config: SimConfig, repeats: int) -> dict:
    runs = [run_once(config) for _ in range(repeats)]
    totals = [total for total, _ in runs]
    best = min(range(repeats), key=lambda i: totals[i])
    per_frame = {stage: round(seconds / config.frames, 3) for stage, seconds in runs[best][1].items()}
    return {
        "frames": config.frames,
        "image_size": list(config.image_size),
        "seconds_per_key_frame_median": round(statistics.median(totals) / config.frames, 3),
        "seconds_per_key_frame_best": round(totals[best] / config.frames, 3),
        "stages_per_key_frame_best_run": per_frame,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/sim_frame.json"))
    args = parser.parse_args()
    torch.set_num_threads(1)

    single = SimConfig(scenes=1, frames=1, seed=7)
    run_once(single)  # warm-up: JIT compilation and caches
    results = {
        "single_key_frame": measure(single, args.repeats),
        "scene_of_4_key_frames": measure(SimConfig(scenes=1, frames=4, seed=7), max(1, args.repeats - 1)),
        "environment": {k: environment_report()[k] for k in ("occkit", "python", "packages", "devices")},
    }
    for name in ("single_key_frame", "scene_of_4_key_frames"):
        row = results[name]
        stages = ", ".join(f"{stage} {seconds:.3f}" for stage, seconds in row["stages_per_key_frame_best_run"].items())
        print(f"{name}: {row['seconds_per_key_frame_median']:.3f} s per key frame (median); stages: {stages}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
