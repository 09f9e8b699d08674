"""BEV history: aligning earlier frames' BEV maps with the current frame and fusing them into it.

A BEV map ``(B, C, X, Y)`` (docs/conventions.md: dim 2 along x forward, dim 3 along y left) lies in the (augmented)
frame of its own key frame and covers ``bev_range = (x_min, y_min, x_max, y_max)`` there; cell ``(i, j)`` covers
``[x_min + i * sx, x_min + (i + 1) * sx) x [y_min + j * sy, y_min + (j + 1) * sy)`` and its centre is
``x_min + (i + 0.5) * sx, y_min + (j + 0.5) * sy`` (``sx = (x_max - x_min) / X``), as a column of
:class:`~occkit.geometry.VoxelGrid`. An earlier frame's map is brought onto the current one by backward warping:
every current cell centre is mapped into the earlier frame (:func:`history_to_current` gives the matrix) and the
earlier map is read there (:func:`align_bev`).

**Alignment.** :func:`align_bev` samples with ``grid_sample`` (bilinear, ``align_corners=False``) at coordinates
normalised as :class:`~occkit.models.range_extension.RangeExtension` normalises them: ``-1`` and ``+1`` are the map's
edges, so cell centres sit where ``align_corners=False`` puts pixel centres, and ``grid_sample``'s first coordinate is
y (width, dim 3), its second x (height, dim 2). BEVDet4D's ``gen_grid`` / ``shift_feature`` transform pixel indices
and sample with ``align_corners=True`` (pixel ``i`` at ``-1 + 2 i / (W - 1)``, again its centre), the same reading of
a pixel position; but they map index ``i`` to ``x_min + i * interval``, the cell's lower corner, so their rotations
pivot half a cell away from the ego origin (on 0.4 m cells, 1.5 cm off after a 3 degree turn). Here the rotation
acts on the true cell centres. The columns are mapped at height 0 (the ground), as in BEVDet4D (which keeps only the
x, y and homogeneous rows and columns of the 4x4) and RangeExtension. Points that leave the earlier map are marked
invalid and set to exactly zero; inside it, the half cell between the outermost centres and the map's edge holds the
edge value (``padding_mode="border"``) instead of fading towards zero.

**Short histories: concatenate and convolve** (:class:`ConcatFusion`). BEVDet4D (``bevdet4d.py`` of the FlashOcc
code) has no layer of its own for the fusion: each frame's BEV first goes through ``pre_process`` (one BasicBlock at
stride 1, applied to every frame before alignment), then the current BEV and the K aligned earlier ones are
concatenated on the channel axis, current first (``torch.cat(bev_feat_list, dim=1)``), and go straight into the BEV
encoder, whose first layer is a BasicBlock (3x3 conv-BN-ReLU, 3x3 conv-BN, plus a shortcut that is a biased 3x3 conv
without BatchNorm; ``CustomResNet`` with ``numC_input = C * (K + 1)``) at stride 2. :class:`ConcatFusion` is the
alignment and the concatenation; :class:`TemporalFusion` adds ``pre_process``; the model's BEV encoder, built with
``(K + 1) C`` input channels, is the convolution. The earlier frames run without gradient, as in BEVDet4D
(``torch.no_grad()`` around the adjacent frames' ``prepare_bev_feat``), and at the start of a scene the missing
frames repeat the current one with an identity transform (its data pipeline pads with the key frame).

**Long histories: one recurrent state** (:class:`RecurrentFusion`). DA-Occ's 16-frame row (39.3 mIoU) fuses a long
history at the BEV level; the long-history fusion it cites, SparseOcc's, and the BEV-level designs differ in what a
frame costs as the history grows:

* SparseOcc keeps the image features of the last frames in a memory queue (up to 16) and has every query sample
  points in each of them, projected with each frame's own ``lidar2img``: its sampling and mixing take
  ``num_points * num_frames`` points, so a frame's cost grows linearly with the history length.
* SOLOFusion keeps a sliding window of the last T single-frame BEVs (detached), re-warps all T to the current frame
  every step, appends a time-offset channel to each, mixes each with a 1x1 conv-BN-ReLU and the concatenation of
  all ``T + 1`` with another: the warp and the fusion conv grow with T, and so does the memory.
* VideoBEV ("Exploring Recurrent Long-term Temporal Fusion for Multi-view 3D Perception") keeps one fused BEV
  memory for LSS-style models: each frame warps the previous memory into the current frame and fuses it with the
  current BEV, so the history reaches back indefinitely while a frame costs one warp and one fusion, whatever the
  history length.

:class:`RecurrentFusion` follows VideoBEV, because a per-frame cost that does not grow with the history is what a
16-frame history needs on occkit's CPU-sized models and in deployment, where the state is one ``(B, C, X, Y)``
tensor carried from frame to frame: ``state_t = f([current_t, align(state_{t-1}), valid])`` with ``f`` BEVDet4D's
BasicBlock (that of its BEV encoder's first layer and of ``pre_process``) at stride 1 on ``2 C + 1`` channels.
The valid mask is part of the input by default: after a turn or a long drive, part of the map is new ground every
frame, and the mask tells the block where the aligned state is zero because nothing was there rather than because
the features are zero. As SOLOFusion does at the start of a sequence, a missing state is replaced by the current
frame itself. VideoBEV's temporal embedding (robustness
to dropped frames) is not part of it.

**Training and streaming** (:class:`TemporalFusion`, :class:`StreamMemory`). The concatenation trains as BEVDet4D
does: a sample carries its K earlier key frames (``DatasetConfig.history``), whose BEVs the model computes without
gradient. The recurrent fusion trains as it runs, on streams (SOLOFusion's and VideoBEV's streaming training): the
trainer feeds each scene's frames in time order (``train.sampler: streams``) and carries the memory from step to
step, detached, so a step costs one frame and the state is trained at every age it reaches at inference. (Trained
instead on windows of a few earlier frames and then streamed over whole scenes, the state drifts where it was
never trained: on the synthetic world a tiny model trained on 2-frame windows lost 3.3 mIoU streamed against the
same model evaluated on its windows.) At inference a stream computes every frame once: :class:`StreamMemory` keeps
what the next frame needs (the last K pre-processed BEVs for the concatenation, the state for the recurrent fusion)
with their poses, per batch row, and forgets a row's history when its scene changes. The history enters the
network as three explicit tensors (:data:`HISTORY_INPUTS`), and the network returns this frame's contribution to
the memory (``ModelOutput.history_state``): an exported network takes the state in and gives it out.

**Determinism.** Everything here runs on any device, with no host synchronisation (no ``.item()``). On the CPU the
forward and backward passes are deterministic. On CUDA, ``grid_sample``'s backward accumulates the gradient of the
sampled map with atomic adds, so its gradient (not its forward) may differ from run to run in the last bits, and
``torch.use_deterministic_algorithms(True)`` refuses to differentiate it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occkit.geometry.se3 import invert_transform, transform_points
from occkit.models.resnet import BasicBlock

__all__ = ["history_to_current", "align_bev", "ConcatFusion", "RecurrentFusion", "TemporalConfig", "TemporalFusion",
           "StreamMemory", "HISTORY_INPUTS"]

BevRange = tuple[float, float, float, float]


def _check_matrices(x: Tensor, name: str) -> None:
    if x.ndim < 2 or tuple(x.shape[-2:]) != (4, 4):
        raise ValueError(f"{name} must have shape (..., 4, 4), got {tuple(x.shape)}")


def history_to_current(
    prev_ego2global: Tensor,
    curr_ego2global: Tensor,
    prev_aug: Tensor | None = None,
    curr_aug: Tensor | None = None,
) -> Tensor:
    """The matrix that brings an earlier frame's BEV onto the current one: it maps points of the current
    (augmented) ego frame into the earlier (augmented) ego frame, where :func:`align_bev` reads the earlier map.

    ``current_to_history = prev_aug @ inverse(prev_ego2global) @ curr_ego2global @ inverse(curr_aug)``

    read right to left: undo the current frame's BEV augmentation, go from the current ego frame to the global frame,
    from there into the earlier ego frame, and apply the earlier frame's augmentation. A sequence is augmented with
    one BEV augmentation for all its frames, so ``prev_aug`` and ``curr_aug`` are normally the same ``occ_aug``;
    without augmentation leave both None. For a BEV in another frame (DAOcc's LiDAR-frame BEV) pass that frame's
    ``frame2global`` (``ego2global @ lidar2ego``) and its augmentation (``bev_aug``).

    The product is formed in float64, the precision the dataset keeps ``ego2global`` in: the poses' translations run
    to kilometres, and only their small difference matters.

    Args:
        prev_ego2global: ``(B, 4, 4)`` the earlier key frame's ego pose.
        curr_ego2global: ``(B, 4, 4)`` the current key frame's ego pose.
        prev_aug: ``(B, 4, 4)`` or ``(4, 4)`` the earlier frame's BEV augmentation (un-augmented -> augmented frame),
            or None for none.
        curr_aug: the same for the current frame.

    Returns:
        ``(B, 4, 4)`` float64 ``current_to_history``.
    """
    _check_matrices(prev_ego2global, "prev_ego2global")
    _check_matrices(curr_ego2global, "curr_ego2global")
    current_to_history = invert_transform(prev_ego2global.double()) @ curr_ego2global.double()
    if curr_aug is not None:
        _check_matrices(curr_aug, "curr_aug")
        # An augmentation may scale, so it is inverted in general, not as a rigid transform.
        current_to_history = current_to_history @ torch.linalg.inv(curr_aug.double())
    if prev_aug is not None:
        _check_matrices(prev_aug, "prev_aug")
        current_to_history = prev_aug.double() @ current_to_history
    return current_to_history


def _check_range(bev_range: BevRange) -> tuple[float, float, float, float]:
    values = tuple(float(v) for v in bev_range)
    if len(values) != 4 or not (values[2] > values[0] and values[3] > values[1]):
        raise ValueError(f"bev_range must be (x_min, y_min, x_max, y_max) with max > min, got {bev_range!r}")
    return values  # type: ignore[return-value]


def _cell_centres(shape: tuple[int, int], bev_range: BevRange, device, dtype) -> Tensor:
    """``(X, Y, 3)`` centres of the map's cells at height 0."""
    x_min, y_min, x_max, y_max = bev_range
    nx, ny = shape
    xs = x_min + (torch.arange(nx, device=device, dtype=dtype) + 0.5) * ((x_max - x_min) / nx)
    ys = y_min + (torch.arange(ny, device=device, dtype=dtype) + 0.5) * ((y_max - y_min) / ny)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="ij"), dim=-1)
    return torch.cat([grid, torch.zeros_like(grid[..., :1])], dim=-1)


