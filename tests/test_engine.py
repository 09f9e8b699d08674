"""The training engine end to end on one tiny synthetic dataset.

* a run SIGKILLed at random moments and resumed with ``--resume auto`` ends bitwise equal to an uninterrupted one
  (model, EMA, optimizer, random generators, logs), also with gradient accumulation and a DataLoader worker;
* checkpoints are never seen truncated, and a failing ``torch.save`` leaves the previous file intact;
* ``torchrun`` with two CPU processes (gloo): training completes with one and the same model on both ranks, and
  ``occkit eval`` gives the same metrics with one process and with two; where a 2-process run with batch 1 and a
  1-process run with batch 2 differ, the difference is pinned to per-process BatchNorm and loss normalisation;
* bad input is one ``occkit <command>: error:`` line on stderr, a non-zero exit and nothing overwritten;
* ``occkit eval``, ``occkit predict`` and ``occkit eval-preds`` agree; the learning-rate schedule.

Every training run is a small ``flashocc_tiny`` (64 x 176 crops, no C5 stage, narrow BEV) on the CPU,
in a subprocess. The runs compared bitwise (kill and resume) have two threads each, PyTorch's default on a two-core
machine: a thread count above one is what exposes an order of floating-point additions left to thread scheduling.
The ranks of a ``torchrun`` launch have one thread each, so that two of them share the two cores of a laptop.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import torch_threads

from occkit.classes import DETECTION_CLASSES
from occkit.engine.checkpoint import atomic_save, checkpoint_step, latest_checkpoint, load_checkpoint, save_checkpoint
from occkit.sim.generate import SimConfig, simulate_dataset
from occkit.zoo import load_experiment

REPO = Path(__file__).resolve().parents[1]
CAMERAS = ("CAM_FRONT", "CAM_BACK")
#: flashocc_tiny made smaller still, and the training settings every run here shares (all that the tests rely on
#: set here, whatever the zoo entry says).
SMALL = (
    "data.cameras=[CAM_FRONT, CAM_BACK]",
    "data.image_aug.final_size=[64, 176]",
    "model.lss.image_size=[64, 176]",
    "model.image.out_stages=[3]",
    "model.bev.channels=[16, 32, 64]",
    "model.bev.neck_channels=16",
    "model.occupancy.in_channels=16",
    "model.occupancy.hidden_channels=16",
    "model.occupancy.use_mask=true",
    "model.occupancy.class_balance=true",
    "train.batch_size=1",
    "train.accumulate=1",
    "train.workers=0",
    "train.epochs=100",
    "train.max_steps=0",
    "train.log_every=1",
    "train.lr=0.005",
    "train.warmup_steps=2",
    "train.ema_decay=0",
    "train.val_every=0",
    "train.val_split=val",
    "train.checkpoint_every=0",
    "train.keep_last=2",
    "train.seed=0",
)
#: Added to SMALL in the runs compared bitwise: 88 depth bins rather than the entry's 22, enough frustum points that
#: the splat's gradient kernels run on both threads (with 22, every such kernel stays under PyTorch's parallel grain
#: and runs on one thread). The other runs keep 22, at a quarter of the splat's cost.
BITWISE_SMALL = ("model.lss.depth_range=[1.0, 45.0, 0.5]",)
#: One thread per process, for the runs that share the two cores (torchrun ranks) or compare nothing bitwise.
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: Two threads per process for the runs compared bitwise: runs repeat exactly at any fixed thread count, and more
#: than one is the case that needs the fixed-order reductions of the models. Two such runs go side by side on two
#: cores; passive waiting lets a thread that waits for a descheduled sibling give its core away instead of spinning
#: (three times quicker here), and changes no result.
BITWISE_THREADS = 2
BITWISE_ENV = {**os.environ, "OMP_NUM_THREADS": str(BITWISE_THREADS), "MKL_NUM_THREADS": str(BITWISE_THREADS),
               "OMP_WAIT_POLICY": "PASSIVE"}  # fmt: skip
#: Change to draw other kill moments (``OCCKIT_TEST_KILL_SEED=7 pytest tests/test_engine.py``).
KILL_SEED = int(os.environ.get("OCCKIT_TEST_KILL_SEED", "0"))
TIMEOUT = 300


# ------------------------------------------------------------------------------------------------------ helpers
def _sets(overrides) -> list[str]:
    return [part for value in overrides for part in ("--set", value)]


def _train_args(data: Path, out: Path, *extra: str) -> list[str]:
    return ["train", "--config", "flashocc_tiny", "--out", str(out), "--no-progress", "--device", "cpu",
            *_sets((f"data.root={data}", *SMALL, *extra))]  # fmt: skip


def _command(args) -> list[str]:
    return [sys.executable, "-m", "occkit", *map(str, args)]


def _torchrun(args) -> list[str]:
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", *map(str, args)]


def _run(command: list[str], timeout: float = TIMEOUT, env: dict = ENV) -> subprocess.CompletedProcess:
    result = subprocess.run(command, env=env, cwd=REPO, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"{command[2:5]} exited {result.returncode}:\n{result.stderr[-4000:]}"
    return result


def _start(command: list[str], stderr: Path, env: dict = ENV, stdout: int = subprocess.DEVNULL) -> subprocess.Popen:
    """``command`` in the background, its stderr going to the file ``stderr`` (a pipe nobody reads could fill); its
    stdout dropped, or with ``subprocess.PIPE`` read by :func:`_finish`."""
    with open(stderr, "wb") as handle:
        return subprocess.Popen(command, env=env, cwd=REPO, stdout=stdout, stderr=handle, text=True)


def _finish(process: subprocess.Popen, stderr: Path) -> str | None:
    """The stdout (None where dropped) of a :func:`_start` process, once it has ended; it must have succeeded."""
    stdout, _ = process.communicate(timeout=TIMEOUT)
    assert process.returncode == 0, stderr.read_text()[-4000:]
    return stdout


def _rows(path: Path) -> list[dict]:
    """The complete JSON lines of a log (a line being appended right now is skipped)."""
    rows = []
    for line in path.read_text().splitlines() if path.is_file() else []:
        with contextlib.suppress(ValueError):
            rows.append(json.loads(line))
    return rows


def _logged_step(out: Path) -> int:
    rows = _rows(out / "log.jsonl")
    return rows[-1]["step"] if rows else 0


def _kill_mid_training(process: subprocess.Popen, out: Path, step: int, rng: random.Random, stderr: Path) -> None:
    """SIGKILL ``process`` once ``out`` has a checkpoint and has logged ``step``, a random fraction of a step later."""
    deadline = time.monotonic() + TIMEOUT
    while not ((out / "last.json").is_file() and _logged_step(out) >= step):
        assert process.poll() is None, f"the run ended before step {step}: {stderr.read_text()[-3000:]}"
        assert time.monotonic() < deadline, "the run did not reach the step to kill it at"
        time.sleep(0.005)
    time.sleep(rng.uniform(0.0, 0.3))
    assert process.poll() is None, "the run ended before it could be killed"
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=60)
    assert process.returncode == -signal.SIGKILL


def _final(out: Path) -> dict:
    return load_checkpoint(latest_checkpoint(out))


def _assert_equal_tensors(a: dict, b: dict, what: str) -> None:
    assert a.keys() == b.keys(), what
    for key in a:
        assert torch.equal(a[key], b[key]), f"{what}: {key} differs"


def _assert_equal_optimizers(a: dict, b: dict) -> None:
    assert a["param_groups"] == b["param_groups"]
    assert a["state"].keys() == b["state"].keys()
    for index in a["state"]:
        _assert_equal_tensors(a["state"][index], b["state"][index], f"optimizer state of parameter {index}")


def _checksums(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


def _without_speed(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in row.items() if k != "samples_per_s"} for row in rows]


# ------------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module", autouse=True)
def _tests_on_one_thread():
    with torch_threads(1):
        yield


@pytest.fixture(scope="session")
def data(tmp_path_factory) -> Path:
    """2 scenes x 4 key frames, 2 cameras at 176 x 99: scene-0001 trains, scene-0002 validates."""
    from occkit.data.dataset import DatasetConfig, OccupancyDataset

    root = tmp_path_factory.mktemp("engine") / "data"
    simulate_dataset(SimConfig(scenes=2, frames=4, seed=0, image_size=(176, 99), cameras=CAMERAS), root)
    # Index once here: the ranks of a torchrun launch would otherwise all build and cache it at the same moment.
    OccupancyDataset(DatasetConfig(root=str(root), split="all", cameras=CAMERAS, sweeps=-1))
    return root


def _kill_and_resume(data: Path, folder: Path, extra: tuple[str, ...], kills_after: list[int], seed: int) -> dict:
    """An uninterrupted run, and one killed ``kills_after[i]`` steps past the last logged one of the previous attempt
    and resumed (``--resume auto``) each time, then resumed to the end; every process with ``BITWISE_THREADS``.

    Returns both run folders and copies of the killed folder right after each kill."""
    rng = random.Random(seed)
    extra = (*BITWISE_SMALL, *extra)
    reference, killed = folder / "uninterrupted", folder / "killed"
    started = time.perf_counter()
    # The uninterrupted run goes alongside the others (see BITWISE_ENV).
    uninterrupted = _start(_command(_train_args(data, reference, *extra)), folder / "uninterrupted.stderr",
                           env=BITWISE_ENV)
    snapshots = []
    for number, steps in enumerate(kills_after):
        # Past every row the killed attempts logged, so it is this attempt that reaches the step.
        step = _logged_step(killed) + steps
        stderr = folder / f"attempt-{number}.stderr"
        process = _start(_command(_train_args(data, killed, *extra) + (["--resume", "auto"] if number else [])),
                         stderr, env=BITWISE_ENV)  # fmt: skip
        _kill_mid_training(process, killed, step, rng, stderr)
        snapshots.append(folder / f"after-kill-{number}")
        shutil.copytree(killed, snapshots[-1])
    _run(_command(_train_args(data, killed, *extra) + ["--resume", "auto"]), env=BITWISE_ENV)
    _finish(uninterrupted, folder / "uninterrupted.stderr")
    return {"reference": reference, "killed": killed, "snapshots": snapshots,
            "seconds": time.perf_counter() - started}  # fmt: skip


#: The run killed and resumed: 12 steps of 2 accumulated batches read by a DataLoader worker, a checkpoint every 2
#: steps and a log row every 3 (so a checkpoint falls between two rows), a ramped EMA, a per-epoch cosine, validation
#: every epoch (2 steps).
RESUMED_RUN = ("train.max_steps=12", "train.accumulate=2", "train.workers=1", "train.checkpoint_every=2",
               "train.log_every=3", "train.ema_decay=0.9", "train.ema_ramp=4", "train.val_every=1",
               "train.lr_by_epoch=true")  # fmt: skip

#: The CBGS run killed once and resumed: its epoch is the class-balanced list (longer than the 12 steps), so the kill
#: falls inside it and the resumed sampler must skip into the resampled order.
CBGS_RUN = ("train.max_steps=12", "train.workers=1", "train.checkpoint_every=2", "train.log_every=3",
            "train.ema_decay=0.9", "train.val_every=-1", "train.sampler=cbgs",
            "data.valid_boxes_only=true")  # fmt: skip


@pytest.fixture(scope="session")
def resumed(data, tmp_path_factory) -> dict:
    """RESUMED_RUN uninterrupted, and killed twice (the second time while resumed) then resumed to the end."""
    rng = random.Random(KILL_SEED)
    kills_after = [rng.randint(3, 5), rng.randint(2, 3)]  # after the row of step 3 or 6, then of step 6 or 9
    return _kill_and_resume(data, tmp_path_factory.mktemp("resume"), RESUMED_RUN, kills_after, KILL_SEED)


@pytest.fixture(scope="session")
def resumed_cbgs(data, tmp_path_factory) -> dict:
    """CBGS_RUN uninterrupted, and killed once then resumed to the end."""
    kills_after = [random.Random(KILL_SEED + 1).randint(3, 5)]
    return _kill_and_resume(data, tmp_path_factory.mktemp("resume-cbgs"), CBGS_RUN, kills_after, KILL_SEED + 1)


# ------------------------------------------------------------------------------------------------------ checkpoints
def test_atomic_save_failing_midway_keeps_the_previous_file(tmp_path, monkeypatch):
    target = tmp_path / "step-00000002.pt"
    save_checkpoint(tmp_path, {"model": {"w": torch.ones(3)}, "step": 2}, step=2, keep_last=2)
    before, pointer = target.read_bytes(), (tmp_path / "last.json").read_text()

    def broken_save(payload, handle, *args, **kwargs):
        handle.write(b"PK\x03\x04 half a checkpoint")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError, match="No space left"):
        atomic_save({"model": {"w": torch.zeros(3)}}, target)
    with pytest.raises(OSError, match="No space left"):
        save_checkpoint(tmp_path, {"model": {"w": torch.zeros(3)}, "step": 4}, step=4, keep_last=2)
    monkeypatch.undo()
    assert target.read_bytes() == before and (tmp_path / "last.json").read_text() == pointer
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.json", "step-00000002.pt"]  # no temporary left
    assert torch.equal(load_checkpoint(latest_checkpoint(tmp_path))["model"]["w"], torch.ones(3))
    target.write_bytes(before[: len(before) // 2])  # what a plain torch.save killed mid-way leaves
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        load_checkpoint(target)


def test_checkpoint_step_reads_the_name_and_refuses_other_files():
    assert checkpoint_step("runs/a/step-00000144.pt") == 144
    for name in ("best.pt", "step-.pt", "step-12a.pt"):
        with pytest.raises(ValueError, match=f"{re.escape(name)} is not named like a checkpoint"):
            checkpoint_step(name)


def test_killed_folders_never_hold_a_truncated_checkpoint(resumed):
    runs = resumed
    # Temporary files may remain only where a kill landed mid-write, and never under a checkpoint's name.
    temporary = re.compile(r"\.(step-\d{8}\.pt|best\.pt|last\.json)\.\d+\.tmp|\.(log|val)\.jsonl\.tmp|\.write-test")
    allowed = {"config.yaml", "last.json", "log.jsonl", "train.csv", "val.jsonl", "best.pt", "tensorboard",
               "summary.json", "loss.png", "per_class_iou.png"}  # fmt: skip
    for folder in [*runs["snapshots"], runs["killed"]]:
        pointed = latest_checkpoint(folder)
        assert pointed is not None, f"{folder.name}: killed before its first checkpoint"
        payload = load_checkpoint(pointed)
        assert payload["step"] == json.loads((folder / "last.json").read_text())["step"] == checkpoint_step(pointed)
        checkpoints = sorted(folder.glob("*.pt"))
        assert pointed in checkpoints
        for path in checkpoints:
            assert load_checkpoint(path)["model"], path
        for path in folder.iterdir():
            name = path.name
            assert name in allowed or re.fullmatch(r"step-\d{8}\.pt", name) or temporary.fullmatch(name), name


# ------------------------------------------------------------------------------------------------------ resume
def test_killed_and_resumed_run_is_bitwise_the_uninterrupted_one(resumed):
    runs = resumed
    print(f"both runs, kills and resumes took {runs['seconds']:.1f} s")
    reference, resumed = _final(runs["reference"]), _final(runs["killed"])
    assert reference["step"] == resumed["step"] == 12
    assert (reference["epoch"], reference["best_miou"]) == (resumed["epoch"], resumed["best_miou"])
    _assert_equal_tensors(reference["model"], resumed["model"], "model")
    _assert_equal_tensors(reference["ema"], resumed["ema"], "EMA")
    _assert_equal_optimizers(reference["optimizer"], resumed["optimizer"])
    assert torch.equal(reference["rng"]["torch"], resumed["rng"]["torch"])
    assert torch.equal(reference["rng"]["numpy"]["keys"], resumed["rng"]["numpy"]["keys"])
    assert reference["rng"]["python"] == resumed["rng"]["python"]
    # The logs of the resumed run hold every row once, with the uninterrupted run's values (means over the steps
    # since the previous row included, when a checkpoint fell between two rows).
    rows = _rows(runs["killed"] / "log.jsonl")
    assert [r["step"] for r in rows] == [3, 6, 9, 12]
    assert _without_speed(rows) == _without_speed(_rows(runs["reference"] / "log.jsonl"))
    assert _rows(runs["killed"] / "val.jsonl") == _rows(runs["reference"] / "val.jsonl")
    assert len(_rows(runs["reference"] / "val.jsonl")) == 6
    best_reference, best_resumed = load_checkpoint(runs["reference"] / "best.pt"), load_checkpoint(
        runs["killed"] / "best.pt")  # fmt: skip
    assert best_reference["step"] == best_resumed["step"]
    _assert_equal_tensors(best_reference["model"], best_resumed["model"], "best.pt")


def test_a_killed_and_resumed_cbgs_run_is_bitwise_the_uninterrupted_one(resumed_cbgs, data):
    from occkit.data.dataset import DatasetConfig, OccupancyDataset
    from occkit.data.sampling import cbgs_indices

    runs = resumed_cbgs
    reference, resumed = _final(runs["reference"]), _final(runs["killed"])
    assert reference["step"] == resumed["step"] == 12
    _assert_equal_tensors(reference["model"], resumed["model"], "model")
    _assert_equal_tensors(reference["ema"], resumed["ema"], "EMA")
    _assert_equal_optimizers(reference["optimizer"], resumed["optimizer"])
    assert _without_speed(_rows(runs["killed"] / "log.jsonl")) == _without_speed(_rows(runs["reference"] / "log.jsonl"))
    # The 12 steps stayed inside the first CBGS epoch, which is longer than the split: the kill fell mid-epoch.
    split = OccupancyDataset(DatasetConfig(root=str(data), split="train", cameras=CAMERAS, sweeps=-1,
                                           valid_boxes_only=True))  # fmt: skip
    population = cbgs_indices(split.sample_classes(), DETECTION_CLASSES, seed=0)
    assert len(population) > max(12, len(split)) and reference["epoch"] == 0


def test_resume_auto_after_a_kill_before_the_first_checkpoint_starts_afresh(data, tmp_path):
    from occkit.engine.train import train

    experiment = load_experiment("flashocc_tiny", [f"data.root={data}", *SMALL, *BITWISE_SMALL, "train.max_steps=3",
                                             "train.val_every=-1"])  # fmt: skip
    out = tmp_path / "run"

    class Killed(Exception):
        pass

    def kill_at_step_two(step: int) -> None:
        if step == 2:
            raise Killed

    with torch_threads(BITWISE_THREADS):  # the logged losses of both attempts are compared bitwise
        with pytest.raises(Killed):  # steps 1 and 2 logged; the first checkpoint would come at step 3
            train(experiment, out, progress=False, device="cpu", on_step=kill_at_step_two)
        first_attempt = _rows(out / "log.jsonl")
        assert latest_checkpoint(out) is None and [r["step"] for r in first_attempt] == [1, 2]
        assert train(experiment, out, resume="auto", progress=False, device="cpu").steps == 3
    rows = _rows(out / "log.jsonl")
    assert [r["step"] for r in rows] == [1, 2, 3]  # no step twice
    assert _without_speed(rows[:2]) == _without_speed(first_attempt)


def test_a_checkpoint_without_its_optimizer_state_resumes_with_fresh_moments(data, tmp_path, capsys):
    """A run moved between machines may travel without AdamW's moments (they double the file): it resumes with the
    weights, the step and the schedule, and says that the moments start afresh."""
    from occkit.engine.train import train

    experiment = load_experiment("flashocc_tiny", [f"data.root={data}", *SMALL, "train.max_steps=2",
                                             "train.val_every=-1", "train.checkpoint_every=1"])  # fmt: skip
    out = tmp_path / "run"
    with torch_threads(1):
        train(experiment, out, progress=False, device="cpu")
        checkpoint = latest_checkpoint(out)
        payload = torch.load(checkpoint, map_location="cpu", weights_only=False)
        payload["optimizer"] = None
        torch.save(payload, checkpoint)
        longer = load_experiment("flashocc_tiny", [f"data.root={data}", *SMALL, "train.max_steps=3",
                                                   "train.val_every=-1", "train.checkpoint_every=1"])  # fmt: skip
        run = train(longer, out, resume="auto", progress=False, device="cpu", allow_changes=("train.max_steps",))
    assert run.steps == 3
    assert "holds no optimizer state: AdamW's moments start afresh at step 2" in capsys.readouterr().out
    resumed = torch.load(latest_checkpoint(out), map_location="cpu", weights_only=False)
    assert resumed["optimizer"]["state"]  # the moments of the steps after the resume


# ------------------------------------------------------------------------------------------------------ DDP
#: ``python -m occkit`` that also saves this rank's final training state to the folder given first.
DUMP_RANK_STATE = '''
import os, runpy, sys

import torch

from occkit.engine import train as engine

trainers = []
original_init = engine._Trainer.__init__


def recording_init(self, *args, **kwargs):
    original_init(self, *args, **kwargs)
    trainers.append(self)


engine._Trainer.__init__ = recording_init
folder = sys.argv.pop(1)
try:
    runpy.run_module("occkit", run_name="__main__", alter_sys=True)
finally:
    if trainers:
        t = trainers[-1]
        state = {"model": t.model.state_dict(), "ema": t.ema.module.state_dict(), "optimizer": t.optimizer.state_dict()}
        torch.save(state, os.path.join(folder, "rank%s.pt" % os.environ.get("RANK", "0")))
'''
#: 4 epochs of the 4 training frames, validated after each.
DDP_TRAIN = ("train.epochs=2", "train.val_every=1", "train.ema_decay=0.9")


@pytest.fixture(scope="session")
def ddp(data, tmp_path_factory) -> dict:
    """A 2-process run with batch 1 per process, a 1-process run with batch 2, and ``occkit eval`` of the first's
    best.pt with 1 and with 2 processes."""
    from occkit.cli import main

    folder = tmp_path_factory.mktemp("ddp")
    driver, dumps = folder / "dump_rank_state.py", folder / "ranks"
    driver.write_text(DUMP_RANK_STATE)
    dumps.mkdir()
    seconds = {}
    # The 1-process runs go in this process while a torchrun group runs beside them: a group spends much of its
    # time starting and meeting its ranks, which leaves a core free.
    started = time.perf_counter()
    # torchrun --standalone --nproc-per-node 2 -m occkit train ..., through a script that also saves each rank's state
    group = _start(_torchrun([driver, dumps, *_train_args(data, folder / "two", *DDP_TRAIN)]), folder / "two.stderr",
                   stdout=subprocess.PIPE)
    with torch_threads(1):  # one process: this one, on one thread as each rank
        assert main([str(arg) for arg in _train_args(data, folder / "one", *DDP_TRAIN, "train.batch_size=2")]) == 0
    seconds["train, 1 process"] = time.perf_counter() - started
    two = _finish(group, folder / "two.stderr")
    seconds["train, 2 processes"] = time.perf_counter() - started
    evaluate = ["eval", "--ckpt", folder / "two" / "best.pt", "--data", data, "--workers", "0", "--device", "cpu"]
    started = time.perf_counter()
    group = _start(_torchrun(["-m", "occkit", *evaluate, "--out", folder / "eval-two"]), folder / "eval-two.stderr")
    with torch_threads(1):
        assert main([str(arg) for arg in (*evaluate, "--out", folder / "eval-one", "--save-predictions")]) == 0
    seconds["eval, 1 process"] = time.perf_counter() - started
    _finish(group, folder / "eval-two.stderr")
    seconds["eval, 2 processes"] = time.perf_counter() - started
    print("durations: " + ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items()))
    return {"folder": folder, "two": folder / "two", "one": folder / "one", "ranks": dumps, "stdout": two,
            "eval_one": folder / "eval-one", "eval_two": folder / "eval-two"}  # fmt: skip


def test_ddp_training_completes_with_one_model_on_both_ranks(ddp):
    assert ddp["stdout"].count("trained 4 steps") == 1  # rank 0 alone reports
    summary = json.loads((ddp["two"] / "summary.json").read_text())
    assert summary["steps"] == 4 and summary["best_miou"] == max(r["miou"] for r in _rows(ddp["two"] / "val.jsonl"))
    rank0, rank1 = (torch.load(ddp["ranks"] / f"rank{r}.pt", weights_only=True) for r in (0, 1))
    for key in ("model", "ema"):  # parameters and buffers, BatchNorm running statistics included
        _assert_equal_tensors(rank0[key], rank1[key], f"{key}, rank 0 vs rank 1")
    _assert_equal_optimizers(rank0["optimizer"], rank1["optimizer"])
    saved = _final(ddp["two"])
    assert saved["step"] == 4
    _assert_equal_tensors(saved["model"], rank0["model"], "checkpoint vs rank 0")
    _assert_equal_tensors(saved["ema"], rank0["ema"], "checkpoint EMA vs rank 0")
    rows = _rows(ddp["two"] / "log.jsonl")
    assert [r["step"] for r in rows] == list(range(1, 5))


def test_ddp_eval_equals_single_process_eval_and_training_validation(ddp):
    one = json.loads((ddp["eval_one"] / "metrics.json").read_text())
    two = json.loads((ddp["eval_two"] / "metrics.json").read_text())
    assert one == two
    assert one["frames"] == 4 and {"miou", "iou", "per_class_iou", "rayiou", "rayiou@1"} <= one.keys()
    # best.pt holds the EMA weights the 2-process run validated, each rank on half of the frames.
    best = load_checkpoint(ddp["two"] / "best.pt")
    logged = next(r for r in _rows(ddp["two"] / "val.jsonl") if r["step"] == best["step"])
    assert (one["miou"], one["iou"], one["per_class_iou"]) == (logged["miou"], logged["iou"], logged["per_class_iou"])


def test_ddp_and_single_process_validation_agree_up_to_batchnorm_and_loss_normalisation(ddp):
    """2 processes x batch 1 vs 1 process x batch 2 on the same data: same samples per step, same initial weights,
    same schedule; what differs is measured in the next test. Here: the numbers, and that they stay close."""
    two, one = _rows(ddp["two"] / "val.jsonl"), _rows(ddp["one"] / "val.jsonl")
    assert [r["step"] for r in two] == [r["step"] for r in one] == [2, 4]
    for a, b in zip(two, one, strict=True):
        print(f"step {a['step']}: 2 processes mIoU {a['miou']:.6f} IoU {a['iou']:.6f} | "
              f"1 process mIoU {b['miou']:.6f} IoU {b['iou']:.6f}")  # fmt: skip
        assert abs(a["miou"] - b["miou"]) < 0.02 and abs(a["iou"] - b["iou"]) < 0.02
    losses = [(a["loss"], b["loss"]) for a, b in zip(_rows(ddp["two"] / "log.jsonl"), _rows(ddp["one"] / "log.jsonl"),
                                                      strict=True)]  # fmt: skip
    print("training loss (2 processes, 1 process): " + ", ".join(f"{a:.5f}/{b:.5f}" for a, b in losses))
    assert all(abs(a - b) < 0.02 * b for a, b in losses)


def test_what_separates_two_processes_from_one_batch(data):
    """The first optimizer step of both runs, on the same weights and the same two samples: DDP averages the two
    per-sample gradients, one process differentiates the loss of the pair. Two things make them differ, and nothing
    else: the loss is normalised by the local batch's camera-visible voxels (each weighted by its class-balance
    weight), so in a pair each sample weighs by its share of that sum, under DDP by one half; and BatchNorm normalises
    with the statistics of the local batch (one sample per process under DDP)."""
    from occkit import zoo
    from occkit.data.collate import collate
    from occkit.data.dataset import OccupancyDataset
    from occkit.engine.distributed import EpochSampler

    # Cross-entropy only: the Lovasz term is a loss of the whole batch, which no per-sample weighting decomposes.
    experiment = load_experiment("flashocc_tiny", [f"data.root={data}", *SMALL, "model.occupancy.lovasz_weight=0.0"])
    dataset = OccupancyDataset(experiment.data)
    first = list(EpochSampler(len(dataset), 2, seed=experiment.train.seed))[:2]  # the first global batch
    samples = [dataset[i] for i in first]
    pair, singles = collate(samples), [collate([s]) for s in samples]
    torch.manual_seed(experiment.train.seed)
    model = zoo.build_from_config(experiment.architecture, experiment.model)
    initial = {k: v.clone() for k, v in model.state_dict().items()}
    class_weights = model.occupancy_head.class_weights
    shares = [float((s.mask_camera * class_weights[s.voxel_semantics.long()]).sum()) for s in singles]

    def gradient(batch, training: bool) -> torch.Tensor:
        model.load_state_dict(initial)  # a train-mode forward moves the running statistics
        model.train(training)
        model.zero_grad()
        sum(model.loss(model(batch), batch).values()).backward()
        return torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None])

    def relative(a: torch.Tensor, b: torch.Tensor) -> float:
        return float((a - b).norm() / b.norm())

    # BatchNorm on its running statistics (each sample computed alone): weighting by the loss's normaliser is exact
    frozen_pair, frozen = gradient(pair, False), [gradient(s, False) for s in singles]
    weighted = (shares[0] * frozen[0] + shares[1] * frozen[1]) / sum(shares)
    ddp_mean = (frozen[0] + frozen[1]) / 2
    # ... and with batch statistics, no weighting recovers the pair's gradient.
    train_pair, train = gradient(pair, True), [gradient(s, True) for s in singles]
    train_weighted = (shares[0] * train[0] + shares[1] * train[1]) / sum(shares)
    errors = {"normaliser-weighted, running statistics": relative(weighted, frozen_pair),
              "plain mean (DDP), running statistics": relative(ddp_mean, frozen_pair),
              "normaliser-weighted, batch statistics": relative(train_weighted, train_pair)}  # fmt: skip
    print(f"loss normalisers {shares}; relative gradient differences to one batch of two: {errors}")
    assert abs(shares[0] - shares[1]) > 0.05 * sum(shares)
    assert errors["normaliser-weighted, running statistics"] < 1e-4  # float32 rounding
    assert errors["plain mean (DDP), running statistics"] > 20 * errors["normaliser-weighted, running statistics"]
    assert errors["normaliser-weighted, batch statistics"] > 20 * errors["normaliser-weighted, running statistics"]


# ------------------------------------------------------------------------------------------------------ eval, predict
def test_eval_writes_a_report_and_predict_scores_the_same_with_eval_preds(ddp, data, tmp_path, capsys):
    from occkit.cli import main

    report = ddp["eval_one"]
    metrics = json.loads((report / "metrics.json").read_text())
    assert {"miou", "iou", "per_class_iou", "rayiou", "rayiou@1", "rayiou@2", "rayiou@4", "frames"} <= metrics.keys()
    assert metrics["split"] == "val" and metrics["frames"] == 4 and len(metrics["per_class_iou"]) == 18
    assert "mIoU" in (report / "metrics.md").read_text() and "RayIoU" in (report / "metrics.md").read_text()
    assert (report / "per_class_iou.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    predictions = tmp_path / "predictions"
    assert main(["predict", "--ckpt", str(ddp["two"] / "best.pt"), "--data", str(data), "--out", str(predictions),
                 "--workers", "0", "--device", "cpu"]) == 0  # fmt: skip
    val_scenes = json.loads((data / "splits.json").read_text())["val"]
    gts = tmp_path / "gts-val"  # the val split's labels alone: eval-preds scores every frame of a gts/ tree
    for scene in val_scenes:
        shutil.copytree(data / "gts" / scene, gts / scene)
    tokens = sorted(p.name for scene in val_scenes for p in (data / "gts" / scene).iterdir())
    assert sorted(p.stem for p in predictions.glob("*.npz")) == tokens
    for token in tokens:  # the same files as occkit eval --save-predictions
        with np.load(predictions / f"{token}.npz") as a, np.load(report / "predictions" / f"{token}.npz") as b:
            assert a["semantics"].dtype == np.uint8 and a["semantics"].shape == (200, 200, 16)
            assert np.array_equal(a["semantics"], b["semantics"])
    capsys.readouterr()
    scored = tmp_path / "scored"
    assert main(["eval-preds", "--gt", str(gts), "--preds", str(predictions), "--out", str(scored)]) == 0
    again = json.loads((scored / "metrics.json").read_text())
    assert again["frames"] == 4 and again["missing_predictions"] == 0
    assert again["miou"] == pytest.approx(metrics["miou"], abs=1e-12)
    assert again["iou"] == pytest.approx(metrics["iou"], abs=1e-12)
    assert again["per_class_iou"] == pytest.approx(metrics["per_class_iou"], abs=1e-12)


# ------------------------------------------------------------------------------------------------------ bad input
def _one_error_line(capsys, command: str) -> str:
    err = capsys.readouterr().err
    lines = err.strip("\n").splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"occkit {command}: error: ") and "Traceback" not in err
    return lines[0]


@pytest.fixture
def earlier_run(resumed, tmp_path) -> Path:
    """A copy of a finished flashocc run folder."""
    return Path(shutil.copytree(resumed["reference"], tmp_path / "earlier"))


def test_unknown_config_key_is_named_with_a_suggestion(data, tmp_path):
    result = subprocess.run(_command(_train_args(data, tmp_path / "run", "train.lrr=1")), env=ENV, cwd=REPO,
                            capture_output=True, text=True, timeout=TIMEOUT)  # fmt: skip
    assert result.returncode == 2
    lines = result.stderr.strip("\n").splitlines()
    assert len(lines) == 1 and lines[0].startswith("occkit train: error: "), result.stderr
    assert "'lrr'" in lines[0] and "did you mean 'lr'?" in lines[0]
    assert not (tmp_path / "run").exists()


def test_missing_data_root(tmp_path, capsys):
    from occkit.cli import main

    missing = tmp_path / "no-such-data"
    assert main(_train_args(missing, tmp_path / "run")) == 2
    line = _one_error_line(capsys, "train")
    assert str(missing) in line and "does not exist" in line
    assert not (tmp_path / "run").exists()
    assert main(["eval", "--ckpt", str(tmp_path / "none.pt"), "--out", str(tmp_path / "eval")]) == 2
    assert "none.pt does not exist" in _one_error_line(capsys, "eval")


def test_eval_of_a_checkpoint_with_another_model_config(earlier_run, data, tmp_path, capsys):
    from occkit.cli import main

    checkpoint = str(latest_checkpoint(earlier_run))
    out = tmp_path / "eval"
    assert main(["eval", "--ckpt", checkpoint, "--out", str(out), "--set", "model.occupancy.hidden_channels=32"]) == 2
    line = _one_error_line(capsys, "eval")
    assert "model.occupancy.hidden_channels is 16 in the checkpoint but 32 here" in line
    # A config file or zoo name: here flashocc_tiny without this file's smaller settings.
    assert main(["eval", "--ckpt", checkpoint, "--out", str(out), "--config", "flashocc_tiny",
                 "--set", f"data.root={data}"]) == 2  # fmt: skip
    line = _one_error_line(capsys, "eval")
    assert re.search(r"trained with another model config: model\.\S+ is .+ in the checkpoint but .+ here", line)
    assert main(["eval", "--ckpt", checkpoint, "--out", str(out), "--config", "daocc_tiny"]) == 2
    assert "holds a flashocc model, not daocc" in _one_error_line(capsys, "eval")
    assert not out.exists()


def test_resume_of_a_flashocc_checkpoint_into_a_daocc_run(earlier_run, data, tmp_path, capsys):
    from occkit.cli import main

    before = _checksums(earlier_run)
    daocc = ["train", "--config", "daocc_tiny", "--no-progress", "--device", "cpu", "--set", f"data.root={data}",
             "--set", "data.cameras=[CAM_FRONT, CAM_BACK]"]  # fmt: skip
    assert main([*daocc, "--out", str(earlier_run), "--resume", "auto"]) == 2
    assert "holds a flashocc model, not daocc" in _one_error_line(capsys, "train")
    assert _checksums(earlier_run) == before  # config.yaml included
    checkpoint = str(latest_checkpoint(earlier_run))
    wider = _train_args(data, tmp_path / "wider", *BITWISE_SMALL, "model.occupancy.hidden_channels=32")
    assert main([*wider, "--resume", checkpoint]) == 2
    assert "model.occupancy.hidden_channels is 16 in the checkpoint but 32 here" in _one_error_line(capsys, "train")
    assert _checksums(earlier_run) == before


def test_resume_with_changed_settings_is_refused_unless_allowed(earlier_run, data, capsys):
    from occkit.cli import main

    before = _checksums(earlier_run)
    saved_lr = load_checkpoint(latest_checkpoint(earlier_run))["experiment"]["train"]["lr"]
    same = (*BITWISE_SMALL, *RESUMED_RUN)  # as the earlier run trained
    resume = [*_train_args(data, earlier_run, *same, "train.lr=0.5", "train.workers=0"), "--resume", "auto"]
    assert main(resume) == 2
    line = _one_error_line(capsys, "train")
    assert f"train.lr is {saved_lr!r} in the checkpoint but 0.5 here" in line and "--allow-change train.lr" in line
    assert "workers" not in line  # bookkeeping: changes no weight
    assert _checksums(earlier_run) == before  # config.yaml included
    # Allowed explicitly, the run continues (no steps are left) and its config.yaml records the new value.
    assert main([*resume, "--allow-change", "train.lr"]) == 0
    assert "lr: 0.5" in (earlier_run / "config.yaml").read_text()
    assert f"train.lr: {saved_lr!r} -> 0.5" in capsys.readouterr().out


def test_out_holding_an_earlier_run_is_not_overwritten(earlier_run, data, tmp_path, capsys):
    from occkit.cli import main

    before = _checksums(earlier_run)
    assert main(_train_args(data, earlier_run)) == 2
    line = _one_error_line(capsys, "train")
    assert "already holds a run" in line and "--resume auto" in line
    assert _checksums(earlier_run) == before
    # Nor by resuming another run's checkpoint into it.
    other = Path(shutil.copytree(earlier_run, tmp_path / "other"))
    assert main([*_train_args(data, earlier_run), "--resume", str(latest_checkpoint(other))]) == 2
    assert "already holds another run" in _one_error_line(capsys, "train")
    assert _checksums(earlier_run) == before


def test_out_below_a_file(data, tmp_path, capsys):
    from occkit.cli import main

    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    assert main(_train_args(data, blocker / "run")) == 2
    assert f"cannot be created: {blocker} is a file" in _one_error_line(capsys, "train")
    assert main(_train_args(data, blocker)) == 2
    assert f"--out {blocker} is a file; give a folder" in _one_error_line(capsys, "train")


def _assert_unwritable_out_is_one_error(locked: Path, checkpoint: Path, data: Path, capsys) -> None:
    from occkit.cli import main

    assert main(_train_args(data, locked / "run")) == 2
    assert "cannot write to --out" in _one_error_line(capsys, "train")
    assert main(["eval", "--ckpt", str(checkpoint), "--out", str(locked / "eval")]) == 2
    assert "cannot write to --out" in _one_error_line(capsys, "eval")
    assert main(["predict", "--ckpt", str(checkpoint), "--data", str(data), "--out", str(locked / "predictions")]) == 2
    assert "cannot write to --out" in _one_error_line(capsys, "predict")
    assert list(locked.iterdir()) == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_unwritable_out(earlier_run, data, tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        _assert_unwritable_out_is_one_error(locked, latest_checkpoint(earlier_run), data, capsys)
    finally:
        locked.chmod(0o700)


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("chattr") is None, reason="needs root and chattr")
def test_unwritable_out_as_root(earlier_run, data, tmp_path, capsys):
    """The same for root, whom only an immutable folder stops."""
    locked = tmp_path / "locked"
    locked.mkdir()
    if subprocess.run(["chattr", "+i", str(locked)], capture_output=True).returncode:
        pytest.skip("this filesystem or container has no immutable folders")
    try:
        _assert_unwritable_out_is_one_error(locked, latest_checkpoint(earlier_run), data, capsys)
    finally:
        subprocess.run(["chattr", "-i", str(locked)], check=True)


def test_a_checkpoint_from_before_a_new_option_is_compatible_while_the_option_keeps_its_default():
    from occkit import zoo
    from occkit.engine.checkpoint import check_compatible

    current = zoo.experiment("flashocc_m0").to_dict()["model"]
    older = copy.deepcopy(current)
    del older["occupancy"]["lovasz_weight"]  # written before the option existed
    payload = {"architecture": "flashocc", "experiment": {"model": older}}
    check_compatible(payload, "flashocc", current, "old.pt")
    changed = copy.deepcopy(current)
    changed["occupancy"]["lovasz_weight"] = 0.5
    with pytest.raises(ValueError, match=r"old\.pt .*model\.occupancy\.lovasz_weight is 0\.0 in the checkpoint"):
        check_compatible(payload, "flashocc", changed, "old.pt")
    older["occupancy"]["retired_option"] = 1  # an option since removed: compared as saved, so named
    with pytest.raises(ValueError, match="model.occupancy.retired_option is 1 in the checkpoint but absent here"):
        check_compatible(payload, "flashocc", current, "old.pt")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_plain_cuda_means_this_processs_gpu():
    from occkit.engine import distributed

    try:
        assert distributed.setup("cuda").device == torch.device("cuda", 0)
    finally:
        distributed.teardown()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_generator_states_loaded_onto_the_gpu_restore():
    """A checkpoint loaded with map_location="cuda" (as a CUDA run resumes) carries its generator states there."""
    from occkit.engine.checkpoint import rng_state, set_rng_state

    state = rng_state()
    expected = (torch.rand(3), torch.rand(3, device="cuda"))
    on_gpu = {**state, "torch": state["torch"].cuda(), "cuda": [s.cuda() for s in state["cuda"]],
              "numpy": {**state["numpy"], "keys": state["numpy"]["keys"].cuda()}}  # fmt: skip
    set_rng_state(on_gpu)
    assert torch.equal(torch.rand(3), expected[0]) and torch.equal(torch.rand(3, device="cuda"), expected[1])
