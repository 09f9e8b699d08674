"""Peak memory of one forward pass: the CUDA allocator's peak, or the process's peak resident set on a CPU."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

__all__ = ["reset_peak_memory", "peak_memory"]


def reset_peak_memory(device: torch.device) -> bool:
    """Start a new peak-memory window; False when only the process-lifetime peak can be read (non-Linux CPU)."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        return True
    try:  # Linux: writing 5 resets the process's peak resident set size (VmHWM)
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def peak_memory(device: torch.device, window: bool) -> dict:
    """``bytes`` at the peak since :func:`reset_peak_memory` (``window``: what it returned) and the ``measure`` read."""
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
