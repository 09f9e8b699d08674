"""How far labels built from sensor data are from the truth: ``occkit label`` scored against the sim's exact labels.

    python benchmarks/label_quality.py [--data data/label-world] [--seed 2026] [--scenes 6] [--frames 16]
        [--variants NAME ...] [--workers 2] [--train-steps 500] [--out benchmarks/results/label_quality]

Writes a synthetic world (unless ``--data`` already holds one), labels it with each pipeline variant
(:data:`VARIANTS`: sweep counts, with and without Poisson densification) and scores every key frame's generated
labels against the exact ones:

* under the exact camera mask (the Occ3D protocol), the exact LiDAR mask, and every voxel: geometry IoU, mIoU and
  per-class IoU, the challenge's confusion-matrix definitions (:mod:`occkit.metrics.confusion`);
* each generated mask against the exact mask: IoU, and the share of the exact mask the generated one covers;
* time per key frame (labelling wall time x workers / key frames).

With ``--train-steps N`` it then trains ``daocc_tiny`` for N steps on the world's training scenes twice, once on the
exact labels and once on the best variant's generated labels (same seed, same everything else), and scores both on
the exact labels of the held-out scenes: what label noise costs a model.

Resumable: each variant's labels stay in ``<out>/labels/<variant>`` and each training run's result in ``<out>``;
a rerun reuses them. Results: ``<out>/label_quality.json`` and ``label_quality.md``. Time it on an idle machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np

from occkit.classes import OCC3D
from occkit.data.labels import read_occ3d_labels
from occkit.data.names import folder_name
from occkit.geometry.grid import OCC3D_GRID
from occkit.labeling.pipeline import SUMMARY_FILE, LabelConfig, label_dataset
from occkit.metrics.confusion import confusion_matrix, geometry_iou, iou_from_confusion, miou

#: Pipeline variants: name -> settings.
VARIANTS: dict[str, LabelConfig] = {
    "key frames only": LabelConfig(sweeps=0),
    "3 sweeps per interval": LabelConfig(sweeps=3),
    "all sweeps": LabelConfig(),
    "all sweeps + Poisson": LabelConfig(densify="poisson"),
}
#: Masks the labels are scored under: name -> the exact labels' mask (None: every voxel).
MASKS = {"camera": "mask_camera", "lidar": "mask_lidar", "none": None}


def ensure_world(args: argparse.Namespace) -> None:
    """Simulate the world into ``--data`` unless a world with lidarseg is there."""
    if (args.data / "v1.0-synth" / "lidarseg.json").is_file():
        return
    from occkit.sim.generate import SimConfig, simulate_dataset

    config = SimConfig(scenes=args.scenes, frames=args.frames, seed=args.seed, image_size=(400, 225))
    print(f"[labels] simulating {args.scenes} scenes x {args.frames} key frames (seed {args.seed}) into {args.data}",
          flush=True)  # fmt: skip
    simulate_dataset(config, args.data, workers=args.workers, overwrite=args.data.exists())


def _labels_folder(args: argparse.Namespace, variant: str) -> Path:
    return args.out / "labels" / folder_name(variant)


def label_variant(name: str, args: argparse.Namespace) -> dict:
    """Label the world with one variant (reused when its labels exist with the same settings); its summary."""
    config = VARIANTS[name]
    out = _labels_folder(args, name)
    summary_file = out / SUMMARY_FILE
    if summary_file.is_file():
        summary = json.loads(summary_file.read_text())
        if summary["config"] == json.loads(json.dumps(dataclasses.asdict(config))):
            print(f"[labels] {name}: reusing {out}", flush=True)
            return summary
    print(f"[labels] {name}: labelling into {out}", flush=True)
    return label_dataset(args.data, "v1.0-synth", out, config, workers=args.workers, overwrite=True)


def score(labels: Path, data: Path) -> dict:
    """Generated labels under ``labels`` against the exact ones of ``data``, per mask (module doc)."""
    confusion = {mask: np.zeros((18, 18), np.int64) for mask in MASKS}
    agreement = {name: np.zeros(3, np.int64) for name in ("mask_camera", "mask_lidar")}  # both, generated, exact
    files = sorted(labels.glob("*/*/labels.npz"))
    for path in files:
        generated = read_occ3d_labels(path)
        exact = read_occ3d_labels(data / "gts" / path.relative_to(labels))
        for mask, key in MASKS.items():
            keep = getattr(exact, key) if key else None
            confusion[mask] += confusion_matrix(exact.semantics, generated.semantics, keep)
        for key, counts in agreement.items():
            a, b = getattr(generated, key), getattr(exact, key)
            counts += [int((a & b).sum()), int(a.sum()), int(b.sum())]
    result = {"frames": len(files)}
    for mask, cm in confusion.items():
        per_class = iou_from_confusion(cm)
        result[mask] = {
            "iou": geometry_iou(cm),
            "miou": miou(cm),
            "per_class_iou": {OCC3D.classes[c]: (None if math.isnan(per_class[c]) else float(per_class[c]))
                              for c in OCC3D.semantic_ids},  # fmt: skip
        }
    for key, (both, generated, exact) in agreement.items():
        result[key] = {"iou": both / max(generated + exact - both, 1), "recall": both / max(exact, 1),
                       "precision": both / max(generated, 1)}  # fmt: skip
    return result


#: Distance bins (m from the ego, in the ground plane) of the recall table.
DISTANCE_BINS = (0, 10, 20, 30, 40, 60)


def recall_by_distance(labels: Path, data: Path) -> dict:
    """Per class and distance bin, under the exact camera mask: the exact voxels, and the shares the generated
    labels give the same class, leave free (no point ever landed there), or give another class."""
    centres = (np.arange(OCC3D_GRID.shape[0]) + 0.5) * OCC3D_GRID.voxel_size[0] + OCC3D_GRID.lower[0]
    distance = np.hypot(centres[:, None], centres[None, :])
    bin_of = np.digitize(distance, DISTANCE_BINS) - 1  # (X, Y); beyond the last edge -> len(bins) - 1
    bins = len(DISTANCE_BINS) - 1
    counts = np.zeros((OCC3D.num_classes, bins, 4), np.int64)  # exact, same, free, other
    for path in sorted(labels.glob("*/*/labels.npz")):
        generated = read_occ3d_labels(path)
        exact = read_occ3d_labels(data / "gts" / path.relative_to(labels))
        seen = exact.mask_camera & (exact.semantics != OCC3D.empty_index)
        cls = exact.semantics[seen].astype(np.int64)
        where = np.broadcast_to(bin_of[:, :, None], seen.shape)[seen]
        ok = where < bins
        cls, where, got = cls[ok], where[ok], generated.semantics[seen][ok]
        outcome = np.where(got == cls, 1, np.where(got == OCC3D.empty_index, 2, 3))
        np.add.at(counts, (cls, where, 0), 1)
        np.add.at(counts, (cls, where, outcome), 1)
    table = {}
    for c in OCC3D.semantic_ids:
        rows = []
        for b in range(bins):
            total = int(counts[c, b, 0])
            rows.append({"from": DISTANCE_BINS[b], "to": DISTANCE_BINS[b + 1], "voxels": total,
                         **{key: (int(counts[c, b, i]) / total if total else None)
                            for i, key in ((1, "recall"), (2, "free"), (3, "other"))}})  # fmt: skip
        table[OCC3D.classes[c]] = rows
    return table


def train_on(labels: str, label_root: Path | None, args: argparse.Namespace) -> dict:
    """``daocc_tiny`` trained on the world's training scenes with the given labels, scored on exact val labels."""
    result_file = args.out / f"train-{folder_name(labels)}.json"
    if result_file.is_file():
        return json.loads(result_file.read_text())
    import torch

    from occkit import zoo
    from occkit.engine.evaluate import evaluation_dataset, load_trained, score_model
    from occkit.engine.train import train
    from occkit.experiment import replace_train

    experiment = zoo.experiment("daocc_tiny")
    label_folder = str(label_root) if label_root is not None else None
    experiment = dataclasses.replace(experiment, data=dataclasses.replace(experiment.data, root=str(args.data),
                                                                          label_root=label_folder))  # fmt: skip
    experiment = replace_train(experiment, max_steps=args.train_steps, epochs=10_000, val_every=-1,
                               checkpoint_every=100, seed=0)  # fmt: skip
    folder = args.runs / folder_name(labels)
    print(f"[labels] daocc_tiny on {labels} labels: training {args.train_steps} steps into {folder}", flush=True)
    start = time.perf_counter()
    train(experiment, folder, resume="auto", progress=False)
    seconds = time.perf_counter() - start
    model, trained = load_trained(sorted(folder.glob("step-*.pt"))[-1])
    # Scored on the exact labels whatever it trained on.
    trained = dataclasses.replace(trained, data=dataclasses.replace(trained.data, label_root=None))
    dataset = evaluation_dataset(trained, args.data, "val")
    scores = score_model(model, dataset, workers=1)
    result = {"labels": labels, "label_root": label_folder, "steps": args.train_steps, "train_seconds": seconds,
              "threads": torch.get_num_threads(), "frames": scores["frames"],
              **{key: scores[key] for key in ("miou", "iou", "rayiou", "per_class_iou")}}  # fmt: skip
    result_file.write_text(json.dumps(result, indent=2) + "\n")
    print(f"[labels] daocc_tiny on {labels} labels: mIoU {100 * result['miou']:.2f}, IoU {100 * result['iou']:.2f}",
          flush=True)  # fmt: skip
    return result


