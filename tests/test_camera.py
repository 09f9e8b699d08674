import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from occkit.geometry.camera import (
    apply_image_aug,
    crop_matrix,
    flip_matrix,
    image_aug_matrix,
    image_aug_to_post_rot_tran,
    in_image_mask,
    invert_image_aug,
    post_rot_tran_to_image_aug,
    project,
    project_points,
    resize_matrix,
    rotate_matrix,
    unproject,
)
from occkit.geometry.se3 import make_transform, rotation_about_z, transform_from_quaternion

F64 = torch.float64
SETTINGS = settings(max_examples=50, deadline=None)
# nuScenes CAM_FRONT-like intrinsics for a 1600 x 900 image.
K_FRONT = torch.tensor([[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]], dtype=F64)


def _floats(low: float, high: float) -> st.SearchStrategy[float]:
    return st.floats(low, high, allow_nan=False, allow_infinity=False)


def _intrinsics() -> st.SearchStrategy[torch.Tensor]:
    def build(fx, fy, skew, cx, cy):
        return torch.tensor([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=F64)

    return st.builds(build, _floats(100, 2000), _floats(100, 2000), _floats(-5, 5), _floats(0, 1600), _floats(0, 900))


def _pixels(n: int) -> st.SearchStrategy[torch.Tensor]:
    return hnp.arrays(np.float64, (n, 2), elements=_floats(-2000, 2000)).map(torch.from_numpy)


@st.composite
def _aug_params(draw):
    resize = draw(_floats(0.2, 1.5))
    width, height = round(1600 * resize), round(900 * resize)
    crop_w, crop_h = draw(st.integers(64, width)), draw(st.integers(64, height))
    left, top = draw(st.integers(0, width - crop_w)), draw(st.integers(0, height - crop_h))
    return resize, (left, top, left + crop_w, top + crop_h), draw(st.booleans()), draw(_floats(-10, 10))


def _image_augs() -> st.SearchStrategy[torch.Tensor]:
    return _aug_params().map(lambda p: image_aug_matrix(*p, dtype=F64))


def _bevdet_post_rot_tran(resize, crop, flip, rotate):
    """BEVDet ``PrepareImageInputs.img_transform`` post-homography bookkeeping, transcribed."""

    def get_rot(h):
        return torch.tensor([[math.cos(h), math.sin(h)], [-math.sin(h), math.cos(h)]], dtype=F64)

    post_rot = torch.eye(2, dtype=F64)
    post_tran = torch.zeros(2, dtype=F64)
    post_rot *= resize
    post_tran -= torch.tensor(crop[:2], dtype=F64)
    if flip:
        A = torch.tensor([[-1.0, 0.0], [0.0, 1.0]], dtype=F64)
        b = torch.tensor([crop[2] - crop[0], 0.0], dtype=F64)
        post_rot = A.matmul(post_rot)
        post_tran = A.matmul(post_tran) + b
    A = get_rot(rotate / 180 * math.pi)
    b = torch.tensor([crop[2] - crop[0], crop[3] - crop[1]], dtype=F64) / 2
    b = A.matmul(-b) + b
    post_rot = A.matmul(post_rot)
    post_tran = A.matmul(post_tran) + b
    post_rot3, post_tran3 = torch.eye(3, dtype=F64), torch.zeros(3, dtype=F64)
    post_rot3[:2, :2] = post_rot
    post_tran3[:2] = post_tran
    return post_rot3, post_tran3


# ------------------------------------------------------------------ projection
def test_project_hand_checked_values():
    intrinsics = torch.tensor([[1000.0, 5.0, 800.0], [0.0, 900.0, 450.0], [0.0, 0.0, 1.0]], dtype=F64)
    points = torch.tensor([[2.0, -1.0, 10.0], [0.0, 0.0, 4.0]], dtype=F64)
    uv, depth = project(points, intrinsics)
    # u = 1000 * 0.2 + 5 * -0.1 + 800, v = 900 * -0.1 + 450; the optical axis hits the principal point.
    torch.testing.assert_close(uv, torch.tensor([[999.5, 360.0], [800.0, 450.0]], dtype=F64))
    torch.testing.assert_close(depth, torch.tensor([10.0, 4.0], dtype=F64))


def test_project_is_finite_on_and_behind_the_image_plane():
    points = torch.tensor([[1.0, 1.0, 0.0], [1.0, 1.0, -1e-9], [1.0, 1.0, -2.0]], dtype=F64)
    uv, depth = project(points, K_FRONT)
    assert torch.isfinite(uv).all()
    torch.testing.assert_close(depth, points[:, 2])
    # Clamping keeps the sign of z: a point just behind the camera projects mirrored, like any point behind it.
    assert uv[0, 0] > K_FRONT[0, 2] and uv[1, 0] < K_FRONT[0, 2] and uv[2, 0] < K_FRONT[0, 2]


@SETTINGS
@given(
    _intrinsics(),
    hnp.arrays(np.float64, (32, 2), elements=_floats(-50, 50)).map(torch.from_numpy),
    hnp.arrays(np.float64, (32,), elements=_floats(0.1, 100)).map(torch.from_numpy),
)
def test_project_unproject_round_trip(intrinsics, xy, z):
    points = torch.cat((xy, z[:, None]), dim=-1)
    uv, depth = project(points, intrinsics)
    torch.testing.assert_close(unproject(uv, depth, intrinsics), points, atol=1e-8, rtol=1e-8)


@SETTINGS
@given(_intrinsics(), _pixels(32), hnp.arrays(np.float64, (32,), elements=_floats(0.1, 100)).map(torch.from_numpy))
def test_unproject_project_round_trip(intrinsics, uv, depth):
    points = unproject(uv, depth, intrinsics)
    torch.testing.assert_close(points[:, 2], depth)
    uv_back, depth_back = project(points, intrinsics)
    torch.testing.assert_close(uv_back, uv, atol=1e-8, rtol=1e-8)
    torch.testing.assert_close(depth_back, depth)


def test_in_image_mask_uses_half_open_pixel_bounds():
    uv = torch.tensor([[0.0, 0.0], [1599.999, 899.999], [1600.0, 10.0], [10.0, 900.0], [-1e-6, 10.0], [10.0, 10.0]])
    depth = torch.tensor([1.0, 1.0, 1.0, 1.0, 1.0, 0.0])
    mask = in_image_mask(uv, depth, (900, 1600))
    assert mask.tolist() == [True, True, False, False, False, False]


# ------------------------------------------------------------------ project_points
def _front_cam2ego():
    """A camera at the ego origin looking along ego +x: camera (right, down, forward) = ego (-y, -z, x)."""
    rotation = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=F64)
    return make_transform(rotation, torch.zeros(3, dtype=F64))


