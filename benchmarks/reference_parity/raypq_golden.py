"""RayPQ goldens from SparseOcc's own ``Metric_RayPQ`` (``loaders/ray_pq.py``) on seeded ray-level frames.

    PYTHONPATH=MMSITE python benchmarks/reference_parity/raypq_golden.py --reference PATH/TO/SparseOcc \\
        [--out tests/golden/reference_parity/raypq.json]

``MMSITE`` holds ``prettytable`` (the reference prints its table with it). The rays of a frame are what
``main_raypq`` hands the metric after its ray casting: the class, instance id and depth error of each ray whose
ground truth is not free. The caster is occkit's, checked bit for bit against SparseOcc's elsewhere
(``tests/golden/rayiou``); what this golden pins down is the panoptic counting. :func:`frames` makes the frames
from a seed with every case the counting distinguishes: objects of thing classes split or merged by the prediction,
stuff classes, an instance whose rays carry two classes, thing rays outside any instance, segments under the
10-ray floor, and depth errors on both sides of each threshold. The test regenerates the same frames and compares
occkit's counts and scores with the reference's.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from data_side import pinned_checkout  # noqa: E402 - beside this script

REPOSITORY = "MCG-NJU/SparseOcc"
PINNED_COMMIT = "af4d9df83bfd1b82c2b095fca793ff7ba49d5e9f"
OCC_CLASSES = ["others", "barrier", "bicycle", "bus", "car", "construction_vehicle", "motorcycle", "pedestrian",
               "traffic_cone", "trailer", "truck", "driveable_surface", "other_flat", "sidewalk", "terrain",
               "manmade", "vegetation", "free"]  # fmt: skip
SEEDS = (0, 1, 2, 3)


def frames(seed: int) -> dict[str, np.ndarray]:
    """One frame's rays: ``sem_pred``, ``sem_gt``, ``inst_pred``, ``inst_gt`` (int32) and ``l1_error`` (float32)."""
    rng = np.random.default_rng(seed)
    rays = 4000
    things = [2, 3, 4, 5, 6, 7, 9, 10]
    stuff = [0, 1, 8, 11, 12, 13, 14, 15, 16]
    sem_gt = np.empty(rays, dtype=np.int32)
    inst_gt = np.zeros(rays, dtype=np.int32)
    position, instance = 0, 1
    while position < rays:
        length = int(rng.integers(3, 160))
        end = min(rays, position + length)
        if rng.random() < 0.55:  # an object of a thing class
            sem_gt[position:end] = rng.choice(things)
            inst_gt[position:end] = instance if rng.random() < 0.9 else 0  # now and then thing rays with no instance
            instance += 1
        else:
            sem_gt[position:end] = rng.choice(stuff)
        position = end
    instances = np.unique(inst_gt[inst_gt > 0])
    if instances.size:  # an instance whose rays carry two classes
        rays_of = np.flatnonzero(inst_gt == instances[0])
        sem_gt[rays_of[: len(rays_of) // 2]] = things[0] if sem_gt[rays_of[0]] != things[0] else things[1]
    # The prediction: mostly the ground truth's class, its instances renumbered, some split, some merged, noise.
    sem_pred = sem_gt.copy()
    flip = rng.random(rays) < 0.12
    sem_pred[flip] = rng.integers(0, 17, int(flip.sum()))
    inst_pred = np.where(inst_gt > 0, inst_gt * 3 + 7, 0).astype(np.int32)
    split = rng.random(rays) < 0.08
    inst_pred[split & (inst_pred > 0)] += 1
    merged = np.isin(inst_gt, rng.choice(np.arange(1, instance), size=max(1, instance // 6)))
    inst_pred[merged] = 5
    near = rng.random(rays) < 0.75  # most rays stop close to the truth, the others anywhere within a few metres
    l1_error = np.where(near, np.abs(rng.normal(0.0, 0.4, rays)), np.abs(rng.normal(0.0, 3.0, rays)))
    l1_error = l1_error.astype(np.float32)
    l1_error[rng.random(rays) < 0.05] = np.float32(2.0)  # exactly on a threshold: not closer than it
    return {"sem_pred": sem_pred, "sem_gt": sem_gt, "inst_pred": inst_pred, "inst_gt": inst_gt, "l1_error": l1_error}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path, required=True, help=f"a checkout of {REPOSITORY}")
    parser.add_argument("--out", type=Path, default=Path("tests/golden/reference_parity/raypq.json"))
    args = parser.parse_args()
    commit = pinned_checkout(args.reference, REPOSITORY, PINNED_COMMIT)
    spec = importlib.util.spec_from_file_location("ray_pq", args.reference / "loaders" / "ray_pq.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    metric = module.Metric_RayPQ(occ_class_names=OCC_CLASSES, num_classes=len(OCC_CLASSES), thresholds=[1, 2, 4])
    for seed in SEEDS:
        rays = frames(seed)
        metric.add_batch(rays["sem_pred"], rays["sem_gt"], rays["inst_pred"], rays["inst_gt"], rays["l1_error"])
    result = metric.count_pq()
    golden = {
        "repository": REPOSITORY, "commit": commit, "file": "loaders/ray_pq.py", "seeds": list(SEEDS),
        "counts": {"tp": metric.pan_tp.tolist(), "iou": metric.pan_iou.tolist(), "fp": metric.pan_fp.tolist(),
                   "fn": metric.pan_fn.tolist()},
        "result": {key: float(value) for key, value in result.items()},
    }  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(golden, indent=1) + "\n")
    print(f"wrote RayPQ {golden['result']['RayPQ']:.6f} of {REPOSITORY}@{commit[:12]} to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
