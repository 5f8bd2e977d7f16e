"""Several runs, one robot: a joint fit with the robot's effects shared and each run's own unknowns (issue 28).

Unknowns of a joint fit over runs r = 1..R:

* the **shared** effects (cell offsets, compliance, geometry: what belongs to the robot), one value for all
  runs, first in the parameter vector;
* per run, its **own** unknowns: the initial pose zeta_0 and the poses of its rows, the devices' constant
  errors within their datasheet accuracy (:class:`DeviceBase`, whose priors step aside where a shared effect
  overlaps them), the reference window's noise (``ReferenceNoise``, with the run's own priors) and the AHRS
  yaw drift rate (``ahrs_yaw_drift``: a gyro-only heading drifts by a different rate in every run).

Each run keeps its own :class:`calib.selfcal.problem.Problem` (its rows and weights); the theta of run r is
[zeta_0, its own effect values, the shared values], so the joint Jacobian is the runs' dense Jacobians
(:func:`calib.fitting.residuals`) side by side on the shared columns. It is solved by Levenberg-Marquardt
with geodesic acceleration on unit-norm columns, the normal equations by blocks (each pose's 6 x 6 block
eliminated, :class:`Arrow`; a ridge keeps the directions no run sees where they started), until a stated
criterion holds or the cap is reached (:class:`Stop`; every JointFit says which).

**Weights that fit the data** (:func:`fit_runs` with ``components``): the sigma of each run's channel group
(tension, length, swivel, orientation) is rescaled by its variance component, sum r^2 / (n (1 - h)), with
h the share of the fit's free parameters in the residual count; up as well as down, floored at the sensors'
specification (``calib.selfcal.sensor_noise``): the model being judged sets its own noise, so one channel's
misfit does not dominate the others' (with window-scatter weights the swivel encoders did on the real runs).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from calib.arrow import Arrow
from calib.effects import Effect, EffectModel, ParamSpec, Projected
from calib.effects.base import Physical, physical_rows
from calib.effects.builtin import AhrsYawDrift
from calib.effects.priors import DeviceAccuracy, ReferenceNoise
from calib.fitting import Residuals, residuals
from calib.runrows import RunRows
from calib.selfcal.model import CHANNELS
from calib.selfcal.problem import Problem

GROUPS = CHANNELS  # the channel groups whose noise the variance components set
LAMBDA_MAX = 1e10  # an LM iteration gives up when no damping up to this (relative to diag N) lowers the chi2
HOLD_MAX = 8  # iterations at most that LM keeps a damping whose tenth was refused before trying it again
RIDGE = 1e-9  # relative ridge of the normal equations (unit-norm columns)
# the normal matrix's eigenvalue ratio above which its inverse is taken by a solve (condition below 1e8: the
# covariance to ~1e-8, its rank full, far from the SVD's cut at 1e-10); below it, the SVD of the Jacobian
FULL_RANK = 1e-8
PIN = 1e-6  # a device prior that steps aside is pinned at its absent value: sd = PIN * its typical size
# which device priors a shared effect overlaps (the same columns): they step aside while it is fitted
OVERLAPS = {"tension_offset": ("b_",), "ahrs_mounting": ("b_roll", "b_pitch")}
PER_RUN = ("ahrs_yaw_drift",)  # library effects that are a run's own unknown, never shared
NOT_CANDIDATES = (*PER_RUN, DeviceAccuracy.name, ReferenceNoise.name)  # in every fit of a run, never selected


class DeviceBase(DeviceAccuracy):
    """The devices' datasheet errors (``DeviceAccuracy``) with the priors named in ``aside`` (names, or a
    prefix ending in '_' for the numbered ones: 'b_' is the cells b_1..b_n) pinned at zero: a shared effect
    that explains the same readings takes them instead. The yaw drift rate is always aside: every run fits
    its own (``ahrs_yaw_drift``)."""

    def __init__(self, aside: Sequence[str] = ()):
        self.aside = ("yaw_rate", *aside)

    def params(self, robot) -> list[ParamSpec]:
        out = []
        for s in super().params(robot):
            if any(s.name == a or (a.endswith("_") and s.name.startswith(a) and s.name[len(a):].isdigit())
                   for a in self.aside):
                s = replace(s, prior=PIN * s.scale)
            out.append(s)
        return out


class Learned(Projected):
    """An effect at a learned value: values = learned + delta, delta a parameter with a Gaussian prior of
    standard deviation ``sd`` (per parameter, same unit: a model used as prior); ``sd=None`` freezes it (the
    prior pinned, PIN times the typical size). Reported and checked as the inner effect's full values."""

    def __init__(self, inner: Effect, robot, values: np.ndarray, sd: np.ndarray | None = None):
        specs = inner.params(robot)
        super().__init__(inner, np.eye(len(specs)), [s.name for s in specs])
        self.learned = np.asarray(values, float)
        scales = np.array([s.scale for s in specs], float)
        self.sd = PIN * scales if sd is None else np.maximum(np.asarray(sd, float), PIN * scales)
        self.frozen = sd is None

    def _absent(self, robot) -> np.ndarray:
        return self.learned

    def transform(self, ctx, values, preds) -> None:
        """As Projected's, with ctx.theta and the physical columns widened too (effects that build their
        columns from them)."""
        q, p = self.basis.shape[0], ctx.theta.shape[0]
        for pr in preds.values():
            pr.d_theta = np.concatenate([pr.d_theta, np.zeros(pr.d_theta.shape[:2] + (q,))], axis=2)
        def wide(ph):
            z = np.zeros(ph.tL.shape[:2] + (q,))
            return replace(ph, tL=np.concatenate([ph.tL, z], 2), tsigma=np.concatenate([ph.tsigma, z], 2),
                           ttau=np.concatenate([ph.ttau, z], 2))

        inner_ctx = replace(ctx, theta=np.r_[ctx.theta, np.zeros(q)], cols=slice(p, p + q), at=wide(ctx.at),
                            ref=wide(ctx.ref))
        self.inner.transform(inner_ctx, self.full_values(ctx.robot, values), preds)
        for pr in preds.values():
            extra = pr.d_theta[..., p:]
            pr.d_theta = pr.d_theta[..., :p]
            pr.d_theta[..., ctx.cols] = extra @ self.basis

    def params(self, robot) -> list[ParamSpec]:
        return [ParamSpec(s.name, s.unit, 0.0, -np.inf, np.inf, s.scale, prior=float(sd))
                for s, sd in zip(self.inner.params(robot), self.sd, strict=True)]


