"""Thick spheres of the calibration equations (Sandretto eq. 2) from bounded measurement errors.

For measurement k of cable i the platform point is B = P + R(e) b_i, measured as B0 = P0 + R(e0) b_i with
|P - P0| <= pose_tol per axis, |e - e0| <= angle_tol per Euler angle and b_i known to +-platform_tol per
axis. Instead of the interval point [B] = [P] + [R][b] (whose naive rotation product overestimates badly)
the error E = B - B0 is folded into the radius of a sphere centred on the *point* B0:

    E = dP + J de + r,   J = [h_j x R(e0) b]_j (the centred, mean-value form of R(e) b about e0),
    |r| <= 1/2 |de|_1^2 |b| + sqrt(3) platform_tol       (second derivatives of R b are bounded by |b|),

and for any anchor a of the initial box, with u the unit vector from a to B0 and d = |B0 - a|,

    |B - a| - d  in  [u.E, u.E + |E|^2 / (2 (d - |E|))],

where |u.E| <= w = pose_tol |u|_1 + angle_tol sum_j |u.J_j| + |r| holds for every u of the directions
from the box (|u - u0| <= 2 h / d0, h the half-diagonal of the box). Hence |B0 - a| in
[L + dL_lo - w - s, L + dL_hi + w]: a thick sphere about a point, on which HC4-revise is optimal.

The naive form (``rotation_bound="naive"``) encloses [B] by interval arithmetic on [Rx][Ry][Rz][b] and uses
the same radius rule; it is kept for comparison.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.certify._rounding import codac, codac_rounding
from calib.kinematics import euler_axes, rotation
from calib.robot import Robot

# Margin covering the floating-point rounding of the radius computation (m); the values are O(1) m, so
# rounding errors are O(1e-15) m.
_ROUNDING_MARGIN = 1e-9


@dataclass(frozen=True)
class Shells:
    """Thick spheres |centre - a| in [r_lo, r_hi] for one cable: centres (k, 3), r_lo and r_hi (k,), m."""

    centres: np.ndarray
    r_lo: np.ndarray
    r_hi: np.ndarray

    @property
    def thickness(self) -> np.ndarray:
        """r_hi - r_lo (k,), m."""
        return self.r_hi - self.r_lo


def _naive_error_radius(orientation: str, angles: np.ndarray, b: np.ndarray, centre_rb: np.ndarray,
                        angle_tol: float, platform_tol: float) -> np.ndarray:
    """Half-widths (k, 3) of [R]([b]) - R(e0) b with [R] = [Rx][Ry][Rz] evaluated in interval arithmetic."""
    out = np.zeros((len(angles), 3))
    bi = [codac.Interval(x - platform_tol, x + platform_tol) for x in b]
    for k, e in enumerate(angles):
        c = [codac.cos(codac.Interval(v - angle_tol, v + angle_tol)) for v in e]
        s = [codac.sin(codac.Interval(v - angle_tol, v + angle_tol)) for v in e]
        one, zero = codac.Interval(1.0), codac.Interval(0.0)
        rx = [[one, zero, zero], [zero, c[0], -s[0]], [zero, s[0], c[0]]]
        ry = [[c[1], zero, s[1]], [zero, one, zero], [-s[1], zero, c[1]]]
        rz = [[c[2], -s[2], zero], [s[2], c[2], zero], [zero, zero, one]]
        first, second, third = (rx, ry, rz) if orientation == "xyz" else (rz, ry, rx)
        m = _imatmul(_imatmul(first, second), third)
        for a in range(3):
            comp = m[a][0] * bi[0] + m[a][1] * bi[1] + m[a][2] * bi[2]
            out[k, a] = max(abs(comp.ub() - centre_rb[k, a]), abs(comp.lb() - centre_rb[k, a]))
    return out


def _imatmul(x: list, y: list) -> list:
    return [[x[i][0] * y[0][j] + x[i][1] * y[1][j] + x[i][2] * y[2][j] for j in range(3)] for i in range(3)]


def cable_shells(
    robot: Robot,
    cable: int,
    poses: np.ndarray,
    lengths: np.ndarray,
    box_lo: np.ndarray,
    box_hi: np.ndarray,
    *,
    pose_tol: float,
    angle_tol: float,
    platform_tol: float,
    model_error: tuple[float, float],
    rotation_bound: str = "centred",
) -> Shells:
    """The thick spheres of cable ``cable`` (0-based) from poses (k, 6) and its lengths (k,), for anchors in
    the box [box_lo, box_hi] (m). ``model_error`` is [dL] = distance - length (m)."""
    poses = np.atleast_2d(np.asarray(poses, float))
    lengths = np.asarray(lengths, float)
    b = np.asarray(robot.a_local[cable], float)
    rot = rotation(poses[:, 3:], robot.orientation)
    rb = rot @ b
    centres = poses[:, :3] + rb
    a0 = 0.5 * (box_lo + box_hi)
    h = 0.5 * float(np.linalg.norm(box_hi - box_lo))
    v0 = centres - a0
    d0 = np.linalg.norm(v0, axis=1)
    u0 = v0 / d0[:, None]
    du = np.minimum(2.0 * h / d0, 2.0)  # bound of |u - u0| over the box
    bnorm = float(np.linalg.norm(b))
    if rotation_bound == "centred":
        hax = euler_axes(poses[:, 3:], robot.orientation)  # columns: roll, pitch, yaw axes
        jac = np.cross(np.swapaxes(hax, 1, 2), rb[:, None, :])  # (k, 3 angles, 3 comps): h_j x R b
        rem = 0.5 * (3.0 * angle_tol) ** 2 * bnorm + np.sqrt(3.0) * platform_tol
        proj = np.abs(np.einsum("kjc,kc->kj", jac, u0)) + du[:, None] * np.linalg.norm(jac, axis=2)
        w = pose_tol * (np.abs(u0).sum(axis=1) + np.sqrt(3.0) * du) + angle_tol * proj.sum(axis=1) + rem
        emax = np.sqrt(3.0) * pose_tol + angle_tol * np.linalg.norm(jac, axis=2).sum(axis=1) + rem
    elif rotation_bound == "naive":
        with codac_rounding():
            half = _naive_error_radius(robot.orientation, poses[:, 3:], b, rb, angle_tol, platform_tol)
        half = half + pose_tol
        w = ((np.abs(u0) + du[:, None]) * half).sum(axis=1)
        emax = np.linalg.norm(half, axis=1)
    else:
        raise ValueError(f"rotation_bound = {rotation_bound!r} must be 'centred' or 'naive'.")
    dmin = d0 - h
    if np.any(dmin <= 2.0 * emax):
        k = int(np.argmin(dmin - 2.0 * emax))
        raise ValueError(
            f"measurement {k}: the platform point of cable {cable + 1} comes within {dmin[k]:.3g} m of the "
            f"anchor box, too close for the distance bound."
        )
    s = emax**2 / (2.0 * (dmin - emax))
    r_lo = np.maximum(lengths + model_error[0] - w - s - _ROUNDING_MARGIN, 0.0)
    r_hi = lengths + model_error[1] + w + _ROUNDING_MARGIN
    return Shells(centres, r_lo, r_hi)
