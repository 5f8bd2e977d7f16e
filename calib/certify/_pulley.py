"""Bound of the swivel-pulley effect on cable length, for certifying the pulley entry points d_i.

Certification uses the straight distance |B_i - d_i| from the platform point to the pulley entry point; the
robot's length model (calib.kinematics, Zoffoli eq. 1-5) winds the cable on the pulley. Their difference
e_p = |B_i - d_i| - l_i goes into the bounded model error: [dL] becomes [dL_lo + min e_p, dL_hi + max e_p].
The range is taken over a grid of a pose region (positions and Euler angles), widened by a Lipschitz
margin: twice the largest first-order change over half a grid cell seen on the grid. Moving d_i by delta
changes e_p as moving the platform by -delta does (the pulley frames are fixed), so the region's positions
are widened by the anchor tolerance to cover the unknown d_i.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.kinematics import inverse_kinematics, kinematic_jacobians, pose_jacobian_of_points
from calib.robot import Robot


@dataclass(frozen=True)
class PulleyBound:
    """Range of |B_i - d_i| - l_i over a pose region, per cable (n,), margin included, and the margin, m."""

    lo: np.ndarray
    hi: np.ndarray
    margin: float

    @property
    def interval(self) -> tuple[float, float]:
        """(min, max) over all cables, margin included, m."""
        return float(self.lo.min()), float(self.hi.max())


def workspace_region(robot: Robot, angle_range: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """The robot's workspace positions with Euler angles in +-angle_range, as (6,) lower and upper bounds."""
    lo, hi = np.asarray(robot.workspace_lower), np.asarray(robot.workspace_upper)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"robot '{robot.name}': field 'workspace' is missing; cannot bound the pulley effect.")
    return np.r_[lo, [-angle_range] * 3], np.r_[hi, [angle_range] * 3]


def pulley_length_bound(robot: Robot, lower: np.ndarray, upper: np.ndarray, points: int = 13,
                        angle_points: int = 5) -> PulleyBound:
    """Range of the straight distance minus the pulley-model length over the poses in [lower, upper] (6,),
    m and rad, on a grid of ``points`` per position axis and ``angle_points`` per angle, with its margin."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    counts = [points] * 3 + [angle_points] * 3
    axes = [np.linspace(lower[j], upper[j], counts[j]) if upper[j] > lower[j] else np.array([lower[j]])
            for j in range(6)]
    step = np.array([(upper[j] - lower[j]) / max(len(axes[j]) - 1, 1) for j in range(6)])
    pos = np.stack(np.meshgrid(*axes[:3], indexing="ij"), -1).reshape(-1, 3)
    angles = np.stack(np.meshgrid(*axes[3:], indexing="ij"), -1).reshape(-1, 3)
    dmin, dmax = np.full(robot.n, np.inf), np.full(robot.n, -np.inf)
    slope = 0.0
    for ang in angles:
        kin = inverse_kinematics(robot, np.concatenate([pos, np.broadcast_to(ang, pos.shape)], 1))
        straight = np.linalg.norm(kin.q, axis=-1)
        diff = straight - kin.lengths  # (k, n)
        dmin, dmax = np.minimum(dmin, diff.min(axis=0)), np.maximum(dmax, diff.max(axis=0))
        # gradient of the difference w.r.t. the pose: (q/|q| - t) . dq/dzeta
        dq = pose_jacobian_of_points(kin)
        grad = np.einsum("kna,knaj->knj", kin.q / straight[..., None], dq) - kinematic_jacobians(robot, kin).lengths
        slope = max(slope, float(np.max(np.abs(grad) @ (0.5 * step))))
    margin = 2.0 * slope
    return PulleyBound(dmin - margin, dmax + margin, margin)
