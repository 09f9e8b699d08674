"""Commands that make and index datasets: ``occkit sim``, ``occkit label``, ``occkit index``."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from occkit.arguments import (
    check_disk,
    check_memory,
    input_folder,
    integer,
    output_file,
    output_folder,
)
from occkit.commands.common import FrameBar, write_json


# -------------------------------------------------------------------------------------------------- sim
def _image_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"image size must look like 800x450 (width x height), got {text!r}") from None
    return width, height


def add_sim(parser: argparse.ArgumentParser) -> None:
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
    parser.add_argument("--openocc", action="store_true",
                        help="also write OpenOcc v2 ground truth (openocc_v2/: 17 classes with flow, no masks)")
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


#: The label spaces ``occkit label`` writes (OpenOcc v2's flow needs tracked objects, which point clouds lack).
LABELLED_SPACES = ("occ3d", "surroundocc")


def run_sim(args: argparse.Namespace) -> int:
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
        "openocc": args.openocc,
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
        write_json(args.json, summary)
    return 0


# ------------------------------------------------------------------------------------------------ label
def add_label(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--root", type=Path, required=True, help="nuScenes-layout dataset root with nuScenes-lidarseg")
    parser.add_argument("--version", required=True, help="table folder, e.g. v1.0-mini, v1.0-trainval, v1.0-synth")
    parser.add_argument("--out", type=Path, required=True,
                        help="folder for the labels (train on them with --set data.label_root=OUT)")
    parser.add_argument("--label-space", choices=LABELLED_SPACES, default="occ3d",
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


def run_label(args: argparse.Namespace) -> int:
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


# ------------------------------------------------------------------------------------------------ index
def add_index(parser: argparse.ArgumentParser) -> None:
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


def run_index(args: argparse.Namespace) -> int:
    input_folder(args.root, "--root")
    # The index is always a .npz (its readers go by content): a .json name would promise what it does not hold.
    output_file(args.out, "--out", suffix=".npz", what="an occkit index")
    if args.from_info is not None:
        return _index_from_info(args)

    from occkit.data.index import build_split_index, save_index

    with FrameBar("index") as progress:
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
