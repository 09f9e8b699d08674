"""The machine a measurement ran on: the CPU's model and cores, Python and the platform, the compute devices.

One description for every number occkit measures: ``occkit bench`` and the scripts under ``benchmarks/`` store it
beside their results, ``occkit info`` prints it, so that a number can be traced to the hardware that produced it.
"""

from __future__ import annotations

import contextlib
import os
import platform
import subprocess
from pathlib import Path

import torch

__all__ = ["cpu_model", "host", "compute_devices", "machine_info", "gpu_driver"]


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux), else what :mod:`platform` knows: the processor's name or
    the architecture."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def gpu_driver() -> str | None:
    """The NVIDIA driver's version, as ``nvidia-smi`` reports it; None where there is none."""
    try:
        found = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                               capture_output=True, text=True, check=True, timeout=30)  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    return found.stdout.strip().splitlines()[0] if found.stdout.strip() else None


def host() -> dict:
    """The machine without its compute devices: ``cpu`` (:func:`cpu_model`), ``cpu_count`` (logical cores),
    ``python`` (its version) and ``platform`` (the operating system, its release and the architecture)."""
    return {"cpu": cpu_model(), "cpu_count": os.cpu_count(), "python": platform.python_version(),
            "platform": platform.platform()}  # fmt: skip


def compute_devices() -> dict:
    """What PyTorch can compute on: ``cuda_available``, ``cuda_version`` (PyTorch's build), ``gpus`` (every CUDA
    device's name) and ``cpu_threads`` (PyTorch's thread count)."""
    cuda = torch.cuda.is_available()
    return {
        "cuda_available": cuda,
        "cuda_version": torch.version.cuda,
        "gpus": [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())] if cuda else [],
        "cpu_threads": torch.get_num_threads(),
    }


def machine_info(device: torch.device | str = "cpu") -> dict:
    """The machine of a measurement on ``device``: ``cpu``, ``cpu_count``, ``threads`` (PyTorch's), ``torch``,
    ``platform`` and ``device`` (the CPU's model, or the GPU's name); on CUDA also ``cuda``, ``cudnn`` and whether
    TF32 is allowed in matrix products (``tf32_matmul``) and in cuDNN's convolutions (``tf32_cudnn``)."""
    device = torch.device(device)
    here = host()
    info = {
        "cpu": here["cpu"],
        "cpu_count": here["cpu_count"],
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "platform": here["platform"],
        "device": here["cpu"] if device.type == "cpu" else torch.cuda.get_device_name(device),
    }
    if device.type == "cuda":
        info.update(
            cuda=torch.version.cuda,
            cudnn=torch.backends.cudnn.version(),
            tf32_matmul=torch.backends.cuda.matmul.allow_tf32,
            tf32_cudnn=torch.backends.cudnn.allow_tf32,
        )
    return info
