"""Where does a camera-only model's learning stall? flashocc_tiny with parts of its BEV replaced by oracles.

    python benchmarks/camera_probe.py [--data data/demo] [--steps 200] [--lr 2e-3] [--probes NAME ...]
        [--stride 16] [--seed 0] [--out FILE]

Each probe trains a fresh ``flashocc_tiny`` for ``--steps`` optimizer steps of batch 1 on the training scenes, with
the zoo's recipe (augmentation, AdamW, warm-up and cosine, clipping; ``--lr`` replaces the peak rate), and scores
the held-out scenes (mIoU and IoU under the camera mask). The oracle acts in training and in scoring alike:

- ``model``: the model as the zoo has it.
- ``oracle-depth``: every feature cell with a LiDAR point gets a one-hot depth distribution at the LiDAR depth (the
  nearest point of the cell, BEVDepth's target) in place of the predicted one.
- ``oracle-depth-4z``: ``oracle-depth`` with the LSS grid cut into 4 height slices folded into channels, so that the
  BEV keeps the height of the lifted features (FlashOcc pools one slice).
- ``geometry-4z``: ``oracle-depth-4z`` with a constant context (cells without a LiDAR point add nothing): the BEV
  holds where the LiDAR-depth rays end per slice and nothing of the images, a LiDAR-like input at the cameras'
  sampling density.
- ``true-occupancy``: the BEV is the label's occupancy (its 16 layers as 16 channels): what the BEV encoder and the
  channel-to-height head learn in the budget from a perfect input.

A probe that scores far above ``model`` locates what the model fails to learn before it. Writes every probe's scores
to ``--out`` (default ``benchmarks/results/camera_probe.json``).
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
from occkit.engine.evaluate import evaluation_dataset, score_model
from occkit.engine.schedule import Schedule
from occkit.experiment import Experiment, replace_train

PROBES = ("model", "oracle-depth", "oracle-depth-4z", "geometry-4z", "true-occupancy")


def probe_experiment(probe: str, args: argparse.Namespace) -> Experiment:
    """flashocc_tiny on ``args.data`` with the probe's data (LiDAR depth maps) and grid changes."""
    experiment = zoo.experiment("flashocc_tiny")
    model, data = experiment.model, dataclasses.replace(experiment.data, root=str(args.data), index=None)
    if args.stride != model.lss.feature_stride:
        stages = {8: (2, 3), 16: (3, 4)}[args.stride]
        model = dataclasses.replace(model, image=dataclasses.replace(model.image, out_stages=stages),
                                    lss=dataclasses.replace(model.lss, feature_stride=args.stride))  # fmt: skip
    if probe.startswith(("oracle-depth", "geometry")):
        data = dataclasses.replace(data, sweeps=0, depth_downsample=args.stride)
    if probe.endswith("-4z"):
        x, y, _ = model.lss.grid_size
        model = dataclasses.replace(model, lss=dataclasses.replace(model.lss, grid_size=(x, y, 4)),
                                    bev=dataclasses.replace(model.bev, in_channels=4 * model.lss.context_channels))
    if probe == "true-occupancy":
        height = model.occupancy.height
        model = dataclasses.replace(model, bev=dataclasses.replace(model.bev, in_channels=height))
    experiment = dataclasses.replace(experiment, model=model, data=data)
    return replace_train(experiment, lr=args.lr, max_steps=args.steps, seed=args.seed)


