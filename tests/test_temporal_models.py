"""Temporal FlashOcc and DA-Occ: training with history frames, streaming, scene boundaries, the engine's streams."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from conftest import make_batch, parameters_without_gradient, torch_threads

from occkit import zoo
from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.data.transforms import ImageAugConfig
from occkit.engine import distributed
from occkit.engine.checkpoint import latest_checkpoint, load_checkpoint
from occkit.engine.evaluate import evaluate_model, split_loader
from occkit.geometry.se3 import make_transform, rotation_about_z
from occkit.metrics.evaluate import read_prediction
from occkit.models.da_occ import DirectionAwareOccConfig
from occkit.models.flashocc import FlashOccConfig
from occkit.models.temporal import TemporalConfig
from occkit.sim.generate import SimConfig, simulate_dataset


def _flashocc_concat() -> torch.nn.Module:
    """flashocc_tiny with BEVDet4D's one-frame history (flashocc_m0_4d's design at small size)."""
    cfg = zoo.experiment("flashocc_tiny").model
    return zoo.build_from_config("flashocc", dataclasses.replace(
        cfg, temporal=TemporalConfig(history=1), bev=dataclasses.replace(cfg.bev, in_channels=32)))


def _da_occ_concat() -> torch.nn.Module:
    """da_occ_tiny with two concatenated earlier frames and their valid masks (da_occ_1f's design, K = 2)."""
    cfg = zoo.experiment("da_occ_tiny").model
    temporal = TemporalConfig(history=2, with_valid=True)
    return zoo.build_from_config("da_occ", dataclasses.replace(
        cfg, temporal=temporal, bev=dataclasses.replace(cfg.bev, in_channels=temporal.out_channels(16))))


def _da_occ_recurrent() -> torch.nn.Module:
    return zoo.build("da_occ_tiny_temporal")


MODELS = {"flashocc_concat": _flashocc_concat, "da_occ_concat": _da_occ_concat, "da_occ_recurrent": _da_occ_recurrent}
#: DA-Occ's DACs fix the feature height (128 / 16).
OPTIONS = {"batch_size": 1, "num_cameras": 2, "image_size": (128, 352), "num_points": 500}


def _model(kind: str) -> torch.nn.Module:
    torch.manual_seed(0)
    return MODELS[kind]()


def _pose(t: int) -> torch.Tensor:
    """Frame t of a drive: 2 m forward and 3 degrees left per frame."""
    yaw = torch.tensor(math.radians(3.0 * t))
    return make_transform(rotation_about_z(yaw), torch.tensor([2.0 * t, 0.3 * t, 0.0])).double()[None]


def _scene(name: str, frames: int, seed: int) -> list:
    """``frames`` single-frame batches of one scene (random images, a moving ego)."""
    batches = []
    for t in range(frames):
        batch = make_batch(seed=seed + t, occupancy=False, depth_stride=16, **OPTIONS)
        batch.scenes, batch.tokens, batch.ego2global = [name], [f"{name}-{t}"], _pose(t)
        batches.append(batch)
    return batches


def _windowed(frames: list, t: int, history: int):
    """Frame t with its ``history`` earlier frames as the dataset gives them: newest first, the missing ones the
    current frame again, flagged padded."""
    batch = dataclasses.replace(frames[t])
    earlier = [frames[t - k - 1] if t - k - 1 >= 0 else frames[t] for k in range(history)]
    batch.history_images = torch.stack([e.images for e in earlier], dim=1)
    batch.history_intrinsics = torch.stack([e.intrinsics for e in earlier], dim=1)
    batch.history_cam2ego = torch.stack([e.cam2ego for e in earlier], dim=1)
    batch.history_img_aug = torch.stack([e.img_aug for e in earlier], dim=1)
    batch.history_ego2global = torch.stack([e.ego2global for e in earlier], dim=1)
    batch.history_padded = torch.tensor([[t - k - 1 < 0 for k in range(history)]])
    return batch


@pytest.mark.parametrize("kind", ["flashocc_concat", "da_occ_concat"])
def test_a_training_step_reaches_every_parameter_and_no_history_frame(kind):
    model = _model(kind).train()
    history = model.temporal.cfg.history
    batch = make_batch(depth_stride=16, history=history, padded=1, **OPTIONS)
    batch.history_images.requires_grad_(True)
    losses = model.loss(model(batch), batch)
    sum(losses.values()).backward()
    assert not parameters_without_gradient(model)
    # The earlier frames run without gradient, as BEVDet4D's adjacent frames.
    assert batch.history_images.grad is None


def test_a_streamed_training_step_reaches_every_parameter_and_not_the_previous_frame():
    model = _model("da_occ_recurrent").train()
    memory = model.stream()
    first, second = _scene("scene-a", 2, seed=40)
    for frame in (first, second):
        frame.voxel_semantics = make_batch(**OPTIONS).voxel_semantics
        frame.mask_camera = torch.ones_like(frame.voxel_semantics, dtype=torch.bool)
    first.images.requires_grad_(True)
    model(first, memory=memory)
    losses = model.loss(model(second, memory=memory), second)
    sum(losses.values()).backward()
    assert not parameters_without_gradient(model)
    # The state comes from the previous step detached: one frame is differentiated per step.
    assert first.images.grad is None and not memory.states.requires_grad


def test_training_without_its_history_names_the_setting():
    model = _model("da_occ_recurrent").train()
    with pytest.raises(ValueError, match="trains on streams"):
        model(make_batch(depth_stride=16, **OPTIONS))
    with pytest.raises(ValueError, match="set data.history = 0"):
        model(make_batch(depth_stride=16, history=2, **OPTIONS))
    concat = _model("flashocc_concat").train()
    with pytest.raises(ValueError, match="set data.history = 1"):
        concat(make_batch(**OPTIONS))
    with pytest.raises(ValueError, match="set data.history = 1"):
        concat(make_batch(history=3, **OPTIONS))
    with pytest.raises(ValueError, match="history must be 0 for the recurrent fusion"):
        TemporalConfig(fusion="recurrent", history=2)


def test_the_encoder_must_take_the_fused_channels():
    cfg = zoo.experiment("flashocc_tiny").model
    with pytest.raises(ValueError, match="bev.in_channels = 16 must equal .* fused with the history by temporal = 32"):
        dataclasses.replace(cfg, temporal=TemporalConfig(history=1))
    da_occ = zoo.experiment("da_occ_tiny").model
    with pytest.raises(ValueError, match=r"bev.in_channels = 16 must be 3 x the context channels \(temporal: the "
                                         r"current frame and 2 earlier ones concatenated\)"):  # fmt: skip
        dataclasses.replace(da_occ, temporal=TemporalConfig(history=2))
    assert isinstance(da_occ, DirectionAwareOccConfig) and isinstance(cfg, FlashOccConfig)


@pytest.mark.parametrize("kind", ["flashocc_concat", "da_occ_concat"])
def test_streaming_gives_what_the_window_of_earlier_frames_gives(kind):
    """The concatenation trained on samples with K earlier frames sees the same K frames when streamed."""
    model = _model(kind).eval()
    history = model.temporal.cfg.history
    frames = _scene("scene-a", history + 2, seed=10)
    memory = model.stream()
    with torch.no_grad():
        for t, frame in enumerate(frames):
            streamed = model(frame, memory=memory).occupancy
            windowed = model(_windowed(frames, t, history)).occupancy
            torch.testing.assert_close(streamed, windowed, rtol=1e-4, atol=1e-4)
    # The stream computes each frame once: its memory holds the last frames' BEVs (or one state), nothing more.
    assert memory.states.shape == (1, model.temporal.memory_frames, model.temporal.channels, 200, 200)
    assert memory.filled.all()


@pytest.mark.parametrize("kind", ["flashocc_concat", "da_occ_recurrent"])
def test_a_history_never_crosses_scenes(kind):
    """Two scenes streamed back to back: the second is predicted as if streamed alone."""
    model = _model(kind).eval()
    first, second = _scene("scene-a", 3, seed=20), _scene("scene-b", 2, seed=30)
    together, alone = model.stream(), model.stream()
    with torch.no_grad():
        for frame in first:
            model(frame, memory=together)
        for t, frame in enumerate(second):
            inputs = together.inputs(frame.scenes, frame.ego2global, frame.occ_aug, frame.images.device,
                                     frame.images.dtype)
            if t == 0:  # the scene changed: every slot is padded, no BEV of scene-a is read
                assert inputs["history_padded"].all()
            streamed = model(frame, memory=together).occupancy
            torch.testing.assert_close(streamed, model(frame, memory=alone).occupancy, rtol=0, atol=0)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """2 scenes x 3 key frames, 176 x 99 images of two cameras."""
    root = tmp_path_factory.mktemp("streams") / "data"
    simulate_dataset(SimConfig(scenes=2, frames=3, seed=3, image_size=(176, 99),
                               cameras=("CAM_FRONT", "CAM_BACK")), root)  # fmt: skip
    return root


def _world_dataset(root) -> OccupancyDataset:
    data = dataclasses.replace(zoo.experiment("da_occ_tiny_temporal").data, root=str(root), split="all",
                               cameras=("CAM_FRONT", "CAM_BACK"), augment=False, history=0, depth_downsample=0,
                               image_aug=ImageAugConfig(final_size=(128, 352)))  # fmt: skip
    assert isinstance(data, DatasetConfig)
    return OccupancyDataset(data)


def test_ranks_stream_whole_scenes_in_time_order(world):
    dataset = _world_dataset(world)
    shares = []
    for rank in range(2):
        context = distributed.Context(rank=rank, world_size=2, device=torch.device("cpu"))
        shares.append(list(split_loader(dataset, 1, 0, context, by_scene=True).sampler))
    scenes = [{dataset.records[i].scene for i in share} for share in shares]
    assert scenes[0].isdisjoint(scenes[1]) and all(len(s) == 1 for s in scenes)
    for share in shares:
        assert [dataset.records[i].index_in_scene for i in share] == [0, 1, 2]


def test_evaluation_streams_each_scene_and_restarts_at_the_next(world, tmp_path):
    dataset = _world_dataset(world)
    model = _model("da_occ_recurrent").eval()
    result = evaluate_model(model, dataset, batch_size=4, predictions=tmp_path)
    assert result["frames"] == 6
    from occkit.data.collate import collate

    for scene in ("scene-0001", "scene-0002"):
        memory = model.stream()
        indices = [i for i, r in enumerate(dataset.records) if r.scene == scene]
        for i in indices:
            expected = model.predict(collate([dataset[i]]), memory=memory).semantics[0].numpy()
            np.testing.assert_array_equal(read_prediction(tmp_path / f"{dataset.records[i].token}.npz"), expected)


def test_streams_deal_whole_scenes_in_time_order_and_resume_mid_epoch():
    scenes = [list(range(0, 5)), list(range(5, 8)), list(range(8, 14)), list(range(14, 18))]
    sampler = distributed.StreamSampler(scenes, batch_size=2, seed=3)
    streams = sampler.streams()
    assert len(streams) == 2 and len(streams[0]) == len(streams[1]) == sampler.batches_per_epoch()
    for stream in streams:  # each stream: whole scenes one after the other (cut at the end), frames in order
        runs = [[i for i in stream if i in scene] for scene in scenes]
        assert all(run == scene[: len(run)] for run, scene in zip(runs, scenes, strict=True))
    order = list(sampler)
    assert order[0::2] == streams[0] and order[1::2] == streams[1]
    sampler.set_epoch(0, skip_batches=3)
    assert list(sampler) == order[6:]
    sampler.set_epoch(1)
    assert sampler.streams() != streams  # another deal
    ranks = [distributed.StreamSampler(scenes, 1, rank, 2, seed=3) for rank in range(2)]
    assert [list(r) for r in ranks] == [streams[0], streams[1]]
    with pytest.raises(ValueError, match="a scene per stream: 4 scenes for 5 samples"):
        distributed.StreamSampler(scenes, batch_size=5)


def test_a_killed_and_resumed_streamed_run_is_bitwise_the_uninterrupted_one(world, tmp_path):
    """The memory is part of the checkpoint: a run resumed mid-scene goes on with the stream's state."""
    from occkit.engine.train import train
    from occkit.experiment import replace_train

    experiment = zoo.experiment("da_occ_tiny_temporal")
    experiment = dataclasses.replace(experiment, data=dataclasses.replace(
        experiment.data, root=str(world), split="all", cameras=("CAM_FRONT", "CAM_BACK"), sweeps=0))
    experiment = replace_train(experiment, max_steps=4, epochs=100, val_every=-1, checkpoint_every=1, workers=0,
                               log_every=1, warmup_steps=1)  # fmt: skip

    class Killed(Exception):
        pass

    def kill_after_step_two(step: int) -> None:
        if step == 2:
            raise Killed

    with torch_threads(2):
        train(experiment, tmp_path / "uninterrupted", progress=False, device="cpu")
        with pytest.raises(Killed):
            train(experiment, tmp_path / "killed", progress=False, device="cpu", on_step=kill_after_step_two)
        saved = load_checkpoint(latest_checkpoint(tmp_path / "killed"))
        assert saved["step"] in (1, 2) and saved["stream_memory"]["filled"].any()
        train(experiment, tmp_path / "killed", resume="auto", progress=False, device="cpu")
    reference = load_checkpoint(latest_checkpoint(tmp_path / "uninterrupted"))
    resumed = load_checkpoint(latest_checkpoint(tmp_path / "killed"))
    assert reference["step"] == resumed["step"] == 4
    for key, value in reference["model"].items():
        assert torch.equal(value, resumed["model"][key]), key
    assert torch.equal(reference["stream_memory"]["states"], resumed["stream_memory"]["states"])
