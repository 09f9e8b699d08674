"""Seconds per training step of a zoo model on real batches of the synthetic world (forward, loss, backward, AdamW).

    python benchmarks/train_step.py --model daocc_tiny [--cameras 4] [--image-size 128 352] [--sweeps 2]
        [--batch 1] [--steps 5] [--data data/synth]

The batch is loaded once through the dataset with training augmentation and reused, so only the model is timed.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from occkit import zoo
from occkit.data.collate import collate
from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.data.transforms import ImageAugConfig
from occkit.models.complexity import count_parameters
from occkit.nuscenes import CAMERAS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="daocc_tiny", choices=zoo.names())
    parser.add_argument("--data", type=Path, default=Path("data/synth"))
    parser.add_argument("--cameras", type=int, default=4, help="the first N of the six nuScenes cameras")
    parser.add_argument("--image-size", type=int, nargs=2, default=(128, 352), metavar=("H", "W"))
    parser.add_argument("--sweeps", type=int, default=2)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if not args.data.exists():
        parser.error(f"{args.data} does not exist: write one with `occkit sim --out {args.data}`")

    torch.manual_seed(0)
    model = zoo.build(args.model).train()
    needs_maps = args.model.startswith("da_occ")
    config = DatasetConfig(
        root=str(args.data), split="all", sweeps=args.sweeps, augment=True, cameras=CAMERAS[: args.cameras],
        image_aug=ImageAugConfig(final_size=tuple(args.image_size)), depth_downsample=16 if needs_maps else 0,
    )  # fmt: skip
    dataset = OccupancyDataset(config)
    middle = len(dataset) // 2  # a key frame with its full set of earlier sweeps
    batch = collate([dataset[middle + i] for i in range(args.batch)])
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    times = []
    for _ in range(args.steps + 1):  # the first step warms up
        start = time.perf_counter()
        loss = sum(model.loss(model(batch), batch).values())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        times.append(time.perf_counter() - start)
    result = {
        "model": args.model,
        "threads": torch.get_num_threads(),
        "images": list(batch.images.shape),
        "points": int(batch.num_points.sum()),
        "params": count_parameters(model),
        "step_s_median": statistics.median(times[1:]),
        "step_s": times[1:],
    }
    print(json.dumps(result, indent=2))
    out = args.out or Path("benchmarks/results") / f"train_step_{args.model}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
