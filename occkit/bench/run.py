"""One benchmark run, its steps in order (the package's docstring lists them): :func:`run_bench`."""

from __future__ import annotations

import contextlib
import statistics
from collections.abc import Callable, Iterator

import torch
from torch import nn

from occkit import zoo
from occkit.bench.config import BenchConfig
from occkit.bench.fast_path import ablate, apply_given
from occkit.bench.gemm import GemmProbe
from occkit.bench.memory import peak_memory, reset_peak_memory
from occkit.bench.runner import ModelRunner
from occkit.bench.sample import DEFAULT_DATA, load_sample
from occkit.bench.stages import stage_report
from occkit.bench.streaming import streaming
from occkit.bench.timing import percentile
from occkit.machine import machine_info
from occkit.metrics.realtime import rt_miou_table
from occkit.models.complexity import count_macs, count_parameters
from occkit.models.inference import eager_network, prepare_for_inference
from occkit.types import Batch

__all__ = ["run_bench"]

_MACS_CONVENTION = (
    "multiply-accumulates (1 MAC = 1 multiply + 1 add), the papers' 'GFLOPs'; FLOPs = 2 x MACs; "
    "convolutions, linear layers and matrix products, sparse convolutions from their active sites"
)


def run_bench(cfg: BenchConfig, log: Callable[[str], None] = print) -> dict:
    """Run the benchmark of ``cfg`` and return its JSON-ready result (the package docstring lists its steps)."""
    device = torch.device(cfg.device)
    with _run_settings(device, cfg.threads, cfg.cudnn_benchmark):
        torch.manual_seed(0)
        batch = load_sample(cfg.model, cfg.data, cfg.batch_size, log).to(device)
        runner = ModelRunner(batch, device, cfg.precision)
        architecture = zoo.model_config(cfg.model)[0]
        model = zoo.build(cfg.model).to(device).eval()
        result: dict = {"model": cfg.model, "architecture": architecture, "device": str(device),
                        "precision": cfg.precision, "batch": cfg.batch_size, "iters": cfg.iters,
                        "warmup": cfg.warmup, "cudnn_benchmark": cfg.cudnn_benchmark,
                        "input": _input_summary(batch, cfg.data)}  # fmt: skip
        log(f"{cfg.model}: counting parameters and MACs")
        if cfg.count_detection and getattr(model, "detection_head", None) is not None:
            result["params_with_detection"] = count_parameters(model)
            result["macs_with_detection"] = _count(model, runner, detect=True).total // cfg.batch_size
        prepare_for_inference(model)
        macs = _count(model, runner)
        result.update(params=count_parameters(model), macs=macs.total // cfg.batch_size,
                      macs_convention=_MACS_CONVENTION)  # fmt: skip

        if cfg.optimizations == "auto":
            log(f"{cfg.model}: measuring the fast-path optimizations ({cfg.ablation_iters} interleaved pairs each)")
            model, steps = ablate(model, runner, cfg, log)
        else:
            model, steps = apply_given(model, runner, cfg, log)
        result["fast_path"] = {
            "mode": "auto" if cfg.optimizations == "auto" else "given",
            "applied": [step["optimization"] for step in steps if step["kept"]],
            "steps": steps,  # auto: the measured ablation; given: each step's first pass, or why it was skipped
        }

        log(f"{cfg.model}: {cfg.warmup} warm-up and {cfg.iters} timed passes, a GEMM after each")
        result.update(_time_model(model, runner, cfg, device, macs.total))
        log(f"{cfg.model}: {cfg.stage_iters} passes with stage hooks")
        with eager_network(model):  # a CUDA graph's replay calls no module, so the hooks would see nothing
            result["stages"], result["stages_total_ms"] = stage_report(
                zoo.architecture(architecture), model, runner, cfg, macs, result["gemm_peak_gflops"]
            )
        result["stages_eager"] = "cuda_graph" in result["fast_path"]["applied"]
        # Two views of the stage that falls furthest short: the lowest GEMM fraction (among stages with MACs), and
        # the most time lost against the GEMM rate (which also weighs how much of the pass the stage is).
        stages = result["stages"]
        result["lowest_gemm_fraction"] = min(
            (s for s in stages if s != "other" and stages[s]["macs"]),
            key=lambda s: stages[s]["gemm_fraction"],
            default=None,
        )
        result["most_time_beyond_gemm"] = max(stages, key=lambda s: stages[s]["ms_beyond_gemm"])
        if getattr(model, "temporal", None) is not None:
            log(f"{cfg.model}: streaming the scene, {cfg.iters} interleaved pairs against the model without history")
            result["streaming"] = streaming(model, result["fast_path"]["applied"], cfg, device)
        if cfg.miou is not None:
            result["rt_miou"] = {"miou": cfg.miou, **rt_miou_table(cfg.miou, result["fps"])}
        result["machine"] = machine_info(device)
        result["flush_denormal"] = device.type == "cpu"
    return result


