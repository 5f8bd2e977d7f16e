"""Which effects does the robot have? Selection by prediction across runs (issue 28, what to build 1, 2, 8).

A candidate set of shared effects is judged by what it predicts on data it was not fitted on:

* with two runs or more, **leave one run out**: the shared effects are learned on the other runs (joint fit,
  :func:`calib.multirun.fit_runs`), frozen, and the left-out run is solved with only its own unknowns
  refitted (initial pose, poses, device errors, reference noise, yaw drift rate; its weights by variance
  components); the figure is that run's :func:`calib.multirun.held_out_score` (a Gaussian negative
  log-likelihood with each channel group's variance its own, so no channel's units dominate), summed over
  the left-out runs;
* with one run, **leave one pose out** (:func:`calib.prediction.leave_one_pose_out`) on the weights of the
  base model, so that every candidate is scored in the same units.

Forward steps: every single candidate is fitted on all runs (a short fit from the current one, then its
own fit with a weighting round) and judged by prediction, and so are the pairs of the best ``PAIR_POOL``
singles by prediction and the best plausible single (:func:`pair_pool`). No in-sample screen decides what
is judged (an in-sample score favours the effects with many parameters); every candidate's prediction is
measured and reported. The best
option by prediction is taken, unless one with fewer parameters predicts within ``CONFUSED`` of its gain
(the fewest parameters among confused candidates). An option must predict better in total and on most
left-out runs (poses). When the best option by prediction has a value outside its plausible range, that is
a finding (and so is an effect whose values together are that far from their plausible box:
:func:`box_chi2`), not a reason to take the next one: the selection stops there and says so (a likely
error in the robot description or the setup, with the value found), unless one more effect brings it into
range and predicts better still (:func:`extend_finding`: its out-of-range value was that effect's part, as a
transmission-ratio error read as cable compliance; the extension explains more, not less). With several runs
the finding's out-of-range effects are also fitted on each run alone (:func:`calib.spread.spread`): runs that agree on
them point to a fixed property of the robot as set up (a description or calibration error to check on it),
runs that disagree to a model error that each run's fit absorbs differently.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib.chi2 import chi2_sf
from calib.effects import Effect, Implausible, Projected
from calib.fitting import residuals
from calib.multirun import (
    GROUPS,
    JointFit,
    RunFit,
    fit_runs,
    held_out_score,
    misfit_j,
    score_of,
)
from calib.prediction import leave_one_pose_out
from calib.runrows import RunRows
from calib.selfcal.problem import Problem
from calib.spread import Spread, spread

PAIR_POOL = 3  # the best single candidates by prediction whose pairs are judged together
CONFUSED = 0.10  # an option predicting within this share of the best gain is confused with it
MIN_GAIN = 2.0  # held-out -2 log-likelihood gain an added option must bring (a likelihood ratio of e)
QUICK_ITER = 15  # LM iterations of a screening fit
CONSISTENT_P = 0.01  # an added effect on whose values the runs disagree beyond this p-value is not learned
FOLD_ROUNDS = 1  # variance-component rounds in the folds (started from the full fit's weights)
WEIGHT_ITER = 20  # LM iterations of the round that only sets the weights of a judged fit (its last: 60)


@dataclass
class Trial:
    """One candidate set judged: the names, parameter count, the joint fit on all runs, the prediction
    score (lower is better) and per fold (left-out run or pose) its score and the left-out run's rms per
    channel and J; the fitted values outside their plausible ranges."""

    names: tuple[str, ...]
    n_params: int
    fit: JointFit
    fit_score: float
    score: float | None = None
    folds: list[dict[str, Any]] = field(default_factory=list)
    implausible: list[Implausible] = field(default_factory=list)
    spread: Spread | None = None  # the runs' agreement on the effects it adds (when chosen) or on its
    # implausible effects (when it is the finding); several runs only

    @property
    def plausible(self) -> bool:
        return not self.implausible


@dataclass
class Selection:
    """Outcome: the base trial, each step's options (trials) and choice, the selected names, the finding
    (an implausible best candidate) if any, and the final trial."""

    base: Trial
    steps: list[dict[str, Any]]
    selected: list[str]
    final: Trial
    finding: Trial | None = None
    mode: str = "leave-one-run-out"


def _n_params(effects: Sequence[Effect], robot) -> int:
    return sum(len(e.params(robot)) for e in effects)


Z_RANGE = 2.0  # a value is implausible when it leaves its plausible range by more than this many sigma
RANGE_P = math.erfc(Z_RANGE / math.sqrt(2.0))  # the same level for an effect's values taken together (0.0455)


def box_chi2(values: np.ndarray, cov: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[float, int]:
    """How far an effect's fitted values are from the nearest values inside their plausible box [lo, hi],
    in its covariance's metric: min over b in the box of (v - b)' C^+ (v - b) on the directions the fit
    determines (C's eigenvalues above 1e-12 of the largest), and that number of directions (0: no
    covariance). Correlated values can each lie within Z_RANGE sigma of the box and together far from it."""
    w, U = np.linalg.eigh(np.asarray(cov, float))
    keep = w > 1e-12 * max(float(w.max()), 0.0) if w.size else np.zeros(0, bool)
    if not keep.any():
        return 0.0, 0
    A = (U[:, keep] / np.sqrt(w[keep])).T
    if np.all((values >= lo) & (values <= hi)):
        return 0.0, int(keep.sum())
    from scipy.optimize import lsq_linear  # here: only for values out of their box (scipy.optimize's import ~0.2 s)

    big = 1e9 * np.maximum(np.abs(values), 1.0)
    b = lsq_linear(A, A @ values, bounds=(np.where(np.isfinite(lo), lo, -big), np.where(np.isfinite(hi), hi, big)))
    return float(np.sum((A @ (values - b.x)) ** 2)), int(keep.sum())


def _implausible(f: JointFit) -> list[Implausible]:
    """The shared values outside their plausible range by more than Z_RANGE times their 1-sigma, and every
    value outside its range of an effect whose values together are farther than that level from their
    plausible box (:func:`box_chi2`, p < RANGE_P on its determined directions; the same rule for one value)."""
    robot = f.runs[0].rows.robot
    sig = f.shared_sigmas()
    out, q = [], 0
    for e in f.shared:
        nq = len(e.params(robot))
        outside = e.implausible(robot, f.values[q:q + nq])
        alone = [v for v in outside
                 if min(abs(v.value - v.lo), abs(v.value - v.hi)) > Z_RANGE * sig.get(e.name, {}).get(
                     v.param.split(".", 1)[1], 0.0)]
        if outside and not alone:
            vals, cov, specs = f.values[q:q + nq], f.cov[q:q + nq, q:q + nq], e.params(robot)
            if isinstance(e, Projected):
                vals, cov, specs = e.full_values(robot, vals), e.covariance(cov), e.inner.params(robot)
            d2, k = box_chi2(vals, cov, np.array([s.plausible[0] for s in specs], float),
                             np.array([s.plausible[1] for s in specs], float))
            if k and chi2_sf(d2, k) < RANGE_P:
                alone = outside
        out.extend(alone)
        q += nq
    return out


def _outside(f: JointFit) -> list[str]:
    """The "effect.param" names of the shared values outside their plausible range (by value, no sigma)."""
    robot, out, q = f.runs[0].rows.robot, [], 0
    for e in f.shared:
        nq = len(e.params(robot))
        out += [v.param for v in e.implausible(robot, f.values[q:q + nq])]
        q += nq
    return out


def _starts(f: JointFit, idx: Sequence[int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Starts of a fit whose effects extend f's: each run's theta (own values, then f's shared values; the
    added effects start absent) and poses."""
    return [(f.runs[i].theta.copy(), f.runs[i].poses.copy()) for i in idx]


