"""Empirical-Bayes shrinkage of one group's per-cable variance factors toward their pooled level
(:func:`cable_factors`, used by :func:`calib.selfcal.noise.rescaled_sigma`): the prior's degrees of freedom from
the spread of the cables' log variances beyond their own chi2 sampling (Smyth 2004). digamma and trigamma are
computed here with the math module alone: scipy.special's import costs a command ~0.15 s (calib/chi2.py)."""

from __future__ import annotations

import math

import numpy as np


def _digamma(x: float) -> float:
    """psi(x) for x > 0: the recurrence up to 10, then the asymptotic series (error < 1e-12)."""
    acc = 0.0
    while x < 10.0:
        acc -= 1.0 / x
        x += 1.0
    r = 1.0 / (x * x)
    return acc + math.log(x) - 0.5 / x - r * (1.0 / 12.0 - r * (1.0 / 120.0 - r * (1.0 / 252.0 - r / 240.0)))


def _trigamma(x: float) -> float:
    """psi'(x) for x > 0: the recurrence up to 10, then the asymptotic series (error < 1e-12)."""
    acc = 0.0
    while x < 10.0:
        acc += 1.0 / (x * x)
        x += 1.0
    r = 1.0 / (x * x)
    return acc + 1.0 / x + 0.5 * r + r / x * (1.0 / 6.0 - r * (1.0 / 30.0 - r * (1.0 / 42.0 - r / 30.0)))


def prior_dof(variances: np.ndarray, dof: np.ndarray) -> float:
    """Empirical-Bayes degrees of freedom d0 of a scaled inverse-chi2 prior shared by k variance estimates
    (``variances`` with ``dof`` degrees of freedom each; Smyth 2004, the moments of log s^2): the spread of the
    logs beyond what their own chi2 sampling makes, Var = trigamma(d0 / 2). inf when they spread no more than
    sampling does (one common variance: pool them), 0 for a spread no prior can hold (keep each its own)."""
    v, r = np.asarray(variances, float), np.asarray(dof, float)
    if v.size < 2 or np.any(v <= 0) or np.any(r <= 0):
        return math.inf
    z = np.log(v) - np.array([_digamma(x / 2.0) - math.log(x / 2.0) for x in r])
    excess = float(np.var(z, ddof=1)) - float(np.mean([_trigamma(x / 2.0) for x in r]))
    if excess <= 0.0:
        return math.inf
    lo, hi = 1e-3, 1e6  # trigamma(d0 / 2) decreases in d0: bisect on a log scale
    if excess >= _trigamma(lo / 2.0):
        return 0.0
    for _ in range(100):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if _trigamma(mid / 2.0) > excess else (lo, mid)
    return math.sqrt(lo * hi)


def cable_factors(factors: np.ndarray, dof: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """The cables' variance factors of one group (``factors`` f_i on ``dof`` r_i degrees of freedom, against
    the cables' current ``sigma``) shrunk toward the group's pooled variance by empirical Bayes: each cable's
    variance f_i sigma_i^2 is averaged with the pooled one, sum r_i f_i sigma_i^2 / sum r_i, weighed r_i
    against the prior's d0 (:func:`prior_dof`); returned as factors against ``sigma``. With a few degrees of
    freedom a cable (grid2: about 3) keeps its own factor only as far as the cables' factors differ by more
    than their sampling does; identical cables pool (d0 = inf)."""
    f, r, s2 = np.asarray(factors, float), np.asarray(dof, float), np.asarray(sigma, float) ** 2
    v = f * s2
    pooled = float(np.sum(r * v) / np.sum(r))
    d0 = prior_dof(v, r)
    post = np.full_like(v, pooled) if math.isinf(d0) else (d0 * pooled + r * v) / (d0 + r)
    return post / s2
