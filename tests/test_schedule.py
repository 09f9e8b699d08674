"""Learning-rate and EMA schedules against mmcv's LrUpdaterHook and BEVDepth's MEGVII EMA, computed by hand."""

from __future__ import annotations

import math

import pytest

from occkit.config import ConfigError
from occkit.engine.schedule import Schedule
from occkit.engine.train import accumulation
from occkit.experiment import TrainConfig


def test_cosine_per_step_with_a_warm_up_scaling_it():
    train = TrainConfig(epochs=10, warmup_steps=10, warmup_ratio=0.25, min_lr_ratio=0.01)
    schedule = Schedule(train, total_steps=100, steps_per_epoch=10)
    factors = [schedule.lr_factor(step) for step in range(101)]
    cosine = [0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * step / 100)) for step in range(101)]
    assert factors[0] == pytest.approx(0.25 * cosine[0])
    assert factors[5] == pytest.approx((0.25 + 0.75 * 0.5) * cosine[5])  # mmcv: warm-up times the regular rate
    assert factors[10:] == pytest.approx(cosine[10:])
    assert factors[50] == pytest.approx(0.01 + 0.99 * 0.5)
    assert factors[100] == pytest.approx(0.01)
    assert schedule.lr_factor(150) == pytest.approx(0.01)  # stays at the floor


def test_cosine_by_epoch_changes_once_per_epoch_as_daocc_runs_it():
    train = TrainConfig(epochs=6, warmup_steps=500, warmup_ratio=1 / 3, min_lr_ratio=1e-3, lr_by_epoch=True)
    schedule = Schedule(train, total_steps=6 * 1000, steps_per_epoch=1000)
    for epoch in range(6):
        regular = 1e-3 + (1 - 1e-3) * 0.5 * (1 + math.cos(math.pi * epoch / 6))
        assert schedule.lr_factor(epoch * 1000 + 999) == pytest.approx(regular)
        assert schedule.lr_factor(epoch * 1000 + 600) == pytest.approx(regular)
    assert schedule.lr_factor(250) == pytest.approx(1 / 3 + (2 / 3) * 0.5)  # epoch 0: regular rate 1


def test_step_policy_as_flashocc_keeps_the_rate_after_warm_up():
    flashocc = TrainConfig(epochs=24, warmup_steps=200, warmup_ratio=0.001, lr_policy="step", lr_steps=(24,))
    schedule = Schedule(flashocc, total_steps=24 * 100, steps_per_epoch=100)
    assert schedule.lr_factor(0) == pytest.approx(0.001)
    assert schedule.lr_factor(100) == pytest.approx(0.001 + 0.999 * 0.5)
    assert {schedule.lr_factor(step) for step in range(200, 2400)} == {1.0}
    decays = TrainConfig(epochs=24, warmup_steps=0, lr_policy="step", lr_steps=(16, 22), lr_gamma=0.1)
    schedule = Schedule(decays, total_steps=2400, steps_per_epoch=100)
    assert [schedule.lr_factor(step) for step in (1599, 1600, 2199, 2200)] == pytest.approx([1, 0.1, 0.1, 0.01])


def test_ema_decay_ramps_as_the_megvii_hook():
    constant = Schedule(TrainConfig(ema_decay=0.999), 100, 10)
    assert constant.ema_decay(0) == constant.ema_decay(99) == 0.999
    ramp = Schedule(TrainConfig(ema_decay=0.999, ema_ramp=2000.0), 100, 10)
    assert ramp.ema_decay(0) == pytest.approx(0.999 * (1 - math.exp(-1 / 2000)))  # the first update: t = 1
    references = Schedule(TrainConfig(ema_decay=0.999, ema_ramp=2000.0, ema_initial_updates=10560), 100, 10)
    assert references.ema_decay(9) == pytest.approx(0.999 * (1 - math.exp(-10570 / 2000)))


def test_global_batch_derives_the_accumulation():
    daocc = TrainConfig(batch_size=4, global_batch=32)
    assert accumulation(daocc, world_size=8) == 1
    assert accumulation(daocc, world_size=1) == 8
    assert accumulation(daocc, world_size=2) == 4
    with pytest.raises(ConfigError, match=r"global_batch 32 is not a multiple of batch_size x processes = 4 x 3"):
        accumulation(daocc, world_size=3)
    assert accumulation(TrainConfig(accumulate=3), world_size=4) == 3
    with pytest.raises(ValueError, match="not both"):
        TrainConfig(global_batch=32, accumulate=2)
    with pytest.raises(ValueError, match="lr_policy: step only"):
        TrainConfig(lr_steps=(3,))
