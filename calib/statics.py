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
    cable_direction_jacobian,
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
    """Generalised equilibrium terms and their pose derivatives.

    A: (k, 6, n) generalised structure matrix; b: (k, 6) generalised gravity; dA: (k, 6, n, 6);
    db: (k, 6, 6). The equilibrium is A tau = b.
    """

    A: np.ndarray
    b: np.ndarray
    dA: np.ndarray
    db: np.ndarray


def generalised_statics(
    robot: Robot, kin: Kinematics, jac: KinematicJacobians | None = None, derivatives: bool = True
) -> GeneralisedStatics:
    """The equilibrium in Euler-axis coordinates: forces, then moments projected on H's columns."""
    k, n = kin.lengths.shape
    H = kin.H
    m_cab = cross(kin.a_rel, kin.t)  # (k, n, 3)
    g = gravity_vector(robot)
    s = np.einsum("kab,b->ka", kin.R, robot.com)
    m_g = cross(s, g)  # (k, 3)
    A = np.empty((k, 6, n))
    A[:, :3] = kin.t.transpose(0, 2, 1)
    A[:, 3:] = np.einsum("kaj,kna->kjn", H, m_cab)
    b = np.empty((k, 6))
    b[:, :3] = g
    b[:, 3:] = np.einsum("kaj,ka->kj", H, m_g)
    if not derivatives:
        return GeneralisedStatics(A, b, np.empty(0), np.empty(0))
    if jac is None:
        jac = kinematic_jacobians(robot, kin)
    dt = cable_direction_jacobian(robot, kin, jac)  # (k, n, 3, 6)
    hcols = np.swapaxes(H, 1, 2)  # (k, 3 axes, 3)
    # d(a_rel)/d(angle_m) = h_m x a_rel ; d(s)/d(angle_m) = h_m x s
    da = np.zeros((k, n, 3, 6))
    da[..., 3:] = np.swapaxes(cross(hcols[:, None, :, :], kin.a_rel[:, :, None, :]), -1, -2)
    dm_cab = np.swapaxes(
        cross(np.swapaxes(da, 2, 3), kin.t[:, :, None, :]) + cross(kin.a_rel[:, :, None, :], np.swapaxes(dt, 2, 3)),
        2,
        3,
    )  # (k, n, 3, 6)
    dH = euler_axes_derivative(kin.poses[:, 3:], robot.orientation)  # (k, 3 comp, 3 axes j, 3 angles m)
    dA = np.zeros((k, 6, n, 6))
    dA[:, :3] = dt.transpose(0, 2, 1, 3)
    dA[:, 3:] = np.einsum("kaj,knam->kjnm", H, dm_cab)
    dA[:, 3:, :, 3:] += np.einsum("kajm,kna->kjnm", dH, m_cab)
    ds = np.swapaxes(cross(hcols, s[:, None, :]), 1, 2)  # (k, 3, 3 angles)
    dm_g = np.swapaxes(cross(np.swapaxes(ds, 1, 2), g), 1, 2)  # (k, 3, 3)
    db = np.zeros((k, 6, 6))
    db[:, 3:, 3:] = np.einsum("kaj,kam->kjm", H, dm_g) + np.einsum("kajm,ka->kjm", dH, m_g)
    return GeneralisedStatics(A, b, dA, db)


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
    st = generalised_statics(robot, kin, jac, derivatives)
    c = list(robot.controlled)
    Ac = st.A[:, c, :]
    bc = st.b[:, c]
    tau = np.linalg.solve(Ac, bc[..., None])[..., 0]
    if not derivatives:
        return TensionModel(tau, None)
    rhs = st.db[:, c, :] - np.einsum("kanj,kn->kaj", st.dA[:, c], tau)
    return TensionModel(tau, np.linalg.solve(Ac, rhs))


def equilibrium_residual(
    robot: Robot, poses: np.ndarray, tau: np.ndarray, derivatives: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Generalised residual A tau - b (k, 6) and its pose Jacobian (k, 6, 6); for the direct static problem."""
    kin = inverse_kinematics(robot, poses)
    st = generalised_statics(robot, kin, None, derivatives)
    tau = np.broadcast_to(np.atleast_2d(tau), (kin.lengths.shape[0], robot.n))
    res = np.einsum("kan,kn->ka", st.A, tau) - st.b
    if not derivatives:
        return res, None
    return res, np.einsum("kanj,kn->kaj", st.dA, tau) - st.db
