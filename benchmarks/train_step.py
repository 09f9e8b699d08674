"""Seconds per training step of a zoo model on real batches of a synthetic world, and where they go.

    python benchmarks/train_step.py --model daocc_tiny [--data data/demo] [--batch 1] [--steps 5]
        [--cameras N] [--image-size H W] [--sweeps S] [--out FILE]

The model's own data settings (its zoo entry's ``data``) load the batches, with training augmentation, so the step
is the one ``occkit train`` takes; ``--cameras``, ``--image-size`` and ``--sweeps`` override them. Each timed step
loads a new batch in this process (``data``: reading, augmenting and collating), then runs the forward pass, the
loss, the backward pass and the AdamW step, with the thread count PyTorch chose. Forward and backward are split by
stage (the architecture's benchmark stages, timed with :class:`occkit.bench.StageTimer`); ``other`` is the part of
forward and backward outside every stage. The JSON (default ``benchmarks/results/train_step_<model>.json``) holds
every step and the per-stage medians.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from pathlib import Path

import torch

from occkit import zoo
from occkit.bench import StageTimer, stage_modules
from occkit.data.collate import collate
from occkit.data.dataset import OccupancyDataset
from occkit.machine import machine_info
from occkit.models.complexity import count_parameters
from occkit.nuscenes import CAMERAS


def _step_profile(model, optimizer, batch_of, timer: StageTimer, index: int) -> dict[str, float]:
    """One training step, timed piece by piece: data, forward stages, loss, backward stages, optimizer."""
    started = time.perf_counter()
    batch = batch_of(index)
    loaded = time.perf_counter()
    timer.reset()
    output = model(batch)
    forwarded = time.perf_counter()
    loss = sum(model.loss(output, batch).values())
    lossed = time.perf_counter()
    optimizer.zero_grad(set_to_none=True)
    timer.backward_started()
    loss.backward()
    timer.backward_done()
    backwarded = time.perf_counter()
    optimizer.step()
    done = time.perf_counter()
    forward, backward = timer.seconds, timer.backward_seconds
    return {
        "data": loaded - started,
        **{f"forward/{stage}": seconds for stage, seconds in forward.items()},
        "forward/other": (forwarded - loaded) - sum(forward.values()),
        "loss": lossed - forwarded,
        "backward/loss": timer.loss_backward_seconds,
        **{f"backward/{stage}": seconds for stage, seconds in backward.items()},
        "backward/other": (backwarded - lossed) - sum(backward.values()) - timer.loss_backward_seconds,
        "optimizer": done - backwarded,
        "step": done - started,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="daocc_tiny", choices=zoo.names())
    parser.add_argument("--data", type=Path, default=Path("data/demo"))
    parser.add_argument("--cameras", type=int, default=None, help="the first N of the six nuScenes cameras")
    parser.add_argument("--image-size", type=int, nargs=2, default=None, metavar=("H", "W"))
    parser.add_argument("--sweeps", type=int, default=None)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if not args.data.exists():
        parser.error(f"{args.data} does not exist: write one with `occkit demo` or `occkit sim --out {args.data}`")

    torch.manual_seed(0)
    experiment = zoo.experiment(args.model)
    config = dataclasses.replace(experiment.data, root=str(args.data), split="train", augment=True)
    if args.cameras is not None:
        config = dataclasses.replace(config, cameras=CAMERAS[: args.cameras])
    if args.image_size is not None:
        config = dataclasses.replace(config, image_aug=dataclasses.replace(config.image_aug,
                                                                           final_size=tuple(args.image_size)))
    if args.sweeps is not None:
        config = dataclasses.replace(config, sweeps=args.sweeps)
    dataset = OccupancyDataset(config)
    model = zoo.build(args.model).train()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    torch.set_flush_denormal(True)  # as occkit train does on CPUs
    stride = max(1, len(dataset) // (args.steps + 2))

    def batch_of(step: int):
        first = (step * stride * args.batch) % len(dataset)
        return collate([dataset[(first + i) % len(dataset)] for i in range(args.batch)])

    profiles = []
    with StageTimer(stage_modules(experiment.architecture, model), lambda: None, backward=True) as timer:
        for step in range(args.steps + 1):  # the first step warms up
            profiles.append(_step_profile(model, optimizer, batch_of, timer, step))
    profiles = profiles[1:]
    median = {key: statistics.median(p[key] for p in profiles) for key in profiles[0]}
    sample = batch_of(0)
    result = {
        "model": args.model,
        "machine": machine_info("cpu"),
        "images": list(sample.images.shape),
        "points": 0 if sample.num_points is None else int(sample.num_points.sum()),
        "params": count_parameters(model),
        "step_s_median": median["step"],
        "median_s": median,
        "steps": profiles,
    }
    width = max(map(len, median))
    print(f"{args.model}: {median['step']:.3f} s per step (median of {args.steps}), images {result['images']}, "
          f"{result['points']} points, {result['machine']['threads']} threads")
    for key, seconds in median.items():
        if key != "step":
            print(f"  {key:<{width}} {1000 * seconds:8.1f} ms  {100 * seconds / median['step']:5.1f}%")
    out = args.out or Path("benchmarks/results") / f"train_step_{args.model}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
