"""The GPU suite's dry run: ``benchmarks/gpu_suite.py --device cpu --quick`` runs the code the GPU run runs, on a
CPU-sized entry, and writes its JSON with every section."""

from __future__ import annotations

import json

from conftest import benchmark_module


def test_the_gpu_suite_dry_runs_on_the_cpu_and_writes_one_json_per_model(tmp_path):
    from occkit.sim.generate import SimConfig, simulate_dataset

    world = tmp_path / "world"
    simulate_dataset(SimConfig(scenes=1, frames=3, seed=4, image_size=(400, 225)), world)
    suite = benchmark_module("gpu_suite.py")
    out = tmp_path / "gpu"
    assert suite.main(["--device", "cpu", "--quick", "--models", "flashocc_tiny", "--data", str(world),
                       "--train-data", str(world), "--workers", "0", "--out", str(out)]) == 0  # fmt: skip
    result = json.loads((out / "flashocc_tiny.json").read_text())
    assert set(result["inference"]) == {"fp32", "bf16"}  # no fp16 on a CPU
    for bench in result["inference"].values():
        assert bench["latency_ms"]["median"] > 0 and bench["fps"] > 0 and bench["peak_memory"]["bytes"] > 0
        assert bench["gemm_fraction"] > 0 and bench["gemm_peak_gflops"] > 0
    assert 0.9 <= result["agreement"]["bf16"] <= 1.0
    training = result["training"]
    assert training["steps_timed"] == 2 and training["samples_per_second"] > 0
    assert 0 <= training["loader_wait_fraction"] < 1 and training["projection_8_devices"]["hours"] > 0
    assert result["versions"]["occkit"] and result["machine"]["device"]
