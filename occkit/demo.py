"""``occkit demo``: the whole system on a laptop CPU, end to end, in under 20 minutes.

1. Write a small synthetic world (train scenes and held-out validation scenes) if the data folder is absent.
2. Score the weights occkit ships for one model of each family (:mod:`occkit.shipped`, trained on a world of another
   seed) on the held-out scenes: ``daocc_tiny`` (camera + LiDAR fusion), ``da_occ_tiny`` (camera only, DA-Occ's
   height-score projection and direction-aware convolutions) and ``flashocc_tiny`` (camera only, the baseline).
   Occ3D mIoU and geometry IoU under the camera mask, RayIoU, per class; beside two predictions that need no model:
   free space everywhere, and the labels' own ground layer.
3. Train each family from random weights for a few hundred steps on the training scenes, to show the loop learning
   (its loss curve and held-out score).
4. Render the predictions next to the ground truth and write ``report.md`` and ``metrics.json``.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from occkit import zoo
from occkit.data.collate import collate
from occkit.engine.checkpoint import checkpoint_step, latest_checkpoint
from occkit.engine.evaluate import evaluation_dataset, load_trained, score_model
from occkit.engine.train import train
from occkit.errors import UsageError
from occkit.experiment import replace_train
from occkit.figure import new_figure, save_figure
from occkit.label_space import OCC3D_SPACE
from occkit.metrics.confusion import OccupancyMetric
from occkit.shipped import SYNTHETIC, card, shipped_entries
from occkit.sim.generate import SimConfig, simulate_dataset
from occkit.viz.bev import bev_image
from occkit.viz.palette import add_class_legend

__all__ = ["run_demo", "check_world", "baselines", "learned", "DEMO_MODELS", "DEMO_WORLD", "GROUND_CLASSES"]

#: Zoo entries the demo scores (their shipped weights) and trains from random weights, one per family, with the short
#: run's optimizer steps (docs/training.md gives the minutes).
DEMO_MODELS: dict[str, int] = {"daocc_tiny": 300, "da_occ_tiny": 150, "flashocc_tiny": 150}
#: The label space of the demo's world and models: Occ3D (the world writes its labels and visibility masks).
DEMO_SPACE = OCC3D_SPACE
#: The synthetic world of the demo: 10 scenes of 24 key frames at 400 x 225 (the last 2-3 scenes held out).
DEMO_WORLD = {"scenes": 10, "frames": 24, "image_size": (400, 225), "seed": 1}


def _say(text: str) -> None:
    print(f"[demo] {text}", flush=True)


def check_world(data: Path) -> None:
    """Refuse, in one line, a ``data`` folder that exists but does not hold the demo's world (nothing is written
    into it): the demo's scores and the shipped weights' cards are of that world only."""
    if data.exists():
        differs = _differs_from_demo_world(data)
        if differs:
            raise UsageError(f"--data {data} is not the demo's world ({differs}): the demo writes and reuses only its "
                             "own world; choose another --data (a new folder is written)")  # fmt: skip


def _ensure_world(data: Path) -> None:
    check_world(data)
    if data.exists():
        _say(f"using the demo's synthetic world in {data}")
        return
    config = SimConfig(**DEMO_WORLD)
    _say(f"writing a synthetic world to {data}: {config.scenes} scenes x {config.frames} key frames, six cameras, "
         "LiDAR, boxes, Occ3D labels")  # fmt: skip
    with tqdm(total=config.scenes * config.frames, unit="frame", desc="sim") as bar:
        simulate_dataset(config, data, workers=2, progress=bar.update)


def _differs_from_demo_world(data: Path) -> str:
    """How the world in ``data`` differs from :data:`DEMO_WORLD`, from its ``sim_config.yaml`` ("" when it is the
    demo's; a folder without one is another dataset)."""
    from occkit.config import load_config
    from occkit.sim.generate import DATASET_MARKER

    try:
        config = load_config(SimConfig, data / DATASET_MARKER)
    except ValueError:  # absent or unreadable: not a world occkit sim wrote
        return f"{data} holds no readable {DATASET_MARKER}"
    expected = SimConfig(**DEMO_WORLD)
    changed = [f"{f.name} {getattr(config, f.name)!r} instead of {getattr(expected, f.name)!r}"
               for f in dataclasses.fields(SimConfig) if getattr(config, f.name) != getattr(expected, f.name)]
    return ", ".join(changed[:3]) + (f" and {len(changed) - 3} more" if len(changed) > 3 else "")


#: The classes of the ground layer (Occ3D's flat classes): what a model that has learned only the ground predicts.
GROUND_CLASSES = ("driveable_surface", "other_flat", "sidewalk", "terrain")
#: IoU (fraction) from which a class above the ground counts as learned in the report's one-line summaries.
LEARNED_IOU = 0.05


def baselines(dataset) -> dict[str, dict]:
    """Scores of two predictions that need no model, on ``dataset``'s frames: ``free``, free space everywhere (the
    most frequent class), and ``ground``, the labels' own ground layer (:data:`GROUND_CLASSES`, each voxel with its
    class) and free space above it: the most a model that has learned only the ground can score."""
    taxonomy = DEMO_SPACE.taxonomy
    ground = np.array([taxonomy.classes.index(name) for name in GROUND_CLASSES])
    metrics = {"free": OccupancyMetric.for_space(DEMO_SPACE), "ground": OccupancyMetric.for_space(DEMO_SPACE)}
    for record_index in range(len(dataset)):
        sample = dataset[record_index]
        labels, mask = sample.voxel_semantics.numpy(), sample.mask_camera.numpy()
        free = np.full_like(labels, DEMO_SPACE.free_index)
        metrics["free"].update(labels, free, mask)
        metrics["ground"].update(labels, np.where(np.isin(labels, ground), labels, free), mask)
    return {name: metric.compute() for name, metric in metrics.items()}


def learned(scores: dict, ground: dict) -> str:
    """What a model's scores say it has learned, in one line: the ground layer only (geometry IoU within a point of
    the ground layer's and no class above the ground at :data:`LEARNED_IOU`), or the classes above the ground it
    finds, best first."""
    taxonomy = DEMO_SPACE.taxonomy
    above = {name: iou for name, iou in scores["per_class_iou"].items()
             if iou is not None and name not in GROUND_CLASSES and name != taxonomy.classes[DEMO_SPACE.free_index]}
    found = sorted((item for item in above.items() if item[1] >= LEARNED_IOU), key=lambda item: -item[1])
    if not found:
        near = abs(scores["iou"] - ground["iou"]) <= 0.01
        return ("the ground layer and free space above it, nothing above the ground" if near else
                "no class above the ground yet")  # fmt: skip
    listed = ", ".join(f"{name} {100 * iou:.0f}" for name, iou in found[:4])
    more = f" and {len(found) - 4} more" if len(found) > 4 else ""
    return f"objects above the ground: {listed}{more} IoU"


def _render(models: dict, datasets: dict, path: Path, title: str, frames: int = 3) -> Path:
    """Ground truth and each model's prediction, bird's-eye view under the camera mask, a row per frame, into
    ``path``.

    ``datasets`` holds each model's own view of the validation split (a camera-only model loads no LiDAR); they
    list the same frames in the same order.
    """
    first = next(iter(datasets.values()))
    picks = np.linspace(0, len(first) - 1, frames).round().astype(int)
    fig = new_figure(3.2 * (1 + len(models)) + 1.6, 3.3 * frames)
    axes = fig.subplots(frames, 1 + len(models), squeeze=False)
    shown: set[int] = set()  # the classes drawn, for the legend
    for row, index in enumerate(picks):
        batch = collate([first[int(index)]])
        mask = batch.mask_camera[0].numpy()
        panels = [("ground truth", batch.voxel_semantics[0].numpy())]
        with torch.no_grad():
            for name, model in models.items():
                own = collate([datasets[name][int(index)]])
                assert own.tokens == batch.tokens, "the models' validation datasets list different frames"
                panels.append((name, model.predict(own).semantics[0].numpy()))
        for column, (panel, grid) in enumerate(panels):
            shown.update(np.unique(grid[mask > 0]).tolist())
            axis = axes[row, column]
            axis.imshow(bev_image(grid, mask, DEMO_SPACE.taxonomy))
            axis.set_title(f"{panel}\n{batch.tokens[0][:8]}" if row == 0 else batch.tokens[0][:8], fontsize=9)
            axis.axis("off")
    fig.suptitle(f"{title}: held-out frames, bird's-eye view (forward up), camera-visible voxels", fontsize=10)
    add_class_legend(axes[0, -1], shown, taxonomy=DEMO_SPACE.taxonomy)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110, tight=True)


