"""Writers of occupancy ground truth, byte for byte reproducible: Occ3D and OpenOcc v2 ``labels.npz``, SurroundOcc
sparse ``.npy``.

Shared by the synthetic world (:mod:`occkit.sim`) and ``occkit label`` (:mod:`occkit.labeling`); the readers, which
check what they read, are in :mod:`occkit.data.labels`.
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from occkit.classes import IGNORE_INDEX, OCC3D_TO_OPENOCC

__all__ = ["save_npz", "write_occ3d_labels", "occ3d_to_openocc", "write_openocc_labels", "write_surroundocc_labels"]


def save_npz(path: str | Path, compressed: bool = True, **arrays: np.ndarray) -> None:
    """``numpy.savez_compressed`` with a fixed timestamp in the zip entries, so equal arrays give equal bytes
    (``numpy.savez`` stamps the current time into every archive)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    method = zipfile.ZIP_DEFLATED if compressed else zipfile.ZIP_STORED
    with zipfile.ZipFile(buffer, "w", compression=method) as archive:
        for name, array in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = method
            archive.writestr(info, member.getvalue())
    path.write_bytes(buffer.getvalue())


def write_occ3d_labels(
    path: str | Path,
    semantics: np.ndarray,
    mask_lidar: np.ndarray,
    mask_camera: np.ndarray,
    flow: np.ndarray | None = None,
    instances: np.ndarray | None = None,
    instance_tokens: dict[int, str] | None = None,
) -> None:
    """Write an Occ3D ``labels.npz`` as the benchmark ships it: the three arrays as uint8 ``(X, Y, Z)``, byte for byte
    reproducible; with ``flow``, also the occupancy flow as the CVPR 2024 challenge's OpenOcc v2 files carry it
    (key ``flow``, float32 ``(X, Y, Z, 2)`` ``vx, vy`` in m/s in the labels' frame); with ``instances``, the
    panoptic instance id of every voxel (key ``instances``, int32 ``(X, Y, Z)``, 0 for stuff and free space) and
    ``instance_tokens`` id -> nuScenes instance token, empty for an object the sample does not annotate (keys
    ``instance_ids`` int32 ``(K,)`` and ``instance_tokens`` ``(K,)`` strings, ascending ids)."""
    arrays = {"semantics": np.asarray(semantics, np.uint8), "mask_lidar": np.asarray(mask_lidar, np.uint8),
              "mask_camera": np.asarray(mask_camera, np.uint8)}  # fmt: skip
    if flow is not None:
        flow = np.asarray(flow, np.float32)
        if flow.shape != (*arrays["semantics"].shape, 2):
            raise ValueError(f"{path}: flow must have shape {(*arrays['semantics'].shape, 2)}, got {flow.shape}")
        arrays["flow"] = flow
    if instances is not None:
        instances = np.asarray(instances, np.int32)
        if instances.shape != arrays["semantics"].shape:
            raise ValueError(f"{path}: instances must have shape {arrays['semantics'].shape}, got {instances.shape}")
        tokens = dict(sorted((instance_tokens or {}).items()))
        present = set(np.unique(instances[instances > 0]).tolist())
        if present - tokens.keys():
            raise ValueError(f"{path}: instances {sorted(present - tokens.keys())[:5]} have no instance token")
        arrays["instances"] = instances
        arrays["instance_ids"] = np.array(list(tokens), dtype=np.int32)
        arrays["instance_tokens"] = np.array(list(tokens.values()), dtype="<U64")
    save_npz(path, **arrays)


def occ3d_to_openocc(semantics: np.ndarray) -> np.ndarray:
    """Occ3D class ids (any shape) as OpenOcc v2's, uint8 (:data:`~occkit.classes.OCC3D_TO_OPENOCC`: by class name,
    ``others`` becoming free); ignored voxels (255) stay ignored."""
    table = np.full(256, IGNORE_INDEX, np.uint8)
    table[: len(OCC3D_TO_OPENOCC)] = OCC3D_TO_OPENOCC
    return table[np.asarray(semantics, np.uint8)]


def write_openocc_labels(path: str | Path, semantics: np.ndarray, flow: np.ndarray) -> None:
    """Write an OpenOcc v2 ``labels.npz`` as the CVPR 2024 challenge ships it: ``semantics`` uint8 ``(X, Y, Z)`` in
    OpenOcc's ids (16 = free) and ``flow`` float32 ``(X, Y, Z, 2)`` ``vx, vy`` in m/s, no visibility mask."""
    semantics = np.asarray(semantics, np.uint8)
    flow = np.asarray(flow, np.float32)
    if flow.shape != (*semantics.shape, 2):
        raise ValueError(f"{path}: flow must have shape {(*semantics.shape, 2)}, got {flow.shape}")
    save_npz(path, semantics=semantics, flow=flow)


def write_surroundocc_labels(path: str | Path, rows: np.ndarray) -> None:
    """Write SurroundOcc sparse labels: int64 ``(N, 4)`` rows ``(x, y, z, label)`` as a ``.npy`` file."""
    rows = np.asarray(rows)
    if rows.ndim != 2 or rows.shape[1] != 4:
        raise ValueError(f"{path}: SurroundOcc rows must have shape (N, 4), got {rows.shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, rows.astype(np.int64))
