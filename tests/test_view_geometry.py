"""Projection view transform and BEV range extension: samples land where the batch's matrices say they should."""

from __future__ import annotations

import math

import pytest
import torch

from occkit.data.transforms import lidar_frame_aug
from occkit.geometry.camera import image_aug_matrix, project_points
from occkit.geometry.grid import VoxelGrid
from occkit.geometry.se3 import compose, invert_transform, make_transform, rotation_about_z, transform_points
from occkit.models.range_extension import RangeExtension, RangeExtensionConfig
from occkit.models.view_transform.projection import ProjectionConfig, ProjectionViewTransform

IMAGE_SIZE = (48, 96)  # augmented image (H, W)
STRIDE = 4


def lidar2ego() -> torch.Tensor:
    """nuScenes-like: the LiDAR is turned 90 degrees about z and sits 0.94 m ahead, 1.84 m up."""
    return make_transform(rotation_about_z(torch.tensor(math.pi / 2)), torch.tensor([0.94, 0.0, 1.84]))


def camera2ego(yaw_deg: float) -> torch.Tensor:
    """A camera looking along ego yaw ``yaw_deg``, camera axes x right, y down, z forward."""
    optical = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera -> ego-forward axes
    rotation = rotation_about_z(torch.tensor(math.radians(yaw_deg))) @ optical
    return make_transform(rotation, torch.tensor([1.0, 0.0, 1.5]))


def intrinsics(width: float = 400.0, height: float = 225.0, focal: float = 200.0) -> torch.Tensor:
    return torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


def pixel_field(channels_u_v: bool, height: int, width: int, stride: int) -> torch.Tensor:
    """``(2, h, w)`` feature map holding each cell's centre in augmented-image pixels: bilinear sampling of a linear
    field is exact, so a sample's value says where it was taken."""
    h, w = height // stride, width // stride
    v = (torch.arange(h, dtype=torch.float32) + 0.5) * stride
    u = (torch.arange(w, dtype=torch.float32) + 0.5) * stride
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu, vv]) if channels_u_v else torch.stack([vv, uu])


def make_view(mode: str = "average") -> ProjectionViewTransform:
    cfg = ProjectionConfig(
        point_cloud_range=(-16.0, -16.0, -2.0, 16.0, 16.0, 2.0), grid_size=(16, 16, 2), in_channels=2,
        out_channels=2, mode=mode,
    )  # fmt: skip
    return ProjectionViewTransform(cfg)


def batch_geometry(num_cameras: int, flip_bev: bool, augment_image: bool):
    occ_aug = torch.diag(torch.tensor([-1.0 if flip_bev else 1.0, 1.0, 1.0, 1.0]))
    bev_aug = lidar_frame_aug(occ_aug, lidar2ego()).float()
    if augment_image:
        img_aug = image_aug_matrix(0.3, (10, 20, 10 + IMAGE_SIZE[1], 20 + IMAGE_SIZE[0]), flip=True, rotate_deg=4.0)
    else:
        img_aug = image_aug_matrix(0.24, (0, 6, IMAGE_SIZE[1], 6 + IMAGE_SIZE[0]))
    yaws = [0.0, 30.0, 180.0][:num_cameras]
    return {
        "intrinsics": intrinsics()[None, None].expand(1, num_cameras, 3, 3),
        "cam2ego": torch.stack([camera2ego(y) for y in yaws])[None],
        "img_aug": img_aug[None, None].expand(1, num_cameras, 3, 3),
        "lidar2ego": lidar2ego()[None],
        "bev_aug": bev_aug[None],
    }


@pytest.mark.parametrize("flip_bev", [False, True])
@pytest.mark.parametrize("augment_image", [False, True])
def test_voxel_centres_sample_the_pixel_they_project_to(flip_bev, augment_image):
    view = make_view()
    geometry = batch_geometry(1, flip_bev, augment_image)
    plan = view.plan(**geometry, image_size=IMAGE_SIZE)
    features = pixel_field(True, *IMAGE_SIZE, STRIDE)[None, None]  # (1, 1, 2, h, w)
    bev = view(features, plan)  # (1, Z * 2, X, Y)
    x, y, z = view.grid.shape
    sampled = bev.view(1, z, 2, x, y).permute(0, 3, 4, 1, 2).reshape(-1, 2)  # (X*Y*Z, 2) in voxel order

    # Independent path: un-augment the centre, LiDAR -> ego -> camera, pinhole, image augmentation.
    centres_lidar = transform_points(invert_transform(geometry["bev_aug"][0]), view.grid.centers().reshape(-1, 3))
    lidar2cam = compose(invert_transform(geometry["cam2ego"][0, 0]), geometry["lidar2ego"][0])
    uv, _, valid = project_points(centres_lidar, lidar2cam, geometry["intrinsics"][0, 0],
                                  geometry["img_aug"][0, 0], IMAGE_SIZE)
    # Half a feature cell from the border, bilinear sampling mixes in zero padding; compare the interior.
    interior = valid & (uv[:, 0] > STRIDE) & (uv[:, 0] < IMAGE_SIZE[1] - STRIDE)
    interior &= (uv[:, 1] > STRIDE) & (uv[:, 1] < IMAGE_SIZE[0] - STRIDE)
    assert interior.sum() > 20
    torch.testing.assert_close(sampled[interior], uv[interior], atol=2e-3, rtol=0)
    assert torch.all(sampled[~valid] == 0)


