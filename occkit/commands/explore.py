"""Commands that look at models, data and the machine: ``occkit info``, ``zoo``, ``robustness``, ``viz``, ``view``
and ``demo``."""

from __future__ import annotations

import argparse
import difflib
import sys
from pathlib import Path

from occkit.arguments import (
    check_device,
    check_memory,
    input_file,
    input_folder,
    integer,
    output_file,
    output_folder,
)
from occkit.commands.common import LABEL_SPACE_NAMES, add_model_source, model_source, write_json
from occkit.errors import MissingDependencyError, UsageError


# ------------------------------------------------------------------------------------------------- info
def add_info(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the report as JSON to FILE")


def run_info(args: argparse.Namespace) -> int:
    from occkit.environment import environment_report, format_environment_report

    if args.json is not None:
        output_file(args.json, "--json")
    report = environment_report()
    print(format_environment_report(report))
    if args.json is not None:
        write_json(args.json, report)
    return 0


def add_zoo(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=("list", "diff"), help="list: every entry with its paper row; diff A B: "
                        "the settings where entry B differs from entry A")  # fmt: skip
    parser.add_argument("entries", nargs="*", metavar="ENTRY", help="diff: the two entries to compare")


def run_zoo(args: argparse.Namespace) -> int:
    from occkit import zoo
    from occkit.config import MISSING

    if args.action == "list":
        if args.entries:
            raise UsageError("occkit zoo list takes no entries")
        for name in zoo.names():
            row = zoo.paper_row(name)
            reproduces = f"{row.row}: {row.result}" if row else "(no paper row)"
            print(f"{name:<28} {zoo.model_config(name)[0]:<9} {reproduces}")
        return 0
    if len(args.entries) != 2:
        raise UsageError(f"occkit zoo diff takes two entries, got {len(args.entries)}")
    for name in args.entries:
        if name not in zoo.names():
            close = difflib.get_close_matches(name, zoo.names(), n=3)
            hint = f" (did you mean {', '.join(close)}?)" if close else ""
            raise UsageError(f"unknown zoo entry {name!r}{hint}; occkit zoo list shows all {len(zoo.names())}")
    first, second = args.entries
    differences = zoo.diff(first, second)

    def show(value) -> str:
        if value is MISSING:
            return "(absent)"
        return f"{{...}} ({len(value)} settings)" if isinstance(value, dict) else repr(value)

    print(f"{second} differs from {first} in {len(differences)} setting(s)" + (":" if differences else ""))
    for key, old, new in differences:
        print(f"  {key}: {show(old)} -> {show(new)}")
    return 0


# ------------------------------------------------------------------------------------------- robustness
def add_robustness(parser: argparse.ArgumentParser) -> None:
    add_model_source(parser.add_mutually_exclusive_group(), parser, "checkpoint to score (best.pt, step-*.pt)")
    parser.add_argument("--data", type=Path, default=None, help="dataset root (default: the one it was trained on)")
    parser.add_argument("--split", default=None, help="split to score (default: the run's validation split)")
    parser.add_argument("--suite", default="default", metavar="default|quick|NAMES",
                        help="default (every corruption, every level), quick (one level of each kind of failure), "
                             "or a comma list of NAME or NAME:LEVEL, e.g. fog,missing_camera:CAM_FRONT "
                             "(see --list)")  # fmt: skip
    parser.add_argument("--baseline", type=Path, default=None, metavar="FILE",
                        help="robustness.json of a baseline model: adds the corruption errors CE and mCE")
    parser.add_argument("--out", type=Path, help="folder for robustness.json, robustness.md, the plots and the "
                                                 "per-case cache that a rerun resumes from")  # fmt: skip
    parser.add_argument("--seed", type=integer(0, 2**63 - 1), default=0,
                        help="seed of the corruptions' draws (default 0)")
    parser.add_argument("--no-rayiou", action="store_true", help="skip RayIoU (mIoU and IoU only)")
    parser.add_argument("--workers", type=integer(0, 256), default=1, help="data loading processes (default 1)")
    parser.add_argument("--device", default=None, help="cpu, cuda (default: CUDA when available)")
    parser.add_argument("--list", action="store_true", help="list the corruptions and their levels, and exit")


def _corruption_table() -> str:
    from occkit.data.corruptions import CORRUPTIONS
    from occkit.robustness.suite import SUITES

    lines = []
    for corruption in CORRUPTIONS.values():
        needs = " + ".join(corruption.needs)
        lines.append(f"{corruption.name} ({corruption.family}; needs {needs}): {corruption.summary}")
        for severity, label, params in zip(corruption.severities, corruption.labels, corruption.levels, strict=True):
            values = ", ".join(f"{k}={v}" for k, v in params.items()) or "-"
            lines.append(f"    {severity}: {label:<14} {values}")
    quick = ", ".join(f"{c.corruption}:{c.severity}" for c in SUITES["quick"])
    return "\n".join(lines) + f"\nsuites: default (all of the above), quick ({quick})\n"


def run_robustness(args: argparse.Namespace) -> int:
    import torch
    from tqdm import tqdm

    if args.list:
        print(_corruption_table(), end="")
        return 0
    if (args.ckpt is None and args.weights is None) or args.out is None:
        raise UsageError("--ckpt (or --weights) and --out are required (or --list)")
    model = model_source(args)
    if args.data is not None:
        input_folder(args.data, "--data")
    if args.baseline is not None:
        input_file(args.baseline, "--baseline")
    output_folder(args.out, "--out")
    check_device(args.device)
    from occkit.outputs import OutputLock
    from occkit.robustness import parse_suite, run_robustness

    try:
        parse_suite(args.suite)
    except ValueError as error:
        raise UsageError(str(error)) from None
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    bar = None  # opened by the first frame: an error before it stays the one line on stderr

    def progress(done: int, total: int, label: str) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, unit="frame")
        bar.total = total
        bar.set_description(label, refresh=False)
        bar.update(done - bar.n)

    try:
        with OutputLock(args.out, "occkit robustness"):  # one run at a time writes the cases and the report
            report = run_robustness(model, args.out, data=args.data, split=args.split, suite=args.suite,
                                    baseline=args.baseline, workers=args.workers, device=device,
                                    rayiou=not args.no_rayiou, seed=args.seed, log=tqdm.write, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    print((args.out / "robustness.md").read_text(), end="")
    written = [name for name in ("robustness.json", "robustness.md", "resilience.png", "severity.png")
               if (args.out / name).is_file()]  # severity.png: only with a corruption of severities
    print(f"wrote {', '.join(written)} to {args.out} ({report['seconds']:.0f} s, {report['seconds_computed']:.0f} s "
          "of it evaluating)")
    return 0


# -------------------------------------------------------------------------------------------------- viz
def add_viz(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset root (nuScenes layout)")
    parser.add_argument("--split", default="val", help="split to take frames from (default val)")
    parser.add_argument("--version", default="v1.0-synth", help="table folder under --data (default v1.0-synth)")
    parser.add_argument("--label-space", choices=LABEL_SPACE_NAMES, default=None,
                        help="labels and predictions to draw (default: the checkpoint's, else occ3d)")
    frames = parser.add_mutually_exclusive_group()
    frames.add_argument("--frames", type=integer(1, 10_000), default=3,
                        help="frames spread evenly over the split (default 3)")
    frames.add_argument("--token", nargs="+", default=(), metavar="TOKEN", help="sample tokens to render instead")
    predictions = parser.add_mutually_exclusive_group()
    predictions.add_argument("--pred", type=Path, metavar="DIR",
                             help="folder of <token>.npz predictions (as occkit predict writes them)")
    add_model_source(predictions, parser, "predict on the fly with this checkpoint")
    parser.add_argument("--device", default="cpu", help="where the model of --ckpt / --weights runs (default cpu)")
    parser.add_argument("--sweeps", type=integer(0, 100), default=0,
                        help="earlier LiDAR sweeps added to the key frame in the LiDAR overlay (default 0)")
    parser.add_argument("--display-width", type=integer(16, 8192), default=800,
                        help="camera images wider than this are shown resized to it (default 800 px)")
    parser.add_argument("--dpi", type=integer(20, 1000), default=100, help="PNG resolution, 20 to 1000 (default 100)")
    parser.add_argument("--colors", type=integer(2, 256), default=None, metavar="N",
                        help="store PNGs with a palette of N colours (<= 256): files several times smaller")
    parser.add_argument("--out", type=Path, required=True, help="folder for the PNGs, index.md/html and index.json")


def run_viz(args: argparse.Namespace) -> int:
    from occkit.viz.run import LARGEST_FIGURE_INCHES, VizConfig, render_frames

    input_folder(args.data, "--data")
    output_folder(args.out, "--out")
    if args.pred is not None:
        input_folder(args.pred, "--pred")
    model = model_source(args)
    check_device(args.device)
    width, height = LARGEST_FIGURE_INCHES
    # An RGBA canvas, its PNG encoding and (with --colors) a palette conversion are alive at once.
    check_memory(3 * 4 * width * height * args.dpi**2, f"a {width:g} x {height:g} inch figure at {args.dpi} dpi",
                 "--dpi")
    config = VizConfig(data=str(args.data), out=str(args.out), split=args.split, version=args.version,
                       frames=args.frames, tokens=tuple(args.token), label_space=args.label_space,
                       pred=None if args.pred is None else str(args.pred),
                       model=model, device=args.device, sweeps=args.sweeps,
                       display_width=args.display_width, dpi=args.dpi, colors=args.colors)  # fmt: skip
    render_frames(config)
    return 0


# ------------------------------------------------------------------------------------------------- view
def add_view(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset root (nuScenes layout)")
    parser.add_argument("--split", default="val", help="split whose first scene is shown without --scene (default val)")
    parser.add_argument("--version", default="v1.0-synth", help="table folder under --data (default v1.0-synth)")
    parser.add_argument("--scene", default=None, metavar="NAME",
                        help="scene to show, from whichever split holds it (default: the first scene of --split)")
    parser.add_argument("--frames", type=integer(1, 100_000), default=None, metavar="N",
                        help="only the scene's first N key frames (default: all)")
    parser.add_argument("--label-space", choices=LABEL_SPACE_NAMES, default=None,
                        help="labels and predictions to show (default: the checkpoint's, else occ3d)")
    predictions = parser.add_mutually_exclusive_group()
    predictions.add_argument("--pred", type=Path, metavar="DIR",
                             help="folder of <token>.npz predictions (as occkit predict writes them)")
    add_model_source(predictions, parser, "predict on the fly with this checkpoint")
    parser.add_argument("--device", default="cpu", help="where the model of --ckpt / --weights runs (default cpu)")
    sink = parser.add_mutually_exclusive_group()
    sink.add_argument("--save", type=Path, metavar="FILE.rrd",
                      help="write the recording to FILE.rrd (open it with: rerun FILE.rrd) instead of spawning the "
                           "viewer")  # fmt: skip
    sink.add_argument("--serve", action="store_true",
                      help="serve the web viewer over HTTP (for a browser or a remote machine) until Ctrl-C")
    parser.add_argument("--web-port", type=integer(1, 65535), default=9090,
                        help="HTTP port of the web viewer with --serve (default 9090)")
    parser.add_argument("--grpc-port", type=integer(1, 65535), default=9876,
                        help="port of the recording's gRPC server with --serve (default 9876)")
    parser.add_argument("--bind", default="127.0.0.1", metavar="ADDR",
                        help="address --serve listens on (default 127.0.0.1: this machine only; 0.0.0.0 lets every "
                             "machine that reaches this one read the scene)")  # fmt: skip


def run_view(args: argparse.Namespace) -> int:
    import signal

    input_folder(args.data, "--data")
    if args.pred is not None:
        input_folder(args.pred, "--pred")
    model = model_source(args)
    if args.save is not None:
        output_file(args.save, "--save")
        if args.save.suffix != ".rrd":
            raise UsageError(f"--save {args.save} must be a .rrd file")
    check_device(args.device)
    from occkit.viz.serving import check_bind, check_port_free, is_loopback, start_server

    check_bind(args.bind)
    if args.serve:  # a taken port is refused before rerun, torch and the scene load (start_server checks again)
        if args.web_port == args.grpc_port:
            raise UsageError(f"--web-port and --grpc-port are both {args.web_port}: the two servers need two ports")
        check_port_free(args.bind, args.web_port, "--web-port")
        check_port_free(args.bind, args.grpc_port, "--grpc-port")
    try:
        from occkit.viz.recording import ViewConfig, view_scene
    except ModuleNotFoundError as error:
        if error.name != "rerun":
            raise
        raise MissingDependencyError('occkit view needs the rerun viewer, an optional extra: pip install -e '
                                     '".[viewer]"') from None
    config = ViewConfig(data=str(args.data), split=args.split, version=args.version, scene=args.scene,
                        frames=args.frames, pred=None if args.pred is None else str(args.pred),
                        model=model, label_space=args.label_space,
                        device=args.device)  # fmt: skip
    server = None
    if args.serve:
        if not is_loopback(args.bind):
            print(f"warning: --bind {args.bind} serves the scene to every machine that can reach this one on ports "
                  f"{args.web_port} and {args.grpc_port}", file=sys.stderr)
        server = start_server(args.bind, args.web_port, args.grpc_port)  # the ports are checked before any work
        # `kill` as well as Ctrl-C stops the child server: SystemExit runs the `finally` below.
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    try:
        view_scene(config, save=args.save, server=server)
    except KeyboardInterrupt:
        pass
    finally:
        if server is not None:
            server.stop()
    return 0


# ------------------------------------------------------------------------------------------------- demo
def add_demo(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("runs/demo"), help="demo folder (default runs/demo)")
    parser.add_argument("--data", type=Path, default=Path("data/demo"),
                        help="synthetic dataset, written first if absent (default data/demo)")
    parser.add_argument("--steps", type=integer(1, 100_000_000), default=None,
                        help="optimizer steps of each model's short run from random weights (default: each model's "
                             "own, occkit.demo.DEMO_MODELS)")


def run_demo(args: argparse.Namespace) -> int:
    from occkit.demo import DEMO_MODELS, check_world, run_demo

    output_folder(args.out, "--out")
    output_folder(args.data, "--data")
    check_world(args.data)  # before any work: another world is refused, never written into
    models = None if args.steps is None else {name: args.steps for name in DEMO_MODELS}
    report = run_demo(args.out, args.data, models)
    print(f"report: {report}")
    return 0
