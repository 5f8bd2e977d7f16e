"""From a run's signals to a :class:`Solution`: the LM solve of the prepared problem (:mod:`calib.selfcal.guess`),
the estimate noise's refinement and the solution (:func:`calib.selfcal.solve` is the public entry)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.robot import Robot
from calib.selfcal.guess import prepare
from calib.selfcal.lm import levenberg_marquardt
from calib.selfcal.noise import (
    _GROUP_SLICE,
    MISFIT_FACTOR,
    PER_CABLE,
    pose_free_noise,
    reference_sigma,
    rejects,
    rescaled_sigma,
    sigma_change,
    variance_factors,
    window_mean_noise,
)
from calib.selfcal.options import SolveOptions
from calib.selfcal.problem import Problem
from calib.selfcal.result import SelfCalFailure, Solution, compare_pose
from calib.selfcal.rows import paper_noise, sensor_noise
from calib.selfcal.sway import with_sway

REFINE = 2  # estimate-noise solves: pose-free kinematic noise at the solution, then the solve again, twice
# then variance-component rounds on the window means (noise.rescaled_sigma) until they settle: 2-3 on the
# simulated runs; 3-8 on the real ones, whose levels raised to model error in the first round (sized at a pose
# fitted at chi2/dof 2000-9000) follow their scatter to Helmert's fixed point (sc_8_medium_a's lengths 7.1 ->
# 1.4 mm; stopped at 4 rounds the pose was 10 mm off: the "third minimum" of issue 28; docs/windows.md,
# "Rounds that settle at one weighting"); the cap only guards against a cycle
VCE_ROUNDS_ROWS = 20
# the rounds have settled when no group's sigma would change by more than SETTLE_SIGMA (relative) and the last
# round moved the initial position by less than SETTLE_POSE of its 1-sigma on every axis: a Helmert walk that
# creeps on (a group with little redundancy: the lengths, 1-2 % a round at the end) moves nothing that matters
SETTLE_SIGMA = 0.03
SETTLE_POSE = 0.1


@dataclass(frozen=True)
class _RoundsData:
    """What an estimate solve's variance-component rounds weigh against: the within-window sigmas (``within``,
    SI), the sensors' specifications (``floor``), the window means' quantisation error (``lower``), the
    reference window's size (samples)."""

    within: dict[str, np.ndarray]
    floor: dict[str, np.ndarray]
    lower: dict[str, np.ndarray]
    ref_size: int


def _dof(problem: Problem) -> int:
    """A solve's degrees of freedom: its weighted rows less theta and every pose."""
    return max(problem.n_residuals - (problem.model.n_params + 6 * problem.meas.k), 1)


def _with_reference_noise(robot: Robot, model, theta: np.ndarray, sigma: dict[str, np.ndarray],
                          windows: np.ndarray | None, ref_size: int):
    """The model with the reference window's noise for these sigmas (priors.ReferenceNoise.for_rows, in
    place of any earlier one) and theta to match (its values start at 0)."""
    from calib.effects import EffectModel
    from calib.effects.priors import ReferenceNoise

    kept = [e for e in getattr(model, "effects", []) if not isinstance(e, ReferenceNoise)]
    n_kept = EffectModel(robot, kept).n_params if kept else 6
    new = EffectModel(robot, [*kept, ReferenceNoise.for_rows(sigma, windows, ref_size)])
    return new, np.r_[theta[:n_kept], np.zeros(new.n_params - n_kept)]


def _group_variance(sigma: dict[str, np.ndarray], group: str) -> float:
    """The mean variance (SI^2) of a variance-component group's channels (``noise.VCE_GROUPS``: tilt and yaw
    are the orientation's first two and its third)."""
    ch, sl = _GROUP_SLICE.get(group, (group, slice(None)))
    return float(np.mean(np.asarray(sigma[ch], float)[sl] ** 2))


