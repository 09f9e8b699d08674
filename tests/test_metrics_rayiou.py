"""RayIoU against the SparseOcc reference run unchanged on 20 golden frames: ray by ray, count by count."""

from __future__ import annotations

import importlib
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
import torch

from occkit.metrics.rayiou import RAYIOU_THRESHOLDS, cast_rays_exact, ray_directions, rayiou

GOLDEN = Path(__file__).parent / "golden" / "occ3d_metrics"


@pytest.fixture(scope="module")
def golden():
    frames = np.load(GOLDEN / "all_frames.npz")
    lidar = np.load(GOLDEN / "lidar_origins.npz")
    origins = [lidar["origins"][i, : lidar["n_origins"][i]] for i in range(len(lidar["n_origins"]))]
    return {
        "gt": frames["semantics"],
        "pred": frames["pred"],
        "origins": origins,
        "rays": np.load(GOLDEN / "rayiou_rays_per_frame.npz"),
        "summary": json.loads((GOLDEN / "rayiou_sparseocc.json").read_text()),
    }


def test_ray_directions():
    dirs = ray_directions()
    assert dirs.shape == (14040, 3) and dirs.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-6)
    # Pitch-major: the first 360 rays share the steepest pitch, -(pi/2 - atan(1)) = -pi/4, at azimuths 0..359 deg.
    np.testing.assert_allclose(dirs[:360, 2], -math.sqrt(0.5), atol=1e-6)
    np.testing.assert_allclose(dirs[1, :2], np.array([math.cos(math.radians(1)), math.sin(math.radians(1))]) * 0.5**0.5)
    assert dirs[-1, 2] > math.sin(0.21) - 0.05 and np.all(np.diff(dirs[::360, 2]) > 0)


def test_rays_match_reference_bit_for_bit(golden):
    for i, org in enumerate(golden["origins"]):
        for kind in ("gt", "pred"):
            label, dist = cast_rays_exact(golden[kind][i], org)
            assert label.dtype == np.uint8 and dist.dtype == np.float32
            np.testing.assert_array_equal(label, golden["rays"][f"{kind}_label_{i:02d}"], err_msg=f"{kind} {i}")
            np.testing.assert_array_equal(dist, golden["rays"][f"{kind}_dist_{i:02d}"], err_msg=f"{kind} {i}")


def test_rayiou_matches_reference(golden):
    result = rayiou(golden["gt"], golden["pred"], golden["origins"])
    ref = golden["summary"]
    assert result["rayiou"] == pytest.approx(ref["main_rayiou_return"]["RayIoU"], abs=1e-6)
    counts = ref["counts"]
    assert result["counts"]["gt"] == counts["gt_cnt"]
    assert result["counts"]["pred"] == counts["pred_cnt"]
    for t in RAYIOU_THRESHOLDS:
        assert result[f"rayiou@{t}"] == pytest.approx(ref["main_rayiou_return"][f"RayIoU@{t}"], abs=1e-6)
        assert result["counts"]["tp"][t] == counts["tp_cnt"][f"@{t}"]
        expected = np.array(ref["per_class_iou"][f"@{t}"], dtype=np.float64)  # null -> NaN
        np.testing.assert_allclose(np.array(result["per_class"][t]), expected, rtol=0, atol=1e-12)


def test_rayiou_of_ground_truth_against_itself_is_one(golden):
    result = rayiou(golden["gt"][:1], golden["gt"][:1], golden["origins"][:1])
    assert result["rayiou"] == pytest.approx(1.0)


@pytest.mark.parametrize(
    "labels, origins",
    [
        (np.zeros((200, 200, 16), np.int64), np.zeros((1, 3))),
        (np.zeros((200, 200, 17), np.uint8), np.zeros((1, 3))),
        (np.zeros((200, 200, 16), np.uint8), np.zeros(3)),
        (np.zeros((200, 200, 16), np.uint8), np.zeros((2, 2))),
        (np.zeros((200, 200, 16), np.uint8), np.zeros((0, 3))),
        (np.zeros((200, 200, 16), np.uint8), np.full((1, 3), np.nan)),
        (np.zeros((200, 200, 16), np.uint8), np.array([["a", "b", "c"]])),
    ],
)
def test_bad_input_raises(labels, origins):
    with pytest.raises(ValueError):
        cast_rays_exact(labels, origins)
    with pytest.raises(ValueError):
        rayiou([labels], [labels], [origins])


def test_rayiou_rejects_mismatched_frames():
    grid = np.full((200, 200, 16), 17, np.uint8)
    with pytest.raises(ValueError):
        rayiou([grid, grid], [grid], [np.zeros((1, 3))])


def test_casting_keeps_the_callers_thread_count():
    """numba's first parallel launch after torch has run a parallel region resets the shared OpenMP thread count;
    casting puts the caller's back (a fresh process: the launch happens once per process)."""
    script = (
        "import numpy as np, torch\n"
        "from occkit.metrics.rayiou import cast_rays_exact\n"
        "torch.set_num_threads(1)\n"
        "(torch.randn(256, 256) @ torch.randn(256, 256)).sum()\n"
        "labels = np.full((200, 200, 16), 17, np.uint8)\n"
        "cast_rays_exact(labels, np.zeros((1, 3)))\n"
        "import numba\n"
        "print(torch.get_num_threads(), numba.get_num_threads())\n"
    )
    env = {key: value for key, value in os.environ.items() if key not in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS")}
    env["NUMBA_NUM_THREADS"] = "2"  # numba's own count differs from the caller's even on a one-core machine
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
    assert done.stdout.split()[-2:] == ["1", "2"]


def test_casting_restores_thread_counts_when_the_kernel_raises(monkeypatch):
    module = importlib.import_module("occkit.metrics.rayiou")  # the package exports a function of that name

    def failing_kernel(*args):
        torch.set_num_threads(2)  # what numba's launch does to the shared OpenMP count
        raise RuntimeError("kernel failed")

    monkeypatch.setattr(module, "_cast_kernel", failing_kernel)
    before_torch, before_numba = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    try:
        with pytest.raises(RuntimeError, match="kernel failed"):
            module.cast_rays_exact(np.full((200, 200, 16), 17, np.uint8), np.zeros((1, 3)))
        assert torch.get_num_threads() == 1
        assert numba.get_num_threads() == before_numba
    finally:
        torch.set_num_threads(before_torch)
