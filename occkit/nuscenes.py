"""Names of the nuScenes on-disk layout, shared by its readers (:mod:`occkit.data`) and its writer
(:mod:`occkit.sim`), so that neither imports the other."""

from __future__ import annotations

__all__ = ["TABLE_NAMES", "LIDARSEG_TABLE", "CAMERAS", "CAMERA_ORDER", "LIDAR_CHANNEL"]

#: The 13 tables of a nuScenes version folder, in the devkit's load order.
TABLE_NAMES = (
    "category",
    "attribute",
    "visibility",
    "instance",
    "sensor",
    "calibrated_sensor",
    "ego_pose",
    "log",
    "scene",
    "sample",
    "sample_data",
    "sample_annotation",
    "map",
)

#: The table of nuScenes-lidarseg (an extension: ``<version>/lidarseg.json``, present only where it is installed).
LIDARSEG_TABLE = "lidarseg"

#: The six camera channels in the order of BEVDet / FlashOcc / DAOcc configs (the surround view read left to
#: right, front row then back row): the order of a model's camera inputs.
CAMERAS = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT")

#: Camera order of the nuScenes sensor table and of mmdetection3d's info files.
CAMERA_ORDER = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")

#: The key-frame LiDAR channel.
LIDAR_CHANNEL = "LIDAR_TOP"
