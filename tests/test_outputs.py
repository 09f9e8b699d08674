"""Output folders: one writer at a time (a real second process holds the lock), ``--overwrite`` that removes only
what occkit wrote (its manifest), report files that never replace an output or a user's file, and failed writes
that leave no temporary file."""

from __future__ import annotations

import builtins
import contextlib
import errno
import io
import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from occkit import outputs
from occkit.cli import main
from occkit.errors import UsageError, one_line
from occkit.export import check_export_output
from occkit.labeling.pipeline import LabelConfig, label_dataset
from occkit.metrics.evaluate import write_prediction
from occkit.outputs import (
    MANIFEST,
    OutputBusyError,
    OutputLock,
    check_replaceable,
    check_report_file,
    lock_path,
    report_beside,
    write_atomic,
    write_report,
)
from occkit.sim.generate import SimConfig, simulate_dataset
from occkit.sim.world import WorldConfig

WORLD = SimConfig(scenes=1, frames=1, seed=5, image_size=(64, 36), cameras=("CAM_FRONT",),
                  world=WorldConfig(density=0.5))  # fmt: skip
VERSION = WORLD.version
SIM_ARGS = ["--scenes", "1", "--frames", "1", "--image-size", "64x36", "--cameras", "CAM_FRONT"]

#: A second occkit process: takes the lock of argv[1] as command argv[2], says so, and holds it until stdin closes.
HOLDER = """
import sys
from occkit.outputs import OutputLock
lock = OutputLock(sys.argv[1], sys.argv[2])
lock.acquire()
print("locked", flush=True)
sys.stdin.read()
lock.release()
"""


#: Another process trying to take the lock of argv[1]: prints the refusal, or "taken".
TRIER = """
import sys
from occkit.outputs import OutputBusyError, OutputLock
try:
    OutputLock(sys.argv[1], "occkit sim").acquire()
    print("taken")
except OutputBusyError as error:
    print(error)
"""


@contextlib.contextmanager
def holding(out: Path, command: str) -> Iterator[subprocess.Popen]:
    """Another process holding the lock of ``out`` for the duration of the block."""
    process = subprocess.Popen([sys.executable, "-c", HOLDER, str(out), command], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert process.stdout.readline().strip() == "locked"
        yield process
    finally:
        process.stdin.close()
        process.wait(timeout=60)


def _error_line(capsys, command: str) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"occkit {command}: error: "), err
    return lines[0]


def _busy(out: Path, holder: subprocess.Popen, command: str) -> str:
    return f"--out {out} is being written by another occkit process (PID {holder.pid}, {command}, started "


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("outputs") / "world"
    simulate_dataset(WORLD, root)
    return root


# ----------------------------------------------------------------------------------------------------- the lock
def test_a_second_writer_is_refused_naming_the_holder_and_a_dead_holder_leaves_no_lock(tmp_path):
    out = tmp_path / "synth"
    with holding(out, "occkit sim") as holder:
        with pytest.raises(OutputBusyError) as refused:
            OutputLock(out, "occkit sim").acquire()
        message = str(refused.value)
        assert message.startswith(_busy(out, holder, "occkit sim"))
        assert message.endswith("); wait for it or choose another folder")
        assert lock_path(out) == tmp_path / ".synth.lock" and lock_path(out).exists()
        assert not out.exists()  # the lock lives beside the folder, which sim renames into place
        holder.send_signal(signal.SIGKILL)  # a crashed run: the kernel drops its lock
        holder.wait(timeout=60)
        with OutputLock(out, "occkit sim") as lock:
            assert lock.held
            assert json.loads(lock_path(out).read_text())["pid"] == os.getpid()
    assert not lock_path(out).exists()  # released: the lock file goes too


#: A run that takes the lock of argv[1] and forks a worker (as a DataLoader does), then waits to be killed. The worker
#: prints its PID: fork's hooks have run in it by then (the parent's return from fork does not wait for them).
FORKING_HOLDER = """
import os, sys, time
from occkit.outputs import OutputLock
OutputLock(sys.argv[1], "occkit train").acquire()
if os.fork() == 0:
    print(os.getpid(), flush=True)
    time.sleep(60)
    os._exit(0)
time.sleep(60)
"""


def test_a_killed_run_leaves_no_lock_to_its_forked_workers(tmp_path):
    out = tmp_path / "run"
    run = subprocess.Popen([sys.executable, "-c", FORKING_HOLDER, str(out)], stdout=subprocess.PIPE, text=True)
    worker = int(run.stdout.readline())
    try:
        with pytest.raises(OutputBusyError, match=f"PID {run.pid}, occkit train"):
            OutputLock(out, "occkit train").acquire()
        run.send_signal(signal.SIGKILL)
        run.wait(timeout=60)
        os.kill(worker, 0)  # the orphaned worker still runs...
        with OutputLock(out, "occkit train") as lock:  # ...and holds no lock: a resumed run starts at once
            assert lock.held
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(worker, signal.SIGKILL)
        run.kill()


