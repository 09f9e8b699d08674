"""What several commands share: the model-source options (a checkpoint, a weights file or the shipped weights), the
experiment overrides, the label-space names, JSON output and the frame progress bar."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from occkit.arguments import (
    check_device,
    input_file,
    input_folder,
    output_folder,
)
from occkit.errors import UsageError

#: The names of :data:`occkit.label_space.LABEL_SPACES`, spelled out so that ``occkit --help`` imports no torch
#: (``tests/test_cli.py`` keeps them equal).
LABEL_SPACE_NAMES = ("occ3d", "surroundocc", "openocc")


class FrameBar:
    """A progress bar over frames, called with (done, total); it opens at the first call, once the library knows the
    total, so an error before any frame prints no bar."""

    def __init__(self, desc: str) -> None:
        self.desc = desc
        self.bar = None

    def __call__(self, done: int, total: int) -> None:
        from tqdm import tqdm

        if self.bar is None:
            self.bar = tqdm(total=total, unit="frame", desc=self.desc)
        self.bar.update(done - self.bar.n)

    def __enter__(self) -> FrameBar:
        return self

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()


def write_json(path: Path, payload: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"wrote {path}")


def add_experiment_overrides(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default=None,
                        help="experiment YAML or zoo name to run the checkpoint with (default: the one saved in it); "
                             "its model must be the checkpoint's")  # fmt: skip
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a value of the experiment, e.g. --set 'data.drop_cameras=[CAM_FRONT]' "
                             "(repeatable)")  # fmt: skip


def add_model_source(group, parser: argparse.ArgumentParser, ckpt_help: str) -> None:
    """``--ckpt FILE`` or ``--weights FILE|synthetic`` (in ``group``, which makes them exclusive) and ``--model``."""
    group.add_argument("--ckpt", type=Path, metavar="FILE", help=ckpt_help)
    group.add_argument("--weights", metavar="FILE|synthetic",
                       help="weights without a run: a .safetensors file (e.g. an official checkpoint converted by "
                            "occkit convert), or synthetic: the weights occkit ships for --model (trained on the "
                            "synthetic world; see occkit info)")  # fmt: skip
    parser.add_argument("--model", default=None, metavar="ENTRY",
                        help="with --weights: the zoo entry that runs them (for a file, default: the entry it was "
                             "converted for)")  # fmt: skip


def model_source(args: argparse.Namespace, entry: str | None = None, config: str | None = None):
    """The ``ModelSource`` of ``--ckpt`` (run with ``config`` when given) / ``--weights`` (+ ``--model``, or
    ``entry``), checked; None when neither is given. A shipped entry without weights is refused here, before any other
    work."""
    from occkit.model_source import ModelSource
    from occkit.shipped import SYNTHETIC, card, shipped_entries

    entry = entry if entry is not None else args.model
    if args.ckpt is None and args.weights is None:
        if entry is not None:
            raise UsageError("--model goes with --weights")
        return None
    if args.ckpt is not None:
        input_file(args.ckpt, "--ckpt")
        if entry is not None:
            raise UsageError("--model goes with --weights; a checkpoint names its own model (use --config to run "
                             "it with another experiment)")  # fmt: skip
        return ModelSource(ckpt=str(args.ckpt), config=config)
    if args.weights == SYNTHETIC:
        if entry is None:
            raise UsageError(f"--weights {SYNTHETIC} needs --model ENTRY (shipped: "
                             f"{', '.join(shipped_entries()) or 'none yet'})")  # fmt: skip
        card(entry)  # an entry without shipped weights is refused in one line
    else:
        input_file(Path(args.weights), "--weights")
    return ModelSource(weights=args.weights, entry=entry)


def trained_model_source(args: argparse.Namespace):
    """``eval`` / ``predict``: the model source of ``--ckpt`` (with ``--config``) or ``--weights`` (with ``--model``
    or ``--config``, a zoo name or YAML), and the other options they share, checked before the model is loaded."""
    if args.weights is not None and args.model is not None and args.config is not None:
        raise UsageError("--model and --config both name the experiment to run --weights with: give one")
    entry = args.model or (args.config if args.weights is not None else None)
    source = model_source(args, entry, config=args.config if args.ckpt is not None else None)
    if args.data is not None:
        input_folder(args.data, "--data")
    output_folder(args.out, "--out")
    check_device(args.device)
    return source