def _front_camera():
    """ego2cam of :func:`_front_cam2ego`."""
    return torch.linalg.inv(_front_cam2ego())


def test_project_points_marks_points_behind_and_outside_the_augmented_image_invalid():
    ego2cam = _front_camera()
    aug = image_aug_matrix(0.44, (0, 140, 704, 396), dtype=F64)
    points = torch.tensor(
        [
            [10.0, 0.0, 0.0],  # straight ahead: inside
            [-10.0, 0.0, 0.0],  # behind the camera, projects onto the principal point
            [10.0, 0.0, 3.5],  # high up: inside the original image, above the crop
        ],
        dtype=F64,
    )
    uv, depth, valid = project_points(points, ego2cam, K_FRONT, aug, (256, 704))
    torch.testing.assert_close(depth, torch.tensor([10.0, -10.0, 10.0], dtype=F64))
    uv_orig, _ = project(torch.tensor([[0.0, -3.5, 10.0]], dtype=F64), K_FRONT)
    assert in_image_mask(uv_orig, torch.ones(1, dtype=F64), (900, 1600)).all()
    assert valid.tolist() == [True, False, False]
    torch.testing.assert_close(uv[0], apply_image_aug(aug, K_FRONT[:2, 2]))


def test_project_points_without_augmentation_uses_the_original_image():
    uv, depth, valid = project_points(
        torch.tensor([[10.0, 0.0, 0.0]], dtype=F64), _front_camera(), K_FRONT, None, (900, 1600)
    )
    torch.testing.assert_close(uv, K_FRONT[None, :2, 2])
    torch.testing.assert_close(depth, torch.tensor([10.0], dtype=F64))
    assert valid.tolist() == [True]


