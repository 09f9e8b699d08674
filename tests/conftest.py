"""Shared fixtures: a small, geometrically consistent synthetic Batch for model tests, and the synthetic worlds that
several test files read, simulated once per session (per worker, when pytest-xdist runs the suite on every core).

Under pytest-xdist each worker computes on one thread (``OMP_NUM_THREADS=1``, set before torch loads, and so for the
subprocesses the tests start unless they set their own): the workers share the cores, and spconv's CPU path slows
several-fold when its threads compete for them. Tests that need more threads ask for them (:func:`torch_threads`).
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import math
import os
import shutil
import sys
from pathlib import Path

if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = "1"

import pytest  # noqa: E402
import torch  # noqa: E402

from occkit.geometry.se3 import make_transform, rotation_about_z
from occkit.label_space import OCC3D_SPACE, LabelSpace
from occkit.types import Batch


def _camera2ego(yaw_deg: float) -> torch.Tensor:
    optical = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera axes in ego-forward terms
    return make_transform(rotation_about_z(torch.tensor(math.radians(yaw_deg))) @ optical, torch.tensor([1.0, 0, 1.5]))


def make_batch(
    batch_size: int = 2,
    num_cameras: int = 2,
    image_size: tuple[int, int] = (64, 176),
    num_points: int = 3000,
    seed: int = 0,
    occupancy: bool = True,
    depth_stride: int = 0,
    space: LabelSpace = OCC3D_SPACE,
    history: int = 0,
    padded: int = 0,
    flow: bool = False,
) -> Batch:
    """A batch with ``num_cameras`` cameras (0 allowed) spread around the car, random points in +-40 m, ten boxes per
    sample and ``space`` labels that follow simple rules (ground low, a vehicle class around three of the boxes, free
    above; the visibility masks where the space has them); with ``depth_stride``, LiDAR-like depth (0 = none) and
    height (NaN = none) maps at that feature stride; with ``flow``, the vehicles' voxels moving at a velocity of their
    own (``voxel_flow``). With ``history``, as many earlier frames of the same rig
    (random images), the ego 2 m further back and 3 degrees less turned per frame, the oldest ``padded`` of them
    padded (the current frame repeated, as the dataset pads)."""
    generator = torch.Generator().manual_seed(seed)
    height, width = image_size
    focal = width / 2
    intrinsics = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    yaws = [360.0 * i / num_cameras for i in range(num_cameras)]
    lidar2ego = make_transform(rotation_about_z(torch.tensor(math.pi / 2)), torch.tensor([0.94, 0.0, 1.84]))
    points = torch.rand(batch_size, num_points, 5, generator=generator)
    points[..., :2] = points[..., :2] * 80 - 40
    points[..., 2] = points[..., 2] * 4 - 3
    points[..., 4] = (points[..., 4] * 10).floor() * 0.05
    # Boxes of every detection task, an odd number per task (so no regression gradient can cancel exactly).
    box_labels = torch.tensor([0, 1, 2, 2, 3, 5, 6, 7, 7, 8])
    num_boxes = len(box_labels)
    centres = torch.rand(batch_size, num_boxes, 2, generator=generator) * 40 - 20
    boxes = [
        torch.cat([c, torch.full((num_boxes, 1), -0.9), torch.rand(num_boxes, 3, generator=generator) * 3 + 0.5,
                   torch.rand(num_boxes, 1, generator=generator) * 6, torch.randn(num_boxes, 2, generator=generator)],
                  dim=1)
        for c in centres
    ]  # fmt: skip
    batch = Batch(
        tokens=[f"sample{i}" for i in range(batch_size)],
        scenes=["scene-test"] * batch_size,
        images=torch.randn(batch_size, num_cameras, 3, height, width, generator=generator),
        intrinsics=intrinsics.expand(batch_size, num_cameras, 3, 3).clone(),
        cam2ego=torch.stack([_camera2ego(y) for y in yaws] or [torch.eye(4)])[:num_cameras]
        .expand(batch_size, -1, -1, -1).clone(),
        img_aug=torch.eye(3).expand(batch_size, num_cameras, 3, 3).clone(),
        camera_mask=torch.ones(batch_size, num_cameras, dtype=torch.bool),
        lidar2ego=lidar2ego.expand(batch_size, 4, 4).clone(),
        ego2global=torch.eye(4, dtype=torch.float64).expand(batch_size, 4, 4).clone(),
        points=points,
        num_points=torch.full((batch_size,), num_points, dtype=torch.int64),
        bev_aug=torch.eye(4).expand(batch_size, 4, 4).clone(),
        occ_aug=torch.eye(4).expand(batch_size, 4, 4).clone(),
        boxes=boxes,
        box_labels=[box_labels.clone() for _ in range(batch_size)],
    )
    if occupancy:
        shape, grid = space.grid.shape, space.grid
        # Occ3D and SurroundOcc share the ids 1..16 (barrier .. vegetation); free / empty is 17 or 0.
        road, vehicle = space.taxonomy.index("driveable_surface"), space.taxonomy.index("barrier")
        labels = torch.full((batch_size, *shape), space.free_index, dtype=torch.uint8)
        labels[..., :2] = road  # the two lowest layers
        for b, centre in enumerate(centres):
            ix, iy = ((centre[:3] - torch.tensor(grid.lower[:2])) / torch.tensor(grid.voxel_size[:2])).long().T
            for x, y in zip(ix.tolist(), iy.tolist(), strict=True):
                labels[b, x - 5 : x + 6, y - 2 : y + 3, 2:6] = vehicle + b  # a vehicle class per sample
        batch.voxel_semantics = labels
        if flow:
            velocity = torch.randn(batch_size, 1, 1, 1, 2, generator=generator) * 5.0
            batch.voxel_flow = torch.where((labels >= vehicle)[..., None] & (labels != space.free_index)[..., None],
                                           velocity, torch.zeros(()))  # fmt: skip
        if "camera" in space.masks:
            batch.mask_camera = torch.rand(batch_size, *shape, generator=generator) > 0.3
        if "lidar" in space.masks:
            batch.mask_lidar = torch.ones(batch_size, *shape, dtype=torch.bool)
    if history:
        repeat = (1, history, 1, 1, 1)
        batch.history_tokens = [tuple(f"sample{i}-{k + 1}" for k in range(history)) for i in range(batch_size)]
        batch.history_images = torch.randn(batch_size, history, num_cameras, 3, height, width, generator=generator)
        batch.history_intrinsics = batch.intrinsics[:, None].repeat(*repeat)
        batch.history_cam2ego = batch.cam2ego[:, None].repeat(*repeat)
        batch.history_img_aug = batch.img_aug[:, None].repeat(*repeat)
        poses = [make_transform(rotation_about_z(torch.tensor(math.radians(-3.0 * (k + 1)))),
                                torch.tensor([-2.0 * (k + 1), 0.0, 0.0])).double() for k in range(history)]
        batch.history_ego2global = torch.stack(poses)[None].repeat(batch_size, 1, 1, 1)
        batch.history_padded = torch.zeros(batch_size, history, dtype=torch.bool)
        if padded:
            batch.history_padded[:, history - padded :] = True
            batch.history_images[:, history - padded :] = batch.images[:, None]
            batch.history_ego2global[:, history - padded :] = batch.ego2global[:, None]
    if depth_stride:
        shape = (batch_size, num_cameras, height // depth_stride, width // depth_stride)
        batch.depth_maps = (torch.rand(shape, generator=generator) * 50).where(
            torch.rand(shape, generator=generator) > 0.3, torch.tensor(0.0))
        batch.height_maps = (torch.rand(shape, generator=generator) * 6.4 - 1).where(
            torch.rand(shape, generator=generator) > 0.3, torch.tensor(float("nan")))
    return batch


def fit_batch(model: torch.nn.Module, batch: Batch, steps: int = 20, lr: float = 2e-3) -> list[float]:
    """Train ``model`` on one fixed batch with AdamW; the summed loss before each step."""
    optimizer = torch.optim.AdamW(model.parameters(), lr=lr)
    history = []
    for _ in range(steps):
        loss = sum(model.loss(model(batch), batch).values())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        history.append(loss.item())
    return history


def parameters_without_gradient(model: torch.nn.Module) -> list[str]:
    """Names of trainable parameters whose gradient is missing or all zero after a backward pass."""
    return [n for n, p in model.named_parameters() if p.requires_grad and (p.grad is None or not p.grad.any())]


@contextlib.contextmanager
def torch_threads(count: int):
    """Run the block with ``count`` intra-op threads, then restore the previous count."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@pytest.fixture
