"""The per-case cache of ``occkit robustness``: ``OUT/cases/<case>.json``, each case's scores and their fingerprint.

A cached case is reused only when its fingerprint equals the one the run would give it now. The fingerprint holds
everything the scores depend on:

- the model: the SHA-256 of its file (a checkpoint: weights and the saved experiment; a weights file, with the zoo
  entry that runs it);
- the data it is scored on: the evaluation dataset's settings (root, label space and label folder, cameras, sweeps,
  image transform, ...), the nuScenes tables (:func:`~occkit.data.index.tables_key`), a prebuilt index file's
  SHA-256, the split's key frames in order, and the **content** of every label file of the split;
- the case: the corruption, its level and that level's parameters (and albumentations' version, whose code makes
  the pixels of the image corruptions);
- the seed of the corruptions' draws, whether RayIoU is scored, and the occkit version.

The label files are hashed, not merely listed with their sizes and modification times: an uncompressed
``labels.npz`` has the same size whatever its classes, and ``cp -p``, ``rsync -a`` or unpacking an archive gives a
file whose content is new the modification time of the old one. Hashing reads each label file once per run, while
every case computed reads all of them again, so it costs less than one case (about 0.7 s per GB when the files are
in the page cache).

The camera images and LiDAR sweeps are not fingerprinted (tens of GB on nuScenes): a run over data whose sensor
files were replaced in place under the same tables must be given a fresh ``--out``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

from occkit import __version__
from occkit.data.corruptions import CORRUPTIONS
from occkit.data.dataset import OccupancyDataset
from occkit.data.index import tables_key
from occkit.errors import InputError
from occkit.outputs import file_digest, write_atomic
from occkit.robustness.suite import Case

if TYPE_CHECKING:  # the engine is imported by the run, not by the cache
    from occkit.model_source import ModelSource

__all__ = ["CASES_FOLDER", "cache_context", "case_fingerprint", "case_path", "check_case_paths", "read_cached",
           "write_case", "labels_digest"]  # fmt: skip

#: Where each case's scores are cached, inside the output folder.
CASES_FOLDER = "cases"

#: Dataset settings a run sets itself: they are in the fingerprint as the case, its parameters and the seed.
_RUN_SETTINGS = ("corruption", "corruption_severity", "seed")


def labels_digest(dataset: OccupancyDataset) -> str:
    """One SHA-256 over the label file of every key frame of ``dataset``, in order: each file's path and content
    (a missing file counts as missing: scoring it fails, or skips the frame, as the dataset says)."""
    digest = hashlib.sha256()
    for record in dataset.records:
        path = dataset.label_path(record)
        digest.update(f"{record.token}\0{path}\0".encode())
        try:
            content = file_digest(path).hexdigest()
        except FileNotFoundError:
            content = "missing"
        digest.update(f"{content}\n".encode())
    return f"sha256:{digest.hexdigest()}"


def _library_version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def cache_context(
    model: ModelSource | str | Path, dataset: OccupancyDataset, seed: int, rayiou: bool
) -> dict[str, Any]:
    """What every case of a run depends on (see the module's docstring): ``model`` (a checkpoint's path, or where
    the model comes from) scored on the clean ``dataset`` (the evaluation split, no corruption), with the
    corruptions' ``seed``, RayIoU or not."""
    model_file, entry = (Path(model), None) if isinstance(model, (str, Path)) else (model.file, model.entry)
    config = dataset.config
    root = Path(config.root).resolve()
    settings = {key: value for key, value in dataclasses.asdict(config).items() if key not in _RUN_SETTINGS}
    settings["root"] = str(root)
    tokens = hashlib.sha256("\n".join(f"{r.scene}/{r.token}" for r in dataset.records).encode()).hexdigest()
    context = {
        "model_sha256": file_digest(model_file).hexdigest(),
        "model_entry": entry,
        "data": str(root),
        "dataset": settings,
        "tables": tables_key(root, config.version, 0),
        "index_sha256": None if config.index is None else file_digest(Path(config.index)).hexdigest(),
        "split": config.split,
        "frames": len(dataset),
        "key_frames_sha256": tokens,
        "labels": labels_digest(dataset) if config.occupancy else None,
        "seed": seed,
        "rayiou": rayiou,
        "occkit": __version__,
    }
    return json.loads(json.dumps(context))  # tuples -> lists, as read back from a file


def case_fingerprint(context: dict[str, Any], case: Case) -> dict[str, Any]:
    """What a case's scores depend on: the run's ``context`` (:func:`cache_context`) and the case itself."""
    fingerprint = {**context, "case": case.key}
    if case.corruption is not None:
        corruption = CORRUPTIONS[case.corruption]
        fingerprint["params"] = corruption.levels[case.severity - 1]
        if corruption.family == "images":  # the pixels are the library's
            fingerprint["albumentations"] = _library_version("albumentations")
    return json.loads(json.dumps(fingerprint))


def case_path(cases_folder: Path, case: Case) -> Path:
    """The file of ``case`` in the cache folder."""
    return cases_folder / f"{case.key}.json"


def check_case_paths(cases_folder: Path, cases: list[Case]) -> None:
    """Refuse, before any case is computed, a cache folder or case file that something else stands in for (a file
    where the folder goes, a folder where a case's file goes): its scores could never be written.

    Raises:
        InputError: naming the path and what to do.
    """
    if cases_folder.exists() and not cases_folder.is_dir():
        raise InputError(f"{cases_folder} is a file where occkit robustness keeps its per-case cache (a folder): "
                         "move it away, or choose another --out")  # fmt: skip
    for case in cases:
        path = case_path(cases_folder, case)
        if path.exists() and not path.is_file():
            kind = "a folder" if path.is_dir() else "not a regular file"
            raise InputError(f"{path} is {kind}, where occkit robustness writes the scores of case {case.label}: "
                             "remove it, or choose another --out")  # fmt: skip


def read_cached(path: Path, fingerprint: dict) -> dict | None:
    """The cached result of a case when ``path`` holds one under ``fingerprint``; None when it is absent, unreadable,
    of other inputs, or not a case file at all (then the case is computed again and the file replaced)."""
    try:
        entry = json.loads(path.read_text())
    except (OSError, ValueError):
        return None  # absent (a kill before the rename leaves no half file: it is written atomically)
    if not isinstance(entry, dict) or entry.get("fingerprint") != fingerprint:
        return None
    result = entry.get("result")
    if not isinstance(result, dict) or not isinstance(result.get("seconds"), (int, float)) or "miou" not in result:
        return None
    return result


def write_case(path: Path, fingerprint: dict, result: dict) -> None:
    """Store a case's ``result`` under its ``fingerprint``, atomically."""
    write_atomic(path, json.dumps({"fingerprint": fingerprint, "result": result}, indent=2) + "\n")
