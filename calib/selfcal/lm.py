"""Levenberg-Marquardt on block-arrow problems, with a Schur complement on the normal equations.

The normal equations of a problem with global parameters theta (p) and k independent pose blocks (6 each)
are [[U, W], [W^T, V]]: U is block diagonal (k, 6, 6), so eliminating the poses leaves a p x p system
S = V - sum W_i^T U_i^-1 W_i. One iteration costs O(k) batched 6x6 solves plus one p x p solve.

Stopping. Besides the usual tolerances on the cost, the step and the gradient, the solve stops as soon as
the Gauss-Newton step d from the current point is shorter than ``stol`` a-posteriori standard deviations:
sqrt(d^T J^T J d) <= stol sqrt(chi2 / dof). In the metric of the covariance (J^T J)^-1 this bounds every
unknown's remaining change, and every linear combination's, by stol times its sigma scaled by the fit's own
variance factor chi2/dof: iterating further changes nothing the data can tell, and it saves the last
evaluations of a solve that would end in rounding-level steps (sc_8_final: 7 evaluations -> 5). Exact data
(chi2 -> 0) are still solved to rounding level; without redundancy (dof <= 0) the rule does not apply.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.selfcal.problem import Evaluation, Problem


@dataclass
class LMResult:
    """Solution, final cost (0.5 sum r^2), iterations, status, and the covariance of the estimate."""

    theta: np.ndarray
    poses: np.ndarray
    cost: float
    iterations: int
    converged: bool
    message: str
    cov_theta: np.ndarray
    cov_poses: np.ndarray
    evaluation: Evaluation | None = None  # residuals at the solution (reused for the per-channel summary)


def _normal_equations(ev: Evaluation, k: int, p: int):
    U = np.zeros((k, 6, 6))
    W = np.zeros((k, 6, p))
    bz = np.zeros((k, 6))
    V = np.zeros((p, p))
    bt = np.zeros(p)
    for g, r, J, G in ev.groups:
        Jt = J.transpose(0, 2, 1)
        U[g.idx] = Jt @ J
        W[g.idx] = Jt @ G
        bz[g.idx] = (Jt @ r[..., None])[..., 0]
        Gf = G.reshape(-1, p)
        V += Gf.T @ Gf
        bt += Gf.T @ r.reshape(-1)
    V += ev.g0.T @ ev.g0
    bt += ev.g0.T @ ev.r0
    return U, W, bz, V, bt


def _schur_solve(U, W, bz, V, bt):
    """Solve [[U, W], [W^T, V]] [dz; dt] = -[bz; bt]; also returns U^-1 W and S for the covariance."""
    k, _, p = W.shape
    sol = np.linalg.solve(U, np.concatenate([W, bz[..., None]], axis=2))
    Y, y = sol[..., :p], sol[..., p]
    Wt = W.transpose(0, 2, 1)
    S = V - np.einsum("kpi,kiq->pq", Wt, Y)
    rhs = -bt + np.einsum("kpi,ki->p", Wt, y)
    dt = np.linalg.solve(S, rhs)
    dz = -y - (Y @ dt[:, None])[..., 0] if k else np.zeros((0, 6))
    return dz, dt, Y, S


def _gauss_newton_length(U, W, bz, V, bt) -> float:
    """sqrt(d^T J^T J d) of the undamped step d = -(J^T J)^-1 g, i.e. sqrt(-d . g); inf when J^T J is singular."""
    try:
        dz, dt, _, _ = _schur_solve(U, W, bz, V, bt)
    except np.linalg.LinAlgError:
        return math.inf
    m2 = -(float(np.sum(dz * bz)) + float(np.sum(dt * bt)))
    return math.sqrt(m2) if np.isfinite(m2) and m2 >= 0 else math.inf


def levenberg_marquardt(
    problem: Problem,
    theta0: np.ndarray,
    poses0: np.ndarray,
    max_iter: int = 200,
    ftol: float = 1e-12,
    xtol: float = 1e-12,
    gtol: float = 1e-10,
    stol: float = 1e-3,
) -> LMResult:
    """Minimise 0.5 |r|^2 over theta and the poses with Marquardt scaling and Nielsen's damping update; stop
    when the Gauss-Newton step is below ``stol`` a-posteriori standard deviations (module docstring), or on
    the cost's relative reduction (ftol), the step's relative size (xtol) or the gradient (gtol)."""
    theta = np.array(theta0, dtype=float)
    Z = np.array(poses0, dtype=float).reshape(-1, 6)
    k, p = Z.shape[0], theta.shape[0]
    dof = problem.n_residuals - (p + 6 * k)
    ev = problem.evaluate(theta, Z)
    cost = ev.cost
    U, W, bz, V, bt = _normal_equations(ev, k, p)
    dz_scale = np.maximum(np.diagonal(U, axis1=1, axis2=2), 1e-12)
    dt_scale = np.maximum(np.diagonal(V), 1e-12)
    lam, nu = 1e-4, 2.0
    converged, message, it, fresh = False, "maximum number of iterations reached", 0, True
    for it in range(1, max_iter + 1):  # noqa: B007 (reported)
        grad_max = max(np.abs(bz).max(initial=0.0), np.abs(bt).max(initial=0.0))
        if grad_max <= gtol:
            converged, message = True, "gradient below tolerance"
            break
        if fresh and dof > 0 and _gauss_newton_length(U, W, bz, V, bt) <= stol * math.sqrt(2.0 * cost / dof):
            converged, message = True, f"the Gauss-Newton step is below {stol:g} a-posteriori standard deviations"
            it -= 1  # this iteration took no step
            break
        fresh = False  # the check is made once per point
        Ud = U.copy()
        Ud[:, range(6), range(6)] += lam * dz_scale
        Vd = V + np.diag(lam * dt_scale)
        try:
            dz, dt, _, _ = _schur_solve(Ud, W, bz, Vd, bt)
        except np.linalg.LinAlgError:
            lam *= nu
            nu *= 2.0
            continue
        Zn, thn = Z + dz, theta + dt
        evn = problem.evaluate(thn, Zn)
        cost_n = evn.cost
        # predicted reduction of the quadratic model: 0.5 d^T (lam D d - g)
        pred = 0.5 * (
            np.sum(dz * (lam * dz_scale * dz - bz)) + np.sum(dt * (lam * dt_scale * dt - bt))
        )
        rho = (cost - cost_n) / pred if pred > 0 else -1.0
        step_norm = np.sqrt(np.sum(dz_scale * dz**2) + np.sum(dt_scale * dt**2))
        x_norm = np.sqrt(np.sum(dz_scale * Z**2) + np.sum(dt_scale * theta**2))
        if rho > 0 and np.isfinite(cost_n):
            reduction = cost - cost_n
            Z, theta, ev, cost, fresh = Zn, thn, evn, cost_n, True
            U, W, bz, V, bt = _normal_equations(ev, k, p)
            dz_scale = np.maximum(dz_scale, np.diagonal(U, axis1=1, axis2=2))
            dt_scale = np.maximum(dt_scale, np.diagonal(V))
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if reduction <= ftol * max(cost, 1e-300) or step_norm <= xtol * (x_norm + xtol):
                converged, message = True, "relative reduction of the cost below tolerance"
                break
        else:
            lam *= nu
            nu *= 2.0
            if step_norm <= xtol * (x_norm + xtol):
                converged, message = True, "step below tolerance"
                break
            if lam > 1e16:
                message = "damping grew without bound: no descent direction"
                break
    cov_theta, cov_poses = covariance(U, W, V)
    return LMResult(theta, Z, cost, it, converged, message, cov_theta, cov_poses, ev)


def covariance(U: np.ndarray, W: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(J^T J)^-1 of the weighted problem: the theta block (p, p) and the pose diagonal blocks (k, 6, 6)."""
    k, _, p = W.shape
    try:
        Uinv = np.linalg.inv(U)
        Y = Uinv @ W
        S = V - np.einsum("kip,kiq->pq", W, Y)
        Sinv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return np.full((p, p), np.nan), np.full((k, 6, 6), np.nan)
    cov_poses = Uinv + Y @ Sinv[None] @ Y.transpose(0, 2, 1)
    return 0.5 * (Sinv + Sinv.T), cov_poses