def own_effects(rows: RunRows, shared: Sequence[Effect]) -> list[Effect]:
    """A run's own unknowns besides its poses: device errors (priors aside where a shared effect overlaps),
    the reference window's noise, the yaw drift rate."""
    names = {e.name for e in shared}
    aside = [p for n, pre in OVERLAPS.items() if n in names for p in pre]
    out: list[Effect] = [DeviceBase(aside)]
    if rows.reference is not None:
        out.append(rows.reference)
    out.append(AhrsYawDrift())
    return out


@dataclass
class RunFit:
    """One run in a joint fit: its name, problem, theta ([zeta_0, own values, shared values]), poses, the
    weights it was fitted with and its chi2 with them."""

    name: str
    rows: RunRows
    problem: Problem
    theta: np.ndarray
    poses: np.ndarray
    sigma: dict[str, np.ndarray]
    chi2: float = 0.0
    res: Residuals | None = field(default=None, repr=False, compare=False)  # residuals at this state, if known

    def residuals(self) -> Residuals:
        """The run's weighted residuals at its state (those of its last evaluation when known)."""
        if self.res is None:
            self.res = residuals(self.problem, self.theta, self.poses)
        return self.res

    def params(self) -> dict[str, dict[str, float]]:
        return self.problem.model.report(self.theta)

    def rms(self) -> dict[str, float]:
        """Rms residual per channel in physical units (N, m, rad), the rows and the reference row."""
        res = self.residuals()
        return {c: float(np.sqrt(np.mean(res.si[res.channel == c] ** 2))) for c in GROUPS
                if (res.channel == c).any()}