def test_a_point_ahead_lands_in_the_image_centre_column():
    """A voxel straight ahead of the forward camera, at camera height, projects to the principal point."""
    view = make_view()
    geometry = batch_geometry(1, flip_bev=False, augment_image=False)
    geometry["img_aug"] = torch.eye(3)[None, None]
    plan = view.plan(**geometry, image_size=(225, 400))
    features = pixel_field(True, 225, 400, 1)[None, None]
    bev = view(features, plan).view(1, 2, 2, 16, 16)  # (B, Z, C, X, Y)
    # Ego point (11, 0, 1.5) in the camera is (0, 0, 10) -> pixel (200, 112.5). Find its voxel in the LiDAR frame.
    point_lidar = transform_points(invert_transform(lidar2ego()), torch.tensor([[11.0, 0.0, 1.5]]))[0]
    # Pick the voxel centre nearest to it and project that centre exactly instead: the test is about indexing.
    index, _ = view.grid.world_to_index(point_lidar[None])
    i, j, k = index[0].tolist()
    centre = view.grid.index_to_world(index)[0]
    centre_ego = transform_points(lidar2ego(), centre[None])[0]
    camera = transform_points(invert_transform(camera2ego(0.0)), centre_ego[None])[0]
    expected_u = 200.0 + 200.0 * camera[0] / camera[2]
    expected_v = 112.5 + 200.0 * camera[1] / camera[2]
    torch.testing.assert_close(bev[0, k, :, i, j], torch.stack([expected_u, expected_v]), atol=2e-3, rtol=0)


def constant_features(values: list[float]) -> torch.Tensor:
    h, w = IMAGE_SIZE[0] // STRIDE, IMAGE_SIZE[1] // STRIDE
    return torch.stack([torch.full((2, h, w), v) for v in values])[None]  # (1, N, 2, h, w)


def overlap_and_single(view, plan_geometry):
    plan = view.plan(**plan_geometry, image_size=IMAGE_SIZE)
    counts = (plan.weight > 0).sum(dim=1).float()  # cameras seeing each voxel (one sample here)
    return plan, counts


def test_average_over_the_cameras_that_see_a_voxel_and_mask_failed_cameras():
    view = make_view("average")
    geometry = batch_geometry(2, flip_bev=False, augment_image=False)
    plan, counts = overlap_and_single(view, geometry)
    assert (counts == 2).any() and (counts == 1).any()
    bev = view(constant_features([1.0, 3.0]), plan)
    values = bev.view(1, 2, 2, 16, 16).permute(0, 3, 4, 1, 2).reshape(-1, 2)[:, 0].round(decimals=4)
    assert torch.allclose(values[counts == 2], torch.tensor(2.0))
    assert set(values[counts == 1].unique().tolist()) <= {1.0, 3.0}
    assert torch.all(values[counts == 0] == 0)

    masked = view.plan(**geometry, image_size=IMAGE_SIZE, camera_mask=torch.tensor([[False, True]]))
    bev = view(constant_features([1.0, 3.0]), masked)
    values = bev.view(1, 2, 2, 16, 16).permute(0, 3, 4, 1, 2).reshape(-1, 2)[:, 0].round(decimals=4)
    assert set(values.unique().tolist()) == {0.0, 3.0}


def test_first_mode_takes_the_first_camera_only():
    view = make_view("first")
    geometry = batch_geometry(2, flip_bev=False, augment_image=False)
    _, counts = overlap_and_single(make_view("average"), geometry)
    bev = view(constant_features([1.0, 3.0]), view.plan(**geometry, image_size=IMAGE_SIZE))
    values = bev.view(1, 2, 2, 16, 16).permute(0, 3, 4, 1, 2).reshape(-1, 2)[:, 0].round(decimals=4)
    assert torch.allclose(values[counts == 2], torch.tensor(1.0))


