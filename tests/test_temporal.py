"""BEV history alignment and fusion: the pose chain, exact warps, gradients, fusion shapes and per-frame cost, and the
alignment of ground truth between key frames of a turning synthetic scene."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from occkit.geometry.se3 import make_transform, rotation_about_z, transform_points
from occkit.models.temporal import ConcatFusion, RecurrentFusion, align_bev, history_to_current

REPO = Path(__file__).resolve().parents[1]
#: 16 x 16 cells of 1 m: every coordinate of the warps below is exact in binary floating point.
EXACT_RANGE = (-8.0, -8.0, 8.0, 8.0)
OCC3D_RANGE = (-40.0, -40.0, 40.0, 40.0)


def _translation(x: float, y: float, batch: int = 1) -> torch.Tensor:
    matrix = torch.eye(4).repeat(batch, 1, 1)
    matrix[:, 0, 3], matrix[:, 1, 3] = x, y
    return matrix


def _pose(yaw: float, x: float, y: float, z: float = 0.0) -> torch.Tensor:
    rotation = rotation_about_z(torch.tensor(yaw, dtype=torch.float64))
    return make_transform(rotation, torch.tensor([x, y, z], dtype=torch.float64))


# ------------------------------------------------------------------------------------------------ the pose chain
def test_history_to_current_maps_a_fixed_world_point_between_the_frames():
    prev, curr = _pose(0.3, 812.5, 1204.25, 0.1), _pose(0.42, 816.0, 1206.5, 0.12)
    # An augmentation with a flip, a rotation and a scale: inverted as a general matrix, not as a rigid one.
    flip_y = torch.diag(torch.tensor([1.0, -1.0, 1.0, 1.0], dtype=torch.float64))
    aug = make_transform(rotation_about_z(torch.tensor(0.2, dtype=torch.float64)) * 1.05, torch.zeros(3)) @ flip_y
    world = torch.tensor([[830.0, 1190.0, 0.5], [800.0, 1210.0, 2.0]], dtype=torch.float64)
    in_prev = transform_points(aug, transform_points(torch.linalg.inv(prev), world))
    in_curr = transform_points(aug, transform_points(torch.linalg.inv(curr), world))
    current_to_history = history_to_current(prev[None], curr[None], aug[None], aug[None])
    assert current_to_history.shape == (1, 4, 4) and current_to_history.dtype == torch.float64
    torch.testing.assert_close(transform_points(current_to_history[0], in_curr), in_prev, rtol=0, atol=1e-9)
    # Without augmentation it is the relative ego pose.
    torch.testing.assert_close(history_to_current(prev[None], curr[None])[0], torch.linalg.inv(prev) @ curr)


def test_history_to_current_of_one_frame_with_itself_is_the_identity():
    pose = _pose(-2.0, 1500.0, 300.0)[None]
    torch.testing.assert_close(history_to_current(pose, pose), torch.eye(4, dtype=torch.float64)[None])


# --------------------------------------------------------------------------------------------------- alignment
def test_identity_gives_the_input_back():
    history = torch.randn(2, 3, 16, 16)
    aligned, valid = align_bev(history, torch.eye(4).expand(2, 4, 4), EXACT_RANGE)
    assert torch.equal(aligned, history) and valid.shape == (2, 1, 16, 16) and valid.all()
    # On Occ3D's 0.4 m cells the normalised coordinates are rounded in float32: equal to a few ulps of a pixel.
    history = torch.randn(1, 2, 200, 200)
    aligned, valid = align_bev(history, torch.eye(4)[None], OCC3D_RANGE)
    assert valid.all()
    torch.testing.assert_close(aligned, history, rtol=0, atol=1e-3)


def test_translation_by_whole_cells_shifts_the_map_and_vacates_the_border():
    history = torch.randn(2, 3, 16, 16) + 5.0  # no zeros of its own
    # The earlier frame sees the current cell (i, j) at (i + 3, j - 2): the ego drove 3 m back and 2 m to the left.
    aligned, valid = align_bev(history, _translation(3.0, -2.0, batch=2), EXACT_RANGE)
    assert torch.equal(aligned[:, :, :13, 2:], history[:, :, 3:, :14])
    assert valid[:, :, :13, 2:].all()
    vacated = torch.ones(16, 16, dtype=torch.bool)
    vacated[:13, 2:] = False
    assert not valid[:, 0, vacated].any()
    assert torch.equal(aligned[:, :, vacated], torch.zeros_like(aligned[:, :, vacated]))


def test_a_quarter_turn_of_yaw_rotates_the_map():
    history = torch.randn(1, 2, 16, 16)
    # Exact entries: the current frame is the earlier one turned 90 degrees to the left (x -> y).
    turn = torch.tensor([[0.0, -1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    aligned, valid = align_bev(history, turn[None], EXACT_RANGE)
    assert valid.all()
    # What was ahead of the earlier frame (large x) is now on the current frame's right (small y): the map turns
    # clockwise in (x, y) index space, from dim 3 towards dim 2.
    assert torch.equal(aligned, torch.rot90(history, k=-1, dims=(2, 3)))
    assert torch.equal(aligned[0, :, 4, 0], history[0, :, 15, 4])


def test_a_small_turn_moves_points_as_the_pose_says():
    """A point feature lands where the rigid transform puts it, to within the bilinear footprint."""
    history = torch.zeros(1, 1, 200, 200)
    history[0, 0, 150, 120] = 1.0  # cell centre (20.2, 8.2) m in the earlier frame
    current_to_history = history_to_current(_pose(0.0, 0.0, 0.0)[None], _pose(math.radians(5.0), 4.0, 1.0)[None])
    aligned, _ = align_bev(history, current_to_history, OCC3D_RANGE)
    peak = torch.tensor(divmod(int(aligned[0, 0].argmax()), 200), dtype=torch.float64)
    centre = torch.tensor([[-40.0 + 0.4 * (peak[0] + 0.5), -40.0 + 0.4 * (peak[1] + 0.5), 0.0]], dtype=torch.float64)
    in_history = transform_points(current_to_history[0], centre)[0]
    assert torch.linalg.vector_norm(in_history[:2] - torch.tensor([20.2, 8.2], dtype=torch.float64)) < 0.4


def test_gradients_reach_the_history_features():
    history = (torch.randn(1, 2, 16, 16) + 3.0).requires_grad_()
    weights = torch.randn(1, 2, 16, 16)
    aligned, _ = align_bev(history, _translation(2.0, 1.0), EXACT_RANGE)
    (aligned * weights).sum().backward()
    # Each history cell read by a current cell receives that cell's weight; the cells nobody reads receive none.
    expected = torch.zeros_like(weights)
    expected[:, :, 2:, 1:] = weights[:, :, :14, :15]
    assert torch.equal(history.grad, expected)


def test_gradients_reach_the_pose_and_the_cpu_backward_is_repeatable():
    def run() -> tuple[torch.Tensor, torch.Tensor]:
        history = torch.randn(2, 4, 32, 32, generator=torch.Generator().manual_seed(0)).requires_grad_()
        pose = history_to_current(_pose(0.0, 0.0, 0.0).expand(2, 4, 4), _pose(0.1, 1.3, -0.4).expand(2, 4, 4))
        pose = pose.float().requires_grad_()
        aligned, _ = align_bev(history, pose, OCC3D_RANGE)
        aligned.square().sum().backward()
        return history.grad, pose.grad

    first, second = run(), run()
    assert torch.isfinite(first[1]).all() and first[1].abs().sum() > 0
    assert torch.equal(first[0], second[0]) and torch.equal(first[1], second[1])


def test_half_precision_maps_are_sampled_in_float32():
    history = torch.randn(1, 2, 16, 16).bfloat16()
    aligned, valid = align_bev(history, _translation(0.5, 0.25), EXACT_RANGE)
    expected, _ = align_bev(history.float(), _translation(0.5, 0.25), EXACT_RANGE)
    assert aligned.dtype == torch.bfloat16 and valid.dtype == torch.bool
    assert torch.equal(aligned, expected.bfloat16())


def test_align_checks_its_arguments():
    with pytest.raises(ValueError, match="current_to_history"):
        align_bev(torch.zeros(2, 1, 4, 4), torch.eye(4)[None], EXACT_RANGE)
    with pytest.raises(ValueError, match="bev_range"):
        align_bev(torch.zeros(1, 1, 4, 4), torch.eye(4)[None], (8.0, -8.0, -8.0, 8.0))
    with pytest.raises(ValueError, match="history"):
        align_bev(torch.zeros(1, 4, 4), torch.eye(4)[None], EXACT_RANGE)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_alignment_matches_the_cpu():
    history = torch.randn(2, 3, 64, 64)
    pose = history_to_current(_pose(0.0, 0.0, 0.0).expand(2, 4, 4), _pose(0.05, 2.1, 0.3).expand(2, 4, 4))
    on_cpu, valid_cpu = align_bev(history, pose, OCC3D_RANGE)
    on_gpu, valid_gpu = align_bev(history.cuda(), pose.cuda(), OCC3D_RANGE)
    assert torch.equal(valid_gpu.cpu(), valid_cpu)
    torch.testing.assert_close(on_gpu.cpu(), on_cpu, rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------------------------------------------ fusion
def _inputs_of(module: torch.nn.Module) -> list[torch.Tensor]:
    seen: list[torch.Tensor] = []
    module.register_forward_hook(lambda _m, inputs, _out: seen.append(inputs[0].detach().clone()))
    return seen


def test_concat_fusion_concatenates_current_then_the_aligned_frames():
    # BEVDet4D's fusion has no layer of its own: the BEV encoder's first block convolves the concatenation.
    fusion = ConcatFusion(channels=4, history=2, bev_range=EXACT_RANGE, with_valid=True)
    assert fusion.out_channels == 4 * 3 + 2 and not list(fusion.parameters())
    current, history = torch.randn(2, 4, 16, 16), torch.randn(2, 2, 4, 16, 16)
    transforms = torch.stack([torch.eye(4).expand(2, 4, 4), _translation(1.0, 0.0, batch=2)], dim=1)
    fused = fusion(current, history, transforms)
    assert fused.shape == (2, 14, 16, 16)
    assert torch.equal(fused[:, :4], current)
    assert torch.equal(fused[:, 4:8], history[:, 0])
    assert torch.equal(fused[:, 8:12, :15], history[:, 1, :, 1:])
    assert fused[:, 12].all() and not fused[:, 13, 15].any() and fused[:, 13, :15].all()
    plain = ConcatFusion(channels=4, history=3, bev_range=EXACT_RANGE)
    assert plain.out_channels == 16
    assert plain(current, torch.randn(2, 3, 4, 16, 16), torch.eye(4).expand(2, 3, 4, 4)).shape == (2, 16, 16, 16)
    with pytest.raises(ValueError, match="history"):
        plain(current, history, transforms)


def test_recurrent_fusion_starts_from_the_current_frame_and_resets_per_sample():
    fusion = RecurrentFusion(channels=3, bev_range=EXACT_RANGE).eval()
    assert fusion.fuse.conv1.in_channels == 2 * 3 + 1
    seen = _inputs_of(fusion.fuse)
    first, second = torch.randn(2, 3, 16, 16), torch.randn(2, 3, 16, 16)
    state = fusion(first)
    assert state.shape == (2, 3, 16, 16)
    assert torch.equal(seen[0][:, 3:6], first) and seen[0][:, 6].all()
    # Sample 0 starts a new scene at the second frame; sample 1 goes on with its state, aligned.
    fusion(second, state, _translation(1.0, 0.0, batch=2), reset=torch.tensor([True, False]))
    step = seen[1]
    assert torch.equal(step[:, :3], second)
    assert torch.equal(step[0, 3:6], second[0]) and step[0, 6].all()
    assert torch.equal(step[1, 3:6, :15], state[1, :, 1:]) and not step[1, 6, 15].any()
    with pytest.raises(ValueError, match="current_to_previous"):
        fusion(second, state)


def test_a_recurrent_frame_costs_the_same_whatever_the_history_length():
    fusion = RecurrentFusion(channels=4, bev_range=OCC3D_RANGE).eval()
    frames = 12
    poses = [_pose(0.03 * t, 4.0 * t, 0.2 * t) for t in range(frames)]
    steps = [history_to_current(poses[t - 1][None], poses[t][None])[0] for t in range(1, frames)]
    transforms = torch.stack([torch.eye(4, dtype=torch.float64), *steps])[None]  # (1, T, 4, 4)
    bevs = torch.randn(1, frames, 4, 40, 40)
    calls = []
    fusion.fuse.register_forward_hook(lambda _m, inputs, _out: calls.append(tuple(inputs[0].shape)))
    with torch.no_grad():
        states = fusion.unroll(bevs, transforms)
    # The same modules once per frame, on inputs of the same size, however long the history behind them.
    assert states.shape == (1, frames, 4, 40, 40)
    assert calls == [(1, 9, 40, 40)] * frames
    flops = []
    for t in (1, 5, 11):
        with torch.no_grad(), FlopCounterMode(display=False) as counter:
            step = fusion(bevs[:, t], states[:, t - 1], transforms[:, t])
        flops.append(counter.get_total_flops())
        # A frame needs the previous state only: one step from it reproduces the unrolled sequence.
        assert torch.equal(step, states[:, t])
    assert flops[0] > 0 and flops[0] == flops[1] == flops[2]


def test_recurrent_fusion_backpropagates_through_the_state_unless_detached():
    fusion = RecurrentFusion(channels=2, bev_range=EXACT_RANGE)
    bevs = torch.randn(1, 3, 2, 16, 16, requires_grad=True)
    transforms = _translation(1.0, 0.0)[:, None].expand(1, 3, 4, 4)
    fusion.unroll(bevs, transforms)[:, -1].sum().backward()
    assert bevs.grad[:, 0].abs().sum() > 0
    bevs.grad = None
    fusion.unroll(bevs, transforms, detach=True)[:, -1].sum().backward()
    assert bevs.grad[:, 0].abs().sum() == 0 and bevs.grad[:, 2].abs().sum() > 0


# ---------------------------------------------------------------------- ground truth between key frames (sim)
def _benchmark():
    """benchmarks/temporal_alignment.py as a module (benchmarks/ is not a package)."""
    name = "benchmarks_temporal_alignment"
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / "temporal_alignment.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # its dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def turning_scene(tmp_path_factory) -> dict:
    """benchmarks/temporal_alignment.py's measurement on one scene of 3 key frames on a bend (2.6 deg per frame)."""
    benchmark = _benchmark()
    root = benchmark.simulate(seed=12, frames=3, out=tmp_path_factory.mktemp("temporal") / "data", density=0.2)
    (row,) = benchmark.measure_dataset(root)
    return row


