"""ONNX export of a zoo model for one fixed rig, checked against PyTorch in onnxruntime.

The exported graph is :mod:`occkit.models.deployment`'s fixed-rig network: camera images (and for DAOcc the voxel
features and sparse-convolution rulebooks of the LiDAR sweep) in, ``occupancy_logits (B, K, X, Y, Z)`` out, every
calibration-only index or sampling tensor a constant of the graph. It uses standard ONNX operators only (domain
``""`` / ``ai.onnx``), which :func:`operator_counts` checks on the written file.

Exporter: ``torch.onnx.export(..., dynamo=True)`` (``torch.export``), opset 18 by default. The TorchScript exporter
(``dynamo=False``, opset 17) is not used: it writes ``index_add`` as a ScatterElements *without* reduction, which is
silently wrong wherever two entries hit the same row (DAOcc's camera average over overlapping cameras); the
``torch.export`` path writes ScatterND with ``reduction="add"``, takes the LiDAR inputs' variable lengths as named
dynamic dimensions, and is the exporter PyTorch maintains.

Parity (:func:`check_parity`): the graph runs in onnxruntime on a real sample and is compared with the model's own
``forward`` in eval mode: the largest absolute logit difference must be at most 1e-3 and the arg-max class must agree
on at least 99.9% of the voxels. Latencies (median over a few runs after a warm-up, same thread count) are measured
for onnxruntime, the same network in PyTorch, and the model's full ``forward``.

fp16 (``precision="fp16"``, :func:`convert_fp16`): the fp32 graph's weights and arithmetic in half precision, inputs
and outputs kept fp32, the scatter-adds of the pooling kept fp32 (onnxruntime's CPU provider has no fp16
scatter-add, and sums of many terms are what half precision rounds worst); for GPUs and TensorRT, and half the file.
int8 (``precision="int8"``, :func:`occkit.quantization.quantize_int8`): onnxruntime's post-training static
quantization of the fp32 graph (QDQ format, per-channel int8 weights, uint8 activations of the convolutions and matrix
products, their ranges calibrated on key frames of the same rig at the 99.999th percentile, the layers int8 hurts most
left fp32), which stays standard ONNX (``QuantizeLinear`` / ``DequantizeLinear``). Its report gives the arg-max
agreement and logit difference against the fp32 model (reported, not held to fp32's tolerance) and both graphs'
onnxruntime latencies timed in interleaved pairs in one run, with their ratio.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from occkit import zoo
from occkit.config import to_dict
from occkit.engine.checkpoint import check_compatible
from occkit.engine.evaluate import load_trained
from occkit.engine.reference_frame import SyntheticWorld, load_reference_frame
from occkit.errors import UsageError
from occkit.models.deployment import DeployedNetwork, deploy
from occkit.onnx_runtime import open_session, paired_latency, require, to_feeds
from occkit.outputs import check_report_file, report_beside, write_report
from occkit.quantization import quantize_int8
from occkit.types import Batch

__all__ = [
    "DEFAULT_OPSET",
    "MAX_ABS_TOLERANCE",
    "MIN_ARGMAX_AGREEMENT",
    "STANDARD_DOMAINS",
    "ExportError",
    "check_opset",
    "check_export_output",
    "load_model",
    "load_sample",
    "export_onnx",
    "operator_counts",
    "check_parity",
    "measure_latency",
    "export_model",
    "convert_fp16",
    "PRECISIONS",
]

#: ``occkit export --precision``.
PRECISIONS = ("fp32", "fp16", "int8")
DEFAULT_OPSET = 18
#: Largest absolute difference between onnxruntime and PyTorch logits that passes.
MAX_ABS_TOLERANCE = 1e-3
#: Smallest fraction of voxels whose arg-max class must agree.
MIN_ARGMAX_AGREEMENT = 0.999
#: ONNX operator domains of the standard operator set.
STANDARD_DOMAINS = ("", "ai.onnx")


class ExportError(RuntimeError):
    """The exported graph is unusable: it needs operators outside the standard ONNX domains."""


# ------------------------------------------------------------------------------------------------- what to export
def load_model(name: str, checkpoint: str | Path | None = None,
               seed: int = 0) -> tuple[nn.Module, Any, str | None]:
    """A zoo model in eval mode without its detection head, its experiment (whose data settings load samples), and
    how a checkpoint's config differs from the zoo entry's.

    A checkpoint is exported as it was trained (its own saved config). It must hold the zoo entry's model: the same
    architecture and the same parameters (names and shapes); other config differences (a loss weight, a grid
    extent) are allowed and returned as a one-line note, None when there are none.

    Args:
        name: zoo entry.
        checkpoint: occkit checkpoint of that entry; None: the entry's random initialisation under ``seed``.

    Raises:
        ValueError: unknown name, or a checkpoint holding another model.
        FileNotFoundError: a missing checkpoint.
    """
    if name not in zoo.names():
        raise ValueError(f"unknown model {name!r}; the zoo has: {', '.join(zoo.names())}")
    architecture, config = zoo.model_config(name)
    difference = None
    if checkpoint is None:
        torch.manual_seed(seed)
        model, experiment = zoo.build(name), zoo.experiment(name)
    else:
        model, experiment = load_trained(checkpoint, "cpu")
        if experiment.architecture != architecture:
            raise ValueError(f"{checkpoint} holds a {experiment.architecture} model, not {architecture}: it is not a "
                             f"checkpoint of zoo model {name}")
        _check_parameters(model, zoo.build(name), f"{checkpoint} is not a checkpoint of zoo model {name}")
        try:
            check_compatible({"architecture": architecture, "experiment": experiment.to_dict()}, architecture,
                             to_dict(config), checkpoint)  # fmt: skip
        except ValueError as error:
            difference = f"{error} (exported with the checkpoint's own config)"
    if hasattr(model, "remove_detection"):
        model.remove_detection()  # the exported graph outputs occupancy only
    model.flow_head = None  # and no flow
    return model.eval(), experiment, difference


def _check_parameters(model: nn.Module, reference: nn.Module, message: str) -> None:
    """Raise ``ValueError(message: first differing parameter)`` unless both have the same state-dict layout."""
    shapes = {key: tuple(value.shape) for key, value in model.state_dict().items()}
    expected = {key: tuple(value.shape) for key, value in reference.state_dict().items()}
    for key in sorted(set(shapes) | set(expected)):
        if shapes.get(key) != expected.get(key):
            raise ValueError(f"{message}: parameter {key} is {shapes.get(key, 'missing')} in it but "
                             f"{expected.get(key, 'missing')} in the zoo model")


def load_sample(experiment: Any, data: str | Path | None = None, index: int | None = None,
                scene: bool = False) -> tuple[Batch, dict[str, Any], list[Batch]]:  # fmt: skip
    """One key frame with the experiment's data settings and the test transform, as a batch of one; with ``scene``
    also every key frame of its scene in time order (the stream a temporal model's parity is checked on).

    Args:
        experiment: from :func:`load_model`.
        data: a nuScenes-layout dataset root; None simulates a one-scene synthetic world (two key frames, six with
            ``scene``; 400 x 225 images) in a temporary folder.
        index: key frame of the whole dataset (split ``all``); None takes the last, which has the longest history of
            earlier LiDAR sweeps.
        scene: also load the key frame's scene.

    Returns:
        The batch, a description of where it came from, and the scene's frames (empty without ``scene``).
    """
    world = SyntheticWorld(image_size=(400, 225), frames=6 if scene else 2)
    frame = load_reference_frame(experiment.data, data, world, index=index, scene=scene)
    return frame.batch, frame.source, frame.scene


# ----------------------------------------------------------------------------------------------------- export
def _dynamic_shapes(net: DeployedNetwork) -> tuple | None:
    """``torch.export`` dynamic shapes of ``forward(*inputs)`` from the network's named dynamic axes."""
    if not net.dynamic_axes:
        return None
    specs = tuple(
        {axis: torch.export.Dim(label, min=0) for axis, label in net.dynamic_axes[name].items()}
        if name in net.dynamic_axes else None
        for name in net.input_names
    )  # fmt: skip
    return (specs,)


def _nodes(graph) -> list:
    """Every node of an ONNX graph, those of its subgraphs (If, Loop, Scan bodies) included."""
    found = []
    for node in graph.node:
        found.append(node)
        for attribute in node.attribute:
            subgraphs = ([attribute.g] if attribute.HasField("g") else []) + list(attribute.graphs)
            for subgraph in subgraphs:
                found += _nodes(subgraph)
    return found


def operator_counts(path: str | Path) -> dict[str, int]:
    """ONNX operator types of a model file and how often each occurs, checked to be standard operators.

    Raises:
        ExportError: naming the operators outside :data:`STANDARD_DOMAINS` or the model's local functions.
    """
    onnx = require("onnx")
    model = onnx.load(str(path), load_external_data=False)
    nodes = _nodes(model.graph) + [n for function in model.functions for n in function.node]
    foreign = sorted({f"{n.domain}::{n.op_type}" for n in nodes if n.domain not in STANDARD_DOMAINS})
    if foreign or model.functions:
        functions = [f"{f.domain}::{f.name}" for f in model.functions]
        raise ExportError(f"{path} uses operators outside the standard ONNX domains: {', '.join(foreign + functions)}")
    return dict(sorted(Counter(node.op_type for node in nodes).items()))


def check_opset(opset: int) -> None:
    """Refuse an opset the exporter cannot write: below 18 (the torch.export-based exporter's first) or above the
    newest the installed ``onnx`` package defines."""
    if opset < 18:
        raise ValueError(f"opset {opset} is not available: the torch.export-based exporter writes opset 18 or newer")
    newest = require("onnx").defs.onnx_opset_version()
    if opset > newest:
        raise ValueError(f"opset {opset} is not available: the installed onnx package knows opsets up to {newest}")


#: The command named in the report; a report of it may be replaced by the next export to the same file.
COMMAND = "occkit export"
#: Keys every export report has held, also those written before reports named their command.
_REPORT_KEYS = ("model", "opset", "op_types", "files")


def check_export_output(out: Path) -> Path:
    """The report file of an export to ``out`` (``FILE.json`` beside ``FILE.onnx``), once ``out`` is known to be a
    ``.onnx`` name and the report's name to hold no file but an earlier export report (checked before any work).

    Raises:
        UsageError: ``out`` does not end in ``.onnx`` (``--out model.json`` would put the report over the model).
        FileExistsError: ``FILE.json`` exists and is not a report of ``occkit export``.
    """
    if out.suffix != ".onnx":
        raise UsageError(f"--out {out} must be a .onnx file: the report goes beside it, to FILE.json")
    report = report_beside(out, ".json")
    check_report_file(report, COMMAND, "--out", earlier_keys=_REPORT_KEYS)
    return report


def _file_opset(model) -> int:
    """The default-domain opset a model file declares."""
    return next(entry.version for entry in model.opset_import if entry.domain in STANDARD_DOMAINS)


def _translations() -> dict:
    """PyTorch operators the exporter writes in other standard ONNX operators than its own choice.

    ``softplus``: as ``Relu(x) + Log(1 + Exp(-Abs(x)))`` (with ``beta``: of ``beta * x``, over ``beta``), equal to
    PyTorch's within float rounding (its ``threshold`` only skips a term below 2e-9). The exporter writes ONNX's
    ``Softplus`` plus a ``Where`` for the threshold, and onnxruntime's CPU ``Softplus`` kernel is slow: on the
    channel-to-height head's (1, 200, 200, 64) hidden layer 19.2 ms against 5.8 ms for these seven vectorised
    elementwise operators (2 threads), about a tenth of flashocc_tiny's fp32 pass and a quarter of its int8 one.
    """
    from onnxscript import opset18 as op

    def softplus(x, beta: float = 1.0, threshold: float = 20.0):
        scaled = op.Mul(x, op.CastLike(beta, x)) if beta != 1.0 else x
        value = op.Add(op.Relu(scaled), op.Log(op.Add(op.Exp(op.Neg(op.Abs(scaled))), op.CastLike(1.0, x))))
        return op.Div(value, op.CastLike(beta, x)) if beta != 1.0 else value

    return {torch.ops.aten.softplus.default: softplus}


def export_onnx(net: DeployedNetwork, inputs: dict[str, Tensor], path: str | Path,
                opset: int = DEFAULT_OPSET) -> dict[str, Any]:
    """Export a fixed-rig network to ``path`` and check its operators.

    Args:
        net: from :func:`occkit.models.deployment.deploy`.
        inputs: example inputs (``net.inputs(batch)``); tensors on the network's device.
        path: the ``.onnx`` file; weights go to ``<path>.data`` only past protobuf's 2 GB.
        opset: ONNX opset, 18 or newer.

    Returns:
        ``opset``, ``inputs`` / ``outputs`` (name, shape with dynamic axes named, dtype, description),
        ``op_types`` (operator -> count), ``files`` written.
    """
    require("onnxscript")
    check_opset(opset)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    args = tuple(inputs[name] for name in net.input_names)
    with torch.no_grad():
        output = net(*args)
        program = torch.onnx.export(net, args, dynamo=True, opset_version=opset, input_names=net.input_names,
                                    output_names=net.output_names, dynamic_shapes=_dynamic_shapes(net), verbose=False,
                                    custom_translation_table=_translations())  # fmt: skip
    # The weights file of an earlier export to the same path would be left behind, unreferenced.
    external = path.with_name(path.name + ".data")
    external.unlink(missing_ok=True)
    program.save(str(path))
    files = [str(path)] + ([str(external)] if external.is_file() else [])
    # The exporter falls back to the opset it built the graph in when its version converter fails (it logs the
    # converter's traceback and goes on): a file of another opset than asked for is an error, not a report.
    written = _file_opset(require("onnx").load(str(path), load_external_data=False))
    if written != opset:
        raise ExportError(f"{path}: the exporter could not convert the graph to opset {opset} and wrote opset "
                          f"{written}; export with --opset {written}")

    def spec(name: str, tensor: Tensor, doc: str) -> dict[str, Any]:
        axes = net.dynamic_axes.get(name, {})
        shape = [axes.get(axis, size) for axis, size in enumerate(tensor.shape)]
        return {"name": name, "shape": shape, "dtype": str(tensor.dtype).removeprefix("torch."), "doc": doc}

    return {
        "opset": opset,
        "inputs": [spec(name, inputs[name], net.input_docs[name]) for name in net.input_names],
        "outputs": [spec(name, tensor, net.output_docs[name])
                    for name, tensor in zip(net.output_names, output if isinstance(output, tuple) else (output,),
                                            strict=True)],
        "op_types": operator_counts(path),
        "files": files,
    }


# ----------------------------------------------------------------------------------------------------- parity
def _median_seconds(run: Callable[[], Any], repeats: int, device: torch.device) -> float:
    """Median wall time of ``run`` over ``repeats`` calls after one warm-up (CUDA work is waited for)."""
    run()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        run()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _compare(onnx_logits: Tensor, reference: Tensor) -> dict[str, Any]:
    """Parity numbers of ``(B, K, X, Y, Z)`` logits against the reference."""
    max_abs = float((onnx_logits - reference).abs().max())
    onnx_class, reference_class = onnx_logits.argmax(dim=1), reference.argmax(dim=1)
    disagree = onnx_class != reference_class
    # How close the reference's two best classes are where the graphs disagree: a disagreement within the logit
    # error is a numerical tie (random-init heads produce many), anything else is a real difference.
    top2 = reference.topk(2, dim=1).values
    margins = (top2[:, 0] - top2[:, 1])[disagree]
    disagreements = int(disagree.sum())
    agreement = 1 - disagreements / disagree.numel()
    return {
        "max_abs_diff": max_abs,
        "argmax_agreement": agreement,
        "voxels": int(disagree.numel()),
        "argmax_disagreements": disagreements,
        "disagreements_within_twice_max_abs_diff": int((margins <= 2 * max_abs).sum()),
        "passed": max_abs <= MAX_ABS_TOLERANCE and agreement >= MIN_ARGMAX_AGREEMENT,
        "tolerance": {"max_abs_diff": MAX_ABS_TOLERANCE, "argmax_agreement": MIN_ARGMAX_AGREEMENT},
    }


def check_parity(path: str | Path, model: nn.Module, net: DeployedNetwork, batch: Batch,
                 frames: list[Batch] | None = None) -> dict[str, Any]:  # fmt: skip
    """Run the exported graph in onnxruntime (CPU) on ``batch`` and compare it with ``model(batch)``; for a temporal
    model, on every frame of ``frames`` streamed in order, the graph's state output fed back as its next input,
    against the model streamed with its own memory.

    Args:
        path: the exported ``.onnx``.
        model: the model ``net`` was made from, in eval mode.
        net: the fixed-rig network, which makes the graph's inputs from the batch.
        batch: a sample of the rig ``net`` was made for.
        frames: a temporal model's stream (a scene's key frames in time order); None: ``[batch]``.

    Returns:
        ``max_abs_diff`` and ``argmax_agreement`` (over ``voxels``, all frames), ``passed`` (both within
        ``tolerance``), ``argmax_disagreements`` and how many of them are numerical ties
        (``disagreements_within_twice_max_abs_diff``: the model's two best logits differ by at most twice
        ``max_abs_diff``), and ``network_max_abs_diff``: the PyTorch network against the model; with a stream also
        ``frames`` and ``max_abs_diff_per_frame``.
    """
    session = open_session(path)
    stream = frames if frames is not None else [batch]
    temporal = net.temporal is not None
    graph_memory = model.stream() if temporal else None
    model_memory = model.stream() if temporal else None
    network_memory = model.stream() if temporal else None
    onnx_all, reference_all, per_frame, network_diff = [], [], [], 0.0
    with torch.no_grad():
        for frame in stream:
            inputs = net.inputs(frame, graph_memory)
            outputs = session.run(net.output_names, to_feeds(inputs))
            logits = torch.from_numpy(np.asarray(outputs[0])).float()
            if temporal:
                state = torch.from_numpy(np.asarray(outputs[1])).to(frame.ego2global.device)
                graph_memory.push(state, frame.ego2global, frame.occ_aug)
                reference = model(frame, memory=model_memory).occupancy.float().cpu()
                network = net.stream(frame, network_memory).float().cpu()
            else:
                reference = model(frame).occupancy.float().cpu()
                network = net(*inputs.values()).float().cpu()
            per_frame.append(float((logits - reference).abs().max()))
            network_diff = max(network_diff, float((network - reference).abs().max()))
            onnx_all.append(logits)
            reference_all.append(reference)
    parity = _compare(torch.cat(onnx_all), torch.cat(reference_all))
    parity["network_max_abs_diff"] = network_diff
    if temporal:
        parity.update(frames=len(stream), max_abs_diff_per_frame=per_frame)
    return parity


def measure_latency(path: str | Path, model: nn.Module, net: DeployedNetwork, batch: Batch,
                    repeats: int = 3) -> dict[str, Any]:
    """Median latencies in milliseconds over ``repeats`` runs after a warm-up, on one batch.

    Returns:
        ``onnxruntime`` (the graph, CPU), ``torch_network`` (the same network in PyTorch, no grad),
        ``torch_model`` (the model's ``forward``, plans and voxelization included), for LiDAR models
        ``preprocess`` (voxelization and rulebooks, done outside the graph), and ``repeats``, ``threads``,
        ``providers``, ``torch_device``.
    """
    device = next(model.parameters()).device
    session = open_session(path)
    with torch.no_grad():
        inputs = net.inputs(batch)
        feeds, args = to_feeds(inputs), tuple(inputs.values())
        seconds = {
            "onnxruntime": _median_seconds(lambda: session.run(net.output_names, feeds), repeats,
                                           torch.device("cpu")),
            "torch_network": _median_seconds(lambda: net(*args), repeats, device),
            "torch_model": _median_seconds(lambda: model(batch), repeats, device),
        }
        if "voxel_features" in inputs:
            seconds["preprocess"] = _median_seconds(lambda: net.inputs(batch), repeats, device)
    latency: dict[str, Any] = {key: round(1000 * value, 2) for key, value in seconds.items()}
    latency.update(repeats=repeats, threads=torch.get_num_threads(), providers=session.get_providers(),
                   torch_device=str(device))  # fmt: skip
    return latency


# ------------------------------------------------------------------------------------------------------- int8
def convert_fp16(fp32_path: str | Path, out: str | Path) -> dict[str, Any]:
    """The fp32 graph at ``fp32_path`` in half precision at ``out`` (onnxruntime's float16 converter): fp32 inputs and
    outputs, the scatter operators kept fp32. Returns the converter's settings and ``op_types``."""
    onnx = require("onnx")
    from onnxruntime.transformers.float16 import convert_float_to_float16

    kept = ["ScatterElements", "ScatterND"]
    converted = convert_float_to_float16(onnx.load(str(fp32_path)), keep_io_types=True, op_block_list=kept)
    onnx.save(converted, str(out))
    return {"converter": "onnxruntime.transformers.float16", "kept_fp32": kept, "op_types": operator_counts(out)}


# ------------------------------------------------------------------------------------------------- end to end
def export_model(
    name: str,
    out: str | Path,
    checkpoint: str | Path | None = None,
    data: str | Path | None = None,
    opset: int = DEFAULT_OPSET,
    check: bool = True,
    repeats: int = 3,
    sample: int | None = None,
    precision: str = "fp32",
    calibration_frames: int = 8,
    keep_fp32: str | tuple[str, ...] = "auto",
) -> dict[str, Any]:
    """``occkit export``: load, export, check parity and write the report ``FILE.json`` beside ``out``
    (``FILE.onnx``; :func:`check_export_output`, before any work).

    Args:
        name: zoo entry; checkpoint: its trained weights (None: seeded random initialisation).
        data: dataset root for the reference sample (None: a synthetic world generated on the fly).
        opset: ONNX opset (18 or newer); check: run the parity check and timings; repeats: timed runs.
        sample: key frame of ``data`` (split ``all``) whose rig the graph is made for.
        precision: ``fp32``; ``fp16`` (:func:`convert_fp16`); or ``int8``: the fp32 graph quantized
            (:func:`quantize_int8`) on up to ``calibration_frames`` key frames of the sample's scene, single-frame
            models only.
        keep_fp32: with int8, the layers left fp32 (:func:`occkit.quantization.quantize_int8`).

    Returns:
        The report written to the JSON file; ``report["parity"]["passed"]`` tells whether parity holds.
    """
    out = Path(out)
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    json_path = check_export_output(out)
    check_opset(opset)
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    if calibration_frames < 1:
        raise ValueError(f"calibration_frames must be >= 1, got {calibration_frames}")
    model, experiment, difference = load_model(name, checkpoint)
    temporal = getattr(model, "temporal", None) is not None
    if temporal and precision == "int8":
        raise UsageError(f"{name} carries a history state between frames: int8 export takes single-frame models "
                         "(its calibration is of single frames)")
    batch, source, frames = load_sample(experiment, data, sample, scene=temporal or precision == "int8")
    net = deploy(model, batch)
    with torch.no_grad():
        inputs = net.inputs(batch)
    start = time.perf_counter()
    report: dict[str, Any] = {"model": name, "checkpoint": None if checkpoint is None else str(checkpoint),
                              "config_difference": difference, "sample": source, "precision": precision}  # fmt: skip
    if precision != "fp32":
        return _export_reduced(precision, report, model, net, batch, frames[:calibration_frames], out, opset, check,
                               repeats, json_path, start, keep_fp32)  # fmt: skip
    report.update(export_onnx(net, inputs, out, opset))
    report.update(exporter=f"torch.onnx.export(dynamo=True), torch {torch.__version__}",
                  export_seconds=round(time.perf_counter() - start, 1),
                  precomputed={n: list(b.shape) for n, b in net.named_buffers(recurse=False)})
    if check:
        report["parity"] = check_parity(out, model, net, batch, frames if temporal else None)
        report["latency_ms"] = measure_latency(out, model, net, batch, repeats)
        report["onnxruntime"] = require("onnxruntime").__version__
    write_report(json_path, report, COMMAND)
    report["json"] = str(json_path)
    return report


def _export_reduced(
    precision: str, report: dict[str, Any], model: nn.Module, net: DeployedNetwork, batch: Batch,
    frames: list[Batch], out: Path, opset: int, check: bool, repeats: int, json_path: Path, start: float,
    keep_fp32: str | tuple[str, ...] = "auto",
) -> dict[str, Any]:
    """The fp16 / int8 half of :func:`export_model`: the fp32 graph in a temporary folder, converted into ``out``."""
    with torch.no_grad():
        inputs = net.inputs(batch)
        calibration = [to_feeds(net.inputs(frame)) for frame in frames] if precision == "int8" else []
    with tempfile.TemporaryDirectory() as folder:
        fp32 = Path(folder) / "fp32.onnx"
        fp32_report = export_onnx(net, inputs, fp32, opset)
        out.parent.mkdir(parents=True, exist_ok=True)
        report.update(fp32_report)
        if precision == "int8":
            conversion = quantize_int8(fp32, out, calibration, keep_fp32=keep_fp32)
            conversion["op_types"] = operator_counts(out)
        else:
            conversion = convert_fp16(fp32, out)
        report[precision] = conversion
        report.update(op_types=conversion["op_types"], files=[str(out)],
                      exporter=f"torch.onnx.export(dynamo=True), torch {torch.__version__}; "
                               + ("onnxruntime.quantization" if precision == "int8" else conversion["converter"]),
                      export_seconds=round(time.perf_counter() - start, 1))  # fmt: skip
        if check:
            parity = check_parity(out, model, net, batch)
            parity["passed"] = None  # not held to fp32's tolerance: a reduced precision's cost is measured in mIoU
            report["parity"] = parity
            latency = paired_latency(fp32, out, to_feeds(inputs), net.output_names, max(repeats, 3))
            report["latency_ms"] = {"onnxruntime_fp32": latency["first_ms"],
                                    f"onnxruntime_{precision}": latency["second_ms"],
                                    f"{precision}_over_fp32": latency["ratio"], "pairs": latency["pairs"],
                                    "threads": latency["threads"]}  # fmt: skip
            report["onnxruntime"] = require("onnxruntime").__version__
    write_report(json_path, report, COMMAND)
    report["json"] = str(json_path)
    return report
