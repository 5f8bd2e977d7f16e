"""Static equilibria: the direct static problem, the inverse geometrico-static problem and stability.

* :func:`direct_statics` — given cable tensions, the equilibrium pose (Zoffoli Sec. 3.3, initial guess):
  damped Newton on the six generalised equilibrium equations A(zeta) tau = b(zeta) with their analytic
  Jacobian, vectorised over k problems.
* :func:`inverse_geometrico_static` — given a position, the orientation and the tensions in equilibrium
  (Appendix A, eq. A1-A2) under the tension-distribution rule documented there.
* :func:`stability` — static stability from the free-motion stiffness (eq. A4-A5), computed as the
  Hessian of the Lagrangian U + tau.(l - l0) projected on the motions that keep every cable length,
  which is what eq. A4-A5 evaluate in closed form.

Units: m, rad, N.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.kinematics import _as_poses, inverse_kinematics, kinematic_jacobians
from calib.robot import Robot
from calib.statics import equilibrium_residual, generalised_statics


@dataclass(frozen=True)
class DirectStaticsResult:
    poses: np.ndarray  # (k, 6)
    converged: np.ndarray  # (k,) bool
    residual: np.ndarray  # (k,) max |A tau - b| at the end, N and N m
    iterations: int


def default_guess(robot: Robot, k: int = 1) -> np.ndarray:
    """A pose to start iterations from: the robot's home pose, else the centre of the workspace bounds."""
    if robot.home_pose is not None:
        g = np.array(robot.home_pose, dtype=float)
    elif np.all(np.isfinite(robot.workspace_lower)):
        g = np.r_[(robot.workspace_lower + robot.workspace_upper) / 2, 0.0, 0.0, 0.0]
    else:
        g = np.r_[robot.d.mean(axis=0) - [0, 0, 1.0], 0.0, 0.0, 0.0]
    return np.tile(g, (k, 1))