def test_project_points_broadcasts_over_a_camera_dimension():
    generator = torch.Generator().manual_seed(0)
    batch, cams, n = 2, 6, 50
    yaw = torch.linspace(0, 2 * math.pi, cams + 1, dtype=F64)[:cams]
    # Six cameras yawed around the car, as on nuScenes.
    ego2cams = torch.linalg.inv(
        make_transform(rotation_about_z(yaw), torch.zeros(cams, 3, dtype=F64)) @ _front_cam2ego()
    )
    ego2cams = ego2cams.expand(batch, cams, 4, 4)
    intrinsics = K_FRONT.expand(batch, cams, 3, 3)
    augs = torch.stack([image_aug_matrix(0.44, (0, 140, 704, 396), flip=i % 2 == 1, dtype=F64) for i in range(cams)])
    augs = augs.expand(batch, cams, 3, 3)
    points = (torch.rand(batch, 1, n, 3, generator=generator, dtype=F64) - 0.5) * torch.tensor(
        [80.0, 80.0, 4.0], dtype=F64
    )

    uv, depth, valid = project_points(points, ego2cams, intrinsics, augs, (256, 704))

    assert uv.shape == (batch, cams, n, 2) and depth.shape == valid.shape == (batch, cams, n)
    assert valid.any(dim=1).float().mean() > 0.5  # six cameras around the car see most points
    for b in range(batch):
        for c in range(cams):
            uv_bc, depth_bc, valid_bc = project_points(points[b, 0], ego2cams[b, c], K_FRONT, augs[b, c], (256, 704))
            torch.testing.assert_close(uv[b, c], uv_bc)
            torch.testing.assert_close(depth[b, c], depth_bc)
            assert torch.equal(valid[b, c], valid_bc)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_project_points_on_cuda_matches_cpu():
    generator = torch.Generator().manual_seed(4)
    ego2cam = transform_from_quaternion(torch.randn(3, 4, generator=generator), torch.randn(3, 3, generator=generator))
    intrinsics = K_FRONT.float().expand(3, 3, 3)
    aug = image_aug_matrix(0.5, (10, 100, 714, 356), flip=True, rotate_deg=4.0)
    points = torch.randn(1, 200, 3, generator=generator) * 20
    cpu = project_points(points, ego2cam, intrinsics, aug, (256, 704))
    cuda = project_points(points.cuda(), ego2cam.cuda(), intrinsics.cuda(), aug.cuda(), (256, 704))
    assert all(t.device.type == "cuda" for t in cuda)
    torch.testing.assert_close(cuda[0].cpu(), cpu[0], rtol=1e-4, atol=1e-2)
    torch.testing.assert_close(cuda[1].cpu(), cpu[1])
    # float32 rounding differs between devices, which can flip a point lying exactly on the image border.
    assert (cuda[2].cpu() == cpu[2]).float().mean() > 0.99


# ------------------------------------------------------------------ image augmentation
def test_image_aug_matrix_known_value():
    aug = image_aug_matrix(0.44, (0, 140, 704, 396))
    assert aug.shape == (3, 3) and aug.dtype == torch.float32
    # The centre of a 1600 x 900 image, resized to 704 x 396 and cropped by 140 rows at the top.
    torch.testing.assert_close(apply_image_aug(aug, torch.tensor([800.0, 450.0])), torch.tensor([352.0, 58.0]))


def test_flip_maps_u_to_width_minus_u():
    uv = torch.tensor([[0.0, 5.0], [0.5, 7.0], [703.5, 1.0], [352.0, 3.0]], dtype=F64)
    flipped = apply_image_aug(flip_matrix(704, dtype=F64), uv)
    torch.testing.assert_close(flipped, torch.stack((704 - uv[:, 0], uv[:, 1]), dim=-1))


def test_elementary_matrices():
    uv = torch.tensor([10.0, 20.0], dtype=F64)
    torch.testing.assert_close(apply_image_aug(resize_matrix(0.5, dtype=F64), uv), torch.tensor([5.0, 10.0], dtype=F64))
    torch.testing.assert_close(
        apply_image_aug(resize_matrix((2.0, 3.0), dtype=F64), uv), torch.tensor([20.0, 60.0], dtype=F64)
    )
    torch.testing.assert_close(apply_image_aug(crop_matrix(4, 5, dtype=F64), uv), torch.tensor([6.0, 15.0], dtype=F64))
    # Positive angles turn counter-clockwise on screen: a point right of the centre moves up (smaller v).
    rotated = apply_image_aug(rotate_matrix(90.0, (100.0, 50.0), dtype=F64), torch.tensor([110.0, 50.0], dtype=F64))
    torch.testing.assert_close(rotated, torch.tensor([100.0, 40.0], dtype=F64))