def test_two_spellings_of_one_folder_share_the_lock(tmp_path, monkeypatch):
    (tmp_path / "data").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "data")
    monkeypatch.chdir(tmp_path)
    with OutputLock(Path("data/synth"), "occkit sim"):
        other = tmp_path / "link" / "x" / ".." / "synth"
        tried = subprocess.run([sys.executable, "-c", TRIER, str(other)], capture_output=True, text=True, check=True)
        assert f"(PID {os.getpid()}, occkit sim, started " in tried.stdout


def test_a_locker_that_opened_a_released_lock_file_starts_again(tmp_path, monkeypatch):
    """The holder removes the file between a racer's open and its flock: the racer must not keep a lock on a file
    that no path names any more (a third process would create a new one and get in too)."""
    out = tmp_path / "run"
    real_open, calls = os.open, []

    def open_then_released(path, flags, mode=0o777):
        fd = real_open(path, flags, mode)
        calls.append(path)
        if len(calls) == 1:
            os.unlink(path)  # the holder releases now
        return fd

    monkeypatch.setattr(outputs.os, "open", open_then_released)
    lock = OutputLock(out, "occkit train")
    lock.acquire()
    try:
        assert len(calls) == 2
        assert os.path.samestat(os.fstat(lock._fd), os.stat(lock_path(out)))
    finally:
        lock.release()


def test_without_flock_the_lock_names_a_live_holder_and_takes_over_a_dead_ones(tmp_path, monkeypatch):
    monkeypatch.setattr(outputs, "_fcntl", None)
    out = tmp_path / "labels"
    path = lock_path(out)
    path.write_text(json.dumps({"pid": os.getppid(), "command": "occkit label", "started": 0}))
    with pytest.raises(OutputBusyError, match=rf"\(PID {os.getppid()}, occkit label, started .*delete {path}"):
        OutputLock(out, "occkit label").acquire()
    finished = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    path.write_text(json.dumps({"pid": int(finished.stdout), "command": "occkit label", "started": 0}))
    with OutputLock(out, "occkit label"):
        assert json.loads(path.read_text())["pid"] == os.getpid()
    assert not path.exists()


def test_a_lock_file_that_cannot_be_created_is_one_line(tmp_path, monkeypatch):
    def refuse(*_):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(outputs.os, "open", refuse)
    with pytest.raises(PermissionError, match=r"^cannot write to --out .*run: its lock file .*\.run\.lock cannot be"):
        OutputLock(tmp_path / "run", "occkit train").acquire()


def test_a_second_sim_into_the_same_folder_is_refused_before_any_work(tmp_path, capsys):
    out = tmp_path / "synth"
    with holding(out, "occkit sim") as holder:
        assert main(["sim", "--out", str(out), *SIM_ARGS]) == 2
        assert _busy(out, holder, "occkit sim") in _error_line(capsys, "sim")
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no dataset, no staging folder, no lock left