def direct_statics(
    robot: Robot,
    tau: np.ndarray,
    guess: np.ndarray | None = None,
    tol: float = 1e-9,
    max_iter: int = 60,
) -> DirectStaticsResult:
    """Equilibrium poses (k, 6) under tensions tau (k, n) (or (n,)), from ``guess`` (k, 6) or the default.

    Damped Newton with a backtracking line search on the residual norm; a problem counts as converged when
    the largest residual is below ``tol`` times the platform weight.
    """
    t = np.atleast_2d(np.asarray(tau, dtype=float))
    k = t.shape[0]
    z = default_guess(robot, k) if guess is None else _as_poses(guess).copy()
    if z.shape[0] != k:
        z = np.broadcast_to(z, (k, 6)).copy()
    scale = robot.weight
    res, jac = equilibrium_residual(robot, z, t)
    norm = np.abs(res).max(axis=1)
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (reported)
        active = norm > tol * scale
        if not active.any():
            break
        try:
            step = np.linalg.solve(jac[active], -res[active][..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = np.linalg.lstsq(jac[active][0], -res[active][0], rcond=None)[0][None]
        # limit the step: 0.2 m and 0.3 rad at most
        lim = np.maximum(np.abs(step[:, :3]).max(1) / 0.2, np.abs(step[:, 3:]).max(1) / 0.3)
        step /= np.maximum(lim, 1.0)[:, None]
        alpha = np.ones(step.shape[0])
        za = z[active]
        na = norm[active]
        accepted = np.zeros(step.shape[0], bool)
        ra, ja = res[active], jac[active]
        for _ in range(12):
            # the candidates are evaluated with their Jacobian: the full step is nearly always accepted,
            # and its Jacobian is the next iteration's
            cand = za + alpha[:, None] * step
            r_c, j_c = equilibrium_residual(robot, cand, t[active])
            n_c = np.abs(r_c).max(1)
            ok = (n_c < na) & ~accepted
            za, ra = np.where(ok[:, None], cand, za), np.where(ok[:, None], r_c, ra)
            ja = np.where(ok[:, None, None], j_c, ja)
            accepted |= ok
            if accepted.all():
                break
            alpha = np.where(accepted, alpha, alpha * 0.5)
        if not accepted.any():
            break
        z[active], res[active], jac[active] = za, ra, ja
        norm = np.abs(res).max(axis=1)
    return DirectStaticsResult(z, norm <= tol * scale, norm, it)


@dataclass(frozen=True)
class StaticPose:
    """Solutions of the inverse geometrico-static problem at k positions."""

    poses: np.ndarray  # (k, 6)
    tensions: np.ndarray  # (k, n), N
    converged: np.ndarray  # (k,) bool: the equilibrium equations hold
    within_bounds: np.ndarray  # (k,) bool: tau_min <= tau <= tau_max (eq. A3)
    stable: np.ndarray  # (k,) bool: free-motion stiffness positive definite (eq. A4)
    min_stiffness: np.ndarray  # (k,) smallest eigenvalue of the free-motion stiffness

    @property
    def feasible(self) -> np.ndarray:
        return self.converged & self.within_bounds & self.stable


def distribute_tensions(
    force_matrix: np.ndarray, force: np.ndarray, tau_min: float, tau_max: float
) -> tuple[np.ndarray, np.ndarray]:
    """Tension distribution for the force equations F tau = force (F: (k, 3, n), force (3,)), eq. A2.

    tau = F^+ force + N lambda. The rule: for n - 3 = 1 the barycentre (midpoint) of the segment of lambda
    where tau_min <= tau <= tau_max (Lamaury & Gouttefarde's barycentric method in one dimension); where
    that segment is empty, the lambda that minimises the largest bound violation; for n - 3 > 1 the
    tensions closest (2-norm) to the middle of the bounds. Returns (tau (k, n), feasible (k,)).
    """
    k, _, n = force_matrix.shape
    pinv = np.linalg.pinv(force_matrix)  # (k, n, 3)
    tp = np.einsum("kna,a->kn", pinv, force)
    _, _, vt = np.linalg.svd(force_matrix)
    null = vt[:, 3:, :]  # (k, n-3, n)
    mid = 0.5 * (tau_min + tau_max)
    if n - 3 == 1:
        nv = null[:, 0, :]
        nv = nv * np.where(nv.sum(axis=1, keepdims=True) < 0, -1.0, 1.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            l1 = (tau_min - tp) / nv
            l2 = (tau_max - tp) / nv
        lo = np.where(nv > 0, l1, l2)
        hi = np.where(nv > 0, l2, l1)
        small = np.abs(nv) < 1e-12
        lo = np.where(small, -np.inf, lo)
        hi = np.where(small, np.inf, hi)
        lam_lo, lam_hi = lo.max(axis=1), hi.min(axis=1)
        feasible = (lam_lo <= lam_hi) & np.all(~small | ((tp >= tau_min) & (tp <= tau_max)), axis=1)
        # infeasible: minimise the largest violation -> the crossing point of the two active bounds
        lam = np.where(feasible, 0.5 * (lam_lo + lam_hi), 0.5 * (lam_lo + lam_hi))
        lam = np.where(np.isfinite(lam), lam, 0.0)
        tau = tp + lam[:, None] * nv
        return tau, feasible
    lam = np.einsum("kmn,kn->km", null, mid - tp)
    tau = tp + np.einsum("km,kmn->kn", lam, null)
    feasible = np.all((tau >= tau_min) & (tau <= tau_max), axis=1)
    return tau, feasible


def _igsp_moment_residual(robot: Robot, p: np.ndarray, ang: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    poses = np.c_[p, ang]
    kin = inverse_kinematics(robot, poses)
    st = generalised_statics(robot, kin)
    g = np.array([0.0, 0.0, -robot.weight])
    bad = ~(np.isfinite(st.A).all(axis=(1, 2)) & np.isfinite(st.b).all(axis=1))
    A = np.where(bad[:, None, None], np.eye(6, robot.n), st.A)  # placeholder rows, reported as failed below
    tau, feas = distribute_tensions(A[:, :3, :], g, robot.tau_min, robot.tau_max)
    res = np.einsum("kan,kn->ka", A[:, 3:, :], tau) - np.where(bad[:, None], 0.0, st.b[:, 3:])
    res[bad] = np.inf
    return res, tau, feas & ~bad


def _solve3(jac: np.ndarray, res: np.ndarray) -> np.ndarray:
    """Newton steps -J^-1 r for a batch of 3x3 systems; singular ones get a least-squares step."""
    ok = np.abs(np.linalg.det(jac)) > 1e-300
    step = np.zeros_like(res)
    if ok.any():
        step[ok] = np.linalg.solve(jac[ok], -res[ok][..., None])[..., 0]
    for j in np.flatnonzero(~ok):
        step[j] = np.linalg.lstsq(jac[j], -res[j], rcond=None)[0]
    return step


def inverse_geometrico_static(
    robot: Robot, positions: np.ndarray, guess_angles: np.ndarray | None = None, tol: float = 1e-9, max_iter: int = 50
) -> StaticPose:
    """Orientation and tensions in equilibrium at given positions (k, 3) (eq. A1-A3), plus stability (A4).

    Solves the three moment equations of A1 for (roll, pitch, yaw) by Newton with a finite-difference
    Jacobian (three unknowns per point), the tensions following from the distribution rule of
    :func:`distribute_tensions`. Vectorised over the k positions.
    """
    p = np.atleast_2d(np.asarray(positions, dtype=float))
    k = p.shape[0]
    ang = np.zeros((k, 3)) if guess_angles is None else np.atleast_2d(np.asarray(guess_angles, float)).copy()
    h = 1e-7
    res, tau, feas = _igsp_moment_residual(robot, p, ang)
    norm = np.abs(res).max(1)
    for _ in range(max_iter):
        active = (norm > tol * robot.weight) & np.isfinite(norm)
        if not active.any():
            break
        pa, aa, ra = p[active], ang[active], res[active]
        jac = np.empty((pa.shape[0], 3, 3))
        for j in range(3):
            da = aa.copy()
            da[:, j] += h
            rj, _, _ = _igsp_moment_residual(robot, pa, da)
            jac[:, :, j] = (rj - ra) / h
        jac = np.where(np.isfinite(jac), jac, 0.0)
        step = _solve3(jac, ra)
        step /= np.maximum(np.abs(step).max(1) / 0.3, 1.0)[:, None]
        alpha = np.ones(len(pa))
        best_a, best_r = aa.copy(), ra.copy()
        best_n = norm[active].copy()
        done = np.zeros(len(pa), bool)
        for _ in range(10):
            cand = aa + alpha[:, None] * step
            rc, _, _ = _igsp_moment_residual(robot, pa, cand)
            nc = np.abs(rc).max(1)
            ok = (nc < best_n) & ~done
            best_a[ok], best_r[ok], best_n[ok] = cand[ok], rc[ok], nc[ok]
            done |= ok
            if done.all():
                break
            alpha = np.where(done, alpha, alpha * 0.5)
        if not done.any():
            break
        ang[active] = best_a
        res, tau, feas = _igsp_moment_residual(robot, p, ang)
        norm = np.abs(res).max(1)
    poses = np.c_[p, ang]
    converged = norm <= 1e-6 * robot.weight
    within = feas & np.all((tau >= robot.tau_min - 1e-9) & (tau <= robot.tau_max + 1e-9), axis=1)
    stab = np.full(k, -np.inf)
    fin = np.isfinite(poses).all(1) & np.isfinite(tau).all(1)
    if fin.any():
        stab[fin] = stability(robot, poses[fin], tau[fin])
    stab = np.where(np.isfinite(stab) | (stab == np.inf), stab, -np.inf)
    return StaticPose(poses, tau, converged, within, stab > 0, stab)


def free_motion_stiffness(robot: Robot, poses: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """The free-motion stiffness (k, 6-n, 6-n) of eq. A4, N m per unit of the free coordinates.

    The Hessian of the Lagrangian U + tau.(l(zeta) - l0), which is the pose Jacobian of the generalised
    equilibrium residual A tau - b, projected on an orthonormal basis of the motions that keep every cable
    length (the null space of dl/dzeta). For n >= 6 there are no free motions: shape (k, 0, 0).
    """
    z = _as_poses(poses)
    kin = inverse_kinematics(robot, z)
    jac = kinematic_jacobians(robot, kin)
    _, jres = equilibrium_residual(robot, z, tau)
    hess = 0.5 * (jres + np.swapaxes(jres, 1, 2))
    free = 6 - robot.n
    if free <= 0:
        return np.zeros((z.shape[0], 0, 0))
    bad = ~(np.isfinite(jac.lengths).all(axis=(1, 2)) & np.isfinite(hess).all(axis=(1, 2)))
    if bad.any():  # degenerate geometry (a cable through its pulley axis): report as not positive
        jl = np.where(bad[:, None, None], np.eye(robot.n, 6), jac.lengths)
        hess = np.where(bad[:, None, None], -np.eye(6), hess)
        jac = type(jac)(jl, jac.swivel, jac.psi)
    _, _, vt = np.linalg.svd(jac.lengths)
    basis = np.swapaxes(vt[:, robot.n :, :], 1, 2)  # (k, 6, 6-n)
    return np.einsum("kai,kab,kbj->kij", basis, hess, basis)


def stability(robot: Robot, poses: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Smallest eigenvalue (k,) of the free-motion stiffness: positive means statically stable.

    For robots with n >= 6 cables the platform has no free motion and every taut equilibrium is stable
    (returns +inf).
    """
    kf = free_motion_stiffness(robot, poses, tau)
    if kf.shape[1] == 0:
        return np.full(kf.shape[0], np.inf)
    return np.linalg.eigvalsh(kf)[:, 0]
