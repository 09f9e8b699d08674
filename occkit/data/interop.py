"""Import the field's pickled info files as occkit :class:`~occkit.data.index.FrameRecord` lists.

Two layouts, told apart by their top-level key:

``bevdet``
    ``{"infos": [...], "metadata": {"version"}}``: mmdetection3d 1.0's ``create_nuscenes_infos``
    (``tools/data_converter/nuscenes_converter.py``), which BEVDet and FlashOcc run to write
    ``bevdetv2-nuscenes_infos_{train,val}.pkl``; FlashOcc's ``tools/create_data_bevdet.py`` then adds ``scene_token``,
    ``scene_name``, ``occ_path`` and ``ann_infos``. Poses are (w, x, y, z) quaternions and translations, timestamps
    microseconds, paths as the writer's nuScenes root gave them (``./data/nuscenes/samples/...``).
``mmdet3d-v2``
    ``{"metainfo": {"categories", "version", ...}, "data_list": [...]}``: mmdetection3d 1.x's
    ``tools/dataset_converters/update_infos_to_v2.py``, which rewrites the first layout. Poses are 4x4 lists (float32
    before listing: about 1e-4 m at global offsets of a kilometre), timestamps seconds, key-frame LiDAR and image paths
    bare file names (the dataset config's ``data_prefix`` supplies ``samples/LIDAR_TOP`` and ``samples/<camera>``).

Conventions confirmed in the writers:

* ``gt_boxes`` rows are ``(x, y, z, l, w, h, yaw)`` in the key frame's LiDAR frame: the centres and sizes of
  ``get_sample_data``'s boxes with the devkit's ``wlh`` reordered ``[1, 0, 2]``, and ``yaw`` pyquaternion's
  ``yaw_pitch_roll[0]`` of the box rotation in that frame, that is the heading of the box's length axis about +z, 0
  along +x. These are occkit's :data:`~occkit.data.index.BOX_COLUMNS`. Files from mmdetection3d before 1.0.0rc0
  (``wlh`` and ``-yaw - pi / 2``) look the same and are not supported.
* The v2 ``bbox_3d`` is the ``gt_boxes`` row copied: ``(x, y, z, l, w, h, yaw)``, whatever the schema's comment
  (``[x, y, z, w, h, l, yaw]``) says.
* ``gt_velocity`` is the devkit's ``box_velocity`` (global) with its vertical part zeroed, rotated into the LiDAR
  frame, first two components kept; NaN where the devkit has no estimate (kept, not zeroed). Here: ``velocity_valid``
  False and 0 there.
* ``sensor2lidar_rotation`` / ``_translation`` map sweep points into the key frame's LiDAR frame as
  ``p @ rotation.T + translation``: the rotation is the column-vector matrix, so ``sweep2lidar = [rotation,
  translation]``. v2 stores the inverse, ``lidar2sensor``; its ``lidar2cam`` likewise, which (through the camera's own
  ego pose) gives ``cam2keyego = lidar2ego @ inv(lidar2cam)``.
* ``gt_names`` are the detection classes for the 14 mapped nuScenes categories and the raw category otherwise; v2
  keeps a class index (``bbox_label_3d``, -1 for the others).
* FlashOcc's ``ann_infos`` is not per annotation: ``get_gt`` rewrites it as ``(boxes, labels)`` of the detection
  targets with points, in the ego frame at CAM_FRONT's timestamp. It is ignored; boxes come from ``gt_boxes``.

Conversion: paths that start with ``root`` or ``data/nuscenes`` (``./`` or not) are made relative to the root, other
relative paths are kept as they are; an absolute path elsewhere or one with a ``..`` component is an error (records
hold paths under the root), as are tokens and scene names that are no safe names (:mod:`occkit.data.names`).
Ego-frame boxes are the LiDAR-frame boxes through ``lidar2ego``, the box rotation taken as
the turn by ``yaw`` about the LiDAR z axis and the vertical velocity as 0 (the files keep neither): where the ego
pitches and rolls, yaw and velocity differ from the index's by about pitch x roll and pitch x vz. Fields a file lacks
get these defaults:

* scene: ``scene_token`` / ``scene_name`` or ``""``; ``prev``, ``next`` and ``index_in_scene`` from the file's frames
  of the same scene in time order (files hold whole scenes); a frame without a scene stands alone;
* ``occ_path``: ``occ_path + "/labels.npz"`` (FlashOcc stores the folder), else ``gts/<scene>/<token>/labels.npz``
  if that file exists under the root, else None;
* image width and height: read once per camera from the first frame's image header, nuScenes' 1600 x 900 when that
  file is missing;
* no ``gt_boxes`` (test split) or ``instances``: no boxes; box instance and visibility tokens: ``""``; box categories:
  the nuScenes category where the file has it, else the detection class, else ``"ignore"`` (v2 label -1);
* ``box_valid`` (mmdetection3d's ``valid_flag``, ``num_lidar_pts + num_radar_pts > 0``): the file's ``valid_flag``
  (first layout) or each instance's ``bbox_3d_isvalid`` (v2, which ``update_infos_to_v2`` copies from
  ``valid_flag``); where a file lacks it, ``num_lidar_pts > 0`` (radar counts are not read: the writers that keep
  them keep the flag too);
* v2 without ``lidar_sweeps`` (the writer drops empty lists): no sweeps; without ``metainfo.categories``:
  mmdetection3d's nuScenes class order (:data:`MMDET3D_NUSCENES_CLASSES`).

Unpickling runs whatever code the file names, so :func:`import_info_file` refuses unless ``trust_pickle=True``.
"""

