"""Readers of occupancy ground truth: Occ3D and OpenOcc v2 ``labels.npz`` and SurroundOcc sparse ``.npy`` (the writers
are in :mod:`occkit.label_files`).

Both validate what they read and name the file and sample in every error, because label files are where
silent mistakes (a wrong shape, a float mask, a SurroundOcc file read as Occ3D) cost a training run.
:func:`label_file` and :func:`read_labels` choose the file and the reader from a
:class:`~occkit.label_space.LabelSpace`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occkit.archives import NpyHeader, NpzArchive, read_npy
from occkit.classes import IGNORE_INDEX, OCC3D, OPENOCC, SURROUNDOCC, Taxonomy
from occkit.data.names import path_under, safe_name
from occkit.geometry.grid import OCC3D_GRID, SURROUNDOCC_GRID, VoxelGrid
from occkit.label_space import LabelSpace

__all__ = ["LabelError", "OccupancyLabels", "MAX_FLOW_SPEED", "read_occ3d_labels", "read_openocc_labels", "check_flow",
           "read_surroundocc_labels", "label_file", "carry_instances", "read_labels"]

#: The fastest occupancy flow (m/s) a label or prediction may hold: faster than anything on a road (the simulator's
#: ego drives at most 40 m/s), and far from where sums of errors overflow float32.
MAX_FLOW_SPEED = 100.0


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
        instances: ``(X, Y, Z)`` int32 panoptic instance ids (0: stuff or free), or None when not asked for.
    """

    semantics: np.ndarray
    mask_camera: np.ndarray | None = None
    mask_lidar: np.ndarray | None = None
    flow: np.ndarray | None = None
    instances: np.ndarray | None = None


def _where(path: Path, token: str | None) -> str:
    return f"sample {token}: {path}" if token else str(path)


def read_occ3d_labels(
    path: str | Path, token: str | None = None, grid: VoxelGrid = OCC3D_GRID, flow: bool = False,
    instances: bool = False,
) -> OccupancyLabels:
    """Read an Occ3D ``labels.npz`` (``semantics``, ``mask_lidar``, ``mask_camera``: uint8 ``(X, Y, Z)``).

    Masks are returned as bool: the official metric indexes with them, and a uint8 mask would index as integers.
    With ``flow``, the file must also carry the occupancy flow as OpenOcc v2's ``labels.npz`` does (key ``flow``,
    float ``(X, Y, Z, 2)``, m/s, at most :data:`MAX_FLOW_SPEED`); it is returned as float32. Each array's shape and
    dtype are checked from its header before its data is read (:class:`~occkit.archives.NpzArchive`), so a file
    that declares a larger array costs no memory. With ``instances``, also the panoptic instance ids (key
    ``instances``, integer ``(X, Y, Z)``, non-negative, 0 for stuff and free space), as ``occkit sim`` writes them.
    """
    return _read_dense_labels(path, token, grid, OCC3D, masks=True, flow=flow, instances=instances)


def read_openocc_labels(
    path: str | Path, token: str | None = None, grid: VoxelGrid = OCC3D_GRID, flow: bool = False
) -> OccupancyLabels:
    """Read an OpenOcc v2 ``labels.npz``: ``semantics`` uint8 ``(X, Y, Z)`` in OpenOcc's ids (16 = free) and, with
    ``flow``, the occupancy flow (key ``flow``, float ``(X, Y, Z, 2)``, m/s), checked as :func:`read_occ3d_labels`
    checks them. The files carry no visibility mask (the masks are None)."""
    return _read_dense_labels(path, token, grid, OPENOCC, masks=False, flow=flow)


