"""Per-frame time of RayIoU (SparseOcc protocol) on the golden Occ3D frames, projected to the 6,019 val frames.

Each pass runs :func:`occkit.metrics.rayiou` over the 20 golden frames (8 origins x 14040 rays, prediction and
ground truth), repeated after a warm-up pass that compiles the kernel, on all cores numba is given (2 on the
reference machine). Loading the frames is not timed.

    python benchmarks/rayiou_speed.py [--golden DIR] [--repeats 10] [--out benchmarks/results/rayiou_speed.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numba
import numpy as np

from occkit.machine import host
from occkit.metrics.rayiou import rayiou

VAL_FRAMES = 6019
TARGET_PER_FRAME_S = 0.030
TARGET_TOTAL_S = 300.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--golden", type=Path, default=Path(__file__).resolve().parents[1] / "tests" / "golden" / "occ3d_metrics"
    )
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "rayiou_speed.json")
    args = parser.parse_args()

    frames = np.load(args.golden / "all_frames.npz")
    lidar = np.load(args.golden / "lidar_origins.npz")
    gts, preds = frames["semantics"], frames["pred"]
    origins = [lidar["origins"][i, : lidar["n_origins"][i]] for i in range(len(gts))]

    start = time.perf_counter()
    rayiou(gts[:1], preds[:1], origins[:1])
    warmup_s = time.perf_counter() - start

    per_frame = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        result = rayiou(gts, preds, origins)
        per_frame.append((time.perf_counter() - start) / len(gts))
    median = statistics.median(per_frame)
    machine = host()
    report = {
        "machine": {
            "cpu": machine["cpu"],
            "cores": machine["cpu_count"],
            "numba_threads": numba.get_num_threads(),
            "python": machine["python"],
            "numpy": np.__version__,
            "numba": numba.__version__,
        },
        "frames": len(gts),
        "origins_per_frame": [len(o) for o in origins],
        "repeats": args.repeats,
        "warmup_first_frame_s": round(warmup_s, 4),
        "per_frame_s": {
            "median": round(median, 5),
            "best": round(min(per_frame), 5),
            "worst": round(max(per_frame), 5),
        },
        "projected_val_frames": VAL_FRAMES,
        "projected_total_s": round(median * VAL_FRAMES, 1),
        "targets": {"per_frame_s": TARGET_PER_FRAME_S, "total_s": TARGET_TOTAL_S},
        "meets_targets": bool(median <= TARGET_PER_FRAME_S and median * VAL_FRAMES <= TARGET_TOTAL_S),
        "rayiou": result["rayiou"],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
