"""Fitting a model with effects to the rows of a run: the fit (zeta_0, row poses, effect parameters by the
block-arrow LM), its weighted residuals and dense Jacobian, the parameter directions the data can observe,
the refit with one more effect, its leave-one-pose-out prediction, and the score (Lagrange multiplier) test
of an effect at a solution without refitting. The diagnosis (:mod:`calib.diagnose`), the multi-run fit
(:mod:`calib.multirun`) and ``cdpr solve --effects`` (:mod:`calib.runrows`) are built on these."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calib.effects import Effect, EffectModel, Projected
from calib.prediction import Prediction, leave_one_pose_out
from calib.robot import Robot
from calib.selfcal.lm import levenberg_marquardt
from calib.selfcal.problem import Measurements, Problem


@dataclass
class Fit:
    """A fitted model: effects, theta (p,), poses (k, 6), theta covariance, chi2, residual count."""

    effects: list[Effect]
    model: EffectModel
    problem: Problem
    theta: np.ndarray
    poses: np.ndarray
    cov_theta: np.ndarray
    chi2: float
    n_residuals: int
    converged: bool
    iterations: int = 0

    @property
    def n_free(self) -> int:
        return self.model.n_params + 6 * self.poses.shape[0]

    @property
    def dof(self) -> int:
        return self.n_residuals - self.n_free

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.effects]

    def params(self) -> dict[str, dict[str, float]]:
        return self.model.report(self.theta)

    def param_sigmas(self) -> dict[str, dict[str, float]]:
        """1-sigma uncertainty of each effect parameter (for restricted effects, of the full parameters)."""
        out = {}
        for e, sl, specs in zip(self.model.effects, self.model.slices, self.model.specs, strict=True):
            cov = self.cov_theta[sl, sl]
            if isinstance(e, Projected):
                cov, specs = e.covariance(cov), e.inner.params(self.model.robot)
            sd = np.sqrt(np.clip(np.diag(cov), 0, None))
            out[e.name] = {s.name: float(v) for s, v in zip(specs, sd, strict=True)}
        return out


@dataclass
class Residuals:
    """Weighted residuals (m,) and dense Jacobian (m, 6k + p) at a solution, observed entries only, with
    labels: channel name, cable/component index, row index (-1: the reference row)."""

    r: np.ndarray
    A: np.ndarray
    si: np.ndarray
    channel: np.ndarray
    index: np.ndarray
    row: np.ndarray


def residuals(problem: Problem, theta: np.ndarray, poses: np.ndarray, jacobian: bool = True,
              physical: tuple | None = None) -> Residuals:
    """Dense weighted residuals and Jacobian (columns: the k pose blocks, then theta). Order: per group,
    channel and component, the observed rows; then the reference row's observed entries; then the priors
    (``Problem.observed``). ``physical``: as :meth:`Problem.evaluate`'s."""
    ev = problem.evaluate(theta, poses, derivatives=jacobian, physical=physical)
    obs = problem.observed
    k, p = poses.shape[0], theta.shape[0]
    ok, m0, q = obs.ref, obs.n_ref, problem.prior_idx.size
    rs, sis, Js, Gs = [], [], [], []
    for (_, r, J, G), (flat, w) in zip(ev.groups, obs.groups, strict=True):
        rs.append(r.ravel()[flat])
        sis.append(rs[-1] / w)
        if jacobian:
            Js.append(J.reshape(-1, 6)[flat])
            Gs.append(G.reshape(-1, p)[flat])
    rs += [ev.r0[ok], ev.r0[m0:m0 + q]]
    sis += [ev.r0[ok] / problem.ref_weight[ok], ev.r0[m0:m0 + q] * problem.prior_sd]
    if jacobian:
        start = obs.pose_cols.shape[0]
        A = np.zeros((start + ok.size + q, 6 * k + p))
        if start:
            A[np.arange(start)[:, None], obs.pose_cols] = np.concatenate(Js)
            A[:start, 6 * k:] = np.concatenate(Gs)
        A[start:start + ok.size, 6 * k:] = ev.g0[ok]
        A[start + ok.size:, 6 * k:] = ev.g0[m0:m0 + q]
    else:
        A = np.zeros((0, 0))
    return Residuals(np.concatenate(rs), A, np.concatenate(sis), obs.channel, obs.index, obs.row)


OBSERVABLE = 1e-2  # a typical-size change must move the weighted residuals by this much (noise units)