from __future__ import annotations

import os
import pickle
import posixpath
from collections import defaultdict
from collections.abc import Mapping, Sequence
from numbers import Integral, Real
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from occkit.classes import DETECTION_CLASSES, NUSCENES_TO_OCC3D, detection_name
from occkit.data.index import CameraRecord, FrameRecord, SweepRecord
from occkit.data.names import is_safe_relative_path, safe_name, safe_relative_path
from occkit.geometry.numpy_se3 import (
    invert_transform,
    make_transform,
    rotation_about_z,
    rotation_yaw,
    transform_from_quaternion,
    transform_points,
)
from occkit.nuscenes import CAMERA_ORDER

__all__ = [
    "INFO_FORMATS",
    "MMDET3D_NUSCENES_CLASSES",
    "DEFAULT_IMAGE_SIZE",
    "IGNORED_CATEGORY",
    "InfoFileError",
    "UntrustedPickleError",
    "detect_format",
    "convert_infos",
    "import_info_file",
]

#: Layouts :func:`convert_infos` reads (see the module doc).
INFO_FORMATS = ("bevdet", "mmdet3d-v2")

#: Class order of mmdetection3d's nuScenes ``METAINFO``, which v2 labels index when a file has no categories.
MMDET3D_NUSCENES_CLASSES = (
    "car",
    "truck",
    "trailer",
    "bus",
    "construction_vehicle",
    "bicycle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "barrier",
)

#: Width and height of nuScenes images, for cameras whose image is not under the root.
DEFAULT_IMAGE_SIZE = (1600, 900)

#: Category of boxes whose class the file does not keep (v2 label -1), FlashOcc's name for non-targets.
IGNORED_CATEGORY = "ignore"

#: The nuScenes data root of the writers' scripts, relative to their working directory.
_WRITER_ROOT = "data/nuscenes"

_WRITERS = {
    "bevdet": "mmdetection3d 1.0's tools/data_converter/nuscenes_converter.py (create_nuscenes_infos, which "
    "BEVDet's and FlashOcc's tools/create_data_bevdet.py run)",
    "mmdet3d-v2": "mmdetection3d 1.x's tools/dataset_converters/update_infos_to_v2.py",
}


class InfoFileError(ValueError):
    """An info file is unreadable, of an unknown layout, or an entry lacks a key or holds a bad value; the message
    names the file, the entry (index and token) and the key."""


