"""int8 post-training quantization of an exported fp32 graph (onnxruntime's static quantizer), with the layers that
int8 hurts most kept in fp32.

The quantizer (:func:`quantize_int8`): QDQ nodes (``QuantizeLinear`` / ``DequantizeLinear``, standard ONNX) around the
operators :data:`INT8_OPERATORS`, per-channel symmetric int8 weights, uint8 activations whose ranges
:data:`INT8_CALIBRATION` calibrates on the calibration frames' feeds. It quantizes onnxruntime's pre-processed graph
(shape inference and graph optimisation, :func:`prepare`), which lets it cover more nodes.

Which layers stay fp32 (:func:`layer_sensitivity`): each quantizable layer is quantized alone, every other one left
fp32, and the graph runs on the calibration frames; the layer's sensitivity is the fraction of voxels whose arg-max
class (axis 1 of the graph's first output, the occupancy logits) differs from the fp32 graph's. No labels are needed.
Layers above :data:`MAX_LAYER_DISAGREEMENT` stay fp32. The reason, measured on ``flashocc_tiny``'s shipped weights
(docs/export.md): the BEV encoder's first residual block reads the view transform's pooled sums, a long-tailed range
that 256 levels resolve badly, and quantizing that block alone costs more mIoU than quantizing the whole network
with it kept fp32.
"""

from __future__ import annotations

import inspect
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from occkit.onnx_runtime import open_session, require

__all__ = ["INT8_OPERATORS", "INT8_CALIBRATION", "MAX_LAYER_DISAGREEMENT", "prepare", "quantizable_layers",
           "layer_sensitivity", "quantize_int8", "parse_keep_fp32"]  # fmt: skip

#: The operators int8 quantizes by default (the arithmetic the int8 kernels speed up). Quantizing every operator the
#: quantizer knows also rounds the view transform's gathers, products and sums: flashocc_tiny's shipped weights lost
#: 5.8 mIoU that way against 1.9 with these alone (docs/export.md).
INT8_OPERATORS: tuple[str, ...] | None = ("Conv", "MatMul", "Gemm")
#: onnxruntime's calibration method by default: ``Percentile`` clips the activations' rare outliers (MinMax lets one
#: outlier stretch a tensor's 256 levels).
INT8_CALIBRATION = "Percentile"
#: A layer whose int8 version alone changes the arg-max class of more than this fraction of the calibration frames'
#: voxels stays fp32 (``keep_fp32="auto"``).
MAX_LAYER_DISAGREEMENT = 0.05


def parse_keep_fp32(text: str) -> str | tuple[str, ...]:
    """``--keep-fp32`` as :func:`quantize_int8` takes it: ``auto``, ``none`` (no layer: ``()``) or comma-separated
    node names."""
    if text == "auto":
        return "auto"
    return () if text == "none" else tuple(name for name in text.split(",") if name)


def prepare(fp32_path: str | Path, out: str | Path) -> Path:
    """onnxruntime's pre-processing of an fp32 graph for quantization (shape inference, graph optimisation), written
    to ``out``. Layer names (:func:`quantizable_layers`) are those of the prepared graph."""
    quantization = require("onnxruntime.quantization")
    quantization.shape_inference.quant_pre_process(str(fp32_path), str(out), skip_symbolic_shape=True)
    return Path(out)


def quantizable_layers(prepared: str | Path, op_types: Sequence[str] | None = INT8_OPERATORS) -> list[dict[str, str]]:
    """The nodes of the prepared graph the quantizer would quantize with ``op_types`` (None: every operator it
    knows), in graph order: ``{"node": name, "op_type": ...}``."""
    onnx = require("onnx")
    quantization = require("onnxruntime.quantization")
    registry = quantization.registry
    known = set(op_types) if op_types is not None else {*registry.QLinearOpsRegistry, *registry.QDQRegistry}
    graph = onnx.load(str(prepared), load_external_data=False).graph
    return [{"node": node.name, "op_type": node.op_type} for node in graph.node if node.op_type in known]


def _quantize(prepared: Path, out: Path, calibration: list[dict[str, np.ndarray]], op_types: Sequence[str] | None,
              method: str, exclude: Sequence[str] = (), ranges: Path | None = None) -> None:  # fmt: skip
    """quantize_static with the module's settings; ``ranges``: a file caching the calibrated ranges, written by the
    first call and read by the next (where onnxruntime's quantize_static takes a ``calibration_cache_path``; older
    versions calibrate again each time)."""
    quantization = require("onnxruntime.quantization")
    cache = {}
    if ranges is not None and "calibration_cache_path" in inspect.signature(quantization.quantize_static).parameters:
        cache = {"calibration_cache_path": str(ranges)}

    class Frames(quantization.CalibrationDataReader):
        def __init__(self) -> None:
            self.feeds = iter(calibration)

        def get_next(self):
            return next(self.feeds, None)

    quantization.quantize_static(str(prepared), str(out), Frames(), quant_format=quantization.QuantFormat.QDQ,
                                 per_channel=True, weight_type=quantization.QuantType.QInt8,
                                 activation_type=quantization.QuantType.QUInt8,
                                 op_types_to_quantize=None if op_types is None else list(op_types),
                                 nodes_to_exclude=list(exclude),
                                 calibrate_method=getattr(quantization.CalibrationMethod, method), **cache)  # fmt: skip