def align_bev(history: Tensor, current_to_history: Tensor, bev_range: BevRange) -> tuple[Tensor, Tensor]:
    """An earlier frame's BEV resampled onto the current frame's cells.

    Each current cell centre ``p`` (at height 0) is mapped to ``q = current_to_history @ p`` and the history is read
    there bilinearly (``grid_sample``, ``align_corners=False``, coordinates normalised so that ``-1`` / ``+1`` are the
    map's edges; see the module docstring). Both maps cover ``bev_range`` in their own frames and have the same
    ``(X, Y)``. Differentiable in ``history`` (and in ``current_to_history``).

    Args:
        history: ``(B, C, X, Y)`` the earlier frame's map, dim 2 along x, dim 3 along y.
        current_to_history: ``(B, 4, 4)`` from :func:`history_to_current`, any float dtype. The coordinates and
            the sampling are computed in ``history``'s dtype or float32, whichever is wider.
        bev_range: ``(x_min, y_min, x_max, y_max)`` metres, the extent of both maps.

    Returns:
        aligned: ``(B, C, X, Y)`` in ``history``'s dtype; exactly 0 where ``valid`` is False.
        valid: ``(B, 1, X, Y)`` bool, True where the mapped centre lies in the earlier map,
        ``[x_min, x_max) x [y_min, y_max)``.
    """
    if history.ndim != 4:
        raise ValueError(f"history must be (B, C, X, Y), got shape {tuple(history.shape)}")
    _check_matrices(current_to_history, "current_to_history")
    batch, _, nx, ny = history.shape
    if current_to_history.shape[:-2] != (batch,):
        raise ValueError(
            f"current_to_history must be ({batch}, 4, 4) for a history of batch {batch}, "
            f"got {tuple(current_to_history.shape)}"
        )
    x_min, y_min, x_max, y_max = _check_range(bev_range)
    # Half-precision maps are sampled in float32: sub-cell positions on a 200-cell map need more than fp16's 11 bits.
    dtype = torch.promote_types(history.dtype, torch.float32)
    centres = _cell_centres((nx, ny), (x_min, y_min, x_max, y_max), history.device, dtype)
    points = transform_points(current_to_history.to(device=history.device, dtype=dtype)[:, None], centres[None])
    px, py = points[..., 0], points[..., 1]  # (B, X, Y)
    valid = (px >= x_min) & (px < x_max) & (py >= y_min) & (py < y_max)
    norm_x = (px - x_min) / (x_max - x_min) * 2 - 1
    norm_y = (py - y_min) / (y_max - y_min) * 2 - 1
    grid = torch.stack([norm_y, norm_x], dim=-1)  # grid_sample's last axis: (width = y, height = x)
    sampled = F.grid_sample(history.to(dtype), grid, mode="bilinear", padding_mode="border", align_corners=False)
    valid = valid[:, None]
    return (sampled * valid.to(dtype)).to(history.dtype), valid


