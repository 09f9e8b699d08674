"""Does the BEV history pay off? The single-frame tiny DA-Occ against its temporal twin, trained with one budget.

Three arms train for the same number of optimizer steps (batch 1), from the same seed, on the same synthetic world:

* ``da_occ_tiny``, the single-frame model, on shuffled frames (its zoo recipe);
* ``da_occ_tiny_temporal``, the same model plus da_occ_16f_recurrent's BEV history, trained on streams of each
  scene's frames in time order with its memory carried from step to step (its zoo recipe);
* ``da_occ_tiny (streams)``, the single-frame model trained in the temporal model's order (``train.sampler:
  streams``): the control that tells the history's effect from the effect of the order, since consecutive frames
  of one scene make a less varied stream of gradients than shuffled frames.

Each is scored on the world's held-out scenes (mIoU and IoU under the camera mask, RayIoU), the temporal model
streamed scene by scene as ``occkit eval`` does, and also with an empty history (every frame alone) to show what
its history adds inside the model. Training times are reported beside.

    python benchmarks/temporal_training.py [--data data/temporal-world] [--steps 600]
        [--out benchmarks/results/temporal_training]

Writes ``<out>/temporal_training.json`` and prints a markdown table. Each arm's result is cached in its folder
(``result.json``): a rerun skips finished arms and trains the others (a killed run resumes from its checkpoint).
Run it on an idle machine: the times are wall-clock.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import torch

from occkit import zoo
from occkit.engine.evaluate import dataset_ray_origins, evaluation_dataset, load_trained, score_model
from occkit.engine.train import train
from occkit.experiment import replace_train
from occkit.sim.generate import SimConfig, simulate_dataset

#: Arm name -> (zoo entry, training sampler).
ARMS = {
    "da_occ_tiny": ("da_occ_tiny", "random"),
    "da_occ_tiny_temporal": ("da_occ_tiny_temporal", "streams"),
    "da_occ_tiny (streams)": ("da_occ_tiny", "streams"),
}
#: 8 scenes of 16 key frames at 400 x 225 (the sim holds the last scenes out as the val split).
WORLD = {"scenes": 8, "frames": 16, "image_size": (400, 225), "seed": 5}


def _arm(name: str, entry: str, sampler: str, args) -> dict:
    folder = args.out / name.replace(" ", "_").replace("(", "").replace(")", "")
    cached = folder / "result.json"
    if cached.is_file():
        return json.loads(cached.read_text())
    experiment = zoo.experiment(entry)
    experiment = dataclasses.replace(experiment, data=dataclasses.replace(experiment.data, root=str(args.data)))
    experiment = replace_train(experiment, max_steps=args.steps, epochs=1000, val_every=-1, checkpoint_every=100,
                               seed=0, sampler=sampler)  # fmt: skip
    started = time.perf_counter()
    run = train(experiment, folder, resume="auto")
    train_seconds = time.perf_counter() - started
    model, experiment = load_trained(sorted(folder.glob("step-*.pt"))[-1])
    dataset = evaluation_dataset(experiment, args.data, "val")
    torch.set_flush_denormal(True)
    origins = dataset_ray_origins(dataset)
    scores = score_model(model, dataset, workers=1, ray_origins=origins)
    result = {key: scores[key] for key in ("miou", "iou", "rayiou", "per_class_iou", "frames")}
    result.update(entry=entry, sampler=sampler, steps=run.steps, train_seconds=train_seconds)
    if model.temporal is not None:
        # The same weights with an empty history on every frame: what the history adds inside the model.
        alone = _without_history(model)
        empty = score_model(alone, dataset, workers=1, ray_origins=origins)
        result["empty_history"] = {key: empty[key] for key in ("miou", "iou", "rayiou")}
    cached.write_text(json.dumps(result, indent=2) + "\n")
    return result


class _without_history(torch.nn.Module):
    """A temporal model seen as a single-frame one: every frame predicted with an empty history (no stream)."""

    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def predict(self, batch):
        return self.model.predict(batch)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/temporal-world"))
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/temporal_training"))
    args = parser.parse_args()
    if not args.data.exists():
        print(f"simulating {WORLD['scenes']} scenes x {WORLD['frames']} key frames into {args.data}", flush=True)
        simulate_dataset(SimConfig(**WORLD), args.data, workers=2)
    results = {}
    for name, (entry, sampler) in ARMS.items():
        results[name] = result = _arm(name, entry, sampler, args)
        print(f"{name}: mIoU {100 * result['miou']:.2f}, IoU {100 * result['iou']:.2f}, "
              f"RayIoU {100 * result['rayiou']:.2f} ({result['steps']} steps)", flush=True)
    report = {"world": {**WORLD, "data": str(args.data)}, "steps": args.steps, "arms": results,
              "threads": torch.get_num_threads()}  # fmt: skip
    (args.out / "temporal_training.json").write_text(json.dumps(report, indent=2) + "\n")
    print("\n| arm | order | train time | mIoU | IoU | RayIoU | empty history: mIoU / IoU / RayIoU |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, r in results.items():
        empty = r.get("empty_history")
        alone = "" if empty is None else " / ".join(f"{100 * empty[k]:.2f}" for k in ("miou", "iou", "rayiou"))
        print(f"| `{name}` | {r['sampler']} | {r['train_seconds'] / 60:.1f} min | {100 * r['miou']:.2f} | "
              f"{100 * r['iou']:.2f} | {100 * r['rayiou']:.2f} | {alone} |")


if __name__ == "__main__":
    main()
