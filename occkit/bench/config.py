"""What one benchmark run measures and how: :class:`BenchConfig`, and the precisions it runs in."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from occkit import zoo
from occkit.models.inference import check_optimizations

__all__ = ["PRECISIONS", "BenchConfig"]

#: ``--precision`` -> dtype of autocast and of the GEMM yardstick.
PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}


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
    cudnn_benchmark: bool = False
    """Let cuDNN time its algorithms for each convolution on the first passes and keep the fastest
    (``torch.backends.cudnn.benchmark``), as a deployment with fixed input sizes can; CUDA only. Off: PyTorch's
    default, cuDNN's heuristic choice."""
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
    """Dataset root to take the key frame from; None: :data:`~occkit.bench.DEFAULT_DATA`, simulated on first use."""
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
        if device.type == "cpu" and self.cudnn_benchmark:
            raise ValueError("cudnn_benchmark needs a CUDA device (cuDNN runs the convolutions there only)")
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