def _fusion_block(in_channels: int, channels: int) -> nn.Module:
    """BEVDet4D's first BEV-encoder block, at stride 1: BasicBlock with a biased 3x3 conv shortcut (no BatchNorm)."""
    return BasicBlock(in_channels, channels, stride=1, downsample=nn.Conv2d(in_channels, channels, 3, 1, 1))


class ConcatFusion(nn.Module):
    """BEVDet4D's fusion of the current BEV with K aligned earlier ones: their concatenation, which the BEV encoder's
    first layer convolves.

    ``[current, aligned_1, ..., aligned_K (, valid_1, ..., valid_K)]`` on the channel axis, ``out_channels =
    (K + 1) C (+ K)``: the model's BEV encoder takes that many input channels (BEVDet4D's ``numC_input = C * (K +
    1)``), so the fusion's convolution is the encoder's first BasicBlock, as in the reference. A frame costs K warps
    and a first layer whose input grows with K: for a few frames (BEVDet4D uses one; see :class:`RecurrentFusion`
    for long histories). No parameters.

    Args:
        channels: C, the channels of every frame's BEV.
        history: K, the number of earlier frames, newest first.
        bev_range: ``(x_min, y_min, x_max, y_max)`` metres covered by every frame's map in its own frame.
        with_valid: also concatenate the K valid masks as float channels (BEVDet4D does not).
    """

    def __init__(self, channels: int, history: int, bev_range: BevRange, with_valid: bool = False) -> None:
        super().__init__()
        if channels < 1 or history < 1:
            raise ValueError(f"channels and history must be >= 1, got channels={channels}, history={history}")
        self.channels = channels
        self.history = history
        self.bev_range = _check_range(bev_range)
        self.with_valid = with_valid
        self.out_channels = channels * (history + 1) + (history if with_valid else 0)

    def forward(self, current: Tensor, history: Tensor, current_to_history: Tensor) -> Tensor:
        """``current`` and its aligned history, concatenated.

        Args:
            current: ``(B, C, X, Y)``.
            history: ``(B, K, C, X, Y)`` the earlier frames' maps, newest first, each in its own frame. At the
                start of a scene, where a frame has fewer than K predecessors, pass the current map with an
                identity transform in their place (BEVDet4D's data pipeline repeats the key frame the same way).
            current_to_history: ``(B, K, 4, 4)`` from :func:`history_to_current`, one per earlier frame.

        Returns:
            ``(B, out_channels, X, Y)``.
        """
        batch, channels, nx, ny = current.shape
        expected = (batch, self.history, self.channels, nx, ny)
        if channels != self.channels or tuple(history.shape) != expected:
            raise ValueError(
                f"expected current (B, {self.channels}, X, Y) and history {expected}, "
                f"got {tuple(current.shape)} and {tuple(history.shape)}"
            )
        if tuple(current_to_history.shape) != (batch, self.history, 4, 4):
            raise ValueError(
                f"current_to_history must be ({batch}, {self.history}, 4, 4), got {tuple(current_to_history.shape)}"
            )
        # The K frames go through one grid_sample as a batch of B * K maps.
        aligned, valid = align_bev(history.flatten(0, 1), current_to_history.flatten(0, 1), self.bev_range)
        parts = [current, aligned.reshape(batch, self.history * channels, nx, ny)]
        if self.with_valid:
            parts.append(valid.reshape(batch, self.history, nx, ny).to(current.dtype))
        return torch.cat(parts, dim=1)


