"""Weighted least-squares estimate of one fixed anchor from the same thick spheres (for comparison).

Residual k is (|a - c_k| - m_k) / sigma_k with m_k the middle of the sphere's radius interval and sigma_k
its half-width / sqrt(3) (the standard deviation of a uniform error over the interval), in m / m.
"""

from __future__ import annotations

import numpy as np

from calib.certify._bounds import Shells

LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")


def anchor_least_squares(shells: Shells, start: np.ndarray, loss: str = "linear") -> np.ndarray:
    """The NWLS anchor estimate (3,), m, from ``start`` (3,); ``loss`` is a scipy.optimize robust loss."""
    if loss not in LOSSES:
        raise ValueError(f"loss = {loss!r} must be one of {', '.join(LOSSES)}.")
    mid = 0.5 * (shells.r_lo + shells.r_hi)
    sigma = np.maximum(0.5 * (shells.r_hi - shells.r_lo) / np.sqrt(3.0), 1e-9)

    def fun(a: np.ndarray) -> np.ndarray:
        return (np.linalg.norm(shells.centres - a, axis=1) - mid) / sigma

    def jac(a: np.ndarray) -> np.ndarray:
        v = a - shells.centres
        return v / np.linalg.norm(v, axis=1)[:, None] / sigma[:, None]

    from scipy.optimize import least_squares  # here: importing scipy.optimize costs every cdpr command ~0.2 s

    sol = least_squares(fun, np.asarray(start, float), jac=jac, loss=loss, f_scale=1.0, x_scale="jac")
    return sol.x
