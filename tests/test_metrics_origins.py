"""RayIoU ray origins, against the origins SparseOcc's helper dataset produced for the golden frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from occkit.geometry.se3 import transform_from_quaternion
from occkit.metrics.origins import PoseRecord, ray_origins

GOLDEN = Path(__file__).parent / "golden" / "occ3d_metrics"


def _pose(translation, rotation) -> np.ndarray:
    quaternion = torch.tensor(rotation, dtype=torch.float64)
    return transform_from_quaternion(quaternion, torch.tensor(translation, dtype=torch.float64)).numpy()


def test_origins_match_the_reference():
    infos = json.loads((GOLDEN / "infos.json").read_text())
    frames = [
        PoseRecord(
            info["token"],
            info["scene_name"],
            _pose(info["lidar2ego_translation"], info["lidar2ego_rotation"]),
            _pose(info["ego2global_translation"], info["ego2global_rotation"]),
        )
        for info in infos
    ]
    origins = ray_origins(frames)
    with np.load(GOLDEN / "lidar_origins.npz") as golden:
        for i, token in enumerate(golden["tokens"]):
            expected = golden["origins"][i, : golden["n_origins"][i]]
            assert origins[str(token)].shape == expected.shape
            np.testing.assert_allclose(origins[str(token)], expected, rtol=0, atol=1e-12)
