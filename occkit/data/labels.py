"""Readers of occupancy ground truth: Occ3D ``labels.npz`` and SurroundOcc sparse ``.npy`` (the writers are in
:mod:`occkit.label_files`).

Both validate what they read and name the file and sample in every error, because label files are where
silent mistakes (a wrong shape, a float mask, a SurroundOcc file read as Occ3D) cost a training run.
:func:`label_file` and :func:`read_labels` choose the file and the reader from a
:class:`~occkit.label_space.LabelSpace`.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occkit.classes import IGNORE_INDEX, OCC3D, SURROUNDOCC
from occkit.data.names import path_under, safe_name
from occkit.geometry.grid import OCC3D_GRID, SURROUNDOCC_GRID, VoxelGrid
from occkit.label_space import LabelSpace

__all__ = ["LabelError", "OccupancyLabels", "read_occ3d_labels", "read_surroundocc_labels", "label_file",
           "read_labels"]


class LabelError(ValueError):
    """A label file is missing, corrupt or has the wrong content; the message names the file and sample."""


@dataclass(frozen=True)
class OccupancyLabels:
    """Dense labels of one key frame.

    Attributes:
        semantics: ``(X, Y, Z)`` uint8 class ids (255 = ignore).
        mask_camera: ``(X, Y, Z)`` bool, or None when the format has no visibility masks.
        mask_lidar: ``(X, Y, Z)`` bool, or None.
        flow: ``(X, Y, Z, 2)`` float32 occupancy flow ``vx, vy`` (m/s, labels' frame), or None when not asked for.
    """

    semantics: np.ndarray
    mask_camera: np.ndarray | None = None
    mask_lidar: np.ndarray | None = None
    flow: np.ndarray | None = None


def _where(path: Path, token: str | None) -> str:
    return f"sample {token}: {path}" if token else str(path)


def read_occ3d_labels(
    path: str | Path, token: str | None = None, grid: VoxelGrid = OCC3D_GRID, flow: bool = False
) -> OccupancyLabels:
    """Read an Occ3D ``labels.npz`` (``semantics``, ``mask_lidar``, ``mask_camera``: uint8 ``(X, Y, Z)``).

    Masks are returned as bool: the official metric indexes with them, and a uint8 mask would index as integers.
    With ``flow``, the file must also carry the occupancy flow as OpenOcc v2's ``labels.npz`` does (key ``flow``,
    float ``(X, Y, Z, 2)``, m/s); it is returned as float32.
    """
    path = Path(path)
    where = _where(path, token)
    wanted = ("semantics", "mask_lidar", "mask_camera") + (("flow",) if flow else ())
    try:
        with np.load(path, allow_pickle=False) as archive:
            missing = [key for key in wanted if key not in archive.files]
            if missing:
                hint = " (occkit sim writes label files with flow)" if missing == ["flow"] else ""
                raise LabelError(
                    f"{where}: has no {', '.join(missing)} (keys: {', '.join(archive.files) or 'none'}){hint}"
                )
            arrays = {key: archive[key] for key in wanted}
    except FileNotFoundError:
        raise LabelError(f"{where}: label file not found") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise LabelError(f"{where}: cannot read labels ({error})") from error
    for key in ("semantics", "mask_lidar", "mask_camera"):
        array = arrays[key]
        if array.shape != grid.shape:
            raise LabelError(f"{where}: {key} has shape {array.shape} but expected {grid.shape}")
        if array.dtype not in (np.uint8, np.bool_):
            raise LabelError(f"{where}: {key} has dtype {array.dtype} but expected uint8")
    for key in ("mask_lidar", "mask_camera"):
        if arrays[key].dtype == np.uint8 and arrays[key].max(initial=0) > 1:
            raise LabelError(f"{where}: {key} holds values {sorted(np.unique(arrays[key]).tolist())[:8]}, not 0/1")
    semantics = arrays["semantics"].astype(np.uint8, copy=False)
    last = OCC3D.num_classes - 1
    bad = (semantics > last) & (semantics != IGNORE_INDEX)
    if bad.any():
        raise LabelError(
            f"{where}: semantics holds class ids {sorted(np.unique(semantics[bad]).tolist())} beyond 0..{last}"
        )
    return OccupancyLabels(semantics, arrays["mask_camera"].astype(bool), arrays["mask_lidar"].astype(bool),
                           _check_flow(arrays["flow"], where, grid) if flow else None)  # fmt: skip


def _check_flow(flow: np.ndarray, where: str, grid: VoxelGrid) -> np.ndarray:
    """``flow`` as float32 after checking its shape, dtype and values."""
    if flow.shape != (*grid.shape, 2):
        raise LabelError(f"{where}: flow has shape {flow.shape} but expected {(*grid.shape, 2)}")
    if flow.dtype.kind != "f":
        raise LabelError(f"{where}: flow has dtype {flow.dtype} but expected a float type (m/s)")
    flow = flow.astype(np.float32, copy=False)
    if not np.isfinite(flow).all():
        raise LabelError(f"{where}: flow holds {int((~np.isfinite(flow)).any(-1).sum())} voxels that are not finite")
    return flow


def read_surroundocc_labels(
    path: str | Path, token: str | None = None, grid: VoxelGrid = SURROUNDOCC_GRID
) -> OccupancyLabels:
    """Read SurroundOcc sparse labels: int ``(N, 4)`` rows ``(x, y, z, label)``, labels 1..16, 0 = noise.

    Returns dense ``(X, Y, Z)`` uint8 semantics with unlisted voxels empty (0) and noise voxels ignored (255).
    """
    path = Path(path)
    where = _where(path, token)
    try:
        rows = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise LabelError(f"{where}: label file not found") from None
    except (OSError, ValueError) as error:
        raise LabelError(f"{where}: cannot read labels ({error})") from error
    if rows.ndim != 2 or rows.shape[1] != 4 or not np.issubdtype(rows.dtype, np.integer):
        raise LabelError(f"{where}: expected integer rows (N, 4) = (x, y, z, label), got {rows.dtype} {rows.shape}")
    index, labels = rows[:, :3], rows[:, 3]
    outside = ((index < 0) | (index >= np.array(grid.shape))).any(axis=1)
    if outside.any():
        raise LabelError(f"{where}: {int(outside.sum())} rows index outside the {grid.shape} grid")
    last = SURROUNDOCC.num_classes - 1
    if ((labels < 0) | (labels > last)).any():
        raise LabelError(
            f"{where}: labels must be 0..{last}, got {np.unique(labels[(labels < 0) | (labels > last)]).tolist()}"
        )
    semantics = np.zeros(grid.shape, dtype=np.uint8)
    semantics[index[:, 0], index[:, 1], index[:, 2]] = np.where(labels == 0, IGNORE_INDEX, labels).astype(np.uint8)
    return OccupancyLabels(semantics)


def label_file(space: LabelSpace, folder: str | Path, scene: str, token: str, lidar_path: str) -> Path:
    """The ground-truth file of a key frame in ``folder`` (the dataset root's ``space.label_folder``, or a folder of
    its own), as the benchmark names it:

    * Occ3D: ``<folder>/<scene>/<token>/labels.npz`` (the ``gts/`` tree);
    * SurroundOcc: ``<folder>/samples/<LiDAR file name>.npy``, e.g. ``samples/n008-...__LIDAR_TOP__...pcd.bin.npy``
      (its ``tools/generate_occupancy_nuscenes`` names each file after the key frame's LiDAR file).

    Names are checked (:func:`~occkit.data.names.safe_name`), so the path stays in ``folder``.
    """
    if space.name == "surroundocc":
        name = safe_name(Path(lidar_path).name, f"sample {token}: LiDAR file name")
        return path_under(folder, f"samples/{name}.npy", str(folder))
    where = f"sample {token}"
    return path_under(folder, f"{safe_name(scene, where + ' scene')}/{safe_name(token, where)}/labels.npz",
                      str(folder))  # fmt: skip


def read_labels(space: LabelSpace, path: str | Path, token: str | None = None, flow: bool = False) -> OccupancyLabels:
    """Read one ground-truth file of ``space`` with its reader (``semantics`` in the space's class ids); ``flow``
    reads the occupancy flow too, which only Occ3D-layout files carry."""
    if space.name == "surroundocc":
        if flow:
            raise LabelError(f"{path}: SurroundOcc label files carry no occupancy flow; flow needs occ3d labels")
        return read_surroundocc_labels(path, token, space.grid)
    return read_occ3d_labels(path, token, space.grid, flow)