def test_ground_truth_aligned_between_key_frames_agrees_where_ignoring_ego_motion_does_not(turning_scene):
    row = turning_scene
    assert row["pairs"] == 2 and row["yaw_deg_per_key_frame"]["mean"] > 2.0 and row["metres_per_key_frame"] > 3.0
    # Measured here: agreement (static mIoU) aligned 0.988 (0.959), identity 0.754 (0.471), inverted 0.625 (0.349),
    # one cell off 0.966 (0.887). benchmarks/temporal_alignment.py's five scenes of 6 key frames: aligned 0.982..0.992,
    # identity 0.72..0.84.
    assert row["aligned"]["agreement"] >= 0.95 and row["aligned"]["static_miou"] >= 0.9
    assert row["identity"]["agreement"] < 0.95 and row["identity"]["static_miou"] < 0.9
    assert row["inverted"]["agreement"] < 0.95 and row["inverted"]["static_miou"] < 0.9
    assert row["aligned"]["share_of_cells_compared"] > 0.5


def test_the_alignment_is_better_than_one_cell(turning_scene):
    row = turning_scene
    # Moving the aligned sampling points by one cell costs 0.022 of agreement and 0.072 of static mIoU here.
    assert row["aligned"]["agreement"] > row["off_by_one_cell"]["agreement"] + 0.01
    assert row["aligned"]["static_miou"] > row["off_by_one_cell"]["static_miou"] + 0.03


def test_a_sequence_wide_bev_augmentation_leaves_the_agreement_unchanged(turning_scene):
    row = turning_scene
    assert abs(row["aligned_augmented"]["agreement"] - row["aligned"]["agreement"]) <= 0.002
    assert abs(row["aligned_augmented"]["static_miou"] - row["aligned"]["static_miou"]) <= 0.005