@dataclass
class JointFit:
    """A joint fit: the shared effects, their values (q,) and covariance, the runs, the total chi2."""

    shared: list[Effect]
    values: np.ndarray
    cov: np.ndarray
    runs: list[RunFit]
    chi2: float
    converged: bool
    iterations: int
    n_residuals: int = 0
    n_free: int = 0
    history: list[dict[str, Any]] = field(default_factory=list)  # per weighting round: run -> weights, pose
    stop: Stop | None = None  # why the last round's LM stopped (converged or not, the criterion)

    def convergence_words(self) -> str:
        """One sentence on the fit's convergence; a fit that did not converge is a WARNING (its values are where
        the iterations stopped, not the least-squares solution)."""
        c = self.convergence()
        if c["converged"]:
            return (f"converged ({c['criterion']}: {c['remaining_chi2']:.2g} chi2 left to gain; "
                    f"{c['iterations']} iterations)")
        what = "the iteration cap" if c["criterion"] == "cap" else "no damping lowering the chi2"
        return (f"WARNING: not converged (stopped by {what} after {c['iterations']} iterations, the Gauss-Newton step "
                f"still predicting {c['remaining_chi2']:.2g} chi2 to gain): its values are where it stopped")

    def convergence(self) -> dict[str, Any]:
        """Whether the fit reported converged, by which criterion, its LM iterations (all rounds) and the chi2
        decrease the Gauss-Newton step still predicted (docs/effects.md, "Converged fits")."""
        s = self.stop
        return {"converged": bool(self.converged), "criterion": None if s is None else s.reason,
                "iterations": int(self.iterations), "remaining_chi2": None if s is None else float(s.remaining)}

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.shared]

    def shared_params(self) -> dict[str, dict[str, float]]:
        """The shared effects' values as they report them."""
        if not self.runs:
            return {}
        return {k: v for k, v in self.runs[0].params().items() if k in self.names}

    def shared_sigmas(self) -> dict[str, dict[str, float]]:
        """1-sigma of every shared effect parameter (full parameters for restricted effects)."""
        out, start = {}, 0
        robot = self.runs[0].rows.robot
        for e in self.shared:
            q = len(e.params(robot))
            cov = self.cov[start:start + q, start:start + q]
            specs = e.params(robot)
            if isinstance(e, Projected):
                cov, specs = e.covariance(cov), e.inner.params(robot)
            sd = np.sqrt(np.clip(np.diag(cov), 0, None))
            out[e.name] = {s.name: float(v) for s, v in zip(specs, sd, strict=True)}
            start += q
        return out


def _layout(shared: Sequence[Effect], robot) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    specs = [s for e in shared for s in e.params(robot)]
    lo = np.array([s.lower for s in specs], float)
    hi = np.array([s.upper for s in specs], float)
    return len(specs), np.array([s.absent for s in specs], float), lo, hi


def start_runs(items: Sequence[tuple[str, RunRows]], shared: Sequence[Effect],
               starts: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
               sigmas: Sequence[dict[str, np.ndarray]] | None = None) -> list[RunFit]:
    """The RunFits of a joint fit before fitting: each run's model (own effects, then the shared), its
    start (the given (theta_own, poses) or the run's rigid solve) and weights (given or the run's own)."""
    out = []
    for j, (name, rows) in enumerate(items):
        own = own_effects(rows, shared)
        model = EffectModel(rows.robot, [*own, *shared])
        sigma = dict(rows.sigma) if sigmas is None else sigmas[j]
        problem = Problem(model, rows.meas, sigma)
        q_sh = sum(len(e.params(rows.robot)) for e in shared)
        if starts is None:
            theta = model.initial_params(rows.solution.theta[:6])
            poses = np.asarray(rows.solution.poses, float).copy()
        else:
            own_theta, poses = starts[j]
            theta = np.r_[own_theta, model.absent_values()[own_theta.shape[0] - 6:]]
            theta = theta[: model.n_params]
            poses = np.asarray(poses, float).copy()
        assert theta.shape[0] == model.n_params, (theta.shape, model.n_params, q_sh)
        out.append(RunFit(name, rows, problem, theta, poses, sigma))
    return out


