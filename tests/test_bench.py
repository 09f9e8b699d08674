"""occkit bench, the inference fast path and RT-mIoU: structure and equivalence, never timings."""

from __future__ import annotations

import copy
import json
import time

import pytest
import torch
from torch import nn

from occkit import zoo
from occkit.bench import BenchConfig, format_report, load_sample, run_bench, single_frame_twin, stage_modules
from occkit.cli import main
from occkit.metrics.realtime import rt_miou, rt_miou_table
from occkit.models import inference
from occkit.models.complexity import count_macs
from occkit.models.inference import fix_calibration, fold_conv_bn, prepare_for_inference, to_channels_last

TINY = ("flashocc_tiny", "da_occ_tiny", "daocc_tiny")
# A bench run that measures nothing for long: one pass of each kind and a 64 x 64 GEMM.
QUICK = {"iters": 1, "warmup": 1, "stage_iters": 1, "ablation_iters": 1, "gemm_size": 64, "gemm_repeats": 1}


@pytest.fixture(scope="module")
def world(synthetic_world):
    """A one-scene, two-frame synthetic world with 176 x 99 images: enough for every tiny model's input."""
    return synthetic_world(scenes=1, frames=2, image_size=(176, 99))


def _randomise_batch_norms(model: nn.Module) -> None:
    """Statistics and affine parameters far from the initial (0, 1), so folding them is not a no-op."""
    generator = torch.Generator().manual_seed(0)
    for module in model.modules():
        if isinstance(module, nn.BatchNorm2d):
            channels = module.num_features
            module.running_mean.copy_(torch.randn(channels, generator=generator) * 0.5)
            module.running_var.copy_(torch.rand(channels, generator=generator) * 1.5 + 0.5)
            module.weight.data.copy_(torch.rand(channels, generator=generator) + 0.5)
            module.bias.data.copy_(torch.randn(channels, generator=generator) * 0.3)


# ----------------------------------------------------------------------------------------------------- RT-mIoU
def test_rt_miou_by_hand():
    # DA-Occ's definition: mIoU * min(FPS / K, 1).
    assert rt_miou(34.38, fps=7.5, k=15) == pytest.approx(17.19)  # half the frame rate: half the mIoU
    assert rt_miou(34.38, fps=25.0, k=20) == pytest.approx(34.38)  # faster than K: no discount
    assert rt_miou_table(30.0, fps=12.0) == pytest.approx({"rt_miou@10": 30.0, "rt_miou@15": 24.0, "rt_miou@20": 18.0})
    with pytest.raises(ValueError, match="K must be"):
        rt_miou(30.0, fps=10.0, k=0)
    with pytest.raises(ValueError, match="fps"):
        rt_miou(30.0, fps=-1.0, k=10)


# ------------------------------------------------------------------------------------------------- fast path
@pytest.mark.parametrize("name", TINY)
def test_folded_channels_last_model_matches_unfolded(name, synthetic_batch):
    torch.manual_seed(0)
    model = prepare_for_inference(zoo.build(name))
    _randomise_batch_norms(model)
    batch = synthetic_batch(batch_size=1, num_cameras=2, image_size=(128, 352), occupancy=False)
    with torch.no_grad():
        reference = model(batch).occupancy
        folded = fold_conv_bn(model)
        output = model(batch).occupancy
        assert to_channels_last(model)  # every Conv2d, and none of DAOcc's 5-D sparse convolution weights
        output_channels_last = model(batch).occupancy
    assert (output - reference).abs().max() < 1e-4
    assert (output_channels_last - reference).abs().max() < 1e-4
    left = [n for n, m in model.named_modules() if isinstance(m, nn.BatchNorm2d)]
    # Only the BatchNorms after DA-Occ's direction-aware convolutions (not a Conv2d) remain.
    assert all(n.endswith(".bn") and "Direction" in type(model.get_submodule(n[:-3]).conv).__name__ for n in left)
    assert len(folded) > 15 and (name == "da_occ_tiny") == bool(left)


def test_fold_leaves_shared_outputs_and_training_mode_alone():
    class Residual(nn.Module):
        def __init__(self):
            super().__init__()
            self.conv = nn.Conv2d(4, 4, 3, padding=1)
            self.bn = nn.BatchNorm2d(4)

        def forward(self, x):
            y = self.conv(x)
            return self.bn(y) + y  # the un-normalised output is read twice: folding would change the sum

    block = nn.Sequential(Residual(), nn.Conv2d(4, 4, 1), nn.BatchNorm2d(4)).eval()
    _randomise_batch_norms(block)
    x = torch.randn(1, 4, 8, 8)
    with torch.no_grad():
        reference = block(x)
        assert fold_conv_bn(block) == ["2"]
        assert torch.allclose(block(x), reference, atol=1e-5)
    assert isinstance(block[0].bn, nn.BatchNorm2d) and isinstance(block[2], nn.Identity)
    with pytest.raises(ValueError, match="eval-mode"):
        fold_conv_bn(block.train())