def _read_dense_labels(path: str | Path, token: str | None, grid: VoxelGrid, taxonomy: Taxonomy, masks: bool,
                       flow: bool, instances: bool = False) -> OccupancyLabels:  # fmt: skip
    """A dense ``labels.npz`` of ``taxonomy``'s ids, with Occ3D's visibility masks where ``masks``."""
    path = Path(path)
    where = _where(path, token)
    mask_keys = ("mask_lidar", "mask_camera") if masks else ()
    wanted = ("semantics", *mask_keys) + (("flow",) if flow else ()) + (("instances",) if instances else ())
    try:
        with NpzArchive(path, "labels", where, LabelError) as archive:
            missing = [key for key in wanted if key not in archive]
            if missing:
                hint = f" (occkit sim writes label files with {missing[0]})" if missing in (["flow"], ["instances"]) \
                    else ""  # fmt: skip
                raise LabelError(
                    f"{where}: has no {', '.join(missing)} (keys: {', '.join(archive.keys) or 'none'}){hint}"
                )
            arrays = {key: archive.read(key, _expect(key, where, grid)) for key in wanted}
    except FileNotFoundError:
        raise LabelError(f"{where}: label file not found") from None
    except OSError as error:
        raise LabelError(f"{where}: cannot read labels ({error})") from error
    for key in mask_keys:
        if arrays[key].dtype == np.uint8 and arrays[key].max(initial=0) > 1:
            raise LabelError(f"{where}: {key} holds values {sorted(np.unique(arrays[key]).tolist())[:8]}, not 0/1")
    semantics = arrays["semantics"].astype(np.uint8, copy=False)
    last = taxonomy.num_classes - 1
    bad = (semantics > last) & (semantics != IGNORE_INDEX)
    if bad.any():
        raise LabelError(f"{where}: semantics holds class ids {sorted(np.unique(semantics[bad]).tolist())} beyond "
                         f"0..{last} of {taxonomy.name}")  # fmt: skip
    camera, lidar = (arrays["mask_camera"].astype(bool), arrays["mask_lidar"].astype(bool)) if masks else (None, None)
    ids = None
    if instances:
        ids = arrays["instances"]
        if ids.min(initial=0) < 0 or ids.max(initial=0) > np.iinfo(np.int32).max:
            raise LabelError(f"{where}: instances holds ids from {int(ids.min())} to {int(ids.max())}; 0 is stuff and "
                             "objects count from 1 (int32)")  # fmt: skip
        ids = ids.astype(np.int32)
    return OccupancyLabels(semantics, camera, lidar, check_flow(arrays["flow"], where, LabelError) if flow else None,
                           ids)  # fmt: skip


def _expect(key: str, where: str, grid: VoxelGrid) -> Callable[[NpyHeader], None]:
    """The header check of array ``key`` of a ``labels.npz``: the grid's shape, uint8 (or bool), float flow."""
    shape = (*grid.shape, 2) if key == "flow" else grid.shape

    def check(header: NpyHeader) -> None:
        if header.shape != shape:
            raise LabelError(f"{where}: {key} has shape {header.shape} but expected {shape}")
        if key == "flow" and header.dtype.kind != "f":
            raise LabelError(f"{where}: flow has dtype {header.dtype} but expected a float type (m/s)")
        if key == "instances" and (header.dtype.kind not in "iu" or header.dtype.itemsize > 8):
            raise LabelError(f"{where}: instances has dtype {header.dtype} but expected an integer type")
        if key not in ("flow", "instances") and header.dtype not in (np.uint8, np.bool_):
            raise LabelError(f"{where}: {key} has dtype {header.dtype} but expected uint8")

    return check


def check_flow(flow: np.ndarray, where: str, error: type[ValueError] = ValueError) -> np.ndarray:
    """``flow`` (``(..., 2)`` m/s, shape and dtype already checked) as float32, after checking it is finite and no
    faster than :data:`MAX_FLOW_SPEED`: a value like 3e38 is finite, but summed in a loss it overflows to an
    infinite ``loss/flow`` at every step.

    Raises:
        error: naming ``where``, how many voxels are wrong, and the fastest value with the bound.
    """
    flow = flow.astype(np.float32, copy=False)
    if not np.isfinite(flow).all():
        raise error(f"{where}: flow holds {int((~np.isfinite(flow)).any(-1).sum())} voxels that are not finite")
    if np.abs(flow).max(initial=0.0) <= MAX_FLOW_SPEED / np.sqrt(2):  # the common case, without the speeds
        return flow
    speed = np.hypot(flow[..., 0].astype(np.float64), flow[..., 1].astype(np.float64))  # (3e38, 3e38) is beyond float32
    fastest = float(speed.max(initial=0.0))
    if fastest > MAX_FLOW_SPEED:
        raise error(f"{where}: flow holds {int((speed > MAX_FLOW_SPEED).sum())} voxels faster than "
                    f"{MAX_FLOW_SPEED:g} m/s (up to {fastest:.3g} m/s): flow is in m/s, and nothing on a road is "
                    "that fast")  # fmt: skip
    return flow