def attach(probe: str, model: torch.nn.Module) -> None:
    """Hooks that put the probe's oracle into ``model`` (a FlashOcc) for every batch it runs."""
    seen: dict = {}
    forward = model.forward

    def remember(batch, **kwargs):  # on the instance: ``predict`` calls ``self.forward``, past module hooks
        seen["batch"] = batch
        return forward(batch, **kwargs)

    model.forward = remember
    transform = model.view_transform
    bins = transform.num_depth_bins
    if probe.startswith(("oracle-depth", "geometry")):

        def depth_net_output(_, __, output: torch.Tensor) -> torch.Tensor:  # (B*N, D + C, h, w)
            depth = seen["batch"].depth_maps.flatten(0, 1)  # (B*N, h, w), 0 where no point
            low, _, step = transform.cfg.depth_range
            index = ((depth - low) / step).floor().long()
            valid = (depth > 0) & (index >= 0) & (index < bins)
            one_hot = torch.nn.functional.one_hot(index.clamp(0, bins - 1), bins).permute(0, 3, 1, 2).bool()
            # Logits of -1e4 off the bin make an exact one-hot softmax; cells without a point keep the prediction.
            logits = torch.where(valid[:, None], torch.where(one_hot, 0.0, -1e4), output[:, :bins])
            context = output[:, bins:]
            if probe.startswith("geometry"):  # ones where the ray's end is known; cells without a point add nothing
                context = valid[:, None].to(context.dtype).expand_as(context)
            return torch.cat([logits, context], dim=1)

        transform.depth_net.register_forward_hook(depth_net_output)
    if probe == "true-occupancy":
        free = model.cfg.occupancy.free_index

        def true_bev(_, __, output: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
            bev, depth = output
            occupied = (seen["batch"].voxel_semantics != free).to(bev.dtype).permute(0, 3, 1, 2)  # (B, Z, X, Y)
            return occupied + 0.0 * bev.sum(), depth  # keeps the image path in the graph (no unused parameters)

        transform.register_forward_hook(true_bev)


def run_probe(probe: str, args: argparse.Namespace) -> dict:
    """Train and score one probe."""
    experiment = probe_experiment(probe, args)
    cfg = experiment.train
    torch.manual_seed(cfg.seed)
    model = zoo.build_from_config(experiment.architecture, experiment.model).train()
    attach(probe, model)
    dataset = OccupancyDataset(experiment.data)
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)
    schedule = Schedule(cfg, args.steps, len(dataset))
    order = torch.randperm(len(dataset) * (args.steps // len(dataset) + 1), generator=torch.Generator().manual_seed(
        cfg.seed)) % len(dataset)  # fmt: skip
    started = time.perf_counter()
    for step in range(args.steps):
        dataset.set_epoch(step // len(dataset))
        batch = collate([dataset[int(order[step])]])
        for group in optimizer.param_groups:
            group["lr"] = schedule.lr(step)
        losses = model.loss(model(batch), batch)
        optimizer.zero_grad(set_to_none=True)
        sum(losses.values()).backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        optimizer.step()
    train_seconds = time.perf_counter() - started
    scores = score_model(model.eval(), evaluation_dataset(experiment, args.data, "val"), rayiou=False)
    result = {"probe": probe, "steps": args.steps, "lr": cfg.lr, "stride": args.stride, "seed": cfg.seed,
              "miou": scores["miou"], "iou": scores["iou"], "per_class_iou": scores["per_class_iou"],
              "train_seconds": train_seconds}  # fmt: skip
    print(f"{probe}: mIoU {100 * result['miou']:.1f}, IoU {100 * result['iou']:.1f} "
          f"({train_seconds / 60:.1f} min training)", flush=True)
    return result


def _settings(result: dict) -> tuple:
    """What identifies a probe's result: a rerun with the same settings replaces it."""
    return result["probe"], result["steps"], result["lr"], result["stride"], result["seed"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/demo"))
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--lr", type=float, default=2e-3, help="peak learning rate (the zoo's: 2e-3)")
    parser.add_argument("--probes", nargs="+", choices=PROBES, default=list(PROBES))
    parser.add_argument("--stride", type=int, choices=(8, 16), default=16, help="image feature stride")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/camera_probe.json"))
    args = parser.parse_args()
    if not args.data.exists():
        parser.error(f"{args.data} does not exist: write one with `occkit demo` or `occkit sim --out {args.data}`")
    torch.set_flush_denormal(True)
    results = [run_probe(probe, args) for probe in args.probes]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    previous = json.loads(args.out.read_text()) if args.out.is_file() else []
    rerun = {_settings(r) for r in results}
    keep = [r for r in previous if _settings(r) not in rerun]
    args.out.write_text(json.dumps(keep + results, indent=2) + "\n")


if __name__ == "__main__":
    main()
