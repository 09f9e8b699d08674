"""DAOcc's CPU hot spots before and after, interleaved in one run: the sparse LiDAR encoder (spconv against occkit's
gather-GEMM path) and the projection view transform (grid_sample + index_add against the batched gathers).

    python benchmarks/sparse_path.py [--pairs 5] [--train-pairs 6] [--data data/bench-1600x900]
        [--train-data data/demo] [--out docs/results/cpu/sparse_path.json]

Three measurements, each as pairs of the old and the new code, the order alternating from pair to pair:

1. ``daocc`` (paper size) on the benchmark's reference frame (``occkit bench``'s, a 10-sweep cloud): the LiDAR encoder
   stage (voxelization included, as ``occkit bench`` counts it) under each sparse backend, with its MACs, the same-run
   GEMM peak (a 4096 GEMM, timed after each pair) and the fraction reached;
2. the projection view transform of that frame: the previous implementation (``grid_sample`` of each camera's visible
   voxels, then ``index_add`` into the volume; kept below as the baseline) against today's (each voxel gathers its
   bilinear taps in one ``embedding_bag``), from the same image features, with their largest difference;
3. a ``daocc_tiny`` training step (forward, loss, backward, AdamW) on batches of a synthetic world, loaded
   beforehand, with each sparse backend: the speed-up is the median of the pairs' ratios.

The JSON holds every timing, the machine (:func:`occkit.machine.machine_info`) and the medians. Nothing else should run
on the machine meanwhile: spconv's CPU path slows several-fold when its threads compete for the cores.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from functools import partial
from pathlib import Path

import torch
import torch.nn.functional as F

from occkit import zoo
from occkit.bench.gemm import GemmProbe
from occkit.bench.sample import DEFAULT_DATA, load_sample
from occkit.bench.timing import paired_times
from occkit.data.collate import collate
from occkit.data.dataset import OccupancyDataset
from occkit.machine import machine_info
from occkit.models.complexity import count_macs
from occkit.models.inference import prepare_for_inference
from occkit.models.sparse import SparseConv3d, SubMConv3d
from occkit.models.sparse_gemm import build_neighbour_tables, gather_gemm_conv
from occkit.models.view_transform.projection import ProjectionViewTransform, SamplingPlan


def previous_view_transform(view: ProjectionViewTransform, features: torch.Tensor, plan: SamplingPlan) -> torch.Tensor:
    """The projection view transform as it ran before the batched gathers: per (sample, camera) a ``grid_sample`` of
    the voxels it sees, then an ``index_add`` of the samples into the volume, camera by camera."""
    batch, cameras = features.shape[:2]
    flat = features.flatten(0, 1)
    if view.reduce is not None:
        flat = view.reduce(flat)
    channels = flat.shape[1]
    # The old plan's layout, from today's: per (sample, camera) the voxels it sees, their coordinates and weights.
    slots = plan.weight > 0  # (B * P, M)
    voxel, slot = slots.nonzero(as_tuple=True)
    camera = plan.view[voxel, slot]
    order = torch.argsort(camera, stable=True)
    voxel, slot, camera = voxel[order], slot[order], camera[order]
    counts = torch.bincount(camera, minlength=batch * cameras)
    longest = int(counts.max())
    rank = torch.arange(voxel.numel()) - (torch.cumsum(counts, 0) - counts)[camera]
    grid = flat.new_zeros(batch * cameras, longest, 1, 2)
    target = torch.full((batch * cameras, longest), batch * plan.num_voxels, dtype=torch.int64)
    weight = flat.new_zeros(batch * cameras, longest)
    grid[camera, rank, 0] = plan.grid[voxel, slot]
    target[camera, rank] = voxel
    weight[camera, rank] = plan.weight[voxel, slot]

    def run() -> torch.Tensor:
        sampled = F.grid_sample(flat, grid, mode="bilinear", padding_mode="zeros",
                                align_corners=view.cfg.align_corners)  # fmt: skip
        sampled = sampled[..., 0].transpose(1, 2) * weight[..., None]
        volume = flat.new_zeros(batch * plan.num_voxels + 1, channels)
        for index in range(sampled.shape[0]):
            volume.index_add_(0, target[index], sampled[index])
        x, y, z = view.cfg.grid_size
        return volume[:-1].view(batch, x, y, z, channels).permute(0, 3, 4, 1, 2).reshape(batch, z * channels, x, y)

    return run


def _seconds(run) -> float:
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def _summary(old: list[float], new: list[float]) -> dict:
    return {"old_ms": [1000 * t for t in old], "new_ms": [1000 * t for t in new],
            "old_median_ms": 1000 * statistics.median(old), "new_median_ms": 1000 * statistics.median(new),
            "speedup": statistics.median(o / n for o, n in zip(old, new, strict=True))}  # fmt: skip


def _table_conv(tables, conv, rows):
    return gather_gemm_conv(rows, conv.weight, tables[conv.indice_key])


def new_path_breakdown(lidar, batch, runs: int, macs: int) -> dict:
    """Where the gather-GEMM path spends the stage (median ms of ``runs``), and the zeros its products multiply: per
    rulebook key the fill (active pairs over table entries), and the padded MACs against the pairs' MACs."""
    encoder = lidar.encoder
    times: dict[str, list[float]] = {"voxelize": [], "tables": [], "layers": [], "bev": []}
    for _ in range(runs):
        start = time.perf_counter()
        features, coords, _ = lidar.voxelize(batch.points, batch.num_points)
        voxelized = time.perf_counter()
        tables = build_neighbour_tables(encoder.conv_specs, coords, 1)
        built = time.perf_counter()
        rows = encoder.run_rows(features, partial(_table_conv, tables))
        ran = time.perf_counter()
        encoder.bev_from_rows(rows, tables[encoder.conv_specs[-1].key].out_coords, 1)
        done = time.perf_counter()
        for key, seconds in zip(times, (voxelized - start, built - voxelized, ran - built, done - ran), strict=True):
            times[key].append(seconds)
    padded = sum(tables[m.indice_key].table.numel() * m.in_channels * m.out_channels
                 for m in encoder.modules() if isinstance(m, (SubMConv3d, SparseConv3d)))  # fmt: skip
    return {"median_ms": {key: 1000 * statistics.median(values) for key, values in times.items()},
            "fill": {key: table.num_pairs / table.table.numel() for key, table in tables.items()},
            "padded_macs": padded, "pair_macs": macs}  # fmt: skip


