"""A temporal model streamed over its scene's key frames, timed against the same model without history."""

from __future__ import annotations

import dataclasses
import statistics
from functools import partial

import torch
from torch import nn

from occkit import zoo
from occkit.bench.config import PRECISIONS, BenchConfig
from occkit.bench.sample import WORLD
from occkit.bench.timing import paired_times, percentile, synchronizer, timed
from occkit.engine.reference_frame import load_reference_frame
from occkit.models.complexity import count_parameters
from occkit.models.inference import apply_optimization, prepare_for_inference

__all__ = ["single_frame_twin", "streaming"]


def single_frame_twin(name: str) -> nn.Module:
    """Zoo entry ``name``'s model without its history: the same config with ``temporal`` None and the BEV encoder
    taking one frame's channels (the model a temporal entry's streaming latency is compared with)."""
    architecture, config = zoo.model_config(name)
    if getattr(config, "temporal", None) is None:
        raise ValueError(f"{name} has no history")
    frame_channels = zoo.build_from_config(architecture, config).temporal.channels
    twin = dataclasses.replace(config, temporal=None, bev=dataclasses.replace(config.bev, in_channels=frame_channels))
    return zoo.build_from_config(architecture, twin)


def streaming(model: nn.Module, applied: list[str], cfg: BenchConfig, device: torch.device) -> dict:
    """Per-frame latency of ``model`` streamed over its scene's key frames against its single-frame twin (the same
    fast path applied) on the same frames, in interleaved pairs."""
    scene = load_reference_frame(zoo.experiment(cfg.model).data, cfg.data, WORLD, batch_size=cfg.batch_size,
                                 scene=True).scene  # fmt: skip
    frames = [batch.to(device) for batch in scene]
    twin = single_frame_twin(cfg.model).to(device).eval()
    prepare_for_inference(twin)
    for name in applied:
        apply_optimization(twin, name)
    memory = model.stream()
    dtype = PRECISIONS[cfg.precision]
    autocast = partial(torch.autocast, device.type, dtype=dtype, enabled=dtype != torch.float32)
    synchronize = synchronizer(device)
    step = {"streamed": 0, "single": 0}

    def streamed() -> float:
        batch = frames[step["streamed"] % len(frames)]
        step["streamed"] += 1
        with torch.no_grad(), autocast():
            return timed(lambda: model(batch, memory=memory), synchronize)

    def single() -> float:
        batch = frames[step["single"] % len(frames)]
        step["single"] += 1
        with torch.no_grad(), autocast():
            return timed(lambda: twin(batch), synchronize)

    for _ in range(max(cfg.warmup, 1)):
        streamed(), single()
    times, twin_times = paired_times(streamed, single, cfg.iters)
    slots = memory.states
    return {
        "frames": len(frames),
        "history": model.temporal.cfg.history,
        "fusion": model.temporal.cfg.fusion,
        "memory_slots": model.temporal.memory_frames,
        "memory_bytes": int(slots.numel() * slots.element_size()) if slots is not None else 0,
        "latency_ms": {"median": 1000 * statistics.median(times), "p90": 1000 * percentile(times, 90),
                       "all": [1000 * t for t in times]},
        "fps": cfg.batch_size / statistics.median(times),
        "single_frame": {"model": f"{cfg.model} without history", "params": count_parameters(twin),
                         "latency_ms": {"median": 1000 * statistics.median(twin_times),
                                        "all": [1000 * t for t in twin_times]}},
        # The median of the pairs' ratios: each pair saw one machine load.
        "latency_ratio": statistics.median(t / s for t, s in zip(times, twin_times, strict=True)),
    }  # fmt: skip