def one_robot(runs: list[RunFit], shared: Sequence[Effect]) -> bool:
    """Whether the runs' physical quantities (kinematics, statics, robot effects) can be computed in one
    model call for all their poses: one robot description, every problem one group of rows, and the robot
    effects all shared (the same instances, last in every run's model)."""
    m0, ns = runs[0].problem.model, len(shared)
    if not all(isinstance(rf.problem.model, EffectModel) and rf.problem.single for rf in runs):
        return False
    desc = m0.robot.to_dict()
    for rf in runs:
        m = rf.problem.model
        own, tail = m.effects[:len(m.effects) - ns], m.effects[len(m.effects) - ns:]
        if (m.robot is not m0.robot and m.robot.to_dict() != desc) or any(e.stage == "robot" for e in own) \
                or any(a is not b for a, b in zip(tail, m0.effects[len(m0.effects) - ns:], strict=True)):
            return False
    return True


def _rows_of(ph: Physical, rows: slice, p0: int, p: int, q: int) -> Physical:
    """Rows of physical quantities computed with a model of p0 parameters, laid out for one of p whose last q
    are the same shared ones (the theta columns of robot effects are all among them)."""
    def cols(t):
        out = np.zeros(t[rows].shape[:2] + (p,))
        if q:
            out[..., p - q:] = t[rows, :, p0 - q:]
        return out

    out = physical_rows(ph, rows)
    out.tL, out.tsigma, out.ttau = cols(ph.tL), cols(ph.tsigma), cols(ph.ttau)
    return out


def _evaluate(runs: list[RunFit], q: int = 0, batch: bool = False, jacobian: bool = True) -> tuple[list, float]:
    """Each run's Residuals with their Jacobian (the model's predictions carry their derivatives anyway, so
    an accepted LM trial is not evaluated twice) and the joint chi2 (weighted residuals' sum of squares,
    priors included). ``batch`` (:func:`one_robot`; q the shared parameters): the physical quantities of all
    runs' rows and zeta_0s in one model call (the same numbers, a third of the calls for three runs)."""
    t0 = runs[0].theta
    if batch and all(np.array_equal(rf.theta[rf.theta.shape[0] - q:], t0[t0.shape[0] - q:]) for rf in runs):
        rows = [np.vstack([rf.theta[None, :6], rf.poses[rf.problem.groups[0].idx], rf.theta[None, :6]])
                for rf in runs]
        robot, ph = runs[0].problem.model.physical(t0, np.vstack(rows), derivatives=jacobian)
        ends = np.cumsum([0] + [z.shape[0] for z in rows])
        blocks = [residuals(rf.problem, rf.theta, rf.poses, jacobian,
                            physical=(robot, _rows_of(ph, slice(a, b), t0.shape[0], rf.theta.shape[0], q)))
                  for rf, a, b in zip(runs, ends[:-1], ends[1:], strict=True)]
    else:
        blocks = [residuals(rf.problem, rf.theta, rf.poses, jacobian) for rf in runs]
    return blocks, float(sum(np.sum(b.r ** 2) for b in blocks))


