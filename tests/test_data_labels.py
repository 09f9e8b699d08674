"""Ground-truth readers: Occ3D labels.npz and SurroundOcc sparse .npy, with errors that name file and sample."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from occkit.data.labels import LabelError, read_occ3d_labels, read_surroundocc_labels
from occkit.geometry.grid import VoxelGrid

SMALL = VoxelGrid((-1.6, -1.6, -0.4, 1.6, 1.6, 0.4), 0.4)  # 8 x 8 x 2


def _write(path, **arrays):
    np.savez_compressed(path, **arrays)
    return path


def _volume(rng, high=18):
    return rng.integers(0, high, SMALL.shape, dtype=np.uint8)


def test_occ3d_round_trip_with_bool_masks(tmp_path):
    rng = np.random.default_rng(0)
    semantics, lidar, camera = _volume(rng), _volume(rng, 2), _volume(rng, 2)
    path = _write(tmp_path / "labels.npz", semantics=semantics, mask_lidar=lidar, mask_camera=camera)
    labels = read_occ3d_labels(path, "tok", SMALL)
    assert np.array_equal(labels.semantics, semantics)
    assert labels.mask_camera.dtype == bool and np.array_equal(labels.mask_camera, camera == 1)
    assert np.array_equal(labels.mask_lidar, lidar == 1)


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        ({"semantics": np.zeros((8, 8, 2), np.uint8)}, "has no mask_lidar, mask_camera"),
        (
            {k: np.zeros((8, 8), np.uint8) for k in ("semantics", "mask_lidar", "mask_camera")},
            r"semantics has shape \(8, 8\) but expected \(8, 8, 2\)",
        ),
        (
            {
                "semantics": np.zeros((8, 8, 2), np.float32),
                "mask_lidar": np.zeros((8, 8, 2), np.uint8),
                "mask_camera": np.zeros((8, 8, 2), np.uint8),
            },
            "semantics has dtype float32 but expected uint8",
        ),
        (
            {
                "semantics": np.full((8, 8, 2), 40, np.uint8),
                "mask_lidar": np.zeros((8, 8, 2), np.uint8),
                "mask_camera": np.zeros((8, 8, 2), np.uint8),
            },
            r"class ids \[40\] beyond 0..17",
        ),
        (
            {
                "semantics": np.zeros((8, 8, 2), np.uint8),
                "mask_lidar": np.full((8, 8, 2), 2, np.uint8),
                "mask_camera": np.zeros((8, 8, 2), np.uint8),
            },
            r"mask_lidar holds values \[2\], not 0/1",
        ),
    ],
)
def test_occ3d_errors_name_file_and_sample(tmp_path, arrays, message):
    path = _write(tmp_path / "labels.npz", **arrays)
    with pytest.raises(LabelError, match=f"sample tok-1: .*labels.npz: .*{message}"):
        read_occ3d_labels(path, "tok-1", SMALL)


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(LabelError, match="sample t: .*absent.npz: label file not found"):
        read_occ3d_labels(tmp_path / "absent.npz", "t", SMALL)
    (tmp_path / "bad.npz").write_bytes(b"not a zip archive")
    with pytest.raises(LabelError, match="bad.npz: cannot read labels"):
        read_occ3d_labels(tmp_path / "bad.npz", "t", SMALL)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.binary(min_size=0, max_size=300))
def test_occ3d_reader_fuzz_raises_only_label_errors(tmp_path, payload):
    path = tmp_path / "fuzz.npz"
    path.write_bytes(payload)
    with pytest.raises(LabelError):
        read_occ3d_labels(path, "fuzz", SMALL)


def test_surroundocc_sparse_to_dense(tmp_path):
    rows = np.array([[0, 0, 0, 4], [7, 7, 1, 16], [3, 2, 1, 0]], dtype=np.int64)
    np.save(tmp_path / "a.npy", rows)
    semantics = read_surroundocc_labels(tmp_path / "a.npy", "s", SMALL).semantics
    assert semantics[0, 0, 0] == 4 and semantics[7, 7, 1] == 16 and semantics[3, 2, 1] == 255
    assert (semantics == 0).sum() == semantics.size - 3


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        (np.zeros((3, 3), np.int64), r"expected integer rows \(N, 4\)"),
        (np.zeros((3, 4), np.float32), r"expected integer rows \(N, 4\)"),
        (np.array([[8, 0, 0, 1]]), "1 rows index outside"),
        (np.array([[0, 0, 0, 17]]), r"labels must be 0..16, got \[17\]"),
    ],
)
def test_surroundocc_errors(tmp_path, rows, message):
    np.save(tmp_path / "b.npy", rows)
    with pytest.raises(LabelError, match=f"sample s: .*b.npy: {message}"):
        read_surroundocc_labels(tmp_path / "b.npy", "s", SMALL)
