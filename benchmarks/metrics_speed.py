"""Speed of occkit's confusion matrix against the official Occ3D ``Metric_mIoU`` algorithm, on the golden frames.

The baseline re-implements what the CVPR 2023 challenge's ``add_batch`` does per frame: boolean-mask selection of
GT and prediction, the ``0 <= gt < K`` filter, the labelled / correct counts, then
``np.bincount(K * gt + pred, minlength=K**2)``. Both run on the 20 frames of ``tests/golden/occ3d_metrics``
(200 x 200 x 16 uint8), one thread each; the median per frame is reported for each mask setting.

    python benchmarks/metrics_speed.py [--golden DIR] [--repeats 5] [--out benchmarks/results/metrics_speed.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from occkit.machine import host
from occkit.metrics.confusion import confusion_matrix

GOLDEN = Path(__file__).resolve().parents[1] / "tests" / "golden" / "occ3d_metrics"
K = 18


def official_confusion(gt: np.ndarray, pred: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """The reference's per-frame work: mask selection, range filter, counts, one int64 bincount."""
    if mask is not None:
        gt, pred = gt[mask], pred[mask]
    keep = (gt >= 0) & (gt < K)
    labelled = np.sum(keep)  # noqa: F841 - the reference computes it on every frame, so the baseline does too
    correct = np.sum(pred[keep] == gt[keep])  # noqa: F841
    counts = np.bincount(K * gt[keep].astype(int) + pred[keep].astype(int), minlength=K**2)
    return counts.reshape(K, K)


def median_ms(fn, frames, repeats: int) -> float:
    """Median wall time of ``fn(*frame)`` over every frame and repeat, in milliseconds."""
    times = []
    for _ in range(repeats):
        for frame in frames:
            start = time.perf_counter()
            fn(*frame)
            times.append(time.perf_counter() - start)
    return float(np.median(times) * 1e3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--golden", type=Path, default=GOLDEN)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "metrics_speed.json")
    args = parser.parse_args()

    data = np.load(args.golden / "all_frames.npz")
    gt, pred = data["semantics"], data["pred"]
    masks = {
        "camera_mask": data["mask_camera"].astype(bool),
        "lidar_mask": data["mask_lidar"].astype(bool),
        "no_mask": None,
    }
    # Compile (or load the cached kernels) before timing.
    confusion_matrix(gt[0], pred[0], masks["camera_mask"][0])
    confusion_matrix(gt[0], pred[0])

    results = {}
    for mode, mask in masks.items():
        frames = [(gt[i], pred[i], None if mask is None else mask[i]) for i in range(len(gt))]
        for frame in frames:
            if not np.array_equal(official_confusion(*frame), confusion_matrix(*frame)):
                raise SystemExit(f"{mode}: occkit and the official algorithm disagree")
        official = median_ms(official_confusion, frames, args.repeats)
        occkit = median_ms(confusion_matrix, frames, args.repeats)
        results[mode] = {"official_ms": official, "occkit_ms": occkit, "speedup": official / occkit}
        print(
            f"{mode:12s} official {official:7.3f} ms/frame   occkit {occkit:7.3f} ms/frame   x{official / occkit:5.1f}"
        )

    machine = host()
    report = {
        "frames": len(gt),
        "frame_shape": list(gt.shape[1:]),
        "repeats": args.repeats,
        "statistic": "median seconds per frame x 1e3, one thread",
        "machine": {"processor": machine["cpu"], "python": machine["python"]},
        "modes": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