@pytest.mark.parametrize("name", TINY)
def test_fixed_calibration_set_from_outside(name, synthetic_batch):
    model = prepare_for_inference(zoo.build(name))
    plain = copy.deepcopy(model)
    assert fix_calibration(model) == [type(model).__name__] and model.reuse_plan and not plain.reuse_plan
    batch = synthetic_batch(batch_size=1, num_cameras=2, image_size=(128, 352), occupancy=False)
    # A camera marked failed changes the geometry (its points leave the plans) and nothing else, unless the first
    # geometry is reused. (Moving a camera would also change DA-Occ's camera-aware depth net.)
    changed_rig = copy.deepcopy(batch)
    changed_rig.camera_mask[:, 1] = False
    with torch.no_grad():
        first = model(batch).occupancy
        assert torch.equal(model(changed_rig).occupancy, first)
        assert torch.equal(plain(batch).occupancy, first) and not torch.equal(plain(changed_rig).occupancy, first)


def test_unknown_optimization_is_an_error():
    with pytest.raises(ValueError, match="unknown optimization"):
        prepare_for_inference(nn.Linear(2, 2), ["fold_bn", "int8"])


@pytest.mark.parametrize("name", TINY)
def test_every_parametrised_child_belongs_to_a_stage(name):
    model = prepare_for_inference(zoo.build(name))
    architecture = zoo.model_config(name)[0]
    staged = {id(m) for modules in stage_modules(architecture, model).values() for m in modules}
    unstaged = [n for n, m in model.named_children() if next(m.parameters(), None) is not None and id(m) not in staged]
    assert unstaged == []


# ----------------------------------------------------------------------------------------------------- bench
@pytest.mark.parametrize("name", TINY)
def test_bench_result_structure(name, world):
    result = run_bench(BenchConfig(model=name, data=str(world), optimizations=("fixed_calibration", "fold_bn"),
                                   miou=30.0, **QUICK), log=lambda _: None)  # fmt: skip
    for key in ("params", "macs", "latency_ms", "fps", "gemm_peak_gflops", "achieved_gflops", "stages",
                "gemm_fraction", "peak_memory", "machine", "fast_path", "rt_miou"):  # fmt: skip
        assert key in result, key
    stages = zoo.architecture(zoo.model_config(name)[0]).stages
    assert list(result["stages"]) == [*stages, "other"]
    stage_ms = [entry["ms"] for stage, entry in result["stages"].items() if stage != "other"]
    assert all(ms > 0 for ms in stage_ms) and sum(stage_ms) <= result["stages_total_ms"]
    assert sum(e["ms"] for e in result["stages"].values()) == pytest.approx(result["stages_total_ms"])
    assert (
        result["lowest_gemm_fraction"] in stages and result["most_time_beyond_gemm"] in result["stages"]
    )
    fast_path = result["fast_path"]
    assert fast_path["mode"] == "given" and fast_path["applied"] == ["fixed_calibration", "fold_bn"]
    assert [step["optimization"] for step in fast_path["steps"]] == fast_path["applied"]
    assert result["rt_miou"]["rt_miou@10"] == pytest.approx(rt_miou(30.0, result["fps"], 10))
    assert result["achieved_gflops"] == pytest.approx(2 * result["macs"] / result["latency_ms"]["median"] / 1e6)

    # MACs are count_macs of the network as run: detection removed, on the same key frame.
    model = prepare_for_inference(zoo.build(name))
    batch = load_sample(name, world)
    with torch.no_grad():
        macs = count_macs(model, lambda: model(batch))
    assert result["macs"] == macs.total
    assert sum(entry["macs"] for entry in result["stages"].values()) == macs.total
    assert ("macs_with_detection" in result) == (name == "daocc_tiny")


def test_a_temporal_model_streams_its_scene_against_its_single_frame_twin(world):
    result = run_bench(BenchConfig(model="da_occ_tiny_temporal", data=str(world), optimizations=(), **QUICK),
                       log=lambda _: None)  # fmt: skip
    stream = result["streaming"]
    assert stream["frames"] == 2 and stream["fusion"] == "recurrent" and stream["history"] == 0
    assert stream["memory_slots"] == 1 and stream["memory_bytes"] == 16 * 200 * 200 * 4
    assert stream["latency_ms"]["median"] > 0 and stream["single_frame"]["latency_ms"]["median"] > 0
    assert stream["latency_ratio"] > 0 and stream["single_frame"]["params"] < result["params"]
    assert "streaming (recurrent, one state, 2 frames" in format_report(result)
    twin = single_frame_twin("da_occ_tiny_temporal")
    assert twin.temporal is None and twin.cfg.bev.in_channels == 16


def test_auto_fast_path_measures_each_step_and_survives_a_failing_compile(world, monkeypatch):
    def no_compiler(model):
        raise RuntimeError("no C++ compiler found\nmore detail")

    monkeypatch.setattr(inference, "compile_dense_stages", no_compiler)
    result = run_bench(BenchConfig(model="flashocc_tiny", data=str(world), **QUICK), log=lambda _: None)
    steps = {step["optimization"]: step for step in result["fast_path"]["steps"]}
    assert list(steps) == list(inference.OPTIMIZATIONS)
    assert steps["compile"] == {"optimization": "compile", "kept": False,
                                "error": "RuntimeError: no C++ compiler found"}  # fmt: skip
    for name in ("fixed_calibration", "fold_bn", "channels_last"):
        assert steps[name]["relative_difference"] < 1e-3 and steps[name]["speedup"] > 0
    assert result["fast_path"]["applied"] == [name for name, step in steps.items() if step["kept"]]
    assert "compile" in format_report(result)


def test_given_fast_path_skips_a_failing_compile(world, monkeypatch):
    monkeypatch.setattr(inference, "compile_dense_stages", lambda model: 1 / 0)
    config = BenchConfig(model="flashocc_tiny", data=str(world), optimizations=("fold_bn", "compile"), **QUICK)
    fast_path = run_bench(config, log=lambda _: None)["fast_path"]
    assert fast_path["applied"] == ["fold_bn"]
    assert fast_path["steps"][1] == {"optimization": "compile", "kept": False,
                                     "error": "ZeroDivisionError: division by zero"}  # fmt: skip


def test_bench_cli_end_to_end(world, tmp_path, capsys):
    out = tmp_path / "bench.json"
    code = main(["bench", "--model", "flashocc_tiny", "--data", str(world), "--iters", "2", "--warmup", "1",
                 "--gemm-size", "64", "--optimizations", "fold_bn,channels_last", "--threads", "1", "--miou", "31.95",
                 "--out", str(out)])  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert "latency median" in printed and "RT-mIoU@15" in printed and "image_encoder" in printed
    result = json.loads(out.read_text())
    assert result["model"] == "flashocc_tiny" and result["batch"] == 1 and len(result["latency_ms"]["all"]) == 2
    assert result["machine"]["threads"] == 1 and result["fast_path"]["applied"] == ["fold_bn", "channels_last"]
    assert result["cudnn_benchmark"] is False


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cudnn_algorithm_search_is_recorded_and_switched_off_after_the_run(world):
    torch.backends.cudnn.benchmark = False
    config = BenchConfig(model="flashocc_tiny", device="cuda", data=str(world), cudnn_benchmark=True,
                         optimizations=("fixed_calibration", "fold_bn", "channels_last", "cuda_graph"), **QUICK)
    result = run_bench(config, log=lambda _: None)
    assert result["cudnn_benchmark"] is True and "cuDNN's algorithm search" in format_report(result)
    assert torch.backends.cudnn.benchmark is False


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--model", "resnet"], "unknown model 'resnet'"),
        (["--model", "flashocc_tiny", "--optimizations", "fold_bn,int8"], "unknown optimization(s) int8"),
        (["--model", "flashocc_tiny", "--precision", "fp16"], "fp16 needs a CUDA device"),
        (["--model", "flashocc_tiny", "--cudnn-benchmark"], "cudnn_benchmark needs a CUDA device"),
        (["--model", "flashocc_tiny", "--device", "tpu"], "--device must be cpu, cuda or cuda:N, got 'tpu'"),
        (["--model", "flashocc_tiny", "--data", "no/such/folder"], "--data no/such/folder does not exist"),
    ],
)
def test_bench_cli_bad_input(arguments, message, tmp_path, capsys):
    assert main(["bench", *arguments, "--out", str(tmp_path / "b.json")]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("occkit bench: error:") and message in error and "\n" not in error


class _SlowBackward(torch.autograd.Function):
    """Identity whose backward waits ``seconds``: a stage whose backward is known to dominate."""

    @staticmethod
    def forward(ctx, x, seconds):
        ctx.seconds = seconds
        return x.clone()

    @staticmethod
    def backward(ctx, grad):
        time.sleep(ctx.seconds)
        return grad, None


class _Stage(nn.Module):
    def __init__(self, seconds: float = 0.0) -> None:
        super().__init__()
        self.linear = nn.Linear(8, 8)
        self.seconds = seconds

    def forward(self, x):
        return _SlowBackward.apply(self.linear(x), self.seconds)


def test_stage_timer_splits_the_backward_by_stage():
    """The backward is shared among the stages in reverse forward order: the stamps partition it, and the stage
    whose backward sleeps gets that time."""
    from occkit.bench import StageTimer

    first, slow, last = _Stage(), _Stage(seconds=0.05), _Stage()
    stages = {"first": [first], "slow": [slow], "last": [last]}
    with StageTimer(stages, lambda: None, backward=True) as timer:
        loss = last(slow(first(torch.randn(4, 8)))).square().sum()
        started = time.perf_counter()
        timer.backward_started()
        loss.backward()
        timer.backward_done()
        elapsed = time.perf_counter() - started
    assert set(timer.backward_seconds) == {"first", "slow", "last"}
    assert all(seconds > 0 for seconds in timer.backward_seconds.values())
    assert timer.backward_seconds["slow"] >= 0.05
    assert timer.backward_seconds["slow"] > timer.backward_seconds["first"] + timer.backward_seconds["last"]
    covered = sum(timer.backward_seconds.values()) + timer.loss_backward_seconds
    assert covered == pytest.approx(elapsed, abs=0.01)  # the intervals partition the backward
    assert all(seconds > 0 for seconds in timer.seconds.values())  # forward times as before