class UntrustedPickleError(InfoFileError):
    """:func:`import_info_file` was asked to unpickle a file without ``trust_pickle=True``."""


# ----------------------------------------------------------------------------------------------------- entry fields
class _Fields:
    """A mapping from an info file, read key by key: errors name where it is and the writer that produces a key."""

    def __init__(self, data: Any, where: str, writer: str) -> None:
        if not isinstance(data, Mapping):
            raise InfoFileError(f"{where}: expected a dict, got {type(data).__name__}")
        self.data, self.where, self.writer = data, where, writer

    def __contains__(self, key: str) -> bool:
        return key in self.data

    def __getitem__(self, key: str) -> Any:
        try:
            return self.data[key]
        except KeyError:
            raise InfoFileError(f"{self.where}: no key {key!r} (written by {self.writer})") from None

    def error(self, key: str, message: str) -> InfoFileError:
        return InfoFileError(f"{self.where}.{key}: {message}")

    def sub(self, key: str) -> _Fields:
        return _Fields(self[key], f"{self.where}.{key}", self.writer)

    def items(self, key: str) -> list[_Fields]:
        """The dicts of the list at ``key``."""
        values = self[key]
        if isinstance(values, (str, bytes, Mapping)) or not isinstance(values, Sequence):
            raise self.error(key, f"expected a list, got {type(values).__name__}")
        return [_Fields(value, f"{self.where}.{key}[{i}]", self.writer) for i, value in enumerate(values)]

    def text(self, key: str) -> str:
        value = self[key]
        if not isinstance(value, str):
            raise self.error(key, f"expected a string, got {type(value).__name__}")
        return value

    def path(self, key: str) -> str:
        value = self[key]
        if not isinstance(value, (str, os.PathLike)):
            raise self.error(key, f"expected a path, got {type(value).__name__}")
        return os.fspath(value)

    def microseconds(self, key: str, scale: int) -> int:
        """A timestamp in units of ``scale`` microseconds (1: microseconds, 10**6: seconds) as microseconds."""
        value = self[key]
        if isinstance(value, bool) or not isinstance(value, Real) or not np.isfinite(value):
            raise self.error(key, f"expected a timestamp, got {value!r}")
        return int(value) * scale if isinstance(value, Integral) else round(float(value) * scale)

    def array(self, key: str, shape: tuple[int, ...], finite: bool = True) -> np.ndarray:
        """``key`` as float64 of ``shape`` (``-1``: any length)."""
        value = self[key]
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            array = None
        if (
            array is None
            or array.ndim != len(shape)
            or any(n not in (-1, m) for n, m in zip(shape, array.shape, strict=True))
            or (finite and not np.isfinite(array).all())
        ):
            wanted = str(tuple("N" if n == -1 else n for n in shape)).replace("'", "")
            got = "values that are not numbers" if array is None else f"shape {array.shape}"
            raise self.error(key, f"expected {'finite ' if finite else ''}numbers of shape {wanted}, got {got}")
        return array

    def flags(self, key: str, shape: tuple[int, ...]) -> np.ndarray:
        """``key`` as bool of ``shape`` (a numpy bool array, a list of bools or one bool): integers are refused, a
        count where a flag belongs is a writer's mistake, not a flag."""
        array = np.asarray(self[key])
        if array.dtype != np.bool_ or array.shape != shape:
            wanted = str(shape).replace(",)", ")")
            raise self.error(key, f"expected booleans of shape {wanted}, got {array.dtype} of shape {array.shape}")
        return array

    def pose(self, rotation: str, translation: str) -> np.ndarray:
        """4x4 from a (w, x, y, z) quaternion and a translation."""
        quaternion, offset = self.array(rotation, (4,)), self.array(translation, (3,))
        try:
            return transform_from_quaternion(quaternion, offset)
        except ValueError as error:  # a zero quaternion
            raise self.error(rotation, str(error)) from None