def synthetic_batch():
    """Factory: ``synthetic_batch(**kwargs)`` -> :func:`make_batch`."""
    return make_batch


@pytest.fixture(scope="session")
def small_world(synthetic_world) -> Path:
    """2 scenes x 2 key frames, 2 cameras at 176 x 99, a sparse world, with OpenOcc v2 labels beside Occ3D's: the
    world the flow, panoptic, OpenOcc and viz tests share (scene-0002 is the val split). Read only."""
    from occkit.sim.world import WorldConfig

    return synthetic_world(scenes=2, frames=2, seed=3, image_size=(176, 99), cameras=("CAM_FRONT", "CAM_BACK"),
                           openocc=True, world=WorldConfig(density=0.5))  # fmt: skip


@pytest.fixture(scope="session")
def synthetic_world(tmp_path_factory):
    """Factory: ``synthetic_world(**settings)`` -> the root of a world simulated with ``SimConfig(**settings)``, once
    per session for each set of settings. The world is shared: read it only. ``synthetic_world(copy_to=path,
    **settings)`` copies it to ``path`` for a test that alters its files."""
    from occkit.sim.generate import SimConfig, simulate_dataset

    worlds: dict[tuple, Path] = {}

    def world(copy_to: Path | None = None, **settings) -> Path:
        key = tuple(sorted(settings.items()))
        if key not in worlds:
            worlds[key] = tmp_path_factory.mktemp("world") / "data"
            simulate_dataset(SimConfig(**settings), worlds[key])
        if copy_to is None:
            return worlds[key]
        shutil.copytree(worlds[key], copy_to)
        return copy_to

    return world


@functools.cache
def benchmark_module(relative: str):
    """A script under ``benchmarks/`` (``bad_inputs.py``, ``reference_parity/key_coverage.py``) as a module, for
    tests that share its code rather than copy it."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / relative
    spec = importlib.util.spec_from_file_location("benchmarks_" + relative.removesuffix(".py").replace("/", "_"), path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the file runs
    spec.loader.exec_module(module)
    return module


def crafting():
    """``benchmarks/bad_inputs.py``: the one home of the crafted files of the bad-input tests (archive bombs, a pickle
    that calls ``os.system``, ``.npy`` headers) and of its reading of a command's error lines."""
    return benchmark_module("bad_inputs.py")