def test_view_transform_backpropagates_into_the_image_features():
    view = make_view()
    features = torch.randn(1, 2, 2, IMAGE_SIZE[0] // STRIDE, IMAGE_SIZE[1] // STRIDE, requires_grad=True)
    bev = view(features, view.plan(**batch_geometry(2, True, True), image_size=IMAGE_SIZE))
    bev.square().sum().backward()
    assert features.grad is not None and features.grad.abs().sum() > 0


@pytest.mark.parametrize("flip", [(False, False), (True, False), (True, True)])
def test_range_extension_samples_the_lidar_bev_cell_under_each_occupancy_column(flip):
    occ_grid = VoxelGrid((-8.0, -8.0, -1.0, 8.0, 8.0, 5.4), 0.4)
    cfg = RangeExtensionConfig(bev_range=(-12.0, -12.0, 12.0, 12.0), in_channels=2, out_channels=2)
    bvre = RangeExtension(cfg, occ_grid)
    # BEV (1, 2, X_bev, Y_bev) holding each cell's centre (x, y) in the augmented LiDAR frame.
    centres = (torch.arange(40, dtype=torch.float32) + 0.5) * 0.6 - 12.0
    xx, yy = torch.meshgrid(centres, centres, indexing="ij")
    bev = torch.stack([xx, yy])[None]
    occ_aug = torch.diag(torch.tensor([-1.0 if flip[0] else 1.0, -1.0 if flip[1] else 1.0, 1.0, 1.0]))
    bev_aug = lidar_frame_aug(occ_aug, lidar2ego()).float()
    to_bev = bvre.to_bev_frame(lidar2ego()[None], bev_aug[None], occ_aug[None])
    out = bvre(bev, bvre.sampling_grid(to_bev))  # (1, 2, 40, 40)
    assert out.shape == (1, 2, 40, 40)
    # Occupancy column centres (augmented ego frame) -> un-augment -> LiDAR -> augmented LiDAR.
    xs, ys = occ_grid.axis_centers(0), occ_grid.axis_centers(1)
    columns = torch.stack(torch.meshgrid(xs, ys, indexing="ij") + (torch.zeros(40, 40),), dim=-1).reshape(-1, 3)
    expected = transform_points(bev_aug @ invert_transform(lidar2ego()) @ invert_transform(occ_aug), columns)
    torch.testing.assert_close(out[0].permute(1, 2, 0).reshape(-1, 2), expected[:, :2], atol=1e-4, rtol=0)


def test_range_extension_zero_outside_the_bev_and_identity_in_the_lidar_frame():
    occ_grid = VoxelGrid((-50.0, -50.0, -5.0, 50.0, 50.0, 3.0), 0.5)
    cfg = RangeExtensionConfig(bev_range=(-54.0, -54.0, 54.0, 54.0), in_channels=1, out_channels=1,
                               label_frame="lidar")
    bvre = RangeExtension(cfg, occ_grid)
    ones = torch.ones(1, 1, 180, 180)
    eye = torch.eye(4)[None]
    out = bvre(ones, bvre.sampling_grid(bvre.to_bev_frame(lidar2ego()[None], eye, eye)))
    assert out.shape == (1, 1, 200, 200)
    torch.testing.assert_close(out, torch.ones_like(out))  # +-50 lies inside +-54: no zero padding reaches it
    narrow = RangeExtension(RangeExtensionConfig((-25.0, -25.0, 25.0, 25.0), 1, 1, "lidar"), occ_grid)
    far = narrow(torch.ones(1, 1, 50, 50), narrow.sampling_grid(narrow.to_bev_frame(lidar2ego()[None], eye, eye)))
    assert far[0, 0, 0, 0] == 0 and far[0, 0, 100, 100] == 1


@pytest.mark.parametrize("entry", ["flashocc_tiny", "da_occ_tiny", "daocc_tiny"])
def test_the_plan_is_computed_in_full_precision_under_autocast(entry, synthetic_batch):
    """Under bf16 autocast the rig's geometry would round ego coordinates to 8 significant bits (0.2 m at 50 m): the
    plan a forward pass uses is the float32 one, bit for bit, whatever precision the network runs at."""
    from occkit import zoo
    from occkit.models.plans import plan_tensors

    model = zoo.build(entry).eval()
    batch = synthetic_batch(batch_size=1, num_cameras=6)
    exact = plan_tensors(model.plan(batch))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        used = plan_tensors(model.current_plan(batch))
        rounded = plan_tensors(model.plan(batch))  # the plan computed under autocast, as before
    assert used.keys() == exact.keys()
    for path, tensor in exact.items():
        assert used[path].dtype == tensor.dtype and torch.equal(used[path], tensor), path
    assert any(not torch.equal(rounded[path], tensor) for path, tensor in exact.items())
