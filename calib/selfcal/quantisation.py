"""The quantisation error of a window mean (Widrow's quantisation of an average): an encoder reading that sits
on one count keeps up to half a step of error however long it is averaged; one that visits several counts
averages it away as its motion spans more steps. :func:`calib.selfcal.noise.pose_free_noise` adds it to the
window means of the lengths and swivel angles (issue 29, docs/windows.md)."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

_MOTION_GRID = np.r_[0.0, np.geomspace(1e-3, 4.0, 240)]  # std of the motion in steps
_HARMONICS = np.arange(1, 80)


def _normal_cdf(x: np.ndarray) -> np.ndarray:
    """The standard normal distribution function, vectorised without scipy (a solve imports none):
    Abramowitz and Stegun 7.1.26 for erf, absolute error below 1.5e-7."""
    z = np.abs(x) / math.sqrt(2.0)
    t = 1.0 / (1.0 + 0.3275911 * z)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    erf = 1.0 - poly * np.exp(-z * z)
    return 0.5 * (1.0 + np.sign(x) * erf)


@lru_cache(maxsize=1)
def _quantisation_tables() -> tuple[np.ndarray, np.ndarray]:
    """For Gaussian motion of std s (steps, :data:`_MOTION_GRID`) about a mean placed uniformly within a step:
    the expected variance of the quantised readings (steps^2) and Widrow's variance of the quantisation error
    of their mean, sum_k |phi(2 pi k)|^2 / (2 pi^2 k^2) with phi the motion's characteristic function (steps^2;
    1/12 for a still reading, 0 once the motion spans several steps)."""
    offsets = (np.arange(128) + 0.5) / 128.0
    cells = np.arange(-16, 17, dtype=float)
    s = np.maximum(_MOTION_GRID, 1e-12)[:, None, None]
    p = _normal_cdf((cells[None, None, :] + 0.5 - offsets[None, :, None]) / s) \
        - _normal_cdf((cells[None, None, :] - 0.5 - offsets[None, :, None]) / s)  # (grid, offsets, cells)
    mean = np.sum(p * cells, axis=2)
    readings = np.mean(np.sum(p * cells**2, axis=2) - mean**2, axis=1)
    k = _HARMONICS[None, :]
    widrow = np.sum(np.exp(-((2.0 * np.pi * k * _MOTION_GRID[:, None]) ** 2)) / (2.0 * np.pi**2 * k**2), axis=1)
    last = float(_HARMONICS[-1]) + 0.5  # the harmonics left out, as an integral (1/12 exactly for s = 0)
    widrow += np.exp(-((2.0 * np.pi * last * _MOTION_GRID) ** 2)) / (2.0 * np.pi**2 * last)
    return readings, widrow


def quantisation_variance(windows: list[np.ndarray], step: float | np.ndarray) -> np.ndarray:
    """Variance (SI^2) of the quantisation error of a window mean of a channel that counts in ``step`` (SI,
    scalar or (c,)), per column of the windows' readings (``windows``: (N_w, c) arrays), averaged over the
    windows: Widrow's quantisation of an average. A reading that sits on one count keeps up to half a step of
    error however long it is averaged (step^2 / 12: no dither); one that visits several counts averages it
    away as its motion spans more steps. Each window's motion is read from its own readings: the std s of a
    Gaussian motion whose quantised readings have, in expectation over where its mean falls within a step,
    the window's variance of the readings (windows differ: a hold at rest, a slow sway). Calibration
    (tests/test_noise.py): exact for a still and a dithered reading; for a white motion of 0.1 and 0.25 steps
    it over-states the error 1.5 and 3.2 times in variance (where the mean falls within its step sets one
    window's variance as much as the motion does: a centred mean reads steady and errs little); on the
    simulator's slow sway, whose ramps err more than a Gaussian motion of the same std, the swivel rows' sigma
    is still 0.95-1.25 times narrower than their error against the truth (docs/windows.md)."""
    if not windows:
        return np.zeros(0)
    q = np.broadcast_to(np.asarray(step, float), (windows[0].shape[1],))
    var_readings, widrow = _quantisation_tables()
    out = np.zeros(q.shape)
    for x in windows:
        r = np.var(np.asarray(x, float), axis=0) / np.where(q > 0, q, 1.0) ** 2
        s = np.interp(r, var_readings, _MOTION_GRID)  # the expected variance grows with s
        out += np.interp(s, _MOTION_GRID, widrow)
    return np.where(q > 0, out / len(windows) * q**2, 0.0)