class Judge:
    """Fits and scores candidate sets on the runs; ``make(names)`` builds fresh effect instances;
    ``prior`` effects (a model given as prior) are in every set, first."""

    def __init__(self, items: Sequence[tuple[str, RunRows]], make: Callable[[Sequence[str]], list[Effect]],
                 prior: Sequence[Effect] = ()):
        self.items = list(items)
        self.make = make
        self.prior = list(prior)
        self.robot = self.items[0][1].robot
        from calib.selfcal import sensor_noise

        self.floor = sensor_noise(self.robot)
        self.base_sigmas: list[dict[str, np.ndarray]] | None = None

    def effects(self, names: Sequence[str]) -> list[Effect]:
        return [*self.prior, *self.make(names)]

    def fit(self, names: Sequence[str], start: JointFit | None = None, also: JointFit | None = None) -> Trial:
        """The joint fit of all runs with these effects (started from ``start``, whose effects are a prefix
        of these, and its weights; None: from the runs' rigid solves and own weights). ``also``: a fit whose
        last effect is the last of ``names`` (a pair's other member), whose values start it instead of absent."""
        eff = self.effects(names)
        if start is None:
            f = fit_runs(self.items, eff)
        else:
            starts = _starts(start, range(len(self.items)))
            if also is not None:
                nb = len(eff[-1].params(self.robot))
                starts = [(np.r_[th, rf.theta[rf.theta.shape[0] - nb:]], po)
                          for (th, po), rf in zip(starts, also.runs, strict=True)]
            f = fit_runs(self.items, eff, starts=starts, sigmas=[rf.sigma for rf in start.runs],
                         rounds=FOLD_ROUNDS, weight_iter=WEIGHT_ITER)
        fs = sum(held_out_score(rf) for rf in f.runs)
        return Trial(tuple(names), _n_params(eff, self.robot), f, fs, implausible=_implausible(f))

    def quick(self, current: JointFit, names: Sequence[str]) -> tuple[float, JointFit]:
        """Screening of adding the last of ``names`` to ``current``: the joint fit's own score
        (:func:`calib.multirun.held_out_score` of every run, in-sample) after a short fit with current's
        weights (no variance-component round), and that fit."""
        eff = self.effects(names)
        f = fit_runs(self.items, eff, starts=_starts(current, range(len(self.items))),
                     sigmas=[rf.sigma for rf in current.runs], rounds=0, max_iter=QUICK_ITER, covariance=False)
        return sum(held_out_score(rf) for rf in f.runs), f

    def judge(self, t: Trial) -> Trial:
        """Fill the trial's prediction score and folds."""
        if len(self.items) >= 2:
            self._leave_one_run_out(t)
        else:
            self._leave_one_pose_out(t)
        return t

    def _leave_one_run_out(self, t: Trial) -> None:
        t.score, t.folds = leave_one_run_out(t.fit, self.floor)

    def _leave_one_pose_out(self, t: Trial) -> None:
        rf: RunFit = t.fit.runs[0]
        sig = self.base_sigmas[0] if self.base_sigmas else rf.sigma
        res = residuals(Problem(rf.problem.model, rf.rows.meas, sig), rf.theta, rf.poses)
        pred = leave_one_pose_out(res.r, res.A, res.row, rf.poses.shape[0])
        t.score = pred.total
        t.folds = [{"pose": i + 1, "score": float(v)} for i, v in enumerate(pred.rows)]


