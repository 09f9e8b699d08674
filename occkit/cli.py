"""The ``occkit`` command line: the table of commands, the parser and the error policy.

The commands' arguments and glue live in :mod:`occkit.commands` (one module per group of commands); each command is
a pair of functions, ``add_<verb>(parser)`` and ``run_<verb>(args)``, around library functions. Heavy libraries
(torch, spconv) are imported inside each command, so ``occkit --help`` answers at once.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from occkit import __version__
from occkit.commands import data, deploy, explore, runs

Command = tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]

COMMANDS: dict[str, Command] = {
    "info": (
        "show versions, devices, the sparse-convolution backend, grids and class taxonomies",
        explore.add_info,
        explore.run_info,
    ),
    "zoo": ("list the zoo's entries, or show how one entry's settings differ from another's", explore.add_zoo,
            explore.run_zoo),
    "sim": ("simulate a synthetic driving dataset in the nuScenes + Occ3D layout", data.add_sim, data.run_sim),
    "index": ("index the key frames of a nuScenes-layout dataset", data.add_index, data.run_index),
    "label": ("build occupancy labels and visibility masks from a dataset's LiDAR sweeps, lidarseg and boxes",
              data.add_label, data.run_label),
    "eval-preds": (
        "score Occ3D predictions against a gts/ tree: mIoU, IoU, RayIoU (mAVE / OccScore with flow, RayPQ with "
        "instances)",
        runs.add_eval_preds,
        runs.run_eval_preds,
    ),
    "train": ("train a model: checkpoints, logs, plots, validation (torchrun for several processes)", runs.add_train,
              runs.run_train),
    "eval": ("score a checkpoint on a dataset split: mIoU, IoU, RayIoU (mAVE, OccScore with a flow head; RayPQ "
             "panoptic), per-class table and plots", runs.add_eval, runs.run_eval),
    "predict": ("write Occ3D-format <token>.npz predictions of a checkpoint", runs.add_predict, runs.run_predict),
    "convert": ("convert an official FlashOcc / BEVDet or DAOcc checkpoint to occkit weights (.safetensors) with "
                "a report", deploy.add_convert, deploy.run_convert),
    "export": ("export a model to ONNX (standard operators, one fixed rig) and check it in onnxruntime",
               deploy.add_export, deploy.run_export),
    "bench": ("inference latency, FPS, per-stage times, MACs and GEMM efficiency of a model; the fast path",
              deploy.add_bench, deploy.run_bench),
    "robustness": ("score a checkpoint under sensor failures and corruptions: resilience, corruption error, plots",
                   explore.add_robustness, explore.run_robustness),
    "viz": ("render ground truth, predictions and cameras with projected LiDAR / voxels to PNGs and a page",
            explore.add_viz, explore.run_viz),
    "view": ("one scene in rerun's interactive 3D viewer: cameras, LiDAR, boxes, trajectory, occupancy, predictions "
             "and their errors on a timeline", explore.add_view, explore.run_view),
    "demo": ("the whole system on a laptop: synthetic world, three tiny models (one per family) scored with their "
             "shipped weights and trained briefly from scratch, rendered, reported",
             explore.add_demo, explore.run_demo),
}


class _Parser(argparse.ArgumentParser):
    """argparse with usage errors on one line: the option, what is wrong, where help is; exit code 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _add_debug(parser: argparse.ArgumentParser, default) -> None:
    parser.add_argument("--debug", action="store_true", default=default,
                        help="show the full traceback of an error instead of its one-line message")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="occkit",
        description="3D semantic occupancy prediction in pure PyTorch: models, data, metrics and tools.",
    )
    parser.add_argument("--version", action="version", version=f"occkit {__version__}")
    _add_debug(parser, False)
    commands = parser.add_subparsers(dest="command", metavar="<command>")
    for name, (summary, add_arguments, _) in COMMANDS.items():
        command = commands.add_parser(name, help=summary, description=summary)
        add_arguments(command)
        _add_debug(command, argparse.SUPPRESS)  # `occkit --debug X` and `occkit X --debug` both work
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. Errors a user can cause (bad options, files, records, sizes) end in one line naming the
    option, file or record, with exit code 2; anything else is occkit's bug: one line asking for a report, exit
    code 1. ``--debug`` shows the traceback of either."""
    from occkit.errors import is_input_error, one_line

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    _, _, run = COMMANDS[args.command]
    try:
        return run(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as error:
        if args.debug:
            raise
        if is_input_error(error):
            print(f"occkit {args.command}: error: {one_line(error)}", file=sys.stderr)
            return 2
        print(f"occkit {args.command}: internal error: {type(error).__name__}: {one_line(error)} (run again with "
              "--debug for the traceback, and please report it)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