def read_surroundocc_labels(
    path: str | Path, token: str | None = None, grid: VoxelGrid = SURROUNDOCC_GRID
) -> OccupancyLabels:
    """Read SurroundOcc sparse labels: int ``(N, 4)`` rows ``(x, y, z, label)``, labels 1..16, 0 = noise.

    Returns dense ``(X, Y, Z)`` uint8 semantics with unlisted voxels empty (0) and noise voxels ignored (255). The
    header is checked before the rows are read: integer ``(N, 4)`` with at most one row per voxel of the grid.
    """
    path = Path(path)
    where = _where(path, token)
    voxels = int(np.prod(grid.shape))

    def check(header: NpyHeader) -> None:
        shape, dtype = header.shape, header.dtype
        if len(shape) != 2 or shape[1] != 4 or dtype.kind not in "iu":
            raise LabelError(f"{where}: expected integer rows (N, 4) = (x, y, z, label), got {dtype} {shape}")
        if shape[0] > voxels:
            raise LabelError(f"{where}: declares {shape[0]} rows, more than the {voxels} voxels of the "
                             f"{grid.shape} grid")  # fmt: skip

    try:
        rows = read_npy(path, "labels", check, where, LabelError)
    except FileNotFoundError:
        raise LabelError(f"{where}: label file not found") from None
    except OSError as error:
        raise LabelError(f"{where}: cannot read labels ({error})") from error
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

    * Occ3D and OpenOcc v2: ``<folder>/<scene>/<token>/labels.npz`` (the ``gts/`` and ``openocc_v2/`` trees);
    * SurroundOcc: ``<folder>/samples/<LiDAR file name>.npy``, e.g. ``samples/n008-...__LIDAR_TOP__...pcd.bin.npy``
      (its ``tools/generate_occupancy_nuscenes`` names each file after the key frame's LiDAR file).

    Names are checked (:func:`~occkit.data.names.safe_name`), so the path stays in ``folder``.
    """
    if space.layout == "lidar_files":
        name = safe_name(Path(lidar_path).name, f"sample {token}: LiDAR file name")
        return path_under(folder, f"samples/{name}.npy", str(folder))
    where = f"sample {token}"
    return path_under(folder, f"{safe_name(scene, where + ' scene')}/{safe_name(token, where)}/labels.npz",
                      str(folder))  # fmt: skip


def carry_instances(space: LabelSpace, paths: Iterable[str | Path]) -> bool:
    """Whether every label file of ``paths`` (of ``space``) carries panoptic instance ids: only Occ3D-layout files
    can, and of those the synthetic world's do (Occ3D's own do not). An unreadable file counts as not."""
    if space.name != "occ3d":
        return False
    for path in paths:
        try:
            with NpzArchive(Path(path), "labels", str(path), LabelError) as archive:
                if "instances" not in archive:
                    return False
        except (OSError, LabelError):
            return False
    return True


def read_labels(space: LabelSpace, path: str | Path, token: str | None = None, flow: bool = False,
                instances: bool = False) -> OccupancyLabels:  # fmt: skip
    """Read one ground-truth file of ``space`` with its reader (``semantics`` in the space's class ids); ``flow``
    reads the occupancy flow too, which only the dense files carry (OpenOcc v2's, occkit's Occ3D files), and
    ``instances`` the panoptic instance ids, which only occkit's Occ3D files carry."""
    if instances and space.name != "occ3d":
        raise LabelError(f"{path}: {space.name} label files carry no instance ids; panoptic labels are occ3d's")
    if space.name == "surroundocc":
        if flow:
            raise LabelError(f"{path}: SurroundOcc label files carry no occupancy flow; flow needs occ3d or openocc "
                             "labels")  # fmt: skip
        return read_surroundocc_labels(path, token, space.grid)
    if space.name == "openocc":
        return read_openocc_labels(path, token, space.grid, flow)
    return read_occ3d_labels(path, token, space.grid, flow, instances)

