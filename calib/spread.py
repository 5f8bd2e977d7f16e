"""Is a robot effect one value on every run? Per-run fits of a joint fit's shared effects (issue 28).

A robot effect learned from several runs is worth learning only if the runs agree on it: each run alone
(its own unknowns and the shared effects refitted on that run's rows, from the joint solution and with its
weights) gives values x_r with covariance C_r, and

* the **consistency test**: chi2 = sum_r (x_r - xbar)^T C_r^+ (x_r - xbar), xbar the generalised
  least-squares mean, on (R - 1) times the observable parameters; a small p-value says the runs disagree
  by more than their 1-sigma (the value changed between recordings, or the effect stands for something
  else on some runs' paths);
* the **between-run spread** tau of every parameter (DerSimonian and Laird's moment estimator, the
  random-effects meta-analysis of R estimates with their variances): the 1-sigma of the value a new run
  will show around the mean, beyond the mean's own uncertainty. A model file's 1-sigma carries it, so that
  a new run solved with the model as prior can move a parameter that varied between the runs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calib.chi2 import chi2_sf
from calib.multirun import JointFit, fit_runs

RCOND = 1e-8  # relative cut of a covariance's pseudo-inverse (on parameters scaled to unit joint sigma)


@dataclass
class Spread:
    """Per-run values (R, q) and covariances (R, q, q) of the shared parameters (in the joint fit's order),
    the consistency test (chi2, dof, p) and the between-run 1-sigma tau (q,) of every parameter."""

    runs: list[str]
    values: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int
    p: float
    tau: np.ndarray


def per_run_fits(fit: JointFit) -> list[JointFit]:
    """Each run of a joint fit alone with the same shared effects, started from the joint solution, with
    the run's weights of the joint fit (no new variance-component round)."""
    out = []
    for rf in fit.runs:
        out.append(fit_runs([(rf.name, rf.rows)], fit.shared, starts=[(rf.theta.copy(), rf.poses.copy())],
                            sigmas=[rf.sigma], rounds=0))
    return out


def consistency(x: np.ndarray, cov: np.ndarray, scale: np.ndarray | None = None) -> tuple[float, int]:
    """chi2 and degrees of freedom of R estimates x (R, q) with covariances cov (R, q, q) around their
    generalised least-squares mean; singular covariances (a direction one run cannot see) by
    pseudo-inverse, the dof counting only what the runs see. ``scale`` (q,): typical sizes the parameters
    are divided by before the pseudo-inverses (mixed units)."""
    x = np.asarray(x, float)
    s = np.ones(x.shape[1]) if scale is None else np.where(np.asarray(scale, float) > 0, scale, 1.0)
    xs, cs = x / s, np.asarray(cov, float) / np.outer(s, s)
    inv = [np.linalg.pinv(c, rcond=RCOND, hermitian=True) for c in cs]
    W = sum(inv)
    mean = np.linalg.pinv(W, rcond=RCOND, hermitian=True) @ sum(w @ v for w, v in zip(inv, xs, strict=True))
    chi2 = float(sum((v - mean) @ w @ (v - mean) for w, v in zip(inv, xs, strict=True)))
    ranks = [np.linalg.matrix_rank(w, hermitian=True, tol=RCOND * max(np.abs(w).max(), 1e-300)) for w in inv]
    dof = int(sum(ranks) - np.linalg.matrix_rank(W, hermitian=True, tol=RCOND * max(np.abs(W).max(), 1e-300)))
    return chi2, max(dof, 0)


def between_run_sd(x: np.ndarray, var: np.ndarray) -> np.ndarray:
    """DerSimonian-Laird between-run standard deviation of each column of x (R, q) with variances var
    (R, q): tau^2 = max(0, (Q - (R - 1)) / (S1 - S2 / S1)), Q the weighted sum of squares about the
    inverse-variance mean, S1, S2 the sums of the weights and of their squares. Zero with one run."""
    x, var = np.atleast_2d(np.asarray(x, float)), np.atleast_2d(np.asarray(var, float))
    if x.shape[0] < 2:
        return np.zeros(x.shape[1])
    w = 1.0 / np.maximum(var, 1e-300)
    mean = np.sum(w * x, axis=0) / np.sum(w, axis=0)
    q = np.sum(w * (x - mean) ** 2, axis=0)
    s1, s2 = np.sum(w, axis=0), np.sum(w ** 2, axis=0)
    return np.sqrt(np.maximum(0.0, (q - (x.shape[0] - 1)) / (s1 - s2 / s1)))


def spread(fit: JointFit, cols: Sequence[int] | None = None, fits: list[JointFit] | None = None) -> Spread:
    """The runs' spread of the shared parameters of a joint fit (``cols``: only those, e.g. the effect
    just added; ``fits``: its :func:`per_run_fits` if already made)."""
    fits = per_run_fits(fit) if fits is None else fits
    q = fit.values.shape[0]
    idx = np.arange(q) if cols is None else np.asarray(cols, int)
    x = np.array([f.values[idx] for f in fits])
    c = np.array([f.cov[np.ix_(idx, idx)] for f in fits])
    scale = np.sqrt(np.clip(np.diag(fit.cov)[idx], 0, None))
    chi2, dof = consistency(x, c, scale)
    p = chi2_sf(chi2, dof) if dof > 0 else 1.0
    var = np.clip(np.diagonal(c, axis1=1, axis2=2), 0, None)
    return Spread([rf.name for rf in fit.runs], x, c, chi2, dof, p, between_run_sd(x, var))
