"""One forward pass of a zoo model on a real sample of the synthetic world: parameters, MACs and time on this machine.

Loads one key frame through the dataset at the model's paper setting (six 1600x900 cameras cropped to 256x704, key
frame + 9 LiDAR sweeps, test transform), then reports parameters and multiply-accumulates with and without the
detection branch (``occkit.models.complexity``; MACs are the papers' "GFLOPs") and the median eval-mode forward time
over ``--repeats`` runs after one warm-up.

    python benchmarks/model_forward.py --model daocc [--data data/synth-1600x900] [--repeats 3]
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
from occkit.models.complexity import count_macs, count_parameters
from occkit.sim.generate import SimConfig, simulate_dataset


def load_batch(root: Path, sweeps: int) -> object:
    if not root.exists():
        print(f"simulating a 1600x900 world into {root} (once) ...")
        simulate_dataset(SimConfig(scenes=1, frames=3, image_size=(1600, 900)), root, workers=2)
    dataset = OccupancyDataset(DatasetConfig(root=str(root), split="all", sweeps=sweeps, augment=False))
    # A key frame from the middle of a scene has its full set of earlier sweeps.
    return collate([dataset[min(len(dataset) - 1, sweeps // 2 + 1)]])


def timed(run, repeats: int) -> list[float]:
    run()  # warm-up: allocator, lazy initialisation, spconv's index building caches
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="daocc", choices=zoo.names())
    parser.add_argument("--data", type=Path, default=Path("data/synth-1600x900"))
    parser.add_argument("--sweeps", type=int, default=9)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    torch.manual_seed(0)
    model = zoo.build(args.model).eval()
    batch = load_batch(args.data, args.sweeps)
    result = {
        "model": args.model,
        "threads": torch.get_num_threads(),
        "images": list(batch.images.shape) if batch.images is not None else None,
        "points": int(batch.num_points.sum()),
        "params": count_parameters(model),
    }
    with torch.no_grad():
        if getattr(model, "detection_head", None) is not None:
            macs = count_macs(model, lambda: model(batch, detect=True))
            result["macs_with_detection"] = macs.total
            result["macs_by_module_with_detection"] = macs.by_module
            result["forward_s_with_detection"] = statistics.median(timed(lambda: model(batch, detect=True),
                                                                         args.repeats))
            model.remove_detection()
        result["params_without_detection"] = count_parameters(model)
        macs = count_macs(model, lambda: model(batch))
        result["macs"] = macs.total
        result["macs_by_module"] = macs.by_module
        result["forward_s"] = statistics.median(timed(lambda: model(batch), args.repeats))

    for key, value in result.items():
        if key.startswith("macs") and isinstance(value, int):
            value = f"{value / 1e9:.2f} G"
        elif key.startswith("macs_by"):
            value = ", ".join(f"{k} {v / 1e9:.2f} G" for k, v in value.items())
        elif key.startswith("params"):
            value = f"{value / 1e6:.2f} M"
        print(f"{key:>32}: {value}")
    out = args.out or Path("benchmarks/results") / f"model_forward_{args.model}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