# ----------------------------------------------------------------------------------------------------- shared parts
def _root_prefixes(root: Path) -> tuple[str, ...]:
    """Prefixes that paths in a file may carry instead of the dataset root, most specific first."""
    given = posixpath.normpath(root.as_posix())
    # "." would match every relative path: those are kept as they are.
    candidates = (given, posixpath.normpath(root.absolute().as_posix()), _WRITER_ROOT)
    return tuple(dict.fromkeys(prefix for prefix in candidates if prefix != "."))


def _relative(path: str, prefixes: tuple[str, ...]) -> str:
    """``path`` relative to the dataset root when it starts with one of ``prefixes``, else as it is."""
    text = posixpath.normpath(path)
    for prefix in prefixes:
        if text.startswith(prefix.rstrip("/") + "/"):
            return text[len(prefix.rstrip("/")) + 1 :]
    return text


class _ImageSizes:
    """Width and height per camera, read once from the header of the first image (the info files keep none)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.sizes: dict[str, tuple[int, int]] = {}

    def __call__(self, channel: str, path: str) -> tuple[int, int]:
        if not is_safe_relative_path(path):  # an error once the frame is complete; nothing is opened outside the root
            return DEFAULT_IMAGE_SIZE
        if channel not in self.sizes:
            try:
                with Image.open(self.root / path) as image:  # reads the header, not the pixels
                    self.sizes[channel] = image.size
            except OSError:  # missing or unreadable (PIL's UnidentifiedImageError is an OSError)
                self.sizes[channel] = DEFAULT_IMAGE_SIZE
        return self.sizes[channel]


def _camera_order(channels: Sequence[str]) -> list[str]:
    return sorted(channels, key=lambda c: (CAMERA_ORDER.index(c) if c in CAMERA_ORDER else len(CAMERA_ORDER), c))


def _class_names(name: str, fields: _Fields, key: str) -> tuple[str, str | None]:
    """(nuScenes category, detection class) of a box's class name: a detection class or a nuScenes category."""
    if name in DETECTION_CLASSES:
        return name, name
    if name in NUSCENES_TO_OCC3D:
        return name, detection_name(name)
    raise fields.error(
        key, f"{name!r} is neither a detection class ({', '.join(DETECTION_CLASSES)}) nor a nuScenes category"
    )


def _boxes(boxes: np.ndarray, velocity: np.ndarray, lidar2ego: np.ndarray) -> dict[str, np.ndarray]:
    """Box fields of a record from ``(N, 7)`` LiDAR-frame boxes and ``(N, 2)`` velocities (NaN: none)."""
    valid = np.isfinite(velocity).all(axis=1)
    velocity = np.where(valid[:, None], velocity, 0.0)
    rotation = lidar2ego[:3, :3]
    velocity_3d = np.concatenate((velocity, np.zeros((len(velocity), 1))), axis=1)  # the files keep no vz
    boxes_ego = np.concatenate(
        (
            transform_points(lidar2ego, boxes[:, :3]),
            boxes[:, 3:6],
            rotation_yaw(rotation @ rotation_about_z(boxes[:, 6]))[:, None],
            (velocity_3d @ rotation.T)[:, :2],
        ),
        axis=1,
    )
    return {
        "boxes_ego": boxes_ego,
        "boxes_lidar": np.concatenate((boxes, velocity), axis=1),
        "velocity_valid": valid,
    }


def _scene_and_labels(entry: _Fields, token: str, root: Path, prefixes: tuple[str, ...]) -> dict[str, Any]:
    """``scene``, ``scene_token`` and ``occ_path``: FlashOcc's keys, or the defaults of the module doc."""
    safe_name(token, f"{entry.where}.token", InfoFileError)
    scene_token = entry.text("scene_token") if "scene_token" in entry else ""
    scene = entry.text("scene_name") if "scene_name" in entry else ""
    for key, name in (("scene_token", scene_token), ("scene_name", scene)):
        if name != "":
            safe_name(name, f"{entry.where}.{key}", InfoFileError)
    if "occ_path" in entry:
        folder = _relative(entry.path("occ_path"), prefixes)
        occ_path: str | None = folder if folder.endswith(".npz") else f"{folder}/labels.npz"
    else:
        guess = f"gts/{scene}/{token}/labels.npz"
        occ_path = guess if scene and (root / guess).is_file() else None
    return {"scene": scene, "scene_token": scene_token, "occ_path": occ_path}


