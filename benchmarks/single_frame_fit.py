"""How fast can a model fit one frame? A diagnostic of optimisation, not of generalisation.

    python benchmarks/single_frame_fit.py --model daocc_tiny [--data data/demo] [--frame 40] [--steps 80]
        [--lr 2e-3] [--lidar-only] [--no-detection] [--heatmap-init-std STD] [--out FILE]

Trains a fresh zoo model on a single training frame of a synthetic world (no augmentation, AdamW at a constant
rate, batch 1) and every 20 steps scores its prediction of that same frame: mIoU and geometry IoU under the camera
mask, and how many camera-visible voxels between the ground layer and the top layer it predicts occupied against
the truth's. A model that fits one frame slowly will learn slowly from many: comparing variants (``--lidar-only``,
``--no-detection``, ``--heatmap-init-std``) finds the part that holds learning back, in minutes rather than in
full training runs. Writes the curve to ``--out`` (default ``benchmarks/results/single_frame_fit_<model>.json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import torch

from occkit import zoo
from occkit.data.collate import collate
from occkit.data.dataset import OccupancyDataset
from occkit.label_space import OCC3D_SPACE
from occkit.metrics.confusion import OccupancyMetric


def _variant(name: str, args: argparse.Namespace):
    """The zoo entry's experiment with the asked changes."""
    experiment = zoo.experiment(name)
    model, data = experiment.model, dataclasses.replace(experiment.data, root=str(args.data), augment=False)
    if args.lidar_only:
        model, data = dataclasses.replace(model, image=None), dataclasses.replace(data, cameras=())
    if args.no_detection:
        model, data = dataclasses.replace(model, detection=None), dataclasses.replace(data, boxes=False)
    if args.heatmap_init_std is not None:
        std = None if args.heatmap_init_std <= 0 else args.heatmap_init_std
        model = dataclasses.replace(model, detection=dataclasses.replace(model.detection, heatmap_init_std=std))
    return dataclasses.replace(experiment, model=model, data=data)


def _score(logits: torch.Tensor, batch) -> dict:
    prediction = logits.argmax(1)[0]
    labels, mask = batch.voxel_semantics[0].long(), batch.mask_camera[0].bool()
    metric = OccupancyMetric.for_space(OCC3D_SPACE)
    metric.update(labels.numpy(), prediction.to(torch.uint8).numpy(), mask.numpy())
    scores = metric.compute()
    free = OCC3D_SPACE.free_index
    # Above the ground layer (z index 2 holds z = 0) and below the top one: where the objects are.
    middle = slice(3, labels.shape[-1] - 1)
    return {"miou": scores["miou"], "iou": scores["iou"],
            "middle_predicted": int(((prediction != free) & mask)[..., middle].sum()),
            "middle_true": int(((labels != free) & mask)[..., middle].sum())}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="daocc_tiny", choices=zoo.names())
    parser.add_argument("--data", type=Path, default=Path("data/demo"))
    parser.add_argument("--frame", type=int, default=40, help="index of the frame in the training split")
    parser.add_argument("--steps", type=int, default=80)
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--lidar-only", action="store_true", help="DAOcc without its camera branch")
    parser.add_argument("--no-detection", action="store_true", help="DAOcc without its detection head")
    parser.add_argument("--heatmap-init-std", type=float, default=None,
                        help="DAOcc's detection heatmap: normal(0, STD) output weights; 0: Kaiming (mmdet3d)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if not args.data.exists():
        parser.error(f"{args.data} does not exist: write one with `occkit demo` or `occkit sim --out {args.data}`")
    torch.manual_seed(args.seed)
    experiment = _variant(args.model, args)
    dataset = OccupancyDataset(experiment.data)
    model = zoo.build_from_config(experiment.architecture, experiment.model).train()
    optimizer = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=experiment.train.weight_decay)
    torch.set_flush_denormal(True)
    batch = collate([dataset[args.frame]])
    curve, started = [], time.perf_counter()
    for step in range(1, args.steps + 1):
        output = model(batch)
        losses = model.loss(output, batch)
        optimizer.zero_grad(set_to_none=True)
        sum(losses.values()).backward()
        optimizer.step()
        if step % 20 == 0 or step == args.steps:
            row = {"step": step, "seconds": time.perf_counter() - started,
                   "losses": {k: v.item() for k, v in losses.items() if "/" not in k},
                   **_score(output.occupancy.detach(), batch)}  # fmt: skip
            curve.append(row)
            print(f"step {step}: mIoU {100 * row['miou']:.1f}, IoU {100 * row['iou']:.1f}, voxels above the ground "
                  f"{row['middle_predicted']} predicted / {row['middle_true']} true, losses "
                  + ", ".join(f"{k} {v:.3f}" for k, v in row["losses"].items()), flush=True)  # fmt: skip
    out = args.out or Path("benchmarks/results") / f"single_frame_fit_{args.model}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "curve": curve}, indent=2) + "\n")


if __name__ == "__main__":
    main()
