"""occkit's GPU measurements in one prepared run: inference latency, memory, GEMM fraction and fp16 / bf16 agreement,
and training throughput with the data loader's share, per model; one JSON per model.

    python benchmarks/gpu_suite.py [--device cuda] [--out docs/results/gpu] [--models NAME ...] [--quick]

For each model (default :data:`MODELS`, the paper entries the papers report speed for):

* **inference**: ``occkit bench`` (:func:`occkit.bench.run_bench`) at fp32 and under fp16 and bf16 autocast (bf16
  only on a CPU), batch 1, on the bench's 1600 x 900 synthetic key frame: median and p90 latency, FPS, peak memory,
  the same-run GEMM peak at that precision and the fraction reached, stage times; with ``--compile`` also the
  fast path with ``torch.compile``;
* **agreement**: the arg-max of the occupancy logits under fp16 / bf16 autocast against fp32, on that frame, over
  every voxel (random weights, or the shipped ones for a CPU-sized entry that has them);
* **training**: the entry's own training step at its per-GPU batch and precision (AdamW, autocast and a gradient
  scaler for fp16), fed by a ``DataLoader`` with ``--workers`` processes reading and augmenting the synthetic world's
  1600 x 900 JPEGs: median step time, samples per second, peak memory, and the share of each step spent waiting for
  the loader (the device's idle fraction, ~0 when the loader keeps up); and the wall-clock time of the paper's
  schedule projected to 8 such devices (nuScenes' 28,130 training samples per epoch, perfect scaling; CBGS epochs
  are longer, which the JSON says where the recipe uses it).

Each JSON names the device, driver, CUDA, torch and occkit versions. ``--device cpu --quick`` runs the same code on
the CPU-sized entries with one or two passes of each (a test does); every number in ``docs/results/gpu/`` comes from a
run on the device it names.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from occkit import __version__, zoo
from occkit.bench import DEFAULT_DATA, BenchConfig, load_sample, machine_info, run_bench
from occkit.data.collate import collate
from occkit.data.dataset import OccupancyDataset
from occkit.data.loader import sample_loader
from occkit.engine.reference_frame import simulate_reference_world
from occkit.shipped import shipped_entries

MODELS = ("flashocc_m0", "flashocc_m1", "da_occ", "da_occ_16f", "daocc", "daocc_no_detection")
QUICK_MODELS = ("flashocc_tiny", "da_occ_tiny", "daocc_tiny")
#: nuScenes' training split, the papers' epoch.
NUSCENES_TRAIN_SAMPLES = 28130
#: Key frames of the training world (1600 x 900, one scene): enough distinct frames for the loader to read.
TRAIN_WORLD_FRAMES = 12


def _precisions(device: torch.device) -> tuple[str, ...]:
    return ("fp32", "fp16", "bf16") if device.type == "cuda" else ("fp32", "bf16")


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def agreement(entry: str, device: torch.device, data: Path | None) -> dict[str, float]:
    """Share of voxels whose arg-max class under each reduced-precision autocast equals fp32's, on the bench frame."""
    weights = "synthetic" if entry in shipped_entries() else None
    torch.manual_seed(0)
    model = zoo.build(entry, weights=weights).to(device).eval()
    batch = load_sample(entry, data, log=lambda _: None).to(device)
    with torch.no_grad():
        reference = model(batch).occupancy.argmax(dim=1)
        shares = {}
        for precision in _precisions(device)[1:]:
            dtype = {"fp16": torch.float16, "bf16": torch.bfloat16}[precision]
            with torch.autocast(device.type, dtype=dtype):
                predicted = model(batch).occupancy.float().argmax(dim=1)
            shares[precision] = float((predicted == reference).float().mean())
    return {"weights": weights or "random", **shares}


def training_throughput(entry: str, device: torch.device, root: Path, steps: int, warmup: int, workers: int) -> dict:
    """The entry's training step on batches a ``DataLoader`` reads from ``root``: times, memory, loader share."""
    experiment = zoo.experiment(entry)
    train = experiment.train
    data = dataclasses.replace(experiment.data, root=str(root), split="all")
    dataset = OccupancyDataset(data)
    loader = sample_loader(dataset, collate_fn=collate, batch_size=train.batch_size, shuffle=True,
                           num_workers=workers, persistent_workers=workers > 0, drop_last=True,
                           generator=torch.Generator().manual_seed(0))  # fmt: skip
    torch.manual_seed(0)
    model = zoo.build(entry).to(device).train()
    optimizer = torch.optim.AdamW(model.parameters(), lr=train.lr, weight_decay=train.weight_decay)
    dtype = {"fp16": torch.float16, "bf16": torch.bfloat16}.get(train.precision)
    scaler = torch.amp.GradScaler(device.type, enabled=train.precision == "fp16")
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    batches = iter(_endless(loader))
    step_times, waits = [], []
    for index in range(warmup + steps):
        started = time.perf_counter()
        batch = next(batches).to(device)
        loaded = time.perf_counter()
        with torch.autocast(device.type, dtype=dtype or torch.float32, enabled=dtype is not None):
            output = model(batch)
            loss = sum(model.loss(output, batch).values())
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(loss).backward()
        scaler.step(optimizer)
        scaler.update()
        _synchronize(device)
        if index >= warmup:
            step_times.append(time.perf_counter() - started)
            waits.append(loaded - started)
    step = statistics.median(step_times)
    samples = NUSCENES_TRAIN_SAMPLES * train.epochs
    return {
        "batch_per_device": train.batch_size, "precision": train.precision, "loader_workers": workers,
        "steps_timed": steps, "step_seconds": {"median": step, "all": step_times},
        "samples_per_second": train.batch_size / step,
        "loader_wait_fraction": sum(waits) / sum(step_times),
        "peak_memory_bytes": torch.cuda.max_memory_allocated(device) if device.type == "cuda" else None,
        "projection_8_devices": {
            "epochs": train.epochs, "sampler": train.sampler, "samples": samples,
            "hours": samples / (8 * train.batch_size) * step / 3600,
            "assumes": f"{NUSCENES_TRAIN_SAMPLES} samples per epoch (nuScenes train), 8 devices each taking this "
                       "step on its own batch, perfect scaling" + ("; CBGS resamples the epoch to more samples, not "
                                                                  "counted" if train.sampler == "cbgs" else ""),
        },
    }  # fmt: skip


