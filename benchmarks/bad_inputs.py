"""Bad-input sweep: every occkit command run with hostile or careless input, as a user would type it.

    python benchmarks/bad_inputs.py [--out benchmarks/results/bad_inputs.json] [--work DIR]

Each case runs ``occkit ...`` in a fresh process and checks what the command promises: an error a user can cause
ends in exactly one line on stderr naming the file, record or option, with exit code 2 and no traceback; nothing is
written or read outside ``--out`` or the dataset root; no file of the user's is deleted; a fixed input gives the
right answer. The report lists every case and ends with the number of tracebacks and failed cases (both must be 0).
A small synthetic world and a one-step checkpoint are made first (about a minute on 2 cores); each case then
takes a few seconds, most of it importing torch.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

VERSION = "v1.0-synth"
#: tqdm's progress lines on stderr: not error output.
_PROGRESS = re.compile(r"\d+%\|| \d+/\d+ \[|it/s\]|frame/s\]|step/s\]")


@dataclass
class Case:
    """One command and what it must end in."""

    name: str
    argv: list[str]
    expect: str = "error"
    """``error``: exit code 2 and one stderr line; ``ok``: exit code 0."""
    contains: tuple[str, ...] = ()
    """Texts the error line (or, for ``ok``, stdout + stderr) must hold."""
    lacks: tuple[str, ...] = ()
    """Texts it must not hold (a library's boilerplate, such as torch's advice to unpickle with weights_only=False)."""
    check: Callable[[], str | None] | None = None
    """A post-condition: None when it holds, else what is wrong."""
    result: dict = field(default_factory=dict)


def _occkit(argv: list[str], cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.run([sys.executable, "-m", "occkit", *argv], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)  # fmt: skip


def error_lines(stderr: str) -> list[str]:
    lines = []
    for line in stderr.replace("\r", "\n").splitlines():
        if line.strip() and not _PROGRESS.search(line) and not line.startswith("WARNING:"):
            lines.append(line)
    return lines


def run_case(case: Case, cwd: Path) -> dict:
    started = time.perf_counter()
    process = _occkit(case.argv, cwd)
    lines = error_lines(process.stderr)
    problems = []
    traceback = "Traceback (most recent call last)" in process.stderr
    if traceback:
        problems.append("traceback")
    if case.expect == "error":
        if process.returncode != 2:
            problems.append(f"exit code {process.returncode}, expected 2")
        errors = [line for line in lines if ": error: " in line]
        if len(errors) != 1:
            problems.append(f"{len(errors)} error lines, expected 1")
        text = errors[0] if errors else ""
    else:
        if process.returncode != 0:
            problems.append(f"exit code {process.returncode}, expected 0")
        text = process.stdout + process.stderr
    problems += [f"message lacks {needle!r}" for needle in case.contains if needle not in text]
    problems += [f"message holds {needle!r}" for needle in case.lacks if needle in text]
    if case.check is not None:
        failed = case.check()
        if failed:
            problems.append(failed)
    return {"name": case.name, "command": "occkit " + " ".join(case.argv), "exit_code": process.returncode,
            "message": (lines[-1] if lines else ""), "traceback": traceback, "passed": not problems,
            "problems": problems, "seconds": round(time.perf_counter() - started, 1)}  # fmt: skip


# ----------------------------------------------------------------------------------------------------- crafting
def _tables(root: Path) -> dict[str, list[dict]]:
    return {p.stem: json.loads(p.read_text()) for p in sorted((root / VERSION).glob("*.json"))}


def _write_table(root: Path, name: str, rows, mtime: float | None = None) -> None:
    path = root / VERSION / f"{name}.json"
    path.unlink()  # hard-linked copies: never write through to the original
    path.write_text(json.dumps(rows, indent=1))
    if mtime is not None:
        os.utime(path, (mtime, mtime))


def _replace_file(path: Path, data: bytes) -> None:
    path.unlink(missing_ok=True)
    path.write_bytes(data)


def _copy(world: Path, to: Path) -> Path:
    """A copy of the world whose files are hard links (crafting replaces files, never writes into them)."""
    shutil.copytree(world, to, copy_function=os.link, ignore=shutil.ignore_patterns(".occkit"))
    return to


def _val_sample(root: Path) -> dict:
    tables = _tables(root)
    val = json.loads((root / "splits.json").read_text())["val"][0]
    scene = next(s for s in tables["scene"] if s["name"] == val)
    return next(s for s in tables["sample"] if s["token"] == scene["first_sample_token"])


def _rename_token(root: Path, old: str, new: str) -> None:
    """Rename a token in every table (a global replace of the quoted string) and the label folder."""
    quoted_old, quoted_new = json.dumps(old), json.dumps(new)
    for path in sorted((root / VERSION).glob("*.json")):
        text = path.read_text()
        if quoted_old in text:
            path.unlink()
            path.write_text(text.replace(quoted_old, quoted_new))


def _key_file(root: Path, token: str, channel: str) -> Path:
    record = next(sd for sd in _tables(root)["sample_data"] if sd["sample_token"] == token and sd["is_key_frame"]
                  and channel in sd["filename"])  # fmt: skip
    return root / record["filename"]


def _no_file_named(folder: Path, name: str) -> Callable[[], str | None]:
    def check() -> str | None:
        found = [str(p) for p in folder.rglob(f"*{name}*")]
        return f"wrote outside its root: {found}" if found else None

    return check


def _still_there(path: Path, text: str) -> Callable[[], str | None]:
    return lambda: None if path.is_file() and path.read_text() == text else f"{path} was deleted or changed"


def _absent(*paths: Path) -> Callable[[], str | None]:
    return lambda: next((f"{p} was written" for p in paths if p.exists()), None)


def build_cases(work: Path) -> list[Case]:
    world, run = work / "world", work / "run"
    ckpt = str(run / "best.pt") if (run / "best.pt").exists() else str(sorted(run.glob("step-*.pt"))[-1])
    sample = _val_sample(world)
    token = sample["token"]
    cases: list[Case] = []

    def crafted(name: str) -> Path:
        return _copy(world, work / "crafted" / name)

    def eval_args(data: Path, out: str | Path, *extra: str) -> list[str]:
        return ["eval", "--ckpt", ckpt, "--data", str(data), "--split", "val", "--out", str(work / "out" / out),
                "--workers", "0", "--no-rayiou", *extra]  # fmt: skip

    def viz_args(data: Path, out: str | Path, *extra: str) -> list[str]:
        return ["viz", "--data", str(data), "--split", "val", "--token", token, "--out", str(work / "out" / out),
                *extra]  # fmt: skip

    # --- names that would become paths
    escape = crafted("escape-token")
    _rename_token(escape, token, "../../escape_tok")
    preds = work / "out" / "deep" / "preds"
    cases.append(Case("token ../../escape_tok, predict", ["predict", "--ckpt", ckpt, "--data", str(escape), "--out",
                      str(preds), "--workers", "0"], contains=("escape_tok",),
                      check=_no_file_named(work / "out", "escape_tok")))  # fmt: skip
    cases.append(Case("token ../../escape_tok, index", ["index", "--root", str(escape), "--version", VERSION, "--out",
                      str(work / "out" / "escape.npz")], contains=("escape_tok",),
                      check=_absent(work / "out" / "escape.npz")))  # fmt: skip
    absolute = crafted("absolute-token")
    target = work / "out" / "absolute_tok"
    _rename_token(absolute, token, str(target))
    cases.append(Case("absolute token, predict", ["predict", "--ckpt", ckpt, "--data", str(absolute), "--out",
                      str(work / "out" / "preds-abs"), "--workers", "0"], contains=("absolute_tok",),
                      check=_absent(target.with_suffix(".npz"))))  # fmt: skip
    cases.append(Case("token ../../escape_tok, viz --pred", ["viz", "--data", str(escape), "--split", "val", "--out",
                      str(work / "out" / "deep" / "viz"), "--frames", "1"], contains=("escape_tok",),
                      check=_no_file_named(work / "out", "escape_tok")))  # fmt: skip
    scene_escape = crafted("escape-scene")
    scenes = _tables(scene_escape)["scene"]
    val_scene = json.loads((scene_escape / "splits.json").read_text())["val"][0]
    for scene in scenes:
        if scene["name"] == val_scene:
            scene["name"] = "../../../escape_scene"
    _write_table(scene_escape, "scene", scenes)
    splits = json.loads((scene_escape / "splits.json").read_text())
    splits["val"] = ["../../../escape_scene"]
    _replace_file(scene_escape / "splits.json", json.dumps(splits).encode())
    cases.append(Case("scene ../../../escape_scene, eval", eval_args(scene_escape, "eval-escape-scene"),
                      contains=("escape_scene",)))  # fmt: skip

    # --- --overwrite of a user's folder
    thesis = work / "user" / "thesis"
    thesis.mkdir(parents=True)
    (thesis / "thesis.tex").write_text("\\documentclass{article}\n")
    cases.append(Case("sim --overwrite of a user's folder", ["sim", "--out", str(thesis), "--overwrite", "--scenes",
                      "1", "--frames", "1"], contains=("nothing was deleted",),
                      check=_still_there(thesis / "thesis.tex", "\\documentclass{article}\n")))  # fmt: skip

    # --- the index cache and the tables
    stale = crafted("stale-cache")
    subprocess.run([sys.executable, "-m", "occkit", "index", "--root", str(stale), "--version", VERSION, "--out",
                    str(work / "out" / "stale-index.npz")], capture_output=True, check=True)  # fmt: skip
    _occkit(eval_args(stale, "eval-stale-first"), work)  # builds the dataset's own cache
    old = (stale / VERSION / "scene.json").stat().st_mtime - 3600
    scenes = _tables(stale)["scene"]
    renamed = "scene-9999"
    for scene in scenes:
        if scene["name"] == val_scene:
            scene["name"] = renamed
    _write_table(stale, "scene", scenes, mtime=old)
    (stale / "gts" / val_scene).rename(stale / "gts" / renamed)
    splits = json.loads((stale / "splits.json").read_text())
    splits["val"] = [renamed]
    _replace_file(stale / "splits.json", json.dumps(splits).encode())
    cases.append(Case("table changed with an old mtime, eval", eval_args(stale, "eval-stale"), expect="ok",
                      contains=("mIoU",)))  # fmt: skip
    unknown_scene = crafted("unknown-scene-token")
    samples = _tables(unknown_scene)["sample"]
    next(s for s in samples if s["token"] == token)["scene_token"] = "f" * 32
    _write_table(unknown_scene, "sample", samples)
    cases.append(Case("sample with an unknown scene token", eval_args(unknown_scene, "eval-unknown-scene"),
                      contains=("f" * 32,)))  # fmt: skip
    zero = crafted("zero-rotation")
    poses = _tables(zero)["ego_pose"]
    lidar = next(sd for sd in _tables(zero)["sample_data"] if sd["sample_token"] == token and "LIDAR" in sd["filename"])
    next(p for p in poses if p["token"] == lidar["ego_pose_token"])["rotation"] = [0, 0, 0, 0]
    _write_table(zero, "ego_pose", poses)
    cases.append(Case("ego pose rotation [0, 0, 0, 0]", eval_args(zero, "eval-zero-rotation"),
                      contains=("ego_pose", "rotation")))  # fmt: skip
    typed = crafted("string-translation")
    poses = _tables(typed)["ego_pose"]
    poses[0]["translation"] = "1, 2, 3"
    _write_table(typed, "ego_pose", poses)
    cases.append(Case("translation given as a string", eval_args(typed, "eval-typed"),
                      contains=("ego_pose", "translation")))  # fmt: skip
    missing_sample = crafted("missing-sample-record")
    data = _tables(missing_sample)["sample_data"]
    data[0]["sample_token"] = "e" * 32
    _write_table(missing_sample, "sample_data", data)
    cases.append(Case("sample_data pointing at a missing sample", eval_args(missing_sample, "eval-missing-sample"),
                      contains=("e" * 32,)))  # fmt: skip

    # --- sensor files
    front = _key_file(world, token, "CAM_FRONT/")
    small = crafted("small-jpeg")
    from PIL import Image

    Image.new("RGB", (50, 40)).save(_replace_target(small, front, world), "JPEG")
    cases.append(Case("50x40 JPEG where the calibration says otherwise", viz_args(small, "viz-small-jpeg"),
                      contains=(front.name,)))  # fmt: skip
    truncated = crafted("truncated-jpeg")
    _replace_file(_replace_target(truncated, front, world), front.read_bytes()[: front.stat().st_size // 2])
    cases.append(Case("truncated JPEG", viz_args(truncated, "viz-truncated"), contains=(front.name,)))
    empty_jpeg = crafted("empty-jpeg")
    _replace_file(_replace_target(empty_jpeg, front, world), b"")
    cases.append(Case("empty JPEG", eval_args(empty_jpeg, "eval-empty-jpeg"), contains=(front.name,)))
    missing_jpeg = crafted("missing-jpeg")
    _replace_target(missing_jpeg, front, world).unlink()
    cases.append(Case("missing JPEG", eval_args(missing_jpeg, "eval-missing-jpeg"), contains=(front.name,)))
    cases.append(Case("missing JPEG with data.on_error=skip at batch size 1",
                      eval_args(missing_jpeg, "eval-skip", "--set", "data.on_error=skip"), expect="ok",
                      contains=("mIoU",)))  # fmt: skip
    points = _key_file(world, token, "LIDAR_TOP")
    odd = crafted("odd-points")
    _replace_file(_replace_target(odd, points, world), b"\0" * 22)
    cases.append(Case(".pcd.bin of 22 bytes", viz_args(odd, "viz-odd-points"), contains=(points.name,)))
    empty_points = crafted("empty-points")
    _replace_file(_replace_target(empty_points, points, world), b"")
    cases.append(Case("empty .pcd.bin", viz_args(empty_points, "viz-empty-points"), contains=(points.name,)))
    missing_points = crafted("missing-points")
    _replace_target(missing_points, points, world).unlink()
    cases.append(Case("missing .pcd.bin", viz_args(missing_points, "viz-missing-points"), contains=(points.name,)))
    missing_labels = crafted("missing-labels")
    label = next((missing_labels / "gts").glob(f"*/{token}/labels.npz"))
    label.unlink()
    _replace_file(label.with_name("other.npz"), b"")  # the folder stays, the labels are gone
    cases.append(Case("missing labels.npz", eval_args(missing_labels, "eval-missing-labels"), contains=(token,)))

    # --- options
    out = work / "out"
    a_file = out / "a-file.txt"
    a_file.parent.mkdir(parents=True, exist_ok=True)
    a_file.write_text("a file\n")
    cases += [
        Case("export --opset 99 --no-check", ["export", "--model", "flashocc_tiny", "--opset", "99", "--no-check",
             "--out", str(out / "m.onnx")], contains=("opset 99",), check=_absent(out / "m.onnx")),
        Case("export --sample 99", ["export", "--model", "flashocc_tiny", "--data", str(world), "--sample", "99",
             "--no-check", "--out", str(out / "m99.onnx")], contains=("--sample 99",), check=_absent(out / "m99.onnx")),
        Case("bench --miou 250", ["bench", "--model", "flashocc_tiny", "--miou", "250", "--out",
             str(out / "b.json")], contains=("--miou",)),
        Case("bench --gemm-size 10000000", ["bench", "--model", "flashocc_tiny", "--gemm-size", "10000000", "--out",
             str(out / "b.json")], contains=("--gemm-size",)),
        Case("bench --out a folder", ["bench", "--model", "flashocc_tiny", "--out", str(out)], contains=("--out",)),
        Case("info --json a folder", ["info", "--json", str(out)], contains=("--json",)),
        Case("index --out a folder", ["index", "--root", str(world), "--version", VERSION, "--out", str(out)],
             contains=("--out",), check=lambda: next((f"left {p}" for p in out.glob(".*.partial")), None)),
        Case("export --out a folder", ["export", "--model", "flashocc_tiny", "--out", str(out)], contains=("--out",)),
        Case("viz --out a file", viz_args(world, a_file), contains=("--out",)),
        Case("eval --out below a file", eval_args(world, a_file / "eval"), contains=("--out",)),
        Case("sim --out .", ["sim", "--out", "."], contains=("--out .",)),
        Case("train --device tpu", ["train", "--config", "flashocc_tiny", "--out", str(out / "tpu"), "--device",
             "tpu", "--set", f"data.root={world}"], contains=("--device",), check=_absent(out / "tpu")),
        Case("eval --device cuda without a GPU", eval_args(world, "cuda", "--device", "cuda"),
             contains=("--device cuda",)),
        Case("demo --steps -5", ["demo", "--steps", "-5", "--out", str(out / "demo"), "--data", str(world)],
             contains=("--steps",), check=_absent(out / "demo")),
        Case("demo --steps 0", ["demo", "--steps", "0", "--out", str(out / "demo"), "--data", str(world)],
             contains=("--steps",), check=_absent(out / "demo")),
        Case("sim --image-size 16000x9000", ["sim", "--out", str(out / "huge"), "--image-size", "16000x9000"],
             contains=("memory",), check=_absent(out / "huge")),
        Case("sim --scenes 100000", ["sim", "--out", str(out / "many"), "--scenes", "100000"], contains=("disk",),
             check=_absent(out / "many")),
        Case("viz --dpi 100000", viz_args(world, "dpi", "--dpi", "100000"), contains=("--dpi",)),
        Case("resume with --set train.lr=0.5", ["train", "--config", "flashocc_tiny", "--out", str(run), "--resume",
             "auto", "--no-progress", *_run_sets(world), "--set", "train.lr=0.5"], contains=("train.lr",)),
    ]
    cases += _crafted_file_cases(work, world, ckpt)
    return cases


def _crafted_file_cases(work: Path, world: Path, ckpt: str) -> list[Case]:
    """What a hostile but realistic user hands occkit: archive bombs, refused pickles, random bytes, NaN weights,
    settings past every physical bound, report names that collide with outputs."""
    import numpy as np
    import torch

    files, out = work / "files", work / "out"
    files.mkdir(parents=True, exist_ok=True)
    (files / "random.pt").write_bytes(np.random.default_rng(0).bytes(4096))
    torch.save({"meta": System()}, files / "system.pt")
    torch.save({"state_dict": {"img_backbone.conv1.weight": torch.full((4, 3, 3, 3), float("nan"))}}, files / "nan.pt")
    torch_zip_bomb(files / "bomb.pt")
    preds = files / "preds"
    preds.mkdir(exist_ok=True)
    npz_bomb(preds / f"{_val_sample(world)['token']}.npz")
    user = work / "user" / "labels"
    user.mkdir(parents=True, exist_ok=True)
    (user / "notes").mkdir(exist_ok=True)
    (user / "notes" / "mine.txt").write_text("mine\n")
    convert = ["convert", "--model", "flashocc_tiny", "--out"]
    return [
        Case("convert a 2 GiB zip bomb", [*convert, str(out / "bomb.safetensors"), str(files / "bomb.pt")],
             contains=("bomb.pt",), check=_absent(out / "bomb.safetensors")),
        Case("convert a pickle calling os.system", [*convert, str(out / "sys.safetensors"), str(files / "system.pt")],
             contains=("system",), lacks=("weights_only",)),
        Case("convert random bytes", [*convert, str(out / "rnd.safetensors"), str(files / "random.pt")],
             contains=("random.pt",), lacks=("weights_only",)),
        Case("convert all-NaN weights", [*convert, str(out / "nan.safetensors"), str(files / "nan.pt")],
             contains=("nan.pt",), check=_absent(out / "nan.safetensors")),
        Case("eval --ckpt random bytes", ["eval", "--ckpt", str(files / "random.pt"), "--data", str(world), "--out",
             str(out / "eval-random")], contains=("random.pt",)),
        Case("eval-preds with a (200, 200, 40000) header", ["eval-preds", "--gt", str(world / "gts"), "--preds",
             str(preds), "--out", str(out / "preds-bomb"), "--allow-missing"], contains=("semantics",)),
        Case("sim --set world.density=1e308", ["sim", "--out", str(out / "dense"), "--set", "world.density=1e308"],
             contains=("world.density",), check=_absent(out / "dense")),
        Case("train --set train.max_steps=-5", ["train", "--config", "flashocc_tiny", "--out", str(out / "neg"),
             "--set", f"data.root={world}", "--set", "train.max_steps=-5"], contains=("train.max_steps",),
             check=_absent(out / "neg")),
        Case("train --set train.lr=nan", ["train", "--config", "flashocc_tiny", "--out", str(out / "nan-lr"),
             "--set", f"data.root={world}", "--set", "train.lr=nan"], contains=("train.lr",),
             check=_absent(out / "nan-lr")),
        Case("label --overwrite of a user's folder", ["label", "--root", str(world), "--version", VERSION, "--out",
             str(user), "--overwrite"], check=_still_there(user / "notes" / "mine.txt", "mine\n")),
        Case("export --out model.json", ["export", "--model", "flashocc_tiny", "--no-check", "--out",
             str(out / "x" / "model.json")], contains=("model.json",)),
        Case("view --bind a name", ["view", "--data", str(world), "--serve", "--bind", "everywhere"],
             contains=("--bind",)),
        Case("robustness --ckpt random bytes", ["robustness", "--ckpt", str(files / "random.pt"), "--out",
             str(out / "rob")], contains=("random.pt",)),
    ]  # fmt: skip


class System:
    """Unpickles as a call of ``os.system``: what a malicious checkpoint holds."""

    def __reduce__(self):
        return os.system, ("true",)


def zip_bomb(path: Path, member: str, size: int, header: bytes = b"", mode: str = "w") -> None:
    """Add ``member`` to the zip at ``path``: ``header`` then zeros up to ``size`` bytes, deflated to a few MB."""
    import zipfile
    import zlib

    with (zipfile.ZipFile(path, mode, compression=zipfile.ZIP_DEFLATED) as archive,
          archive.open(member, "w", force_zip64=True) as stream):  # fmt: skip
        # Run-length matching deflates zeros to the same size as the default strategy, 2.4 x faster; the stream is
        # still plain deflate, which every reader inflates.
        stream._compressor = zlib.compressobj(9, zlib.DEFLATED, -15, 9, zlib.Z_RLE)
        stream.write(header)
        chunk = bytes(1 << 24)
        for _ in range(size // len(chunk)):
            stream.write(chunk)


def torch_zip_bomb(path: Path, size: int = 1 << 31) -> None:
    """A torch checkpoint whose one tensor record inflates to ``size`` bytes (2 GiB: a 2 MB file)."""
    import zipfile

    import torch

    torch.save({"weight": torch.zeros(4)}, path)
    with zipfile.ZipFile(path) as original:
        entries = {info.filename: original.read(info) for info in original.infolist()}
    record = next(name for name in entries if name.endswith("data/0"))
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in entries.items():
            if name != record:
                archive.writestr(name, data)
    zip_bomb(path, record, size, mode="a")


def npy_header(shape: tuple[int, ...], dtype: str = "|u1") -> bytes:
    """The header of a ``.npy`` file declaring an array of ``shape`` and ``dtype`` (its data may be anything)."""
    import io

    import numpy as np

    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": dtype, "fortran_order": False, "shape": shape})
    return header.getvalue()


def npz_bomb(path: Path) -> None:
    """An Occ3D prediction whose ``semantics.npy`` header declares (200, 200, 40000) uint8: 1.6 GB from 1.5 MB."""
    zip_bomb(path, "semantics.npy", 1 << 27, npy_header((200, 200, 40000)))




def _replace_target(copy: Path, original_file: Path, world: Path) -> Path:
    """The path in ``copy`` of ``original_file`` of ``world``, unlinked from the original (a private file)."""
    path = copy / original_file.relative_to(world)
    data = path.read_bytes()
    path.unlink()
    path.write_bytes(data)
    return path


def _run_sets(world: Path) -> list[str]:
    overrides = (f"data.root={world}", "train.max_steps=1", "train.val_every=-1", "train.workers=0",
                 "train.batch_size=1", "train.warmup_steps=1")  # fmt: skip
    return [part for value in overrides for part in ("--set", value)]


def prepare(work: Path) -> None:
    """The world (2 scenes of 3 key frames at 320x180) and a one-step flashocc_tiny checkpoint."""
    world, run = work / "world", work / "run"
    if not world.exists():
        subprocess.run([sys.executable, "-m", "occkit", "sim", "--out", str(world), "--scenes", "2", "--frames", "3",
                        "--image-size", "320x180"], check=True, capture_output=True)  # fmt: skip
    if not run.exists():
        subprocess.run([sys.executable, "-m", "occkit", "train", "--config", "flashocc_tiny", "--out", str(run),
                        "--no-progress", *_run_sets(world)], check=True, capture_output=True)  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/bad_inputs.json"))
    parser.add_argument("--work", type=Path, default=None, help="working folder (default: a temporary one)")
    parser.add_argument("--only", default=None, help="run the cases whose name holds this text")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as temporary:
        work = (args.work or Path(temporary)).absolute()
        shutil.rmtree(work / "crafted", ignore_errors=True)
        shutil.rmtree(work / "out", ignore_errors=True)
        shutil.rmtree(work / "user", ignore_errors=True)
        work.mkdir(parents=True, exist_ok=True)
        prepare(work)
        cases = [c for c in build_cases(work) if args.only is None or args.only in c.name]
        results = []
        for case in cases:
            result = run_case(case, work)
            results.append(result)
            mark = "ok  " if result["passed"] else "FAIL"
            print(f"{mark} {case.name:55s} exit {result['exit_code']}  {result['message'][:150]}", flush=True)
            for problem in result["problems"]:
                print(f"       {problem}")
    summary = {"cases": len(results), "failed": sum(not r["passed"] for r in results),
               "tracebacks": sum(r["traceback"] for r in results), "results": results}  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=2) + "\n")
    print(f"{summary['cases']} cases, {summary['failed']} failed, {summary['tracebacks']} tracebacks -> {args.out}")
    return 0 if summary["failed"] == 0 and summary["tracebacks"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
