"""LSS view transform: pooling equals a naive loop, lifted points reproject to their pixels, plans are reused only
when they should be, and the FlashOcc sizes come out right."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from occkit.config import from_dict, to_dict
from occkit.geometry.camera import image_aug_matrix, project_points
from occkit.geometry.grid import VoxelGrid
from occkit.geometry.se3 import invert_transform, make_transform, rotation_about_z
from occkit.models.view_transform.lss import (
    LSSConfig,
    LSSViewTransform,
    PoolingPlan,
    fold_height,
    frustum,
    gather_point_weights,
    lift_geometry,
    make_pooling_plan,
    voxel_pool,
)


def camera2ego(yaw_deg: float) -> torch.Tensor:
    """A camera 1.5 m up looking along ego yaw ``yaw_deg`` (camera axes x right, y down, z forward)."""
    optical = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera -> ego-forward axes
    rotation = rotation_about_z(torch.tensor(math.radians(yaw_deg))) @ optical
    return make_transform(rotation, torch.tensor([1.0, 0.0, 1.5]))


def rig(batch: int, cameras: int, image_size: tuple[int, int], focal_scale: float = 0.8):
    """Intrinsics ``(B, N, 3, 3)`` and cam2ego ``(B, N, 4, 4)`` of ``cameras`` cameras spread around the car."""
    height, width = image_size
    focal = focal_scale * width
    k = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    extrinsics = torch.stack([camera2ego(360.0 * i / cameras) for i in range(cameras)])
    return k.expand(batch, cameras, 3, 3).clone(), extrinsics.expand(batch, cameras, 4, 4).clone()


def small_config(**changes) -> LSSConfig:
    values = dict(
        image_size=(64, 176), feature_stride=16, depth_range=(1.0, 20.0, 1.0), grid_size=(32, 32, 2), in_channels=8,
        context_channels=4,
    )  # fmt: skip
    values.update(changes)
    return LSSConfig(**values)


# --------------------------------------------------------------------------- 1. pooling against a naive loop
def naive_pool(points, weights, context, grid: VoxelGrid):
    """Per-point loop: each point inside the grid adds weight * context to its voxel; ``(B, C, Z, X, Y)``."""
    batch, cameras, bins, h, w = weights.shape
    size_x, size_y, size_z = grid.shape
    totals: dict[tuple[int, int, int, int], torch.Tensor] = {}
    for b, n, d, i, j in itertools.product(range(batch), range(cameras), range(bins), range(h), range(w)):
        p = points[b, n, d, i, j].tolist()
        x, y, z = (math.floor((p[a] - grid.lower[a]) / grid.voxel_size[a]) for a in range(3))
        if 0 <= x < size_x and 0 <= y < size_y and 0 <= z < size_z:
            key = (b, z, x, y)
            totals[key] = totals.get(key, 0) + weights[b, n, d, i, j] * context[b, n, :, i, j]
    zero = context.new_zeros(context.shape[2])
    cells = [
        totals.get((b, z, x, y), zero)
        for b, z, x, y in itertools.product(range(batch), range(size_z), range(size_x), range(size_y))
    ]
    return torch.stack(cells).view(batch, size_z, size_x, size_y, -1).permute(0, 4, 1, 2, 3)


def test_voxel_pool_matches_a_naive_loop_values_and_gradients():
    generator = torch.Generator().manual_seed(0)
    batch, cameras, bins, h, w, channels = 2, 2, 3, 4, 5, 3
    grid = VoxelGrid((-2.0, -2.0, -1.0, 2.0, 2.0, 1.0), 1.0)  # 4 x 4 x 2
    points = torch.rand(batch, cameras, bins, h, w, 3, generator=generator, dtype=torch.float64) * 6 - 3
    points[..., 2] = points[..., 2] / 2  # z in [-1.5, 1.5): some inside, some out
    weights = torch.rand(batch, cameras, bins, h, w, generator=generator, dtype=torch.float64, requires_grad=True)
    context = torch.randn(batch, cameras, channels, h, w, generator=generator, dtype=torch.float64, requires_grad=True)
    upstream = torch.randn(batch, channels, 2, 4, 4, generator=generator, dtype=torch.float64)

    plan = make_pooling_plan(points, grid)
    assert 0 < plan.num_points < points[..., 0].numel()  # some points are dropped
    assert bool((plan.ranks_bev[1:] >= plan.ranks_bev[:-1]).all())  # sorted, as the reference
    pooled = voxel_pool(weights, context, plan, grid.shape)
    expected = naive_pool(points, weights, context, grid)
    assert pooled.shape == (batch, channels, 2, 4, 4) and pooled.dtype == torch.float64
    torch.testing.assert_close(pooled, expected)

    grads = torch.autograd.grad((pooled * upstream).sum(), (weights, context))
    expected_grads = torch.autograd.grad((expected * upstream).sum(), (weights, context))
    for got, want in zip(grads, expected_grads, strict=True):
        torch.testing.assert_close(got, want)


def test_truncated_indices_keep_the_band_below_the_lower_bound():
    grid = VoxelGrid((-2.0, -2.0, -1.0, 2.0, 2.0, 1.0), 1.0)
    points = torch.tensor([[0.5, 0.5, -1.5], [-2.5, 0.5, 0.5], [0.5, 0.5, -2.5], [0.5, 0.5, 0.5]])
    points = points.view(1, 1, 4, 1, 1, 3)
    floor_plan = make_pooling_plan(points, grid)
    assert floor_plan.ranks_depth.tolist() == [3]
    truncated = make_pooling_plan(points, grid, truncate_indices=True)
    assert sorted(truncated.ranks_depth.tolist()) == [0, 1, 3]  # BEVDet's .long(): (-1, 0) voxels -> voxel 0
    volume = voxel_pool(torch.ones(1, 1, 4, 1, 1), torch.ones(1, 1, 1, 1, 1), truncated)
    assert volume[0, 0, 0, 2, 2] == 1 and volume[0, 0, 1, 0, 2] == 1 and volume[0, 0, 1, 2, 2] == 1


def test_height_weights_are_gathered_per_point():
    generator = torch.Generator().manual_seed(1)
    probabilities = torch.rand(2, 3, 5, 4, 6, generator=generator)
    bins = torch.randint(-1, 7, (2, 3, 7, 4, 6), generator=generator)
    weights = gather_point_weights(probabilities, bins)
    assert weights.shape == (2, 3, 7, 4, 6)
    for b, n, d, i, j in [(0, 0, 0, 0, 0), (1, 2, 6, 3, 5), (1, 1, 3, 2, 1)]:
        k = min(max(int(bins[b, n, d, i, j]), 0), 4)
        assert weights[b, n, d, i, j] == probabilities[b, n, k, i, j]


# --------------------------------------------------------------------------- 2. cached vs dynamic plans
def geometry(cfg: LSSConfig, yaw_offset_deg: float = 0.0, batch: int = 2, cameras: int = 3):
    intrinsics, cam2ego = rig(batch, cameras, cfg.image_size)
    turn = make_transform(rotation_about_z(torch.tensor(math.radians(yaw_offset_deg))), torch.zeros(3))
    img_aug = torch.eye(3).expand(batch, cameras, 3, 3)
    return intrinsics, turn @ cam2ego, img_aug, torch.eye(4).expand(batch, 4, 4)


def test_plan_equals_the_one_made_from_the_lifted_frustum():
    torch.manual_seed(0)
    cfg = small_config()
    vt = LSSViewTransform(cfg).eval()
    h, w = cfg.feature_size
    features = torch.randn(2, 3, cfg.in_channels, h, w)
    first = geometry(cfg)
    plan = vt.plan(*first)
    dynamic = make_pooling_plan(lift_geometry(frustum(cfg.image_size, 16, cfg.depth_range), *first), vt.grid)
    with torch.no_grad():
        bev, depth = vt(features, plan)
        bev_dynamic, depth_dynamic = vt(features, dynamic)
    torch.testing.assert_close(bev, bev_dynamic, rtol=0, atol=0)
    torch.testing.assert_close(depth, depth_dynamic, rtol=0, atol=0)
    assert bev.abs().sum() > 0
    turned = vt.plan(*geometry(cfg, yaw_offset_deg=30.0))  # the plan follows the calibration it is given
    assert not torch.equal(turned.ranks_bev, plan.ranks_bev)


def test_plan_mismatch_is_a_clear_error():
    cfg = small_config()
    vt = LSSViewTransform(cfg)
    plan = vt.plan(*geometry(cfg))
    with pytest.raises(ValueError, match="plan was made for"):
        vt(torch.randn(2, 2, cfg.in_channels, *cfg.feature_size), plan)


# --------------------------------------------------------------------------- 3. geometry
def test_lifted_points_reproject_to_their_pixel_and_depth():
    image_size = (64, 176)
    points_uvd = frustum(image_size, 8, (2.0, 30.0, 7.0))  # (4, 8, 22, 3)
    intrinsics, cam2ego = rig(2, 3, (400, 900), focal_scale=0.6)  # original images are larger
    img_aug = image_aug_matrix(0.2, (2, 8, 2 + image_size[1], 8 + image_size[0]), flip=True, rotate_deg=5.0)
    img_aug = img_aug.expand(2, 3, 3, 3)
    flip_x = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
    turn = make_transform(rotation_about_z(torch.tensor(0.3)), torch.tensor([0.5, -1.0, 0.2]))
    occ_aug = torch.stack([flip_x, turn])
    points = lift_geometry(points_uvd, intrinsics, cam2ego, img_aug, occ_aug)
    assert points.shape == (2, 3, 4, 8, 22, 3)

    ego2cam = invert_transform(cam2ego) @ torch.linalg.inv(occ_aug)[:, None]  # augmented ego -> camera
    uv, depth, _ = project_points(points.flatten(2, 4), ego2cam, intrinsics, img_aug, image_size)
    target = points_uvd.reshape(-1, 3).expand(2, 3, -1, 3)
    torch.testing.assert_close(uv, target[..., :2], atol=2e-3, rtol=0)
    torch.testing.assert_close(depth, target[..., 2], atol=1e-4, rtol=1e-5)


def test_occ_aug_flip_mirrors_the_lifted_points():
    points_uvd = frustum((64, 176), 16, (1.0, 10.0, 2.0))
    intrinsics, cam2ego = rig(1, 4, (64, 176))
    plain = lift_geometry(points_uvd, intrinsics, cam2ego)
    flipped = lift_geometry(points_uvd, intrinsics, cam2ego, occ_aug=torch.diag(torch.tensor([-1.0, 1, 1, 1]))[None])
    torch.testing.assert_close(flipped, plain * torch.tensor([-1.0, 1.0, 1.0]))


def test_image_augmentation_does_not_move_the_points_of_an_original_pixel():
    """The frustum lives in the augmented image; each of its pixels is some original pixel, whose ray is fixed."""
    image_size = (64, 176)
    points_uvd = frustum(image_size, 16, (1.0, 10.0, 2.0))
    intrinsics, cam2ego = rig(1, 2, (400, 900))
    img_aug = image_aug_matrix(0.25, (20, 30, 20 + image_size[1], 30 + image_size[0]), flip=True, rotate_deg=-3.0)
    augmented = lift_geometry(points_uvd, intrinsics, cam2ego, img_aug.expand(1, 2, 3, 3))
    # The same rays, written as original-image pixels and lifted without augmentation.
    back = torch.linalg.inv(img_aug)  # augmented -> original pixels
    original_uv = points_uvd[..., :2] @ back[:2, :2].T + back[:2, 2]
    original = lift_geometry(torch.cat([original_uv, points_uvd[..., 2:]], -1), intrinsics, cam2ego)
    torch.testing.assert_close(augmented, original, atol=1e-4, rtol=1e-5)


# --------------------------------------------------------------------------- 4. FlashOcc sizes
def test_flashocc_m0_shapes():
    torch.manual_seed(0)
    cfg = LSSConfig()
    assert cfg.num_depth_bins == 44 and LSSConfig(depth_range=(1.0, 45.0, 0.5)).num_depth_bins == 88
    assert frustum(cfg.image_size, cfg.feature_stride, cfg.depth_range).shape == (44, 16, 44, 3)
    vt = LSSViewTransform(cfg).eval()
    intrinsics, cam2ego = rig(1, 6, cfg.image_size, focal_scale=0.8)
    plan = vt.plan(intrinsics, cam2ego, torch.eye(3).expand(1, 6, 3, 3), torch.eye(4)[None])
    with torch.no_grad():
        bev, depth = vt(torch.randn(1, 6, 256, 16, 44), plan)
    assert bev.shape == (1, 64, 200, 200) and vt.out_channels == 64
    assert depth.shape == (1, 6, 44, 16, 44)
    torch.testing.assert_close(depth.sum(2), torch.ones(1, 6, 16, 44))


def test_height_grid_folds_height_into_channels():
    """DA-Occ's 16 x 32 x 32 height grid: voxel 2.5 x 2.5 x 0.4 m, BEV (B, 16 * C, 32, 32), channel z * C + c."""
    cfg = small_config(grid_size=(32, 32, 16))
    vt = LSSViewTransform(cfg)
    assert vt.grid.voxel_size == pytest.approx((2.5, 2.5, 0.4))
    plan = vt.plan(*geometry(cfg, batch=1))
    bev, _ = vt(torch.randn(1, 3, cfg.in_channels, *cfg.feature_size), plan)
    assert bev.shape == (1, 16 * cfg.context_channels, 32, 32)
    volume = torch.randn(1, 4, 16, 3, 5)
    folded = fold_height(volume)
    assert torch.equal(folded[:, 2 * 4 + 1], volume[:, 1, 2])