def _endless(loader):
    while True:
        yield from loader


def _versions(device: torch.device) -> dict:
    versions = {"occkit": __version__, "torch": torch.__version__, "python": sys.version.split()[0]}
    try:
        import spconv

        versions["spconv"] = getattr(spconv, "__version__", "installed")
    except ImportError:
        versions["spconv"] = None
    if device.type == "cuda":
        try:
            versions["driver"] = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                                                capture_output=True, text=True, check=True).stdout.strip()  # fmt: skip
        except (OSError, subprocess.CalledProcessError):
            versions["driver"] = None
    return versions


def run_model(entry: str, args: argparse.Namespace, device: torch.device, train_root: Path) -> dict:
    result: dict = {"model": entry, "machine": machine_info(device), "versions": _versions(device),
                    "inference": {}, "written": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}  # fmt: skip
    quick = args.quick
    for precision in _precisions(device):
        cfg = BenchConfig(model=entry, device=str(device), precision=precision, iters=1 if quick else 20,
                          warmup=1 if quick else 5, optimizations=("fixed_calibration", "fold_bn"),
                          stage_iters=1 if quick else 3, gemm_size=256 if quick else None,
                          gemm_repeats=1 if quick else 3, data=args.data)  # fmt: skip
        result["inference"][precision] = run_bench(cfg, log=lambda text: print(f"  {text}", flush=True))
    if args.compile:
        cfg = BenchConfig(model=entry, device=str(device), precision="fp16" if device.type == "cuda" else "fp32",
                          iters=20, optimizations=("fixed_calibration", "fold_bn", "compile"), data=args.data)
        result["inference"]["compiled"] = run_bench(cfg, log=lambda text: print(f"  {text}", flush=True))
    result["agreement"] = agreement(entry, device, None if args.data is None else Path(args.data))
    result["training"] = training_throughput(entry, device, train_root, steps=2 if quick else 10,
                                             warmup=1 if quick else 3, workers=args.workers)  # fmt: skip
    return result


def summary(result: dict) -> str:
    lines = [f"{result['model']} on {result['machine']['device']}"]
    for precision, bench in result["inference"].items():
        lines.append(f"  {precision}: {bench['latency_ms']['median']:.2f} ms median, {bench['fps']:.1f} FPS, "
                     f"{bench['peak_memory']['bytes'] / 2**20:.0f} MiB, {100 * bench['gemm_fraction']:.0f}% of GEMM")
    lines.append("  agreement with fp32: " + ", ".join(f"{k} {100 * v:.2f}%" for k, v in result["agreement"].items()
                                                       if k != "weights"))  # fmt: skip
    training = result["training"]
    lines.append(f"  training: {1000 * training['step_seconds']['median']:.0f} ms/step, "
                 f"{training['samples_per_second']:.2f} samples/s, "
                 f"loader wait {100 * training['loader_wait_fraction']:.0f}%, "
                 f"8 devices: {training['projection_8_devices']['hours']:.1f} h")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="cuda (default) or cpu")
    parser.add_argument("--out", type=Path, default=Path("docs/results/gpu"), help="folder of the JSON files")
    parser.add_argument("--models", nargs="+", default=None, help="zoo entries (default: the paper entries)")
    parser.add_argument("--quick", action="store_true", help="one or two passes of everything (a dry run)")
    parser.add_argument("--compile", action="store_true", help="also the fast path with torch.compile (slow start)")
    parser.add_argument("--workers", type=int, default=4, help="loader processes of the training measurement")
    parser.add_argument("--data", default=None, help="dataset of the inference frame (default: the bench's world)")
    parser.add_argument("--train-data", type=Path, default=Path("data/gpu-suite-train"),
                        help="the training measurement's world, simulated if absent (1600 x 900, one scene)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for but CUDA is not available (use --device cpu --quick for a dry run)")
    models = args.models or (QUICK_MODELS if args.quick else MODELS)
    if not args.train_data.exists():
        print(f"simulating the training world into {args.train_data}", flush=True)
        simulate_reference_world(args.train_data, (1600, 900), frames=2 if args.quick else TRAIN_WORLD_FRAMES,
                                 version="v1.0-synth")  # fmt: skip
    if args.data is None and not DEFAULT_DATA.exists():
        load_sample(models[0], None)  # simulates the bench's frame once
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    for entry in models:
        print(f"{entry}:", flush=True)
        result = run_model(entry, args, device, args.train_data)
        (args.out / f"{entry}.json").write_text(json.dumps(result, indent=1) + "\n")
        print(summary(result), flush=True)
    print(f"done in {time.perf_counter() - started:.0f} s; JSON in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