def _report(out: Path, shipped: dict, trained: dict, baseline: dict, seconds: float, renders: dict) -> Path:
    taxonomy = DEMO_SPACE.taxonomy
    free, ground = baseline["free"], baseline["ground"]
    baseline_rows = [
        f"| free space everywhere (the most frequent class) | none | - | {100 * free['miou']:.1f} | "
        f"{100 * free['iou']:.1f} | - |",
        f"| the labels' ground layer, free above it (the most a ground-only model scores) | none | - | "
        f"{100 * ground['miou']:.1f} | {100 * ground['iou']:.1f} | - |",
    ]
    lines = [
        "# occkit demo",
        "",
        f"This run: {seconds / 60:.1f} min on this machine (work already done in this folder is reused). Scored on "
        f"the synthetic world's held-out scenes with the Occ3D protocol: mIoU over the {len(taxonomy.semantic_ids)} "
        "semantic classes and geometry IoU (occupied vs free), both under the camera visibility mask; RayIoU without "
        "mask.",
        "",
    ]
    if shipped:
        lines += [
            "## The shipped weights",
            "",
            "Trained by occkit on a synthetic world of another seed (`scripts/train_shipped_weights.py`; each "
            "file's card in `occkit/weights/` says how, and holds the scores below).",
            "",
            "| model | inputs | trained | mIoU | IoU | RayIoU |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for name, result in shipped.items():
            lines.append(f"| `{name}` | {_inputs(name)} | {result['trained']} | {100 * result['miou']:.1f} | "
                         f"{100 * result['iou']:.1f} | {100 * result['rayiou']:.1f} |")  # fmt: skip
        lines += baseline_rows + ["", "What each has learned (a class counts from 5 IoU):", ""]
        lines += [f"- `{name}`: {learned(result, ground)}" for name, result in shipped.items()]
        lines += ["", f"![the shipped weights' predictions]({renders['shipped'].name})", ""]
    lines += [
        "## A short training run from random weights",
        "",
        "Each family trained here on the training scenes for a few hundred steps: the loop learning, not a trained "
        "model (each run folder holds its `loss.png`, `train.csv` and TensorBoard events).",
        "",
        "| model | inputs | also supervised in training by | steps | train time | loss, first -> last 50 steps | "
        "mIoU | IoU | RayIoU |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, result in trained.items():
        first, last = result["loss"]
        lines.append(f"| `{name}` | {_inputs(name)} | {_training_signals(name)} | {result['steps']} | "
                     f"{result['train_seconds'] / 60:.1f} min | {first:.2f} -> {last:.2f} | "
                     f"{100 * result['miou']:.1f} | {100 * result['iou']:.1f} | {100 * result['rayiou']:.1f} |")
    if not shipped:
        lines += baseline_rows
    lines += ["", "What each has learned so far:", ""]
    lines += [f"- `{name}`: {learned(result, ground)}" for name, result in trained.items()]
    lines += ["", f"![predictions after the short runs]({renders['trained'].name})", ""]
    columns = {**{f"{name} (shipped)": r for name, r in shipped.items()},
               **{f"{name} ({r['steps']} steps)": r for name, r in trained.items()}}  # fmt: skip
    lines += ["## Per-class IoU (%)", "", "| class | " + " | ".join(f"`{n}`" for n in columns) + " |",
              "| --- |" + " --- |" * len(columns)]  # fmt: skip
    for name in (taxonomy.classes[i] for i in taxonomy.semantic_ids):
        values = [result["per_class_iou"].get(name) for result in columns.values()]
        lines.append(f"| {name} | " + " | ".join("-" if v is None else f"{100 * v:.1f}" for v in values) + " |")
    lines.append("")
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _inputs(name: str) -> str:
    return " + ".join(zoo.model_config(name)[1].sensors)


def _training_signals(name: str) -> str:
    """What supervises a zoo entry in training beside the occupancy labels (none of it is an input at inference)."""
    return ", ".join(zoo.model_config(name)[1].training_targets) or "-"


def _training_time(folder: Path, seconds: float) -> float:
    """Total training seconds of a run folder, over the demo runs that trained in it (a rerun adds ~0)."""
    path = folder / "demo_train_seconds.json"
    total = (json.loads(path.read_text())["seconds"] if path.is_file() else 0.0) + seconds
    path.write_text(json.dumps({"seconds": total}) + "\n")
    return total


def run_demo(out: str | Path, data: str | Path, models: dict[str, int] | None = None) -> Path:
    """Run the demo into ``out`` (a new or earlier demo folder) on ``data``; returns the report's path."""
    started = time.perf_counter()
    out, data = Path(out), Path(data)
    models = DEMO_MODELS if models is None else models
    for name, steps in models.items():
        if steps < 1:  # 0 would mean "no step limit" to the trainer: every epoch of the schedule
            raise ValueError(f"{name}: the demo trains at least 1 step, got {steps}")
    _ensure_world(data)
    try:
        return _train_score_report(out, data, models, started)
    finally:
        torch.set_flush_denormal(False)


def _train_score_report(out: Path, data: Path, models: dict[str, int], started: float) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    # On the CPU every core runs the model's threads: a loader process would only take turns with them (a
    # daocc_tiny step took 1.72 s with one loader process and 1.60 s reading in the main process, 2 cores).
    workers = None if torch.cuda.is_available() else 0
    shipped, trained, datasets = {}, {}, {}  # scores by entry, and each entry's held-out frames
    ready, from_scratch = {}, {}  # the models: shipped weights, and after the short run
    for name in models:
        experiment = _demo_experiment(name, data)
        datasets[name] = evaluation_dataset(experiment, data, "val")
        if name not in shipped_entries():
            continue
        described = card(name)
        _say(f"scoring the shipped {name} ({described.steps} steps, card {described.sha256[:12]}) on "
             f"{len(datasets[name])} held-out frames")  # fmt: skip
        model = zoo.build(name, weights=SYNTHETIC).eval()
        scores = _score(name, model, datasets[name], experiment, workers)
        shipped[name] = {**scores, "trained": f"{described.steps} steps, card {described.sha256[:12]}"}
        ready[name] = model
    for name, steps in models.items():
        experiment = replace_train(_demo_experiment(name, data), max_steps=steps, epochs=1000, val_every=-1,
                                   checkpoint_every=100)  # fmt: skip
        if workers == 0:
            experiment = replace_train(experiment, workers=0)
        newest = latest_checkpoint(out / name)
        if newest is not None and checkpoint_step(newest) >= steps:
            _say(f"reusing {name}'s finished {steps}-step run in {out / name}")
        else:
            _say(f"training {name} from random weights for {steps} steps ({zoo.description(name)})")
        # A rerun with other --steps continues the earlier run: only the step count may differ.
        run = train(experiment, out / name, resume="auto", allow_changes=("train.max_steps", "train.workers"))
        train_seconds = _training_time(out / name, run.seconds)
        model, experiment = load_trained(latest_checkpoint(out / name))
        scores = _score(name, model, datasets[name], experiment, workers)
        trained[name] = {**scores, "steps": run.steps, "train_seconds": train_seconds, "loss": _loss_ends(out / name)}
        from_scratch[name] = model
    baseline = baselines(next(iter(datasets.values())))
    renders = {"trained": _render(from_scratch, datasets, out / "predictions_from_scratch.png", "after the short runs")}
    if shipped:
        renders["shipped"] = _render(ready, datasets, out / "predictions.png", "the shipped weights")
    seconds = time.perf_counter() - started
    metrics = {
        "shipped": {name: {**r, "learned": learned(r, baseline["ground"])} for name, r in shipped.items()},
        "from_scratch": {name: {**r, "learned": learned(r, baseline["ground"])} for name, r in trained.items()},
        "most_frequent_class": {"miou": baseline["free"]["miou"], "iou": baseline["free"]["iou"]},
        "ground_layer": {"miou": baseline["ground"]["miou"], "iou": baseline["ground"]["iou"]},
    }
    (out / "metrics.json").write_text(json.dumps({**metrics, "seconds": seconds, "data": str(data)}, indent=2) + "\n")
    report = _report(out, shipped, trained, baseline, seconds, renders)
    _say(f"done in {seconds / 60:.1f} min: {report}")
    return report


def _demo_experiment(name: str, data: Path):
    """Zoo entry ``name``'s experiment on the demo's world in ``data``."""
    experiment = zoo.experiment(name)
    if experiment.data.label_space != DEMO_SPACE.name:
        raise ValueError(f"demo model {name} predicts {experiment.data.label_space} labels; the demo's world holds "
                         f"{DEMO_SPACE.name} labels")  # fmt: skip
    return dataclasses.replace(experiment, data=dataclasses.replace(experiment.data, root=str(data)))


def _score(name: str, model: torch.nn.Module, dataset, experiment, workers: int | None) -> dict:
    torch.set_flush_denormal(True)  # as during training: subnormals are an order of magnitude slower on CPUs
    scores = score_model(model, dataset, workers=experiment.train.workers if workers is None else workers)
    _say(f"{name}: mIoU {100 * scores['miou']:.1f}, IoU {100 * scores['iou']:.1f}, RayIoU {100 * scores['rayiou']:.1f}")
    return scores


def _loss_ends(run: Path, rows: int = 5) -> tuple[float, float]:
    """The run's mean training loss over its first and its last ``rows`` log rows (``train.csv``, a row every 10
    steps)."""
    lines = (run / "train.csv").read_text().splitlines()
    column = lines[0].split(",").index("loss")
    losses = [float(line.split(",")[column]) for line in lines[1:] if line.strip()]
    return float(np.mean(losses[:rows])), float(np.mean(losses[-rows:]))
