"""A plain index of key frames built from the nuScenes tables, saved as typed columns in one ``.npz`` (never pickle).

One :class:`FrameRecord` per sample holds everything a data pipeline needs without the tables: file paths
(relative to the dataset root), calibrations and poses as 4x4 matrices, the LiDAR sweeps before the key frame with
their transforms into the key frame's LiDAR frame, each camera's geometry relative to the key frame's ego pose, and
the sample's boxes in the ego and LiDAR frames.

Names from the tables become file paths (``gts/<scene>/<token>/labels.npz``, ``<out>/<token>.npz``): sample tokens,
scene names and scene tokens must be safe names and every file path a relative path that stays under the root
(:mod:`occkit.data.names`), checked when an index is built, saved and read.

The modules, one role each: ``records`` (:class:`FrameRecord` and its sub-records, :data:`BOX_COLUMNS`), ``kinds``
(what each record field holds, declared once: its checks, its JSON form and its columns follow from it), ``checks``
(the checks of JSON values, :class:`IndexFormatError`), ``builder`` (:func:`build_index`, :func:`index_tables`:
the tables to records), ``columns`` (an index file's arrays in memory), ``files`` (the index file format:
:func:`save_index`, :func:`load_index`, :func:`read_index_header`, :class:`FrameRecords`) and ``key``
(:func:`tables_key`, what an index depends on).
"""

from occkit.data.index.builder import MAX_VELOCITY_TIME_DIFF, build_index, build_split_index, index_tables
from occkit.data.index.checks import IndexFormatError
from occkit.data.index.files import (
    INDEX_FORMAT,
    FrameRecords,
    OutdatedIndexError,
    load_index,
    read_index_header,
    save_index,
)
from occkit.data.index.key import tables_key
from occkit.data.index.records import BOX_COLUMNS, CameraRecord, FrameRecord, SweepRecord
from occkit.geometry.numpy_se3 import MIN_QUATERNION_NORM

__all__ = [
    "INDEX_FORMAT",
    "BOX_COLUMNS",
    "IndexFormatError",
    "OutdatedIndexError",
    "SweepRecord",
    "CameraRecord",
    "FrameRecord",
    "FrameRecords",
    "build_index",
    "build_split_index",
    "index_tables",
    "save_index",
    "load_index",
    "read_index_header",
    "tables_key",
    "MIN_QUATERNION_NORM",
    "MAX_VELOCITY_TIME_DIFF",
]
