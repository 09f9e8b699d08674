"""Inference benchmark of a zoo model on one real key frame: latency, FPS, time and MACs per stage, peak memory, and
the model's arithmetic throughput as a fraction of the same run's GEMM throughput.

    >>> result = run_bench(BenchConfig(model="flashocc_m0", iters=10))  # doctest: +SKIP
    >>> print(format_report(result))  # doctest: +SKIP

What one run does, in this order (``occkit bench`` is the command; ``docs/benchmarks.md`` the conventions):

1. Load one key frame at the model's own input setting (its zoo experiment's test transform: the paper's six
   1600x900 cameras cropped to 256x704 and LiDAR sweeps; smaller for ``*_tiny`` entries), from ``data`` or from a
   one-scene 1600x900 synthetic world simulated once into :data:`DEFAULT_DATA`. ``batch_size`` repeats that frame.
2. Count parameters and MACs (multiply-accumulates, the papers' "GFLOPs"; FLOPs = 2 x MACs) of the network as run:
   eval mode, detection head removed (counted once with it too, when the model has one).
3. Choose the inference fast path (:mod:`occkit.models.inference`): ``auto`` tries each optimization on top of the
   ones kept so far, times it against the current model in interleaved pairs (so machine load hits both alike) and
   keeps it if the median of the pairs' speed-ups exceeds ``1 + min_gain``; the steps go to the JSON as the ablation.
4. After ``warmup`` passes, read the peak memory of one pass; then time ``iters`` passes (median, p90), each
   followed by one square matrix product: the GEMM peak is the best of those and of ``gemm_repeats`` products
   measured just before, so the model and its yardstick see the same threads, device and machine load.
5. Time the stages (image encoder, view transform, LiDAR encoder, fusion + BEV encoder, heads) with forward hooks
   on their submodules over ``stage_iters`` more passes; the remainder of the pass is ``other``.
6. For a temporal model, the ``streaming`` section: the scene's key frames streamed in order, over and over, one
   frame per pass with the history carried in a :class:`~occkit.models.temporal.StreamMemory` (every frame's BEV
   computed once), timed in interleaved pairs against the same model without history on the same frames; the
   per-frame latency of both and the median of the pairs' ratios. (Steps 2 to 5 time a temporal model on one frame
   with an empty history, which costs what a streamed frame costs: the warp and fusion run on zeros.)
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import gc
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from occkit import zoo
from occkit.engine.reference_frame import load_key_frame, load_scene_frames, simulate_reference_world
from occkit.metrics.realtime import rt_miou_table
from occkit.models.base import Architecture
from occkit.models.complexity import count_macs, count_parameters
from occkit.models.inference import OPTIMIZATIONS, apply_optimization, check_optimizations, prepare_for_inference
from occkit.types import Batch

__all__ = [
    "DEFAULT_DATA",
    "PRECISIONS",
    "BenchConfig",
    "run_bench",
    "format_report",
    "load_sample",
    "stage_modules",
    "StageTimer",
    "GemmProbe",
    "ModelRunner",
    "paired_times",
    "machine_info",
    "single_frame_twin",
]

#: Where the benchmark world is simulated when no dataset is given.
DEFAULT_DATA = Path("data/bench-1600x900")

#: ``--precision`` -> dtype of autocast and of the GEMM yardstick.
PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}

_MACS_CONVENTION = (
    "multiply-accumulates (1 MAC = 1 multiply + 1 add), the papers' 'GFLOPs'; FLOPs = 2 x MACs; "
    "convolutions, linear layers and matrix products, sparse convolutions from their active sites"
)


@dataclass(frozen=True)
class BenchConfig:
    """What to benchmark and how."""

    model: str
    """Zoo entry name."""
    device: str = "cpu"
    """``cpu``, ``cuda`` or ``cuda:N``."""
    precision: str = "fp32"
    """``fp32``, or ``bf16`` / ``fp16`` autocast (``fp16`` on CUDA only: CPUs have no fast fp16 kernels)."""
    batch_size: int = 1
    """Copies of the key frame per forward pass."""
    iters: int = 10
    """Timed forward passes."""
    warmup: int = 2
    """Untimed passes first (allocator, spconv's rulebooks, the cached geometry, compilation)."""
    threads: int | None = None
    """CPU threads for PyTorch; None keeps its default."""
    optimizations: str | tuple[str, ...] = "auto"
    """``auto`` (measure each of :data:`~occkit.models.inference.OPTIMIZATIONS`, keep those that speed up) or the
    steps to apply as they are (an empty tuple: none)."""
    ablation_iters: int = 5
    """Interleaved pairs timed per ``auto`` step."""
    min_gain: float = 0.02
    """Relative speed-up an ``auto`` step needs to be kept (below it, noise and the step's risk outweigh it)."""
    stage_iters: int = 3
    """Passes timed with stage hooks; the breakdown of the pass with the median total is reported."""
    gemm_size: int | None = None
    """``n`` of the ``n x n`` GEMM yardstick; None: 4096 on CPU (saturates a few cores), 8192 on CUDA."""
    gemm_repeats: int = 3
    """GEMMs timed before the model timing (besides one after every timed pass)."""
    data: str | None = None
    """Dataset root to take the key frame from; None: :data:`DEFAULT_DATA`, simulated on first use."""
    miou: float | None = None
    """The model's mIoU, for RT-mIoU@10/15/20 at the measured frame rate (same unit back)."""
    count_detection: bool = True
    """Also count parameters and MACs with the detection head, for models that have one."""

    def __post_init__(self) -> None:
        if self.model not in zoo.names():
            raise ValueError(f"unknown model {self.model!r}; the zoo has: {', '.join(zoo.names())}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        try:
            device = torch.device(self.device)
        except RuntimeError:
            raise ValueError(f"device must be cpu or cuda[:N], got {self.device!r}") from None
        if device.type not in ("cpu", "cuda"):
            raise ValueError(f"device must be cpu or cuda[:N], got {self.device!r}")
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device {self.device!r} asked for but CUDA is not available")
        if device.type == "cpu" and self.precision == "fp16":
            raise ValueError("precision fp16 needs a CUDA device (CPU matmuls in fp16 are orders slower); use bf16")
        counts = {"batch_size": self.batch_size, "iters": self.iters, "ablation_iters": self.ablation_iters,
                  "stage_iters": self.stage_iters, "gemm_repeats": self.gemm_repeats}  # fmt: skip
        for key, value in counts.items():
            if value < 1:
                raise ValueError(f"{key} must be >= 1, got {value}")
        if self.warmup < 0 or (self.threads is not None and self.threads < 1):
            raise ValueError(f"warmup must be >= 0 and threads >= 1, got {self.warmup} and {self.threads}")
        if self.gemm_size is not None and self.gemm_size < 16:
            raise ValueError(f"gemm_size must be >= 16, got {self.gemm_size}")
        if self.miou is not None and not 0 <= self.miou <= 100:
            raise ValueError(f"miou is a percentage between 0 and 100, got {self.miou:g}")
        if isinstance(self.optimizations, str) and self.optimizations != "auto":
            raise ValueError(f"optimizations must be 'auto' or a sequence of names, got {self.optimizations!r}")
        if not isinstance(self.optimizations, str):
            object.__setattr__(self, "optimizations", check_optimizations(self.optimizations))


# ------------------------------------------------------------------------------------------------------ input
def load_sample(model: str, data: str | Path | None = None, batch_size: int = 1,
                log: Callable[[str], None] = print) -> Batch:  # fmt: skip
    """The last key frame of ``data`` at ``model``'s input setting (test transform), repeated ``batch_size`` times.

    ``data`` None uses :data:`DEFAULT_DATA`, simulating it first if absent; any other missing folder is an error.
    """
    settings = zoo.experiment(model).data
    root = DEFAULT_DATA if data is None else Path(data)
    if data is None and not root.exists():
        log(f"simulating a one-scene 1600x900 world into {root} (once; about a minute)")
        # Three key frames at 2 Hz: the last one has 20 LiDAR sweeps behind it, more than any model asks for.
        simulate_reference_world(root, (1600, 900), frames=3, version=settings.version)
    elif not root.exists():
        raise FileNotFoundError(f"dataset {root} does not exist (leave out --data to simulate {DEFAULT_DATA})")
    return load_key_frame(settings, root, batch_size=batch_size)[0]


# ---------------------------------------------------------------------------------------------------- timing
def _synchronizer(device: torch.device) -> Callable[[], None]:
    if device.type == "cuda":
        return lambda: torch.cuda.synchronize(device)
    return lambda: None


def _timed(run: Callable[[], object], synchronize: Callable[[], None]) -> float:
    """Seconds of one ``run()``, with the device's queue drained before and after."""
    synchronize()
    start = time.perf_counter()
    run()
    synchronize()
    return time.perf_counter() - start


class GemmProbe:
    """Throughput of the square matrix product ``(n, n) @ (n, n)`` (``2 n^3`` FLOPs) on a device and dtype.

    Two routes to the same product: ``torch.mm`` (the BLAS: MKL or OpenBLAS, cuBLAS) and a 1x1 convolution of a
    channels-last ``(1, n, n, 1)`` input with ``n`` filters (oneDNN, cuDNN: the libraries the models' convolutions
    run on). They can differ by 2x on one machine (MKL on AMD CPUs), and a yardstick slower than what the model's
    own convolutions reach would not measure efficiency, so :meth:`select` keeps the faster route.
    """

    def __init__(self, size: int, dtype: torch.dtype, device: torch.device) -> None:
        generator = torch.Generator().manual_seed(0)
        self.size = size
        a, b = (torch.randn(size, size, generator=generator).to(device, dtype) for _ in range(2))
        out = torch.empty_like(a)
        image = a.view(1, size, 1, size).permute(0, 3, 1, 2)  # (1, C=n, H=n, W=1), channels last: a row per pixel
        weight = b.view(size, size, 1, 1)  # (n filters, n channels, 1, 1)
        self.routes: dict[str, Callable[[], object]] = {
            "matmul": lambda: torch.mm(a, b, out=out),
            "conv1x1": lambda: torch.nn.functional.conv2d(image, weight),
        }
        self.route = "matmul"
        self.synchronize = _synchronizer(device)
        self.best_by_route: dict[str, float] = {}
        self.samples: list[float] = []

    def _rate(self, route: str) -> float:
        return 2 * self.size**3 / _timed(self.routes[route], self.synchronize) / 1e9

    def select(self, repeats: int) -> None:
        """Time each route ``repeats`` times after a warm-up; keep the faster one; its best rate joins the samples."""
        for route in self.routes:
            self._rate(route)  # warm-up: thread pools, library handles, kernel selection
            self.best_by_route[route] = max(self._rate(route) for _ in range(repeats))
        self.route = max(self.best_by_route, key=self.best_by_route.__getitem__)
        self.samples.append(self.best_by_route[self.route])

    def measure(self) -> float:
        """GFLOP/s of one product by the selected route; also appended to :attr:`samples`."""
        self.samples.append(self._rate(self.route))
        return self.samples[-1]


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


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


# ------------------------------------------------------------------------------------------------- machine
def _cpu_model() -> str:
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def machine_info(device: torch.device) -> dict:
    """CPU model, core and thread counts, PyTorch version and the device's name (and TF32 settings on CUDA)."""
    info = {
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "platform": platform.platform(),
        "device": _cpu_model() if device.type == "cpu" else torch.cuda.get_device_name(device),
    }
    if device.type == "cuda":
        info.update(
            cuda=torch.version.cuda,
            cudnn=torch.backends.cudnn.version(),
            tf32_matmul=torch.backends.cuda.matmul.allow_tf32,
            tf32_cudnn=torch.backends.cudnn.allow_tf32,
        )
    return info


def _reset_peak_memory(device: torch.device) -> bool:
    """Start a new peak-memory window; False when only the process-lifetime peak can be read (non-Linux CPU)."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        return True
    try:  # Linux: writing 5 resets the process's peak resident set size (VmHWM)
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _peak_memory(device: torch.device, window: bool) -> dict:
    if device.type == "cuda":
        return {"bytes": torch.cuda.max_memory_allocated(device),
                "measure": "torch.cuda.max_memory_allocated over one pass"}  # fmt: skip
    if window:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return {"bytes": int(line.split()[1]) * 1024,
                        "measure": "process peak RSS (VmHWM) over one pass, CPU"}  # fmt: skip
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"bytes": peak if sys.platform == "darwin" else peak * 1024,
            "measure": "process peak RSS since start (resource.getrusage), CPU"}  # fmt: skip


# ------------------------------------------------------------------------------------------------ the bench
class ModelRunner:
    """Forward passes of models on one batch, in a precision (autocast below fp32), without autograd.

    Args:
        batch: the input, already on ``device``; device: where the models run; precision: a key of
            :data:`PRECISIONS`.
    """

    def __init__(self, batch: Batch, device: torch.device, precision: str = "fp32") -> None:
        self.batch = batch
        self.device = device
        self.dtype = PRECISIONS[precision]
        self.synchronize = _synchronizer(device)

    def forward(self, model: nn.Module, detect: bool = False) -> Tensor:
        """Occupancy logits ``(B, K, X, Y, Z)`` of one pass."""
        autocast = torch.autocast(self.device.type, dtype=self.dtype, enabled=self.dtype != torch.float32)
        with torch.no_grad(), autocast:
            output = model(self.batch, detect=True) if detect else model(self.batch)
        return output.occupancy

    def time(self, model: nn.Module) -> float:
        """Seconds of one pass, the device's queue drained before and after."""
        return _timed(lambda: self.forward(model), self.synchronize)


def _relative_difference(output: Tensor, reference: Tensor) -> float:
    """``max |output - reference| / max |reference|``: how far an optimization moved the logits."""
    scale = reference.float().abs().max().clamp_min(1e-12)
    return float((output.float() - reference.float()).abs().max() / scale)


def paired_times(first: Callable[[], float], second: Callable[[], float], pairs: int) -> tuple[list, list]:
    """Two timings (callables returning seconds) run in ``pairs`` interleaved pairs, the order alternating from pair
    to pair, so that a change of machine load hits both alike; the two lists of seconds."""
    times: tuple[list, list] = ([], [])
    for index in range(pairs):
        for side in (0, 1) if index % 2 == 0 else (1, 0):
            times[side].append((first, second)[side]())
    return times


def _trial(model: nn.Module, name: str, runner: ModelRunner) -> tuple[nn.Module | None, dict]:
    """A copy of ``model`` with the step ``name`` applied and one pass run (for ``compile``: the compilation), and the
    step's record. A failing ``compile`` gives no model and the error in the record; other failures are bugs."""
    trial = copy.deepcopy(model)
    step: dict = {"optimization": name}
    try:
        apply_optimization(trial, name)
        step["first_pass_s"] = runner.time(trial)
    except Exception as error:  # noqa: BLE001 -- compilation fails in many ways (no compiler, unsupported op)
        if name != "compile":
            raise
        first_line = (str(error).strip().splitlines() or [""])[0][:300]
        step.update(kept=False, error=f"{type(error).__name__}: {first_line}")
        return None, step
    return trial, step


def _ablate(model: nn.Module, runner: ModelRunner, cfg: BenchConfig,
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


def _apply_given(model: nn.Module, runner: ModelRunner, cfg: BenchConfig,
                 log: Callable[[str], None]) -> tuple[nn.Module, list]:  # fmt: skip
    """The listed steps applied as they are, unmeasured, a failing ``compile`` skipped; the step records."""
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


def _count(model: nn.Module, runner: ModelRunner, detect: bool = False):
    return count_macs(model, lambda: runner.forward(model, detect=detect))


def _stage_report(architecture: Architecture, model: nn.Module, runner: ModelRunner, cfg: BenchConfig, macs,
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


def run_bench(cfg: BenchConfig, log: Callable[[str], None] = print) -> dict:
    """Run the benchmark of ``cfg`` and return its JSON-ready result (see the module docstring for the steps)."""
    device = torch.device(cfg.device)
    with _run_settings(device, cfg.threads):
        torch.manual_seed(0)
        batch = load_sample(cfg.model, cfg.data, cfg.batch_size, log).to(device)
        runner = ModelRunner(batch, device, cfg.precision)
        architecture = zoo.model_config(cfg.model)[0]
        model = zoo.build(cfg.model).to(device).eval()
        result: dict = {"model": cfg.model, "architecture": architecture, "device": str(device),
                        "precision": cfg.precision, "batch": cfg.batch_size, "iters": cfg.iters,
                        "warmup": cfg.warmup, "input": _input_summary(batch, cfg.data)}  # fmt: skip
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
            model, steps = _ablate(model, runner, cfg, log)
        else:
            model, steps = _apply_given(model, runner, cfg, log)
        result["fast_path"] = {
            "mode": "auto" if cfg.optimizations == "auto" else "given",
            "applied": [step["optimization"] for step in steps if step["kept"]],
            "steps": steps,  # auto: the measured ablation; given: each step's first pass, or why it was skipped
        }

        log(f"{cfg.model}: {cfg.warmup} warm-up and {cfg.iters} timed passes, a GEMM after each")
        result.update(_time_model(model, runner, cfg, device, macs.total))
        log(f"{cfg.model}: {cfg.stage_iters} passes with stage hooks")
        result["stages"], result["stages_total_ms"] = _stage_report(
            zoo.architecture(architecture), model, runner, cfg, macs, result["gemm_peak_gflops"]
        )
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
            result["streaming"] = _streaming(model, result["fast_path"]["applied"], cfg, device)
        if cfg.miou is not None:
            result["rt_miou"] = {"miou": cfg.miou, **rt_miou_table(cfg.miou, result["fps"])}
        result["machine"] = machine_info(device)
        result["flush_denormal"] = device.type == "cpu"
    return result


@contextlib.contextmanager
def _run_settings(device: torch.device, threads: int | None) -> Iterator[None]:
    """The thread count for the run and, on CPUs, subnormal floats flushed to zero, as occkit's training and
    evaluation do (they run an order of magnitude slower on x86; GPUs flush them too); both restored afterwards."""
    previous_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    if device.type == "cpu":
        torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_num_threads(previous_threads)
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
    window = _reset_peak_memory(device)
    runner.forward(model)
    memory = _peak_memory(device, window)
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
        "latency_ms": {"median": 1000 * median, "p90": 1000 * _percentile(times, 90), "min": 1000 * min(times),
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


def single_frame_twin(name: str) -> nn.Module:
    """Zoo entry ``name``'s model without its history: the same config with ``temporal`` None and the BEV encoder
    taking one frame's channels (the model a temporal entry's streaming latency is compared with)."""
    architecture, config = zoo.model_config(name)
    if getattr(config, "temporal", None) is None:
        raise ValueError(f"{name} has no history")
    frame_channels = zoo.build_from_config(architecture, config).temporal.channels
    twin = dataclasses.replace(config, temporal=None, bev=dataclasses.replace(config.bev, in_channels=frame_channels))
    return zoo.build_from_config(architecture, twin)


def _streaming(model: nn.Module, applied: list[str], cfg: BenchConfig, device: torch.device) -> dict:
    """Per-frame latency of ``model`` streamed over its scene's key frames against its single-frame twin (the same
    fast path applied) on the same frames, in interleaved pairs."""
    settings = zoo.experiment(cfg.model).data
    root = DEFAULT_DATA if cfg.data is None else Path(cfg.data)
    frames = [batch.to(device) for batch in load_scene_frames(settings, root, cfg.batch_size)]
    twin = single_frame_twin(cfg.model).to(device).eval()
    prepare_for_inference(twin)
    for name in applied:
        apply_optimization(twin, name)
    memory = model.stream()
    dtype = PRECISIONS[cfg.precision]
    autocast = partial(torch.autocast, device.type, dtype=dtype, enabled=dtype != torch.float32)
    synchronize = _synchronizer(device)
    step = {"streamed": 0, "single": 0}

    def streamed() -> float:
        batch = frames[step["streamed"] % len(frames)]
        step["streamed"] += 1
        with torch.no_grad(), autocast():
            return _timed(lambda: model(batch, memory=memory), synchronize)

    def single() -> float:
        batch = frames[step["single"] % len(frames)]
        step["single"] += 1
        with torch.no_grad(), autocast():
            return _timed(lambda: twin(batch), synchronize)

    for _ in range(max(cfg.warmup, 1)):
        streamed(), single()
    times, twin_times = paired_times(streamed, single, cfg.iters)
    slots = memory.states
    return {
        "frames": len(frames),
        "history": model.temporal.cfg.history,
        "fusion": model.temporal.cfg.fusion,
        "memory_slots": model.temporal.memory_frames,
        "memory_bytes": int(slots.numel() * slots.element_size()) if slots is not None else 0,
        "latency_ms": {"median": 1000 * statistics.median(times), "p90": 1000 * _percentile(times, 90),
                       "all": [1000 * t for t in times]},
        "fps": cfg.batch_size / statistics.median(times),
        "single_frame": {"model": f"{cfg.model} without history", "params": count_parameters(twin),
                         "latency_ms": {"median": 1000 * statistics.median(twin_times),
                                        "all": [1000 * t for t in twin_times]}},
        # The median of the pairs' ratios: each pair saw one machine load.
        "latency_ratio": statistics.median(t / s for t, s in zip(times, twin_times, strict=True)),
    }  # fmt: skip


# ------------------------------------------------------------------------------------------------- report
def format_report(result: dict) -> str:
    """A readable summary of :func:`run_bench`'s result: headline numbers, the stage table and the ablation."""
    latency = result["latency_ms"]
    lines = [
        f"{result['model']} on {result['machine']['device']} ({result['device']}, {result['machine']['threads']} "
        f"threads), {result['precision']}, batch {result['batch']}",
        f"  params {result['params'] / 1e6:.2f} M, MACs {result['macs'] / 1e9:.1f} G per sample",
        f"  latency median {latency['median']:.1f} ms, p90 {latency['p90']:.1f} ms; {result['fps']:.2f} FPS",
        f"  achieved {result['achieved_gflops']:.1f} GFLOP/s = {100 * result['gemm_fraction']:.0f}% of the GEMM peak "
        f"{result['gemm_peak_gflops']:.1f} GFLOP/s ({100 * result['gemm_fraction_paired']:.0f}% paired)",
        f"  peak memory {result['peak_memory']['bytes'] / 2**20:.0f} MiB ({result['peak_memory']['measure']})",
        f"  fast path: {', '.join(result['fast_path']['applied']) or 'none'}",
        "",
        f"  {'stage':<20} {'ms':>9} {'share':>6} {'GMACs':>8} {'GFLOP/s':>8} {'of GEMM':>8} {'ms > GEMM':>10}",
    ]
    for stage, entry in result["stages"].items():
        lines.append(f"  {stage:<20} {entry['ms']:>9.1f} {100 * entry['share']:>5.1f}% {entry['macs'] / 1e9:>8.2f} "
                     f"{entry['achieved_gflops']:>8.1f} {100 * entry['gemm_fraction']:>7.0f}% "
                     f"{entry['ms_beyond_gemm']:>10.1f}")  # fmt: skip
    if result["fast_path"]["mode"] == "auto":
        lines += ["", f"  {'optimization':<18} {'before ms':>10} {'after ms':>10} {'speed-up':>9}  kept"]
        for step in result["fast_path"]["steps"]:
            if "latency_ms" not in step:
                lines.append(f"  {step['optimization']:<18} {'':>10} {'':>10} {'':>9}  no: {step['error']}")
                continue
            kept = "yes" if step["kept"] else "no" + (f": {step['error']}" if "error" in step else "")
            lines.append(f"  {step['optimization']:<18} {step['reference_ms']:>10.1f} {step['latency_ms']:>10.1f} "
                         f"{step['speedup']:>8.3f}x  {kept}")  # fmt: skip
    if "streaming" in result:
        stream = result["streaming"]
        history = "one state" if stream["fusion"] == "recurrent" else f"history {stream['history']}"
        lines += ["", f"  streaming ({stream['fusion']}, {history}, {stream['frames']} frames "
                      f"cycled): {stream['latency_ms']['median']:.1f} ms per frame vs "
                      f"{stream['single_frame']['latency_ms']['median']:.1f} ms without history "
                      f"(x{stream['latency_ratio']:.3f}); memory {stream['memory_bytes'] / 2**20:.1f} MiB"]
    if "rt_miou" in result:
        rt = result["rt_miou"]
        lines += ["", "  " + ", ".join(f"{k.replace('rt_miou', 'RT-mIoU')} {v:.2f}" for k, v in rt.items()
                                       if k != "miou") + f" (mIoU {rt['miou']:g})"]  # fmt: skip
    return "\n".join(lines)
