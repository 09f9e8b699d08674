"""The text summary of a benchmark result: headline numbers, the stage table, the ablation, streaming, RT-mIoU."""

from __future__ import annotations

__all__ = ["format_report"]


def format_report(result: dict) -> str:
    """A readable summary of :func:`~occkit.bench.run_bench`'s result: headline numbers, the stage table and the
    ablation."""
    latency = result["latency_ms"]
    lines = [
        f"{result['model']} on {result['machine']['device']} ({result['device']}, {result['machine']['threads']} "
        f"threads), {result['precision']}, batch {result['batch']}",
        f"  params {result['params'] / 1e6:.2f} M, MACs {result['macs'] / 1e9:.1f} G per sample",
        f"  latency median {latency['median']:.1f} ms, p90 {latency['p90']:.1f} ms; {result['fps']:.2f} FPS",
        f"  achieved {result['achieved_gflops']:.1f} GFLOP/s = {100 * result['gemm_fraction']:.0f}% of the GEMM peak "
        f"{result['gemm_peak_gflops']:.1f} GFLOP/s ({100 * result['gemm_fraction_paired']:.0f}% paired)",
        f"  peak memory {result['peak_memory']['bytes'] / 2**20:.0f} MiB ({result['peak_memory']['measure']})",
        f"  fast path: {', '.join(result['fast_path']['applied']) or 'none'}"
        + ("; cuDNN's algorithm search" if result.get("cudnn_benchmark") else ""),
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
                      f"(x{stream['latency_ratio']:.3f}); memory {stream['memory_bytes'] / 2**20:.1f} MiB"]  # fmt: skip
    if "rt_miou" in result:
        rt = result["rt_miou"]
        lines += ["", "  " + ", ".join(f"{k.replace('rt_miou', 'RT-mIoU')} {v:.2f}" for k, v in rt.items()
                                       if k != "miou") + f" (mIoU {rt['miou']:g})"]  # fmt: skip
    return "\n".join(lines)