class RecurrentFusion(nn.Module):
    """VideoBEV-style recurrent fusion: one fused state carried from frame to frame (see the module docstring).

    ``state_t = f([current_t, align(state_{t-1}) (, valid)])``, ``f`` the BasicBlock of :class:`ConcatFusion` on
    ``2 C (+ 1)`` channels. A frame costs one warp of C channels and one block, whatever the history length; the
    state is the fused BEV itself, the output of the frame.

    Gradients flow through the state into earlier frames if it is passed on as it is; pass ``state.detach()`` to
    train frame by frame in a stream with one frame's memory (SOLOFusion detaches its history this way).

    Args:
        channels: C, the channels of the BEV and of the state.
        bev_range: ``(x_min, y_min, x_max, y_max)`` metres covered by the maps, each in its own frame.
        with_valid: also feed the valid mask of the aligned state as one float channel.
    """

    def __init__(self, channels: int, bev_range: BevRange, with_valid: bool = True) -> None:
        super().__init__()
        if channels < 1:
            raise ValueError(f"channels must be >= 1, got {channels}")
        self.channels = channels
        self.bev_range = _check_range(bev_range)
        self.with_valid = with_valid
        self.fuse = _fusion_block(2 * channels + (1 if with_valid else 0), channels)

    def forward(
        self,
        current: Tensor,
        state: Tensor | None = None,
        current_to_previous: Tensor | None = None,
        reset: Tensor | None = None,
    ) -> Tensor:
        """One frame.

        Args:
            current: ``(B, C, X, Y)`` this frame's BEV.
            state: ``(B, C, X, Y)`` the state after the previous frame, in the previous frame; None at the start of
                a sequence, where the current map stands in for it.
            current_to_previous: ``(B, 4, 4)`` mapping this frame's points into the previous frame,
                ``history_to_current(previous ego2global, this ego2global, ...)``; required with a state.
            reset: ``(B,)`` bool, True for samples whose sequence starts at this frame (a new scene in a streamed
                batch): their state is replaced by the current map, as with no state at all.

        Returns:
            ``(B, C, X, Y)`` the new state, which is also this frame's fused BEV.
        """
        if current.ndim != 4 or current.shape[1] != self.channels:
            raise ValueError(f"current must be (B, {self.channels}, X, Y), got {tuple(current.shape)}")
        if state is None:
            aligned = current
            valid = torch.ones_like(current[:, :1], dtype=torch.bool)
        else:
            if state.shape != current.shape:
                raise ValueError(f"state must be shaped as current {tuple(current.shape)}, got {tuple(state.shape)}")
            if current_to_previous is None:
                raise ValueError("current_to_previous is required with a state")
            aligned, valid = align_bev(state, current_to_previous, self.bev_range)
            if reset is not None:
                restart = reset.to(device=current.device, dtype=torch.bool).view(-1, 1, 1, 1)
                aligned = torch.where(restart, current, aligned)
                valid = valid | restart
        parts = [current, aligned]
        if self.with_valid:
            parts.append(valid.to(current.dtype))
        return self.fuse(torch.cat(parts, dim=1))

    def unroll(self, frames: Tensor, current_to_previous: Tensor, detach: bool = False) -> Tensor:
        """Run a whole sequence, one :meth:`forward` per frame.

        Args:
            frames: ``(B, T, C, X, Y)`` the BEVs of T consecutive frames, oldest first.
            current_to_previous: ``(B, T, 4, 4)``; entry ``t`` maps frame ``t`` to frame ``t - 1`` (entry 0 is
                unused: the first frame starts the sequence).
            detach: pass each state on detached (truncated backpropagation, one frame of memory).

        Returns:
            ``(B, T, C, X, Y)`` the state after each frame.
        """
        if frames.ndim != 5 or tuple(current_to_previous.shape) != (*frames.shape[:2], 4, 4):
            raise ValueError(
                f"need frames (B, T, C, X, Y) and current_to_previous (B, T, 4, 4), got {tuple(frames.shape)} "
                f"and {tuple(current_to_previous.shape)}"
            )
        states = []
        state = None
        for t in range(frames.shape[1]):
            state = self(frames[:, t], state, current_to_previous[:, t] if t else None)
            states.append(state)
            if detach:
                state = state.detach()
        return torch.stack(states, dim=1)