def _classes(path: Path, calibration: list[dict[str, np.ndarray]]) -> list[np.ndarray]:
    """The arg-max class (axis 1 of the first output) of the graph at ``path`` on every calibration frame."""
    graph = open_session(path)
    first = graph.get_outputs()[0].name
    return [np.asarray(graph.run([first], feeds)[0]).argmax(axis=1) for feeds in calibration]


def layer_sensitivity(prepared: str | Path, calibration: list[dict[str, np.ndarray]],
                      op_types: Sequence[str] | None = INT8_OPERATORS, method: str = INT8_CALIBRATION,
                      ranges: Path | None = None) -> list[dict[str, Any]]:  # fmt: skip
    """Each quantizable layer of the prepared graph quantized alone: the fraction of the calibration frames' voxels
    whose arg-max class then differs from the fp32 graph's. The ranges are calibrated once (``ranges``: where they
    are cached; None: a temporary file).

    Returns:
        ``{"node", "op_type", "disagreement"}`` per layer, in graph order.
    """
    prepared = Path(prepared)
    layers = quantizable_layers(prepared, op_types)
    reference = _classes(prepared, calibration)
    voxels = sum(classes.size for classes in reference)
    with tempfile.TemporaryDirectory() as folder:
        alone, ranges = Path(folder) / "alone.onnx", ranges or Path(folder) / "ranges.json"
        for layer in layers:
            others = [other["node"] for other in layers if other["node"] != layer["node"]]
            _quantize(prepared, alone, calibration, op_types, method, exclude=others, ranges=ranges)
            changed = sum(int((a != b).sum()) for a, b in zip(_classes(alone, calibration), reference, strict=True))
            layer["disagreement"] = changed / voxels
    return layers


def quantize_int8(fp32_path: str | Path, out: str | Path, calibration: list[dict[str, np.ndarray]],
                  op_types: Sequence[str] | None = INT8_OPERATORS, method: str = INT8_CALIBRATION,
                  keep_fp32: str | Sequence[str] = "auto") -> dict[str, Any]:  # fmt: skip
    """Quantize the fp32 graph at ``fp32_path`` to int8 at ``out`` (the module's docstring says how).

    Args:
        calibration: the feeds of the frames calibrating the ranges (graph inputs of key frames of the graph's rig).
        op_types: the operators to quantize (None: every one the quantizer knows); method: ``MinMax``,
            ``Percentile`` or ``Entropy``.
        keep_fp32: ``"auto"``: the layers :func:`layer_sensitivity` finds above :data:`MAX_LAYER_DISAGREEMENT`;
            or the prepared graph's node names to leave fp32 (``()``: quantize every one).

    Returns:
        ``calibration_frames``, the quantizer's settings, ``kept_fp32`` (the layers left fp32, with their sensitivity
        where it was measured) and ``sensitivity`` (every layer's, for ``"auto"``).
    """
    if not calibration:
        raise ValueError("int8 quantization needs at least one calibration frame")
    settings = {"quant_format": "QDQ", "per_channel": True, "weight_type": "QInt8", "activation_type": "QUInt8",
                "calibrate_method": method, "op_types": None if op_types is None else list(op_types)}  # fmt: skip
    report: dict[str, Any] = {"calibration_frames": len(calibration), "quantizer": settings}
    with tempfile.TemporaryDirectory() as folder:
        prepared, ranges = prepare(fp32_path, Path(folder) / "prepared.onnx"), Path(folder) / "ranges.json"
        if isinstance(keep_fp32, str):
            if keep_fp32 != "auto":
                raise ValueError(f"keep_fp32 is 'auto' or a list of node names, got {keep_fp32!r}")
            start = time.perf_counter()
            sensitivity = layer_sensitivity(prepared, calibration, op_types, method, ranges)
            report["sensitivity"] = sensitivity
            report["sensitivity_seconds"] = round(time.perf_counter() - start, 1)
            kept = [layer for layer in sensitivity if layer["disagreement"] > MAX_LAYER_DISAGREEMENT]
        else:
            layers = {layer["node"]: layer for layer in quantizable_layers(prepared, op_types)}
            unknown = sorted(set(keep_fp32) - set(layers))
            if unknown:
                raise ValueError(f"keep_fp32 (--keep-fp32) names {', '.join(unknown)}, not quantizable layers of the "
                                 f"prepared graph: an export with --keep-fp32 auto lists them in its report's "
                                 f"int8.sensitivity")  # fmt: skip
            kept = [layers[name] for name in keep_fp32]
        settings["max_layer_disagreement"] = MAX_LAYER_DISAGREEMENT if keep_fp32 == "auto" else None
        report["kept_fp32"] = kept
        _quantize(prepared, Path(out), calibration, op_types, method, [layer["node"] for layer in kept], ranges)
    return report
