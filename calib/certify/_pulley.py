"""Bound of the swivel-pulley effect on cable length, for certifying the pulley entry points d_i.

Certification uses the straight distance |B_i - d_i| from the platform point to the pulley entry point; the
robot's length model (calib.kinematics, Zoffoli eq. 1-5) winds the cable on the pulley. Their difference
e_p = |B_i - d_i| - l_i goes into the bounded model error: [dL] becomes [dL_lo + min e_p, dL_hi + max e_p].
The range is taken over a grid of the workspace positions and Euler angles within +-angle_range, widened
by a Lipschitz margin: the largest gradient norm seen on the grid (doubled) times the half-diagonal of a
grid cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.kinematics import inverse_kinematics, kinematic_jacobians, pose_jacobian_of_points
from calib.robot import Robot


@dataclass(frozen=True)
class PulleyBound:
    """Range of |B_i - d_i| - l_i over the workspace, per cable (n,) and overall, m."""

    lo: np.ndarray
    hi: np.ndarray
    margin: float

    @property
    def interval(self) -> tuple[float, float]:
        """(min, max) over all cables, margin included, m."""
        return float(self.lo.min()), float(self.hi.max())


def pulley_length_bound(robot: Robot, angle_range: float = 0.1, points: int = 13) -> PulleyBound:
    """Range of the straight-distance minus pulley-model length over the workspace, with its margin (m)."""
    lo, hi = np.asarray(robot.workspace_lower), np.asarray(robot.workspace_upper)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"robot '{robot.name}': field 'workspace' is missing; cannot bound the pulley effect.")
    n_ang = 5
    pos = np.stack(np.meshgrid(*[np.linspace(lo[j], hi[j], points) for j in range(3)], indexing="ij"), -1)
    pos = pos.reshape(-1, 3)
    angles = np.linspace(-angle_range, angle_range, n_ang)
    step = np.array([(hi[j] - lo[j]) / (points - 1) for j in range(3)] + [2 * angle_range / (n_ang - 1)] * 3)
    dmin, dmax = np.full(robot.n, np.inf), np.full(robot.n, -np.inf)
    slope = 0.0
    for ang in np.stack(np.meshgrid(angles, angles, angles, indexing="ij"), -1).reshape(-1, 3):
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
    return PulleyBound(diff.min(axis=0) - margin, diff.max(axis=0) + margin, margin)