def _pct(value: float | None) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{100 * value:.1f}"


def markdown(report: dict) -> str:
    world = report["world"]
    lines = [f"Synthetic world: {world['scenes']} scenes x {world['frames']} key frames, seed {world['seed']}; "
             f"{report['frames']} key frames scored.", "",
             "| pipeline | camera mask: IoU | mIoU | LiDAR mask: IoU | mIoU | all voxels: IoU | mIoU | "
             "mask_camera IoU | mask_lidar IoU | s / key frame |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for name, row in report["variants"].items():
        s = row["scores"]
        lines.append(f"| {name} | {_pct(s['camera']['iou'])} | {_pct(s['camera']['miou'])} | {_pct(s['lidar']['iou'])} "
                     f"| {_pct(s['lidar']['miou'])} | {_pct(s['none']['iou'])} | {_pct(s['none']['miou'])} | "
                     f"{_pct(s['mask_camera']['iou'])} | {_pct(s['mask_lidar']['iou'])} | "
                     f"{row['seconds_per_key_frame']:.2f} |")  # fmt: skip
    classes = list(OCC3D.classes[c] for c in OCC3D.semantic_ids)
    lines += ["", "Per-class IoU under the exact camera mask:", "",
              "| pipeline | " + " | ".join(classes) + " |", "| --- " * (len(classes) + 1) + "|"]  # fmt: skip
    for name, row in report["variants"].items():
        per_class = row["scores"]["camera"]["per_class_iou"]
        lines.append(f"| {name} | " + " | ".join(_pct(per_class[c]) for c in classes) + " |")
    if report.get("recall_by_distance"):
        name, table = report["recall_by_distance"]["variant"], report["recall_by_distance"]["classes"]
        edges = [f"{row['from']}-{row['to']} m" for row in next(iter(table.values()))]
        lines += ["", f"Recall by distance from the ego under the exact camera mask ({name}): the share of the exact "
                  "voxels of a class that the generated labels give that class; in brackets the share they leave free "
                  "(no point landed there):", "", "| class | " + " | ".join(edges) + " |",
                  "| --- " * (len(edges) + 1) + "|"]  # fmt: skip
        for cls in ("driveable_surface", "sidewalk", "terrain", "car", "manmade", "vegetation"):
            cells = [f"{_pct(r['recall'])} ({_pct(r['free'])})" if r["voxels"] else "-" for r in table[cls]]
            lines.append(f"| {cls} | " + " | ".join(cells) + " |")
    if report.get("training"):
        lines += ["", "daocc_tiny scored on the exact labels of the held-out scenes:", "",
                  "| trained on | steps | mIoU | IoU | RayIoU |", "| --- | --- | --- | --- | --- |"]  # fmt: skip
        for row in report["training"]:
            lines.append(f"| {row['labels']} | {row['steps']} | {_pct(row['miou'])} | {_pct(row['iou'])} | "
                         f"{_pct(row['rayiou'])} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/label-world"))
    parser.add_argument("--seed", type=int, default=2026, help="world seed (one no setting was tuned on)")
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    parser.add_argument("--workers", type=int, default=2, help="scenes labelled (and simulated) in parallel")
    parser.add_argument("--train-steps", type=int, default=0, help="also train daocc_tiny on exact vs generated")
    parser.add_argument("--train-on", default="all sweeps", choices=list(VARIANTS),
                        help="the variant whose labels daocc_tiny trains on")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/label_quality"))
    parser.add_argument("--runs", type=Path, default=Path("runs/label_quality"))
    args = parser.parse_args()

    ensure_world(args)
    import yaml

    written = yaml.safe_load((args.data / "sim_config.yaml").read_text())
    world = {key: written[key] for key in ("scenes", "frames", "seed", "image_size")}
    report: dict = {"world": world, "workers": args.workers, "variants": {}}
    for name in args.variants:
        summary = label_variant(name, args)
        scores = score(_labels_folder(args, name), args.data)
        report["frames"] = scores["frames"]
        report["variants"][name] = {"config": summary["config"], "scores": scores,
                                    "seconds_per_key_frame": summary["seconds_per_key_frame"],
                                    "seconds": summary["seconds"], "workers": summary["workers"]}  # fmt: skip
        print(f"[labels] {name}: camera mask IoU {100 * scores['camera']['iou']:.1f}, mIoU "
              f"{100 * scores['camera']['miou']:.1f}; {summary['seconds_per_key_frame']:.2f} s per key frame",
              flush=True)  # fmt: skip
    best = max(report["variants"], key=lambda name: report["variants"][name]["scores"]["camera"]["miou"])
    report["recall_by_distance"] = {"variant": best,
                                    "classes": recall_by_distance(_labels_folder(args, best), args.data)}
    if args.train_steps:
        label_variant(args.train_on, args)
        report["training"] = [train_on("exact", None, args),
                              train_on(args.train_on, _labels_folder(args, args.train_on), args)]  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "label_quality.json").write_text(json.dumps(report, indent=2) + "\n")
    (args.out / "label_quality.md").write_text(markdown(report))
    print(markdown(report))


if __name__ == "__main__":
    main()