#: The network inputs that carry the history, as :class:`StreamMemory` and :meth:`TemporalFusion.history_inputs`
#: make them: ``history`` ``(B, S, C, X, Y)`` the memory's BEVs (S = K earlier frames for the concatenation, 1 state
#: for the recurrent fusion), newest first; ``current_to_history`` ``(B, S, 4, 4)`` float32 from
#: :func:`history_to_current`; ``history_padded`` ``(B, S)`` bool, True where a slot holds no earlier frame of the scene
#: (the current frame stands in for it).
HISTORY_INPUTS = ("history", "current_to_history", "history_padded")


@dataclass(frozen=True)
class TemporalConfig:
    """Ego-motion-aligned BEV history (module docstring of :mod:`occkit.models.temporal`)."""

    fusion: Literal["concat", "recurrent"] = "concat"
    """``concat``: BEVDet4D, the current BEV and K aligned earlier ones concatenated into the BEV encoder (whose
    ``in_channels`` must be ``(K + 1) C``, plus K with ``with_valid``); trained on samples that carry their K earlier
    key frames. ``recurrent``: VideoBEV-style, one fused state carried from frame to frame at a cost independent of
    the history (the encoder takes C channels); trained on streams, as it runs (``train.sampler`` ``streams``)."""
    history: int = 1
    """K, the earlier key frames the concatenation fuses (``DatasetConfig.history`` must equal it). 0 for the
    recurrent fusion, whose state spans every earlier frame of the scene."""
    pre_process: bool = True
    """BEVDet4D's ``pre_process``: one BasicBlock at stride 1 on every frame's BEV before alignment."""
    with_valid: bool = False
    """Give the fusion the aligned frames' valid masks (out-of-view cells) as channels; BEVDet4D does not."""

    def __post_init__(self) -> None:
        if self.fusion not in ("concat", "recurrent"):
            raise ValueError(f"temporal.fusion must be 'concat' or 'recurrent', got {self.fusion!r}")
        if self.fusion == "concat" and self.history < 1:
            raise ValueError(f"temporal.history must be >= 1 for the concatenation, got {self.history}")
        if self.fusion == "recurrent" and self.history != 0:
            raise ValueError(f"temporal.history must be 0 for the recurrent fusion (its state spans the scene, and it "
                             f"trains on streams of frames, not on samples with earlier frames), got {self.history}")

    def out_channels(self, channels: int) -> int:
        """Channels of the fused BEV the encoder takes, for frames of ``channels`` channels."""
        if self.fusion == "recurrent":
            return channels
        return channels * (self.history + 1) + (self.history if self.with_valid else 0)

    @property
    def memory_frames(self) -> int:
        """S, the slots a stream keeps: K BEVs for the concatenation, one state for the recurrent fusion."""
        return self.history if self.fusion == "concat" else 1

    @property
    def streamed_training(self) -> bool:
        """Whether training runs the frames of each scene in order with the memory carried from step to step (the
        recurrent fusion), rather than on samples that carry their earlier frames (the concatenation)."""
        return self.fusion == "recurrent"


