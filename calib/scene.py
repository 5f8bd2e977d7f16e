"""The robot's 3D geometry for a viewer, as pure functions of the robot description and the platform pose.

What a 3D view of the robot draws: the frame (the pulleys' swivel points and the floor under them), the
four cables as straight segments from the pulley exit point B_i (where the cable leaves the pulley groove,
eq. 4) to the platform anchor A_i = p + R a'_i, and a colour for each cable's tension. Everything comes from
:func:`calib.kinematics.inverse_kinematics`, so a scene drawn from these points is the model's, to the last
bit. Vectorised over poses; metres, newtons.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.kinematics import _as_poses, inverse_kinematics
from calib.robot import Robot


@dataclass(frozen=True)
class CableSegments:
    """Straight cable segments at k poses: ``exits`` B_i (k, n, 3) on the pulleys, ``anchors`` A_i (k, n, 3) on
    the platform, both in the fixed frame, m."""

    exits: np.ndarray
    anchors: np.ndarray


def cable_segments(robot: Robot, poses: np.ndarray) -> CableSegments:
    """The straight part of every cable at poses (k, 6) or (6,): from the pulley exit point to the anchor."""
    kin = inverse_kinematics(robot, _as_poses(poses))
    anchors = kin.poses[:, None, :3] + kin.a_rel
    return CableSegments(anchors - kin.rho, anchors)


def frame_edges(robot: Robot) -> np.ndarray:
    """Line segments (m, 2, 3) of the frame: a post from the floor (z = 0) to each pulley's swivel point and
    the rings joining the posts' tops and feet, in the order the cables are numbered."""
    top = np.asarray(robot.d, dtype=float)
    foot = top * np.array([1.0, 1.0, 0.0])
    ring = np.roll(np.arange(robot.n), -1)
    return np.concatenate([np.stack([foot, top], 1), np.stack([top, top[ring]], 1), np.stack([foot, foot[ring]], 1)])


def frame_bounds(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """The box (lower (3,), upper (3,)) m the frame encloses: the pulleys' swivel points and the floor."""
    d = np.asarray(robot.d, dtype=float)
    return np.minimum(d.min(0), [np.inf, np.inf, 0.0]), d.max(0)


def tension_colours(tau: np.ndarray, low: float, high: float) -> np.ndarray:
    """RGBA (..., 4) in [0, 1] per tension (...,) N: blue at ``low`` and below, through green, red at ``high``
    and above; a missing tension (NaN) is grey."""
    t = np.asarray(tau, dtype=float)
    s = np.clip((t - low) / (high - low), 0.0, 1.0)
    rgba = np.stack([np.clip(2 * s - 1, 0, 1), 1 - np.abs(2 * s - 1), np.clip(1 - 2 * s, 0, 1), np.ones_like(s)], -1)
    return np.where(np.isfinite(t)[..., None], rgba, [0.5, 0.5, 0.5, 1.0])


def quaternion(poses: np.ndarray, convention: str = "xyz") -> np.ndarray:
    """Unit quaternions (k, 4) as (x, y, z, w) of the platform orientations of poses (k, 6)."""
    from calib.kinematics import rotation

    z = _as_poses(poses)
    R = rotation(z[:, 3:], convention)
    # Shepperd's method: each of the four formulas divides by the largest of 4w^2, 4x^2, 4y^2, 4z^2 (all at once)
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    diag = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], 1)
    s = 2.0 * np.sqrt(np.maximum(diag, 1e-12))  # 4w, 4x, 4y, 4z
    a = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)  # 4w(x, y, z)
    b = np.stack([R[:, 0, 1] + R[:, 1, 0], R[:, 0, 2] + R[:, 2, 0], R[:, 1, 2] + R[:, 2, 1]], 1)  # 4(xy, xz, yz)
    rows = np.stack([  # (x, y, z, w) from each formula, times its divisor
        np.stack([a[:, 0], a[:, 1], a[:, 2], s[:, 0] ** 2 / 4], 1),
        np.stack([s[:, 1] ** 2 / 4, b[:, 0], b[:, 1], a[:, 0]], 1),
        np.stack([b[:, 0], s[:, 2] ** 2 / 4, b[:, 2], a[:, 1]], 1),
        np.stack([b[:, 1], b[:, 2], s[:, 3] ** 2 / 4, a[:, 2]], 1)], 1)
    i = diag.argmax(1)
    k = np.arange(len(z))
    q = rows[k, i] / s[k, i][:, None]
    return q * np.where(q[:, 3:] < 0, -1.0, 1.0)
