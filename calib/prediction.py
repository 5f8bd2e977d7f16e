"""How well a fitted model predicts equilibrium poses it was not fitted to: leave-one-pose-out (issue 17).

For every measurement row i (an equilibrium pose, the reference row excepted: it defines zeta_0), the fit is
redone without row i, and row i's readings are predicted by that fit with row i's pose re-estimated from its
own readings (the pose of an unseen equilibrium is unknown; what the model must predict is the rest: the
tensions, the consistency of lengths, swivels and orientation). The figure is the chi2 of row i's readings
after that, in units of the noise; summed over the rows it is the cross-validated chi2 of the model.

The refit without row i is one Gauss-Newton step from the full fit, on the dense weighted Jacobian at the
solution (linearised leave-one-out, exact for a linear model; the fits the diagnosis compares are converged,
so the step is small). Cost: the normal equations once, then per row a downdate and one dense solve of
size 6(k - 1) + p.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RIDGE = 1e-9  # relative Tikhonov term of the folds' normal equations (unit-norm columns)
LEVEL = 0.05  # one-sided level at which one model predicts the left-out poses better than another


@dataclass
class Prediction:
    """Leave-one-pose-out chi2 of each row (k,) and their sum."""

    rows: np.ndarray

    @property
    def total(self) -> float:
        return float(self.rows.sum())

    def gain_over(self, other: Prediction) -> float:
        """How much lower this model's cross-validated chi2 is than ``other``'s (positive: better)."""
        return other.total - self.total

    def better_p(self, other: Prediction) -> float:
        """One-sided p-value that this model predicts the left-out poses better than ``other``: the
        Wilcoxon signed-rank test of the per-pose decreases of the held-out chi2 (small when most poses are
        predicted better, not just one or two by a lot; exact for up to 50 poses)."""
        d = other.rows - self.rows
        d = d[d != 0]
        if d.size < 2:
            return 1.0
        from scipy import stats  # here: scipy.stats costs the diagnosis's import ~0.45 s CPU, needed with one run only

        return float(stats.wilcoxon(d, alternative="greater").pvalue)

    def clearly_better_than(self, other: Prediction) -> bool:
        """Better than ``other`` on the left-out poses at the LEVEL of :meth:`better_p`."""
        return self.better_p(other) < LEVEL


def leave_one_pose_out(r: np.ndarray, A: np.ndarray, row: np.ndarray, k: int) -> Prediction:
    """Linearised leave-one-pose-out chi2 per row from the weighted residuals r (m,), the dense Jacobian A
    (m, 6k + p; the first 6k columns are the k pose blocks) and each residual's row label (m,; -1 the
    reference row, -2 a prior). The normal equations of the whole fit are formed once; each fold removes
    its row's contribution (a rank-15 downdate) and solves the rest, pose i's block dropped."""
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    As = A / scale
    N = As.T @ As
    g = As.T @ r
    ridge = RIDGE * np.eye(A.shape[1] - 6)  # columns have unit norm: directions the data cannot see stay put
    out = np.zeros(k)
    for i in range(k):
        held = row == i
        if not held.any():
            continue
        keep = np.ones(A.shape[1], bool)
        keep[6 * i : 6 * i + 6] = False
        Ai, ri = As[held], r[held]
        Ni = (N - Ai.T @ Ai)[np.ix_(keep, keep)]
        gi = (g - Ai.T @ ri)[keep]
        delta = -np.linalg.solve(Ni + ridge, gi)
        e = ri + Ai[:, keep] @ delta
        P = Ai[:, 6 * i : 6 * i + 6]
        step, *_ = np.linalg.lstsq(P, e, rcond=1e-10)
        e = e - P @ step
        out[i] = float(e @ e)
    return Prediction(out)
