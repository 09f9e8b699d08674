"""Does the BEV history pay off? The single-frame tiny DA-Occ against its temporal twin, trained with one budget.

``da_occ_tiny`` and ``da_occ_tiny_temporal`` (the same model plus da_occ_16f's recurrent BEV history, trained on
streams of each scene's frames in order) train for the same number of optimizer steps, from the same seed, on the
same synthetic world, in this one run; then both are scored on the world's held-out scenes (mIoU and IoU under the
camera mask, RayIoU), the temporal model streamed scene by scene as ``occkit eval`` does. Each run's training time
is reported beside it.

    python benchmarks/temporal_training.py [--data data/temporal-world] [--steps 300]
        [--out benchmarks/results/temporal_training]

Writes ``<out>/temporal_training.json`` and prints a markdown table. Run it on an idle machine: the times are
wall-clock. A rerun continues each model's run (to a larger ``--steps``, or not at all) and scores it again.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import torch

from occkit import zoo
from occkit.engine.evaluate import dataset_ray_origins, evaluate_model, evaluation_dataset, load_trained
from occkit.engine.train import train
from occkit.experiment import replace_train
from occkit.sim.generate import SimConfig, simulate_dataset

MODELS = ("da_occ_tiny", "da_occ_tiny_temporal")
#: 8 scenes of 16 key frames at 400 x 225 (the sim holds the last scenes out as the val split).
WORLD = {"scenes": 8, "frames": 16, "image_size": (400, 225), "seed": 5}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/temporal-world"))
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/temporal_training"))
    args = parser.parse_args()
    if not args.data.exists():
        print(f"simulating {WORLD['scenes']} scenes x {WORLD['frames']} key frames into {args.data}", flush=True)
        simulate_dataset(SimConfig(**WORLD), args.data, workers=2)
    results = {}
    for name in MODELS:
        experiment = zoo.experiment(name)
        experiment = dataclasses.replace(experiment, data=dataclasses.replace(experiment.data, root=str(args.data)))
        experiment = replace_train(experiment, max_steps=args.steps, epochs=1000, val_every=-1, checkpoint_every=100,
                                   seed=0)  # fmt: skip
        started = time.perf_counter()
        # A rerun with another --steps continues the earlier run.
        run = train(experiment, args.out / name, resume="auto", allow_changes=("train.max_steps",))
        train_seconds = time.perf_counter() - started
        model, experiment = load_trained(sorted((args.out / name).glob("step-*.pt"))[-1])
        dataset = evaluation_dataset(experiment, args.data, "val")
        torch.set_flush_denormal(True)
        started = time.perf_counter()
        scores = evaluate_model(model, dataset, batch_size=1, workers=1, ray_origins=dataset_ray_origins(dataset))
        results[name] = {"miou": scores["miou"], "iou": scores["iou"], "rayiou": scores["rayiou"],
                         "per_class_iou": scores["per_class_iou"], "frames": scores["frames"], "steps": run.steps,
                         "train_seconds": train_seconds, "eval_seconds": time.perf_counter() - started,
                         "streamed": getattr(model, "temporal", None) is not None}  # fmt: skip
        print(f"{name}: mIoU {100 * scores['miou']:.2f}, IoU {100 * scores['iou']:.2f}, "
              f"RayIoU {100 * scores['rayiou']:.2f} ({run.steps} steps)", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"world": {**WORLD, "data": str(args.data)}, "steps": args.steps, "models": results,
              "threads": torch.get_num_threads()}  # fmt: skip
    (args.out / "temporal_training.json").write_text(json.dumps(report, indent=2) + "\n")
    print("\n| model | steps | train time | mIoU | IoU | RayIoU | held-out frames |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, r in results.items():
        print(f"| `{name}` | {r['steps']} | {r['train_seconds'] / 60:.1f} min | {100 * r['miou']:.2f} | "
              f"{100 * r['iou']:.2f} | {100 * r['rayiou']:.2f} | {r['frames']} |")


if __name__ == "__main__":
    main()