def leave_one_run_out(f: JointFit, floor: dict[str, np.ndarray]) -> tuple[float, list[dict[str, Any]]]:
    """Linearised leave-one-run-out from the joint fit f: the shared values learned without run j (one
    Gauss-Newton step on the normal equations less run j's rows, unit-norm columns of the joint Jacobian, a
    relative ridge of 1e-9), then run j's own unknowns refitted with them frozen (least squares on its own
    columns); the figure is run j's held-out score (:func:`calib.multirun.score_of`), summed over the runs,
    and per fold the run, score, rms per channel and J. By blocks: each run's own and pose columns meet only
    its own rows, so every run's normal matrix is reduced once to the shared columns (its Schur complement)
    and fold j sums the others' (the dense joint normal matrix, (6k + p)^2 per row, is never formed)."""
    q = f.values.shape[0]
    blocks = [rf.residuals() for rf in f.runs]
    # unit-norm columns of the joint Jacobian: a run's own and pose columns from its rows, the shared from all
    shared2 = sum(np.sum(b.A[:, b.A.shape[1] - q:] ** 2, axis=0) for b in blocks) if q else np.zeros(0)
    parts = []  # per run: its scaled Jacobian, the shared block, gradient and Schur complement on the shared
    for b in blocks:
        sc = np.r_[np.linalg.norm(b.A[:, :b.A.shape[1] - q], axis=0), np.sqrt(shared2)]
        sc[sc == 0] = 1.0
        As = b.A / sc
        own = As.shape[1] - q
        N, g = As.T @ As, As.T @ b.r
        B = N[:own, :own] + 1e-9 * np.diag(np.maximum(np.diag(N)[:own], 1e-12))
        X = np.linalg.solve(B, np.c_[N[:own, own:], g[:own]])
        parts.append((As, own, N[own:, own:] - N[own:, :own] @ X[:, :q], g[own:] - N[own:, :own] @ X[:, q],
                      np.diag(N)[own:]))
    total, folds = 0.0, []
    for j, (rf, res) in enumerate(zip(f.runs, blocks, strict=True)):
        As, own = parts[j][0], parts[j][1]
        e = res.r
        if q:
            others = [p for i, p in enumerate(parts) if i != j]
            M = sum(p[2] for p in others)
            d = sum(p[4] for p in others)
            delta = -np.linalg.solve(M + 1e-9 * np.diag(np.maximum(d, 1e-12)), sum(p[3] for p in others))
            e = e + As[:, own:] @ delta
        step, *_ = np.linalg.lstsq(As[:, :own], e, rcond=1e-10)
        e = e - As[:, :own] @ step
        with np.errstate(divide="ignore", invalid="ignore"):
            unit = np.where(res.r != 0, res.si / res.r, 0.0)  # physical units per weighted unit
        phys = e * unit
        s = score_of(phys, res.channel, floor)
        rms = {c: float(np.sqrt(np.mean(phys[res.channel == c] ** 2))) for c in GROUPS if (res.channel == c).any()}
        folds.append({"run": rf.name, "score": s, "rms": rms, "J": misfit_j(rms)})
        total += s
    return total, folds