def stack(runs: list[RunFit], q: int, fixed_shared: bool = False, blocks_out: list | None = None,
          blocks: list | None = None) -> tuple[np.ndarray, np.ndarray, list]:
    """Joint weighted residuals and Jacobian; columns: shared (q, unless fixed), then per run own theta and
    poses. Also the per-run column slices (own, poses); ``blocks_out`` receives each run's Residuals;
    ``blocks``: the runs' Residuals already evaluated at their state."""
    rs, cols = [], []
    if blocks is None:
        blocks = [residuals(rf.problem, rf.theta, rf.poses) for rf in runs]
    start = 0 if fixed_shared else q
    for rf, res in zip(runs, blocks, strict=True):
        k = rf.poses.shape[0]
        p_own = rf.theta.shape[0] - q
        rs.append(res.r)
        cols.append((slice(start, start + p_own), slice(start + p_own, start + p_own + 6 * k)))
        start += p_own + 6 * k
    if blocks_out is not None:
        blocks_out.extend(blocks)
    m = sum(r.shape[0] for r in rs)
    A = np.zeros((m, start))
    row = 0
    for rf, res, (so, sp) in zip(runs, blocks, cols, strict=True):
        k = rf.poses.shape[0]
        p_own = rf.theta.shape[0] - q
        mm = res.r.shape[0]
        A[row:row + mm, sp] = res.A[:, :6 * k]
        A[row:row + mm, so] = res.A[:, 6 * k:6 * k + p_own]
        if not fixed_shared and q:
            A[row:row + mm, :q] = res.A[:, 6 * k + p_own:]
        row += mm
    return np.concatenate(rs), A, cols


def _apply(runs: list[RunFit], x: np.ndarray, q: int, cols, fixed_shared: bool) -> list[RunFit]:
    out = []
    for rf, (so, sp) in zip(runs, cols, strict=True):
        p_own = rf.theta.shape[0] - q
        theta = rf.theta.copy()
        theta[:p_own] += x[so]
        if not fixed_shared and q:
            theta[p_own:] += x[:q]
        out.append(replace(rf, theta=theta, poses=rf.poses + x[sp].reshape(-1, 6), res=None))
    return out


def _clip(runs: list[RunFit], q: int, lo: np.ndarray, hi: np.ndarray) -> None:
    for rf in runs:
        if q:
            rf.theta[-q:] = np.clip(rf.theta[-q:], lo, hi)




@dataclass
class Damping:
    """Marquardt's LM damping (x10 after a refused trial, /10 after a success) with a memory: a damping whose
    tenth was just refused is kept for 1, 2, 4, ... HOLD_MAX iterations before the tenth is tried again. Where
    the lighter step keeps failing (a weak, non-quadratic direction: the real medium runs' heights with the
    compliance) it takes Marquardt's accepted steps without one refused trial per iteration."""

    lam: float = 1e-5
    hold: int = 0  # iterations left at this damping
    wait: int = 1  # the next hold

    def refused(self) -> None:
        self.lam *= 10.0

    def accepted(self, after_refusal: bool) -> None:
        if after_refusal:
            self.hold, self.wait = min(self.wait, HOLD_MAX), min(2 * self.wait, HOLD_MAX)
        elif self.hold > 0:
            self.hold -= 1
        if self.hold == 0:
            self.lam = max(self.lam / 10.0, 1e-12)


@dataclass(frozen=True)
class Stop:
    """Why a joint Levenberg-Marquardt fit stopped. ``reason``: 'decrease' (the Gauss-Newton step predicts at
    most FTOL of the chi2, or CHI2_TOL, left to gain), 'gradient' (every scaled column is within GTOL of
    orthogonal to the residuals) -- both converged; 'cap' (max_iter accepted steps) or 'stalled' (no damping
    up to LAMBDA_MAX lowers the chi2 while the Gauss-Newton step still predicts a gain) -- not converged.
    ``remaining``: the chi2 decrease the Gauss-Newton step predicted at the last iterate."""

    converged: bool
    reason: str
    iterations: int
    remaining: float


FTOL = 1e-5  # converged when the Gauss-Newton step predicts at most this share of the chi2 left to gain
CHI2_TOL = 1e-10  # ... or at most this much chi2 (a step of 1e-5 sigma: zero-residual problems)
GTOL = 1e-10  # ... or when the cosine between the residuals and every scaled column is below this
GEO_ALPHA = 0.75  # a geodesic acceleration a is used while 2 |a| / |v| <= this (Transtrum & Sethna 2012)
GEO_H = 0.1  # finite-difference step along v of the residuals' second directional derivative (same paper)


