import ast
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from occkit.geometry import numpy_se3
from occkit.geometry.se3 import (
    compose,
    invert_transform,
    make_transform,
    matrix_to_quaternion,
    quaternion_to_matrix,
    rotation_about_z,
    transform_from_quaternion,
    transform_points,
)

F64 = torch.float64
SETTINGS = settings(max_examples=50, deadline=None)


def _floats(low: float, high: float) -> st.SearchStrategy[float]:
    return st.floats(low, high, allow_nan=False, allow_infinity=False)


def _quaternions(batch: int) -> st.SearchStrategy[torch.Tensor]:
    return (
        hnp.arrays(np.float64, (batch, 4), elements=_floats(-1, 1))
        .filter(lambda q: (np.linalg.norm(q, axis=-1) > 0.1).all())
        .map(torch.from_numpy)
    )


def _transforms(batch: int) -> st.SearchStrategy[torch.Tensor]:
    translations = hnp.arrays(np.float64, (batch, 3), elements=_floats(-50, 50)).map(torch.from_numpy)
    return st.builds(transform_from_quaternion, _quaternions(batch), translations)


def _points(n: int) -> st.SearchStrategy[torch.Tensor]:
    return hnp.arrays(np.float64, (n, 3), elements=_floats(-100, 100)).map(torch.from_numpy)


def _assert_rotation(matrix: torch.Tensor) -> None:
    eye = torch.eye(3, dtype=matrix.dtype).expand_as(matrix)
    torch.testing.assert_close(matrix @ matrix.transpose(-1, -2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(matrix), torch.ones(matrix.shape[:-2], dtype=matrix.dtype))


# ------------------------------------------------------------------ known values
def test_identity_quaternion_gives_identity_matrix():
    matrix = quaternion_to_matrix(torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64))
    torch.testing.assert_close(matrix, torch.eye(3, dtype=F64))


def test_quarter_turn_about_z_maps_x_axis_to_y_axis():
    half = math.sqrt(0.5)
    matrix = quaternion_to_matrix(torch.tensor([half, 0.0, 0.0, half], dtype=F64))
    torch.testing.assert_close(
        matrix @ torch.tensor([1.0, 0.0, 0.0], dtype=F64), torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    )
    torch.testing.assert_close(matrix, rotation_about_z(torch.tensor(math.pi / 2, dtype=F64)))


def test_nuscenes_lidar_top_calibration_maps_lidar_axes_to_ego():
    # nuScenes LIDAR_TOP calibrated_sensor record: about -90 deg yaw, lidar x points to the car's right.
    lidar2ego = transform_from_quaternion(
        torch.tensor([0.7077955119163518, -0.006492242056004365, 0.010646214713995808, -0.7063073142877817]),
        torch.tensor([0.943713, 0.0, 1.84023]),
    )
    points = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    expected = torch.tensor([[0.943713, -1.0, 1.84023], [1.943713, 0.0, 1.84023], [0.943713, 0.0, 1.84023]])
    torch.testing.assert_close(transform_points(lidar2ego, points), expected, atol=0.03, rtol=0)


def test_non_unit_quaternion_is_normalised():
    q = torch.tensor([0.3, -0.2, 0.9, 0.1], dtype=F64)
    torch.testing.assert_close(quaternion_to_matrix(5.0 * q), quaternion_to_matrix(q / q.norm()))
    _assert_rotation(quaternion_to_matrix(5.0 * q))


def test_rotation_about_z_is_counter_clockwise_from_above():
    yaw = torch.tensor([0.0, math.pi / 2, math.pi], dtype=F64)
    rotated = rotation_about_z(yaw) @ torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    expected = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=F64)
    torch.testing.assert_close(rotated, expected, atol=1e-12, rtol=0)


def test_make_transform_layout_and_broadcasting():
    rotation = rotation_about_z(torch.tensor(0.3, dtype=F64))
    translations = torch.arange(6, dtype=F64).reshape(2, 3)
    transform = make_transform(rotation, translations)
    assert transform.shape == (2, 4, 4)
    torch.testing.assert_close(transform[:, :3, :3], rotation.expand(2, 3, 3))
    torch.testing.assert_close(transform[:, :3, 3], translations)
    torch.testing.assert_close(transform[:, 3], torch.tensor([[0.0, 0.0, 0.0, 1.0]] * 2, dtype=F64))


# ------------------------------------------------------------------ quaternion round trips
@SETTINGS
@given(_quaternions(8))
def test_quaternion_to_matrix_is_a_rotation(q):
    _assert_rotation(quaternion_to_matrix(q))


@SETTINGS
@given(_quaternions(8))
def test_quaternion_matrix_quaternion_round_trip(q):
    back = matrix_to_quaternion(quaternion_to_matrix(q))
    unit = q / q.norm(dim=-1, keepdim=True)
    # q and -q are the same rotation; the result must be one of them, unit, with w >= 0.
    error = torch.minimum((back - unit).abs().amax(-1), (back + unit).abs().amax(-1))
    assert error.max() < 1e-9
    torch.testing.assert_close(back.norm(dim=-1), torch.ones(8, dtype=F64))
    assert (back[:, 0] >= 0).all()