class TemporalFusion(nn.Module):
    """A model's history stage: ``pre_process``, then the fusion of :class:`TemporalConfig`.

    ``forward(bev, history, current_to_history, history_padded) -> (fused, state)``: ``fused`` goes on to the BEV
    encoder, ``state`` is what a stream keeps of this frame (the pre-processed BEV for the concatenation, the new
    state for the recurrent fusion), both from the inputs of :data:`HISTORY_INPUTS`.

    Args:
        cfg: the temporal settings.
        channels: C of every frame's BEV.
        bev_range: ``(x_min, y_min, x_max, y_max)`` metres the BEV covers in its (augmented) ego frame.
        bev_size: ``(X, Y)`` cells of the BEV.
    """

    def __init__(self, cfg: TemporalConfig, channels: int, bev_range: BevRange, bev_size: tuple[int, int]) -> None:
        super().__init__()
        self.cfg = cfg
        self.channels = channels
        self.bev_range = _check_range(bev_range)
        self.bev_size = (int(bev_size[0]), int(bev_size[1]))
        self.pre_process = _fusion_block(channels, channels) if cfg.pre_process else nn.Identity()
        self.fusion: ConcatFusion | RecurrentFusion = (
            ConcatFusion(channels, cfg.history, bev_range, cfg.with_valid) if cfg.fusion == "concat"
            else RecurrentFusion(channels, bev_range, cfg.with_valid))  # fmt: skip
        self.out_channels = cfg.out_channels(channels)

    @property
    def memory_frames(self) -> int:
        """S, the slots of ``history``."""
        return self.cfg.memory_frames

    def forward(self, bev: Tensor, history: Tensor, current_to_history: Tensor,
                history_padded: Tensor) -> tuple[Tensor, Tensor]:  # fmt: skip
        """Fuse this frame's BEV with its history.

        Args:
            bev: ``(B, C, X, Y)`` this frame's BEV, before ``pre_process``.
            history: ``(B, S, C, X, Y)``, ``current_to_history`` ``(B, S, 4, 4)``, ``history_padded`` ``(B, S)``
                bool: :data:`HISTORY_INPUTS`. Padded slots are ignored: the current frame stands in for them.

        Returns:
            fused: ``(B, out_channels, X, Y)``; state: ``(B, C, X, Y)`` this frame's slot of the memory.
        """
        frames = self.memory_frames
        batch = bev.shape[0]
        expected = (batch, frames, self.channels, *bev.shape[-2:])
        if tuple(history.shape) != expected or tuple(history_padded.shape) != (batch, frames):
            raise ValueError(f"history must be {expected} with history_padded ({batch}, {frames}), got "
                             f"{tuple(history.shape)} and {tuple(history_padded.shape)}")
        bev = self.pre_process(bev)
        padded = history_padded.to(device=bev.device, dtype=torch.bool)
        if isinstance(self.fusion, RecurrentFusion):
            fused = self.fusion(bev, history[:, 0], current_to_history[:, 0], reset=padded[:, 0])
            return fused, fused
        # BEVDet4D's padding: the current frame with an identity transform.
        history = torch.where(padded[..., None, None, None], bev[:, None], history)
        identity = torch.eye(4, dtype=current_to_history.dtype, device=current_to_history.device)
        current_to_history = torch.where(padded[..., None, None], identity, current_to_history)
        return self.fusion(bev, history, current_to_history), bev

    @torch.no_grad()
    def history_inputs(self, frames: Tensor, history_ego2global: Tensor, ego2global: Tensor, occ_aug: Tensor,
                       history_padded: Tensor) -> dict[str, Tensor]:  # fmt: skip
        """:data:`HISTORY_INPUTS` of the concatenation from a sample's K earlier frames, without gradient.

        Args:
            frames: ``(B, K, C, X, Y)`` the earlier frames' pre-processed BEVs, newest first.
            history_ego2global: ``(B, K, 4, 4)`` their ego poses; ``ego2global`` ``(B, 4, 4)`` the current one.
            occ_aug: ``(B, 4, 4)`` the sequence's one BEV augmentation.
            history_padded: ``(B, K)`` bool, slots that repeat the current frame (the oldest ones).
        """
        count = frames.shape[1]
        if not isinstance(self.fusion, ConcatFusion):
            raise ValueError("the recurrent fusion takes its history from a stream (StreamMemory), not from a "
                             "sample's earlier frames: set data.history = 0")
        if count != self.cfg.history:
            raise ValueError(f"the concatenation fuses {self.cfg.history} earlier frames; the batch has {count} "
                             f"(set data.history = {self.cfg.history})")
        transforms = torch.stack([history_to_current(history_ego2global[:, k], ego2global, occ_aug, occ_aug)
                                  for k in range(count)], dim=1).to(device=frames.device, dtype=frames.dtype)
        padded = history_padded.to(device=frames.device, dtype=torch.bool)
        return {"history": frames, "current_to_history": transforms, "history_padded": padded}

    def empty_history(self, batch: int, device: torch.device, dtype: torch.dtype) -> dict[str, Tensor]:
        """:data:`HISTORY_INPUTS` of frames with no history at all (every slot padded): the single-frame case."""
        frames = self.memory_frames
        return {"history": torch.zeros(batch, frames, self.channels, *self.bev_size, device=device, dtype=dtype),
                "current_to_history": torch.eye(4, device=device, dtype=dtype).expand(batch, frames, 4, 4).clone(),
                "history_padded": torch.ones(batch, frames, dtype=torch.bool, device=device)}  # fmt: skip