def _directional(runs: list[RunFit], blocks: list[Residuals], x: np.ndarray, q: int, cols, fixed_shared: bool
                 ) -> list[np.ndarray]:
    """Per run, the Jacobian times the step x (physical units, :func:`stack`'s column order)."""
    out = []
    for rf, res, (so, sp) in zip(runs, blocks, cols, strict=True):
        k6, p_own = rf.poses.size, rf.theta.shape[0] - q
        dx = np.zeros(res.A.shape[1])
        dx[:k6], dx[k6:k6 + p_own] = x[sp], x[so]
        if not fixed_shared and q:
            dx[k6 + p_own:] = x[:q]
        out.append(res.A @ dx)
    return out


def geodesic_step(runs: list[RunFit], blocks: list[Residuals], arrow: Arrow, damping: float, q: int,
                  fixed_shared: bool, batch: bool) -> np.ndarray:
    """The damped step with geodesic acceleration (Transtrum & Sethna, arXiv:1201.5885), scaled columns:
    v + a / 2, v the damped Gauss-Newton step, a = -(N + damping D)^-1 J^T r_vv with r_vv the residuals'
    second directional derivative along v (one finite difference, GEO_H). It follows a curved valley (the
    medium runs' heights against the cables' compliance) where the straight step v leaves it. Where
    2 |a| / |v| > GEO_ALPHA the second-order expansion does not hold over the step (far from the solution):
    the plain step v."""
    v, _ = arrow.step(damping)
    x = v / arrow.scale
    jv = _directional(runs, blocks, x, q, arrow.cols, fixed_shared)
    near, _ = _evaluate(_apply(runs, GEO_H * x, q, arrow.cols, fixed_shared), q, batch, jacobian=False)
    rvv = [2.0 / GEO_H * ((h.r - b.r) / GEO_H - j) for h, b, j in zip(near, blocks, jv, strict=True)]
    acc, _ = arrow.step(damping, arrow.gradient(rvv))
    if not np.all(np.isfinite(acc)) or 2.0 * np.linalg.norm(acc) > GEO_ALPHA * np.linalg.norm(v):
        return v
    return v + 0.5 * acc


def _at_bounds(runs: list[RunFit], ds: np.ndarray, q: int, lo: np.ndarray, hi: np.ndarray) -> np.ndarray | None:
    """The shared values at a bound that the Gauss-Newton step ds (scaled columns, shared first) would cross
    (held: an active set, so that the other values' step and the convergence test are those of the problem on
    the bound); None when no shared column is free or none is held."""
    if not q or runs[0].theta.shape[0] < q:
        return None
    th = runs[0].theta[runs[0].theta.shape[0] - q:]
    out = ((th >= hi) & (ds[:q] > 0)) | ((th <= lo) & (ds[:q] < 0))
    return out if out.any() else None


def _cosine(arrow: Arrow, cost: float) -> float:
    """The largest cosine between the residual vector and a column of the joint Jacobian (MINPACK's gtol)."""
    qq = arrow.q
    shared = np.zeros(qq)
    top = 0.0
    for (so, _), gp, gt in zip(arrow.cols, arrow.gp, arrow.gt, strict=True):
        no = so.stop - so.start
        top = max(top, float(np.abs(gp).max(initial=0.0)), float(np.abs(gt[:no]).max(initial=0.0)))
        shared += gt[no:]
    if arrow.pinned is not None:
        shared[arrow.pinned] = 0.0
    return max(top, float(np.abs(shared).max(initial=0.0))) / max(math.sqrt(cost), 1e-300)


