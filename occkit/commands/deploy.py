"""Commands that carry a model elsewhere or time it: ``occkit convert``, ``export`` and ``bench``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from occkit.arguments import (
    check_device,
    check_memory,
    input_file,
    input_folder,
    integer,
    number,
    output_file,
)
from occkit.commands.common import write_json
from occkit.errors import UsageError


# ---------------------------------------------------------------------------------------------- convert
def add_convert(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("checkpoint", type=Path, metavar="CKPT",
                        help="official checkpoint: FlashOcc / BEVDet (mmdet3d .pth, EMA files too) or DAOcc "
                             "(BEVFusion-style); read without unpickling code")  # fmt: skip
    parser.add_argument("--model", default=None, metavar="ENTRY",
                        help="zoo entry to convert for (default: from the checkpoint, FlashOcc / BEVDet -> "
                             "flashocc_m0, DAOcc -> daocc)")  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, metavar="FILE",
                        help="occkit weights FILE.safetensors; the report goes to FILE.report.json")
    parser.add_argument("--partial", action="store_true",
                        help="write what converts even when some tensors do not fit (a start for train.load_from, "
                             "e.g. BEVDet's detection checkpoint for FlashOcc); by default any unplaced, missing or "
                             "misshapen tensor is an error")  # fmt: skip


def run_convert(args: argparse.Namespace) -> int:
    from occkit.convert import convert_checkpoint, format_report

    input_file(args.checkpoint, "CKPT")
    output_file(args.out, "--out")
    if args.out.suffix != ".safetensors":
        raise UsageError(f"--out {args.out} must be a .safetensors file")
    conversion = convert_checkpoint(args.checkpoint, args.model, args.out, strict=not args.partial)
    print(format_report(conversion.report()))
    for path in conversion.files.values():
        print(f"wrote {path}")
    return 0


# ----------------------------------------------------------------------------------------------- export
def add_export(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, help="zoo name, e.g. flashocc_m0, da_occ, daocc")
    parser.add_argument("--ckpt", type=Path, default=None,
                        help="checkpoint of that model (default: its random initialisation, seeded)")
    parser.add_argument("--data", type=Path, default=None,
                        help="nuScenes-layout dataset whose rig the graph is made for (default: a one-scene "
                             "synthetic world generated in a temporary folder)")
    # nuScenes trainval has 34,149 key frames; the dataset's own length is checked once it is read.
    parser.add_argument("--sample", type=integer(0, 10_000_000), default=None,
                        help="key frame of --data (split all) used as the reference (default: the last)")
    # The installed onnx package's newest opset is checked before the export (occkit.export.check_opset).
    parser.add_argument("--opset", type=integer(18, 1000), default=18, help="ONNX opset, 18 or newer (default 18)")
    parser.add_argument("--out", type=Path, required=True, help="the .onnx file; the report goes to FILE.json")
    parser.add_argument("--no-check", action="store_true", help="skip the onnxruntime parity check and timings")
    parser.add_argument("--repeats", type=integer(1, 10_000), default=3,
                        help="timed runs for the latencies (default 3)")
    parser.add_argument("--precision", choices=("fp32", "fp16", "int8"), default="fp32",
                        help="fp16: the graph in half precision (for GPUs and TensorRT); int8: quantized by "
                             "onnxruntime (static, QDQ), calibrated on key frames of the sample's scene; either is "
                             "timed against the fp32 graph in one run (default fp32)")  # fmt: skip
    parser.add_argument("--calibration-frames", type=integer(1, 10_000), default=8,
                        help="with --precision int8: key frames of the scene calibrating the ranges (default 8)")
    parser.add_argument("--keep-fp32", default="auto", metavar="auto|none|NODE,...",
                        help="with --precision int8: the layers left fp32. auto (default): those whose int8 version "
                             "alone changes the arg-max of over 5%% of the calibration frames' voxels (each layer "
                             "is quantized alone and run: a minute or more); none; or node names of onnxruntime's "
                             "pre-processed graph, comma-separated, as the report's int8.sensitivity lists "
                             "them")  # fmt: skip


def _kept_fp32_line(int8: dict) -> str:
    """Which layers int8 left fp32, and for ``--keep-fp32 auto`` why."""
    kept = ", ".join(f"{layer['node']}" + (f" ({100 * layer['disagreement']:.1f}%)" if "disagreement" in layer else "")
                     for layer in int8["kept_fp32"]) or "none"  # fmt: skip
    sensitivity = int8.get("sensitivity")
    if not sensitivity:
        return f"layers left fp32: {kept}"
    worst = max(sensitivity, key=lambda layer: layer["disagreement"])
    limit = 100 * int8["quantizer"]["max_layer_disagreement"]
    return (f"layers left fp32 (quantized alone, each changes the arg-max of over {limit:g}% of the calibration "
            f"voxels): {kept}; of {len(sensitivity)} layers, the most sensitive {worst['node']} at "
            f"{100 * worst['disagreement']:.1f}% ({int8['sensitivity_seconds']:.0f} s)")


def run_export(args: argparse.Namespace) -> int:
    from occkit.export import ExportError, check_export_output, check_opset, export_model
    from occkit.quantization import parse_keep_fp32

    output_file(args.out, "--out")
    check_export_output(args.out)  # a .onnx name, and its FILE.json replaces nothing but an earlier report
    if args.ckpt is not None:
        input_file(args.ckpt, "--ckpt")
    if args.data is not None:
        input_folder(args.data, "--data")
    check_opset(args.opset)
    print(f"exporting {args.model} to {args.out} ...")
    try:
        report = export_model(args.model, args.out, checkpoint=args.ckpt, data=args.data, opset=args.opset,
                              check=not args.no_check, repeats=args.repeats, sample=args.sample,
                              precision=args.precision, calibration_frames=args.calibration_frames,
                              keep_fp32=parse_keep_fp32(args.keep_fp32))  # fmt: skip
    except ExportError as error:
        print(f"occkit export: error: {error}", file=sys.stderr)
        return 1
    if report["config_difference"]:
        print(f"note: {report['config_difference']}")
    ops = report["op_types"]
    print(f"wrote {', '.join(report['files'])}: opset {report['opset']}, {sum(ops.values())} nodes, "
          f"standard operators only ({', '.join(ops)})")
    if "parity" not in report:
        print(f"wrote {report['json']}")
        return 0
    parity, latency = report["parity"], report["latency_ms"]
    if args.precision != "fp32":
        reduced = args.precision
        frames = report[reduced].get("calibration_frames")
        print(f"{reduced} against the fp32 model on {report['sample']['token']}: max |logit difference| "
              f"{parity['max_abs_diff']:.2e}, arg-max agreement {100 * parity['argmax_agreement']:.2f}%"
              + (f" ({frames} calibration frames)" if frames else ""))  # fmt: skip
        if reduced == "int8":
            print(_kept_fp32_line(report["int8"]))
        print(f"median onnxruntime latency ({latency['threads']} threads, {latency['pairs']} interleaved pairs): "
              f"fp32 {latency['onnxruntime_fp32']:.1f} ms, {reduced} {latency[f'onnxruntime_{reduced}']:.1f} ms "
              f"({reduced} / fp32 = {latency[f'{reduced}_over_fp32']:.2f})")  # fmt: skip
        print(f"wrote {report['json']}")
        return 0
    print(f"parity on {report['sample']['token']}: max |logit difference| {parity['max_abs_diff']:.2e} "
          f"(<= {parity['tolerance']['max_abs_diff']:g}), arg-max agreement {100 * parity['argmax_agreement']:.4f}% "
          f"(>= {100 * parity['tolerance']['argmax_agreement']:g}%): {'passed' if parity['passed'] else 'FAILED'}")
    print(f"median latency ({latency['threads']} threads): onnxruntime {latency['onnxruntime']:.1f} ms, "
          f"PyTorch same network {latency['torch_network']:.1f} ms, PyTorch model forward "
          f"{latency['torch_model']:.1f} ms" + (f", voxelization + rulebooks {latency['preprocess']:.1f} ms"
                                                 if "preprocess" in latency else ""))
    print(f"wrote {report['json']}")
    return 0 if parity["passed"] else 1


# ------------------------------------------------------------------------------------------------ bench
def _optimizations(text: str) -> str | tuple[str, ...]:
    """``auto``, ``none`` (no step) or a comma-separated list of fast-path steps."""
    if text == "auto":
        return "auto"
    if text == "none":
        return ()
    return tuple(name.strip() for name in text.split(",") if name.strip())


def add_bench(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, help="zoo name, e.g. flashocc_m0, da_occ, daocc")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    parser.add_argument("--precision", choices=("fp32", "bf16", "fp16"), default="fp32",
                        help="fp32, or bf16 / fp16 autocast (fp16 on CUDA only); the GEMM yardstick uses the same")
    parser.add_argument("--batch", type=integer(1, 256), default=1, help="copies of the key frame per pass (default 1)")
    parser.add_argument("--iters", type=integer(1, 100_000), default=10, help="timed passes (default 10)")
    parser.add_argument("--warmup", type=integer(0, 10_000), default=2, help="untimed passes first (default 2)")
    parser.add_argument("--threads", type=integer(1, 1024), default=None, help="CPU threads (default: PyTorch's)")
    parser.add_argument("--data", type=Path, default=None,
                        help="dataset root to take the last key frame from (default: a one-scene 1600x900 "
                             "synthetic world, simulated once into data/bench-1600x900)")  # fmt: skip
    parser.add_argument("--optimizations", type=_optimizations, default="auto", metavar="auto|none|LIST",
                        help="fast path: auto (default) measures fixed_calibration, fold_bn, channels_last, compile "
                             "and cuda_graph (CUDA only) one by one and keeps those that speed up; none; or a comma "
                             "list to apply")
    parser.add_argument("--cudnn-benchmark", action="store_true",
                        help="let cuDNN time its algorithms for each convolution and keep the fastest, as a deployment "
                             "with fixed input sizes can (CUDA only; default: cuDNN's heuristic choice)")
    parser.add_argument("--gemm-size", type=integer(16, 65536), default=None,
                        help="n of the n x n GEMM yardstick (default 4096 on CPU, 8192 on CUDA)")
    parser.add_argument("--miou", type=number(0, 100), default=None,
                        help="the model's mIoU in percent (0 to 100), for RT-mIoU@10/15/20")
    parser.add_argument("--out", type=Path, required=True, help="JSON file for the results")


def run_bench(args: argparse.Namespace) -> int:
    from occkit.bench import BenchConfig, format_report, run_bench

    output_file(args.out, "--out")
    check_device(args.device)
    if args.data is not None:
        input_folder(args.data, "--data")
    if not args.device.startswith("cuda"):
        size = args.gemm_size or 4096
        check_memory(3 * 4 * size**2, f"the {size} x {size} GEMM yardstick (three fp32 matrices)", "--gemm-size")
    config = BenchConfig(model=args.model, device=args.device, precision=args.precision, batch_size=args.batch,
                         iters=args.iters, warmup=args.warmup, threads=args.threads, optimizations=args.optimizations,
                         cudnn_benchmark=args.cudnn_benchmark,
                         gemm_size=args.gemm_size, data=None if args.data is None else str(args.data),
                         miou=args.miou)  # fmt: skip
    result = run_bench(config)
    print(format_report(result))
    write_json(args.out, result)
    return 0
