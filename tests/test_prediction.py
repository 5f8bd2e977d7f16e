"""Leave-one-pose-out prediction (calib.prediction): exact on a linear block-arrow problem, and the
signed-rank comparison of two models over the left-out poses."""

from __future__ import annotations

import numpy as np

from calib.prediction import Prediction, leave_one_pose_out


def _block_arrow(k=6, m=10, p=3, seed=0):
    rng = np.random.default_rng(seed)
    A = np.zeros((k * m, 6 * k + p))
    row = np.repeat(np.arange(k), m)
    for i in range(k):
        A[i * m : (i + 1) * m, 6 * i : 6 * i + 6] = rng.normal(size=(m, 6))
        A[i * m : (i + 1) * m, 6 * k :] = rng.normal(size=(m, p))
    y = rng.normal(size=k * m)
    return A, y, row


def test_linearised_leave_one_out_is_the_exact_refit_on_a_linear_problem():
    A, y, row = _block_arrow()
    k = 6
    x = np.linalg.lstsq(A, -y, rcond=None)[0]
    r = y + A @ x  # residuals at the full fit's solution
    pred = leave_one_pose_out(r, A, row, k)
    for i in range(k):  # refit without pose i, then fit pose i alone to its readings
        held = row == i
        keep = np.ones(A.shape[1], bool)
        keep[6 * i : 6 * i + 6] = False
        xi = np.linalg.lstsq(A[~held][:, keep], -y[~held], rcond=None)[0]
        e = y[held] + A[held][:, keep] @ xi
        P = A[held][:, 6 * i : 6 * i + 6]
        e = e - P @ np.linalg.lstsq(P, e, rcond=None)[0]
        assert abs(pred.rows[i] - e @ e) <= 1e-8 * (e @ e)
    assert pred.total > r @ r  # what a fit has not seen, it predicts worse than what it has


def test_better_on_most_poses_versus_better_in_sum():
    base = Prediction(np.array([10.0, 12.0, 9.0, 11.0, 10.0, 13.0, 8.0]))
    consistent = Prediction(base.rows - np.array([2.0, 3.0, 1.0, 2.5, 2.0, 3.0, 1.5]))
    one_pose = Prediction(base.rows + np.array([-30.0, 1.0, 1.0, 1.0, -0.5, 1.0, 1.0]))
    assert consistent.gain_over(base) > 0 and consistent.better_p(base) < 0.01
    assert consistent.clearly_better_than(base)
    assert one_pose.gain_over(base) > 20 and one_pose.better_p(base) > 0.3
    assert not one_pose.clearly_better_than(base)
