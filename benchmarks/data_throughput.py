"""Throughput of the data pipeline at the paper setting: six 256x704 crops of 1600x900 JPEGs, 10 LiDAR sweeps, labels.

Simulates a small dataset at nuScenes resolution (once; kept in --data), then measures samples/s through a
``torch.utils.data.DataLoader`` with the given number of workers and training augmentation, and where the time goes
in one process (images, points, boxes, labels).

    python benchmarks/data_throughput.py [--workers 2] [--samples 48] [--out benchmarks/results/data_throughput.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from occkit.data.collate import collate
from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.sim.generate import SimConfig, simulate_dataset


def stage_times(dataset: OccupancyDataset, samples: int) -> dict[str, float]:
    """Mean seconds per sample of each loading stage, in this process."""
    rng = np.random.default_rng(0)
    totals = {"cameras": 0.0, "points": 0.0, "boxes": 0.0, "occupancy": 0.0}
    for index in range(samples):
        record = dataset.records[index % len(dataset)]
        sample = dataset._load(record, rng)  # warm caches, then time each stage on the same record
        stages = (
            ("cameras", dataset._load_cameras, (record, sample, rng)),
            ("points", dataset._load_points, (record, sample, rng)),
            ("boxes", dataset._load_boxes, (record, sample)),
            ("occupancy", dataset._load_occupancy, (record, sample, sample.occ_aug.double())),
        )
        for stage, load, arguments in stages:
            start = time.perf_counter()
            load(*arguments)
            totals[stage] += time.perf_counter() - start
    return {stage: round(seconds / samples, 4) for stage, seconds in totals.items()}


def loader_throughput(dataset: OccupancyDataset, workers: int, samples: int, batch_size: int) -> float:
    loader = torch.utils.data.DataLoader(
        dataset,
        batch_size=batch_size,
        shuffle=True,
        num_workers=workers,
        collate_fn=collate,
        persistent_workers=False,
        generator=torch.Generator().manual_seed(0),
    )
    seen, start = 0, None
    for batch in loader:
        if start is None:  # the first batch pays for starting the workers
            start = time.perf_counter()
            continue
        seen += len(batch)
        if seen >= samples:
            break
    return seen / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/synth-1600x900"))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--samples", type=int, default=48)
    parser.add_argument("--batch-size", type=int, default=4)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/data_throughput.json"))
    args = parser.parse_args()

    if not (args.data / "v1.0-synth").is_dir():
        print(f"simulating {args.data} at 1600x900 (once)")
        simulate_dataset(SimConfig(scenes=2, frames=12, seed=11, image_size=(1600, 900)), args.data, workers=2)
    config = DatasetConfig(root=str(args.data), split="all", sweeps=9, augment=True)
    dataset = OccupancyDataset(config)
    stages = stage_times(dataset, 8)
    rate = loader_throughput(dataset, args.workers, args.samples, args.batch_size)
    report = {
        "setting": "6 cameras 1600x900 JPEG -> 256x704, key + 9 sweeps, Occ3D labels, boxes, train augmentation",
        "workers": args.workers,
        "batch_size": args.batch_size,
        "samples_per_second": round(rate, 2),
        "seconds_per_sample_by_stage_one_process": stages,
    }
    print(json.dumps(report, indent=2))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
