"""The command line's one error path: options checked before work, one line, exit code 2, tracebacks on --debug.

The data-level cases (crafted tables, broken sensor files) are in the data tests; ``benchmarks/bad_inputs.py``
runs every command end to end with all of them.
"""

from __future__ import annotations

import argparse
import sys

import pytest

from occkit.arguments import check_device, check_disk, check_memory, integer, number, output_file, output_folder
from occkit.cli import main
from occkit.errors import UsageError, is_input_error, one_line


def _error_line(capsys, command: str) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"occkit {command}: error: ") or lines[0].startswith("occkit: error: "), err
    return lines[0]


def _exit_code(argv: list[str]) -> int:
    """``main``'s return value, or the code argparse exits with."""
    try:
        return main(argv)
    except SystemExit as exit_info:
        return int(exit_info.code)


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["demo", "--steps", "0"], "argument --steps: must be between 1 and 100000000, got 0"),
        (["demo", "--steps", "-5"], "argument --steps: must be between 1 and 100000000, got -5"),
        (["sim", "--out", "x", "--scenes", "many"], "argument --scenes: expected an integer, got 'many'"),
        (["bench", "--model", "flashocc_tiny", "--miou", "250", "--out", "b.json"], "between 0 and 100, got 250"),
        (["bench", "--model", "flashocc_tiny", "--miou", "nan", "--out", "b.json"], "a finite number"),
        (["bench", "--model", "flashocc_tiny", "--gemm-size", "10000000", "--out", "b.json"], "--gemm-size"),
        (["viz", "--data", ".", "--out", "v", "--dpi", "100000"], "argument --dpi: must be between 20 and 1000"),
        (["export", "--model", "flashocc_tiny", "--opset", "17", "--out", "m.onnx"], "argument --opset"),
        (["index", "--root", ".", "--version", "v", "--out", "i.json", "--max-sweeps", "-1"], "--max-sweeps"),
    ],
)
def test_out_of_range_options_are_one_line_before_any_work(argv, needle, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert _exit_code(argv) == 2
    line = _error_line(capsys, argv[0])
    assert needle in line and f"see occkit {argv[0]} --help" in line
    assert list(tmp_path.iterdir()) == []


def test_files_and_folders_in_the_wrong_place(tmp_path, capsys):
    folder, a_file = tmp_path / "folder", tmp_path / "file.txt"
    folder.mkdir()
    a_file.write_text("mine\n")
    assert main(["info", "--json", str(folder)]) == 2
    assert f"--json {folder} is a folder" in _error_line(capsys, "info")
    assert main(["index", "--root", str(tmp_path), "--version", "v1.0-synth", "--out", str(folder)]) == 2
    assert f"--out {folder} is a folder" in _error_line(capsys, "index")
    assert main(["bench", "--model", "flashocc_tiny", "--out", str(folder)]) == 2
    assert f"--out {folder} is a folder" in _error_line(capsys, "bench")
    assert main(["export", "--model", "flashocc_tiny", "--out", str(a_file / "m.onnx")]) == 2
    assert f"{a_file} is a file, not a folder" in _error_line(capsys, "export")
    assert main(["viz", "--data", str(folder), "--out", str(a_file)]) == 2
    assert f"--out {a_file} is a file; give a folder" in _error_line(capsys, "viz")
    assert main(["eval-preds", "--gt", str(a_file), "--preds", str(folder), "--out", str(folder)]) == 2
    assert f"--gt {a_file} is a file" in _error_line(capsys, "eval-preds")
    assert main(["predict", "--ckpt", str(folder), "--data", str(folder), "--out", str(folder)]) == 2
    assert f"--ckpt {folder} is a folder" in _error_line(capsys, "predict")
    assert a_file.read_text() == "mine\n"


def test_devices_are_checked_against_the_machine(tmp_path, capsys):
    import torch

    assert main(["bench", "--model", "flashocc_tiny", "--device", "tpu", "--out", str(tmp_path / "b.json")]) == 2
    assert "--device must be cpu, cuda or cuda:N, got 'tpu'" in _error_line(capsys, "bench")
    with pytest.raises(UsageError, match="cpu, cuda or cuda:N"):
        check_device("cuda:x")
    if torch.cuda.is_available():
        count = torch.cuda.device_count()
        with pytest.raises(UsageError, match=f"has {count} CUDA device"):
            check_device(f"cuda:{count}")
    else:
        with pytest.raises(UsageError, match="CUDA is not available on this machine"):
            check_device("cuda")
    assert check_device("cpu") == "cpu" and check_device(None) is None


def test_sizes_are_checked_against_memory_and_disk(tmp_path, capsys):
    assert main(["sim", "--out", str(tmp_path / "huge"), "--image-size", "16000x9000"]) == 2
    assert "needs about" in _error_line(capsys, "sim") and not (tmp_path / "huge").exists()
    assert main(["sim", "--out", str(tmp_path / "many"), "--scenes", "1000000"]) == 2
    assert "of disk" in _error_line(capsys, "sim") and not (tmp_path / "many").exists()
    with pytest.raises(UsageError, match="--x: a test needs about 1024.0 TB of memory"):
        check_memory(2**50, "a test", "--x")
    with pytest.raises(UsageError, match="of disk"):
        check_disk(tmp_path / "new" / "deeper", 2**62, "a test", "--out")
    check_memory(1, "a byte", "--x")
    check_disk(tmp_path, 1, "a byte", "--out")


def test_sim_overwrite_replaces_only_a_dataset_it_wrote(tmp_path, capsys, monkeypatch):
    small = ["--scenes", "1", "--frames", "1", "--image-size", "64x36"]
    user = tmp_path / "thesis"
    user.mkdir()
    (user / "thesis.tex").write_text("mine\n")
    assert main(["sim", "--out", str(user), "--overwrite", *small]) == 2
    assert "nothing was deleted" in _error_line(capsys, "sim")
    assert (user / "thesis.tex").read_text() == "mine\n"
    dataset = tmp_path / "world"
    assert main(["sim", "--out", str(dataset), *small]) == 0
    (dataset / ".occkit").mkdir()  # a reader's index cache is occkit's too
    assert main(["sim", "--out", str(dataset), "--overwrite", *small, "--seed", "1"]) == 0
    (dataset / "notes.txt").write_text("mine\n")
    capsys.readouterr()
    assert main(["sim", "--out", str(dataset), "--overwrite", *small]) == 2
    assert "did not write (notes.txt)" in _error_line(capsys, "sim")
    assert (dataset / "notes.txt").read_text() == "mine\n"
    monkeypatch.chdir(dataset)
    assert main(["sim", "--out", ".", *small]) == 2
    assert "--out . is the current folder" in _error_line(capsys, "sim")


def test_an_unexpected_error_is_one_line_exit_1_and_debug_shows_the_traceback(monkeypatch, capsys):
    from occkit import cli

    def broken(args):
        raise KeyError("a bug")

    summary, add, _ = cli.COMMANDS["info"]
    monkeypatch.setitem(cli.COMMANDS, "info", (summary, add, broken))
    assert main(["info"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "internal error: KeyError" in err and "--debug" in err
    with pytest.raises(KeyError):
        main(["info", "--debug"])
    with pytest.raises(KeyError):
        main(["--debug", "info"])


def test_input_errors_and_their_line():
    assert is_input_error(ValueError("x")) and is_input_error(FileNotFoundError(2, "No such file", "a.json"))
    assert not is_input_error(KeyError("x")) and not is_input_error(RuntimeError("x"))
    assert one_line(FileNotFoundError(2, "No such file or directory", "a.json")) == "[Errno 2] No such file or " \
        "directory: 'a.json'"  # fmt: skip
    assert one_line(PermissionError(13, "Permission denied")) == "[Errno 13] Permission denied"
    assert one_line(ValueError("two\nlines")) == "two lines"
    assert one_line(MemoryError()).startswith("out of memory (MemoryError)")


def test_argparse_types():
    assert integer(1)("3") == 3 and number(0, 100)("12.5") == 12.5
    for parse, text in ((integer(1), "0"), (integer(0, 5), "6"), (integer(), "1.5"), (number(0, 1), "inf")):
        with pytest.raises(argparse.ArgumentTypeError):
            parse(text)


def test_output_checks(tmp_path):
    (tmp_path / "f").write_text("")
    assert output_file(tmp_path / "new" / "a.json", "--out") == tmp_path / "new" / "a.json"
    assert output_folder(tmp_path / "new" / "run", "--out") == tmp_path / "new" / "run"
    with pytest.raises(UsageError, match="is a file"):
        output_folder(tmp_path / "f", "--out")
    with pytest.raises(UsageError, match="cannot be created"):
        output_file(tmp_path / "f" / "a.json", "--out")


def test_a_missing_optional_extra_is_the_users_to_install_exit_2(tmp_path, capsys, monkeypatch):
    from occkit.data.corruptions import _image_transform
    from occkit.errors import MissingDependencyError
    from occkit.onnx_runtime import require

    for module in ("open3d", "albumentations", "onnxruntime"):
        monkeypatch.setitem(sys.modules, module, None)  # an import of it fails, installed or not
    (tmp_path / "data").mkdir()
    argv = ["label", "--root", str(tmp_path / "data"), "--version", "v1.0-synth", "--out", str(tmp_path / "labels"),
            "--densify", "poisson"]  # fmt: skip
    assert main(argv) == 2
    line = _error_line(capsys, "label")
    assert "densify=poisson needs open3d" in line and 'pip install -e ".[labels]"' in line
    assert not (tmp_path / "labels").exists()
    with pytest.raises(MissingDependencyError, match=r"an image corruption needs albumentations .*\[robustness\]"):
        _image_transform("brightness", {"brightness": 0.1}, seed=0)
    with pytest.raises(MissingDependencyError, match="ONNX export needs onnxruntime"):
        require("onnxruntime")
    assert is_input_error(MissingDependencyError("x")) and issubclass(MissingDependencyError, ImportError)