def observable_basis(MC: np.ndarray, scales: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observable directions of an effect's projected columns MC (m, q) with typical parameter sizes
    scales (q,): basis B (q, r) in parameter units, left singular vectors (m, r), singular values (r,)."""
    if MC.shape[1] == 0:
        return np.zeros((0, 0)), np.zeros((MC.shape[0], 0)), np.zeros(0)
    U, s, Vt = np.linalg.svd(MC * scales, full_matrices=False)
    keep = s > max(OBSERVABLE, 1e-6 * s.max(initial=0.0))
    return scales[:, None] * Vt[keep].T, U[:, keep], s[keep]


def restrict_to_observable(robot: Robot, meas: Measurements, sigma, effects: list[Effect], theta0: np.ndarray,
              poses0: np.ndarray) -> list[Effect]:
    """The effects, each restricted to the parameter directions this data can observe (Projected) where
    some are not (after projecting out the pose and zeta_0 directions)."""
    model = EffectModel(robot, effects)
    problem = Problem(model, meas, sigma)
    res = residuals(problem, theta0, poses0)
    k = poses0.shape[0]
    Q = orthonormal_columns(res.A[:, : 6 * k + 6])
    out = []
    for e, sl, specs in zip(effects, model.slices, model.specs, strict=True):
        C = res.A[:, 6 * k + sl.start : 6 * k + sl.stop]
        B, _, _ = observable_basis(C - Q @ (Q.T @ C), np.array([sp.scale for sp in specs]))
        if B.shape[1] == len(specs) or isinstance(e, Projected):
            out.append(e)
        else:
            out.append(Projected(e, B))
    return out


def orthonormal_columns(A: np.ndarray) -> np.ndarray:
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    U, s, _ = np.linalg.svd(A / scale, full_matrices=False)
    return U[:, s > 1e-10 * s.max(initial=0.0)]


def fit(
    robot: Robot, meas: Measurements, sigma: dict[str, np.ndarray], effects: Sequence[Effect],
    theta0: np.ndarray, poses0: np.ndarray, max_iter: int = 200, restrict: bool = True,
) -> Fit:
    """Fit zeta_0, the row poses and the effects' parameters from a guess (theta0 may be zeta_0 or the
    theta of a model with fewer effects: missing effect values start absent). With ``restrict``, effects
    with unobservable parameter directions are fitted in their observable subspace (the rest absent)."""
    effects = list(effects)
    theta0 = np.asarray(theta0, float)
    poses0 = np.asarray(poses0, float).reshape(-1, 6)
    model = EffectModel(robot, effects)
    if theta0.shape[0] < model.n_params:
        theta0 = np.r_[theta0, model.absent_values()[theta0.shape[0] - 6 :]]
    if restrict and effects:
        new = restrict_to_observable(robot, meas, sigma, effects, theta0, poses0)
        if any(a is not b for a, b in zip(new, effects, strict=True)):
            # restart the restricted effects at their absent values, keep the others' values
            vals = []
            for a, b, sl in zip(new, effects, model.slices, strict=True):
                vals.append(np.zeros(a.basis.shape[1]) if a is not b else theta0[sl])
            effects = new
            model = EffectModel(robot, effects)
            theta0 = np.r_[theta0[:6], np.concatenate(vals) if vals else np.zeros(0)]
    problem = Problem(model, meas, sigma)
    res = levenberg_marquardt(problem, theta0, poses0, max_iter=max_iter)
    return Fit(effects, model, problem, res.theta, res.poses, res.cov_theta, 2.0 * res.cost,
               problem.n_residuals, bool(res.converged), int(res.iterations))


REFIT_ITER = 30  # a candidate's refit that has not converged after this many LM iterations is not evidence


def refit(fit0: Fit, effect: Effect, max_iter: int = 200) -> Fit:
    """``fit0`` with one more effect, started from fit0's solution (the effect absent)."""
    return fit(fit0.model.robot, fit0.problem.meas, fit0.problem.sigma, fit0.effects + [effect], fit0.theta,
               fit0.poses, max_iter=max_iter)


def predict_unseen(f: Fit) -> Prediction:
    """Leave-one-pose-out chi2 of a fit (:mod:`calib.prediction`)."""
    res = residuals(f.problem, f.theta, f.poses)
    return leave_one_pose_out(res.r, res.A, res.row, f.poses.shape[0])


@dataclass
class ScoreBasis:
    """Orthonormal basis of the nuisance directions (poses and theta) at a solution, and the residual."""

    Q: np.ndarray
    r: np.ndarray


def score_basis(res: Residuals) -> ScoreBasis:
    return ScoreBasis(orthonormal_columns(res.A), res.r)


@dataclass
class Score:
    """A score test: LM statistic, its dof (observable directions), the unit vector of the explained part
    of the residual (m,), an orthonormal basis of the effect's projected span (m, dof) and the expected
    parameter change (the effect's values after one Gauss-Newton step from absent, q)."""

    lm: float
    dof: int
    direction: np.ndarray
    span: np.ndarray
    values: np.ndarray


def score_test(fit0: Fit, effect: Effect, basis: ScoreBasis) -> Score:
    """Score test of adding ``effect`` to ``fit0`` (no refit)."""
    model = EffectModel(fit0.model.robot, fit0.effects + [effect])
    problem = Problem(model, fit0.problem.meas, fit0.problem.sigma)
    absent = model.absent_values()[fit0.theta.shape[0] - 6 :]
    theta = np.r_[fit0.theta, absent]
    res = residuals(problem, theta, fit0.poses)
    C = res.A[:, 6 * fit0.poses.shape[0] + fit0.theta.shape[0] :]
    Q = basis.Q
    B, Uk, s = observable_basis(C - Q @ (Q.T @ C), np.array([sp.scale for sp in model.specs[-1]]))
    proj = Uk.T @ basis.r
    lm = float(proj @ proj)
    u = Uk @ proj
    nu = np.linalg.norm(u)
    values = absent + (B @ (-proj / s) if s.size else 0.0)  # r is prediction - reading: the step is -pinv(C) r
    return Score(lm, int(Uk.shape[1]), (u / nu if nu > 0 else u), Uk, values)


def pose_error(a: np.ndarray, b: np.ndarray) -> float:
    """Distance between the positions of two poses, m."""
    return float(np.linalg.norm(np.asarray(a, float)[:3] - np.asarray(b, float)[:3]))
