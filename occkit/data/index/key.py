"""What an index built from the tables depends on, as one digest (:func:`tables_key`): the key of the dataset's index
cache, which is rebuilt when it differs.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator
from pathlib import Path

from occkit import __version__
from occkit.data.index.builder import _labelled_tokens
from occkit.data.index.files import INDEX_FORMAT
from occkit.nuscenes import TABLE_NAMES


def _label_listing(root: Path) -> Iterator[str]:
    """``scene/token`` of every Occ3D ``labels.npz`` under ``root/gts``, in sorted order (an index's ``occ_path``
    values come from this listing, so its cache key covers it: labels added or removed after the cache was built)."""
    try:
        scenes = sorted(entry.name for entry in os.scandir(root / "gts") if entry.is_dir())
    except (FileNotFoundError, NotADirectoryError):
        return
    for scene in scenes:
        for token in sorted(_labelled_tokens(root / "gts" / scene)):
            yield f"{scene}/{token}"


def tables_key(root: str | Path, version: str, max_sweeps: int) -> str:
    """What an index built from ``root/version`` depends on, as one digest: the index format, the occkit version,
    ``max_sweeps``, the size and SHA-256 of each of the 13 table files (their content: modification times are not
    trusted, a file can change and keep an old one), and which key frames have an Occ3D ``labels.npz`` under
    ``root/gts`` (each record's ``occ_path``). The dataset's index cache stores it and is rebuilt when it differs.
    Hashing reads every table once: about 0.7 s per GB on one core when the files are in the page cache; the label
    listing is one directory listing per scene and one stat per frame.
    """
    folder = Path(root) / version
    digest = hashlib.sha256(f"{INDEX_FORMAT}\0{__version__}\0max_sweeps={max_sweeps}\n".encode())
    buffer = bytearray(1 << 20)
    view = memoryview(buffer)
    for name in TABLE_NAMES:
        table = hashlib.sha256()
        size = 0
        try:
            with open(folder / f"{name}.json", "rb", buffering=0) as stream:
                while count := stream.readinto(buffer):
                    table.update(view[:count])
                    size += count
        except FileNotFoundError:
            size = -1  # building fails and names the table
        digest.update(f"{name}\0{size}\0{table.hexdigest()}\n".encode())
    labels = hashlib.sha256()
    for entry in _label_listing(Path(root)):
        labels.update(f"{entry}\n".encode())
    digest.update(f"labels\0{labels.hexdigest()}\n".encode())
    return f"sha256:{digest.hexdigest()}"
