"""Every on-disk cache is keyed on every input its value depends on: change one input, and the cache misses.

The dataset's index cache (``<root>/.occkit/occkit-index-<version>-<max_sweeps>.npz``, or under ``~/.cache/occkit``)
holds the records built from the nuScenes tables and the Occ3D label listing (each record's ``occ_path``). Its key,
:func:`~occkit.data.index.tables_key`, covers the index format, occkit's version, ``max_sweeps`` (in the file name
too), each table's content and the label listing. The split lists have no disk cache (the packaged official lists
are read once per process; a root's ``splits.json`` is read on every use).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.data.index import key as index_key
from occkit.data.index import read_index_header, tables_key
from occkit.sim.generate import SimConfig, simulate_dataset

VERSION = "v1.0-synth"


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("caches") / "world"
    simulate_dataset(SimConfig(scenes=2, frames=2, seed=3, image_size=(64, 36), cameras=("CAM_FRONT",)), root)
    return root


@pytest.fixture
def data(world, tmp_path) -> Path:
    """A private copy of the world's tables and labels (the tests edit them)."""
    shutil.copytree(world / VERSION, tmp_path / "data" / VERSION)
    shutil.copytree(world / "gts", tmp_path / "data" / "gts")
    return tmp_path / "data"


def _records(root: Path, sweeps: int = 0):
    return OccupancyDataset(DatasetConfig(root=str(root), split="all", cameras=(), sweeps=sweeps)).records


def test_the_index_key_changes_with_each_input(data, monkeypatch):
    key = tables_key(data, VERSION, 0)
    assert tables_key(data, VERSION, 0) == key  # a pure function of its inputs
    assert tables_key(data, VERSION, 1) != key  # max_sweeps
    with monkeypatch.context() as patch:
        patch.setattr(index_key, "INDEX_FORMAT", "occkit-index/999")
        assert tables_key(data, VERSION, 0) != key  # the index format
    with monkeypatch.context() as patch:
        patch.setattr(index_key, "__version__", "999.0")
        assert tables_key(data, VERSION, 0) != key  # occkit's version
    for table in ("scene", "sample_data", "ego_pose"):  # a table's content, size and modification time kept
        path = data / VERSION / f"{table}.json"
        stat, text = path.stat(), path.read_text()
        path.write_text(text.replace("0", "1", 1))
        os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
        assert path.stat().st_size == stat.st_size and tables_key(data, VERSION, 0) != key, table
        path.write_text(text)
        assert tables_key(data, VERSION, 0) == key
    labels = next((data / "gts").rglob("labels.npz"))
    labels.rename(labels.with_name("moved.npz"))
    assert tables_key(data, VERSION, 0) != key  # a frame's labels removed
    labels.with_name("moved.npz").rename(labels)
    assert tables_key(data, VERSION, 0) == key  # and put back


def test_labels_added_after_the_cache_was_built_are_indexed(data):
    labels = next((data / "gts").rglob("labels.npz"))
    token = labels.parent.name
    labels.rename(labels.with_name("moved.npz"))  # the labels of one frame are not there yet
    before = {r.token: r.occ_path for r in _records(data)}
    cache = data / ".occkit" / f"occkit-index-{VERSION}-0.npz"
    assert cache.is_file() and before[token] is None and sum(p is None for p in before.values()) == 1
    labels.with_name("moved.npz").rename(labels)  # the labels arrive; the tables are unchanged
    after = {r.token: r.occ_path for r in _records(data)}
    assert after[token] == f"gts/{labels.parent.parent.name}/{token}/labels.npz"
    assert read_index_header(cache)["tables_key"] == tables_key(data, VERSION, 0)  # rebuilt under the new key


def test_max_sweeps_has_a_cache_of_its_own(data):
    assert all(len(r.sweeps) == 0 for r in _records(data, sweeps=0))
    assert any(len(r.sweeps) > 0 for r in _records(data, sweeps=2))
    assert {path.name for path in (data / ".occkit").iterdir()} >= {f"occkit-index-{VERSION}-0.npz",
                                                                     f"occkit-index-{VERSION}-2.npz"}


def test_the_demo_reuses_only_its_own_world_and_refuses_another_in_one_line(tmp_path, capsys):
    """The demo reuses the world in --data only when it is the demo's; another is refused before any work and
    nothing is written into it."""
    from occkit.cli import main
    from occkit.config import save_config
    from occkit.demo import DEMO_WORLD, _differs_from_demo_world
    from occkit.sim.config import SimConfig
    from occkit.sim.generate import DATASET_MARKER

    save_config(SimConfig(**DEMO_WORLD), tmp_path / DATASET_MARKER)
    assert _differs_from_demo_world(tmp_path) == ""
    save_config(SimConfig(**{**DEMO_WORLD, "scenes": 2, "seed": 0}), tmp_path / DATASET_MARKER)
    assert _differs_from_demo_world(tmp_path) == "scenes 2 instead of 10, seed 0 instead of 1"
    before = sorted(tmp_path.iterdir())
    assert main(["demo", "--data", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is not the demo's world (scenes 2 instead of 10, seed 0 instead of 1)" in err
    assert sorted(tmp_path.iterdir()) == before
    (tmp_path / DATASET_MARKER).unlink()
    assert _differs_from_demo_world(tmp_path) == f"{tmp_path} holds no readable {DATASET_MARKER}"