def _check_paths(frame: dict[str, Any], entry: _Fields) -> None:
    """Every path of the record stays under the root (see the module doc); the message names the entry and the
    record field (the file's key differs between layouts)."""
    where = f"{entry.where}: record field"
    safe_relative_path(frame["lidar_path"], f"{where} lidar_path", InfoFileError)
    for i, sweep in enumerate(frame["sweeps"]):
        safe_relative_path(sweep.path, f"{where} sweeps[{i}].path", InfoFileError)
    for channel, camera in frame["cameras"].items():
        safe_relative_path(camera.path, f"{where} cameras.{channel}.path", InfoFileError)
    if frame["occ_path"] is not None:
        safe_relative_path(frame["occ_path"], f"{where} occ_path", InfoFileError)


def _link(frames: list[dict[str, Any]]) -> None:
    """Set ``prev``, ``next`` and ``index_in_scene`` from the frames of each scene in time order."""
    scenes: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for frame in frames:
        frame.update(prev="", next="", index_in_scene=0)
        key = frame["scene_token"] or frame["scene"]
        if key:
            scenes[key].append(frame)
    for members in scenes.values():
        members.sort(key=lambda frame: frame["timestamp"])
        for index, frame in enumerate(members):
            frame["index_in_scene"] = index
            frame["prev"] = members[index - 1]["token"] if index > 0 else ""
            frame["next"] = members[index + 1]["token"] if index + 1 < len(members) else ""


# ----------------------------------------------------------------------------------------------------- bevdet
def _bevdet_frame(entry: _Fields, root: Path, prefixes: tuple[str, ...], sizes: _ImageSizes) -> dict[str, Any]:
    token = entry.text("token")
    timestamp = entry.microseconds("timestamp", 1)
    ego2global = entry.pose("ego2global_rotation", "ego2global_translation")
    lidar2ego = entry.pose("lidar2ego_rotation", "lidar2ego_translation")
    global2ego = invert_transform(ego2global)
    sweeps = []
    for sweep in entry.items("sweeps"):
        sweep2lidar = make_transform(
            sweep.array("sensor2lidar_rotation", (3, 3)), sweep.array("sensor2lidar_translation", (3,))
        )
        sweep_time = sweep.microseconds("timestamp", 1)
        sweeps.append(
            SweepRecord(
                path=_relative(sweep.path("data_path"), prefixes),
                timestamp=sweep_time,
                sweep2lidar=sweep2lidar,
                time_lag=(timestamp - sweep_time) / 1e6,
            )
        )
    cams = entry.sub("cams")
    cameras = {}
    for channel in _camera_order(list(cams.data)):
        cam = cams.sub(channel)
        path = _relative(cam.path("data_path"), prefixes)
        cam2ego = cam.pose("sensor2ego_rotation", "sensor2ego_translation")
        cam_ego2global = cam.pose("ego2global_rotation", "ego2global_translation")
        width, height = sizes(channel, path)
        cameras[channel] = CameraRecord(
            path=path,
            timestamp=cam.microseconds("timestamp", 1),
            width=width,
            height=height,
            intrinsics=cam.array("cam_intrinsic", (3, 3)),
            cam2ego=cam2ego,
            ego2global=cam_ego2global,
            cam2keyego=global2ego @ cam_ego2global @ cam2ego,
        )
    return {
        "token": token,
        "timestamp": timestamp,
        "ego2global": ego2global,
        "lidar_path": _relative(entry.path("lidar_path"), prefixes),
        "lidar2ego": lidar2ego,
        "sweeps": sweeps,
        "cameras": cameras,
        **_bevdet_boxes(entry, lidar2ego),
        **_scene_and_labels(entry, token, root, prefixes),
    }