def _better_on_most(t: Trial, ref: Trial) -> bool:
    d = np.array([b["score"] - a["score"] for a, b in zip(t.folds, ref.folds, strict=True)])
    return bool((d > 0).sum() > d.size / 2)


def _choose(judge: Judge, ok: list[Trial], current: Trial, step: dict[str, Any]) -> Trial | None:
    """Among the eligible options, the best gain's confused ones (within CONFUSED of it) with the fewest
    parameters; with several runs it must also be one value on every run (:func:`calib.spread.spread` of
    the effects it adds: p >= CONSISTENT_P), else it is set aside (``step["inconsistent"]``) and the choice
    made again among the rest."""
    ok = list(ok)
    step["inconsistent"] = []
    while ok:
        top_gain = max(current.score - t.score for t in ok)
        confused = [t for t in ok if current.score - t.score >= (1.0 - CONFUSED) * top_gain]
        chosen = min(confused, key=lambda t: (t.n_params, t.score))
        if len(judge.items) >= 2:
            chosen.spread = spread(chosen.fit, range(current.fit.values.shape[0], chosen.fit.values.shape[0]))
            if chosen.spread.p < CONSISTENT_P:
                step["inconsistent"].append(chosen)
                ok.remove(chosen)
                continue
        step["chosen"] = chosen
        step["confused"] = [t.names for t in confused if t is not chosen]
        return chosen
    return None


def finding_params(t: Trial, robot) -> tuple[list[int], list[str]]:
    """The shared columns and "effect.param" names of every effect of ``t`` with a value out of its plausible
    range: what the runs' agreement on a finding is judged on (:func:`calib.spread.spread`)."""
    bad = {v.param.split(".", 1)[0] for v in t.implausible}
    cols, names, q = [], [], 0
    for e in t.fit.shared:
        specs = e.params(robot)
        if e.name in bad:
            cols += range(q, q + len(specs))
            names += [f"{e.name}.{s.name}" for s in specs]
        q += len(specs)
    return cols, names


