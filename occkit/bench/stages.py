"""Time and MACs per stage of a model (image encoder, view transform, LiDAR encoder, fusion + BEV encoder, heads):
the stages' modules, the forward-hook timer, and the breakdown of a benchmark run."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import torch
from torch import Tensor, nn

from occkit import zoo
from occkit.bench.config import BenchConfig
from occkit.bench.runner import ModelRunner
from occkit.models.base import Architecture

__all__ = ["stage_modules", "StageTimer", "stage_report"]


def stage_modules(architecture: str, model: nn.Module) -> dict[str, list[nn.Module]]:
    """Stage name -> the model's child modules in it (the architecture's ``stages``, declared in its model file);
    stages the model lacks are left out."""
    children = dict(model.named_children())
    stages = {}
    for stage, names in zoo.architecture(architecture).stages.items():
        modules = [children[name] for name in names if name in children]
        if modules:
            stages[stage] = modules
    return stages


class StageTimer:
    """Wall time spent inside each stage's modules, from forward pre- and post-hooks, and optionally in each stage's
    backward.

    Use as a context manager around the passes; :attr:`seconds` (forward) and :attr:`backward_seconds` accumulate
    until :meth:`reset`. On CUDA each hook synchronizes, so a stage's time includes its kernels (and the passes run
    without CPU/GPU overlap at the stage boundaries, which is why the total latency is timed without hooks).

    Backward (``backward=True``): a hook on each stage output's gradient stamps the moment the backward reaches that
    stage. Autograd runs a CPU graph in reverse creation order, so a stage's backward lasts from its stamp to the
    stamp of the stage whose forward ran just before it (the first stage's, to the end of the backward, which the
    caller marks with :meth:`backward_done`). What runs between the backward's start and the first stamp (the loss
    terms' own backward) is :attr:`loss_backward_seconds`.
    """

    def __init__(self, stages: dict[str, list[nn.Module]], synchronize: Callable[[], None],
                 backward: bool = False) -> None:  # fmt: skip
        self.stages = stages
        self.synchronize = synchronize
        self.backward = backward
        self.reset()
        self._started: dict[int, float] = {}
        self._handles: list = []

    def reset(self) -> None:
        self.seconds = dict.fromkeys(self.stages, 0.0)
        self.backward_seconds = dict.fromkeys(self.stages, 0.0)
        self.loss_backward_seconds = 0.0
        self._forward_order: list[tuple[str, int]] = []  # (stage, call number) in forward order
        self._reached: dict[int, float] = {}  # call number -> when its output's gradient arrived

    def backward_started(self) -> None:
        """Mark the start of a backward pass (call just before ``loss.backward()``)."""
        self.synchronize()
        self._backward_start = time.perf_counter()

    def backward_done(self) -> None:
        """Mark the end of a backward pass: share its time among the stages, then forget this pass's calls."""
        self.synchronize()
        end = time.perf_counter()
        reached = sorted((when, call) for call, when in self._reached.items())
        stage_of = dict((call, stage) for stage, call in self._forward_order)
        if reached:
            self.loss_backward_seconds += reached[0][0] - self._backward_start
        for (when, call), following in zip(reached, [*reached[1:], (end, None)], strict=True):
            self.backward_seconds[stage_of[call]] += following[0] - when
        self._forward_order, self._reached = [], {}

    def _start(self, module: nn.Module, args: tuple) -> None:
        self.synchronize()
        self._started[id(module)] = time.perf_counter()

    def _stopper(self, stage: str) -> Callable:
        def stop(module: nn.Module, args: tuple, output: object) -> None:
            self.synchronize()
            self.seconds[stage] += time.perf_counter() - self._started.pop(id(module))
            if self.backward and torch.is_grad_enabled():
                call = len(self._forward_order)
                self._forward_order.append((stage, call))
                for tensor in _tensors(output):
                    if tensor.requires_grad:
                        tensor.register_hook(self._stamper(call))

        return stop

    def _stamper(self, call: int) -> Callable:
        def stamp(grad: Tensor) -> None:
            self.synchronize()
            self._reached.setdefault(call, time.perf_counter())  # the first of the call's outputs to be reached

        return stamp

    def __enter__(self) -> StageTimer:
        for stage, modules in self.stages.items():
            for module in modules:
                self._handles.append(module.register_forward_pre_hook(self._start))
                self._handles.append(module.register_forward_hook(self._stopper(stage)))
        return self

    def __exit__(self, *exc_info) -> None:
        for handle in self._handles:
            handle.remove()
        self._handles.clear()


def _tensors(value: object) -> list[Tensor]:
    """The tensors in a module output: a tensor, a (nested) tuple, list or dict of them, or a dataclass."""
    if isinstance(value, Tensor):
        return [value]
    if isinstance(value, (list, tuple)):
        return [t for item in value for t in _tensors(item)]
    if isinstance(value, dict):
        return [t for item in value.values() for t in _tensors(item)]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return [t for field in dataclasses.fields(value) for t in _tensors(getattr(value, field.name))]
    features = getattr(value, "features", None)  # a sparse tensor
    return [features] if isinstance(features, Tensor) else []


def stage_report(architecture: Architecture, model: nn.Module, runner: ModelRunner, cfg: BenchConfig, macs,
                 gemm_peak: float) -> tuple[dict, float]:  # fmt: skip
    """Per-stage ms, MACs per sample, achieved GFLOP/s and GEMM fraction, from the hooked pass with the median total
    (so the stages and ``other`` add up to that pass); and that pass's total in ms."""
    stages = stage_modules(architecture.name, model)
    totals, breakdowns = [], []
    with StageTimer(stages, runner.synchronize) as timer:
        for _ in range(cfg.stage_iters):
            timer.reset()
            totals.append(runner.time(model))
            breakdowns.append(dict(timer.seconds))
    median_index = sorted(range(len(totals)), key=totals.__getitem__)[len(totals) // 2]
    total, seconds = totals[median_index], breakdowns[median_index]
    report = {}
    for stage, stage_seconds in seconds.items():
        stage_macs = sum(macs.by_module.get(child, 0) for child in architecture.stages[stage]) // cfg.batch_size
        report[stage] = _stage_entry(stage_seconds, stage_macs, total, cfg.batch_size, gemm_peak)
    other_macs = macs.total // cfg.batch_size - sum(entry["macs"] for entry in report.values())
    report["other"] = _stage_entry(total - sum(seconds.values()), other_macs, total, cfg.batch_size, gemm_peak)
    return report, 1000 * total


def _stage_entry(seconds: float, macs: int, total: float, batch_size: int, gemm_peak: float) -> dict:
    """One stage's numbers; ``ms_beyond_gemm`` is its time beyond what its MACs would take at the GEMM peak."""
    flops = 2 * macs * batch_size
    achieved = flops / seconds / 1e9 if seconds > 0 else 0.0
    return {
        "ms": 1000 * seconds,
        "share": seconds / total,
        "macs": macs,
        "achieved_gflops": achieved,
        "gemm_fraction": achieved / gemm_peak,
        "ms_beyond_gemm": 1000 * seconds - flops / gemm_peak / 1e6,
    }