def _bevdet_boxes(entry: _Fields, lidar2ego: np.ndarray) -> dict[str, Any]:
    """Box fields from ``gt_boxes``, ``gt_velocity``, ``gt_names``, ``num_lidar_pts`` and ``valid_flag`` (none
    without them; ``num_lidar_pts > 0`` without ``valid_flag``)."""
    if "gt_boxes" not in entry:  # test-split infos carry no annotations
        return _box_fields(np.zeros((0, 7)), np.zeros((0, 2)), [], [], [], lidar2ego)
    boxes = entry.array("gt_boxes", (-1, 7))
    count = len(boxes)
    velocity = entry.array("gt_velocity", (count, 2), finite=False)
    names = entry["gt_names"]
    if isinstance(names, (str, bytes)) or not isinstance(names, (Sequence, np.ndarray)):
        raise entry.error("gt_names", f"expected a list of names, got {type(names).__name__}")
    names = [str(name) for name in names]
    points = entry.array("num_lidar_pts", (count,))
    if len(names) != count:
        raise entry.error("gt_names", f"expected {count} names (one per gt_boxes row), got {len(names)}")
    classes = [_class_names(name, entry, f"gt_names[{i}]") for i, name in enumerate(names)]
    valid = entry.flags("valid_flag", (count,)) if "valid_flag" in entry else points > 0
    return _box_fields(boxes, velocity, classes, points.astype(np.int64).tolist(), valid.tolist(), lidar2ego)


def _box_fields(
    boxes: np.ndarray,
    velocity: np.ndarray,
    classes: list[tuple[str, str | None]],
    points: list[int],
    valid: list[bool],
    lidar2ego: np.ndarray,
) -> dict[str, Any]:
    """The box fields of a record from ``N`` boxes: ``(N, 7)`` LiDAR-frame boxes, ``(N, 2)`` velocities (NaN: none),
    ``N`` (category, detection class) pairs, LiDAR point counts and valid flags."""
    count = len(boxes)
    return {
        **_boxes(boxes, velocity, lidar2ego),
        "box_categories": [category for category, _ in classes],
        "box_detection_names": [name for _, name in classes],
        "box_instances": [""] * count,
        "box_num_lidar_pts": points,
        "box_valid": valid,
        "box_visibility": [""] * count,
    }


# ----------------------------------------------------------------------------------------------------- mmdet3d v2
def _v2_path(path: str, folder: str, prefixes: tuple[str, ...]) -> str:
    """A v2 path: bare file names live in ``folder`` (the configs' ``data_prefix``), others as in the first layout."""
    return f"{folder}/{path}" if "/" not in path else _relative(path, prefixes)