@contextlib.contextmanager
def _run_settings(device: torch.device, threads: int | None, cudnn_benchmark: bool = False) -> Iterator[None]:
    """The thread count for the run; on CPUs, subnormal floats flushed to zero, as occkit's training and evaluation
    do (they run an order of magnitude slower on x86; GPUs flush them too); cuDNN's algorithm search as asked. All
    restored afterwards."""
    previous_threads, previous_search = torch.get_num_threads(), torch.backends.cudnn.benchmark
    if threads is not None:
        torch.set_num_threads(threads)
    if device.type == "cpu":
        torch.set_flush_denormal(True)
    torch.backends.cudnn.benchmark = cudnn_benchmark
    try:
        yield
    finally:
        torch.set_num_threads(previous_threads)
        torch.backends.cudnn.benchmark = previous_search
        if device.type == "cpu":
            torch.set_flush_denormal(False)


def _input_summary(batch: Batch, data: str | None) -> dict:
    return {
        "data": str(DEFAULT_DATA if data is None else data),
        "token": batch.tokens[0],
        "images": list(batch.images.shape) if batch.images is not None else None,
        "points": int(batch.num_points[0]) if batch.points is not None else 0,
    }


def _time_model(model: nn.Module, runner: ModelRunner, cfg: BenchConfig, device: torch.device, macs: int) -> dict:
    """Peak memory of one pass, then latency statistics, FPS, the interleaved GEMM peak and achieved throughput."""
    for _ in range(cfg.warmup):
        runner.forward(model)
    # Measured over one steady-state pass, before the GEMM's matrices exist, so that they do not count.
    window = reset_peak_memory(device)
    runner.forward(model)
    memory = peak_memory(device, window)
    size = cfg.gemm_size or (8192 if device.type == "cuda" else 4096)
    gemm = GemmProbe(size, runner.dtype, device)
    gemm.select(cfg.gemm_repeats)
    times, paired = [], []
    for _ in range(cfg.iters):
        times.append(runner.time(model))
        # The fraction in this pair: the model's GFLOP/s over the GEMM's measured right after it, on the same load.
        paired.append(2 * macs / times[-1] / 1e9 / gemm.measure())
    median = statistics.median(times)
    peak = max(gemm.samples)
    achieved = 2 * macs / median / 1e9  # macs of the whole batch
    return {
        "latency_ms": {"median": 1000 * median, "p90": 1000 * percentile(times, 90), "min": 1000 * min(times),
                       "all": [1000 * t for t in times]},
        "fps": cfg.batch_size / median,
        "gemm_peak_gflops": peak,
        "gemm": {"size": size, "dtype": str(runner.dtype).removeprefix("torch."), "route": gemm.route,
                 "best_by_route_gflops": gemm.best_by_route, "median_gflops": statistics.median(gemm.samples),
                 "samples_gflops": gemm.samples},
        "achieved_gflops": achieved,
        "gemm_fraction": achieved / peak,
        "gemm_fraction_paired": statistics.median(paired),
        "peak_memory": memory,
    }  # fmt: skip


def _count(model: nn.Module, runner: ModelRunner, detect: bool = False):
    return count_macs(model, lambda: runner.forward(model, detect=detect))