def test_sim_and_label_hold_the_lock_while_they_write_and_nest_within_a_process(world, tmp_path):
    seen = []

    def try_to_take(out: Path):
        def probe(*_):
            tried = subprocess.run([sys.executable, "-c", TRIER, str(out)], capture_output=True, text=True, check=True)
            seen.append(tried.stdout)

        return probe

    with OutputLock(tmp_path / "again", "occkit sim"):  # as the command line does before calling the library
        simulate_dataset(WORLD, tmp_path / "again", progress=try_to_take(tmp_path / "again"))
        assert lock_path(tmp_path / "again").exists()
    label_dataset(world, VERSION, tmp_path / "labels", LabelConfig(sweeps=0), on_scene=try_to_take(tmp_path / "labels"))
    assert len(seen) == 2
    assert f"(PID {os.getpid()}, occkit sim, started " in seen[0]
    assert f"(PID {os.getpid()}, occkit label, started " in seen[1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again", "labels"]


def test_a_second_label_run_into_the_same_folder_is_refused(world, tmp_path, capsys):
    out = tmp_path / "labels"
    with holding(out, "occkit label") as holder:
        assert main(["label", "--root", str(world), "--version", VERSION, "--out", str(out), "--sweeps", "0"]) == 2
        assert _busy(out, holder, "occkit label") in _error_line(capsys, "label")
    assert not out.exists()


def test_predict_and_train_into_a_locked_folder_are_refused(tmp_path, capsys):
    from occkit import zoo
    from occkit.engine.train import train

    checkpoint = tmp_path / "best.pt"
    checkpoint.write_bytes(b"never read: the lock is taken first")
    out = tmp_path / "predictions"
    with holding(out, "occkit predict") as holder:
        command = ["predict", "--ckpt", str(checkpoint), "--data", str(tmp_path), "--out", str(out)]
        assert main([*command, "--device", "cpu"]) == 2
        assert _busy(out, holder, "occkit predict") in _error_line(capsys, "predict")
    run = tmp_path / "run"
    with holding(run, "occkit train") as holder:
        assert main(["train", "--config", "flashocc_tiny", "--out", str(run), "--device", "cpu"]) == 2
        assert _busy(run, holder, "occkit train") in _error_line(capsys, "train")
        with pytest.raises(OutputBusyError, match=rf"PID {holder.pid}, occkit train"):  # the library call too
            train(zoo.experiment("flashocc_tiny"), run, progress=False, device="cpu")
    assert not out.exists() and not run.exists()


# ----------------------------------------------------------------------------------------------------- overwrite
def test_sim_overwrite_refuses_a_nested_file_of_the_user(tmp_path, capsys):
    out = tmp_path / "synth"
    assert main(["sim", "--out", str(out), *SIM_ARGS]) == 0
    listed = json.loads((out / MANIFEST).read_text())
    assert listed["command"] == "occkit sim" and "sim_config.yaml" in listed["files"]
    assert {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()} == {*listed["files"], MANIFEST}
    camera = next((out / "samples" / "CAM_FRONT").iterdir())
    mine = camera.with_name("my-annotation.json")
    mine.write_text("mine\n")
    capsys.readouterr()
    assert main(["sim", "--out", str(out), "--overwrite", *SIM_ARGS]) == 2
    line = _error_line(capsys, "sim")
    assert "occkit sim did not write (samples/CAM_FRONT/my-annotation.json)" in line and "nothing was deleted" in line
    assert mine.read_text() == "mine\n"
    mine.unlink()
    (out / ".occkit").mkdir()
    (out / ".occkit" / "index-cache.npz").write_bytes(b"")  # a reader's cache is occkit's
    assert main(["sim", "--out", str(out), "--overwrite", *SIM_ARGS, "--seed", "1"]) == 0
    assert not (out / ".occkit").exists() and "seed: 1" in (out / "sim_config.yaml").read_text()


def test_overwrite_of_a_folder_without_manifest_says_to_delete_it_by_hand(tmp_path):
    older = tmp_path / "older"
    older.mkdir()
    (older / "sim_config.yaml").write_text("seed: 0\n")
    with pytest.raises(FileExistsError, match=r"written by an older occkit.*delete the folder by hand"):
        check_replaceable(older, "occkit sim", "sim_config.yaml")
    (older / MANIFEST).write_text(json.dumps({"format": "occkit-manifest/1", "command": "occkit label",
                                              "files": ["sim_config.yaml"]}))  # fmt: skip
    with pytest.raises(FileExistsError, match=r"written by occkit label, not occkit sim"):
        check_replaceable(older, "occkit sim", "sim_config.yaml")
    (older / MANIFEST).write_text("{")
    with pytest.raises(FileExistsError, match=r"is not a readable occkit manifest"):
        check_replaceable(older, "occkit sim")
    stranger = tmp_path / "thesis"
    stranger.mkdir()
    (stranger / "thesis.tex").write_text("mine\n")
    with pytest.raises(FileExistsError, match=r"is not an output of occkit label \(it has no \.occkit-manifest"):
        check_replaceable(stranger, "occkit label", "labeling.json")


def test_label_overwrite_keeps_the_users_files(world, tmp_path, capsys):
    out = tmp_path / "labels"
    command = ["label", "--root", str(world), "--version", VERSION, "--out", str(out), "--sweeps", "0"]
    assert main(command) == 0
    scene = next(p for p in out.iterdir() if p.is_dir())
    (scene / "notes.txt").write_text("mine\n")
    (out / "README.md").write_text("mine\n")
    capsys.readouterr()
    assert main([*command, "--overwrite"]) == 2
    line = _error_line(capsys, "label")
    assert f"occkit label did not write (README.md, {scene.name}/notes.txt)" in line
    assert (scene / "notes.txt").read_text() == (out / "README.md").read_text() == "mine\n"
    (scene / "notes.txt").unlink()
    (out / "README.md").unlink()
    assert main([*command, "--overwrite"]) == 0
    assert json.loads((out / MANIFEST).read_text())["command"] == "occkit label"


def test_a_file_added_during_the_run_is_not_deleted_when_the_result_is_published(world, tmp_path):
    out = tmp_path / "labels"
    label_dataset(world, VERSION, out, LabelConfig(sweeps=0))

    def add_a_file(_):
        (out / "late.txt").write_text("mine\n")

    with pytest.raises(FileExistsError, match=r"did not write \(late\.txt\)"):
        label_dataset(world, VERSION, out, LabelConfig(sweeps=0), overwrite=True, on_scene=add_a_file)
    assert (out / "late.txt").read_text() == "mine\n" and (out / "labeling.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["labels"]  # the staging folder is gone


# ----------------------------------------------------------------------------------------------------- reports
def test_export_to_a_json_name_is_refused_before_any_work(tmp_path, capsys):
    out = tmp_path / "deploy" / "model.json"
    assert main(["export", "--model", "flashocc_tiny", "--no-check", "--out", str(out)]) == 2
    assert f"--out {out} must be a .onnx file" in _error_line(capsys, "export")
    assert not out.parent.exists()


def test_export_refuses_to_write_its_report_over_a_users_file(tmp_path, capsys):
    out = tmp_path / "model.onnx"
    report = tmp_path / "model.json"
    report.write_text('{"my": "settings"}\n')
    assert main(["export", "--model", "flashocc_tiny", "--no-check", "--out", str(out)]) == 2
    line = _error_line(capsys, "export")
    assert f"the report goes to {report}, which exists and is not a report of occkit export" in line
    assert report.read_text() == '{"my": "settings"}\n' and not out.exists()
    write_report(report, {"model": "flashocc_tiny"}, "occkit export")  # an earlier export's report may go
    assert check_export_output(out) == report
    report.write_text(json.dumps({"model": "m", "opset": 18, "op_types": {}, "files": []}))  # an older occkit's
    assert check_export_output(out) == report


def test_report_helpers(tmp_path):
    with pytest.raises(UsageError, match=r"report of the run goes to x\.json beside it, which would replace"):
        report_beside(tmp_path / "x.json")
    assert report_beside(tmp_path / "w.safetensors", ".report.json") == tmp_path / "w.report.json"
    report = tmp_path / "w.report.json"
    check_report_file(report, "occkit convert")  # absent: fine
    report.mkdir()
    with pytest.raises(FileExistsError, match="is not a report of occkit convert"):
        check_report_file(report, "occkit convert")


def test_sim_refuses_a_summary_inside_the_dataset_it_replaces(tmp_path, capsys):
    out = tmp_path / "synth"
    assert main(["sim", "--out", str(out), *SIM_ARGS, "--json", str(out / "summary.json")]) == 2
    assert f"--json {out / 'summary.json'} is inside --out {out}" in _error_line(capsys, "sim")
    assert main(["sim", "--out", str(out), *SIM_ARGS, "--json", str(out)]) == 2
    assert "is inside --out" in _error_line(capsys, "sim")
    assert not out.exists()


def test_index_to_a_json_name_is_refused(tmp_path, capsys):
    out = tmp_path / "index.json"
    assert main(["index", "--root", str(tmp_path), "--version", VERSION, "--out", str(out)]) == 2
    assert f"--out {out}: an occkit index is a .npz file, whatever its name says; name it index.npz" in _error_line(
        capsys, "index"
    )


# ----------------------------------------------------------------------------------------------------- full disk
def test_a_prediction_written_on_a_full_disk_leaves_no_temporary_file(tmp_path, monkeypatch):
    real_open = open

    class FullDisk:
        def __init__(self, handle):
            self.handle = handle

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.handle.close()

        def write(self, _):
            raise OSError(errno.ENOSPC, "No space left on device")

    folder = tmp_path / "predictions"
    folder.mkdir()

    def open_on_a_full_disk(file, mode="r", *args, **kwargs):
        handle = real_open(file, mode, *args, **kwargs)  # the file is created, as on a real full disk
        return FullDisk(handle) if "w" in mode and Path(file).parent == folder else handle

    monkeypatch.setattr(builtins, "open", open_on_a_full_disk)
    monkeypatch.setattr(io, "open", open_on_a_full_disk)
    with pytest.raises(OSError) as failed:
        write_prediction(folder, "token0", np.zeros((200, 200, 16), np.uint8))
    assert one_line(failed.value) == f"no space left on device writing {folder / 'token0.npz'}"
    assert failed.value.errno == errno.ENOSPC and list(folder.iterdir()) == []
    with pytest.raises(OSError, match=r"^no space left on device writing .*summary\.json$"):
        write_atomic(folder / "summary.json", "{}")
    assert list(folder.iterdir()) == []
