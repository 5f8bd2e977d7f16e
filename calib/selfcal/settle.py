"""The settle test of a still stretch's head (issue 29): what the ranges of :mod:`calib.selfcal.windows` let in
after a move (a platform that still swings or converges) cut until the head matches the stretch's middle.
Used by :class:`calib.selfcal.windows.Stillness` (the offline search and the online detector), with the
per-sample noise figures of a reading that it and the ends test use."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.chi2 import chi2_isf
from calib.robust import median


def sample_noise(x: np.ndarray) -> np.ndarray:
    """Robust white-noise standard deviation per column of x (N, c) from second differences (MAD): a smooth
    motion leaves them near zero, white noise of sigma gives them sigma sqrt(6)."""
    if x.shape[0] < 3:
        return np.zeros(x.shape[1:])
    d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
    return 1.4826 * median(np.abs(d2), axis=0) / math.sqrt(6.0)


def quiet_noise(x: np.ndarray) -> np.ndarray:
    """As :func:`sample_noise`, from the lower quartile of |second differences| instead of their median (a
    Gaussian's |x| has its lower quartile at 0.3186 sigma): the noise of the quietest samples, which holds
    while up to three quarters of a run still swing, as after every move of a lightly damped platform; a
    reading on its counts most of the time falls back on the median's figure or its count / sqrt(12)."""
    if x.shape[0] < 3:
        return np.zeros(x.shape[1:])
    d2 = np.abs(x[2:] - 2.0 * x[1:-1] + x[:-2])
    quiet = np.quantile(d2, 0.25, axis=0) / 0.3186 / math.sqrt(6.0)
    # a reading that mostly sits on its counts (an encoder of a still platform): its median, else its count
    d1 = np.abs(np.diff(x, axis=0))
    step = np.min(np.where(d1 > 0, d1, np.inf), axis=0)
    step = np.where(np.isfinite(step), step / math.sqrt(12.0), 0.0)
    return np.where(quiet > 0, quiet, np.maximum(sample_noise(x), step))


def resolution(x: np.ndarray) -> np.ndarray:
    """Per column of x (N, c), the smallest non-zero change between consecutive samples over sqrt(12): the
    rounding error of a reading on its counts (a reading that never changes: 0)."""
    d1 = np.abs(np.diff(x, axis=0))
    step = np.min(np.where(d1 > 0, d1, np.inf), axis=0) if x.shape[0] > 1 else np.full(x.shape[1:], np.inf)
    return np.where(np.isfinite(step), step / math.sqrt(12.0), 0.0)



@dataclass(frozen=True)
class SettleTest:
    """Whether a still stretch has settled at its head (and tail, ``tail``): a platform still swinging or
    converging after a move (the wobble of a lightly damped platform, the approach's last samples) shows there
    as samples off the line the rest follows or scattered beyond the rest's scatter, in the channels that see
    the motion (the AHRS the swing, the swivels and lengths the approach). The rest is the stretch's middle
    half: per column a line (mean m, slope: a steady creep or a slow sway the whole window shares is the
    window's, its mean is the line's value at the centre) and the residuals' variance s^2 and lag-1
    correlation (the window's own scatter), s floored at ``floor`` (a column's counts, :func:`resolution`;
    an encoder's at least a twelfth of its range floor). Each block of ``q`` samples (0.5 s, a wobble's
    period) between an end and the middle half gives, per channel group (tensions, lengths, swivels, tilt),
    T = sum of ((x - prediction)^2 / its variance); at rest a scaled chi2 (Satterthwaite, for the AR(1)
    correlation), whose 1 - p / (groups x blocks) quantile is its limit. Scanned from the middle outward,
    the innermost block above its limit and all beyond it are cut, and the test runs again on what is left:
    what is kept matches the middle. A swing is caught by its scatter, a slow approach by its offset."""

    q: int
    p: float
    floor: dict[str, np.ndarray]
    tail: bool = False  # test the tail as well as the head

    @classmethod
    def of_samples(cls, tau: np.ndarray, channels: dict[str, np.ndarray], q: int, p: float,
                   tols: dict[str, float], tail: bool = False) -> SettleTest:
        """The test of a run (tensions (N, n) N, ``channels`` the kinematic channels (N, c) by name): blocks of
        ``q`` samples, false-alarm probability ``p``; ``tols`` the encoders' range floors by channel (SI): their
        columns' scatter is at least a twelfth of it, as the ends test's (a few counts of quasi-static motion
        on a precise encoder are not a move: the real winches creep by micrometres in a hold); the AHRS
        angles, never on counts, keep their own scatter (a wobble shows there first: a twelfth of its 0.3 deg
        floor would hide a 2 mrad swing at 0.35 mrad of noise)."""
        every = {"tension": tau} | dict(channels)
        floor = {c: np.maximum(resolution(x), tols.get(c, 0.0) / 12.0).reshape(-1) for c, x in every.items()}
        return cls(max(2, int(q)), p, floor, tail)

    def end_scores(self, x: np.ndarray, floor: np.ndarray, groups: list[slice]) -> tuple[np.ndarray, np.ndarray]:
        """Per block of ``q`` samples starting at 0, 1, ... up to the middle half (the head's) and ending at
        L - 1, L - 2, ... (the tail's, innermost last), the largest T over its limit among the channel
        ``groups`` (column slices of x (L, c)): <= 1 at rest. Empty when the stretch is too short for a
        block on each side of a middle of at least 2 q samples."""
        L = x.shape[0]
        lo, hi = L // 4, L - L // 4
        n = hi - lo
        if lo < self.q or n < max(2 * self.q, 4):
            return np.zeros(0), np.zeros(0)
        # the rest: a line per column over the middle half (a steady creep or a slow sway is the window's, its
        # mean is where the line is at the window's centre), its residuals' variance and lag-1 correlation
        t = np.arange(L, dtype=float)
        centre = 0.5 * (t[lo] + t[hi - 1])
        tm = t[lo:hi] - centre
        sxx = float(tm @ tm)
        mid = x[lo:hi]
        m = mid.mean(axis=0)
        slope = tm @ (mid - m) / sxx
        res = mid - m - np.outer(tm, slope)
        ss = np.sum(res**2, axis=0)
        s2 = np.maximum(ss / (n - 2), np.maximum(floor**2, 1e-300))
        rho = np.clip(np.sum(res[1:] * res[:-1], axis=0) / np.maximum(ss, 1e-300), 0.0, 0.95)
        # each sample's squared deviation from the line's prediction over its variance, per column
        d = t - centre
        z2 = (x - m - np.outer(d, slope)) ** 2 / (s2 * (1.0 + 1.0 / n + (d**2 / sxx)[:, None]))
        # at rest a block's T in a group sums, per column, q squared deviations over a variance estimated on
        # nu = n - 2 degrees of freedom, correlated in time (AR(1)): per column the mean q nu / (nu - 2) and
        # the variance 2 (q + 2 sum_k (q - k) rho^(2k)) nu^2 (q + nu - 2) / ((nu - 2)^2 (nu - 4)) (q F(q, nu)
        # for white noise) give a scaled chi2 (Satterthwaite), whose 1 - p / (groups x disjoint blocks
        # scanned) quantile is the group's limit
        nu = max(n - 2, 5)
        k = np.arange(1, self.q)
        ar = 2.0 * (self.q + 2.0 * np.sum((self.q - k)[None, :] * rho[:, None] ** (2 * k[None, :]), axis=1))
        mean_c = self.q * nu / (nu - 2.0)
        var_c = ar * nu**2 * (self.q + nu - 2.0) / ((nu - 2.0) ** 2 * (nu - 4.0))
        tests = len(groups) * max(1, -(-lo // self.q))
        c = np.cumsum(np.r_[np.zeros((1, x.shape[1])), z2], axis=0)
        block = c[self.q :] - c[: -self.q]  # (L - q + 1, c): the block starting at each sample
        score = np.zeros(block.shape[0])
        for g in groups:
            mean = mean_c * (g.stop - g.start)
            scale = float(np.sum(var_c[g])) / (2.0 * mean)
            limit = scale * chi2_isf(self.p / tests, max(1, int(round(mean / scale))))
            np.maximum(score, block[:, g].sum(axis=1) / limit, out=score)
        heads = score[: lo - self.q + 1]
        tails = score[hi:][::-1]  # blocks ending at L - 1, L - 2, ...
        return heads, tails

    def trim(self, tau: np.ndarray, channels: dict[str, np.ndarray], min_len: int = 2) -> tuple[int, int]:
        """Samples (a, b) to cut from the start and end of a still stretch (tensions (L, n), channels (L, c)):
        the test runs from the middle outward and cuts up to and including the first sample of the innermost
        end block that still moves, then again on what is left, until no end block moves; the whole stretch
        (a + b = L) when fewer than ``min_len`` samples would be left."""
        every = {"tension": tau} | dict(channels)
        L = tau.shape[0]
        cols = [v.reshape(L, -1) for v in every.values()]
        x = np.concatenate(cols, axis=1)
        edges = np.cumsum([0] + [c.shape[1] for c in cols])
        groups = [slice(int(i), int(j)) for i, j in zip(edges[:-1], edges[1:], strict=True)]
        floor = np.concatenate([self.floor[k] for k in every])
        a, b = 0, 0
        while L - a - b >= min_len:
            heads, tails = self.end_scores(x[a : L - b], floor, groups)
            moving_h = np.flatnonzero(heads > 1.0)
            moving_t = np.flatnonzero(tails > 1.0) if self.tail else np.zeros(0, int)
            if moving_h.size == 0 and moving_t.size == 0:
                return a, b
            if moving_h.size:
                a += int(moving_h[-1]) + 1
            if moving_t.size:
                b += int(moving_t[-1]) + 1
        return a, L - a
