"""int8 quantization (occkit.quantization): which layers are quantized, which stay fp32, and why."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from occkit import quantization
from occkit.commands.deploy import _kept_fp32_line
from occkit.export import operator_counts

pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxscript")


class ClassesPerVoxel(nn.Module):
    """Two convolutions to ``(B, K, X, Y)`` class scores, the class axis 1 as in the occupancy logits."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.features = nn.Conv2d(2, 8, 3, padding=1)
        self.classes = nn.Conv2d(8, 5, 1)

    def forward(self, x):
        return self.classes(torch.relu(self.features(x)))


@pytest.fixture(scope="module")
def fp32_graph(tmp_path_factory):
    path = tmp_path_factory.mktemp("int8") / "fp32.onnx"
    example = torch.randn(1, 2, 16, 16)
    program = torch.onnx.export(ClassesPerVoxel().eval(), (example,), dynamo=True, input_names=["x"], verbose=False)
    program.save(str(path))
    rng = np.random.default_rng(0)
    calibration = [{"x": rng.standard_normal((1, 2, 16, 16)).astype(np.float32)} for _ in range(3)]
    return path, calibration


def _float_convolutions(path) -> int:
    """Convolutions whose weight is a plain initializer (not fed by a DequantizeLinear)."""
    graph = onnx.load(str(path)).graph
    dequantized = {output for node in graph.node if node.op_type == "DequantizeLinear" for output in node.output}
    return sum(node.op_type == "Conv" and node.input[1] not in dequantized for node in graph.node)


def test_the_sensitivity_quantizes_each_layer_alone_and_counts_the_changed_classes(fp32_graph, tmp_path):
    path, calibration = fp32_graph
    prepared = quantization.prepare(path, tmp_path / "prepared.onnx")
    layers = quantization.quantizable_layers(prepared)
    assert [layer["op_type"] for layer in layers] == ["Conv", "Conv"]
    sensitivity = quantization.layer_sensitivity(prepared, calibration)
    assert [layer["node"] for layer in sensitivity] == [layer["node"] for layer in layers]
    assert all(0 <= layer["disagreement"] < 0.5 for layer in sensitivity)


def test_auto_keeps_fp32_exactly_the_layers_above_the_threshold(fp32_graph, tmp_path, monkeypatch):
    path, calibration = fp32_graph
    report = quantization.quantize_int8(path, tmp_path / "auto.onnx", calibration)
    assert len(report["sensitivity"]) == 2 and report["quantizer"]["max_layer_disagreement"] == 0.05
    assert report["kept_fp32"] == [layer for layer in report["sensitivity"] if layer["disagreement"] > 0.05]
    line = _kept_fp32_line(report)  # what occkit export prints
    assert "over 5% of the calibration voxels" in line and "of 2 layers, the most sensitive node_" in line
    monkeypatch.setattr(quantization, "MAX_LAYER_DISAGREEMENT", -1.0)  # every layer "hurts": none is quantized
    report = quantization.quantize_int8(path, tmp_path / "none.onnx", calibration)
    assert len(report["kept_fp32"]) == 2 and _float_convolutions(tmp_path / "none.onnx") == 2
    assert "QuantizeLinear" not in operator_counts(tmp_path / "none.onnx")


def test_named_layers_stay_fp32_and_unknown_names_are_refused(fp32_graph, tmp_path):
    path, calibration = fp32_graph
    report = quantization.quantize_int8(path, tmp_path / "all.onnx", calibration, keep_fp32=())
    assert report["kept_fp32"] == [] and "sensitivity" not in report
    assert _float_convolutions(tmp_path / "all.onnx") == 0
    first = quantization.quantizable_layers(quantization.prepare(path, tmp_path / "prepared.onnx"))[0]["node"]
    report = quantization.quantize_int8(path, tmp_path / "one.onnx", calibration, keep_fp32=(first,))
    assert [layer["node"] for layer in report["kept_fp32"]] == [first]
    assert _float_convolutions(tmp_path / "one.onnx") == 1
    with pytest.raises(ValueError, match=r"keep_fp32 \(--keep-fp32\) names no_such_node, not quantizable layers"):
        quantization.quantize_int8(path, tmp_path / "x.onnx", calibration, keep_fp32=("no_such_node",))


def test_keep_fp32_reads_auto_none_or_node_names():
    assert quantization.parse_keep_fp32("auto") == "auto" and quantization.parse_keep_fp32("none") == ()
    assert quantization.parse_keep_fp32("node_a,node_b,") == ("node_a", "node_b")
