"""Commands that train and score: ``occkit train``, ``eval``, ``predict`` and ``eval-preds``."""

from __future__ import annotations

import argparse
from pathlib import Path

from occkit.arguments import (
    check_device,
    input_folder,
    integer,
    output_folder,
)
from occkit.commands.common import (
    LABEL_SPACE_NAMES,
    FrameBar,
    add_experiment_overrides,
    add_model_source,
    trained_model_source,
    write_json,
)
from occkit.errors import UsageError


# ------------------------------------------------------------------------------------------------ train
def add_train(parser: argparse.ArgumentParser) -> None:
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


def run_train(args: argparse.Namespace) -> int:
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
    write_json(args.out / "summary.json", summary)
    if result.metrics is not None:
        print(f"trained {result.steps} steps in {result.seconds:.0f} s: val mIoU {100 * result.metrics['miou']:.2f}, "
              f"IoU {100 * result.metrics['iou']:.2f}; run folder {args.out}")
    return 0


# ------------------------------------------------------------------------------------------------- eval
def add_eval(parser: argparse.ArgumentParser) -> None:
    add_model_source(parser.add_mutually_exclusive_group(required=True), parser, "checkpoint (best.pt, step-*.pt)")
    add_experiment_overrides(parser)
    parser.add_argument("--data", type=Path, default=None, help="dataset root (default: the one it was trained on)")
    parser.add_argument("--split", default=None, help="split to score (default: the run's validation split)")
    parser.add_argument("--out", type=Path, required=True, help="folder for metrics.json, metrics.md and plots")
    parser.add_argument("--no-rayiou", action="store_true",
                        help="skip RayIoU (mIoU and IoU only); SurroundOcc labels have no RayIoU anyway")
    parser.add_argument("--mask", choices=("camera", "lidar", "none"), default=None,
                        help="visibility mask for mIoU/IoU (default: the label space's, camera for Occ3D, none for "
                             "SurroundOcc)")
    parser.add_argument("--save-predictions", action="store_true", help="also write <token>.npz predictions")
    parser.add_argument("--batch-size", type=integer(1, 4096), default=1, help="frames per forward pass (default 1)")
    parser.add_argument("--workers", type=integer(0, 256), default=2, help="data loading processes (default 2)")
    parser.add_argument("--device", default=None, help="cpu, cuda (default: CUDA when available)")


def run_eval(args: argparse.Namespace) -> int:
    from occkit.engine.jobs import evaluate_source
    from occkit.metrics.evaluate import markdown_table

    source = trained_model_source(args)
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


# ---------------------------------------------------------------------------------------------- predict
def add_predict(parser: argparse.ArgumentParser) -> None:
    add_model_source(parser.add_mutually_exclusive_group(required=True), parser, "checkpoint (best.pt, step-*.pt)")
    add_experiment_overrides(parser)
    parser.add_argument("--data", type=Path, required=True, help="dataset root (nuScenes layout)")
    parser.add_argument("--split", default="val", help="split to predict: train, val, test, all, ... (default val)")
    parser.add_argument("--out", type=Path, required=True, help="folder for <token>.npz files (Occ3D format)")
    parser.add_argument("--batch-size", type=integer(1, 4096), default=1, help="frames per forward pass (default 1)")
    parser.add_argument("--workers", type=integer(0, 256), default=2, help="data loading processes (default 2)")
    parser.add_argument("--device", default=None, help="cpu, cuda (default: CUDA when available)")


def run_predict(args: argparse.Namespace) -> int:
    from occkit.engine.jobs import predict_source

    source = trained_model_source(args)
    counts = predict_source(source, args.data, args.split, args.out, overrides=args.set, batch_size=args.batch_size,
                            workers=args.workers, device=args.device)  # fmt: skip
    if counts is not None:  # rank 0 of a torchrun group, or the only process
        skipped = f"; {counts['skipped']} frame(s) failed to load and were skipped" if counts["skipped"] else ""
        print(f"wrote {counts['written']} predictions to {args.out}{skipped} (score them with occkit eval-preds)")
    return 0


# ------------------------------------------------------------------------------------------- eval-preds
def add_eval_preds(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gt", type=Path, required=True,
                        help="ground truth: Occ3D's gts/ folder (<scene>/<token>/labels.npz), or the folder holding "
                             "SurroundOcc's samples/ (<LiDAR file>.npy)")
    parser.add_argument(
        "--preds", type=Path, required=True, help="folder of <token>.npz predictions (key semantics or pred)"
    )
    parser.add_argument("--out", type=Path, required=True, help="folder for metrics.json, metrics.md and the plot")
    parser.add_argument("--label-space", choices=LABEL_SPACE_NAMES, default="occ3d",
                        help="the benchmark of ground truth and predictions (default occ3d; openocc: OpenOcc v2, "
                             "--gt its openocc_v2/ folder); surroundocc needs --nuscenes ROOT --version V to pair its "
                             "files with sample tokens")
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


def run_eval_preds(args: argparse.Namespace) -> int:

    from occkit.label_space import label_space
    from occkit.metrics.evaluate import evaluate_prediction_folder, markdown_table, write_report

    input_folder(args.gt, "--gt")
    input_folder(args.preds, "--preds")
    output_folder(args.out, "--out")
    if args.rayiou and not label_space(args.label_space).rayiou:
        raise UsageError(f"--rayiou: RayIoU is not defined for {args.label_space} labels (only on Occ3D's grid)")
    if args.rayiou and args.ray_origins is None and args.nuscenes is None:
        raise UsageError("--rayiou needs --ray-origins FILE.npz or --nuscenes ROOT --version V for the ray origins")
    if args.label_space != "occ3d" and args.nuscenes is None:
        raise UsageError(f"--label-space {args.label_space}: its files are named after each frame's LiDAR file; give "
                         "the dataset's tables with --nuscenes ROOT --version V")  # fmt: skip
    notes: list[str] = []  # printed once the progress bar is done
    with FrameBar("eval") as progress:
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