def lm_runs(runs: list[RunFit], shared: Sequence[Effect], fixed_shared: bool = False, max_iter: int = 60,
            covariance: bool = True) -> tuple[list[RunFit], float, Stop, np.ndarray, int]:
    """Levenberg-Marquardt with geodesic acceleration (:func:`geodesic_step`) on the joint problem (its
    normal equations by blocks, :class:`Arrow`, unit-norm columns). Returns the runs, chi2, why it stopped
    (:class:`Stop`), the scaled inverse normal matrix's shared block (covariance of the shared values) and the
    rank (without ``covariance``: zeros and 0, the SVD skipped)."""
    robot = runs[0].problem.model.robot
    q, _, lo, hi = _layout(shared, robot)
    damping = Damping()
    batch = one_robot(runs, shared)
    blocks, cost = _evaluate(runs, q, batch)
    it = 0
    while True:
        arrow = Arrow.of(runs, blocks, q, fixed_shared)
        gn, remaining = arrow.step(RIDGE)
        arrow.pinned = _at_bounds(runs, gn, arrow.q, lo, hi)
        if arrow.pinned is not None:
            _, remaining = arrow.step(RIDGE)
        if remaining <= max(FTOL * cost, CHI2_TOL):
            stop = Stop(True, "decrease", it, remaining)
            break
        if _cosine(arrow, cost) <= GTOL:
            stop = Stop(True, "gradient", it, remaining)
            break
        if it >= max_iter:
            stop = Stop(False, "cap", it, remaining)
            break
        improved, trial_no = False, 0
        while damping.lam <= LAMBDA_MAX:  # Marquardt: x10 after each refused trial
            ds = geodesic_step(runs, blocks, arrow, damping.lam + RIDGE, q, fixed_shared, batch)
            trial = _apply(runs, ds / arrow.scale, q, arrow.cols, fixed_shared)
            _clip(trial, q, lo, hi)
            trial_blocks, c1 = _evaluate(trial, q, batch)
            if np.isfinite(c1) and c1 < cost:
                improved = True
                break
            damping.refused()
            trial_no += 1
        if not improved:
            stop = Stop(False, "stalled", it, remaining)
            break
        runs, cost, blocks = trial, c1, trial_blocks
        damping.accepted(after_refusal=trial_no > 0)
        it += 1
    for rf, b in zip(runs, blocks, strict=True):
        rf.chi2, rf.res = float(b.r @ b.r), b
    if not covariance:
        return runs, cost, stop, np.zeros((q, q)), 0
    by_blocks = arrow.covariance()
    if by_blocks is not None:  # full rank: the shared block of N's inverse from the runs' Schur complements
        cov_s, rank = by_blocks
        cov = cov_s / np.outer(arrow.scale[:cov_s.shape[0]], arrow.scale[:cov_s.shape[0]]) if q and not \
            fixed_shared else np.zeros((q, q))
        return runs, cost, stop, cov, rank
    _, A, _ = stack(runs, q, fixed_shared, blocks=blocks)
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    As = A / scale
    N = As.T @ As
    ev = np.linalg.eigvalsh(N)
    if ev[0] > FULL_RANK * ev[-1]:  # condition below 1e8: a solve is accurate, and the rank is full
        rank = N.shape[0]
        cov_s = np.linalg.solve(N, np.eye(N.shape[0])[:, :q])[:q] if q and not fixed_shared else None
    else:  # a direction the data barely see: the pseudo-inverse and rank of the SVD (cut at 1e-10)
        _, s, Vt = np.linalg.svd(As, full_matrices=False)
        keep = s > 1e-10 * s.max(initial=0.0)
        rank = int(keep.sum())
        cov_s = ((Vt[keep, :q].T / s[keep] ** 2) @ Vt[keep, :q]) if not fixed_shared else None
    cov = np.zeros((q, q)) if cov_s is None else cov_s / np.outer(scale[:q], scale[:q])
    return runs, cost, stop, cov, rank


