"""Train the weights occkit ships for its CPU-sized entries, and write them with their cards into occkit/weights/.

    python scripts/train_shipped_weights.py --entry da_occ_tiny [--entry ...] [--runs runs/shipped]
        [--world data/shipped-world] [--demo-data data/demo] [--epochs 30 | --continue-epochs N] [--write]

For each entry: the training world (:data:`TRAIN_WORLD`, a seed other than the demo's) is written if absent; the
entry's CPU recipe (at ``--batch-size``, if given) trains on it for ``--epochs`` epochs, validating on its held-out
scenes every 2 epochs and saving a checkpoint every 200 steps, and a rerun resumes from the newest checkpoint (a run
may span sessions, and a GPU runs it with ``--device cuda``).

``--continue-epochs N`` continues the shipped weights' run instead, for a run whose curve had not flattened by the
end of its schedule: a new run (``<runs>/<entry>-from-<steps>``, named after the shipped weights' steps) starts from
the shipped weights (kept in that folder with their card, ``base.safetensors`` and ``base.card.json``) with fresh AdamW
moments and the recipe's warm-up and cosine schedule over N more epochs; its card adds the runs up (steps, time,
devices, every command, one curve). A continuation may itself be continued: each starts a folder of its own.

With ``--write``, the last weights are rounded to half precision, scored on the demo world's held-out scenes (mIoU,
IoU, RayIoU, per class) and written with their card (:mod:`occkit.shipped`): the world; the steps; the training
time (summed from the run log's throughput, so resumed runs count only their own steps); the devices (each
session's, from the run folder's ``sessions.jsonl``, saying where a session resumed from a checkpoint without
optimizer state); the command that reproduces the run; the scores; the curve of held-out mIoU over the run and
whether it converged (less than 0.5 mIoU gained over the last fifth of the run), and where its score stands against
the entry's target (:data:`TARGET_MIOU`, :data:`TARGET_OBJECTS`). ``--refresh-notes`` rewrites only the cards' notes,
from the curves and scores they already hold.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import shutil
import sys
from pathlib import Path

import torch

from occkit import zoo
from occkit.demo import DEMO_WORLD
from occkit.engine.checkpoint import checkpoint_step
from occkit.engine.evaluate import evaluation_dataset, load_trained, score_model
from occkit.engine.train import train
from occkit.experiment import replace_train
from occkit.shipped import WeightsCard, card, weights_path, write_card, write_shipped
from occkit.sim.generate import SimConfig, simulate_dataset

#: The world the shipped weights train on: the demo world's size and image size with 16 scenes (4 held out), and a
#: seed other than the demo's, so that the demo scores them on scenes they never saw.
TRAIN_WORLD = {"scenes": 16, "frames": 24, "image_size": (400, 225), "seed": 2026}
ENTRIES = ("daocc_tiny", "da_occ_tiny", "flashocc_tiny")
#: The demo-world held-out mIoU the project set each entry as its target (docs/results.md), which its card measures
#: itself against, and the object classes each should find.
TARGET_MIOU = {"daocc_tiny": 0.45, "da_occ_tiny": 0.25, "flashocc_tiny": 0.20}
TARGET_OBJECTS = ("car", "bus", "truck", "pedestrian")
#: A run has converged when its held-out mIoU gained less than this over the last fifth of its steps.
CONVERGED_GAIN = 0.005
#: Validations a curve needs before it can say so.
MIN_CURVE_POINTS = 4
#: In a run folder: one line per training session, the step it started from and the device it ran on, so that a card
#: says where each part of a run that moved between machines was trained.
SESSIONS = "sessions.jsonl"


def record_session(run: Path, device: str) -> None:
    """Append this session (the step the trainer resumes from, which is its newest checkpoint's, and ``device``)."""
    checkpoints = sorted(run.glob("step-*.pt"))
    start = checkpoint_step(checkpoints[-1]) if checkpoints else 0
    record = {"from_step": start, "device": device}
    # Mapped, not read: only whether the optimizer's moments travelled with the checkpoint matters here.
    payload = torch.load(checkpoints[-1], map_location="cpu", weights_only=False, mmap=True) if checkpoints else None
    if payload is not None and payload["optimizer"] is None:  # the checkpoint travelled without AdamW's moments
        record["fresh_optimizer"] = True
    run.mkdir(parents=True, exist_ok=True)
    with open(run / SESSIONS, "a") as handle:
        handle.write(json.dumps(record) + "\n")


def devices(run: Path, steps: int, fallback: str) -> str:
    """Where the run's first ``steps`` steps were trained: ``"A (steps 0-2304), B (steps 2304-4000)"``, from its
    sessions (a later session that resumed from an earlier step replaces what it retrained); ``fallback`` for a run
    without a record."""
    path = run / SESSIONS
    sessions = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []
    spans: list[list] = []  # [device, first step, last step]
    for session in sessions:
        start = session["from_step"]
        spans = [span for span in spans if span[1] < start]
        if spans:
            spans[-1][2] = min(spans[-1][2], start)
        fresh = ", resumed with fresh optimizer moments" if session.get("fresh_optimizer") else ""
        spans.append([session["device"] + fresh, start, steps])
    spans = [span for span in spans if span[1] < steps]
    if not spans:
        return fallback
    merged = [spans[0]]
    for span in spans[1:]:
        if span[0] == merged[-1][0]:
            merged[-1][2] = span[2]
        else:
            merged.append(span)
    return ", ".join(f"{device} (steps {first}-{last})" for device, first, last in merged)


def ensure_world(root: Path, world: dict) -> None:
    if not (root / "sim_config.yaml").is_file():
        print(f"writing the world {world} to {root}", flush=True)
        simulate_dataset(SimConfig(**world), root)


def run_experiment(entry: str, world: Path, epochs: int, device: str | None, workers: int | None = None,
                   batch_size: int | None = None):  # fmt: skip
    """The entry's recipe on ``world``, at ``batch_size`` samples per step (None: the recipe's); loader processes
    ``workers``, by default the entry's on a GPU and 1 on a CPU (where every other core trains)."""
    experiment = zoo.experiment(entry)
    experiment = dataclasses.replace(experiment, data=dataclasses.replace(experiment.data, root=str(world)))
    if workers is None:
        workers = experiment.train.workers if device != "cpu" else 1
    if batch_size is not None:
        experiment = replace_train(experiment, batch_size=batch_size)
    return replace_train(experiment, epochs=epochs, val_every=2, checkpoint_every=200, workers=workers)


def curve(run: Path) -> list[dict[str, float]]:
    """Held-out mIoU and IoU by step, from the run's ``val.jsonl``."""
    path = run / "val.jsonl"
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []
    return [{"step": row["step"], "miou": row["miou"], "iou": row["iou"]} for row in rows]


def converged(points: list[dict[str, float]]) -> tuple[bool, float]:
    """Whether the held-out mIoU gained less than :data:`CONVERGED_GAIN` over the last fifth of the run (the last
    value against the best one up to 80% of the steps), and that gain; never with fewer than
    :data:`MIN_CURVE_POINTS` validations, which cannot tell a plateau from a dip."""
    if len(points) < MIN_CURVE_POINTS:
        return False, float("nan")
    last = points[-1]["step"]
    before = max(point["miou"] for point in points if point["step"] <= 0.8 * last)
    gain = points[-1]["miou"] - before
    return gain < CONVERGED_GAIN, gain


def card_notes(entry: str, points: list[dict[str, float]], scores: dict) -> str:
    """What a card says a user should know: whether the run converged (:func:`converged`), where its demo-world
    mIoU stands against :data:`TARGET_MIOU`, and any of :data:`TARGET_OBJECTS` it has not found (0 IoU).

    ``scores`` holds ``miou`` and ``per_class`` as a card stores them (fractions)."""
    done, gain = converged(points)
    if len(points) < MIN_CURVE_POINTS:
        notes = [f"not converged: {len(points)} held-out validations, too few to tell"]
    else:
        notes = [f"{'converged' if done else 'not converged'}: {100 * gain:+.2f} mIoU over the last fifth of the run"]
    target = TARGET_MIOU[entry]
    notes.append(f"{100 * scores['miou']:.1f} mIoU on the demo world's held-out frames, "
                 f"{'meeting' if scores['miou'] >= target else 'below'} its target of {100 * target:.0f}")  # fmt: skip
    missing = [name for name in TARGET_OBJECTS if not scores["per_class"].get(name)]
    if missing:
        notes.append(f"0 IoU on {', '.join(missing)}")
    return "; ".join(notes)


def refresh_notes(entry: str, folder: Path) -> str:
    """Rewrite the notes of ``entry``'s card in ``folder`` from the card's own curve and scores (after
    :func:`card_notes` changed); the weights, and the hash the card holds of them, stay as they are."""
    shipped = card(entry, folder)
    notes = card_notes(entry, shipped.curve, shipped.scores)
    write_card(dataclasses.replace(shipped, notes=notes), folder)
    return notes


def training_seconds(run: Path, batch_size: int) -> float:
    """The run's training time from its log: the steps of each logging interval over that interval's throughput."""
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    seconds, previous = 0.0, 0
    for row in rows:
        if row.get("samples_per_s"):
            seconds += (row["step"] - previous) * batch_size / row["samples_per_s"]
        previous = row["step"]
    return seconds


def reproduce_command(entry: str, experiment, continued: bool = False) -> str:
    """The command that trains ``experiment``'s run again and writes the card: the settings that make the run (epochs,
    batch size; ``--continue-epochs`` for a continuation), none of the folders it happened to use (the defaults
    serve)."""
    recipe = zoo.experiment(entry).train
    args = ["--entry", entry, "--continue-epochs" if continued else "--epochs", str(experiment.train.epochs)]
    if experiment.train.batch_size != recipe.batch_size:
        args += ["--batch-size", str(experiment.train.batch_size)]
    return "python scripts/train_shipped_weights.py " + shlex.join([*args, "--write"])


def continuation_folder(runs: Path, entry: str, weights: Path) -> Path:
    """The run folder of a continuation of ``entry``'s weights in ``weights``: named after the steps they were trained
    for, so that the continuation of a continuation neither resumes nor overwrites the one before it."""
    return runs / f"{entry}-from-{card(entry, weights).steps}"


def start_continuation(entry: str, run: Path, weights: Path) -> WeightsCard:
    """The card of the weights a continuation starts from: the shipped ones, copied with their card into ``run`` at
    its start (``--write`` replaces the shipped files, and a resumed continuation must go on from the same start)."""
    base_card, base_weights = run / "base.card.json", run / "base.safetensors"
    if not base_card.is_file():
        run.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(weights_path(entry, weights), base_weights)
        shutil.copyfile(weights / f"{entry}.card.json", base_card)
    return card("base", run)


def merged_card_fields(base: WeightsCard, run: Path, experiment, steps: int, trained_on: str) -> dict:
    """The card fields of a continuation that went ``steps`` steps beyond ``base``: the two runs added up, its
    validations after the base's on one curve (their steps counted from the start of the base run)."""
    points = base.curve + [{**point, "step": base.steps + point["step"]} for point in curve(run)
                           if point["step"] <= steps]  # fmt: skip
    continued = (f"then {experiment.train.epochs} more epochs from those weights (a new warm-up and cosine schedule, "
                 f"fresh optimizer moments; steps counted from there): {devices(run, steps, trained_on)}")  # fmt: skip
    return {"steps": base.steps + steps, "curve": points, "device": f"{base.device}; {continued}",
            "train_seconds": round(base.train_seconds + training_seconds(run, experiment.train.batch_size), 1),
            "command": f"{base.command} && {reproduce_command(base.entry, experiment, continued=True)}"}  # fmt: skip


def package(entry: str, run: Path, demo: Path, world: dict, device: str, trained_on: str, out: Path,
            base: WeightsCard | None = None) -> None:  # fmt: skip
    """Score the run's newest checkpoint, rounded to half precision, on ``demo``'s held-out scenes (on ``device``)
    and write it with its card into ``out`` (``trained_on`` names where the run trained; ``base``: the card of the
    weights a continuation started from)."""
    checkpoint = sorted(run.glob("step-*.pt"))[-1]
    model, experiment = load_trained(checkpoint, device)
    with torch.no_grad():  # the card scores what is shipped: the weights at half precision
        for tensor in model.state_dict().values():
            if tensor.is_floating_point():
                tensor.copy_(tensor.half().float())
    dataset = evaluation_dataset(experiment, demo, "val")
    scores = score_model(model, dataset)
    steps = checkpoint_step(checkpoint)
    if base is None:
        fields = {"steps": steps, "curve": [point for point in curve(run) if point["step"] <= steps],  # as shipped
                  "train_seconds": round(training_seconds(run, experiment.train.batch_size), 1),
                  "device": devices(run, steps, trained_on), "command": reproduce_command(entry, experiment)}
    else:
        fields = merged_card_fields(base, run, experiment, steps, trained_on)
    card_scores = {"miou": scores["miou"], "iou": scores["iou"], "rayiou": scores.get("rayiou"),
                   "per_class": scores["per_class_iou"]}  # fmt: skip
    notes = card_notes(entry, fields["curve"], card_scores)
    written = write_shipped(model, experiment.architecture, {
        "entry": entry, "world": {**world, "image_size": list(world["image_size"])}, **fields, "notes": notes,
        "scores": card_scores,
    }, out)  # fmt: skip
    print(f"{entry}: {fields['steps']} steps, demo held-out mIoU {100 * scores['miou']:.1f}, "
          f"IoU {100 * scores['iou']:.1f}; {notes}; wrote {out / entry}.safetensors ({written.sha256[:12]})")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--entry", action="append", choices=ENTRIES, help="entry to train (repeatable; default all)")
    parser.add_argument("--runs", type=Path, default=Path("runs/shipped"), help="run folders (default runs/shipped)")
    parser.add_argument("--world", type=Path, default=Path("data/shipped-world"), help="training world")
    parser.add_argument("--demo-data", type=Path, default=Path("data/demo"), help="the demo world, scored on")
    parser.add_argument("--epochs", type=int, default=30, help="epochs of the training world (default 30)")
    parser.add_argument("--continue-epochs", type=int, default=0, metavar="N",
                        help="continue the shipped weights' run for N more epochs (a new schedule; see above)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    parser.add_argument("--batch-size", type=int, default=None,
                        help="samples per step (default: the entry's, 1; a GPU trains 4 in the time of 1)")  # fmt: skip
    parser.add_argument("--workers", type=int, default=None,
                        help="loader processes (default: the entry's on a GPU, 1 on a CPU)")  # fmt: skip
    parser.add_argument("--write", action="store_true", help="score the last weights and write them with a card")
    parser.add_argument("--no-train", action="store_true",
                        help="with --write: package the run's newest checkpoint as it is (no training step)")
    parser.add_argument("--refresh-notes", action="store_true",
                        help="only rewrite the shipped cards' notes from their curves and scores (no training)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "occkit" / "weights")
    args = parser.parse_args()
    if args.no_train and not args.write:
        parser.error("--no-train goes with --write")
    if args.refresh_notes:
        for entry in args.entry or ENTRIES:
            print(f"{entry}: {refresh_notes(entry, args.out)}")
        return 0
    if not args.no_train:
        ensure_world(args.world, TRAIN_WORLD)
    threads = torch.get_num_threads()
    trained_on = (f"cpu ({threads} thread{'' if threads == 1 else 's'})" if args.device == "cpu"
                  else torch.cuda.get_device_name())
    for entry in args.entry or ENTRIES:
        run, base = args.runs / entry, None
        if args.continue_epochs:
            run = continuation_folder(args.runs, entry, args.out)
            if args.no_train and not run.is_dir():
                parser.error(f"no continuation of {entry}'s shipped weights in {run} to write")
            base = start_continuation(entry, run, args.out)
        if not args.no_train:
            epochs = args.continue_epochs or args.epochs
            experiment = run_experiment(entry, args.world, epochs, args.device, args.workers, args.batch_size)
            if base is not None:
                experiment = replace_train(experiment, load_from=str(run / "base.safetensors"))
            record_session(run, trained_on)
            # A run may move between machines (a GPU, then a CPU): the world is the same TRAIN_WORLD in another folder.
            result = train(experiment, run, resume="auto", allow_changes=("train.workers", "data.root"),
                           device=args.device)  # fmt: skip
            print(f"{entry}: trained to step {result.steps}", flush=True)
        if args.write:
            ensure_world(args.demo_data, DEMO_WORLD)
            package(entry, run, args.demo_data, TRAIN_WORLD, args.device, trained_on, args.out, base)
    return 0


if __name__ == "__main__":
    sys.exit(main())
