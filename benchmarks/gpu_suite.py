"""occkit's GPU measurements in one prepared run: inference latency, memory, GEMM fraction and fp16 / bf16 agreement,
and training throughput with the data loader's share, per model; one JSON per model.

    python benchmarks/gpu_suite.py [--device cuda] [--out docs/results/gpu] [--models NAME ...] [--quick]

For each model (default :data:`MODELS`, the paper entries the papers report speed for):

* **inference**: ``occkit bench`` (:func:`occkit.bench.run_bench`) at fp32 and under fp16 and bf16 autocast (bf16
  only on a CPU), batch 1, on the bench's 1600 x 900 synthetic key frame: median and p90 latency, FPS, peak memory,
  the same-run GEMM peak at that precision and the fraction reached, stage times; with ``--compile`` also the
  fast path with ``torch.compile`` at fp16 (CUDA graphs on a GPU), and with ``--graphs`` each precision with the
  network in NHWC replayed from a CUDA graph, and at fp16 once more with cuDNN's algorithm search;
* **agreement**: the arg-max of the occupancy logits under fp16 / bf16 autocast against fp32, on that frame, over
  every voxel (random weights, or the shipped ones for a CPU-sized entry that has them), and of the fp32 network
  replayed from a CUDA graph;
* **training**: the entry's own training step at its per-GPU batch and precision (AdamW, autocast and a gradient
  scaler for fp16), fed by a ``DataLoader`` with ``--workers`` processes reading and augmenting the synthetic world's
  1600 x 900 JPEGs: median step time, samples per second, peak memory, and the share of each step spent waiting for
  the loader (the device's idle fraction, ~0 when the loader keeps up); and the wall-clock time of the paper's
  schedule projected to 8 such devices (nuScenes' 28,130 training samples per epoch, perfect scaling; CBGS epochs
  are longer, which the JSON says where the recipe uses it).

The training world is simulated in a background process while the inference measurements run. A section that fails
(spconv missing for DAOcc, a compilation error) is recorded in the model's JSON under ``errors`` and the suite goes
on; it then exits with status 1. Each JSON names the device, driver, CUDA, torch and occkit versions.
``--device cpu --quick`` runs the same code on the CPU-sized entries with one or two passes of each (a test does);
every number in ``docs/results/gpu/`` comes from a run on the device it names.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import multiprocessing
import statistics
import sys
import time
import traceback
from functools import partial
from pathlib import Path

import torch

from occkit import __version__, zoo
from occkit.bench import DEFAULT_DATA, BenchConfig, load_sample, machine_info, run_bench
from occkit.data.collate import collate
from occkit.data.dataset import OccupancyDataset
from occkit.data.loader import sample_loader
from occkit.engine.reference_frame import simulate_reference_world
from occkit.machine import gpu_driver
from occkit.models.inference import graphed_sparse_convolutions, prepare_for_inference
from occkit.shipped import shipped_entries

MODELS = ("flashocc_m0", "flashocc_m1", "da_occ", "da_occ_16f", "daocc", "daocc_no_detection")
QUICK_MODELS = ("flashocc_tiny", "da_occ_tiny", "daocc_tiny")
#: nuScenes' training split, the papers' epoch.
NUSCENES_TRAIN_SAMPLES = 28130
#: A near tie: two best fp32 logits closer than this fraction of the logits' largest magnitude (agreement).
NEAR_TIE = 0.003
#: Key frames of the training world (1600 x 900, one scene): enough distinct frames for the loader to read.
TRAIN_WORLD_FRAMES = 12


def _precisions(device: torch.device) -> tuple[str, ...]:
    return ("fp32", "fp16", "bf16") if device.type == "cuda" else ("fp32", "bf16")


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def agreement(entry: str, device: torch.device, data: Path | None) -> dict[str, float]:
    """Share of voxels whose arg-max class under each reduced-precision autocast equals fp32's, on the bench frame,
    over all voxels and outside the near ties (:data:`NEAR_TIE`, whose share is ``near_tie_share``); on CUDA also the
    fp32 network replayed from a CUDA graph (the ``cuda_graph`` fast path; DAOcc's sparse encoder runs before it)."""
    weights = "synthetic" if entry in shipped_entries() else None
    torch.manual_seed(0)
    model = zoo.build(entry, weights=weights).to(device).eval()
    batch = load_sample(entry, data, log=lambda _: None).to(device)
    with torch.no_grad():
        logits = model(batch).occupancy.float()
        reference = logits.argmax(dim=1)
        best_two = logits.topk(2, dim=1).values
        # Voxels whose two best fp32 logits differ by less than NEAR_TIE of the logits' range: a reduced precision
        # may flip them without being wrong in any useful sense (random weights leave many).
        clear = (best_two[:, 0] - best_two[:, 1]) >= NEAR_TIE * logits.abs().amax()
        shares = {"near_tie_share": float(1 - clear.float().mean())}
        for precision in _precisions(device)[1:]:
            dtype = {"fp16": torch.float16, "bf16": torch.bfloat16}[precision]
            with torch.autocast(device.type, dtype=dtype):
                predicted = model(batch).occupancy.float().argmax(dim=1)
            shares[precision] = float((predicted == reference).float().mean())
            shares[f"{precision}_outside_near_ties"] = float((predicted == reference)[clear].float().mean())
        if device.type == "cuda" and not graphed_sparse_convolutions(model):
            graphed = prepare_for_inference(copy.deepcopy(model), ("fixed_calibration", "cuda_graph"))
            for _ in range(2):  # the capture, then a replay
                predicted = graphed(batch).occupancy.argmax(dim=1)
            shares["fp32_cuda_graph"] = float((predicted == reference).float().mean())
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
    peak = torch.cuda.max_memory_allocated(device) if device.type == "cuda" else None
    result = {"batch_per_device": train.batch_size, "precision": train.precision, "loader_workers": workers,
              "steps_timed": steps, "step_seconds": {"all": step_times}, "wait_seconds": {"all": waits},
              "loader_wait_fraction": sum(waits) / sum(step_times), "peak_memory_bytes": peak}  # fmt: skip
    return {**result, **derived_throughput(result, train.epochs, train.sampler)}


def derived_throughput(training: dict, epochs: int, sampler: str) -> dict:
    """The figures derived from a training measurement's raw step times and loader wait.

    * ``samples_per_second``: what the device trained on with this loader, batch x steps / total time (the loader's
      stalls included: with too few workers every few steps wait a second, which a median would hide);
    * ``device_bound_samples_per_second``: the rate with the loader's waits taken out, what the device alone allows;
    * ``loader_workers_needed``: workers x device-bound rate / delivered rate, rounded up, when the loader made the
      device wait more than 5% of the time (a loader scaling linearly with workers, on as many free cores);
    * the paper's schedule on 8 such devices, at the delivered and at the device-bound rate.
    """
    times, batch, workers = training["step_seconds"]["all"], training["batch_per_device"], training["loader_workers"]
    total = sum(times)
    compute = total * (1 - training["loader_wait_fraction"]) / len(times)
    delivered = batch * len(times) / total
    device_bound = batch / compute
    needed = workers
    if training["loader_wait_fraction"] > 0.05:
        needed = math.ceil(round(workers * device_bound / delivered, 6))  # rounded: 28.000000001 workers are 28
    samples = NUSCENES_TRAIN_SAMPLES * epochs
    return {
        "step_seconds": {"median": statistics.median(times), "mean": total / len(times), "all": times},
        "compute_seconds_mean": compute,
        "samples_per_second": delivered,
        "device_bound_samples_per_second": device_bound,
        "loader_workers_needed": needed,
        "projection_8_devices": {
            "epochs": epochs, "sampler": sampler, "samples": samples,
            "hours": samples / (8 * delivered) / 3600,
            "hours_device_bound": samples / (8 * device_bound) / 3600,
            "assumes": f"{NUSCENES_TRAIN_SAMPLES} samples per epoch (nuScenes train), 8 devices each training at "
                       "this rate on its own batches, perfect scaling" + ("; CBGS resamples the epoch to more "
                                                                          "samples, not counted" if sampler == "cbgs"
                                                                          else ""),
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
        versions["driver"] = gpu_driver()
    return versions


def _section(result: dict, name: str, measure) -> None:
    """``result[name] = measure()``; a failure is recorded under ``result["errors"][name]`` and the suite goes on, so
    that one model's broken section (say, spconv missing on a fresh machine) costs only that section."""
    try:
        result[name] = measure()
    except Exception as error:  # noqa: BLE001 -- every failure is reported in the JSON and the summary
        lines = traceback.format_exception_only(type(error), error)
        result.setdefault("errors", {})[name] = "".join(lines).strip()[-2000:]
        print(f"  {name} failed: {lines[-1].strip()}", flush=True)


def run_model(entry: str, args: argparse.Namespace, device: torch.device, train_world) -> dict:
    """Every measurement of one zoo entry; ``train_world()`` returns the training world's root once it exists."""
    result: dict = {"model": entry, "machine": machine_info(device), "versions": _versions(device),
                    "inference": {}, "written": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}  # fmt: skip
    quick = args.quick
    log = lambda text: print(f"  {text}", flush=True)  # noqa: E731
    for precision in _precisions(device) if "inference" not in args.skip else ():
        cfg = BenchConfig(model=entry, device=str(device), precision=precision, iters=1 if quick else 20,
                          warmup=1 if quick else 5, optimizations=("fixed_calibration", "fold_bn"),
                          stage_iters=1 if quick else 3, gemm_size=256 if quick else None,
                          gemm_repeats=1 if quick else 3, data=args.data)  # fmt: skip
        _section(result["inference"], precision, partial(run_bench, cfg, log=log))
    if "inference" not in args.skip and args.graphs is not None and (not args.graphs or entry in args.graphs):
        # The graphed rows in NHWC (faster for every camera model on the H200, channels_last_fp16.json), and the
        # fp16 one again with cuDNN's algorithm search, as a deployment with fixed input sizes can run.
        searches = [(precision, False) for precision in _precisions(device)]
        searches += [("fp16", True)] if device.type == "cuda" else []
        for precision, search in searches:
            cfg = BenchConfig(model=entry, device=str(device), precision=precision, iters=1 if quick else 20,
                              warmup=1 if quick else 5, stage_iters=1 if quick else 3,
                              gemm_size=256 if quick else None, gemm_repeats=1 if quick else 3, data=args.data,
                              optimizations=("fixed_calibration", "fold_bn", "channels_last", "cuda_graph"),
                              cudnn_benchmark=search)  # fmt: skip
            name = f"{precision}_cuda_graph" + ("_cudnn_search" if search else "")
            _section(result["inference"], name, partial(run_bench, cfg, log=log))
    if args.compile is not None and (not args.compile or entry in args.compile):
        cfg = BenchConfig(model=entry, device=str(device), precision="fp16" if device.type == "cuda" else "fp32",
                          iters=1 if quick else 20, warmup=1 if quick else 5, gemm_size=256 if quick else None,
                          optimizations=("fixed_calibration", "fold_bn", "compile"), data=args.data)  # fmt: skip
        _section(result["inference"], "compiled", partial(run_bench, cfg, log=log))
    if "agreement" not in args.skip:
        data = None if args.data is None else Path(args.data)
        _section(result, "agreement", lambda: agreement(entry, device, data))
    if "training" not in args.skip:
        steps, warmup = (2, 1) if quick else (10, 3)
        _section(result, "training", lambda: training_throughput(entry, device, train_world(), steps, warmup,
                                                                 args.workers))  # fmt: skip
    return result


class BackgroundWorld:
    """The training measurement's world, simulated in a separate process while the inference measurements run (a
    1600 x 900 world takes minutes of CPU time); calling the object waits for it and returns its root."""

    def __init__(self, root: Path, frames: int) -> None:
        self.root = root
        self.process = None
        if not root.exists():
            print(f"simulating the training world into {root} in the background", flush=True)
            context = multiprocessing.get_context("spawn")
            self.process = context.Process(target=simulate_reference_world, args=(root, (1600, 900), frames,
                                                                                  "v1.0-synth"))  # fmt: skip
            self.process.start()

    def __call__(self) -> Path:
        if self.process is not None:
            self.process.join()
            if self.process.exitcode != 0:
                raise RuntimeError(f"simulating the training world into {self.root} failed "
                                   f"(exit code {self.process.exitcode})")  # fmt: skip
            self.process = None
        return self.root


def summary(result: dict) -> str:
    lines = [f"{result['model']} on {result['machine']['device']}"]
    failures = {**result["inference"].get("errors", {}), **result.get("errors", {})}
    for section, error in failures.items():
        lines.append(f"  {section}: FAILED, {error.splitlines()[-1]}")
    for precision, bench in result["inference"].items():
        if precision == "errors":
            continue
        skipped = [step for step in bench["fast_path"]["steps"] if not step["kept"]]
        if skipped:  # a compile or cuda_graph the row asked for failed: the row would time something else
            lines.append(f"  {precision}: {skipped[0]['optimization']} failed, {skipped[0].get('error', '')[:100]}")
            continue
        memory = bench["peak_memory"]["bytes"] / 2**20
        streamed = bench.get("streaming")
        lines.append(f"  {precision}: {bench['latency_ms']['median']:.2f} ms median, {bench['fps']:.1f} FPS, "
                     f"{memory:.0f} MiB, {100 * bench['gemm_fraction']:.0f}% of GEMM"
                     + (f"; streamed {streamed['latency_ms']['median']:.2f} ms per frame, "
                        f"x{streamed['latency_ratio']:.3f} of one frame" if streamed else ""))  # fmt: skip
    if "agreement" in result:
        lines.append("  agreement with fp32: " + ", ".join(f"{k} {100 * v:.2f}%" for k, v in result["agreement"].items()
                                                           if k != "weights"))  # fmt: skip
    if "training" not in result:
        return "\n".join(lines)
    training = result["training"]
    projection = training["projection_8_devices"]
    lines.append(f"  training: {1000 * training['step_seconds']['mean']:.0f} ms/step "
                 f"({1000 * training['compute_seconds_mean']:.0f} ms on the device), "
                 f"{training['samples_per_second']:.2f} samples/s "
                 f"({training['device_bound_samples_per_second']:.2f} device-bound), "
                 f"loader wait {100 * training['loader_wait_fraction']:.0f}% with {training['loader_workers']} "
                 f"workers ({training['loader_workers_needed']} needed), "
                 f"8 devices: {projection['hours']:.1f} h "
                 f"({projection['hours_device_bound']:.1f} h device-bound)")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="cuda (default) or cpu")
    parser.add_argument("--out", type=Path, default=Path("docs/results/gpu"), help="folder of the JSON files")
    parser.add_argument("--models", nargs="+", default=None, help="zoo entries (default: the paper entries)")
    parser.add_argument("--quick", action="store_true", help="one or two passes of everything (a dry run)")
    parser.add_argument("--compile", nargs="*", default=None, metavar="MODEL",
                        help="also the fast path with torch.compile (CUDA graphs on a GPU; slow start), for the "
                             "models named, or all of them when none is")  # fmt: skip
    parser.add_argument("--graphs", nargs="*", default=None, metavar="MODEL",
                        help="also each precision with the network replayed from a CUDA graph (cuda_graph), for the "
                             "models named, or all of them when none is")  # fmt: skip
    parser.add_argument("--skip", nargs="+", default=(), choices=("inference", "agreement", "training"),
                        help="sections left out (a rerun of the inference alone, or of the agreement)")  # fmt: skip
    parser.add_argument("--workers", type=int, default=4, help="loader processes of the training measurement")
    parser.add_argument("--data", default=None, help="dataset of the inference frame (default: the bench's world)")
    parser.add_argument("--train-data", type=Path, default=Path("data/gpu-suite-train"),
                        help="the training measurement's world, simulated if absent (1600x900, one scene)")  # fmt: skip
    parser.add_argument("--rederive", nargs="+", type=Path, default=None, metavar="JSON",
                        help="recompute the derived training figures of these result files from their raw step times "
                             "and loader wait (after a change of the formulas), and measure nothing")  # fmt: skip
    args = parser.parse_args(argv)
    if args.rederive:
        for path in args.rederive:
            result = json.loads(path.read_text())
            if "training" in result:
                training, projection = result["training"], result["training"]["projection_8_devices"]
                training.update(derived_throughput(training, projection["epochs"], projection["sampler"]))
                path.write_text(json.dumps(result, indent=1) + "\n")
            print(summary(result), flush=True)
        return 0
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for but CUDA is not available (use --device cpu --quick for a dry run)")
    models = args.models or (QUICK_MODELS if args.quick else MODELS)
    if "training" in args.skip:
        train_world = None
    else:
        train_world = BackgroundWorld(args.train_data, frames=2 if args.quick else TRAIN_WORLD_FRAMES)
    if args.data is None and not DEFAULT_DATA.exists():
        load_sample(models[0], None)  # simulates the bench's frame once
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    failed = []
    for entry in models:
        print(f"{entry}:", flush=True)
        result = run_model(entry, args, device, train_world)
        (args.out / f"{entry}.json").write_text(json.dumps(result, indent=1) + "\n")
        print(summary(result), flush=True)
        if "errors" in result or "errors" in result["inference"]:
            failed.append(entry)
    print(f"done in {time.perf_counter() - started:.0f} s; JSON in {args.out}"
          + (f"; sections failed for {', '.join(failed)}" if failed else ""))  # fmt: skip
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