def _v2_frame(
    entry: _Fields, root: Path, prefixes: tuple[str, ...], sizes: _ImageSizes, classes: dict[int, str]
) -> dict[str, Any]:
    token = entry.text("token")
    timestamp = entry.microseconds("timestamp", 10**6)
    ego2global = entry.array("ego2global", (4, 4))
    lidar = entry.sub("lidar_points")
    lidar2ego = lidar.array("lidar2ego", (4, 4))
    sweeps = []
    # The file's matrices went through float32 and are not exactly rigid: the general inverse is the inverse of what
    # the file holds, invert_transform's would assume a rotation that is not quite there.
    for sweep in entry.items("lidar_sweeps") if "lidar_sweeps" in entry else []:
        points = sweep.sub("lidar_points")
        sweep_time = sweep.microseconds("timestamp", 10**6)
        sweeps.append(
            SweepRecord(
                path=_v2_path(points.path("lidar_path"), "sweeps/LIDAR_TOP", prefixes),
                timestamp=sweep_time,
                sweep2lidar=np.linalg.inv(points.array("lidar2sensor", (4, 4))),
                time_lag=(timestamp - sweep_time) / 1e6,
            )
        )
    images = entry.sub("images")
    cameras = {}
    for channel in _camera_order(list(images.data)):
        image = images.sub(channel)
        path = _v2_path(image.path("img_path"), f"samples/{channel}", prefixes)
        cam2ego = image.array("cam2ego", (4, 4))
        # lidar2cam runs through the camera's own ego pose (mmdetection3d 1.0's sensor2lidar, inverted).
        cam2keyego = lidar2ego @ np.linalg.inv(image.array("lidar2cam", (4, 4)))
        width, height = sizes(channel, path)
        cameras[channel] = CameraRecord(
            path=path,
            timestamp=image.microseconds("timestamp", 10**6),
            width=width,
            height=height,
            intrinsics=_v2_intrinsics(image),
            cam2ego=cam2ego,
            ego2global=ego2global @ cam2keyego @ np.linalg.inv(cam2ego),
            cam2keyego=cam2keyego,
        )
    return {
        "token": token,
        "timestamp": timestamp,
        "ego2global": ego2global,
        "lidar_path": _v2_path(lidar.path("lidar_path"), "samples/LIDAR_TOP", prefixes),
        "lidar2ego": lidar2ego,
        "sweeps": sweeps,
        "cameras": cameras,
        **_v2_boxes(entry, lidar2ego, classes),
        **_scene_and_labels(entry, token, root, prefixes),
    }


def _v2_intrinsics(image: _Fields) -> np.ndarray:
    """The 3x3 pinhole part of ``cam2img`` (3x3, 3x4 or 4x4)."""
    cam2img = image.array("cam2img", (-1, -1))
    if cam2img.shape[0] not in (3, 4) or cam2img.shape[1] not in (3, 4):
        raise image.error("cam2img", f"expected a 3x3, 3x4 or 4x4 matrix, got shape {cam2img.shape}")
    return cam2img[:3, :3]


def _v2_boxes(entry: _Fields, lidar2ego: np.ndarray, classes: dict[int, str]) -> dict[str, Any]:
    instances = entry.items("instances") if "instances" in entry else []
    boxes = np.array([instance.array("bbox_3d", (7,)) for instance in instances]).reshape(-1, 7)
    velocity = np.array([instance.array("velocity", (2,), finite=False) for instance in instances]).reshape(-1, 2)
    names = []
    for i, instance in enumerate(instances):
        label = instance["bbox_label_3d"]
        if label == -1:
            names.append((IGNORED_CATEGORY, None))
        elif label in classes:
            names.append(_class_names(classes[label], entry, f"instances[{i}].bbox_label_3d"))
        else:
            raise instance.error("bbox_label_3d", f"label {label!r} is not among the categories {classes}")
    points = [int(instance.array("num_lidar_pts", ())) for instance in instances]
    valid = [
        bool(instance.flags("bbox_3d_isvalid", ())) if "bbox_3d_isvalid" in instance else count > 0
        for instance, count in zip(instances, points, strict=True)
    ]
    return _box_fields(boxes, velocity, names, points, valid, lidar2ego)


def _v2_classes(metainfo: _Fields) -> dict[int, str]:
    """Label -> class name, from ``metainfo.categories`` (name -> label; ignored names map to -1)."""
    if "categories" not in metainfo:
        return dict(enumerate(MMDET3D_NUSCENES_CLASSES))
    categories = metainfo["categories"]
    if not isinstance(categories, Mapping):
        raise metainfo.error("categories", f"expected a dict of name -> label, got {type(categories).__name__}")
    return {int(label): str(name) for name, label in categories.items() if label != -1}


# ----------------------------------------------------------------------------------------------------- entry points
def detect_format(data: Any, source: str = "info file") -> str:
    """The layout of an unpickled info file: ``"bevdet"`` (key ``infos``) or ``"mmdet3d-v2"`` (key ``data_list``).

    Raises:
        InfoFileError: neither; the message names ``source`` and what it holds.
    """
    if isinstance(data, Mapping):
        if "infos" in data:
            return "bevdet"
        if "data_list" in data:
            return "mmdet3d-v2"
        found = f"a dict with keys {', '.join(map(repr, list(data)[:8])) or 'none'}"
    else:
        found = f"a {type(data).__name__}"
    raise InfoFileError(
        f"{source}: unknown info file layout: expected a dict with 'infos' (BEVDet / FlashOcc, mmdetection3d 1.0 "
        f"create_data) or 'data_list' (mmdetection3d 1.x v2 infos), got {found}"
    )


