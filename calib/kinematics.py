"""Inverse kinematics of a cable robot with swivel pulleys (Zoffoli eq. 1-5) and its analytic Jacobians.

Everything is vectorised over k poses: ``poses`` is (k, 6) = [x, y, z, roll, pitch, yaw] in m and rad,
results are (k, n) or (k, n, 3); Jacobians are (k, n, 6), derivatives with respect to the six pose
coordinates. The cable unit vector ``t`` points from the pulley exit point B_i to the platform anchor A_i,
so that the cable pulls the platform along -t and the equilibrium reads sum(tau_i t_i) = m g (eq. 6-7).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.robot import Robot


def _as_poses(poses: np.ndarray) -> np.ndarray:
    z = np.asarray(poses, dtype=float)
    if z.ndim == 1:
        z = z[None, :]
    if z.ndim != 2 or z.shape[1] != 6:
        raise ValueError(f"poses must have shape (k, 6), got {np.shape(poses)}")
    return z


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (broadcasting), faster than np.cross on many small vectors."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    c0 = a1 * b2 - a2 * b1  # its shape is the broadcast one (no np.broadcast_shapes call: many tiny arrays)
    out = np.empty(c0.shape + (3,))
    out[..., 0] = c0
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def rotation(angles: np.ndarray, convention: str = "xyz") -> np.ndarray:
    """Rotation matrices (k, 3, 3) from Euler angles (k, 3) = [roll, pitch, yaw].

    ``xyz``: R = Rx(roll) Ry(pitch) Rz(yaw) (the IRMA4U authors' code);
    ``zyx``: R = Rz(yaw) Ry(pitch) Rx(roll).
    """
    e = np.atleast_2d(np.asarray(angles, dtype=float))
    return _rotation_of(np.cos(e), np.sin(e), convention)


def _rotation_of(c: np.ndarray, s: np.ndarray, convention: str) -> np.ndarray:
    """:func:`rotation` from the cosines and sines (k, 3) of the angles."""
    c1, c2, c3 = c[:, 0], c[:, 1], c[:, 2]
    s1, s2, s3 = s[:, 0], s[:, 1], s[:, 2]
    R = np.empty((len(c), 3, 3))
    if convention == "xyz":
        R[:, 0, 0] = c2 * c3
        R[:, 0, 1] = -c2 * s3
        R[:, 0, 2] = s2
        R[:, 1, 0] = c1 * s3 + s1 * s2 * c3
        R[:, 1, 1] = c1 * c3 - s1 * s2 * s3
        R[:, 1, 2] = -s1 * c2
        R[:, 2, 0] = s1 * s3 - c1 * s2 * c3
        R[:, 2, 1] = s1 * c3 + c1 * s2 * s3
        R[:, 2, 2] = c1 * c2
    elif convention == "zyx":
        R[:, 0, 0] = c3 * c2
        R[:, 0, 1] = c3 * s2 * s1 - s3 * c1
        R[:, 0, 2] = c3 * s2 * c1 + s3 * s1
        R[:, 1, 0] = s3 * c2
        R[:, 1, 1] = s3 * s2 * s1 + c3 * c1
        R[:, 1, 2] = s3 * s2 * c1 - c3 * s1
        R[:, 2, 0] = -s2
        R[:, 2, 1] = c2 * s1
        R[:, 2, 2] = c2 * c1
    else:
        raise ValueError(f"unknown orientation convention {convention!r}")
    return R


def euler_axes(angles: np.ndarray, convention: str = "xyz") -> np.ndarray:
    """The matrix H (k, 3, 3) whose columns are the world-frame axes of the roll, pitch and yaw rotations.

    The angular velocity is omega = H @ d(angles)/dt, and dR/d(angle_j) @ v = H[:, j] x (R @ v).
    """
    e = np.atleast_2d(np.asarray(angles, dtype=float))
    return _axes_of(np.cos(e), np.sin(e), convention)


def _axes_of(c: np.ndarray, s: np.ndarray, convention: str) -> np.ndarray:
    """:func:`euler_axes` from the cosines and sines (k, 3) of the angles."""
    h = np.zeros((len(c), 3, 3))
    if convention == "xyz":  # roll axis e_x; pitch axis Rx e_y; yaw axis Rx Ry e_z
        h[:, 0, 0] = 1.0
        h[:, 1, 1], h[:, 2, 1] = c[:, 0], s[:, 0]
        h[:, 0, 2], h[:, 1, 2], h[:, 2, 2] = s[:, 1], -s[:, 0] * c[:, 1], c[:, 0] * c[:, 1]
    elif convention == "zyx":  # yaw axis e_z; pitch axis Rz e_y; roll axis Rz Ry e_x
        h[:, 2, 2] = 1.0
        h[:, 0, 1], h[:, 1, 1] = -s[:, 2], c[:, 2]
        h[:, 0, 0], h[:, 1, 0], h[:, 2, 0] = c[:, 2] * c[:, 1], s[:, 2] * c[:, 1], -s[:, 1]
    else:
        raise ValueError(f"unknown orientation convention {convention!r}")
    return h


def euler_axes_derivative(angles: np.ndarray, convention: str = "xyz") -> np.ndarray:
    """dH/d(angles): (k, 3, 3, 3) with [..., :, j, m] = d(column j of H)/d(angle m)."""
    h = euler_axes(angles, convention)
    k = h.shape[0]
    dh = np.zeros((k, 3, 3, 3))
    cols = [h[:, :, 0], h[:, :, 1], h[:, :, 2]]
    # An axis depends only on the rotations applied before it in the product; d/d(earlier angle) is a cross.
    order = (0, 1, 2) if convention == "xyz" else (2, 1, 0)
    for pos, j in enumerate(order):
        for m in order[:pos]:
            dh[:, :, j, m] = cross(cols[m], cols[j])
    return dh


def rotation_to_euler(rot: np.ndarray, convention: str = "xyz") -> np.ndarray:
    """Euler angles (k, 3) of rotation matrices (k, 3, 3), inverse of :func:`rotation` (away from gimbal lock)."""
    r = np.asarray(rot, dtype=float).reshape(-1, 3, 3)
    if convention == "xyz":
        pitch = np.arcsin(np.clip(r[:, 0, 2], -1, 1))
        roll = np.arctan2(-r[:, 1, 2], r[:, 2, 2])
        yaw = np.arctan2(-r[:, 0, 1], r[:, 0, 0])
    elif convention == "zyx":
        pitch = np.arcsin(np.clip(-r[:, 2, 0], -1, 1))
        roll = np.arctan2(r[:, 2, 1], r[:, 2, 2])
        yaw = np.arctan2(r[:, 1, 0], r[:, 0, 0])
    else:
        raise ValueError(f"unknown orientation convention {convention!r}")
    return np.stack([roll, pitch, yaw], -1)


def convert_euler(angles: np.ndarray, source: str, target: str, rotations: np.ndarray | None = None,
                  axes: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The same rotations (k, 3 angles in ``source``) in the ``target`` convention, and d(target)/d(source).

    The Jacobian (k, 3, 3) is H_target^-1 H_source: both map angle rates to the same angular velocity.
    ``rotations`` and ``axes``: ``rotation(angles, source)`` and ``euler_axes(angles, source)`` if already
    computed (a :class:`Kinematics`' R and H), the same numbers.
    """
    a = np.atleast_2d(np.asarray(angles, dtype=float))
    if source == target:
        return a.copy(), np.broadcast_to(np.eye(3), (len(a), 3, 3)).copy()
    out = rotation_to_euler(rotation(a, source) if rotations is None else rotations, target)
    jac = np.linalg.solve(euler_axes(out, target), euler_axes(a, source) if axes is None else axes)
    return out, jac


@dataclass(frozen=True)
class Kinematics:
    """Inverse-kinematic quantities at k poses for n cables (arrays (k, n) or (k, n, 3)), SI units.

    ``a_rel`` is R a'_i (anchor relative to P, in the fixed frame); ``q`` = a_i - d_i; ``rho`` is the
    straight segment B_i -> A_i and ``t`` its unit vector; ``u``, ``w``, ``nv`` the pulley unit vectors of eq. 1;
    ``rho_u``, ``rho_k`` the components q.u and q.k of eq. 4; ``R`` and ``H`` the (k, 3, 3) rotation and
    Euler-axis matrices.
    """

    poses: np.ndarray
    R: np.ndarray
    H: np.ndarray
    a_rel: np.ndarray
    q: np.ndarray
    swivel: np.ndarray
    psi: np.ndarray
    u: np.ndarray
    w: np.ndarray
    nv: np.ndarray
    rho: np.ndarray
    rho_norm: np.ndarray
    t: np.ndarray
    rho_u: np.ndarray
    rho_k: np.ndarray
    lengths: np.ndarray


def inverse_kinematics(robot: Robot, poses: np.ndarray) -> Kinematics:
    """Cable lengths (eq. 5), swivel angles (eq. 2), tangency angles (eq. 4) and unit vectors at k poses.

    Works on the local pulley components of q_i: with q.u = hypot(q.i, q.j) the swivel angle needs no
    trigonometry, and tan(psi/2) from eq. 4 gives cos(psi) and sin(psi) rationally.
    """
    z = _as_poses(poses)
    c, s = np.cos(z[:, 3:]), np.sin(z[:, 3:])  # once for R and H
    R = _rotation_of(c, s, robot.orientation)
    H = _axes_of(c, s, robot.orientation)
    a_rel = np.matmul(R, robot.a_local.T).transpose(0, 2, 1)  # (k, n, 3)
    q = a_rel + (z[:, None, :3] - robot.d[None])
    ql = np.empty_like(q)  # (k, n, 3): q.i, q.j, q.k
    for i in range(robot.n):
        ql[:, i, :] = q[:, i, :] @ robot.frames[i].T
    qi, qj, rho_k = ql[..., 0], ql[..., 1], ql[..., 2]
    swivel = np.arctan2(qj, qi)
    rho_u = np.hypot(qi, qj)  # q.u, since q has no component along w
    cs, ss = qi / rho_u, qj / rho_u
    fi, fj, fk = robot.frames[:, 0], robot.frames[:, 1], robot.frames[:, 2]
    u = cs[..., None] * fi + ss[..., None] * fj
    w = -ss[..., None] * fi + cs[..., None] * fj
    r = robot.r[None, :]
    ratio = rho_k / rho_u
    half = ratio + np.sqrt(ratio * ratio + 1.0 - 2.0 * r / rho_u)  # tan(psi / 2), eq. 4
    psi = 2.0 * np.arctan(half)
    h2 = half * half
    cp, sp = (1.0 - h2) / (1.0 + h2), 2.0 * half / (1.0 + h2)
    nv = cp[..., None] * u + sp[..., None] * fk
    ru = rho_u - r * (1.0 + cp)  # components of rho along u and k (none along w)
    rk = rho_k - r * sp
    rho_norm = np.hypot(ru, rk)
    t = (ru / rho_norm)[..., None] * u + (rk / rho_norm)[..., None] * fk
    rho = rho_norm[..., None] * t
    lengths = rho_norm + r * (np.pi - psi)
    return Kinematics(z, R, H, a_rel, q, swivel, psi, u, w, nv, rho, rho_norm, t, rho_u, rho_k, lengths)


def pose_gradients(kin: Kinematics, vectors: np.ndarray) -> np.ndarray:
    """Pose gradients of c_i . q_i for per-cable vectors c (k, n, m, 3): (k, n, m, 6).

    d(c . q)/dp = c and d(c . q)/d(angle_j) = c . (h_j x R a') = h_j . (R a' x c).
    """
    out = np.empty(vectors.shape[:-1] + (6,))
    out[..., :3] = vectors
    m = cross(kin.a_rel[:, :, None, :], vectors)
    out[..., 3:] = np.matmul(m, kin.H[:, None])
    return out


def pose_jacobian_of_points(kin: Kinematics) -> np.ndarray:
    """dq_i/dzeta: (k, n, 3, 6). Translation is the identity; rotation: d(R a')/d(angle_j) = h_j x R a'."""
    k, n = kin.lengths.shape
    return pose_gradients(kin, np.broadcast_to(np.eye(3), (k, n, 3, 3)))


@dataclass(frozen=True)
class KinematicJacobians:
    """Analytic derivatives of lengths, swivel and tangency angles with respect to the pose, (k, n, 6)."""

    lengths: np.ndarray
    swivel: np.ndarray
    psi: np.ndarray


def kinematic_jacobians(robot: Robot, kin: Kinematics) -> KinematicJacobians:
    """d(lengths)/dzeta, d(swivel)/dzeta and d(psi)/dzeta, analytic.

    dl = t . dq (the wrapped arc and the straight segment compensate); dsigma = w . dq / (q . u) from eq. 2;
    dpsi from differentiating the tangency condition n.rho = 0, i.e. cos(psi)(rho_u - r) + sin(psi) rho_k = r.
    """
    cp, sp = np.cos(kin.psi), np.sin(kin.psi)
    r = robot.r[None, :]
    den = kin.rho_k * cp - (kin.rho_u - r) * sp
    v_psi = -(cp[..., None] * kin.u + sp[..., None] * robot.frames[None, :, 2]) / den[..., None]
    vecs = np.stack([kin.t, kin.w / kin.rho_u[..., None], v_psi], axis=2)  # (k, n, 3, 3)
    g = pose_gradients(kin, vecs)
    return KinematicJacobians(g[:, :, 0], g[:, :, 1], g[:, :, 2])


def cable_direction_jacobian(robot: Robot, kin: Kinematics, jac: KinematicJacobians) -> np.ndarray:
    """dt_i/dzeta: (k, n, 3, 6). dt = (I - t t^T)(dq - r (1 + cos psi) w dsigma) / |rho|."""
    r = robot.r[None, :, None, None]
    dq = pose_jacobian_of_points(kin)
    drho = dq - r * (1.0 + np.cos(kin.psi))[..., None, None] * kin.w[..., None] * jac.swivel[:, :, None, :]
    proj = np.einsum("kna,knaj->knj", kin.t, drho)
    return (drho - kin.t[..., None] * proj[:, :, None, :]) / kin.rho_norm[..., None, None]
