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


def _rx(c, s, one, zero):
    return np.stack([np.stack([one, zero, zero], -1), np.stack([zero, c, -s], -1), np.stack([zero, s, c], -1)], -2)


def _ry(c, s, one, zero):
    return np.stack([np.stack([c, zero, s], -1), np.stack([zero, one, zero], -1), np.stack([-s, zero, c], -1)], -2)


def _rz(c, s, one, zero):
    return np.stack([np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1), np.stack([zero, zero, one], -1)], -2)


def rotation(angles: np.ndarray, convention: str = "xyz") -> np.ndarray:
    """Rotation matrices (k, 3, 3) from Euler angles (k, 3) = [roll, pitch, yaw].

    ``xyz``: R = Rx(roll) Ry(pitch) Rz(yaw) (the IRMA4U authors' code); ``zyx``: R = Rz(yaw) Ry(pitch) Rx(roll).
    """
    e = np.atleast_2d(np.asarray(angles, dtype=float))
    c, s = np.cos(e), np.sin(e)
    one, zero = np.ones(len(e)), np.zeros(len(e))
    rx = _rx(c[:, 0], s[:, 0], one, zero)
    ry = _ry(c[:, 1], s[:, 1], one, zero)
    rz = _rz(c[:, 2], s[:, 2], one, zero)
    if convention == "xyz":
        return rx @ ry @ rz
    if convention == "zyx":
        return rz @ ry @ rx
    raise ValueError(f"unknown orientation convention {convention!r}")


def euler_axes(angles: np.ndarray, convention: str = "xyz") -> np.ndarray:
    """The matrix H (k, 3, 3) whose columns are the world-frame axes of the roll, pitch and yaw rotations.

    The angular velocity is omega = H @ d(angles)/dt, and dR/d(angle_j) @ v = H[:, j] x (R @ v).
    """
    e = np.atleast_2d(np.asarray(angles, dtype=float))
    c, s = np.cos(e), np.sin(e)
    k = len(e)
    h = np.zeros((k, 3, 3))
    if convention == "xyz":  # roll axis e_x; pitch axis Rx e_y; yaw axis Rx Ry e_z
        h[:, 0, 0] = 1.0
        h[:, :, 1] = np.stack([np.zeros(k), c[:, 0], s[:, 0]], -1)
        h[:, :, 2] = np.stack([s[:, 1], -s[:, 0] * c[:, 1], c[:, 0] * c[:, 1]], -1)
    elif convention == "zyx":  # yaw axis e_z; pitch axis Rz e_y; roll axis Rz Ry e_x
        h[:, 2, 2] = 1.0
        h[:, :, 1] = np.stack([-s[:, 2], c[:, 2], np.zeros(k)], -1)
        h[:, :, 0] = np.stack([c[:, 2] * c[:, 1], s[:, 2] * c[:, 1], -s[:, 1]], -1)
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
            dh[:, :, j, m] = np.cross(cols[m], cols[j])
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
    """Cable lengths (eq. 5), swivel angles (eq. 2), tangency angles (eq. 4) and unit vectors at k poses."""
    z = _as_poses(poses)
    R = rotation(z[:, 3:], robot.orientation)
    H = euler_axes(z[:, 3:], robot.orientation)
    a_rel = np.einsum("kab,nb->kna", R, robot.a_local)
    q = z[:, None, :3] + a_rel - robot.d[None]
    fi, fj, fk = robot.frames[:, 0], robot.frames[:, 1], robot.frames[:, 2]
    qi = np.einsum("kna,na->kn", q, fi)
    qj = np.einsum("kna,na->kn", q, fj)
    rho_k = np.einsum("kna,na->kn", q, fk)
    swivel = np.arctan2(qj, qi)
    cs, ss = np.cos(swivel)[..., None], np.sin(swivel)[..., None]
    u = cs * fi + ss * fj
    w = -ss * fi + cs * fj
    rho_u = np.hypot(qi, qj)  # q.u, since q has no component along w
    r = robot.r[None, :]
    ratio = rho_k / rho_u
    psi = 2.0 * np.arctan(ratio + np.sqrt(ratio**2 + 1.0 - 2.0 * r / rho_u))
    cp, sp = np.cos(psi)[..., None], np.sin(psi)[..., None]
    nv = cp * u + sp * fk[None]
    rho = q - r[..., None] * (u + nv)
    rho_norm = np.linalg.norm(rho, axis=-1)
    t = rho / rho_norm[..., None]
    lengths = rho_norm + r * (np.pi - psi)
    return Kinematics(z, R, H, a_rel, q, swivel, psi, u, w, nv, rho, rho_norm, t, rho_u, rho_k, lengths)


def pose_jacobian_of_points(kin: Kinematics) -> np.ndarray:
    """dq_i/dzeta: (k, n, 3, 6). Translation is the identity; rotation: d(R a')/d(angle_j) = h_j x R a'."""
    k, n = kin.lengths.shape
    dq = np.zeros((k, n, 3, 6))
    dq[:, :, 0, 0] = dq[:, :, 1, 1] = dq[:, :, 2, 2] = 1.0
    h = np.swapaxes(kin.H, 1, 2)  # (k, 3 axes, 3 comps)
    dq[..., 3:] = np.swapaxes(np.cross(h[:, None, :, :], kin.a_rel[:, :, None, :]), -1, -2)
    return dq


@dataclass(frozen=True)
class KinematicJacobians:
    """Analytic derivatives with respect to the pose (k, n, 6) and the point Jacobian dq (k, n, 3, 6)."""

    dq: np.ndarray
    lengths: np.ndarray
    swivel: np.ndarray
    psi: np.ndarray


def kinematic_jacobians(robot: Robot, kin: Kinematics) -> KinematicJacobians:
    """d(lengths)/dzeta, d(swivel)/dzeta and d(psi)/dzeta, analytic.

    dl = t . dq (the wrapped arc and the straight segment compensate); dsigma follows from eq. 2;
    dpsi from differentiating the tangency condition n.rho = 0, i.e. cos(psi)(rho_u - r) + sin(psi) rho_k = r.
    """
    dq = pose_jacobian_of_points(kin)
    dl = np.einsum("kna,knaj->knj", kin.t, dq)
    fi, fj, fk = robot.frames[:, 0], robot.frames[:, 1], robot.frames[:, 2]
    # dsigma = (w . dq) / (q . u)
    dsig = np.einsum("kna,knaj->knj", kin.w, dq) / kin.rho_u[..., None]
    du = np.einsum("kna,knaj->knj", kin.u, dq)
    dk = np.einsum("na,knaj->knj", fk, dq)
    cp, sp = np.cos(kin.psi), np.sin(kin.psi)
    r = robot.r[None, :]
    den = kin.rho_k * cp - (kin.rho_u - r) * sp
    dpsi = -(cp[..., None] * du + sp[..., None] * dk) / den[..., None]
    del fi, fj
    return KinematicJacobians(dq, dl, dsig, dpsi)


def cable_direction_jacobian(robot: Robot, kin: Kinematics, jac: KinematicJacobians) -> np.ndarray:
    """dt_i/dzeta: (k, n, 3, 6). dt = (I - t t^T)(dq - r (1 + cos psi) w dsigma) / |rho|."""
    r = robot.r[None, :, None, None]
    drho = jac.dq - r * (1.0 + np.cos(kin.psi))[..., None, None] * kin.w[..., None] * jac.swivel[:, :, None, :]
    proj = np.einsum("kna,knaj->knj", kin.t, drho)
    return (drho - kin.t[..., None] * proj[:, :, None, :]) / kin.rho_norm[..., None, None]
