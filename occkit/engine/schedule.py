"""Schedules of a run: the learning rate per optimizer step and the EMA's decay per update, as the references run them.

The learning rate follows mmcv's ``LrUpdaterHook``, which every reference trains with: a *regular* rate, either a
cosine from ``lr`` down to ``min_lr_ratio x lr`` or a step policy multiplying ``lr`` by ``lr_gamma`` at each epoch of
``lr_steps``, and a linear warm-up that scales the regular rate by ``warmup_ratio + (1 - warmup_ratio) x step /
warmup_steps`` over the first ``warmup_steps`` steps. With ``lr_by_epoch`` (mmcv's default, which DAOcc's cosine
uses) the regular rate changes once per epoch, its progress being ``epoch / epochs``; otherwise every step, its
progress ``step / total``.

The EMA's decay ramps as BEVDepth's MEGVII hook (DAOcc and FlashOcc): ``ema_decay x (1 - exp(-t / ema_ramp))`` at
update ``t``, counted from ``ema_initial_updates``, so that the average forgets the random initial weights quickly.
Both are pure functions of the step, so a resumed run continues on the same curves without saving them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from occkit.experiment import TrainConfig

__all__ = ["Schedule"]


@dataclass(frozen=True)
class Schedule:
    """The learning rate and EMA decay of a run of ``total_steps`` optimizer steps, ``steps_per_epoch`` per epoch."""

    train: TrainConfig
    total_steps: int
    steps_per_epoch: int

    def regular_factor(self, step: int) -> float:
        """The schedule's multiplier of ``lr`` at ``step`` without the warm-up."""
        cfg = self.train
        epoch = step // self.steps_per_epoch
        if cfg.lr_policy == "step":
            return cfg.lr_gamma ** sum(epoch >= boundary for boundary in cfg.lr_steps)
        if cfg.lr_by_epoch:
            progress = epoch / max(1, math.ceil(self.total_steps / self.steps_per_epoch))
        else:
            progress = step / max(1, self.total_steps)
        progress = min(1.0, progress)
        return cfg.min_lr_ratio + (1.0 - cfg.min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))

    def lr_factor(self, step: int) -> float:
        """The multiplier of ``lr`` at optimizer step ``step`` (0-based), warm-up included."""
        cfg = self.train
        factor = self.regular_factor(step)
        if step < cfg.warmup_steps:
            factor *= cfg.warmup_ratio + (1.0 - cfg.warmup_ratio) * step / cfg.warmup_steps
        return factor

    def lr(self, step: int) -> float:
        """The learning rate at optimizer step ``step``."""
        return self.train.lr * self.lr_factor(step)

    def ema_decay(self, step: int) -> float:
        """The EMA decay applied after optimizer step ``step`` (0-based): the ``step + 1``-th update."""
        cfg = self.train
        if cfg.ema_ramp <= 0:
            return cfg.ema_decay
        updates = cfg.ema_initial_updates + step + 1
        return cfg.ema_decay * (1.0 - math.exp(-updates / cfg.ema_ramp))