def solve_poses(
    problem: Problem,
    theta: np.ndarray,
    poses0: np.ndarray,
    rows: np.ndarray | None = None,
    max_iter: int = 60,
    tol: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray]:
    """Each pose block alone with theta held fixed (a per-pose LM, batched over the rows still iterating):
    poses (k, 6) and the final cost of each row (k,; 0 for rows not solved). Only ``rows`` (default all)
    are solved. Used for initial guesses (pose estimation from the readings)."""
    Z = np.array(poses0, dtype=float).reshape(-1, 6)
    k = Z.shape[0]
    active = np.zeros(k, bool)
    active[np.arange(k) if rows is None else rows] = True
    cost, U, b = np.zeros(k), np.zeros((k, 6, 6)), np.zeros((k, 6))
    act = np.flatnonzero(active)
    cost[act], U[act], b[act] = problem.pose_normal_equations(theta, Z[act], act)
    lam = np.full(k, 1e-3)
    for _ in range(max_iter):
        act = np.flatnonzero(active)
        if not act.size:
            break
        D = np.maximum(np.diagonal(U[act], axis1=1, axis2=2), 1e-9)
        Ud = U[act] + (lam[act, None] * D)[:, :, None] * np.eye(6)[None]
        step = np.linalg.solve(Ud, -b[act][..., None])[..., 0]
        # limit to 0.3 m and 0.5 rad per iteration
        lim = np.maximum(np.abs(step[:, :3]).max(1) / 0.3, np.abs(step[:, 3:]).max(1) / 0.5)
        step /= np.maximum(lim, 1.0)[:, None]
        Zn = Z[act] + step
        cost_n, Un, bn = problem.pose_normal_equations(theta, Zn, act)
        ok = cost_n < cost[act]
        small = (cost[act] - cost_n) <= tol * np.maximum(cost[act], 1e-300)
        acc = act[ok]
        Z[acc], U[acc], b[acc], cost[acc] = Zn[ok], Un[ok], bn[ok], cost_n[ok]
        lam[act] = np.where(ok, lam[act] * 0.3, lam[act] * 10.0)
        active[act[ok & small]] = False
        active &= lam < 1e12
    return Z, cost