@pytest.mark.parametrize(
    "axis", [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, -2.0, 0.5), (1e-8, 1.0, 1e-8)]
)
def test_matrix_to_quaternion_handles_half_turns(axis):
    # A half turn has w == 0, where the naive trace formula divides by zero.
    q = torch.tensor((0.0, *axis), dtype=F64)
    matrix = quaternion_to_matrix(q)
    back = matrix_to_quaternion(matrix)
    assert torch.isfinite(back).all()
    torch.testing.assert_close(quaternion_to_matrix(back), matrix, atol=1e-12, rtol=0)


def test_matrix_to_quaternion_is_batched_and_keeps_dtype():
    q = torch.randn(2, 3, 5, 4, generator=torch.Generator().manual_seed(0))
    back = matrix_to_quaternion(quaternion_to_matrix(q))
    assert back.shape == (2, 3, 5, 4)
    assert back.dtype == torch.float32
    torch.testing.assert_close(quaternion_to_matrix(back), quaternion_to_matrix(q), atol=1e-5, rtol=0)


# ------------------------------------------------------------------ transforms
@SETTINGS
@given(_transforms(4))
def test_invert_transform_is_the_inverse(transform):
    inverse = invert_transform(transform)
    eye = torch.eye(4, dtype=F64).expand(4, 4, 4)
    torch.testing.assert_close(inverse @ transform, eye, atol=1e-10, rtol=0)
    torch.testing.assert_close(inverse, torch.linalg.inv(transform), atol=1e-10, rtol=1e-10)


@SETTINGS
@given(_transforms(1), _points(16))
def test_transform_points_round_trip(transform, points):
    moved = transform_points(transform, points)
    torch.testing.assert_close(transform_points(invert_transform(transform), moved), points[None], atol=1e-9, rtol=0)


@SETTINGS
@given(_transforms(1), _points(16))
def test_transform_points_matches_homogeneous_matmul(transform, points):
    homogeneous = torch.cat((points, torch.ones(16, 1, dtype=F64)), dim=-1)
    expected = (transform @ homogeneous.T).transpose(-1, -2)[..., :3]
    torch.testing.assert_close(transform_points(transform, points), expected)


@SETTINGS
@given(_transforms(3), _transforms(3), _transforms(3))
def test_compose_is_associative_matmul(c, b, a):
    torch.testing.assert_close(compose(c, b, a), c @ b @ a)
    torch.testing.assert_close(compose(compose(c, b), a), compose(c, compose(b, a)))


def test_compose_chains_frames_right_to_left():
    a2b = make_transform(torch.eye(3), torch.tensor([1.0, 0.0, 0.0]))
    b2c = make_transform(rotation_about_z(torch.tensor(math.pi / 2)), torch.zeros(3))
    point_a = torch.tensor([[1.0, 0.0, 0.0]])
    # In b the point is (2, 0, 0); the quarter turn then puts it on the y axis of c.
    torch.testing.assert_close(transform_points(compose(b2c, a2b), point_a), torch.tensor([[0.0, 2.0, 0.0]]))
    torch.testing.assert_close(compose(a2b), a2b)


def test_transform_points_broadcasts_over_cameras():
    generator = torch.Generator().manual_seed(1)
    transforms = transform_from_quaternion(torch.randn(2, 6, 4, generator=generator), torch.randn(2, 6, 3))
    points = torch.randn(2, 1, 10, 3, generator=generator)
    moved = transform_points(transforms, points)
    assert moved.shape == (2, 6, 10, 3)
    torch.testing.assert_close(moved[1, 4], transform_points(transforms[1, 4], points[1, 0]))


