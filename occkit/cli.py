"""The ``occkit`` command line: thin argument parsing around library functions.

Heavy libraries (torch, spconv) are imported inside each command, so ``occkit --help`` answers at once.
Each command is a pair of functions: ``_add_<verb>(parser)`` declares its arguments, ``_run_<verb>(args)`` does
the work and returns the exit code.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from occkit import __version__
from occkit.arguments import (
    check_device,
    check_disk,
    check_memory,
    input_file,
    input_folder,
    integer,
    number,
    output_file,
    output_folder,
)
from occkit.errors import MissingDependencyError, UsageError

#: The names of :data:`occkit.label_space.LABEL_SPACES`, spelled out so that ``occkit --help`` imports no torch
#: (``tests/test_cli.py`` keeps them equal).
LABEL_SPACE_NAMES = ("occ3d", "surroundocc")

# ----------------------------------------------------------------------------------------------------- info
def _add_info(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the report as JSON to FILE")


def _run_info(args: argparse.Namespace) -> int:
    from occkit.environment import environment_report, format_environment_report

    if args.json is not None:
        output_file(args.json, "--json")
    report = environment_report()
    print(format_environment_report(report))
    if args.json is not None:
        _write_json(args.json, report)
    return 0


# ----------------------------------------------------------------------------------------------------- sim
def _image_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"image size must look like 800x450 (width x height), got {text!r}") from None
    return width, height


def _add_sim(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="dataset root to create (nuScenes + Occ3D layout)")
    parser.add_argument("--scenes", type=integer(1, 1_000_000), default=2, help="number of scenes (default 2)")
    parser.add_argument("--frames", type=integer(1, 10_000), default=40,
                        help="key frames per scene at 2 Hz (default 40)")
    parser.add_argument("--seed", type=integer(0, 2**63 - 1), default=0, help="dataset seed (default 0)")
    parser.add_argument(
        "--image-size", type=_image_size, default=(800, 450), help="camera images WxH (default 800x450)"
    )
    parser.add_argument("--version", default="v1.0-synth", help="table folder name, as nuScenes names it")
    parser.add_argument("--cameras", nargs="+", metavar="CAM", help="camera channels to render (default: all six)")
    parser.add_argument("--surroundocc", action="store_true", help="also write SurroundOcc ground truth")
    parser.add_argument("--workers", type=integer(1, 256), default=1, help="scenes simulated in parallel processes")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing dataset that occkit sim wrote (anything else is refused)")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override any SimConfig field, e.g. --set world.density=0.5 (repeatable)",
    )
    parser.add_argument("--preview", type=Path, metavar="PNG", help="also draw a contact sheet of the first scene")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the summary as JSON to FILE")


def _run_sim(args: argparse.Namespace) -> int:
    from occkit.config import apply_overrides
    from occkit.sim.config import SimConfig

    output_folder(args.out, "--out")
    options = {
        "scenes": args.scenes,
        "frames": args.frames,
        "seed": args.seed,
        "image_size": args.image_size,
        "version": args.version,
        "surroundocc": args.surroundocc,
    }
    if args.cameras:
        options["cameras"] = tuple(args.cameras)
    # The settings first, before the simulator's heavy imports: a value out of its bounds is refused at once.
    config = apply_overrides(SimConfig(**options), args.overrides)

    from tqdm import tqdm

    from occkit.outputs import OutputLock, check_not_inside
    from occkit.sim.generate import COMMAND, check_output, estimate_resources, simulate_dataset

    check_output(args.out, args.overwrite)
    for option, path in (("--preview", args.preview), ("--json", args.json)):
        if path is not None:
            output_file(path, option)
            check_not_inside(path, args.out, option)  # the dataset is renamed into place over --out

    needs = estimate_resources(config)
    workers = min(args.workers, config.scenes)
    check_memory(workers * needs["memory_per_worker"], f"simulating {workers} scene(s) at once at "
                 f"{config.image_size[0]}x{config.image_size[1]}", "--image-size/--workers")
    check_disk(args.out, needs["disk"], f"{config.scenes} scene(s) of {config.frames} key frames", "--out")
    # Locked before the progress bar shows: a second run into the folder ends as one line (simulate_dataset nests).
    with OutputLock(args.out, COMMAND), tqdm(total=config.scenes * config.frames, unit="frame", desc="sim") as bar:
        summary = simulate_dataset(
            config, args.out, workers=args.workers, overwrite=args.overwrite, progress=bar.update
        )
    print(
        f"wrote {summary['scenes']} scenes, {summary['samples']} key frames, {summary['annotations']} boxes "
        f"to {summary['root']} ({config.version})"
    )
    print("time per stage (s, summed over scenes): " + ", ".join(f"{k} {v}" for k, v in summary["timings"].items()))
    if args.preview is not None:
        from occkit.viz.contact_sheet import contact_sheet

        print(f"wrote {contact_sheet(args.out, args.preview)}")
    if args.json is not None:
        _write_json(args.json, summary)
    return 0


# ----------------------------------------------------------------------------------------------------- label
def _add_label(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--root", type=Path, required=True, help="nuScenes-layout dataset root with nuScenes-lidarseg")
    parser.add_argument("--version", required=True, help="table folder, e.g. v1.0-mini, v1.0-trainval, v1.0-synth")
    parser.add_argument("--out", type=Path, required=True,
                        help="folder for the labels (train on them with --set data.label_root=OUT)")
    parser.add_argument("--label-space", choices=LABEL_SPACE_NAMES, default="occ3d",
                        help="occ3d: ego frame, 0.4 m, with camera and LiDAR masks (default); surroundocc: LiDAR "
                        "frame, 0.5 m, sparse rows")
    parser.add_argument("--densify", choices=("none", "poisson"), default="none",
                        help="poisson: SurroundOcc's surface reconstruction fills gaps between points (needs the "
                        "[labels] extra, open3d)")
    parser.add_argument("--sweeps", type=integer(0, 100), default=None, metavar="N",
                        help="non-key sweeps used per key-frame interval (default: all; 0: key frames only)")
    parser.add_argument("--mask-window", type=integer(0, 100), default=1, metavar="K",
                        help="mask_lidar casts the sweeps of K key-frame intervals on each side (default 1)")
    parser.add_argument("--scene", dest="scenes", action="append", metavar="NAME",
                        help="label only this scene (repeatable; default: every scene)")
    parser.add_argument("--workers", type=integer(1, 256), default=1, help="scenes labelled in parallel processes")
    parser.add_argument("--overwrite", action="store_true", help="replace a previous occkit label output in --out")


def _run_label(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from occkit.labeling.pipeline import COMMAND, LabelConfig, check_label_output, label_dataset
    from occkit.outputs import OutputLock

    input_folder(args.root, "--root")
    output_folder(args.out, "--out")
    check_label_output(args.out, args.overwrite)
    config = LabelConfig(label_space=args.label_space, sweeps=args.sweeps, densify=args.densify,
                         mask_window=args.mask_window)  # fmt: skip
    if config.densify == "poisson":
        from occkit.labeling.voxels import require_open3d

        require_open3d()  # fail before any work

    # Locked before the progress bar: a second run into the folder ends as one line (label_dataset nests). The bar
    # is delayed: a bad dataset fails before it shows.
    with OutputLock(args.out, COMMAND), tqdm(unit="frame", desc="label", delay=0.5) as bar:

        def scene_done(summary: dict) -> None:
            points = summary["points"]
            bar.write(f"{summary['scene']}: {summary['key_frames']} key frames, {summary['sweeps']} sweeps, "
                      f"{points['static'] + points['objects']} points used ({points['objects']} on "
                      f"{summary['instances']} objects), {summary['occupied_voxels_per_frame']:.0f} voxels labelled "
                      f"per frame, {summary['seconds']['total']:.1f} s")  # fmt: skip

        def start(frames: int) -> None:
            bar.total = frames
            bar.refresh()

        summary = label_dataset(args.root, args.version, args.out, config, workers=args.workers, scenes=args.scenes,
                                overwrite=args.overwrite, progress=bar.update, on_scene=scene_done,
                                on_start=start)  # fmt: skip
    print(f"wrote {config.label_space} labels of {summary['key_frames']} key frames to {args.out} in "
          f"{summary['seconds']:.1f} s ({summary['seconds_per_key_frame']:.2f} s per key frame per worker)")
    if config.label_space == "occ3d":
        print(f"train on them: occkit train ... --set data.root={args.root} --set data.label_root={args.out}")
    return 0


# ----------------------------------------------------------------------------------------------------- index
def _add_index(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--root", type=Path, required=True, help="dataset root (holds <version>/, samples/, gts/)")
    parser.add_argument("--version", required=True, help="table folder, e.g. v1.0-trainval, v1.0-mini, v1.0-synth")
    parser.add_argument("--out", type=Path, required=True, help="index file to write (.npz of typed columns)")
    parser.add_argument("--max-sweeps", type=integer(0, 100), default=10,
                        help="earlier LiDAR sweeps per key frame (default 10)")
    parser.add_argument(
        "--split",
        default="all",
        help="scenes to index: all (default), or a split name (train, val, test; mini_train, mini_val), taken "
        "from <root>/splits.json if present, else the official nuScenes lists, or from --split-file",
    )
    parser.add_argument(
        "--split-file", type=Path, metavar="FILE", help="custom split: a JSON list of scene names or {name: [...]}"
    )
    parser.add_argument(
        "--from-info",
        type=Path,
        metavar="FILE",
        help="convert a BEVDet / FlashOcc or mmdetection3d v2 info pickle instead of reading the tables; --version "
        "is then checked against the file's and recorded in the header, --max-sweeps caps the file's sweeps",
    )
    parser.add_argument(
        "--trust-pickle",
        action="store_true",
        help="allow --from-info to unpickle FILE: unpickling runs any code the file names, so pass --trust-pickle "
        "only for files from a source you trust",
    )


def _run_index(args: argparse.Namespace) -> int:
    input_folder(args.root, "--root")
    # The index is always a .npz (its readers go by content): a .json name would promise what it does not hold.
    output_file(args.out, "--out", suffix=".npz", what="an occkit index")
    if args.from_info is not None:
        return _index_from_info(args)

    from occkit.data.index import build_split_index, save_index

    with _FrameBar("index") as progress:
        records = build_split_index(args.root, args.version, args.split, args.split_file, args.max_sweeps, progress)
    meta = {"version": args.version, "root": str(args.root), "max_sweeps": args.max_sweeps, "split": args.split}
    save_index(records, args.out, meta)
    labelled = sum(record.occ_path is not None for record in records)
    print(
        f"indexed {len(records)} key frames of {len({r.scene for r in records})} scene(s) ({args.split}), "
        f"{sum(r.num_boxes for r in records)} boxes, {labelled} with Occ3D labels -> {args.out}"
    )
    return 0


def _index_from_info(args: argparse.Namespace) -> int:
    from occkit.data.index import save_index
    from occkit.data.interop import import_info_file

    if args.split != "all" or args.split_file is not None:
        raise ValueError(
            "--from-info takes the info file's frames as they are (the file is one split already); "
            "leave out --split and --split-file"
        )
    if args.max_sweeps < 0:
        raise ValueError(f"--max-sweeps must be >= 0, got {args.max_sweeps}")
    records = import_info_file(args.from_info, args.root, version_hint=args.version, trust_pickle=args.trust_pickle)
    records = [dataclasses.replace(r, sweeps=r.sweeps[: args.max_sweeps]) for r in records]
    meta = {
        "version": args.version,
        "root": str(args.root),
        "max_sweeps": args.max_sweeps,
        "from_info": str(args.from_info),
    }
    save_index(records, args.out, meta)
    labelled = sum(record.occ_path is not None for record in records)
    print(
        f"converted {len(records)} key frames of {len({r.scene_token or r.token for r in records})} scene(s) from "
        f"{args.from_info}, {sum(r.num_boxes for r in records)} boxes, {labelled} with Occ3D labels -> {args.out}"
    )
    if records and not labelled:
        print(
            f"note: no Occ3D labels: the file has no 'occ_path' (FlashOcc's tools/create_data_bevdet.py adds it) "
            f"and {args.root}/gts/<scene>/<token>/labels.npz does not exist"
        )
    return 0


# ----------------------------------------------------------------------------------------------------- eval-preds
def _add_eval_preds(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gt", type=Path, required=True,
                        help="ground truth: Occ3D's gts/ folder (<scene>/<token>/labels.npz), or the folder holding "
                             "SurroundOcc's samples/ (<LiDAR file>.npy)")
    parser.add_argument(
        "--preds", type=Path, required=True, help="folder of <token>.npz predictions (key semantics or pred)"
    )
    parser.add_argument("--out", type=Path, required=True, help="folder for metrics.json, metrics.md and the plot")
    parser.add_argument("--label-space", choices=LABEL_SPACE_NAMES, default="occ3d",
                        help="the benchmark of ground truth and predictions (default occ3d); surroundocc needs "
                             "--nuscenes ROOT --version V to pair its files with sample tokens")
    parser.add_argument(
        "--mask",
        choices=("camera", "lidar", "none"),
        default=None,
        help="visibility mask for mIoU/IoU (default: the benchmark's, camera for Occ3D, none for SurroundOcc)",
    )
    parser.add_argument("--rayiou", action="store_true",
                        help="also compute RayIoU (SparseOcc protocol), and mAVE and OccScore when the predictions "
                             "carry flow")  # fmt: skip
    parser.add_argument(
        "--ray-origins", type=Path, metavar="FILE.npz", help="RayIoU ray origins: token -> (T, 3) ego metres"
    )
    parser.add_argument(
        "--nuscenes", type=Path, metavar="ROOT",
        help="the dataset's nuScenes tables: RayIoU origins from its key-frame poses, SurroundOcc file names",
    )  # fmt: skip
    parser.add_argument("--version", default="v1.0-trainval", help="table folder under --nuscenes")
    parser.add_argument(
        "--allow-missing", action="store_true", help="score frames without a prediction as all free (counted)"
    )
    parser.add_argument("--workers", type=integer(1, 256), default=4,
                        help="threads reading and scoring frames (default 4)")


def _run_eval_preds(args: argparse.Namespace) -> int:

    from occkit.label_space import label_space
    from occkit.metrics.evaluate import evaluate_prediction_folder, markdown_table, write_report

    input_folder(args.gt, "--gt")
    input_folder(args.preds, "--preds")
    output_folder(args.out, "--out")
    if args.rayiou and not label_space(args.label_space).rayiou:
        raise UsageError(f"--rayiou: RayIoU is not defined for {args.label_space} labels (only for Occ3D's)")
    if args.rayiou and args.ray_origins is None and args.nuscenes is None:
        raise UsageError("--rayiou needs --ray-origins FILE.npz or --nuscenes ROOT --version V for the ray origins")
    if args.label_space != "occ3d" and args.nuscenes is None:
        raise UsageError(f"--label-space {args.label_space}: its files are named after each frame's LiDAR file; give "
                         "the dataset's tables with --nuscenes ROOT --version V")  # fmt: skip
    notes: list[str] = []  # printed once the progress bar is done
    with _FrameBar("eval") as progress:
        result = evaluate_prediction_folder(
            args.gt, args.preds, args.label_space, mask=args.mask or "default", rayiou=args.rayiou,
            ray_origins=args.ray_origins, nuscenes=args.nuscenes, version=args.version,
            allow_missing=args.allow_missing, workers=args.workers, progress=progress, note=notes.append,
        )  # fmt: skip
    for note in notes:
        print(f"note: {note}")
    print(markdown_table(result), end="")
    for path in write_report(result, args.out).values():
        print(f"wrote {path}")
    return 0


# ----------------------------------------------------------------------------------------------------- helpers
class _FrameBar:
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

    def __enter__(self) -> _FrameBar:
        return self

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()


def _write_json(path: Path, payload: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"wrote {path}")


# ----------------------------------------------------------------------------------------------------- train
def _add_train(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, help="experiment YAML (configs/NAME.yaml) or a zoo name")
    parser.add_argument("--out", type=Path, required=True, help="run folder: checkpoints, logs, plots")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value, e.g. --set train.lr=2e-4 (repeatable)")
    parser.add_argument("--resume", default=None, metavar="auto|CKPT",
                        help="auto: continue from the newest checkpoint in --out; or a checkpoint file")
    parser.add_argument("--allow-change", action="append", default=[], metavar="KEY",
                        help="with --resume: let this experiment key (train.max_steps) or section (train) differ "
                             "from the checkpoint's; other differences are refused (repeatable)")
    parser.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: CUDA when available)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar (logs still written)")


def _is_main_process() -> bool:
    """False on the ranks other than 0 of a ``torchrun`` launch."""
    import os

    return int(os.environ.get("RANK", "0")) == 0


def _add_experiment_overrides(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default=None,
                        help="experiment YAML or zoo name to run the checkpoint with (default: the one saved in it); "
                             "its model must be the checkpoint's")  # fmt: skip
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a value of the experiment, e.g. --set 'data.drop_cameras=[CAM_FRONT]' "
                             "(repeatable)")  # fmt: skip


def _add_model_source(group, parser: argparse.ArgumentParser, ckpt_help: str) -> None:
    """``--ckpt FILE`` or ``--weights FILE|synthetic`` (in ``group``, which makes them exclusive) and ``--model``."""
    group.add_argument("--ckpt", type=Path, metavar="FILE", help=ckpt_help)
    group.add_argument("--weights", metavar="FILE|synthetic",
                       help="weights without a run: a .safetensors file (e.g. an official checkpoint converted by "
                            "occkit convert), or synthetic: the weights occkit ships for --model (trained on the "
                            "synthetic world; see occkit info)")  # fmt: skip
    parser.add_argument("--model", default=None, metavar="ENTRY",
                        help="with --weights: the zoo entry that runs them (for a file, default: the entry it was "
                             "converted for)")  # fmt: skip


def _model_source(args: argparse.Namespace, entry: str | None = None, config: str | None = None):
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


def _run_train(args: argparse.Namespace) -> int:
    from occkit.outputs import OutputLock

    output_folder(args.out, "--out")
    check_device(args.device)
    # One run per folder, refused before the experiment is read; train() takes the lock again (nested) and
    # summary.json is written under it. Under torchrun rank 0 holds it.
    with OutputLock(args.out, "occkit train", enabled=_is_main_process()):
        return _train_locked(args)


def _train_locked(args: argparse.Namespace) -> int:
    from occkit import zoo
    from occkit.engine.train import check_initial_weights, train

    experiment = zoo.load_experiment(args.config, args.set)
    if args.resume is None and _is_main_process():
        check_initial_weights(experiment)  # a missing weights file is named before anything else is looked at
    data_root = Path(experiment.data.root)
    if not data_root.is_dir():
        raise FileNotFoundError(f"data root {data_root} does not exist (set data.root, or write a synthetic dataset "
                                f"with `occkit sim --out {data_root}`)")
    result = train(experiment, args.out, resume=args.resume, progress=not args.no_progress, device=args.device,
                   allow_changes=args.allow_change)
    if not _is_main_process():  # under torchrun, rank 0 alone writes and reports
        return 0
    summary = {"out": str(result.out), "steps": result.steps, "seconds": round(result.seconds, 1),
               "best_miou": result.best_miou, "metrics": result.metrics}  # fmt: skip
    _write_json(args.out / "summary.json", summary)
    if result.metrics is not None:
        print(f"trained {result.steps} steps in {result.seconds:.0f} s: val mIoU {100 * result.metrics['miou']:.2f}, "
              f"IoU {100 * result.metrics['iou']:.2f}; run folder {args.out}")
    return 0


# ----------------------------------------------------------------------------------------------------- eval
def _add_eval(parser: argparse.ArgumentParser) -> None:
    _add_model_source(parser.add_mutually_exclusive_group(required=True), parser, "checkpoint (best.pt, step-*.pt)")
    _add_experiment_overrides(parser)
    parser.add_argument("--data", type=Path, default=None, help="dataset root (default: the one it was trained on)")
    parser.add_argument("--split", default=None, help="split to score (default: the run's validation split)")
    parser.add_argument("--out", type=Path, required=True, help="folder for metrics.json, metrics.md and plots")
    parser.add_argument("--no-rayiou", action="store_true",
                        help="skip RayIoU (mIoU and IoU only); SurroundOcc labels have no RayIoU anyway")
    parser.add_argument("--mask", choices=("camera", "lidar", "none"), default=None,
                        help="visibility mask for mIoU/IoU (default: the label space's, camera for Occ3D, none for "
                             "SurroundOcc)")
    parser.add_argument("--save-predictions", action="store_true", help="also write <token>.npz predictions")
    parser.add_argument("--batch-size", type=integer(1, 4096), default=1)
    parser.add_argument("--workers", type=integer(0, 256), default=2, help="data loading processes")
    parser.add_argument("--device", default=None, help="cpu, cuda (default: CUDA when available)")


def _run_eval(args: argparse.Namespace) -> int:
    from occkit.engine.jobs import evaluate_source
    from occkit.metrics.evaluate import markdown_table

    source = _trained_model_source(args)
    mask = "default" if args.mask is None else None if args.mask == "none" else args.mask
    outcome = evaluate_source(source, args.out, data=args.data, split=args.split, overrides=args.set, mask=mask,
                              rayiou=not args.no_rayiou, save_predictions=args.save_predictions,
                              batch_size=args.batch_size, workers=args.workers, device=args.device)  # fmt: skip
    if outcome is None:  # a torchrun rank other than 0: rank 0 reports
        return 0
    result, paths = outcome
    print(markdown_table(result), end="")
    if result["skipped"]:
        print(f"note: {result['skipped']} frame(s) failed to load and were skipped (data.on_error=skip): the scores "
              f"are over the {result['frames']} others")
    for path in paths.values():
        print(f"wrote {path}")
    return 0


def _trained_model_source(args: argparse.Namespace):
    """``eval`` / ``predict``: the model source of ``--ckpt`` (with ``--config``) or ``--weights`` (with ``--model``
    or ``--config``, a zoo name or YAML), and the other options they share, checked before the model is loaded."""
    if args.weights is not None and args.model is not None and args.config is not None:
        raise UsageError("--model and --config both name the experiment to run --weights with: give one")
    entry = args.model or (args.config if args.weights is not None else None)
    source = _model_source(args, entry, config=args.config if args.ckpt is not None else None)
    if args.data is not None:
        input_folder(args.data, "--data")
    output_folder(args.out, "--out")
    check_device(args.device)
    return source


# ----------------------------------------------------------------------------------------------------- predict
def _add_predict(parser: argparse.ArgumentParser) -> None:
    _add_model_source(parser.add_mutually_exclusive_group(required=True), parser, "checkpoint (best.pt, step-*.pt)")
    _add_experiment_overrides(parser)
    parser.add_argument("--data", type=Path, required=True, help="dataset root (nuScenes layout)")
    parser.add_argument("--split", default="val", help="split to predict: train, val, test, all, ... (default val)")
    parser.add_argument("--out", type=Path, required=True, help="folder for <token>.npz files (Occ3D format)")
    parser.add_argument("--batch-size", type=integer(1, 4096), default=1)
    parser.add_argument("--workers", type=integer(0, 256), default=2, help="data loading processes")
    parser.add_argument("--device", default=None, help="cpu, cuda (default: CUDA when available)")


def _run_predict(args: argparse.Namespace) -> int:
    from occkit.engine.jobs import predict_source

    source = _trained_model_source(args)
    counts = predict_source(source, args.data, args.split, args.out, overrides=args.set, batch_size=args.batch_size,
                            workers=args.workers, device=args.device)  # fmt: skip
    if counts is not None:  # rank 0 of a torchrun group, or the only process
        skipped = f"; {counts['skipped']} frame(s) failed to load and were skipped" if counts["skipped"] else ""
        print(f"wrote {counts['written']} predictions to {args.out}{skipped} (score them with occkit eval-preds)")
    return 0


# ----------------------------------------------------------------------------------------------------- demo
def _add_demo(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("runs/demo"), help="demo folder (default runs/demo)")
    parser.add_argument("--data", type=Path, default=Path("data/demo"),
                        help="synthetic dataset, written first if absent (default data/demo)")
    parser.add_argument("--steps", type=integer(1, 100_000_000), default=None,
                        help="optimizer steps per model (default: each model's own, occkit.demo.DEMO_MODELS)")


def _run_demo(args: argparse.Namespace) -> int:
    from occkit.demo import DEMO_MODELS, check_world, run_demo

    output_folder(args.out, "--out")
    output_folder(args.data, "--data")
    check_world(args.data)  # before any work: another world is refused, never written into
    models = None if args.steps is None else {name: args.steps for name in DEMO_MODELS}
    report = run_demo(args.out, args.data, models)
    print(f"report: {report}")
    return 0


# ----------------------------------------------------------------------------------------------------- convert
def _add_convert(parser: argparse.ArgumentParser) -> None:
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


def _run_convert(args: argparse.Namespace) -> int:
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


# ----------------------------------------------------------------------------------------------------- export
def _add_export(parser: argparse.ArgumentParser) -> None:
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


def _run_export(args: argparse.Namespace) -> int:
    from occkit.export import ExportError, check_export_output, check_opset, export_model

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
                              precision=args.precision, calibration_frames=args.calibration_frames)  # fmt: skip
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


# ----------------------------------------------------------------------------------------------------- bench
def _optimizations(text: str) -> str | tuple[str, ...]:
    """``auto``, ``none`` (no step) or a comma-separated list of fast-path steps."""
    if text == "auto":
        return "auto"
    if text == "none":
        return ()
    return tuple(name.strip() for name in text.split(",") if name.strip())


def _add_bench(parser: argparse.ArgumentParser) -> None:
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
                        help="fast path: auto (default) measures fixed_calibration, fold_bn, channels_last and "
                             "compile one by one and keeps those that speed up; none; or a comma list to apply")
    parser.add_argument("--gemm-size", type=integer(16, 65536), default=None,
                        help="n of the n x n GEMM yardstick (default 4096 on CPU, 8192 on CUDA)")
    parser.add_argument("--miou", type=number(0, 100), default=None,
                        help="the model's mIoU in percent (0 to 100), for RT-mIoU@10/15/20")
    parser.add_argument("--out", type=Path, required=True, help="JSON file for the results")


def _run_bench(args: argparse.Namespace) -> int:
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
                         gemm_size=args.gemm_size, data=None if args.data is None else str(args.data),
                         miou=args.miou)  # fmt: skip
    result = run_bench(config)
    print(format_report(result))
    _write_json(args.out, result)
    return 0


# ----------------------------------------------------------------------------------------------------- robustness
def _add_robustness(parser: argparse.ArgumentParser) -> None:
    _add_model_source(parser.add_mutually_exclusive_group(), parser, "checkpoint to score (best.pt, step-*.pt)")
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


def _run_robustness(args: argparse.Namespace) -> int:
    import torch
    from tqdm import tqdm

    if args.list:
        print(_corruption_table(), end="")
        return 0
    if (args.ckpt is None and args.weights is None) or args.out is None:
        raise UsageError("--ckpt (or --weights) and --out are required (or --list)")
    model = _model_source(args)
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


# ----------------------------------------------------------------------------------------------------- viz
def _add_viz(parser: argparse.ArgumentParser) -> None:
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
    _add_model_source(predictions, parser, "predict on the fly with this checkpoint")
    parser.add_argument("--device", default="cpu", help="where the model of --ckpt / --weights runs (default cpu)")
    parser.add_argument("--sweeps", type=integer(0, 100), default=0,
                        help="earlier LiDAR sweeps added to the key frame in the LiDAR overlay (default 0)")
    parser.add_argument("--display-width", type=integer(16, 8192), default=800,
                        help="camera images wider than this are shown resized to it (default 800 px)")
    parser.add_argument("--dpi", type=integer(20, 1000), default=100, help="PNG resolution, 20 to 1000 (default 100)")
    parser.add_argument("--colors", type=integer(2, 256), default=None, metavar="N",
                        help="store PNGs with a palette of N colours (<= 256): files several times smaller")
    parser.add_argument("--out", type=Path, required=True, help="folder for the PNGs, index.md/html and index.json")


def _run_viz(args: argparse.Namespace) -> int:
    from occkit.viz.run import LARGEST_FIGURE_INCHES, VizConfig, render_frames

    input_folder(args.data, "--data")
    output_folder(args.out, "--out")
    if args.pred is not None:
        input_folder(args.pred, "--pred")
    model = _model_source(args)
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


# ----------------------------------------------------------------------------------------------------- view
def _add_view(parser: argparse.ArgumentParser) -> None:
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
    _add_model_source(predictions, parser, "predict on the fly with this checkpoint")
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


def _run_view(args: argparse.Namespace) -> int:
    import signal

    input_folder(args.data, "--data")
    if args.pred is not None:
        input_folder(args.pred, "--pred")
    model = _model_source(args)
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


Command = tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]

COMMANDS: dict[str, Command] = {
    "info": (
        "show versions, devices, the sparse-convolution backend, grids and class taxonomies",
        _add_info,
        _run_info,
    ),
    "sim": ("simulate a synthetic driving dataset in the nuScenes + Occ3D layout", _add_sim, _run_sim),
    "index": ("index the key frames of a nuScenes-layout dataset", _add_index, _run_index),
    "label": ("build occupancy labels and visibility masks from a dataset's LiDAR sweeps, lidarseg and boxes",
              _add_label, _run_label),
    "eval-preds": (
        "score Occ3D predictions against a gts/ tree: mIoU, IoU, RayIoU (and mAVE / OccScore when they carry flow)",
        _add_eval_preds,
        _run_eval_preds,
    ),
    "train": ("train a model: checkpoints, logs, plots, validation (torchrun for several processes)", _add_train,
              _run_train),
    "eval": ("score a checkpoint on a dataset split: mIoU, IoU, RayIoU (mAVE, OccScore with a flow head), per-class "
             "table and plots", _add_eval, _run_eval),
    "predict": ("write Occ3D-format <token>.npz predictions of a checkpoint", _add_predict, _run_predict),
    "convert": ("convert an official FlashOcc / BEVDet or DAOcc checkpoint to occkit weights (.safetensors) with "
                "a report", _add_convert, _run_convert),
    "export": ("export a model to ONNX (standard operators, one fixed rig) and check it in onnxruntime", _add_export,
               _run_export),
    "bench": ("inference latency, FPS, per-stage times, MACs and GEMM efficiency of a model; the fast path",
              _add_bench, _run_bench),
    "robustness": ("score a checkpoint under sensor failures and corruptions: resilience, corruption error, plots",
                   _add_robustness, _run_robustness),
    "viz": ("render ground truth, predictions and cameras with projected LiDAR / voxels to PNGs and a page",
            _add_viz, _run_viz),
    "view": ("one scene in rerun's interactive 3D viewer: cameras, LiDAR, boxes, trajectory, occupancy, predictions "
             "and their errors on a timeline", _add_view, _run_view),
    "demo": ("the whole system on a laptop: synthetic world, train three tiny models (one per family), evaluate, "
             "render, report",
             _add_demo, _run_demo),
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
