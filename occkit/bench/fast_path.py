"""The inference fast path of a run (:mod:`occkit.models.inference`): each optimization tried on top of the kept
ones and kept when it speeds the model up (``auto``), or the given ones applied as they are."""

from __future__ import annotations

import copy
import gc
import statistics
from collections.abc import Callable
from functools import partial

from torch import Tensor, nn

from occkit.bench.config import BenchConfig
from occkit.bench.runner import ModelRunner
from occkit.bench.timing import paired_times
from occkit.models.inference import OPTIMIZATIONS, apply_optimization

__all__ = ["ablate", "apply_given"]

#: The steps that may fail on a working model (a missing compiler, an operator a graph cannot capture, the wrong
#: device): such a failure skips the step; any other step's failure is a bug and raises.
FALLIBLE = ("compile", "cuda_graph")


def _relative_difference(output: Tensor, reference: Tensor) -> float:
    """``max |output - reference| / max |reference|``: how far an optimization moved the logits."""
    scale = reference.float().abs().max().clamp_min(1e-12)
    return float((output.float() - reference.float()).abs().max() / scale)


def _trial(model: nn.Module, name: str, runner: ModelRunner) -> tuple[nn.Module | None, dict]:
    """A copy of ``model`` with the step ``name`` applied and one pass run (for ``compile``: the compilation), and the
    step's record. A failing ``compile`` or ``cuda_graph`` (no compiler, an unsupported operator, a CPU model) gives
    no model and the error in the record; other failures are bugs."""
    trial = copy.deepcopy(model)
    step: dict = {"optimization": name}
    try:
        apply_optimization(trial, name)
        step["first_pass_s"] = runner.time(trial)
    except Exception as error:  # noqa: BLE001 -- compilation and capture fail in many ways
        if name not in FALLIBLE:
            raise
        first_line = (str(error).strip().splitlines() or [""])[0][:300]
        step.update(kept=False, error=f"{type(error).__name__}: {first_line}")
        return None, step
    return trial, step


def ablate(model: nn.Module, runner: ModelRunner, cfg: BenchConfig,
           log: Callable[[str], None]) -> tuple[nn.Module, list]:  # fmt: skip
    """Greedy fast path: each optimization on top of the kept ones, kept when it speeds the model up."""
    tolerance = 1e-3 if cfg.precision == "fp32" else 5e-2
    reference = runner.forward(model)
    for _ in range(cfg.warmup):
        runner.forward(model)
    steps = []
    for name in OPTIMIZATIONS:
        trial, step = _trial(model, name, runner)
        steps.append(step)
        if trial is None:
            log(f"  {name}: skipped ({step['error']})")
            continue
        step["relative_difference"] = _relative_difference(runner.forward(trial), reference)
        current, candidate = paired_times(partial(runner.time, model), partial(runner.time, trial), cfg.ablation_iters)
        step["reference_ms"] = 1000 * statistics.median(current)
        step["latency_ms"] = 1000 * statistics.median(candidate)
        # The median of the pairs' ratios, not the ratio of the medians: each pair saw one machine load.
        step["speedup"] = statistics.median(c / t for c, t in zip(current, candidate, strict=True))
        accurate = step["relative_difference"] <= tolerance
        step["kept"] = accurate and step["speedup"] > 1 + cfg.min_gain
        if not accurate:
            step["error"] = f"logits moved by {step['relative_difference']:.2e} of their range (> {tolerance:g})"
        log(f"  {name}: {step['reference_ms']:.1f} -> {step['latency_ms']:.1f} ms (x{step['speedup']:.3f}), "
            f"{'kept' if step['kept'] else 'dropped'}")  # fmt: skip
        if step["kept"]:
            model = trial
    gc.collect()  # the dropped trials' weights
    return model, steps


def apply_given(model: nn.Module, runner: ModelRunner, cfg: BenchConfig,
                log: Callable[[str], None]) -> tuple[nn.Module, list]:  # fmt: skip
    """The listed steps applied as they are, unmeasured, a failing ``compile`` or ``cuda_graph`` skipped; the step
    records."""
    steps = []
    for name in cfg.optimizations:
        trial, step = _trial(model, name, runner)
        steps.append(step)
        if trial is None:
            log(f"  {name}: skipped ({step['error']})")
            continue
        model = trial
        step["kept"] = True
    return model, steps
