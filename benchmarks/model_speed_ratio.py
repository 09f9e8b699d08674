"""Speed ratio of two zoo models, timed in interleaved pairs in one process, so machine load hits both alike.

    python benchmarks/model_speed_ratio.py --models flashocc_m0 da_occ [--optimizations fixed_calibration,fold_bn]
        [--pairs 10] [--data data/bench-1600x900] [--out benchmarks/results/speed_ratio.json]

Each model gets its own key frame at its own input setting (``occkit.bench.load_sample``) and the same fast-path
steps (``none`` for the plain forward). ``ratio`` = median latency of the second model / median of the first: above
1 means the first is faster. ``occkit bench`` gives each model's absolute numbers; this script gives their order on
a shared machine, where two separate runs can see different loads.
"""

from __future__ import annotations

import argparse
import json
import statistics
from functools import partial
from pathlib import Path

import torch

from occkit import zoo
from occkit.bench import ModelRunner, load_sample, paired_times
from occkit.models.inference import prepare_for_inference


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs=2, default=("flashocc_m0", "da_occ"), choices=zoo.names())
    parser.add_argument("--optimizations", default="fixed_calibration,fold_bn", help="comma list, or none")
    parser.add_argument("--pairs", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--data", type=Path, default=None, help="dataset root (default: occkit bench's world)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/speed_ratio.json"))
    args = parser.parse_args()
    steps = [] if args.optimizations == "none" else args.optimizations.split(",")

    torch.manual_seed(0)
    torch.set_flush_denormal(True)  # as occkit bench does on CPUs
    device = torch.device("cpu")
    timings = []
    for name in args.models:
        runner = ModelRunner(load_sample(name, args.data), device)
        model = prepare_for_inference(zoo.build(name), steps)
        for _ in range(args.warmup):
            runner.forward(model)
        timings.append(partial(runner.time, model))
    first, second = paired_times(*timings, args.pairs)
    medians = [1000 * statistics.median(times) for times in (first, second)]
    result = {
        "models": list(args.models),
        "optimizations": steps,
        "threads": torch.get_num_threads(),
        "median_ms": dict(zip(args.models, medians, strict=True)),
        "all_ms": {name: [1000 * t for t in times] for name, times in zip(args.models, (first, second), strict=True)},
        "ratio": medians[1] / medians[0],
    }
    first_name, second_name = args.models
    print(
        f"{first_name} {medians[0]:.1f} ms, {second_name} {medians[1]:.1f} ms (medians of {args.pairs} interleaved "
        f"pairs, {result['threads']} threads): latency ratio {second_name} / {first_name} = {result['ratio']:.3f}"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
