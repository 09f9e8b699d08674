"""Scene splits: the official nuScenes lists, custom split files, and the one to use for a dataset.

The official lists (train 700, val 150, test 150, mini_train 8, mini_val 2 scene names) are those of
nuscenes-devkit's ``nuscenes/utils/splits.py``, shipped as ``occkit/data/nuscenes_splits.json``.
A dataset root with a ``splits.json`` (occkit's synthetic datasets write one) uses that file instead.
"""

from __future__ import annotations

import functools
import json
from importlib import resources
from pathlib import Path
from typing import Any

__all__ = ["OFFICIAL_SPLITS", "VERSION_SPLITS", "scene_split", "read_split_file", "split_scenes"]

#: Names of the official scene lists.
OFFICIAL_SPLITS = ("train", "val", "test", "mini_train", "mini_val")

#: nuScenes version -> split name -> official list. ``train`` / ``val`` of v1.0-mini are its mini lists.
VERSION_SPLITS: dict[str, dict[str, str]] = {
    "v1.0-trainval": {"train": "train", "val": "val"},
    "v1.0-mini": {"train": "mini_train", "val": "mini_val", "mini_train": "mini_train", "mini_val": "mini_val"},
    "v1.0-test": {"test": "test"},
}


@functools.cache
def _official() -> dict[str, tuple[str, ...]]:
    text = resources.files("occkit.data").joinpath("nuscenes_splits.json").read_text(encoding="utf-8")
    return {name: tuple(scenes) for name, scenes in json.loads(text).items()}


def scene_split(name: str) -> list[str]:
    """Scene names of an official split, e.g. ``scene_split("val")`` -> 150 names ``scene-0003``, ...

    Raises:
        ValueError: ``name`` is not one of :data:`OFFICIAL_SPLITS`.
    """
    splits = _official()
    if name not in splits:
        raise ValueError(f"unknown nuScenes split {name!r}; official splits: {', '.join(OFFICIAL_SPLITS)}")
    return list(splits[name])


def read_split_file(path: str | Path, split: str | None = None) -> list[str]:
    """Scene names from a custom split file.

    The file is a JSON list of scene names, or an object of split name -> list (the synthetic ``splits.json``:
    ``{"train": [...], "val": [...]}``), from which ``split`` picks one.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not JSON, not of either form, ``split`` missing or unknown for an object (the message lists the
            splits the file has), or given for a plain list.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"split file {path} does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: not valid JSON ({error})") from None
    if isinstance(data, list):
        if split is not None:
            raise ValueError(f"{path} is one list of scenes, not splits by name; it has no split {split!r}")
        return _scene_names(data, str(path))
    if isinstance(data, dict):
        if split not in data:
            wanted = "no split given" if split is None else f"no split {split!r}"
            raise ValueError(f"{path}: {wanted}; the file has {', '.join(map(repr, data)) or 'none'}")
        return _scene_names(data[split], f"{path}: {split}")
    raise ValueError(f"{path}: expected a list of scene names or an object of split -> list, got {type(data).__name__}")


def _scene_names(value: Any, where: str) -> list[str]:
    if not isinstance(value, list) or not all(isinstance(name, str) for name in value):
        raise ValueError(f"{where}: expected a list of scene names (strings)")
    return value


def split_scenes(root: str | Path, version: str, split: str) -> list[str]:
    """Scene names of ``split`` for the dataset at ``root/version``.

    ``<root>/splits.json`` decides when it exists (synthetic data); otherwise the official lists for the version
    (:data:`VERSION_SPLITS`): v1.0-trainval -> train / val, v1.0-mini -> mini_train / mini_val (also as train /
    val), v1.0-test -> test.

    Raises:
        ValueError: ``split`` is not valid here; the message lists the valid names.
    """
    custom = Path(root) / "splits.json"
    if custom.is_file():
        return read_split_file(custom, split)
    if version not in VERSION_SPLITS:
        raise ValueError(
            f"{custom} does not exist and {version!r} has no official splits "
            f"(those are for {', '.join(VERSION_SPLITS)}); pass a split file instead"
        )
    names = VERSION_SPLITS[version]
    if split not in names:
        raise ValueError(f"unknown split {split!r} for {version}; valid: {', '.join(names)}")
    return scene_split(names[split])
