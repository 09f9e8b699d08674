"""What int8 deployment costs a trained model: the mIoU of its fp32 and int8 ONNX graphs on held-out scenes, and
their latency ratio in onnxruntime on this machine, measured in one run.

    python benchmarks/int8_accuracy.py [--entry flashocc_tiny] [--data data/demo] [--calibration-frames 8]
        [--operators all|Conv,MatMul,...] [--calibration MinMax|Percentile|Entropy] [--keep-fp32 auto|none|NODE,...]
        [--pairs 10] [--out FILE]

The entry's shipped weights (``weights="synthetic"``) are exported for the world's rig (:func:`occkit.export.deploy`)
at fp32, and quantized with :func:`occkit.quantization.quantize_int8` (QDQ, per-channel int8 weights, uint8 activations;
by default ``occkit export``'s operators, calibration method and layers left fp32, or the ones given) calibrated on
key frames of the *training* scenes, evenly spaced. Both graphs then run in onnxruntime
on every key frame of the held-out scenes; the Occ3D metric (camera mask) scores each graph's arg-max, and the
PyTorch model is scored beside them (the fp32 graph should equal it). The latencies are onnxruntime's on one frame in
interleaved pairs (:func:`occkit.onnx_runtime.paired_latency`). The JSON says whether the machine was otherwise idle
only as far as its load average tells.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from occkit import __version__, zoo
from occkit.data.collate import collate
from occkit.engine.evaluate import evaluation_dataset
from occkit.export import DEFAULT_OPSET, export_onnx
from occkit.machine import machine_info
from occkit.metrics.confusion import OccupancyMetric
from occkit.models.deployment import deploy
from occkit.onnx_runtime import open_session, paired_latency, to_feeds
from occkit.quantization import INT8_CALIBRATION, INT8_OPERATORS, parse_keep_fp32, quantize_int8


def measure(entry: str, data: Path, calibration_frames: int, pairs: int,
            operators: tuple[str, ...] | None = INT8_OPERATORS, method: str = INT8_CALIBRATION,
            keep_fp32: str | tuple[str, ...] = "auto") -> dict:  # fmt: skip
    experiment = zoo.experiment(entry)
    experiment = dataclasses.replace(experiment, data=dataclasses.replace(experiment.data, root=str(data)))
    model = zoo.build(entry, weights="synthetic").eval()
    train, val = evaluation_dataset(experiment, data, "train"), evaluation_dataset(experiment, data, "val")
    picks = np.linspace(0, len(train) - 1, calibration_frames).round().astype(int)
    reference = collate([val[0]])
    net = deploy(model, reference)
    with torch.no_grad():
        calibration = [to_feeds(net.inputs(collate([train[int(i)]]))) for i in picks]
    metrics = {name: OccupancyMetric.for_space(val.space) for name in ("torch", "onnx_fp32", "onnx_int8")}
    agreement = {"int8_vs_fp32": 0, "fp32_vs_torch": 0, "voxels": 0}
    with tempfile.TemporaryDirectory() as folder:
        fp32, int8 = Path(folder) / "fp32.onnx", Path(folder) / "int8.onnx"
        with torch.no_grad():
            export_onnx(net, net.inputs(reference), fp32, DEFAULT_OPSET)
        quantizer = quantize_int8(fp32, int8, calibration, op_types=operators, method=method,
                                  keep_fp32=keep_fp32)  # fmt: skip
        sessions = {"onnx_fp32": open_session(fp32), "onnx_int8": open_session(int8)}
        started = time.perf_counter()
        for index in range(len(val)):
            batch = collate([val[index]])
            labels, mask = batch.voxel_semantics[0].numpy(), batch.mask_camera[0].numpy()
            with torch.no_grad():
                feeds = to_feeds(net.inputs(batch))
                predicted = {"torch": model(batch).occupancy.argmax(dim=1)[0].numpy()}
            for name, session in sessions.items():
                logits = np.asarray(session.run(net.output_names, feeds)[0])
                predicted[name] = logits.argmax(axis=1)[0]
            for name, metric in metrics.items():
                metric.update(labels, predicted[name].astype(np.uint8), mask)
            agreement["int8_vs_fp32"] += int((predicted["onnx_int8"] == predicted["onnx_fp32"]).sum())
            agreement["fp32_vs_torch"] += int((predicted["onnx_fp32"] == predicted["torch"]).sum())
            agreement["voxels"] += predicted["torch"].size
        scoring_seconds = time.perf_counter() - started
        latency = paired_latency(fp32, int8, to_feeds(net.inputs(reference)), net.output_names, pairs)
    scores = {name: metric.compute() for name, metric in metrics.items()}
    miou = {name: score["miou"] for name, score in scores.items()}
    return {
        "entry": entry,
        "weights": "synthetic (shipped)",
        "data": str(data),
        "held_out_frames": len(val),
        "calibration": {"frames": calibration_frames, "split": "train", "indices": picks.tolist()},
        "quantizer": quantizer["quantizer"],
        "kept_fp32": quantizer["kept_fp32"],
        "sensitivity": quantizer.get("sensitivity"),
        "sensitivity_seconds": quantizer.get("sensitivity_seconds"),
        "miou": miou,
        "iou": {name: score["iou"] for name, score in scores.items()},
        "miou_change_int8": miou["onnx_int8"] - miou["onnx_fp32"],
        "per_class_iou": {name: score["per_class_iou"] for name, score in scores.items()},
        "argmax_agreement": {"int8_vs_fp32": agreement["int8_vs_fp32"] / agreement["voxels"],
                             "fp32_vs_torch": agreement["fp32_vs_torch"] / agreement["voxels"]},  # fmt: skip
        "latency_ms": {"onnx_fp32": latency["first_ms"], "onnx_int8": latency["second_ms"],
                       "int8_speedup": 1 / latency["ratio"], "pairs": pairs, "threads": latency["threads"]},
        "scoring_seconds": scoring_seconds,
        "load_average_1min": os.getloadavg()[0],
        "machine": machine_info(torch.device("cpu")),
        "versions": {"occkit": __version__, "torch": torch.__version__,
                     "onnxruntime": __import__("onnxruntime").__version__},  # fmt: skip
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--entry", default="flashocc_tiny", help="a zoo entry with shipped weights")
    parser.add_argument("--data", type=Path, default=Path("data/demo"), help="the world (default: the demo's)")
    parser.add_argument("--calibration-frames", type=int, default=8, help="training key frames to calibrate on")
    parser.add_argument("--operators", default=",".join(INT8_OPERATORS or ()) or "all",
                        help="operators to quantize, comma-separated, or all (default: occkit export's)")
    parser.add_argument("--calibration", default=INT8_CALIBRATION, choices=("MinMax", "Percentile", "Entropy"),
                        help=f"calibration method (default {INT8_CALIBRATION}, occkit export's)")
    parser.add_argument("--keep-fp32", default="auto",
                        help="layers left fp32: auto (the sensitive ones, the default), none, or node names of the "
                             "prepared graph, comma-separated")  # fmt: skip
    parser.add_argument("--pairs", type=int, default=10, help="interleaved latency pairs")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON (default docs/results/cpu/int8/ENTRY.json, or ENTRY_OPERATORS_METHOD.json when the "
                             "settings are not the default ones)")  # fmt: skip
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        raise SystemExit(f"--data {args.data} does not exist: run occkit demo (it writes data/demo) or occkit sim")
    operators = None if args.operators == "all" else tuple(args.operators.split(","))
    keep = parse_keep_fp32(args.keep_fp32)
    result = measure(args.entry, args.data, args.calibration_frames, args.pairs, operators, args.calibration, keep)
    default = operators == INT8_OPERATORS and args.calibration == INT8_CALIBRATION
    name = args.entry if default else f"{args.entry}_{args.operators.replace(',', '-')}_{args.calibration}"
    name += "" if keep == "auto" else "_all-layers" if not keep else "_kept-" + str(len(keep))
    out = args.out or Path("docs/results/cpu/int8") / f"{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    miou, latency = result["miou"], result["latency_ms"]
    print(f"{args.entry} on {result['held_out_frames']} held-out frames: mIoU torch {100 * miou['torch']:.2f}, "
          f"fp32 ONNX {100 * miou['onnx_fp32']:.2f}, int8 {100 * miou['onnx_int8']:.2f} "
          f"({100 * result['miou_change_int8']:+.2f}); arg-max int8 vs fp32 "
          f"{100 * result['argmax_agreement']['int8_vs_fp32']:.2f}%; onnxruntime {latency['onnx_fp32']:.0f} ms fp32, "
          f"{latency['onnx_int8']:.0f} ms int8 (x{latency['int8_speedup']:.2f}); layers kept fp32: "
          f"{', '.join(layer['node'] for layer in result['kept_fp32']) or 'none'}; {out}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
