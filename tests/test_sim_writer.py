"""nuScenes writer helpers: tokens, static tables, point files and reproducible npz archives."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from occkit.classes import NUSCENES_TO_OCC3D
from occkit.label_files import save_npz
from occkit.sim.writer import make_token, static_tables, write_points


def test_tokens_are_32_hex_and_pure():
    token = make_token("v1.0-synth", "sample", 3)
    assert len(token) == 32 and int(token, 16) >= 0
    assert token == make_token("v1.0-synth", "sample", 3) != make_token("v1.0-synth", "sample", 4)


def test_static_tables_follow_nuscenes():
    tables = static_tables("v1.0-synth")
    names = [row["name"] for row in tables["category"]]
    assert names == list(NUSCENES_TO_OCC3D) and tables["category"][17]["index"] == 17
    assert [row["token"] for row in tables["visibility"]] == ["1", "2", "3", "4"]
    assert {row["channel"] for row in tables["sensor"]} >= {"CAM_FRONT", "CAM_BACK_LEFT", "LIDAR_TOP"}
    assert len({row["token"] for rows in tables.values() for row in rows}) == sum(len(r) for r in tables.values())


def test_points_round_trip_as_float32_rows(tmp_path):
    points = np.arange(20, dtype=np.float64).reshape(4, 5)
    write_points(tmp_path / "a.pcd.bin", points)
    assert np.array_equal(np.fromfile(tmp_path / "a.pcd.bin", dtype=np.float32).reshape(-1, 5), points)
    with pytest.raises(ValueError, match=r"b.pcd.bin: LiDAR points must have shape \(N, 5\)"):
        write_points(tmp_path / "b.pcd.bin", points[:, :4])


def test_npz_is_byte_identical_over_time_and_loads(tmp_path):
    semantics = np.random.default_rng(0).integers(0, 18, (20, 20, 4), dtype=np.uint8)
    save_npz(tmp_path / "a.npz", semantics=semantics, mask=semantics > 3)
    save_npz(tmp_path / "b.npz", semantics=semantics, mask=semantics > 3)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    # numpy.savez stamps the wall clock into each member; ours carry a fixed date, so bytes never depend on time.
    with zipfile.ZipFile(tmp_path / "a.npz") as archive:
        assert {info.date_time for info in archive.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    with np.load(tmp_path / "a.npz") as loaded:
        assert np.array_equal(loaded["semantics"], semantics) and loaded["mask"].dtype == bool
