"""Tension trajectories between setpoints: 5th-degree polynomials at rest at both ends.

Each segment goes from tension vector ``a`` to ``b`` (N) in a duration T (s) with
tau(s) = a + (b - a) p(s), s = t / T, p(s) = 10 s^3 - 15 s^4 + 6 s^5, so rate and acceleration are zero at
both ends (Zoffoli Section 3.2, footnote 2). The peak rate of p is 15/8 at s = 1/2, hence the shortest
duration that keeps every cable's rate under ``max_rate`` (N/s) is T = 15/8 max|b - a| / max_rate.
Evaluation is vectorised over times: arrays (m,) in, (m, n) out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.constants import QUINTIC_PEAK_RATE as PEAK_RATE  # max of dp/ds on [0, 1]

PEAK_ACCEL = 10.0 / np.sqrt(3.0)  # max of |d2p/ds2| on [0, 1], at s = 1/2 -+ sqrt(3)/6


def quintic_profile(s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """p(s), p'(s), p''(s) of the rest-to-rest quintic, s clipped to [0, 1] (dimensionless)."""
    s = np.clip(np.asarray(s, dtype=float), 0.0, 1.0)
    s2 = s * s
    s3 = s2 * s
    p = s3 * (10.0 - 15.0 * s + 6.0 * s2)
    dp = 30.0 * s2 * (1.0 - s) ** 2
    ddp = 60.0 * s * (1.0 - s) * (1.0 - 2.0 * s)
    return p, dp, ddp


def segment_duration(a: np.ndarray, b: np.ndarray, max_rate: float, min_duration: float = 0.0) -> float:
    """Shortest duration (s) of a quintic from a to b (N) whose rate stays under max_rate (N/s)."""
    if not max_rate > 0:
        raise ValueError(f"max_rate must be positive, got {max_rate!r} N/s.")
    span = float(np.max(np.abs(np.asarray(b, dtype=float) - np.asarray(a, dtype=float)), initial=0.0))
    return max(PEAK_RATE * span / max_rate, float(min_duration))


@dataclass(frozen=True)
class TensionTrajectory:
    """A chain of quintic segments through ``waypoints`` (m+1, n) N, with ``durations`` (m,) s.

    Time 0 is the start of the first segment; before it the trajectory holds the first waypoint and after the
    end it holds the last one.
    """

    waypoints: np.ndarray
    durations: np.ndarray

    def __post_init__(self) -> None:
        w = np.atleast_2d(np.asarray(self.waypoints, dtype=float))
        d = np.atleast_1d(np.asarray(self.durations, dtype=float))
        if w.shape[0] != d.shape[0] + 1:
            raise ValueError(f"{w.shape[0]} waypoints need {w.shape[0] - 1} durations, got {d.shape[0]}.")
        if np.any(d < 0) or not np.all(np.isfinite(d)):
            raise ValueError(f"segment durations must be finite and non-negative, got {d.tolist()}.")
        object.__setattr__(self, "waypoints", w)
        object.__setattr__(self, "durations", d)
        object.__setattr__(self, "_starts", np.concatenate([[0.0], np.cumsum(d)]))

    @classmethod
    def through(
        cls, waypoints: np.ndarray, max_rate: float, min_duration: float = 0.0
    ) -> TensionTrajectory:
        """Segments timed by the maximum tension rate (N/s), each at least min_duration (s) long."""
        w = np.atleast_2d(np.asarray(waypoints, dtype=float))
        d = [segment_duration(w[i], w[i + 1], max_rate, min_duration) for i in range(len(w) - 1)]
        return cls(w, np.array(d))

    @property
    def n(self) -> int:
        return int(self.waypoints.shape[1])

    @property
    def duration(self) -> float:
        """Total duration, s."""
        return float(self._starts[-1])

    @property
    def starts(self) -> np.ndarray:
        """(m+1,) start time of each segment and the end time, s."""
        return self._starts

    def evaluate(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Reference tension (N), rate (N/s) and acceleration (N/s^2), each (m, n), at times t (m,) s."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        m = len(self.durations)
        if m == 0:
            z = np.zeros((len(t), self.n))
            return np.broadcast_to(self.waypoints[0], z.shape).copy(), z, z.copy()
        seg = np.clip(np.searchsorted(self._starts, t, side="right") - 1, 0, m - 1)
        T = self.durations[seg]
        safe_T = np.where(T > 0, T, 1.0)
        s = np.where(T > 0, (t - self._starts[seg]) / safe_T, (t >= self._starts[seg + 1]).astype(float))
        p, dp, ddp = quintic_profile(s)
        inside = (s > 0.0) & (s < 1.0) & (T > 0)
        delta = self.waypoints[seg + 1] - self.waypoints[seg]
        tau = self.waypoints[seg] + delta * p[:, None]
        rate = np.where(inside[:, None], delta * (dp / safe_T)[:, None], 0.0)
        accel = np.where(inside[:, None], delta * (ddp / safe_T**2)[:, None], 0.0)
        return tau, rate, accel

    def at(self, t: float) -> np.ndarray:
        """Reference tension (n,) N at one time t (s): the scalar fast path the control loop uses."""
        starts = self._starts
        if t <= 0.0 or len(self.durations) == 0:
            return self.waypoints[0].copy()
        if t >= starts[-1]:
            return self.waypoints[-1].copy()
        i = int(np.searchsorted(starts, t, side="right")) - 1
        T = float(self.durations[i])
        s = (t - float(starts[i])) / T if T > 0 else 1.0
        p = s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
        return self.waypoints[i] + (self.waypoints[i + 1] - self.waypoints[i]) * p
