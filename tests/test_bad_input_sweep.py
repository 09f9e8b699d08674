"""Every command, run with a table of bad inputs: each ends in exit code 2 and one line on stderr, never a traceback or
an "internal error", and deletes or corrupts nothing of the user's.

The table holds what the bad-input probes found (options out of range, files in the wrong place, crafted archives,
refused pickles, a taken port, ...); ``benchmarks/bad_inputs.py`` runs the same kind of cases end to end in fresh
processes with crafted datasets. Here they run in-process through :func:`occkit.cli.main`, so the sweep costs seconds.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import crafting

from occkit.cli import COMMANDS, main


@dataclass(frozen=True)
class Bad:
    """One command line and a text its error line must hold (``{work}`` is the sweep's folder)."""

    argv: tuple[str, ...]
    needle: str


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """The files of the sweep: a user's folder, random bytes, a refused pickle, NaN weights and two archive bombs."""
    work = tmp_path_factory.mktemp("sweep")
    (work / "user").mkdir()
    (work / "user" / "thesis.tex").write_text("mine\n")
    (work / "a-file.txt").write_text("a file\n")
    files = crafting()
    (work / "random.pt").write_bytes(np.random.default_rng(0).bytes(4096))
    torch.save({"state_dict": {"weight": torch.zeros(2)}, "meta": files.System()}, work / "system.pt")
    torch.save({"state_dict": {"img_backbone.conv1.weight": torch.full((4, 3, 3, 3), float("nan"))}}, work / "nan.pt")
    files.torch_zip_bomb(work / "bomb.pt")
    (work / "preds").mkdir()
    files.npz_bomb(work / "preds" / ("0" * 32 + ".npz"))
    labels = work / "gt" / "scene-0000" / ("0" * 32)
    labels.mkdir(parents=True)
    np.savez(labels / "labels.npz", semantics=np.zeros((200, 200, 16), np.uint8),
             mask_lidar=np.ones((200, 200, 16), np.uint8), mask_camera=np.ones((200, 200, 16), np.uint8))
    (work / "text.txt").write_text("not an array\n")
    (work / "link").mkdir()
    (work / "link" / ("0" * 32 + ".npz")).symlink_to(work / "text.txt")
    return work


def _cases() -> list[Bad]:
    data, out = "{work}/user", "{work}/out"
    return [
        Bad(("info", "--json", "{work}"), "is a folder"),
        Bad(("zoo", "diff", "daocc", "no_such_entry"), "unknown zoo entry 'no_such_entry'"),
        Bad(("sim", "--out", "{work}/a-file.txt"), "a-file.txt"),
        Bad(("sim", "--out", "{work}/user", "--overwrite", "--scenes", "1", "--frames", "1"), "nothing was deleted"),
        Bad(("sim", "--out", f"{out}/w", "--set", "world.density=1e308"), "world.density"),
        Bad(("sim", "--out", f"{out}/w", "--set", "world.ego_speed=[1, 1000]"), "world.ego_speed"),
        Bad(("sim", "--out", f"{out}/w", "--frames", "100000"), "--frames"),
        Bad(("index", "--root", "{work}/missing", "--version", "v1.0-synth", "--out", f"{out}/i.npz"), "missing"),
        Bad(("index", "--root", data, "--version", "v1.0-synth", "--out", "{work}"), "--out"),
        Bad(("label", "--root", "{work}/missing", "--version", "v1.0-synth", "--out", f"{out}/l"), "missing"),
        Bad(("label", "--root", data, "--version", "v1.0-synth", "--out", "{work}/user", "--overwrite"), "user"),
        Bad(("eval-preds", "--gt", "{work}/a-file.txt", "--preds", "{work}/preds", "--out", f"{out}/e"), "--gt"),
        Bad(("eval-preds", "--gt", "{work}/gt", "--preds", "{work}/preds", "--out", f"{out}/e"), "semantics"),
        Bad(("eval-preds", "--gt", "{work}/gt", "--preds", "{work}/link", "--out", f"{out}/e"), "0" * 32),
        Bad(("train", "--config", "flashocc_tiny", "--out", f"{out}/t", "--set", "train.max_steps=-5"),
            "train.max_steps"),
        Bad(("train", "--config", "flashocc_tiny", "--out", f"{out}/t", "--set", "train.lr=nan"), "train.lr"),
        Bad(("train", "--config", "flashocc_tiny", "--out", f"{out}/t", "--device", "tpu"), "--device"),
        Bad(("eval", "--ckpt", "{work}/random.pt", "--data", data, "--out", f"{out}/ev"), "random.pt"),
        Bad(("eval", "--ckpt", "{work}/system.pt", "--data", data, "--out", f"{out}/ev"), "system.pt"),
        Bad(("predict", "--ckpt", "{work}", "--data", data, "--out", f"{out}/p"), "--ckpt"),
        Bad(("predict", "--ckpt", "{work}/random.pt", "--data", data, "--out", f"{out}/p", "--batch-size", "100000"),
            "--batch-size"),
        Bad(("convert", "{work}/random.pt", "--model", "flashocc_tiny", "--out", f"{out}/c.safetensors"), "random.pt"),
        Bad(("convert", "{work}/system.pt", "--model", "flashocc_tiny", "--out", f"{out}/c.safetensors"), "system"),
        Bad(("convert", "{work}/bomb.pt", "--model", "flashocc_tiny", "--out", f"{out}/c.safetensors"), "bomb.pt"),
        Bad(("convert", "{work}/nan.pt", "--model", "flashocc_tiny", "--out", f"{out}/c.safetensors"), "nan.pt"),
        Bad(("export", "--model", "flashocc_tiny", "--opset", "17", "--out", f"{out}/m.onnx"), "--opset"),
        Bad(("export", "--model", "flashocc_tiny", "--out", "{work}/a-file.txt/m.onnx"), "a-file.txt"),
        Bad(("bench", "--model", "flashocc_tiny", "--miou", "250", "--out", f"{out}/b.json"), "--miou"),
        Bad(("bench", "--model", "flashocc_tiny", "--iters", "10000000", "--out", f"{out}/b.json"), "--iters"),
        Bad(("robustness", "--ckpt", "{work}/random.pt", "--out", f"{out}/r"), "random.pt"),
        Bad(("viz", "--data", data, "--out", f"{out}/v", "--dpi", "100000"), "--dpi"),
        Bad(("viz", "--data", data, "--out", "{work}/a-file.txt"), "--out"),
        Bad(("view", "--data", data, "--serve", "--bind", "everywhere"), "--bind"),
        Bad(("view", "--data", "{work}/missing"), "--data"),
        Bad(("demo", "--steps", "0"), "--steps"),
    ]


CASES = _cases()


def test_the_table_covers_every_command():
    assert {case.argv[0] for case in CASES} == set(COMMANDS)


@pytest.mark.parametrize("case", CASES, ids=[" ".join(case.argv)[:70] for case in CASES])
def test_a_bad_input_is_one_line_and_exit_code_2(case, work, capsys, monkeypatch):
    monkeypatch.chdir(work)
    argv = [part.format(work=work) for part in case.argv]
    try:
        code = main(argv)
    except SystemExit as exited:  # argparse's own refusals
        code = exited.code
    err = capsys.readouterr().err
    lines = [line for line in crafting().error_lines(err) if not line.startswith("warning:")]  # no progress bars
    assert code == 2, err
    assert len(lines) == 1 and "Traceback" not in err and "internal error" not in err, err
    assert case.needle.format(work=work) in lines[0], lines[0]
    # A line a user reads: no library's boilerplate (torch's advice to unpickle with weights_only=False, above all).
    assert len(lines[0]) < 400 and "weights_only" not in lines[0], lines[0]
    assert (work / "user" / "thesis.tex").read_text() == "mine\n"
    assert not (work / "out").exists() or not any((work / "out").rglob("*.safetensors"))


def test_a_taken_port_is_one_line(work, capsys):
    pytest.importorskip("rerun")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code = main(["view", "--data", str(work / "user"), "--serve", "--grpc-port", str(port)])
    assert code == 2 and f"--grpc-port {port} is already in use" in capsys.readouterr().err


def test_refused_pickles_name_the_global(work, capsys):
    out = work / "c.safetensors"
    assert main(["convert", str(work / "system.pt"), "--model", "flashocc_tiny", "--out", str(out)]) == 2
    line = capsys.readouterr().err.strip()
    assert "system" in line and "weights_only=False" not in line and len(line) < 400, line


#: Runs one command in a fresh process and prints its exit code and how far its peak memory rose above what the
#: imports took (torch's CUDA build alone takes hundreds of MB, so only the rise measures what the input cost).
_PEAK = """
import resource, sys
import torch, occkit.cli, occkit.convert, occkit.metrics.evaluate
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
code = occkit.cli.main(sys.argv[1:])
print(code, (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) // 1024)
"""


def _exit_code_and_peak_rise_mb(argv: list[str]) -> tuple[int, int, str]:
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", _PEAK, *argv], capture_output=True, text=True, timeout=300)
    code, rise = done.stdout.split()[-2:]
    return int(code), int(rise), done.stderr


def test_crafted_archives_cost_no_more_than_their_size(work):
    """The bombs are refused from their declared sizes: nothing near their inflated size is ever allocated."""
    for argv in (["convert", str(work / "bomb.pt"), "--model", "flashocc_tiny", "--out", str(work / "b.safetensors")],
                 ["eval-preds", "--gt", str(work / "gt"), "--preds", str(work / "preds"), "--out", str(work / "ep")]):
        code, rise_mb, err = _exit_code_and_peak_rise_mb(argv)
        lines = crafting().error_lines(err)
        assert code == 2 and len(lines) == 1 and ": error: " in lines[0], err
        assert rise_mb < 300, (argv[0], rise_mb)
