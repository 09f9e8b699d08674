"""The ``occkit`` command line: thin argument parsing around library functions.

Heavy libraries (torch, spconv) are imported inside each command, so ``occkit --help`` answers at once.
Each command is a pair of functions: ``_add_<verb>(parser)`` declares its arguments, ``_run_<verb>(args)`` does
the work and returns the exit code.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from occkit import __version__


# ----------------------------------------------------------------------------------------------------- info
def _add_info(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the report as JSON to FILE")


def _run_info(args: argparse.Namespace) -> int:
    from occkit.environment import environment_report, format_environment_report

    report = environment_report()
    print(format_environment_report(report))
    if args.json is not None:
        _write_json(args.json, report)
    return 0


# ----------------------------------------------------------------------------------------------------- helpers
def _write_json(path: Path, payload: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"wrote {path}")


Command = tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]

COMMANDS: dict[str, Command] = {
    "info": (
        "show versions, devices, the sparse-convolution backend, grids and class taxonomies",
        _add_info,
        _run_info,
    ),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="occkit",
        description="3D semantic occupancy prediction in pure PyTorch: models, data, metrics and tools.",
    )
    parser.add_argument("--version", action="version", version=f"occkit {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="<command>")
    for name, (summary, add_arguments, _) in COMMANDS.items():
        add_arguments(commands.add_parser(name, help=summary, description=summary))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
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


if __name__ == "__main__":
    sys.exit(main())