# ------------------------------------------------------------------ gradients
def test_gradcheck_quaternion_to_matrix():
    q = torch.tensor([[0.9, 0.1, -0.3, 0.2], [0.1, 0.7, 0.5, -0.4]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(quaternion_to_matrix, (q,))


def test_gradcheck_matrix_to_quaternion():
    matrix = quaternion_to_matrix(torch.tensor([[0.9, 0.1, -0.3, 0.2], [0.1, 0.7, 0.5, -0.4]], dtype=F64))
    assert torch.autograd.gradcheck(matrix_to_quaternion, (matrix.requires_grad_(),))


def test_gradcheck_transform_points():
    transform = transform_from_quaternion(torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=F64), torch.ones(3, dtype=F64))
    points = torch.randn(5, 3, dtype=F64, generator=torch.Generator().manual_seed(2))
    assert torch.autograd.gradcheck(transform_points, (transform.requires_grad_(), points.requires_grad_()))


# ------------------------------------------------------------------ devices and bad input
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_transforms_on_cuda_match_cpu():
    generator = torch.Generator().manual_seed(3)
    q, t = torch.randn(7, 4, generator=generator), torch.randn(7, 3, generator=generator)
    points = torch.randn(7, 20, 3, generator=generator)
    transform = transform_from_quaternion(q.cuda(), t.cuda())
    moved = transform_points(invert_transform(transform), points.cuda())
    assert moved.device.type == "cuda"
    expected = transform_points(invert_transform(transform_from_quaternion(q, t)), points)
    torch.testing.assert_close(moved.cpu(), expected)
    torch.testing.assert_close(
        matrix_to_quaternion(transform[:, :3, :3]).cpu(),
        matrix_to_quaternion(transform_from_quaternion(q, t)[:, :3, :3]),
    )


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: quaternion_to_matrix(torch.zeros(3, 3)), r"quaternion must have shape \(\.\.\., 4\), got \(3, 3\)"),
        (lambda: matrix_to_quaternion(torch.zeros(4, 4)), r"rotation must have shape \(\.\.\., 3, 3\), got \(4, 4\)"),
        (lambda: make_transform(torch.eye(3), torch.zeros(4)), r"translation .* got \(4,\)"),
        (lambda: invert_transform(torch.eye(3)), r"transform must have shape \(\.\.\., 4, 4\), got \(3, 3\)"),
        (lambda: transform_points(torch.eye(4), torch.zeros(5, 2)), r"points .* got \(5, 2\)"),
        (
            lambda: transform_points(torch.eye(4), torch.zeros(3)),
            r"points must have shape \(\.\.\., N, 3\), got \(3,\)",
        ),
        (lambda: compose(torch.eye(4), torch.eye(3)), r"transforms\[1\] .* got \(3, 3\)"),
        (lambda: compose(), r"at least one"),
    ],
)
def test_bad_shapes_raise_value_error_naming_the_shape(call, message):
    with pytest.raises(ValueError, match=message):
        call()


# ------------------------------------------------------------------ numpy twins
@SETTINGS
@given(_quaternions(8), _points(8), _points(5))
def test_numpy_twins_match_the_torch_functions(q, t, points):
    """occkit.geometry.numpy_se3 (the index and info-file import) computes what the torch functions compute."""
    transform = transform_from_quaternion(q, t)
    array = numpy_se3.transform_from_quaternion(q.numpy(), t.numpy())
    np.testing.assert_allclose(array, transform.numpy(), atol=1e-12, rtol=0)
    np.testing.assert_allclose(numpy_se3.quaternion_to_matrix(q.numpy()), quaternion_to_matrix(q).numpy(), atol=1e-12)
    np.testing.assert_allclose(numpy_se3.invert_transform(array), invert_transform(transform).numpy(), atol=1e-12)
    moved = numpy_se3.transform_points(array, points.numpy()[None])
    np.testing.assert_allclose(moved, transform_points(transform, points[None]).numpy(), atol=1e-9, rtol=0)
    rotation, translations = quaternion_to_matrix(q[0]), t[:3]  # broadcast: one rotation, three translations
    np.testing.assert_allclose(
        numpy_se3.make_transform(rotation.numpy(), translations.numpy()), make_transform(rotation, translations).numpy()
    )
    yaw = torch.atan2(q[:, 1], q[:, 0]) * 2  # angles in (-2 pi, 2 pi]
    np.testing.assert_allclose(numpy_se3.rotation_about_z(yaw.numpy()), rotation_about_z(yaw).numpy(), atol=1e-15)


@SETTINGS
@given(hnp.arrays(np.float64, (3, 6), elements=_floats(-1.5, 1.5)))
def test_rotation_yaw_reads_pyquaternions_yaw(angles):
    """``R = R_x(roll) R_y(pitch) R_z(yaw)``: the yaw comes back (|pitch| < pi / 2), as pyquaternion's
    ``yaw_pitch_roll[0]``, which nuscenes-devkit takes for a box's yaw."""
    yaw, pitch, roll = angles * np.array([[2.0], [1.0], [2.0]])

    def about(axis: int, angle: np.ndarray) -> np.ndarray:
        # Turns the plane of the two other axes, in their order (about y: by -angle; the angles are random anyway).
        i, j = (k for k in range(3) if k != axis)
        cos, sin = np.cos(angle), np.sin(angle)
        matrix = np.tile(np.eye(3), (len(angle), 1, 1))
        matrix[:, i, i], matrix[:, i, j], matrix[:, j, i], matrix[:, j, j] = cos, -sin, sin, cos
        return matrix

    rotation = about(0, roll) @ about(1, pitch) @ numpy_se3.rotation_about_z(yaw)
    np.testing.assert_allclose(numpy_se3.rotation_yaw(rotation), yaw, atol=1e-9)


def test_numpy_twins_refuse_a_quaternion_that_is_no_rotation():
    with pytest.raises(ValueError, match=r"quaternion 1 \[0\.0, 0\.0, 1e-09, 0\.0\] is no rotation \(norm 1e-09"):
        numpy_se3.quaternion_to_matrix(np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1e-9, 0.0]]))
    with pytest.raises(ValueError, match="quaternion 0 .* is no rotation"):
        numpy_se3.transform_from_quaternion(np.array([np.nan, 0.0, 0.0, 1.0]), np.zeros(3))


def test_numpy_twins_import_numpy_only():
    tree = ast.parse(Path(numpy_se3.__file__).read_text())
    imported = {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    imported |= {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    assert imported == {"__future__", "numpy"}