def inference(data: Path, pairs: int, log) -> dict:
    """Measurements 1 and 2 on ``daocc``'s reference frame."""
    batch = load_sample("daocc", data, 1, log)
    model = zoo.build("daocc").eval()
    prepare_for_inference(model)
    lidar = model.lidar_encoder
    encoder = lidar.encoder
    probe = GemmProbe(4096, torch.float32, torch.device("cpu"))
    probe.select(3)
    with torch.no_grad():
        lidar_macs = count_macs(model, lambda: model(batch)).by_module["lidar_encoder"]
        encoder.backend = "spconv"
        reference = lidar(batch.points, batch.num_points)

        def stage(backend: str):
            def run() -> float:
                encoder.backend = backend
                return _seconds(lambda: lidar(batch.points, batch.num_points))
            return run

        encoder.backend = "gather_gemm"
        difference = float((lidar(batch.points, batch.num_points) - reference).abs().max())
        old, new = [], []
        for _ in range(pairs):
            o, n = paired_times(stage("spconv"), stage("gather_gemm"), 1)
            old += o
            new += n
            probe.measure()
        peak = max(probe.samples)
        encoder_result = _summary(old, new)
        encoder_result["new_path"] = new_path_breakdown(lidar, batch, pairs, lidar_macs)
        encoder_result.update(
            macs=lidar_macs, gemm_peak_gflops=peak, max_abs_difference=difference,
            old_gemm_fraction=2 * lidar_macs / (encoder_result["old_median_ms"] / 1000) / 1e9 / peak,
            new_gemm_fraction=2 * lidar_macs / (encoder_result["new_median_ms"] / 1000) / 1e9 / peak,
        )  # fmt: skip

        plan = model.plan(batch).sampling
        features = model.image_encoder(batch.images)
        view = model.view_transform
        old_view = previous_view_transform(view, features, plan)
        view_difference = float((old_view() - view(features, plan)).abs().max())
        old, new = paired_times(lambda: _seconds(old_view), lambda: _seconds(lambda: view(features, plan)), pairs)
        view_result = _summary(old, new)
        view_result["max_abs_difference"] = view_difference
    return {"lidar_encoder": encoder_result, "view_transform": view_result,
            "points": int(batch.num_points.sum()), "gemm_samples_gflops": probe.samples}  # fmt: skip


def training(data: Path, pairs: int) -> dict:
    """Measurement 3: ``daocc_tiny`` training steps under each sparse backend."""
    torch.manual_seed(0)
    experiment = zoo.experiment("daocc_tiny")
    dataset = OccupancyDataset(dataclasses.replace(experiment.data, root=str(data), split="train", augment=True))
    batches = [collate([dataset[(7 * i) % len(dataset)]]) for i in range(2 * pairs + 2)]
    model = zoo.build("daocc_tiny").train()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    torch.set_flush_denormal(True)  # as occkit train does on CPUs
    encoder = model.lidar_encoder.encoder
    steps = iter(range(10**6))

    def step(backend: str):
        def run() -> float:
            encoder.backend = backend
            batch = batches[next(steps) % len(batches)]
            start = time.perf_counter()
            loss = sum(model.loss(model(batch), batch).values())
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            return time.perf_counter() - start
        return run

    step("spconv")()
    step("gather_gemm")()  # warm-up of both
    old, new = paired_times(step("spconv"), step("gather_gemm"), pairs)
    return {"model": "daocc_tiny", "points": [int(b.num_points.sum()) for b in batches], **_summary(old, new)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=5, help="interleaved pairs of the inference measurements")
    parser.add_argument("--train-pairs", type=int, default=6, help="interleaved pairs of training steps")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the benchmark's 1600 x 900 world")
    parser.add_argument("--train-data", type=Path, default=Path("data/demo"), help="a world for the training steps")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/sparse_path.json"))
    args = parser.parse_args()
    if not args.train_data.exists():
        parser.error(f"{args.train_data} does not exist: write one with `occkit sim --out {args.train_data}`")
    result = {"machine": machine_info("cpu"), **inference(args.data, args.pairs, print),
              "training_step": training(args.train_data, args.train_pairs)}  # fmt: skip
    for name in ("lidar_encoder", "view_transform", "training_step"):
        entry = result[name]
        line = f"{name:<15} {entry['old_median_ms']:8.1f} ms -> {entry['new_median_ms']:8.1f} ms"
        line += f"  x{entry['speedup']:.2f}"
        if name == "lidar_encoder":
            line += f"  GEMM fraction {entry['old_gemm_fraction']:.0%} -> {entry['new_gemm_fraction']:.0%}"
        print(line)
    path = result["lidar_encoder"]["new_path"]
    print("gather-GEMM path: " + ", ".join(f"{k} {v:.0f} ms" for k, v in path["median_ms"].items())
          + f"; products {path['padded_macs'] / 1e9:.1f} GMACs for {path['pair_macs'] / 1e9:.1f} GMACs of pairs")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