def components(rf: RunFit, redundancy: float, floor: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The run's weights rescaled by the variance component of each channel group (up and down), floored
    at the sensors' specification."""
    res = rf.residuals()
    out = {}
    for c, sig in rf.sigma.items():
        m = res.channel == c
        if not m.any():
            out[c] = sig
            continue
        f = float(np.sum(res.r[m] ** 2)) / max(m.sum() * redundancy, 1.0)
        out[c] = np.maximum(np.asarray(sig, float) * math.sqrt(max(f, 1e-12)), floor[c])
    return out


ROUNDS = 3  # variance-component rounds (each: fit, then new weights)


def fit_runs(items: Sequence[tuple[str, RunRows]], shared: Sequence[Effect], *, frozen: bool = False,
             starts=None, sigmas=None, rounds: int = ROUNDS, max_iter: int = 60, covariance: bool = True,
             weight_iter: int | None = None) -> JointFit:
    """Joint fit of the runs with the shared effects (values free, or ``frozen`` at their current values:
    only each run's own unknowns fitted), with ``rounds`` of variance components (0: the given weights).
    Without ``covariance`` (a fit only used as a start) the final covariance is zeros and n_free 0.
    ``weight_iter``: LM iterations at most of a round that only sets the next round's weights (None:
    ``max_iter``); the last round always gets ``max_iter``."""
    from calib.selfcal import sensor_noise

    shared = list(shared)
    runs = start_runs(items, shared, starts, sigmas)
    robot = runs[0].rows.robot
    floor = sensor_noise(robot)
    history = []
    it_total = 0
    for rnd in range(rounds + 1):
        iters = max_iter if rnd == rounds or weight_iter is None else min(max_iter, weight_iter)
        runs, cost, stop, cov, rank = lm_runs(runs, shared, frozen, iters, covariance=covariance or rnd < rounds)
        it_total += stop.iterations
        history.append({rf.name: {"weights": {c: [float(v) for v in s] for c, s in rf.sigma.items()},
                                  "initial_pose": [float(v) for v in rf.theta[:6]], "stop": stop.reason}
                        for rf in runs})
        m = sum(rf.residuals().r.shape[0] for rf in runs)
        if rnd == rounds:
            break
        red = max(1.0 - rank / max(m, 1), 0.05)
        new = []
        for rf in runs:
            sig = components(rf, red, floor)
            new.append(replace(rf, sigma=sig, problem=Problem(rf.problem.model, rf.rows.meas, sig), res=None))
        runs = new
    q = _layout(shared, robot)[0]
    values = runs[0].theta[runs[0].theta.shape[0] - q:] if q else np.zeros(0)
    return JointFit(shared, values.copy(), cov, runs, cost, stop.converged, it_total, m, rank, history, stop)


def held_out_score(rf: RunFit) -> float:
    """Gaussian negative log-likelihood (up to a constant) of a run's residuals with each channel group's
    variance its own mean square, floored at the sensors' specification: sum_g n_g log(ms_g / floor_g^2).
    Independent of the weights; lower is better."""
    from calib.selfcal import sensor_noise

    res = rf.residuals()
    return score_of(res.si, res.channel, sensor_noise(rf.rows.robot))


def score_of(phys: np.ndarray, channel: np.ndarray, floor: dict[str, np.ndarray]) -> float:
    """sum over channel groups of n_g log(ms_g / floor_g^2), ms_g the mean square of the physical residuals
    (m,) labelled ``channel`` in group g, floored at floor_g^2 (:func:`held_out_score`)."""
    total = 0.0
    for c in GROUPS:
        m = channel == c
        if not m.any():
            continue
        f2 = float(np.mean(np.asarray(floor[c], float)) ** 2)
        ms = float(np.mean(phys[m] ** 2))
        total += m.sum() * math.log(max(ms, f2) / f2)
    return total


WEIGHTS = {"tension": 1.0, "length": 0.5e-3, "swivel": math.radians(0.1), "orientation": math.radians(0.2)}


def misfit_j(rms: dict[str, float]) -> float:
    """DW1's misfit J = sum over channels of (rms / w)^2, w: 1 N, 0.5 mm, 0.1 deg, 0.2 deg."""
    return float(sum((rms[c] / WEIGHTS[c]) ** 2 for c in WEIGHTS if c in rms))
