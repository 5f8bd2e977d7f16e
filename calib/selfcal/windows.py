"""Equilibrium windows found from the signals alone, their averages and the noise their scatter shows.

A sample is still when, over a short centred span, every cable length, swivel angle, roll and pitch stays
within a small range and the tension ripple (standard deviation over the span) stays within the load cells'
uncertainty or, if larger, a few times the noise floor the run shows itself (robust scale of the
sample-to-sample differences). Runs of still samples lasting at least ``min_duration_s`` are windows.
The pretension rest before the sequence is dropped; an unusually long gap between windows gets its
stillest stretch as a ``quasi`` window (the platform passed an equilibrium swinging slowly: the
acceleration it leaves in the statics is small next to the tension noise); see :func:`find_windows`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from calib.robot import Robot


@dataclass(frozen=True)
class WindowOptions:
    """Stillness thresholds (SI units) and durations (s)."""

    span_s: float = 0.5
    min_duration_s: float = 1.0
    length_tol: float = 0.002
    swivel_tol: float = math.radians(0.1)
    tilt_tol: float = math.radians(0.3)
    ripple_factor: float = 3.0
    setpoint_tol: float = 0.15  # relative distance |mean tau - setpoint| / |setpoint| to call it a match
    pretension_band: float = 5.0  # N: tau_ref departing this much from its first value ends the pretension
    gap_factor: float = 2.0
    quasi_max: float = 10.0


@dataclass(frozen=True)
class Window:
    """Samples first..last (inclusive, 0-based) held in equilibrium; setpoint index or -1; quasi when the
    window is the stillest stretch rather than a still one."""

    first: int
    last: int
    setpoint: int = -1
    quasi: bool = False

    @property
    def slice(self) -> slice:
        return slice(self.first, self.last + 1)

    @property
    def size(self) -> int:
        return self.last - self.first + 1

    @property
    def middle(self) -> int:
        return (self.first + self.last) // 2


def _centred(stat: np.ndarray, w: int, size: int) -> np.ndarray:
    """Pad a sliding statistic (size - w + 1,) to (size,) so that entry i describes the span around i."""
    lo = w // 2
    return np.pad(stat, (lo, size - stat.shape[0] - lo), mode="edge")


def noise_floor(x: np.ndarray) -> np.ndarray:
    """Robust white-noise standard deviation per column of x (N, c) from first differences (MAD)."""
    d = np.diff(x, axis=0)
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return 1.4826 * mad / math.sqrt(2.0)


def motion_score(
    robot: Robot, dt: float, tau: np.ndarray, dl: np.ndarray, dsigma: np.ndarray, tilt: np.ndarray,
    options: WindowOptions,
) -> np.ndarray:
    """Per sample (N,), the largest ratio of a channel's activity over the span to its threshold (<= 1: still)."""
    size = dl.shape[0]
    w = max(3, int(round(options.span_s / dt)))
    if size < w:
        return np.full(size, np.inf)

    def ptp(x):
        return _centred(np.ptp(sliding_window_view(x, w, axis=0), axis=-1).max(axis=1), w, size)

    ripple_tol = max(robot.sensors.load_cell_uncertainty, options.ripple_factor * float(noise_floor(tau).max()))
    ripple = _centred(sliding_window_view(tau, w, axis=0).std(axis=-1).max(axis=1), w, size)
    return np.max(
        np.stack([
            ptp(dl) / options.length_tol,
            ptp(dsigma) / options.swivel_tol,
            ptp(tilt) / options.tilt_tol,
            ripple / ripple_tol,
        ]),
        axis=0,
    )


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def find_windows(
    robot: Robot,
    t: np.ndarray,
    tau: np.ndarray,
    dl: np.ndarray,
    dsigma: np.ndarray,
    roll: np.ndarray,
    pitch: np.ndarray,
    tau_ref: np.ndarray | None = None,
    setpoints: np.ndarray | None = None,
    options: WindowOptions | None = None,
) -> list[Window]:
    """Equilibrium windows of a run, in time order (arrays (N,) or (N, n), SI units).

    1. still windows: motion score <= 1 for at least ``min_duration_s``;
    2. the pretension rest (before ``tau_ref`` first departs from its initial value by more than
       ``pretension_band``) is not a planned equilibrium and is dropped;
    3. a gap between windows longer than ``gap_factor`` times the median gap hides an equilibrium the
       platform passed without settling: its stillest stretch (score <= ``quasi_max``) is a quasi window;
    4. with ``setpoints`` (k, n), each window is labelled with the setpoint its mean tension is closest to.
    """
    opt = options or WindowOptions()
    N = dl.shape[0]
    dt = float(np.median(np.diff(t))) if N > 1 else 1.0
    tilt = np.stack([roll, pitch], axis=1)
    score = motion_score(robot, dt, tau, dl, dsigma, tilt, opt)
    w = max(3, int(round(opt.span_s / dt)))
    min_len = max(2, int(math.ceil(opt.min_duration_s / dt)))
    wins = [Window(a, b) for a, b in _runs(score <= 1.0) if b - a + 1 >= min_len]
    if tau_ref is not None and N:
        away = np.flatnonzero(np.max(np.abs(tau_ref - tau_ref[0]), axis=1) > opt.pretension_band)
        if away.size:
            kept = [win for win in wins if win.last >= away[0] + w]
            wins = kept or wins
    if len(wins) >= 3:
        gaps = np.array([b.first - a.last for a, b in zip(wins[:-1], wins[1:], strict=True)])
        limit = opt.gap_factor * float(np.median(gaps))
        extra = []
        for (a, b), gap in zip(zip(wins[:-1], wins[1:], strict=True), gaps, strict=True):
            if gap <= limit:
                continue
            lo, hi = a.last + w, b.first - w
            if hi - lo + 1 < w:
                continue
            seg = score[lo : hi + 1]
            i0 = int(np.argmin(seg))
            if seg[i0] > opt.quasi_max:
                continue
            ok = seg <= max(1.0, 1.5 * seg[i0])
            x = y = i0
            while x > 0 and ok[x - 1]:
                x -= 1
            while y < len(seg) - 1 and ok[y + 1]:
                y += 1
            if y - x + 1 < w:
                x, y = max(0, i0 - w // 2), min(len(seg) - 1, i0 + w // 2)
            extra.append(Window(lo + x, lo + y, quasi=True))
        wins = sorted(wins + extra, key=lambda c: c.first)
    if setpoints is not None and len(setpoints):
        sp = np.asarray(setpoints, dtype=float)
        labelled = []
        for win in wins:
            dist = np.linalg.norm(sp - tau[win.slice].mean(axis=0), axis=1) / np.linalg.norm(sp, axis=1)
            j = int(np.argmin(dist))
            labelled.append(Window(win.first, win.last, j if dist[j] <= opt.setpoint_tol else -1, win.quasi))
        wins = labelled
    return wins
