"""How things move: the ego's gently oscillating speed along its lane, and constant-speed tracks along road paths.

Every moving object keeps to a lane (a parallel of a road's path at a fixed offset) at constant speed, so its
pose is an analytic function of time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from occkit.sim.roads import Path

__all__ = ["EgoMotion", "Tracks", "wrap"]


@dataclass(frozen=True)
class EgoMotion:
    """The ego's lane arc length ``s(t) = s0 + v t + (a v / w) (sin(w t + phase) - sin(phase))`` on offset ``l``.

    Its speed ``v (1 + a cos(w t + phase))`` oscillates gently around the scene's mean speed ``v``.
    """

    l: float
    s0: float
    v: float
    a: float
    w: float
    phase: float

    def s(self, t):
        t = np.asarray(t, float)
        return (
            self.s0 + self.v * t + self.a * self.v / self.w * (np.sin(self.w * t + self.phase) - math.sin(self.phase))
        )

    def speed(self, t):
        return self.v * (1.0 + self.a * np.cos(self.w * np.asarray(t, float) + self.phase))

    def deviation(self) -> float:
        """Largest distance (m) between the ego and a car driving at its mean speed from the same start."""
        return 2.0 * self.a * self.v / self.w


@dataclass(frozen=True)
class Tracks:
    """Tracks of ``M`` moving objects as arrays ``(M,)``, fields as in :attr:`occkit.sim.objects.Object.track`."""

    path: np.ndarray
    l: np.ndarray
    s0: np.ndarray
    v: np.ndarray
    reverse: np.ndarray

    @staticmethod
    def of(tracks: list[tuple[int, float, float, float, bool]]) -> Tracks:
        table = np.array(tracks, float).reshape(-1, 5)
        return Tracks(table[:, 0].astype(np.int64), table[:, 1], table[:, 2], table[:, 3], table[:, 4] > 0)

    def poses(self, paths: list[Path], t: np.ndarray) -> tuple[np.ndarray, ...]:
        """``x, y, yaw, vx, vy``, each ``(M, T)``, at times ``t`` ``(T,)``."""
        s_lane = self.s0[:, None] + self.v[:, None] * t[None, :]
        x, y, h = (np.zeros(s_lane.shape) for _ in range(3))
        for p in np.unique(self.path):
            rows = self.path == p
            x[rows], y[rows], h[rows] = paths[p].at_lane(s_lane[rows], self.l[rows, None])
        vx, vy = self.v[:, None] * np.cos(h), self.v[:, None] * np.sin(h)
        return x, y, h + np.pi * self.reverse[:, None], vx, vy


def wrap(angle):
    """Angles folded into ``[-pi, pi)``."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi
