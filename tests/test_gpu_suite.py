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
                       "--train-data", str(world), "--workers", "0", "--out", str(out), "--graphs"]) == 0  # fmt: skip
    result = json.loads((out / "flashocc_tiny.json").read_text())
    # No fp16 on a CPU; the graph rows run, their cuda_graph step skipped with its reason.
    assert set(result["inference"]) == {"fp32", "bf16", "fp32_cuda_graph", "bf16_cuda_graph"}
    graph_step = result["inference"]["fp32_cuda_graph"]["fast_path"]["steps"][-1]
    assert graph_step["optimization"] == "cuda_graph" and not graph_step["kept"]
    assert result["inference"]["fp32_cuda_graph"]["fast_path"]["applied"] == ["fixed_calibration", "fold_bn",
                                                                             "channels_last"]  # fmt: skip
    assert "CUDA device" in graph_step["error"]
    for bench in result["inference"].values():
        assert bench["latency_ms"]["median"] > 0 and bench["fps"] > 0 and bench["peak_memory"]["bytes"] > 0
        assert bench["gemm_fraction"] > 0 and bench["gemm_peak_gflops"] > 0
    assert 0.9 <= result["agreement"]["bf16"] <= 1.0
    training = result["training"]
    assert training["steps_timed"] == 2 and len(training["wait_seconds"]["all"]) == 2
    assert 0 < training["samples_per_second"] <= training["device_bound_samples_per_second"]
    assert 0 <= training["loader_wait_fraction"] < 1 and training["loader_workers_needed"] >= 0
    projection = training["projection_8_devices"]
    assert projection["hours"] >= projection["hours_device_bound"] > 0
    assert result["versions"]["occkit"] and result["machine"]["device"] and "errors" not in result

    # --rederive recomputes the derived figures from the raw ones: the same numbers again.
    before = (out / "flashocc_tiny.json").read_text()
    assert suite.main(["--rederive", str(out / "flashocc_tiny.json")]) == 0
    assert json.loads((out / "flashocc_tiny.json").read_text()) == json.loads(before)


def test_the_derived_training_figures_count_the_loaders_stalls():
    """Three fast steps and one that waited a second for the loader: the rate is samples over the whole time, not
    over the median step, and the workers needed scale the workers by the device-bound rate over the delivered one."""
    suite = benchmark_module("gpu_suite.py")
    times = [0.1, 0.1, 0.1, 1.1]
    training = {"step_seconds": {"all": times}, "batch_per_device": 4, "loader_workers": 8,
                "loader_wait_fraction": 1.0 / 1.4}  # fmt: skip
    derived = suite.derived_throughput(training, epochs=24, sampler="random")
    assert derived["step_seconds"]["median"] == 0.1 and abs(derived["step_seconds"]["mean"] - 0.35) < 1e-12
    assert abs(derived["samples_per_second"] - 16 / 1.4) < 1e-9
    assert abs(derived["compute_seconds_mean"] - 0.1) < 1e-12
    assert abs(derived["device_bound_samples_per_second"] - 40) < 1e-9
    assert derived["loader_workers_needed"] == 28  # ceil(8 * 40 / 11.43)
    assert abs(derived["projection_8_devices"]["hours"] - 28130 * 24 / (8 * 16 / 1.4) / 3600) < 1e-9
