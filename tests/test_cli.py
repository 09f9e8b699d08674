"""The occkit command line: help, version and the info report."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from occkit import __version__
from occkit.cli import COMMANDS, main
from occkit.commands.common import LABEL_SPACE_NAMES
from occkit.label_space import LABEL_SPACES


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"occkit {__version__}"


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "usage: occkit" in capsys.readouterr().out


def test_help_imports_no_heavy_library():
    # `occkit --help` must answer at once: the CLI module may not pull torch or spconv in.
    code = "import sys, occkit.cli; print(sorted(m for m in ('torch', 'spconv', 'numpy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_cli_names_every_label_space():
    assert tuple(LABEL_SPACES) == LABEL_SPACE_NAMES


def test_entry_point_runs():
    # pip installs the console script beside the interpreter of the environment.
    script = Path(sys.executable).with_name("occkit")
    result = subprocess.run([str(script), "--version"], capture_output=True, text=True)
    assert result.returncode == 0 and result.stdout.strip() == f"occkit {__version__}"


def test_info_prints_and_writes_json(tmp_path, capsys):
    path = tmp_path / "env" / "info.json"
    assert main(["info", "--json", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"occkit {__version__}" in out and "occ3d" in out and "shape [200, 200, 16]" in out
    report = json.loads(path.read_text())
    assert report["grids"]["occ3d"]["shape"] == [200, 200, 16]
    assert report["taxonomies"]["occ3d"]["classes"][17] == "free"
    assert "torch" in report["packages"]
    assert report["sparse_conv"]["available"] is True
    # Each shipped model with where its run stands (its card's notes).
    from occkit.shipped import card

    notes = report["shipped_weights"]["da_occ_tiny"]["notes"]
    assert notes == card("da_occ_tiny").notes and notes.startswith("converged") and notes in out