def pair_pool(singles: Sequence[Trial]) -> list[Trial]:
    """The singles whose pairs are judged: the best PAIR_POOL by prediction, and the best plausible one if
    it is not among them (an implausible single may be taking a plausible one's part: the pair tells)."""
    ranked = sorted(singles, key=lambda t: t.score)
    top = ranked[:PAIR_POOL]
    fair = next((t for t in ranked if t.plausible), None)
    return top if fair is None or any(t is fair for t in top) else [*top, fair]


def extend_finding(judge: Judge, best: Trial, candidates: Sequence[str], current: Trial, max_effects: int,
                   step: dict[str, Any]) -> list[Trial]:
    """Is the implausible best option a description error, or an effect taking the part of one it lacks? It is
    judged with each other candidate added (while ``max_effects`` leaves room; the extensions join the step's
    options, ``step["extensions"]``): the plausible extensions whose fit converged with every value the finding
    had out of range now inside its range (the value, not within Z_RANGE sigma of it: a 1-sigma that grew with
    the added effect does not make a value physical), that predict better than it (by MIN_GAIN) and than the
    current model on most left-out runs (poses). They explain more than the finding, so taking one recommends
    nothing that explains less (what to build 8); none: the finding stands."""
    if len(best.names) + 1 > max_effects:
        return []
    ext = [judge.judge(judge.fit([*best.names, c], best.fit)) for c in candidates if c not in best.names]
    step["extensions"] = ext
    step["options"] = [*step["options"], *ext]
    return [t for t in ext if absorbs(t, best, current)]


def absorbs(t: Trial, finding: Trial, current: Trial) -> bool:
    """Does extension ``t`` of ``finding`` take its out-of-range values' part (:func:`extend_finding`)?"""
    bad = {v.param for v in finding.implausible}
    return (t.plausible and t.fit.converged and not bad & set(_outside(t.fit))
            and t.score < finding.score - MIN_GAIN and _better_on_most(t, current))


def select(judge: Judge, candidates: Sequence[str], max_effects: int = 3) -> Selection:
    """Forward selection by prediction (module doc)."""
    base = judge.judge(judge.fit([]))
    judge.base_sigmas = [rf.sigma for rf in base.fit.runs]
    current, selected, steps, finding = base, [], [], None
    while len(selected) < max_effects:
        rest = [c for c in candidates if c not in selected]
        if not rest:
            break
        quick = {c: judge.quick(current.fit, [*selected, c]) for c in rest}
        screen = sorted(rest, key=lambda c: quick[c][0])
        probe = [judge.judge(judge.fit([*selected, c], quick[c][1])) for c in screen]
        top = pair_pool(probe)
        pairs = []
        if len(selected) + 2 <= max_effects:
            for a in range(len(top)):
                for b in range(a + 1, len(top)):
                    t = judge.fit([*selected, top[a].names[-1], top[b].names[-1]], top[a].fit, top[b].fit)
                    pairs.append(judge.judge(t))
        options = probe + pairs
        step: dict[str, Any] = {"screen": screen, "options": options, "chosen": None, "current": current,
                                "confused": []}
        steps.append(step)
        best = min(options, key=lambda t: t.score)
        ok = [t for t in options if t.plausible and current.score - t.score > MIN_GAIN
              and _better_on_most(t, current)]
        margin = max(MIN_GAIN, CONFUSED * (current.score - best.score))
        if not best.plausible and current.score - best.score > MIN_GAIN and (
                not ok or min(t.score for t in ok) > best.score + margin):
            fair = extend_finding(judge, best, candidates, current, max_effects, step)
            if not fair:
                finding = best  # the option that predicts clearly best is out of its range: a finding, stop here
                if len(judge.items) >= 2:  # is it one value on every run (the robot as set up) or not?
                    finding.spread = spread(finding.fit, finding_params(finding, judge.items[0][1].robot)[0])
                break
            step["absorbed"] = best  # its out-of-range value was an effect it lacked: no finding, go on
            ok = fair
        chosen = _choose(judge, ok, current, step)
        if chosen is None:
            break
        selected = list(chosen.names)
        current = chosen
    mode = "leave-one-run-out" if len(judge.items) >= 2 else "leave-one-pose-out"
    return Selection(base, steps, selected, current, finding, mode)