class StreamMemory:
    """What a temporal model carries from frame to frame of a stream: per batch row, its last frames' slots
    (newest first) with their poses, BEV augmentations and scene.

    Row ``b`` of consecutive batches is one stream; when its scene changes, its history is forgotten (every slot
    padded), so a history never crosses scenes. Use one memory per stream of batches, :meth:`inputs` before the
    network and :meth:`push` after it (:meth:`OccupancyModel.forward <occkit.models.base.OccupancyModel.forward>`
    does both when given a memory).
    """

    def __init__(self, fusion: TemporalFusion) -> None:
        self.fusion = fusion
        self.states: Tensor | None = None
        """``(B, S, C, X, Y)`` the slots, newest first."""
        self.ego2global: Tensor | None = None
        """``(B, S, 4, 4)`` float64 the poses of the frames in the slots."""
        self.occ_aug: Tensor | None = None
        """``(B, S, 4, 4)`` their BEV augmentations."""
        self.filled: Tensor | None = None
        """``(B, S)`` bool, slots holding an earlier frame of the row's current scene."""
        self.scenes: list[str] = []

    def reset(self) -> None:
        """Forget every stream."""
        self.states = self.ego2global = self.occ_aug = self.filled = None
        self.scenes = []

    def inputs(self, scenes: list[str], ego2global: Tensor, occ_aug: Tensor, device: torch.device,
               dtype: torch.dtype) -> dict[str, Tensor]:  # fmt: skip
        """:data:`HISTORY_INPUTS` for the next frame of every row.

        Args:
            scenes: ``B`` scene names of the frames.
            ego2global: ``(B, 4, 4)`` their poses; ``occ_aug`` ``(B, 4, 4)`` their BEV augmentations.
        """
        batch = len(scenes)
        if self.states is None or self.states.shape[0] != batch:
            self.reset()
            empty = self.fusion.empty_history(batch, device, dtype)
            self.states = empty["history"]
            self.ego2global = ego2global.double()[:, None].repeat(1, self.fusion.memory_frames, 1, 1)
            self.occ_aug = occ_aug[:, None].repeat(1, self.fusion.memory_frames, 1, 1)
            self.filled = ~empty["history_padded"]
            self.scenes = list(scenes)
        same = torch.tensor([a == b for a, b in zip(self.scenes, scenes, strict=True)], device=device)
        self.filled = self.filled & same[:, None]
        self.scenes = list(scenes)
        slots = self.fusion.memory_frames
        transforms = history_to_current(self.ego2global.flatten(0, 1), ego2global.double().repeat_interleave(slots, 0),
                                        self.occ_aug.flatten(0, 1), occ_aug.repeat_interleave(slots, 0))
        transforms = transforms.unflatten(0, (batch, slots)).to(device=device, dtype=dtype)
        return {"history": self.states, "current_to_history": transforms, "history_padded": ~self.filled}

    def state_dict(self) -> dict:
        """The memory as plain tensors and names (a training checkpoint keeps it, so a resumed stream goes on)."""
        return {"states": self.states, "ego2global": self.ego2global, "occ_aug": self.occ_aug,
                "filled": self.filled, "scenes": list(self.scenes)}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`."""
        self.states, self.ego2global, self.occ_aug = state["states"], state["ego2global"], state["occ_aug"]
        self.filled, self.scenes = state["filled"], list(state["scenes"])

    def push(self, state: Tensor, ego2global: Tensor, occ_aug: Tensor) -> None:
        """Keep a frame's slot (``ModelOutput.history_state``, ``(B, C, X, Y)``) after :meth:`inputs`."""
        if self.states is None:
            raise RuntimeError("StreamMemory.push before inputs")
        self.states = torch.cat([state.detach()[:, None], self.states[:, :-1]], dim=1)
        self.ego2global = torch.cat([ego2global.double()[:, None], self.ego2global[:, :-1]], dim=1)
        self.occ_aug = torch.cat([occ_aug[:, None], self.occ_aug[:, :-1]], dim=1)
        filled = torch.ones_like(self.filled[:, :1])
        self.filled = torch.cat([filled, self.filled[:, :-1]], dim=1)