def test_rotate_and_flip_match_pil():
    image_module = pytest.importorskip("PIL.Image")
    size = 8
    pixel = (5, 2)  # (column, row)
    array = np.zeros((size, size), dtype=np.uint8)
    array[pixel[1], pixel[0]] = 255
    image = image_module.fromarray(array)
    centre = torch.tensor([pixel[0] + 0.5, pixel[1] + 0.5], dtype=F64)
    cases = [
        (
            image.rotate(90, resample=image_module.Resampling.NEAREST),
            rotate_matrix(90.0, (size / 2, size / 2), dtype=F64),
        ),
        (image.transpose(image_module.Transpose.FLIP_LEFT_RIGHT), flip_matrix(size, dtype=F64)),
    ]
    for transformed, aug in cases:
        row, column = np.argwhere(np.asarray(transformed) == 255)[0]
        torch.testing.assert_close(apply_image_aug(aug, centre), torch.tensor([column + 0.5, row + 0.5], dtype=F64))


@SETTINGS
@given(_aug_params())
def test_image_aug_matrix_matches_bevdet_post_rot_tran(params):
    post_rot, post_tran = _bevdet_post_rot_tran(*params)
    aug = image_aug_matrix(*params, dtype=F64)
    torch.testing.assert_close(aug, post_rot_tran_to_image_aug(post_rot, post_tran))
    converted_rot, converted_tran = image_aug_to_post_rot_tran(aug)
    torch.testing.assert_close(converted_rot, post_rot)
    torch.testing.assert_close(converted_tran, post_tran)


@SETTINGS
@given(_image_augs(), _pixels(16))
def test_image_aug_invert_round_trip(aug, uv):
    inverse = invert_image_aug(aug)
    torch.testing.assert_close(apply_image_aug(inverse, apply_image_aug(aug, uv)), uv, atol=1e-9, rtol=0)
    torch.testing.assert_close(inverse, torch.linalg.inv(aug), atol=1e-12, rtol=1e-9)


@SETTINGS
@given(st.lists(_image_augs(), min_size=3, max_size=3).map(torch.stack))
def test_post_rot_tran_round_trip(augs):
    post_rot, post_tran = image_aug_to_post_rot_tran(augs)
    assert post_rot.shape == (3, 3, 3) and post_tran.shape == (3, 3)
    torch.testing.assert_close(post_rot[:, 2], torch.tensor([[0.0, 0.0, 1.0]] * 3, dtype=F64))
    torch.testing.assert_close(post_tran[:, 2], torch.zeros(3, dtype=F64))
    torch.testing.assert_close(post_rot_tran_to_image_aug(post_rot, post_tran), augs)


def test_image_aug_matrix_respects_dtype():
    aug = image_aug_matrix((0.5, 0.6), (1, 2, 300, 200), flip=True, rotate_deg=3.0, dtype=F64)
    assert aug.dtype == F64
    torch.testing.assert_close(aug[2], torch.tensor([0.0, 0.0, 1.0], dtype=F64))


# ------------------------------------------------------------------ gradients
def test_gradcheck_project_and_unproject():
    points = torch.tensor([[1.0, -2.0, 8.0], [0.3, 0.4, 2.0]], dtype=F64, requires_grad=True)
    intrinsics = K_FRONT.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda p, k: project(p, k)[0], (points, intrinsics))
    uv = torch.tensor([[100.0, 200.0], [1500.0, 800.0]], dtype=F64, requires_grad=True)
    depth = torch.tensor([3.0, 40.0], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(unproject, (uv, depth, intrinsics))


def test_gradcheck_apply_image_aug():
    aug = image_aug_matrix(0.44, (0, 140, 704, 396), flip=True, rotate_deg=5.0, dtype=F64).requires_grad_()
    uv = torch.tensor([[100.0, 200.0], [1500.0, 800.0]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(apply_image_aug, (aug, uv))


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: project(torch.zeros(5, 2), K_FRONT), r"points_cam must have shape \(\.\.\., 3\), got \(5, 2\)"),
        (
            lambda: project(torch.zeros(5, 3), torch.eye(4)),
            r"intrinsics must have shape \(\.\.\., 3, 3\), got \(4, 4\)",
        ),
        (
            lambda: unproject(torch.zeros(5, 3), torch.ones(5), K_FRONT),
            r"uv must have shape \(\.\.\., 2\), got \(5, 3\)",
        ),
        (lambda: apply_image_aug(torch.eye(2), torch.zeros(2)), r"image_aug .* got \(2, 2\)"),
        (lambda: in_image_mask(torch.zeros(3, 2), torch.ones(3), (900,)), r"image_size .* \(H, W\)"),
        (
            lambda: project_points(
                torch.zeros(4, 3, dtype=F64), torch.eye(4, dtype=F64), K_FRONT, torch.eye(2), (900, 1600)
            ),
            r"image_aug .* got \(2, 2\)",
        ),
    ],
)
def test_bad_shapes_raise_value_error_naming_the_shape(call, message):
    with pytest.raises(ValueError, match=message):
        call()
