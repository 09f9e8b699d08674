"""Names and relative paths from data files: what passes, what is refused, and that errors name where."""

from __future__ import annotations

from pathlib import Path

import pytest

from occkit.data.names import (
    UnsafeNameError,
    folder_name,
    is_safe_name,
    is_safe_relative_path,
    path_under,
    safe_name,
    safe_relative_path,
)
from occkit.errors import is_input_error

NAMES = ["0" * 32, "e93e98b63d3b40209056d129dc53ceee", "scene-0061", "scene_1.v2", "A", "a" * 128]
NOT_NAMES = ["", "..", ".", ".hidden", "-x", "_x", "a/b", "../../escape_tok", "/abs", "a\\b", "tok\n", "a b",
             "a" * 129, "é", None, 5, ["a"]]  # fmt: skip
PATHS = ["samples/CAM_FRONT/a.jpg", "gts/scene-0001/tok/labels.npz", "a", "./samples/x", "a..b/c", "a/..b"]
NOT_PATHS = ["", "/etc/passwd", "//server/share", "C:/x", "c:x", "..", "../x", "a/../../x", "a/..", "a\\..\\x",
             "a\0b", None, 3]  # fmt: skip


@pytest.mark.parametrize("name", NAMES)
def test_safe_names(name):
    assert is_safe_name(name) and safe_name(name, "here") == name


@pytest.mark.parametrize("name", NOT_NAMES)
def test_unsafe_names_name_where(name):
    assert not is_safe_name(name)
    with pytest.raises(UnsafeNameError, match=r"^v1\.0-mini/sample\.json: record 3\.token: .* is not a safe name"):
        safe_name(name, "v1.0-mini/sample.json: record 3.token")
    with pytest.raises(KeyError):
        safe_name(name, "here", KeyError)  # the caller's error type


@pytest.mark.parametrize("path", PATHS)
def test_safe_relative_paths(path):
    assert is_safe_relative_path(path) and safe_relative_path(path, "here") == path
    assert path_under("/data/root", path, "here") == Path("/data/root") / path


@pytest.mark.parametrize("path", NOT_PATHS)
def test_unsafe_relative_paths_name_where(path):
    assert not is_safe_relative_path(path)
    with pytest.raises(UnsafeNameError, match=r"^index\.json: record 1\.lidar_path: ") as error:
        safe_relative_path(path, "index.json: record 1.lidar_path")
    assert is_input_error(error.value)
    with pytest.raises(UnsafeNameError, match="^--out: "):
        path_under("/data/root", path, "--out")


def test_path_under_for_a_token_file_name(tmp_path):
    out = tmp_path / "preds"
    assert path_under(out, safe_name("abc", "token") + ".npz", "--out") == out / "abc.npz"
    with pytest.raises(UnsafeNameError):
        path_under(out, safe_name("../../escape_tok", "token") + ".npz", "--out")
    assert path_under(out, Path("sub/x.npz"), "--out") == out / "sub" / "x.npz"


@pytest.mark.parametrize(("label", "folder"), [
    ("da_occ_tiny - BEV vertical DAC", "da_occ_tiny_-_BEV_vertical_DAC"),
    ("da_occ_tiny + 1 frame", "da_occ_tiny_-_1_frame"),
    ("daocc_tiny camera only", "daocc_tiny_camera_only"),
    ("all sweeps + Poisson", "all_sweeps_-_Poisson"),
    (" -x.y/z é ", "x-y-z"),
])  # fmt: skip
def test_folder_names_of_labels(label, folder):
    assert folder_name(label) == folder and is_safe_name(folder)


@pytest.mark.parametrize("label", ["", " - ", "a" * 129])
def test_a_label_with_no_folder_name_is_refused(label):
    with pytest.raises(UnsafeNameError, match="folder for"):
        folder_name(label)
