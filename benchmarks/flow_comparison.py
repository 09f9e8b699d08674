"""Occupancy flow at tiny scale: flow heads against the zero-flow baseline, one instant against temporal input.

    python benchmarks/flow_comparison.py [--data data/flow-world] [--steps 1000] [--seed 0] [--arms NAME ...]
        [--out docs/results/flow] [--runs runs/flow]

Each arm (:data:`ARMS`: a zoo entry with a flow head, and settings) trains ``--steps`` optimizer steps of batch 1
from its zoo recipe on the training scenes of a synthetic world whose labels carry flow (:data:`WORLD`, the study's
world, written first if absent), and is scored on its held-out scenes as ``occkit eval`` scores it (temporal models
streamed scene by scene): mIoU and IoU under the camera mask, RayIoU, and the CVPR 2024 challenge's mAVE and OccScore
on the same rays. The zero-flow baseline is the same model's predictions with every velocity set to 0 (the same
true-positive rays, so the difference is the flow head's alone), scored by ``occkit eval-preds``'s evaluator.

Resumable: a finished arm writes ``<out>/<arm>.json`` and is skipped on a rerun with the same steps and seed; a killed
run resumes from its newest checkpoint. ``<out>/flow.md`` and ``<out>/flow.json`` are rewritten after every entry.
Times are wall-clock and CPU seconds of this process and its data workers: run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import time
from pathlib import Path

import numpy as np
import torch

from occkit import zoo
from occkit.engine.evaluate import dataset_ray_origins, evaluation_dataset, load_trained, score_model
from occkit.engine.train import train
from occkit.experiment import replace_train
from occkit.metrics.evaluate import evaluate_predictions, read_prediction, write_prediction
from occkit.metrics.rayiou import FLOW_CLASSES
from occkit.sim.generate import SimConfig, simulate_dataset

#: The study's world (benchmarks/study.py): 16 scenes of 24 key frames at 400 x 225, the last 4 held out.
WORLD = {"scenes": 16, "frames": 24, "image_size": (400, 225), "seed": 7}
#: Arm -> (zoo entry, ``section.key=value`` changes, what its input holds of the past). The default pair: DAOcc's
#: tiny fusion model with its LiDAR sweeps (0.2 s of motion, one channel each in the flow head's motion input) and
#: with the key frame's sweep alone (the same model, its sweeps' channels empty). The camera-only pair
#: (``--arms da_occ_tiny_flow da_occ_tiny_temporal_flow``) compares one frame with a recurrent BEV history; at 1000
#: CPU steps neither has learned velocities yet (docs/flow.md).
ARMS: dict[str, tuple[str, tuple[str, ...], str]] = {
    "daocc_tiny_flow": ("daocc_tiny_flow", (), "key frame + 4 LiDAR sweeps (0.2 s)"),
    "daocc_tiny_flow_key_frame": ("daocc_tiny_flow", ("data.sweeps=0",), "key frame's LiDAR sweep only"),
    "da_occ_tiny_flow": ("da_occ_tiny_flow", (), "one camera frame"),
    "da_occ_tiny_temporal_flow": ("da_occ_tiny_temporal_flow", (), "recurrent BEV history of the scene"),
}
DEFAULT_ARMS = ("daocc_tiny_flow", "daocc_tiny_flow_key_frame")


def _cpu_seconds() -> float:
    """CPU seconds of this process and its finished children (the data loader's workers)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _zero_flow_copies(predictions: Path, out: Path) -> Path:
    """``out`` holding each prediction of ``predictions`` with its flow set to 0 (the zero-flow baseline)."""
    out.mkdir(parents=True, exist_ok=True)
    for path in sorted(predictions.glob("*.npz")):
        semantics = read_prediction(path)
        write_prediction(out, path.stem, semantics, np.zeros((*semantics.shape, 2), np.float32))
    return out


def run_arm(name: str, args: argparse.Namespace) -> dict:
    """Train and score one arm; the cached result when it already ran with these steps and seed."""
    result_file = args.out / f"{name}.json"
    if result_file.is_file():
        cached = json.loads(result_file.read_text())
        if (cached["steps"], cached["seed"]) != (args.steps, args.seed):
            raise SystemExit(f"{result_file} holds a run of {cached['steps']} steps with seed {cached['seed']}, not "
                             f"{args.steps} with seed {args.seed}: pass another --out (and --runs), or remove it")
        return cached
    entry, changes, history = ARMS[name]
    experiment = zoo.load_experiment(entry, list(changes))
    experiment = replace_train(experiment, max_steps=args.steps, epochs=10_000, val_every=-1, checkpoint_every=100,
                               seed=args.seed)  # fmt: skip
    experiment = dataclasses.replace(experiment, data=dataclasses.replace(experiment.data, root=str(args.data)))
    folder = args.runs / name
    print(f"[flow] {name}: training {args.steps} steps into {folder}", flush=True)
    wall, cpu = time.perf_counter(), _cpu_seconds()
    run = train(experiment, folder, resume="auto", progress=args.progress)
    train_wall, train_cpu = time.perf_counter() - wall, _cpu_seconds() - cpu

    model, experiment = load_trained(sorted(folder.glob("step-*.pt"))[-1])
    dataset = evaluation_dataset(experiment, args.data, "val")
    origins = dataset_ray_origins(dataset)
    predictions = folder / "predictions"
    predictions.mkdir(exist_ok=True)
    torch.set_flush_denormal(True)
    wall = time.perf_counter()
    scores = score_model(model, dataset, ray_origins=origins, predictions=predictions)
    eval_wall = time.perf_counter() - wall
    frames = {r.token: (r.scene, r.lidar_path) for r in dataset.records}
    gts = Path(args.data) / "gts"
    scored = evaluate_predictions(gts, predictions, ray_origins=origins, compute_rayiou=True, frames=frames)
    zero = evaluate_predictions(gts, _zero_flow_copies(predictions, folder / "predictions-zero-flow"),
                                ray_origins=origins, compute_rayiou=True, frames=frames)  # fmt: skip
    mave = float("nan") if scored["mave"] is None else scored["mave"]
    if not np.isclose(mave, scores["mave"], rtol=0, atol=1e-9, equal_nan=True):  # two evaluators, one metric
        raise AssertionError(f"{name}: occkit eval and eval-preds disagree on mAVE: {scores['mave']}, {scored['mave']}")
    result = {
        "arm": name, "entry": entry, "changes": list(changes), "history": history, "steps": run.steps,
        "seed": args.seed, "frames": scores["frames"],
        **{key: None if np.isnan(scores[key]) else scores[key]
           for key in ("miou", "iou", "rayiou", "mave", "occ_score")},
        "ave_per_class": scored["ave_per_class"], "ave_rays": scored["ave_rays"],
        "zero_flow": {key: zero[key] for key in ("mave", "occ_score", "ave_per_class")},
        "train_seconds": train_wall, "train_cpu_seconds": train_cpu, "eval_seconds": eval_wall,
        "params": sum(p.numel() for p in model.parameters()), "threads": torch.get_num_threads(),
        "device": torch.cuda.get_device_name() if torch.cuda.is_available() else f"CPU ({os.cpu_count()} cores)",
        "world": {**WORLD, "data": str(args.data)},
    }  # fmt: skip
    result_file.parent.mkdir(parents=True, exist_ok=True)
    result_file.write_text(json.dumps(result, indent=2) + "\n")
    print(f"[flow] {name}: mAVE {_cell(result['mave'], 1, 3)} m/s (zero flow {_cell(zero['mave'], 1, 3)}), OccScore "
          f"{_cell(result['occ_score'])}, RayIoU {_cell(result['rayiou'])}", flush=True)
    return result


def _cell(value: float | None, scale: float = 100.0, digits: int = 2) -> str:
    return "-" if value is None else f"{scale * value:.{digits}f}"


def write_report(results: list[dict], out: Path) -> None:
    """``flow.json`` and ``flow.md``: one row per entry, then the AVE per moving class."""
    (out / "flow.json").write_text(json.dumps(results, indent=2) + "\n")
    lines = [
        "| arm | input | steps | mIoU | RayIoU | mAVE (m/s) | zero-flow mAVE | OccScore | zero-flow OccScore | "
        "train CPU min |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in results:
        lines.append(f"| `{r['arm']}` | {r['history']} | {r['steps']} | "
                     f"{_cell(r['miou'])} | {_cell(r['rayiou'])} | {_cell(r['mave'], 1, 3)} | "
                     f"{_cell(r['zero_flow']['mave'], 1, 3)} | {_cell(r['occ_score'])} | "
                     f"{_cell(r['zero_flow']['occ_score'])} | {r['train_cpu_seconds'] / 60:.0f} |")  # fmt: skip
    lines += ["", "AVE (m/s) per moving class, model / zero flow, over its true-positive rays at 2 m:", "",
              "| arm | " + " | ".join(FLOW_CLASSES) + " |", "| --- |" + " ---: |" * len(FLOW_CLASSES)]  # fmt: skip
    for r in results:
        cells = [f"{_cell(r['ave_per_class'][c], 1, 2)} / {_cell(r['zero_flow']['ave_per_class'][c], 1, 2)} "
                 f"({r['ave_rays'][c]} rays)" if r["ave_per_class"][c] is not None else "-" for c in FLOW_CLASSES]
        lines.append(f"| `{r['arm']}` | " + " | ".join(cells) + " |")
    (out / "flow.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("data/flow-world"))
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--arms", nargs="+", default=list(DEFAULT_ARMS), choices=list(ARMS))
    parser.add_argument("--out", type=Path, default=Path("docs/results/flow"))
    parser.add_argument("--runs", type=Path, default=Path("runs/flow"))
    parser.add_argument("--progress", action="store_true", help="show the training progress bar")
    args = parser.parse_args()
    if not (args.data / "gts").is_dir():
        print(f"[flow] writing the world into {args.data}", flush=True)
        simulate_dataset(SimConfig(scenes=WORLD["scenes"], frames=WORLD["frames"], seed=WORLD["seed"],
                                   image_size=WORLD["image_size"]), args.data)  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    results = []
    for name in args.arms:
        results.append(run_arm(name, args))
        write_report(results, args.out)


if __name__ == "__main__":
    main()
