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

The modules, one step or tool each: ``config`` (:class:`BenchConfig`, :data:`PRECISIONS`), ``sample`` (step 1),
``runner`` (:class:`ModelRunner`), ``fast_path`` (step 3), ``memory`` and ``gemm`` (step 4's peak memory and
yardstick), ``timing`` (drained and paired timings), ``stages`` (step 5), ``streaming`` (step 6), ``run``
(:func:`run_bench`, the steps in order) and ``report`` (:func:`format_report`). The machine description in each
result is :func:`occkit.machine.machine_info`.
"""

from occkit.bench.config import PRECISIONS, BenchConfig
from occkit.bench.gemm import GemmProbe
from occkit.bench.report import format_report
from occkit.bench.run import run_bench
from occkit.bench.runner import ModelRunner
from occkit.bench.sample import DEFAULT_DATA, load_sample
from occkit.bench.stages import StageTimer, stage_modules
from occkit.bench.streaming import single_frame_twin
from occkit.bench.timing import paired_times
from occkit.machine import machine_info

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
