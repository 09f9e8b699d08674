"""onnxruntime on the CPU, as the exporter and the int8 quantizer run it: the optional dependency, a session with
PyTorch's thread count, the feeds of a network's inputs, and two graphs timed against each other."""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from occkit.errors import require_module

__all__ = ["require", "open_session", "to_feeds", "paired_latency"]


def require(module: str):
    """Import an optional dependency of the export, or say how to get it (a MissingDependencyError: exit code 2)."""
    return require_module(module, "ONNX export", "pip install onnx onnxruntime onnxscript (or the package's dev extra)")


def open_session(path: str | Path):
    """An onnxruntime CPU session using as many threads as PyTorch, so that their timings compare, whose threads
    sleep when idle: by default they spin on after each run, and two sessions timed in turn on few cores then time
    each other's spinning (measured on 2 cores: flashocc_tiny's fp32 and int8 graphs in pairs 141 and 80 ms spinning,
    108 and 50 ms not, each alone 109 and 50 ms either way)."""
    ort = require("onnxruntime")
    options = ort.SessionOptions()
    options.intra_op_num_threads = torch.get_num_threads()
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def to_feeds(inputs: dict[str, Tensor]) -> dict[str, np.ndarray]:
    """A network's named input tensors as onnxruntime's feeds."""
    return {name: tensor.detach().cpu().numpy() for name, tensor in inputs.items()}


def paired_latency(first: str | Path, second: str | Path, feeds: dict[str, np.ndarray], output_names: list[str],
                   pairs: int) -> dict[str, Any]:  # fmt: skip
    """Median onnxruntime latencies (ms) of two graphs on the same feeds, timed in interleaved pairs after a warm-up
    of each (so that machine load hits both alike), and the median of the pairs' ratios ``second / first``."""
    sessions = [open_session(first), open_session(second)]
    for each in sessions:
        each.run(output_names, feeds)
    times: list[list[float]] = [[], []]
    for _ in range(pairs):
        for index, each in enumerate(sessions):
            start = time.perf_counter()
            each.run(output_names, feeds)
            times[index].append(time.perf_counter() - start)
    ratios = [b / a for a, b in zip(*times, strict=True)]
    return {"first_ms": round(1000 * statistics.median(times[0]), 2),
            "second_ms": round(1000 * statistics.median(times[1]), 2),
            "ratio": statistics.median(ratios), "pairs": pairs, "threads": torch.get_num_threads()}  # fmt: skip