def judged_noise(fitted: Problem, theta: np.ndarray, poses: np.ndarray, within: dict[str, np.ndarray],
                 floor: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The within-window sigmas ``within`` an estimate solve weighs its rows with next, judged first against
    the scatter of the rows around the current fit (``fitted``, solved to ``theta``, ``poses`` with weights
    the data did not set: the paper's, then the last judged ones): a group whose rows scatter about it by more
    than sqrt(MISFIT_FACTOR) times its within-window sigma on enough degrees of freedom holds model error and
    gets that scatter instead (:func:`noise.rescaled_sigma`, up only; the groups it cannot judge floored at
    ``floor``, the sensors' specifications). Judged under the new weights instead, a group the model misses
    but weighed by its tiny within-window scatter takes its rows' poses with it and shows no redundancy to
    judge (sc_8_medium_a's lengths: 0.7 degrees of freedom at 35 um), and the solve follows its misfit."""
    factors = variance_factors(fitted, theta, poses)
    scaled = {c: (max(1.0, f * _group_variance(fitted.sigma, c) / max(_group_variance(within, c), 1e-300)), red)
              for c, (f, red) in factors.items()}
    return rescaled_sigma(within, scaled, floor) or within


def _usable(problem: Problem, res) -> bool:
    """Whether an estimate solve's end is a usable solution: its chi2 per degree of freedom within what
    model error leaves after the variance components (at most MISFIT_FACTOR: a group beyond it is rescaled
    to its scatter) and its initial pose's covariance finite."""
    return 2.0 * res.cost / _dof(problem) <= MISFIT_FACTOR and bool(np.all(np.isfinite(np.diag(res.cov_theta)[:6])))


def _consistent(problem: Problem, res) -> bool:
    """Whether a settled estimate end is usable (:func:`_usable`) and its chi2 inside its band (not above the
    upper NOISE_LEVEL / 2 tail): the rounds bring every group they can judge to a factor near 1, so a chi2 far
    above its degrees of freedom at their end sits in rows they cannot judge (e.g. the tilt rows, under one
    degree of freedom), the mark of a pose in another minimum."""
    return _usable(problem, res) and not rejects(2.0 * res.cost, _dof(problem))


def _likelier(ends: list):
    """Of estimate ends (LM result, problem, model), the usable one with the smallest REML criterion
    (:func:`neg_log_likelihood`)."""
    return min(ends, key=lambda e: (not _usable(e[1], e[0]), neg_log_likelihood(e[1], e[0])))


def neg_log_likelihood(problem: Problem, res) -> float:
    """-2 log of the restricted (REML) Gaussian likelihood of a solve's rows at its end, the constant dropped:
    chi2, plus the log of every weighted row's variance (its sigma, SI; the priors' included), plus the log
    determinant of the whitened normal matrix of theta and every pose (what the fitted unknowns take of the
    rows: the variance components' own criterion, Helmert's estimator being a REML one). Two ends of one
    run's rows weighed differently (the two estimate starts, whose variance components end at different
    weights) compare by it: the smaller is the more likely."""
    ev = problem.evaluate(res.theta, res.poses)
    k, p = res.poses.shape[0], res.theta.size
    rows, logw = [], []
    for g, _, J, G in ev.groups:
        m = g.idx.size
        full = np.zeros((m, J.shape[1], p + 6 * k))
        full[..., :p] = G
        full[np.arange(m)[:, None], :, p + 6 * g.idx[:, None] + np.arange(6)[None, :]] = J.transpose(0, 2, 1)
        rows.append(full[g.weight > 0])
        logw.append(np.log(g.weight[g.weight > 0]))
    g0 = np.zeros((ev.r0.size, p + 6 * k))
    g0[:, :p] = ev.g0
    a = np.vstack([*rows, g0])
    logdet = np.linalg.slogdet(a.T @ a)[1]
    logw += [np.log(problem.ref_weight[problem.ref_weight > 0]), -np.log(problem.prior_sd)]
    return 2.0 * ev.cost - 2.0 * float(sum(np.sum(x) for x in logw)) + float(logdet)


def _estimate_passes(robot: Robot, pre, problem: Problem, max_iter: int, robust: bool, follow: bool = True,
                     sway: bool = False):
    """The passes of an estimate solve from the prepared problem (weights: the run's within-window noise):
    a first LM pass, REFINE passes on the pose-free noise at the solution, then VCE_ROUNDS_ROWS
    variance-component rounds. ``robust``: the first pass weighs with the paper's eq. 18 (a documented robust
    start, wide against every model error the real runs show) and each refine pass's within-window sigmas
    are judged at the previous solution first (:func:`judged_noise`). ``follow``: a group raised to model
    error follows its rows' scatter in every round (SolveOptions.estimate_rounds 'settle'), else it keeps its
    first round's size ('first'). ``sway``: the pose-free noise's tension rows carry the sway term
    (SolveOptions.sway). Returns (LM result, problem, model, what the rounds weigh against: None when the
    first pass did not converge)."""
    model, meas, wins, ref, ref_sample = problem.model, problem.meas, pre.windows, pre.ref, pre.ref_sample
    if robust:
        problem = Problem(model, meas, paper_noise(robot))
    res = levenberg_marquardt(problem, pre.theta0, pre.poses0, max_iter=max_iter)
    if not res.converged:
        return res, problem, model, None
    # the kinematic channels' window-mean noise without the platform's motion (which the rows' poses
    # absorb), estimated at the solution; a second pass at the better solution settles it
    sig = pre.signals
    base = window_mean_noise(robot, sig, wins)
    ref_win = next(w for w in wins if w.first <= ref_sample <= w.last)
    for _ in range(REFINE):
        spans = [(ref_win.slice, res.theta[:6])] + [
            (slice(int(a), int(b) + 1), z) for (a, b), z in zip(meas.windows, res.poses, strict=True)]
        pose_free = pose_free_noise(model, sig, spans, ref, res.theta, base)
        if sway:  # the platform's sway about the equilibrium of the held tensions, in the statics rows
            pose_free, _ = with_sway(robot, pose_free, np.array([z for _, z in spans]))
        noise = pose_free.noise
        sigma = judged_noise(problem, res.theta, res.poses, noise.sigma, sensor_noise(robot)) if robust \
            else noise.sigma
        model, theta = _with_reference_noise(robot, model, res.theta, sigma, meas.windows, ref_win.size)
        problem = Problem(model, meas, sigma)
        res = levenberg_marquardt(problem, theta, res.poses, max_iter=max_iter)
    # the within-window sigmas bound each group's noise of a mean from above (they include motion the
    # means average out, e.g. the force control's ripple, and the share the rows' poses absorb): where
    # the window means scatter less around the fit, variance components bring them down; up only where
    # the model misses a group far beyond its noise (model error, noise.rescaled_sigma), and a level so
    # raised then follows its scatter both ways ('settle'); the reference window's mean follows its
    # channels down, never up (noise.reference_sigma)
    data = _RoundsData(noise.sigma, sensor_noise(robot), pose_free.quantisation, ref_win.size)
    return (*_rounds(robot, (res, problem, model), data, max_iter, follow), data)


def _rounds(robot: Robot, end: tuple, data: _RoundsData, max_iter: int, follow: bool, rejected: bool = False):
    """Variance-component rounds from an estimate solve's ``end`` (LM result, problem, model) until they
    settle (SETTLE_SIGMA, SETTLE_POSE; at most VCE_ROUNDS_ROWS): :func:`noise.rescaled_sigma` at each fit, the
    reference window's noise following (:func:`noise.reference_sigma`). ``rejected``: the end's chi2 rejects
    its noise; while each new fit's chi2 still does, a group whose own rows reject their sigma is sized by
    their scatter (rescaled_sigma's ``rejected``). Returns (LM result, problem, model)."""
    res, problem, model = end
    meas = problem.meas
    moved = np.inf  # the last round's move of the initial position, in its own 1-sigma
    for _ in range(VCE_ROUNDS_ROWS):
        beyond = rejected and rejects(2.0 * res.cost, _dof(problem))
        shrunk = rescaled_sigma(problem.sigma, variance_factors(problem, res.theta, res.poses, PER_CABLE),
                                data.floor, data.within, data.lower, follow, beyond)
        if shrunk is None or (not beyond and moved < SETTLE_POSE and
                              sigma_change(problem.sigma, shrunk) < SETTLE_SIGMA):
            break
        before = res.theta[:3].copy()
        model, theta = _with_reference_noise(robot, model, res.theta, reference_sigma(shrunk, data.within),
                                             meas.windows, data.ref_size)
        problem = Problem(model, meas, shrunk)
        res = levenberg_marquardt(problem, theta, res.poses, max_iter=max_iter)
        sd = np.sqrt(np.clip(np.diag(res.cov_theta)[:3], 0.0, None))
        moved = float(np.max(np.abs(res.theta[:3] - before) / np.maximum(sd, 1e-12)))
    return res, problem, model


def solve_run(robot: Robot, run: Any, opts: SolveOptions) -> Solution:
    """See :func:`calib.selfcal.solve`."""
    method, max_iter, reference_pose = opts.method, opts.max_iter, opts.reference_pose
    pre = prepare(robot, run, opts)
    problem, theta0, Z0, wins, search, ref = pre.problem, pre.theta0, pre.poses0, pre.windows, pre.search, pre.ref
    model, meas, ref_sample, source = problem.model, problem.meas, pre.ref_sample, pre.noise_source
    t_start, t_rows, t_guess = pre.marks
    estimate = source == "estimate" and method == "tlse" and ref is not None and max_iter > 0
    if estimate:
        follow, sway = opts.estimate_rounds == "settle", opts.sway
        source = "estimate+sway" if sway else source
        if opts.estimate_start == "likelier":
            # both starts, the within-window first pass and the paper's weights (eq. 18) with judged passes:
            # under one weighting a real run's rows have one minimum (LM from either end, or from the paper
            # solve, lands on it), but the variance components end at other weights from each start; the end
            # kept is the more likely (REML), a usable one first (docs/windows.md)
            ends = [_estimate_passes(robot, pre, pre.problem, max_iter, robust, follow, sway)
                    for robust in (False, True)]
            end = _likelier([e for e in ends if e[0].converged] or ends[:1])
        else:
            end = _estimate_passes(robot, pre, problem, max_iter, False, follow, sway)
            # settled rounds bring chi2 into its band: beyond it, the pose is suspect ('first' rounds leave
            # chi2/dof at 2-3 on the real runs: there only an unusable end is)
            suspect = not (_consistent if follow else _usable)(end[1], end[0])
            if end[0].converged and suspect:
                # the within-window first pass fell into another minimum (sc_8_medium_a with its windows cut to
                # their rest: 41 mm off, chi2/dof 165, the covariance not finite; sc_27_medium_a with three samples
                # cut off a few windows' heads: 35 mm off, chi2/dof 5.9 at settled components, REML 856 against
                # -453): again from the robust start, the more likely end kept (a usable one first)
                other = _estimate_passes(robot, pre, pre.problem, max_iter, True, follow, sway)
                end = _likelier([e for e in (end, other) if e[0].converged])
        res, problem, model, data = end
        if follow and res.converged and data is not None and rejects(2.0 * res.cost, _dof(problem)):
            # the kept end's chi2 still rejects its noise (sc_8_medium_a's six-window folds: chi2/dof 5-9, the
            # length rows at their within-window 0.06 mm on 1.2 degrees of freedom, which the rows' poses follow):
            # its printed 1-sigma would be too narrow by what sigma_scale cannot see. The groups whose own rows
            # reject their sigma are sized by their scatter, and the rounds go on until settled
            res, problem, model = _rounds(robot, (res, problem, model), data, max_iter, follow, rejected=True)
    else:
        res = levenberg_marquardt(problem, theta0, Z0, max_iter=max_iter)
    t_end = time.perf_counter()
    if max_iter == 0 and np.isfinite(res.cost):  # the guess is a solution already (a converged fit's)
        res.converged, res.message = True, "the given solution, not iterated"
    if not np.isfinite(res.cost) or not res.converged:
        raise SelfCalFailure(f"the solve did not converge after {res.iterations} iterations ({res.message}).")
    dof = problem.n_residuals - (model.n_params + 6 * meas.k)
    resid = {}
    for c, (si, nz) in problem.channel_residuals(res.theta, res.poses, res.evaluation).items():
        if si.size:
            resid[c] = {"rms": float(np.sqrt(np.mean(si**2))), "rms_normalized": float(np.sqrt(np.mean(nz**2)))}
    absolute = model.absolute_readings(res.theta)
    if ref is None:
        offsets = absolute
    else:
        offsets = {
            "length": absolute["length"] - ref["dl"],
            "swivel": absolute["swivel"] - ref["dsigma"],
            "yaw": float(absolute["yaw"] - ref["ori"][2]),
        }
    report = getattr(model, "report", None)
    effects = report(res.theta) if callable(report) else {}
    comparison = None if reference_pose is None else compare_pose(res.theta[:6], reference_pose, robot.orientation)
    return Solution(
        method=method,
        initial_pose=res.theta[:6].copy(),
        initial_pose_sigma=np.sqrt(np.clip(np.diag(res.cov_theta)[:6], 0, None)),
        reference_sample=ref_sample,
        sensor_offsets=offsets,
        poses=res.poses,
        poses_sigma=np.sqrt(np.clip(np.diagonal(res.cov_poses, axis1=1, axis2=2), 0, None)),
        samples=meas.samples if meas.samples is not None else np.full(meas.k, -1),
        windows=wins,
        theta=res.theta,
        param_names=model.param_names,
        covariance=res.cov_theta,
        chi2=2.0 * res.cost,
        dof=int(dof),
        residuals=resid,
        noise={c: [float(v) for v in s] for c, s in problem.sigma.items()},
        noise_source=source,
        iterations=res.iterations,
        converged=res.converged,
        message=res.message,
        timing={
            "solve_s": t_end - t_start,
            "rows_s": t_rows - t_start,
            "guess_s": t_guess - t_rows,
            "lm_s": t_end - t_guess,
        },
        effects=effects,
        reference=comparison,
        window_search=search,
        reference_noise=next((dict(e.sd) for e in getattr(model, "effects", []) if e.name == "reference_noise"), None),
    )
