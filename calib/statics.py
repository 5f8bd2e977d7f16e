"""Statics of the platform (Zoffoli eq. 6-7, 11-12) with analytic Jacobians, vectorised over poses.

Two forms of the equilibrium are used:

* the world wrench about P: ``W tau - f`` with columns xi_i = [t_i; a'_i x t_i] (eq. 7) and
  f = [m g; s' x m g] (eq. 6), in N and N m;
* the generalised form, whose moment rows are projected on the Euler axes H (roll, pitch, yaw), so that
  row 5 is the moment about the yaw axis Rx(roll) Ry(pitch) e_z that the authors' tension model uses.

The tension model (eq. 11-12) is the left inverse built from the ``robot.controlled`` rows of the
generalised form: tau(zeta) = A(zeta)^-1 b(zeta).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.kinematics import (
    KinematicJacobians,
    Kinematics,
    cross,
    euler_axes_derivative,
    inverse_kinematics,
    kinematic_jacobians,
)
from calib.robot import Robot


def gravity_vector(robot: Robot) -> np.ndarray:
    """m g as a vector in the fixed frame, N (z up)."""
    return np.array([0.0, 0.0, -robot.weight])


def structure_matrix(kin: Kinematics) -> np.ndarray:
    """Xi^T (k, 6, n): columns [t_i; a'_i x t_i] (eq. 7)."""
    return np.concatenate([kin.t, cross(kin.a_rel, kin.t)], axis=-1).transpose(0, 2, 1)


def external_wrench(robot: Robot, kin: Kinematics) -> np.ndarray:
    """f (k, 6) = [m g; s' x m g] of eq. 6, with s' = R s the centre of mass offset in the fixed frame."""
    g = gravity_vector(robot)
    s = np.einsum("kab,b->ka", kin.R, robot.com)
    return np.concatenate([np.broadcast_to(g, s.shape), cross(s, g)], axis=-1)


def wrench_residual(robot: Robot, poses: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Xi^T tau - f (k, 6) at k poses under tensions tau (k, n): zero in static equilibrium."""
    kin = inverse_kinematics(robot, poses)
    return np.einsum("kan,kn->ka", structure_matrix(kin), np.atleast_2d(tau)) - external_wrench(robot, kin)


@dataclass(frozen=True)
class GeneralisedStatics:
    """Generalised equilibrium terms and their pose derivatives at fixed tensions.

    A: (k, 6, n) generalised structure matrix (its columns are the pose gradients of the cable lengths);
    b: (k, 6) generalised gravity; the equilibrium is A tau = b. With tensions given, G: (k, 6, 6) is
    d(A tau)/d zeta at those fixed tensions and db: (k, 6, 6) is d b / d zeta.
    """

    A: np.ndarray
    b: np.ndarray
    G: np.ndarray | None = None
    db: np.ndarray | None = None


def generalised_statics(
    robot: Robot,
    kin: Kinematics,
    jac: KinematicJacobians | None = None,
    tau: np.ndarray | None = None,
    base: GeneralisedStatics | None = None,
    load: tuple[np.ndarray, np.ndarray] | None = None,
) -> GeneralisedStatics:
    """The equilibrium in Euler-axis coordinates: forces, then moments projected on H's columns.

    With ``tau`` (k, n) it also returns the pose derivatives, contracted with the tensions so that no
    (k, 6, n, 6) array is formed: with c_i = tau_i / |rho_i| and e_i = c_i r_i (1 + cos psi_i),
      sum tau_i dt_i         = sum c_i dq_i - sum c_i t_i dl_i^T - sum e_i w_i dsigma_i^T,
      sum tau_i da'_i x t_i  = (S - tr(S) I) H        with S = sum tau_i a'_i t_i^T,
      sum tau_i a'_i x dt_i  = [sum c_i a'_i]x | (sum c_i |a'_i|^2 I - sum c_i a'_i a'_i^T) H
                               - sum c_i (a'_i x t_i) dl_i^T - sum e_i (a'_i x w_i) dsigma_i^T.
    ``base``: A and b already computed for these poses (they are reused). ``load``: the weight (k,) N and
    centre of mass (k, 3) m (platform frame) the cables hold at each pose, instead of the robot's own.
    """
    k, n = kin.lengths.shape
    H = kin.H
    Ht = H.transpose(0, 2, 1)
    a = kin.a_rel
    m_cab = cross(a, kin.t)  # (k, n, 3)
    if load is None:
        g = gravity_vector(robot)
        s = np.einsum("kab,b->ka", kin.R, robot.com)
    else:
        g = np.zeros((k, 3))
        g[:, 2] = -np.asarray(load[0], float)
        s = np.einsum("kab,kb->ka", kin.R, np.asarray(load[1], float))
    m_g = cross(s, g)  # (k, 3)
    if base is None:
        A = np.empty((k, 6, n))
        A[:, :3] = kin.t.transpose(0, 2, 1)
        A[:, 3:] = np.matmul(Ht, m_cab.transpose(0, 2, 1))
        b = np.empty((k, 6))
        b[:, :3] = g
        b[:, 3:] = np.einsum("kaj,ka->kj", H, m_g)
    else:
        A, b = base.A, base.b
    if tau is None:
        return GeneralisedStatics(A, b)
    if jac is None:
        jac = kinematic_jacobians(robot, kin)
    tau = np.broadcast_to(np.atleast_2d(tau), (k, n))
    c = tau / kin.rho_norm
    e = c * robot.r[None, :] * (1.0 + np.cos(kin.psi))
    # the terms that go through dl and dsigma, forces and moments at once: (k, 2n, 6)^T (k, 2n, 6)
    lhs = np.empty((k, 2 * n, 6))
    lhs[:, :n, :3] = c[..., None] * kin.t
    lhs[:, n:, :3] = e[..., None] * kin.w
    lhs[:, :n, 3:] = c[..., None] * m_cab
    lhs[:, n:, 3:] = e[..., None] * cross(a, kin.w)
    rhs = np.concatenate([jac.lengths, jac.swivel], axis=1)
    G = -np.matmul(lhs.transpose(0, 2, 1), rhs)  # rows: forces (3), moments about P (3), not yet on H
    ca = np.einsum("kn,kna->ka", c, a)
    csum = c.sum(1)
    for j in range(3):
        G[:, j, j] += csum
    G[:, :3, 3:] += cross(Ht, ca[:, None, :]).transpose(0, 2, 1)
    # moments about P: skew(sum c a') on the translations, a 3x3 matrix times H on the rotations
    G[:, 3, 1] -= ca[:, 2]
    G[:, 3, 2] += ca[:, 1]
    G[:, 4, 0] += ca[:, 2]
    G[:, 4, 2] -= ca[:, 0]
    G[:, 5, 0] -= ca[:, 1]
    G[:, 5, 1] += ca[:, 0]
    ta = tau[..., None] * a
    ca3 = c[..., None] * a
    M = np.matmul(ta.transpose(0, 2, 1), kin.t) - np.matmul(ca3.transpose(0, 2, 1), a)  # S - sum c a a^T
    diag = np.einsum("kna,kna->k", ca3, a) - np.einsum("kna,kna->k", ta, kin.t)  # sum c |a|^2 - tr(S)
    for j in range(3):
        M[:, j, j] += diag
    G[:, 3:, 3:] += np.matmul(M, H)
    m_tau = np.einsum("kn,kna->ka", tau, m_cab)
    dH = euler_axes_derivative(kin.poses[:, 3:], robot.orientation)  # (k, 3 comp, 3 axes j, 3 angles m)
    G[:, 3:] = np.matmul(Ht, G[:, 3:])
    G[:, 3:, 3:] += np.einsum("kajm,ka->kjm", dH, m_tau)
    # gravity: d(H^T (s x g)) with ds/d(angle_m) = h_m x s
    ds = cross(Ht, s[:, None, :])  # (k, 3 angles, 3)
    dm_g = cross(ds, g if g.ndim == 1 else g[:, None, :]).transpose(0, 2, 1)  # (k, 3, 3 angles)
    db = np.zeros((k, 6, 6))
    db[:, 3:, 3:] = np.matmul(Ht, dm_g) + np.einsum("kajm,ka->kjm", dH, m_g)
    return GeneralisedStatics(A, b, G, db)


@dataclass(frozen=True)
class TensionModel:
    """Modelled tensions (k, n), N, and their Jacobian d tau/d zeta (k, n, 6), N per pose unit."""

    tau: np.ndarray
    jacobian: np.ndarray | None


def tension_model(
    robot: Robot,
    poses: np.ndarray | None = None,
    kin: Kinematics | None = None,
    jac: KinematicJacobians | None = None,
    derivatives: bool = True,
) -> TensionModel:
    """Eq. 11-12: tau = A_c^-1 b_c with A_c the rows of ``robot.controlled`` of the generalised statics."""
    if len(robot.controlled) != robot.n:
        raise ValueError(
            f"robot '{robot.name}': the tension model needs one controlled coordinate per cable "
            f"({robot.n}), the description names {len(robot.controlled)}."
        )
    if kin is None:
        kin = inverse_kinematics(robot, poses)
    st = generalised_statics(robot, kin)
    c = list(robot.controlled)
    Ac = st.A[:, c, :]
    tau = np.linalg.solve(Ac, st.b[:, c, None])[..., 0]
    if not derivatives:
        return TensionModel(tau, None)
    st = generalised_statics(robot, kin, jac, tau, base=st)
    return TensionModel(tau, np.linalg.solve(Ac, st.db[:, c, :] - st.G[:, c, :]))


def point_load_tensions(
    robot: Robot, kin: Kinematics, jac: KinematicJacobians, points: np.ndarray, masses: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tension model (eq. 11-12) for point masses instead of the platform's weight: at k poses, the
    tensions (k, n, m) that hold 1 kg at each of m platform points (m, 3) m alone, and the tensions (k, n)
    that hold masses (k, m) kg at them together with their pose Jacobian (k, n, 6) at fixed masses (one
    statics evaluation for all points: the equilibrium is linear in the load)."""
    c = list(robot.controlled)
    st = generalised_statics(robot, kin)
    Ac = st.A[:, c, :]
    g1 = np.array([0.0, 0.0, -robot.gravity])
    sp = np.einsum("kab,mb->kma", kin.R, np.asarray(points, float))  # (k, m, 3)
    B = np.empty((kin.R.shape[0], 6, sp.shape[1]))
    B[:, :3] = g1[None, :, None]
    B[:, 3:] = np.einsum("kaj,kma->kjm", kin.H, cross(sp, g1))
    each = np.linalg.solve(Ac, B[:, c, :])  # (k, n, m)
    masses = np.asarray(masses, float)
    tau = np.einsum("knm,km->kn", each, masses)
    total = masses.sum(axis=1)
    com = np.einsum("km,ma->ka", masses, np.asarray(points, float)) / total[:, None]
    st = generalised_statics(robot, kin, jac, tau, base=st, load=(robot.gravity * total, com))
    return each, tau, np.linalg.solve(Ac, st.db[:, c, :] - st.G[:, c, :])


def equilibrium_residual(
    robot: Robot, poses: np.ndarray, tau: np.ndarray, derivatives: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Generalised residual A tau - b (k, 6) and its pose Jacobian (k, 6, 6); for the direct static problem."""
    kin = inverse_kinematics(robot, poses)
    tau = np.broadcast_to(np.atleast_2d(tau), (kin.lengths.shape[0], robot.n))
    st = generalised_statics(robot, kin, None, tau if derivatives else None)
    res = np.einsum("kan,kn->ka", st.A, tau) - st.b
    if not derivatives:
        return res, None
    return res, st.G - st.db
