"""Actuation non-idealities of the ROOM scope drive (pure numpy, seeded).

Model (Esposito et al., ROOM)
    A command latency ``dt ~ U(0, delay_max_s)`` drawn **once per sequence** from the
    configured seed (a fixed transport/communication delay of the drive; one draw per
    command would reorder commands), and a magnitude-dependent gain::

        q1(t) = q1cmd(t - dt) * (1 + gain_q1 * |q1cmd(t - dt)| / q1_max)
        q2(t) = q2cmd(t - dt) * (1 + gain_q2 * |q2cmd(t - dt)| / (2 pi))
        q3(t) = q3cmd(t - dt)

    ``q1`` is the tendon differential (m), ``q2`` the axial rotation (rad), ``q3`` the
    insertion (m) (:mod:`room_pipeline.robot.kinematics`).  The actual ``q1`` is not clipped:
    at the limit the gain overshoots it by ``gain_q1`` (5 %), as a real tendon drive would.

The command signal is piecewise linear between the controller's knots (one per frame)
and constant before the first and after the last knot.
"""
from __future__ import annotations

import bisect
import math

import numpy as np


def sample_delay(rng: np.random.Generator, delay_max_s: float) -> float:
    """One command latency ``~ U(0, delay_max_s)`` seconds (0 when ``delay_max_s`` is 0)."""
    if delay_max_s <= 0:
        return 0.0
    return float(rng.uniform(0.0, delay_max_s))


def apply_gain(q_cmd, q1_max: float, gain_q1: float = 0.05, gain_q2: float = 0.05) -> np.ndarray:
    """The magnitude-dependent gain on ``q`` (shape (..., 3)): q1 and q2 scaled, q3 unchanged."""
    q = np.array(q_cmd, dtype=float)
    q[..., 0] = q[..., 0] * (1.0 + gain_q1 * np.abs(q[..., 0]) / q1_max)
    q[..., 1] = q[..., 1] * (1.0 + gain_q2 * np.abs(q[..., 1]) / (2.0 * math.pi))
    return q


class CommandSignal:
    """Piecewise-linear command ``q_cmd(t)`` through knots appended in time order."""

    def __init__(self) -> None:
        self._t: list[float] = []
        self._q: list[np.ndarray] = []
        self._arrays: tuple[np.ndarray, np.ndarray] | None = None

    def add(self, t: float, q) -> None:
        if self._t and t <= self._t[-1]:
            raise ValueError(f"command knots must increase in time: {t} after {self._t[-1]}")
        self._t.append(float(t))
        self._q.append(np.asarray(q, dtype=float).reshape(3).copy())
        self._arrays = None

    def __call__(self, t: float) -> np.ndarray:
        if not self._t:
            raise ValueError("no command yet")
        ts = self._t
        if t <= ts[0]:
            return self._q[0].copy()
        if t >= ts[-1]:
            return self._q[-1].copy()
        i = bisect.bisect_right(ts, t) - 1
        w = (t - ts[i]) / (ts[i + 1] - ts[i])
        return (1.0 - w) * self._q[i] + w * self._q[i + 1]

    def batch(self, t) -> np.ndarray:
        """``q_cmd`` at every time of ``t`` (shape (n,)): (n, 3), the same formula as a call per time."""
        if not self._t:
            raise ValueError("no command yet")
        if self._arrays is None:
            self._arrays = (np.asarray(self._t), np.asarray(self._q))
        T, Q = self._arrays
        t = np.asarray(t, dtype=float).reshape(-1)
        if len(T) == 1:
            return np.repeat(Q[:1], len(t), axis=0)
        i = np.clip(np.searchsorted(T, t, side="right") - 1, 0, len(T) - 2)
        w = np.clip((t - T[i]) / (T[i + 1] - T[i]), 0.0, 1.0)[:, None]
        return (1.0 - w) * Q[i] + w * Q[i + 1]


class Actuator:
    """``q_act(t) = gain(q_cmd(t - delay))`` for a :class:`CommandSignal`."""

    def __init__(self, signal: CommandSignal, delay_s: float, q1_max: float,
                 gain_q1: float = 0.05, gain_q2: float = 0.05, enabled: bool = True) -> None:
        self.signal = signal
        self.delay_s = float(delay_s) if enabled else 0.0
        self.q1_max = float(q1_max)
        self.gain_q1 = float(gain_q1) if enabled else 0.0
        self.gain_q2 = float(gain_q2) if enabled else 0.0

    def __call__(self, t: float) -> np.ndarray:
        return apply_gain(self.signal(t - self.delay_s), self.q1_max, self.gain_q1, self.gain_q2)

    def batch(self, t) -> np.ndarray:
        """``q_act`` at every time of ``t`` (shape (n,)): (n, 3)."""
        return apply_gain(self.signal.batch(np.asarray(t, dtype=float) - self.delay_s), self.q1_max,
                          self.gain_q1, self.gain_q2)
