"""ONNX export: rulebooks against spconv, fixed-rig networks against their models, parity in onnxruntime, the CLI."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch
from conftest import make_batch
from torch import nn

from occkit import zoo
from occkit.cli import main
from occkit.export import ExportError, check_parity, export_onnx, operator_counts
from occkit.geometry.se3 import make_transform, rotation_about_z
from occkit.models.daocc import DAOcc
from occkit.models.deployment import OUTPUT_NAME, STATE_NAME, DeployedNetwork, deploy
from occkit.models.lidar_encoder import LidarEncoder, LidarEncoderConfig
from occkit.models.sparse_rules import (
    ConvSpec,
    RulebookSparseEncoder,
    build_rulebooks,
    encoder_conv_specs,
    strided_rulebook,
    submanifold_rulebook,
)
from occkit.types import Batch


def exporter_available() -> None:
    for module in ("onnx", "onnxruntime", "onnxscript"):
        pytest.importorskip(module)


# ------------------------------------------------------------------------------------------------------ rulebooks
def test_submanifold_rulebook_pairs_neighbours_within_a_sample():
    spec = ConvSpec("subm", True, (3, 3, 3), (1, 1, 1), (1, 1, 1), (4, 4, 4), (4, 4, 4))
    # Sites 0 and 1 are x-neighbours in sample 0; site 2 sits next to site 0's position but in sample 1.
    coords = torch.tensor([[0, 1, 1, 1], [0, 2, 1, 1], [1, 2, 1, 1]])
    pairs = submanifold_rulebook(coords, spec)
    assert spec.centre == 13 and len(spec.offsets) == 26 and pairs.shape == (2, 26, 1)
    minus_x, plus_x = spec.offsets.index(4), spec.offsets.index(22)  # kernel (0, 1, 1) and (2, 1, 1)
    found = {(k, int(pairs[0, k, 0]), int(pairs[1, k, 0])) for k in range(26) if pairs[1, k, 0] != 3}
    # Output 0 reads input 1 through +x, output 1 reads input 0 through -x; sample 1 has no neighbour.
    assert found == {(plus_x, 1, 0), (minus_x, 0, 1)}


def test_strided_rulebook_lists_every_output_its_inputs_reach():
    spec = ConvSpec("down", False, (3, 3, 3), (2, 2, 2), (1, 1, 1), (8, 8, 3), (4, 4, 2))
    pairs, out_coords = strided_rulebook(torch.tensor([[0, 3, 2, 0]]), spec)
    # x = 3 reaches o = 1 (kernel 2) and o = 2 (kernel 0); y = 2 reaches o = 1 (kernel 1); z = 0 reaches o = 0 only.
    assert out_coords.tolist() == [[0, 1, 1, 0], [0, 2, 1, 0]]
    found = {(k, int(pairs[1, k, 0])) for k in range(27) if pairs.shape[2] and pairs[1, k, 0] != 2}
    assert found == {((2 * 3 + 1) * 3 + 1, 0), ((0 * 3 + 1) * 3 + 1, 1)}


def randomize_batch_norms(module: nn.Module, generator: torch.Generator) -> None:
    for bn in module.modules():
        if isinstance(bn, nn.BatchNorm1d):
            channels = bn.num_features
            bn.running_mean.copy_(0.2 * torch.randn(channels, generator=generator))
            bn.running_var.copy_(0.5 + torch.rand(channels, generator=generator))
            with torch.no_grad():
                bn.weight.copy_(0.5 + torch.rand(channels, generator=generator))
                bn.bias.copy_(0.2 * torch.randn(channels, generator=generator))


def random_clouds(cfg: LidarEncoderConfig, sizes: list[int], generator: torch.Generator):
    """Padded ``(B, P, 5)`` points: a ground plane (neighbouring voxels) plus points scattered in the volume."""
    low, high = torch.tensor(cfg.point_cloud_range[:3]), torch.tensor(cfg.point_cloud_range[3:])
    points = torch.zeros(len(sizes), max(sizes), 5)
    for b, size in enumerate(sizes):
        xyz = low + torch.rand(size, 3, generator=generator) * (high - low)
        xyz[: size // 2, :2] = xyz[: size // 2, :2] * 0.2  # a dense patch near the car
        xyz[: size // 2, 2] = -1.7
        points[b, :size] = torch.cat((xyz, torch.rand(size, 2, generator=generator)), dim=1)
    return points, torch.tensor(sizes)


@pytest.mark.parametrize("layout", ["paper", "tiny"])
def test_rulebook_encoder_matches_spconv(layout):
    cfg = LidarEncoderConfig() if layout == "paper" else zoo.model_config("daocc_tiny")[1].lidar
    generator = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    lidar = LidarEncoder(cfg).eval()
    randomize_batch_norms(lidar, generator)
    specs = encoder_conv_specs(lidar.encoder)
    stages = len(cfg.encoder_channels)  # paper: 4; each stage's submanifold key, then its downsampling but the last
    keys = [key for i in range(1, stages + 1) for key in (f"subm{i}", f"spconv{i}")][:-1] + ["spconv_down2"]
    assert [s.key for s in specs] == keys
    assert specs[0].in_shape == cfg.sparse_shape and specs[-1].out_shape == lidar.encoder.output_shape
    points, num_points = random_clouds(cfg, [3000, 2000], generator)
    features, coords, _ = lidar.voxelize(points, num_points)
    runner = RulebookSparseEncoder(lidar.encoder, batch_size=2)
    pairs, out_coords = runner.rulebook_tensors(coords)
    with torch.no_grad():
        expected = lidar.encoder(features, coords, 2)
        bev = runner(features, pairs, out_coords)
    assert bev.shape == expected.shape == (2, cfg.out_channels, *cfg.bev_shape)
    scale = float(expected.abs().max())
    assert scale > 0 and all(bool(expected[b].any()) for b in range(2))
    torch.testing.assert_close(bev, expected, rtol=0, atol=1e-4 * scale)
    # The submanifold rulebooks leave the centre out; the strided ones list all 27 offsets.
    assert [p.shape[1] for p in pairs] == [26, 27] * (stages - 1) + [26, 3]
    rulebooks = build_rulebooks(specs, coords)
    assert torch.equal(rulebooks["spconv_down2"].out_coords, out_coords[-1])
    # Within one offset each output row occurs at most once (padding aside): the per-offset scatters of the
    # exported graph never add twice into one row, so onnxruntime's threads cannot race on real rows.
    for rulebook in rulebooks.values():
        for rows in rulebook.pairs[1]:
            rows = rows[rows != rulebook.num_out]
            assert rows.unique().numel() == rows.numel()


# ------------------------------------------------------------------------------------------------------ export
def tiny_model(name: str) -> nn.Module:
    torch.manual_seed(0)
    model = zoo.build(name).eval()
    if hasattr(model, "remove_detection"):
        model.remove_detection()
    return model


#: Per tiny model: a batch it accepts (DA-Occ's DACs fix the feature height, 128 / 16; DAOcc's five cameras of
#: 90 degrees overlap, so a voxel gathers the samples of several cameras) and operators its graph must hold.
CASES = {
    "flashocc_tiny": ({"num_cameras": 2}, {"Conv", "Gather", "ScatterElements", "Softmax"}),
    "da_occ_tiny": ({"num_cameras": 2, "image_size": (128, 352)}, {"Conv", "GatherElements", "MatMul", "Erf"}),
    "daocc_tiny": ({"num_cameras": 5, "num_points": 2000}, {"Conv", "Gather", "ScatterND", "MatMul"}),
}


@dataclasses.dataclass
class Exported:
    model: nn.Module
    batch: Batch
    net: DeployedNetwork
    path: Path
    summary: dict


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """``exported(name)``: the tiny model exported once per test module, with what it was exported from."""
    exporter_available()
    cache: dict[str, Exported] = {}

    def export(name: str) -> Exported:
        if name not in cache:
            model = tiny_model(name)
            batch = make_batch(batch_size=1, occupancy=False, **CASES[name][0])
            net = deploy(model, batch)
            path = tmp_path_factory.mktemp("onnx") / f"{name}.onnx"
            summary = export_onnx(net, net.inputs(batch), path)
            cache[name] = Exported(model, batch, net, path, summary)
        return cache[name]

    return export


@pytest.mark.parametrize("name", list(CASES))
def test_tiny_model_exports_with_standard_operators_and_matches_in_onnxruntime(name, exported):
    result = exported(name)
    summary = result.summary
    assert summary["opset"] == 18 and summary["files"] == [str(result.path)]
    assert [spec["name"] for spec in summary["inputs"]] == result.net.input_names
    assert summary["outputs"][0] == {"name": OUTPUT_NAME, "shape": [1, 18, 200, 200, 16], "dtype": "float32",
                                     "doc": "occupancy logits (B, K, X, Y, Z)"}  # fmt: skip
    assert CASES[name][1] <= set(summary["op_types"])
    parity = check_parity(result.path, result.model, result.net, result.batch)
    assert parity["passed"], parity
    assert parity["max_abs_diff"] < 1e-4 and parity["network_max_abs_diff"] < 1e-5
    assert parity["argmax_agreement"] == 1.0 and parity["voxels"] == 200 * 200 * 16


def test_a_temporal_graph_takes_the_history_in_and_gives_the_state_out_over_a_streamed_scene(tmp_path):
    exporter_available()
    model = tiny_model("da_occ_tiny_temporal")
    frames = []
    for t in range(5):  # one scene: 2 m and 3 degrees per frame
        frame = make_batch(batch_size=1, occupancy=False, seed=t, num_cameras=2, image_size=(128, 352))
        yaw = torch.tensor(math.radians(3.0 * t))
        frame.ego2global = make_transform(rotation_about_z(yaw), torch.tensor([2.0 * t, 0.0, 0.0])).double()[None]
        frames.append(frame)
    net = deploy(model, frames[0])
    assert net.input_names == ["images", "history", "current_to_history", "history_padded"]
    assert net.output_names == [OUTPUT_NAME, STATE_NAME]
    summary = export_onnx(net, net.inputs(frames[0]), tmp_path / "temporal.onnx")
    assert [spec["name"] for spec in summary["outputs"]] == [OUTPUT_NAME, STATE_NAME]
    assert summary["outputs"][1]["shape"] == [1, 16, 200, 200] and "GridSample" in summary["op_types"]
    parity = check_parity(tmp_path / "temporal.onnx", model, net, frames[0], frames)
    assert parity["passed"], parity
    assert parity["frames"] == 5 and max(parity["max_abs_diff_per_frame"]) <= 1e-3
    assert parity["voxels"] == 5 * 200 * 200 * 16


def test_daocc_graph_takes_any_lidar_sweep_of_the_rig(exported):
    """The voxel and rulebook axes are dynamic: another sweep, with other counts, runs through the same graph."""
    import onnxruntime as ort

    result = exported("daocc_tiny")
    net = result.net
    sampling = net.plan().sampling
    assert bool((sampling.weight == 0.5).any())  # overlapping cameras, each voxel gathering from both (no scatter)
    assert net.input_names[:2] == ["images", "voxel_features"] and net.input_names[-1] == "coords_spconv_down2"
    options = ort.SessionOptions()
    options.intra_op_num_threads = 4  # scatters with repeated rows would race here
    session = ort.InferenceSession(str(result.path), options, providers=["CPUExecutionProvider"])
    shapes = {i.name: i.shape for i in session.get_inputs()}
    assert shapes["voxel_features"] == ["voxels", 5] and shapes["rules_subm1"] == [2, 26, "pairs_subm1"]
    other = make_batch(batch_size=1, occupancy=False, num_cameras=5, num_points=700, seed=3)
    inputs = net.inputs(other)
    assert inputs["voxel_features"].shape[0] != net.inputs(result.batch)["voxel_features"].shape[0]
    feeds = {name: tensor.numpy() for name, tensor in inputs.items()}
    with torch.no_grad():
        expected = result.model(other).occupancy
    for _ in range(3):
        logits = session.run([OUTPUT_NAME], feeds)[0]
        torch.testing.assert_close(torch.from_numpy(logits), expected, rtol=0, atol=1e-4)


@pytest.mark.parametrize(("branch", "names"), [("image", ["voxel_features", "rules_subm1"]), ("lidar", ["images"])])
def test_daocc_variants_deploy_without_the_missing_branch(branch, names):
    """LiDAR-only (no ``image``) and camera-only (no ``lidar``) DAOcc: only their own inputs, same logits."""
    torch.manual_seed(0)
    model = DAOcc(dataclasses.replace(zoo.model_config("daocc_tiny")[1], **{branch: None}, detection=None)).eval()
    batch = make_batch(batch_size=1, occupancy=False, num_points=1000)
    net = deploy(model, batch)
    inputs = net.inputs(batch)
    assert list(inputs) == net.input_names and net.input_names[: len(names)] == names
    assert ("images" in inputs) == (branch != "image")
    with torch.no_grad():
        torch.testing.assert_close(net(*inputs.values()), model(batch).occupancy, rtol=0, atol=1e-5)


def test_non_standard_operators_are_rejected(tmp_path):
    onnx = pytest.importorskip("onnx")
    helper = onnx.helper
    node = helper.make_node("FusedMatMul", ["a", "b"], ["c"], domain="com.microsoft")
    value = [helper.make_tensor_value_info(n, onnx.TensorProto.FLOAT, [2, 2]) for n in "abc"]
    graph = helper.make_graph([helper.make_node("Relu", ["c"], ["d"]), node], "g", value[:2],
                              [helper.make_tensor_value_info("d", onnx.TensorProto.FLOAT, [2, 2])])  # fmt: skip
    opsets = [helper.make_opsetid("", 18), helper.make_opsetid("com.microsoft", 1)]
    model = helper.make_model(graph, opset_imports=opsets)
    onnx.save(model, tmp_path / "custom.onnx")
    with pytest.raises(ExportError, match="com.microsoft::FusedMatMul"):
        operator_counts(tmp_path / "custom.onnx")
    model.graph.node.pop()  # the Relu alone is standard
    onnx.save(model, tmp_path / "standard.onnx")
    assert operator_counts(tmp_path / "standard.onnx") == {"Relu": 1}


# ------------------------------------------------------------------------------------------------------ CLI
def save_checkpoint(name: str, path, **occupancy_changes) -> str:
    """A checkpoint of zoo entry ``name`` (random weights), its occupancy head config changed by the keywords."""
    from occkit.engine.checkpoint import FORMAT, atomic_save
    from occkit.experiment import Experiment

    experiment = zoo.experiment(name)
    model_config = dataclasses.replace(experiment.model, occupancy=dataclasses.replace(experiment.model.occupancy,
                                                                                        **occupancy_changes))
    experiment = Experiment(experiment.architecture, model_config, experiment.data, experiment.train)
    torch.manual_seed(1)
    model = zoo.build_from_config(experiment.architecture, model_config)
    payload = {"format": FORMAT, "architecture": experiment.architecture, "experiment": experiment.to_dict(),
               "model": model.state_dict(), "ema": None}  # fmt: skip
    return str(atomic_save(payload, path))


def test_cli_exports_a_checkpoint_on_a_generated_world(tmp_path, capsys):
    exporter_available()
    # Trained with another loss weight: the same network, exported with the checkpoint's own config and a note.
    lovasz = zoo.model_config("flashocc_tiny")[1].occupancy.lovasz_weight
    checkpoint = save_checkpoint("flashocc_tiny", tmp_path / "flashocc_tiny.pt", lovasz_weight=lovasz + 0.5)
    out = tmp_path / "deploy" / "flashocc_tiny.onnx"
    assert main(["export", "--model", "flashocc_tiny", "--ckpt", checkpoint, "--out", str(out), "--repeats", "1"]) == 0
    printed = capsys.readouterr().out
    assert "note: " in printed and "standard operators only" in printed and ": passed" in printed
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["model"] == "flashocc_tiny" and report["checkpoint"] == checkpoint and report["opset"] == 18
    assert "model.occupancy.lovasz_weight" in report["config_difference"]
    assert report["inputs"][0]["name"] == "images" and report["inputs"][0]["shape"] == [1, 6, 3, 128, 352]
    assert report["outputs"][0]["name"] == OUTPUT_NAME and report["parity"]["passed"]
    assert report["parity"]["argmax_agreement"] >= 0.999 and report["parity"]["max_abs_diff"] <= 1e-3
    assert set(report["precomputed"]) == {"plan_ranks_depth", "plan_ranks_feat", "plan_ranks_bev"}
    assert report["latency_ms"]["onnxruntime"] > 0 and "Conv" in report["op_types"]


@pytest.mark.parametrize(("precision", "operators"), [("int8", {"QuantizeLinear", "DequantizeLinear"}),
                                                      ("fp16", {"Cast", "ScatterElements"})])
def test_reduced_precision_exports_keep_standard_operators_and_time_themselves_against_fp32(
    precision, operators, tmp_path, capsys
):
    exporter_available()
    out = tmp_path / f"{precision}.onnx"
    # Every layer quantized (--keep-fp32 none): the sensitivity sweep is tests/test_quantization.py's.
    assert main(["export", "--model", "flashocc_tiny", "--out", str(out), "--precision", precision,
                 "--calibration-frames", "2", "--repeats", "1", "--keep-fp32", "none"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert f"{precision} / fp32 = " in printed and ("layers left fp32: none" in printed) == (precision == "int8")
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["precision"] == precision and operators | {"Conv"} <= set(operator_counts(out))
    assert report["int8"]["calibration_frames"] == 2 if precision == "int8" else "ScatterElements" in \
        report["fp16"]["kept_fp32"]  # fmt: skip
    assert report["parity"]["passed"] is None and report["parity"]["argmax_agreement"] > 0.9
    latency = report["latency_ms"]
    assert latency[f"onnxruntime_{precision}"] > 0 and latency["onnxruntime_fp32"] > 0
    assert latency[f"{precision}_over_fp32"] > 0
    assert out.stat().st_size < 0.6 * sum(p.numel() for p in zoo.build("flashocc_tiny").parameters()) * 4


def test_int8_export_refuses_a_model_with_a_history_state(tmp_path, capsys):
    exporter_available()
    assert main(["export", "--model", "da_occ_tiny_temporal", "--out", str(tmp_path / "t.onnx"),
                 "--precision", "int8"]) == 2  # fmt: skip
    assert "int8 export takes single-frame models" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--model", "flashocc_m9"], "unknown model 'flashocc_m9'; the zoo has: "),
        (["--model", "daocc_tiny", "--ckpt", "{flashocc}"], "holds a flashocc model, not daocc: it is not a "
                                                            "checkpoint of zoo model daocc_tiny"),
        (["--model", "flashocc_m0", "--ckpt", "{flashocc}"], "is not a checkpoint of zoo model flashocc_m0: "
                                                             "parameter "),
        (["--model", "flashocc_tiny", "--ckpt", "{missing}"], "does not exist"),
        (["--model", "flashocc_tiny", "--opset", "99"], "opset 99 is not available: the installed onnx package"),
        (["--model", "flashocc_tiny", "--data", "{missing}"], "missing does not exist"),
    ],
)
def test_cli_bad_input_is_one_clear_error(arguments, message, tmp_path, capsys):
    paths = {"{flashocc}": None, "{missing}": str(tmp_path / "missing")}
    if "{flashocc}" in arguments:
        paths["{flashocc}"] = save_checkpoint("flashocc_tiny", tmp_path / "flashocc_tiny.pt")
    arguments = [paths.get(a, a) for a in arguments]
    assert main(["export", *arguments, "--out", str(tmp_path / "model.onnx")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("occkit export: error: ") and message in error and error.count("\n") == 1
    assert not (tmp_path / "model.onnx").exists()