def convert_infos(
    data: Any, root: str | Path, source: str = "info file", version_hint: str | None = None
) -> list[FrameRecord]:
    """Frame records, in file order, of an unpickled info file (either layout of the module doc).

    Args:
        data: the unpickled object.
        root: the dataset root that the records' paths are made relative to (see the module doc).
        source: how messages name the file.
        version_hint: the nuScenes version the caller expects (e.g. ``v1.0-trainval``); an error if the file
            records another one (``metadata.version`` / ``metainfo.version``).

    Raises:
        InfoFileError: unknown layout, another version, or an entry without a key the writer produces or with a bad
            value; the message names ``source``, the entry index and token, the key and the writer.
    """
    layout = detect_format(data, source)
    root = Path(root)
    writer = _WRITERS[layout]
    meta_key = "metadata" if layout == "bevdet" else "metainfo"
    meta = _Fields(data.get(meta_key, {}), f"{source}: {meta_key}", writer)
    found = meta.data.get("version")
    if version_hint is not None and found is not None and found != version_hint:
        raise InfoFileError(f"{source}: the file was written for nuScenes {found!r}, not {version_hint!r}")
    entries = data["infos" if layout == "bevdet" else "data_list"]
    if not isinstance(entries, Sequence) or isinstance(entries, (str, bytes)):
        raise InfoFileError(f"{source}: expected a list of entries, got {type(entries).__name__}")
    prefixes = _root_prefixes(root)
    sizes = _ImageSizes(root)
    classes = _v2_classes(meta) if layout == "mmdet3d-v2" else {}
    frames = []
    for i, data_entry in enumerate(entries):
        token = data_entry.get("token") if isinstance(data_entry, Mapping) else None
        entry = _Fields(data_entry, f"{source}: entry {i}" + (f" (token {token!r})" if token else ""), writer)
        if layout == "bevdet":
            frames.append(_bevdet_frame(entry, root, prefixes, sizes))
        else:
            frames.append(_v2_frame(entry, root, prefixes, sizes, classes))
        _check_paths(frames[-1], entry)
    _link(frames)
    return [FrameRecord(**frame) for frame in frames]


def import_info_file(
    path: str | Path, root: str | Path, version_hint: str | None = None, trust_pickle: bool = False
) -> list[FrameRecord]:
    """Read a pickled info file and convert it with :func:`convert_infos`.

    Args:
        path: the ``.pkl`` file.
        root: the dataset root (see :func:`convert_infos`).
        version_hint: see :func:`convert_infos`.
        trust_pickle: unpickling runs any code the file names; the file is read only when this is True.

    Raises:
        FileNotFoundError: no such file.
        UntrustedPickleError: ``trust_pickle`` is False.
        InfoFileError: not a readable pickle, or see :func:`convert_infos`.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"info file {path} does not exist")
    if not trust_pickle:
        raise UntrustedPickleError(
            f"{path}: refusing to unpickle: loading a pickle runs any code the file names, so a crafted file can do "
            "anything your account can; pass --trust-pickle only for files from a source you trust (in Python: "
            "trust_pickle=True)"
        )
    try:
        with open(path, "rb") as stream:
            data = pickle.load(stream)
    except (pickle.UnpicklingError, EOFError, ImportError, AttributeError, IndexError, TypeError) as error:
        # ImportError / AttributeError: the file names classes of a package this environment lacks.
        raise InfoFileError(f"{path}: not a readable pickle ({type(error).__name__}: {error})") from None
    return convert_infos(data, root, str(path), version_hint)
