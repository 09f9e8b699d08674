"""What occkit runs on: library versions, compute devices, the sparse-convolution backend, grids and taxonomies.

Printed by ``occkit info`` and stored beside benchmark and training results, so numbers can be traced to the
software and hardware that produced them.
"""

from __future__ import annotations

import importlib.metadata

from occkit.machine import compute_devices, host

__all__ = ["environment_report", "format_environment_report"]

_PACKAGES = ("torch", "torchvision", "timm", "numpy", "numba", "onnxruntime")


def _package_versions() -> dict[str, str]:
    versions = {}
    for name in _PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    # spconv ships one distribution per CUDA version (spconv, spconv-cu120, spconv-cu126, ...).
    for dist in importlib.metadata.distributions():
        name = dist.metadata["Name"] or ""
        if name.lower().startswith("spconv"):
            versions[name] = dist.version
    return versions


def _sparse_backend() -> dict:
    try:
        from occkit.models import sparse
    except ImportError as error:
        return {"available": False, "error": str(error)}
    # The LiDAR encoder's default (SparseEncoder.backend "auto"): spconv's kernels on CUDA, occkit's gather-GEMM
    # path (occkit.models.sparse_gemm) on the CPU.
    return {"available": True, "cpu_backward_patched": sparse.SPCONV_CPU_BACKWARD_PATCHED,
            "cpu_path": "gather_gemm", "cuda_path": "spconv"}


def _determinism() -> dict:
    """What repeats bitwise from run to run here (measured by ``benchmarks/determinism.py`` and the engine tests)."""
    import torch

    threads = torch.get_num_threads()
    return {
        "cpu_training": f"bitwise repeatable at a fixed thread count (now {threads}), a run killed and resumed with "
                        "--resume auto included",
        "not_deterministic": "runs with different thread counts (they differ in the last bits), CUDA training "
                             "(atomic scatter-adds, cuDNN's algorithm choice); torchrun runs are not checked",
        "torch_deterministic_algorithms": torch.are_deterministic_algorithms_enabled(),
    }


def environment_report() -> dict:
    """A JSON-ready description of the software, hardware, grids and taxonomies occkit sees."""
    from occkit import __version__
    from occkit.classes import TAXONOMIES
    from occkit.label_space import LABEL_SPACES

    machine = host()
    return {
        "occkit": __version__,
        "python": machine["python"],
        "platform": machine["platform"],
        "packages": _package_versions(),
        "devices": compute_devices(),
        "sparse_conv": _sparse_backend(),
        "determinism": _determinism(),
        "grids": {
            name: {**space.grid.to_dict(), "shape": list(space.grid.shape)} for name, space in LABEL_SPACES.items()
        },
        "taxonomies": {
            name: {"classes": list(t.classes), "empty_index": t.empty_index, "ignore_index": t.ignore_index}
            for name, t in TAXONOMIES.items()
        },
        "shipped_weights": _shipped_weights(),
    }


def _shipped_weights() -> dict:
    """Entry -> the demo-world scores of the weights occkit ships for it (``--weights synthetic``) and its card's
    notes (where its run stands: converged or not, against its target)."""
    from occkit.shipped import card, shipped_entries

    return {entry: {**card(entry).scores, "notes": card(entry).notes} for entry in shipped_entries()}


def format_environment_report(report: dict) -> str:
    """Human-readable text of :func:`environment_report`."""
    devices = report["devices"]
    sparse = report["sparse_conv"]
    if devices["cuda_available"]:
        device_line = f"CUDA {devices['cuda_version']}: {', '.join(devices['gpus'])}"
    else:
        device_line = f"CPU only ({devices['cpu_threads']} threads)"
    if sparse["available"]:
        sparse_line = (f"spconv on CUDA, occkit's {sparse['cpu_path']} on the CPU"
                       + (" (spconv's CPU backward fix active)" if sparse["cpu_backward_patched"] else ""))
    else:
        sparse_line = f"unavailable: {sparse['error']}"
    lines = [
        f"occkit {report['occkit']} on Python {report['python']} ({report['platform']})",
        "packages: " + ", ".join(f"{name} {version}" for name, version in report["packages"].items()),
        f"device:   {device_line}",
        f"sparse:   {sparse_line}",
        f"repeats:  CPU training is {report['determinism']['cpu_training']}",
        f"          not bitwise: {report['determinism']['not_deterministic']}",
        "grids:",
    ]
    for name, grid in report["grids"].items():
        lines.append(
            f"  {name:<12} range {grid['point_cloud_range']}  voxel {grid['voxel_size']}  shape {grid['shape']}"
        )
    lines.append("taxonomies:")
    for name, taxonomy in report["taxonomies"].items():
        classes = taxonomy["classes"]
        lines.append(f"  {name:<12} {len(classes)} classes: " + " ".join(f"{i}:{c}" for i, c in enumerate(classes)))
    shipped = report["shipped_weights"]
    lines.append("shipped weights (--weights synthetic --model ENTRY; mIoU / IoU on the demo world's held-out scenes):"
                 if shipped else "shipped weights: none")  # fmt: skip
    for entry, scores in shipped.items():
        lines.append(f"  {entry:<22} {100 * scores['miou']:.1f} / {100 * scores['iou']:.1f}")
        if scores["notes"]:
            lines.append(f"  {'':<22} {scores['notes']}")
    return "\n".join(lines)
