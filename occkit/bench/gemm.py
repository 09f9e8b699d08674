"""The GEMM yardstick: the square matrix product's throughput, which a model's arithmetic rate is a fraction of."""

from __future__ import annotations

from collections.abc import Callable

import torch

from occkit.bench.timing import synchronizer, timed

__all__ = ["GemmProbe"]


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
        self.synchronize = synchronizer(device)
        self.best_by_route: dict[str, float] = {}
        self.samples: list[float] = []

    def _rate(self, route: str) -> float:
        return 2 * self.size**3 / timed(self.routes[route], self.synchronize) / 1e9

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