# --------------------------------------------------------------------------- 5. conservation and orientation
def test_pooled_mass_is_the_probability_inside_the_grid():
    generator = torch.Generator().manual_seed(2)
    cfg = LSSConfig(image_size=(128, 352), depth_range=(1.0, 60.0, 1.0))  # some bins reach beyond 40 m
    h, w = cfg.feature_size
    grid = cfg.voxel_grid()
    intrinsics, cam2ego = rig(2, 6, cfg.image_size)
    points = lift_geometry(frustum(cfg.image_size, cfg.feature_stride, cfg.depth_range), intrinsics, cam2ego)
    plan = make_pooling_plan(points, grid)
    probabilities = torch.randn(2, 6, cfg.num_depth_bins, h, w, generator=generator, dtype=torch.float64).softmax(2)
    bev = fold_height(voxel_pool(probabilities, torch.ones(2, 6, 3, h, w, dtype=torch.float64), plan))
    _, inside = grid.world_to_index(points)
    for b in range(2):
        expected = probabilities[b][inside[b]].sum()
        assert 0 < expected < 6 * h * w  # some mass falls outside (far bins, rays below the ground)
        torch.testing.assert_close(bev[b].sum(dim=(1, 2)), expected.expand(3))


def test_bev_axes_follow_the_voxel_grid():
    """A camera looking forward (+x) fills only x > 0 (dim -2, upper half), both sides of y = 0 (dim -1)."""
    cfg = small_config(grid_size=(20, 20, 1))
    intrinsics, cam2ego = rig(1, 1, cfg.image_size)
    points = lift_geometry(frustum(cfg.image_size, cfg.feature_stride, cfg.depth_range), intrinsics, cam2ego)
    plan: PoolingPlan = make_pooling_plan(points, cfg.voxel_grid())
    h, w = cfg.feature_size
    counts = voxel_pool(torch.ones(plan.point_shape), torch.ones(1, 1, 1, h, w), plan)[0, 0, 0]  # (X, Y)
    assert counts[:10].sum() == 0 and counts[10:].sum() > 0
    left, right = counts[:, 10:].sum(), counts[:, :10].sum()
    assert left > 0 and right > 0 and abs(left - right) < 0.1 * (left + right)


# --------------------------------------------------------------------------- 6. config
def test_config_round_trip():
    cfg = LSSConfig(depth_range=(1.0, 45.0, 0.5), grid_size=(32, 32, 16), truncate_indices=True)
    data = to_dict(cfg)
    assert data["grid_size"] == [32, 32, 16]
    assert from_dict(LSSConfig, data) == cfg
    assert from_dict(LSSConfig, to_dict(LSSConfig())) == LSSConfig()


def test_configs_of_older_versions_still_load():
    # fixed_calibration was a config key; files and checkpoints that hold it load, and asking for it warns.
    assert from_dict(LSSConfig, {"fixed_calibration": False, "grid_size": [8, 8, 1]}) == LSSConfig(grid_size=(8, 8, 1))
    with pytest.warns(UserWarning, match="lss.fixed_calibration is no longer a config key"):
        assert from_dict(LSSConfig, {"fixed_calibration": True}, "lss") == LSSConfig()


# --------------------------------------------------------------------------- export
class _WithPlanInputs(torch.nn.Module):
    """The module with the plan's index lists as graph inputs, as a deployment with fixed calibration feeds them."""

    def __init__(self, vt: LSSViewTransform, point_shape, grid_shape) -> None:
        super().__init__()
        self.vt, self.point_shape, self.grid_shape = vt, point_shape, grid_shape

    def forward(self, features, ranks_depth, ranks_feat, ranks_bev):
        return self.vt(features, PoolingPlan(ranks_depth, ranks_feat, ranks_bev, self.point_shape, self.grid_shape))


@pytest.mark.filterwarnings("ignore::torch.jit.TracerWarning", "ignore::DeprecationWarning")
@pytest.mark.parametrize("dynamo", [False, True], ids=["torchscript", "dynamo"])
def test_onnx_export_uses_standard_operators_and_matches(tmp_path, dynamo):
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    if dynamo:
        pytest.importorskip("onnxscript")
    cfg = small_config(grid_size=(16, 16, 2))
    vt = LSSViewTransform(cfg).eval()
    plan = vt.plan(*geometry(cfg, batch=1))
    model = _WithPlanInputs(vt, plan.point_shape, plan.grid_shape).eval()
    inputs = (torch.randn(1, 3, cfg.in_channels, *cfg.feature_size), plan.ranks_depth, plan.ranks_feat, plan.ranks_bev)
    names = ["features", "ranks_depth", "ranks_feat", "ranks_bev"]
    path = tmp_path / "lss.onnx"
    # The TorchScript exporter is the one that mis-writes index_add; the pooling routes around it while exporting.
    torch.onnx.export(model, inputs, str(path), dynamo=dynamo, opset_version=18 if dynamo else 17, input_names=names)
    graph = onnx.load(str(path)).graph
    assert {node.domain for node in graph.node} <= {"", "ai.onnx"}
    outputs = ort.InferenceSession(str(path)).run(None, {n: t.numpy() for n, t in zip(names, inputs, strict=True)})
    with torch.no_grad():
        bev, depth = model(*inputs)
    assert bev.abs().sum() > 0
    torch.testing.assert_close(torch.from_numpy(outputs[0]), bev, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(torch.from_numpy(outputs[1]), depth, atol=1e-6, rtol=1e-5)
