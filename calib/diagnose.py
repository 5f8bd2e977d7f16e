"""Model versus measurements: where the rigid model fails, and which physical effect is missing (issue 7).

Steps, on the equilibrium rows of a run (or any :class:`calib.selfcal.Measurements` with its noise):

1. fit the current model (zeta_0, the row poses and the effects already included) by the block-arrow LM;
   every fit also holds the devices' constant errors (load-cell bias per channel, AHRS roll/pitch bias)
   with Gaussian priors of their datasheet accuracy (``DeviceAccuracy``): a real run always has such
   errors, and without them the diagnosis would report the load cells' accuracy class as a missing effect
   (measured on 100 effect-free simulated runs: 71 flagged without the priors, 2 with them);
2. residuals in units of the noise, per channel, cable and row; chi2 with its p-value;
3. a score (Lagrange multiplier) test of every candidate effect at that solution, no refit: with the
   weighted residual r and the candidate's Jacobian columns C, after projecting out the nuisance directions
   (the row poses and theta), LM = |P_C r|^2 (P_C: projector on the span of the projected columns),
   chi2-distributed with rank(C) degrees of freedom when the effect is absent;
4. a refit of the significant candidates (and the best scores): delta chi2, likelihood-ratio p-value, AIC
   and BIC, the fitted parameters with 1-sigma uncertainty against their plausible range
   (``ParamSpec.plausible``), how much of each channel's chi2 the effect removes, and how much better the
   fit predicts equilibrium poses left out of it (:mod:`calib.prediction`);
5. candidates whose explained directions nearly coincide (each explains > 95% of what the other explains)
   are reported as indistinguishable with this data;
6. forward selection by prediction: an effect is added only when it is significant, within its plausible
   range and lowers the held-out chi2 (on most poses, where the model still does not fit with it); among
   nested candidates the one with fewer parameters wins unless the larger predicts clearly better; a
   look-ahead step tries pairs when two effects acting at once leave each one's refit short; up to
   ``max_effects``. Every candidate carries the decision and its reason.

:func:`run_rows` and :func:`effect_chain` are shared with ``cdpr solve --effects``: the refits reported
here and that command's fits are the same computation. The words, tables and plots are in
``acquisition/diagnose_report.py``.

Significance is family-wise: an effect is significant at level ``alpha`` when its likelihood-ratio p-value
is below ``alpha / number of candidates`` (Bonferroni over the library).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from calib.effects import BUILTIN, Effect, Implausible, Projected
from calib.effects.priors import DeviceAccuracy, ReferenceNoise
from calib.fitting import (
    REFIT_ITER,
    Fit,
    Residuals,
    fit,
    pose_error,
    predict_unseen,
    refit,
    residuals,
    score_basis,
    score_test,
)
from calib.prediction import LEVEL, Prediction, leave_one_pose_out
from calib.robot import Robot
from calib.runrows import run_rows
from calib.selfcal.model import CHANNELS
from calib.selfcal.problem import Measurements

OVERLAP = 0.95  # share of an explained direction another candidate must reproduce to be a confusion


@dataclass
class Candidate:
    """One candidate effect's evidence. ``score``/``score_dof``/``score_p``: the LM test at the current
    solution, ``epc``: the expected parameter change of that test (one Gauss-Newton step, as reported);
    ``delta_chi2``/``p_value``/``delta_aic``/``delta_bic``: from the refit (None when not refitted);
    ``params`` and ``params_sigma`` as fitted, ``implausible``: the fitted values outside their plausible
    ranges; ``cv_gain``: how much lower the leave-one-pose-out chi2 is with the effect (positive: it
    predicts unseen equilibrium poses better); ``channels``: share of each channel's chi2 removed;
    ``confused_with``: candidates that explain the same thing with this data; ``decision``: why it is
    recommended or rejected."""

    effect: str
    n_params: int
    score: float
    score_dof: int
    score_p: float
    epc: dict[str, float] = field(default_factory=dict)
    delta_chi2: float | None = None
    p_value: float | None = None
    delta_aic: float | None = None
    delta_bic: float | None = None
    params: dict[str, float] = field(default_factory=dict)
    params_sigma: dict[str, float] = field(default_factory=dict)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    implausible: list[Implausible] = field(default_factory=list)
    cv_chi2: float | None = None
    cv_gain: float | None = None
    cv_p: float | None = None
    adequate: bool = False
    channels: dict[str, float] = field(default_factory=dict)
    confused_with: list[str] = field(default_factory=list)
    significant: bool = False
    refit_failed: bool = False
    decision: str = ""
    refit: Fit | None = field(default=None, repr=False)
    prediction: Prediction | None = field(default=None, repr=False)
    span: np.ndarray | None = field(default=None, repr=False)
    direction: np.ndarray | None = field(default=None, repr=False)

    @property
    def plausible(self) -> bool:
        return not self.implausible

    @property
    def eligible(self) -> bool:
        """Significant, refitted, physically plausible and predicting unseen poses better; where the model
        with it still does not fit (its chi2 test rejects: the likelihood-ratio test then rests on a wrong
        model), better on most of them (one-sided signed-rank p below calib.prediction.LEVEL)."""
        return (self.significant and self.plausible and self.cv_gain is not None and self.cv_gain > 0
                and (self.adequate or (self.cv_p is not None and self.cv_p < LEVEL)))

    def to_json(self) -> dict[str, Any]:
        d = self.delta_chi2 if self.delta_chi2 is not None else self.score
        p = self.p_value if self.p_value is not None else self.score_p
        return {
            "effect": self.effect,
            "delta_chi2": float(d),
            "p_value": float(p),
            "params": {k: _num(v) for k, v in self.params.items()},
            "params_sigma": {k: _num(v) for k, v in self.params_sigma.items()},
            "plausible_range": {k: [_num(a), _num(b)] for k, (a, b) in self.bounds.items()},
            "plausible": self.plausible,
            "implausible": [str(v) for v in self.implausible],
            "score": float(self.score),
            "score_dof": int(self.score_dof),
            "score_p": float(self.score_p),
            "expected_change": {k: _num(v) for k, v in self.epc.items()},
            "refitted": self.delta_chi2 is not None,
            "refit_failed": bool(self.refit_failed),
            "delta_aic": None if self.delta_aic is None else float(self.delta_aic),
            "delta_bic": None if self.delta_bic is None else float(self.delta_bic),
            "cv_chi2": None if self.cv_chi2 is None else float(self.cv_chi2),
            "cv_gain": None if self.cv_gain is None else float(self.cv_gain),
            "cv_p": None if self.cv_p is None else float(self.cv_p),
            "significant": bool(self.significant),
            "channels": {k: float(v) for k, v in self.channels.items()},
            "confused_with": list(self.confused_with),
            "decision": self.decision,
        }


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


@dataclass
class Diagnosis:
    """Outcome of :func:`diagnose` (see the module doc). ``steps``: chi2 and the leave-one-pose-out chi2
    as effects are added one by one (names, chi2, dof, initial pose); ``reference_sample``: the run's sample
    of the reference row (None: unknown)."""

    fit: Fit
    chi2: float
    dof: int
    p_value: float
    noise_source: str
    channels: dict[str, dict[str, float]]
    cables: dict[str, list[float]]
    rows: list[dict[str, Any]]
    ranking: list[Candidate]
    selected: list[str]
    steps: list[dict[str, Any]]
    verdict: str
    alpha: float
    residual_data: Residuals
    final: Fit
    reference_sample: int | None = None
    finding: Candidate | None = None  # the implausible candidate that explains most (a description error?)

    def to_json(self) -> dict[str, Any]:
        """The `cdpr diagnose --json` object of spec/cli.md (plus extra keys)."""
        return {
            "chi2": float(self.chi2),
            "dof": int(self.dof),
            "noise": self.noise_source,
            "p_value": float(self.p_value),
            "channels": {c: {k: (int(v) if k == "n" else float(v)) for k, v in d.items()}
                         for c, d in self.channels.items()},
            "cables": {c: [float(v) for v in vals] for c, vals in self.cables.items()},
            "rows": self.rows,
            "ranking": [c.to_json() for c in self.ranking],
            "selected": list(self.selected),
            "steps": self.steps,
            "verdict": self.verdict,
            "alpha": self.alpha,
            "device_errors": {k: _num(v) for k, v in self.fit.params().get("device_accuracy", {}).items()},
            "finding": None if self.finding is None else {
                "effect": self.finding.effect, "params": {k: _num(v) for k, v in self.finding.params.items()},
                "implausible": [str(v) for v in self.finding.implausible]},
        }


def _channel_tables(res: Residuals, n: int, meas: Measurements, ref_sample: int | None = None
                    ) -> tuple[dict, dict, list]:
    channels, cables = {}, {}
    for c in CHANNELS:
        m = res.channel == c
        if not m.any():
            continue
        z = res.r[m]
        channels[c] = {
            "rms": float(np.sqrt(np.mean(res.si[m] ** 2))),
            "rms_normalized": float(np.sqrt(np.mean(z**2))),
            "max_normalized": float(np.abs(z).max()),
            "chi2": float(z @ z),
            "n": int(m.sum()),
        }
        width = 3 if c == "orientation" else n
        cables[c] = [
            float(np.sqrt(np.mean(res.r[m & (res.index == a)] ** 2))) if (m & (res.index == a)).any() else 0.0
            for a in range(width)
        ]
    rows = []
    for i in sorted(set(res.row.tolist()) - {-2}):
        m = res.row == i
        z = res.r[m]
        worst = int(np.argmax(np.abs(z)))
        if i >= 0:
            sample = int(meas.samples[i]) if meas.samples is not None else -1
        else:
            sample = -1 if ref_sample is None else int(ref_sample)
        entry = {
            "row": int(i),
            "label": "reference pose" if i < 0 else f"pose {i + 1}",
            "sample": sample,
            "rms_normalized": float(np.sqrt(np.mean(z**2))),
            "max_normalized": float(np.abs(z).max()),
            "chi2": float(z @ z),
            "worst": f"{res.channel[m][worst]}[{int(res.index[m][worst]) + 1}]",
        }
        if i >= 0 and meas.windows is not None:
            entry["window"] = [int(v) for v in meas.windows[i]]
        # per cable, the way it moved (+1 out, -1 in) and its load changed (+1 up, -1 down) into the window
        for key, rows_dir, ref_dir in (("approach", meas.approach, meas.ref_approach),
                                       ("load_approach", meas.load_approach, meas.ref_load_approach)):
            d = ref_dir if i < 0 else (None if rows_dir is None else rows_dir[i])
            if d is not None:
                entry[key] = [int(v) for v in d]
        rows.append(entry)
    return channels, cables, rows


def _bounds(effect: Effect, robot: Robot) -> dict[str, tuple[float, float]]:
    inner = effect.inner if isinstance(effect, Projected) else effect
    return {s.name: s.plausible for s in inner.params(robot) if np.isfinite(s.plausible).any()}


def _rank_round(fit0: Fit, pred0: Prediction, candidates: Sequence[Effect], alpha: float, alpha_each: float,
                refits: int) -> list[Candidate]:
    """Score tests of every candidate at fit0; refits (with their leave-one-pose-out chi2) of the
    significant ones and of the ``refits`` best scores; ordered: eligible first by predictive gain, then
    the other refitted ones by AIC, then those only scored."""
    base = residuals(fit0.problem, fit0.theta, fit0.poses)
    basis = score_basis(base)
    m = base.r.shape[0]
    robot = fit0.model.robot
    out: list[Candidate] = []
    for eff in candidates:
        sc = score_test(fit0, eff, basis)
        p = float(stats.chi2.sf(sc.lm, sc.dof)) if sc.dof > 0 else 1.0
        out.append(Candidate(eff.name, len(eff.params(robot)), sc.lm, sc.dof, p, span=sc.span,
                             direction=sc.direction, bounds=_bounds(eff, robot),
                             epc=eff.report(robot, sc.values) if sc.dof > 0 else {}))
    by_score = sorted(range(len(out)), key=lambda i: (out[i].score_p, -out[i].score))
    chosen = [i for i in by_score if out[i].score_dof > 0][: max(refits, 0)]
    chosen += [i for i in by_score if out[i].score_p < alpha_each and i not in chosen and out[i].score_dof > 0]
    per_channel0 = {c: float(np.sum(base.r[base.channel == c] ** 2)) for c in CHANNELS}
    for i in chosen:
        cand = out[i]
        eff = candidates[i]
        f1 = refit(fit0, eff, REFIT_ITER)
        d = fit0.chi2 - f1.chi2
        q = cand.score_dof
        cand.refit = f1
        cand.delta_chi2 = d
        cand.p_value = float(stats.chi2.sf(max(d, 0.0), q))
        cand.delta_aic = d - 2 * q
        cand.delta_bic = d - q * math.log(max(m, 2))
        cand.params = f1.params()[eff.name]
        cand.params_sigma = f1.param_sigmas()[eff.name]
        used = f1.effects[-1]
        cand.implausible = used.implausible(robot, f1.theta[f1.model.slices[-1]])
        r1 = residuals(f1.problem, f1.theta, f1.poses)
        cand.prediction = leave_one_pose_out(r1.r, r1.A, r1.row, f1.poses.shape[0])
        cand.cv_chi2 = cand.prediction.total
        cand.cv_gain = cand.prediction.gain_over(pred0)
        cand.cv_p = cand.prediction.better_p(pred0)
        cand.adequate = bool(stats.chi2.sf(f1.chi2, max(f1.dof, 1)) >= alpha)
        cand.channels = {
            c: (per_channel0[c] - float(np.sum(r1.r[r1.channel == c] ** 2))) / per_channel0[c]
            for c in CHANNELS if per_channel0[c] > 0
        }
        # a refit that recovers almost nothing of a large score failed to move (an ill-conditioned start)
        cand.refit_failed = (not f1.converged) or (cand.score > 25.0 and d < 0.1 * cand.score)
        cand.significant = cand.p_value < alpha_each and not cand.refit_failed
    for a in out:
        if a.score_dof == 0 or np.linalg.norm(a.direction) == 0:
            continue
        for b in out:
            if a is b or b.score_dof == 0 or np.linalg.norm(b.direction) == 0:
                continue
            ab = np.linalg.norm(b.span.T @ a.direction)
            ba = np.linalg.norm(a.span.T @ b.direction)
            if ab > OVERLAP and ba > OVERLAP:
                a.confused_with.append(b.effect)
    for c in out:
        c.decision = _rejection(c, alpha_each)

    def key(c: Candidate):
        if c.eligible:
            return (0, -c.cv_gain)
        if c.delta_chi2 is not None and not c.refit_failed:
            return (1, -c.delta_aic)
        if c.delta_chi2 is None:
            return (2, c.score_p)
        return (3, -c.delta_aic)

    return sorted(out, key=key)


def _rejection(c: Candidate, alpha_each: float) -> str:
    """Why a candidate is not (yet) recommended, in words; empty when it is eligible."""
    if c.score_dof == 0:
        return "rejected: this data cannot observe it"
    if c.delta_chi2 is None:
        return f"rejected: not significant (score test p = {c.score_p:.2g}, needs < {alpha_each:.2g})"
    if c.refit_failed:
        return (f"rejected: its refit did not converge in {REFIT_ITER} iterations" if not c.refit.converged
                else "rejected: its refit did not move (ill-conditioned)")
    if not c.significant:
        return f"rejected: not significant (p = {c.p_value:.2g}, needs < {alpha_each:.2g})"
    if not c.plausible:
        return "rejected: implausibly large (" + "; ".join(str(v) for v in c.implausible[:3]) + ")"
    if c.cv_gain is not None and c.cv_gain <= 0:
        return (f"rejected: does not predict left-out poses better (cross-validated chi2 "
                f"{c.cv_chi2:.1f}, {-c.cv_gain:+.1f})")
    if not c.adequate and c.cv_p is not None and c.cv_p >= LEVEL:
        return (f"rejected: the model still does not fit with it, and it predicts some left-out poses better, "
                f"others worse (cross-validated chi2 {c.cv_gain:.1f} lower in sum, signed-rank p = {c.cv_p:.2g} "
                f">= {LEVEL:g})")
    return ""


def _nested(small: Candidate, large: Candidate) -> bool:
    """The smaller candidate's explained direction lies in the larger one's span."""
    u = small.direction
    return u is not None and large.span is not None and float(np.linalg.norm(large.span.T @ u)) > OVERLAP


def choose(ranked: list[Candidate]) -> Candidate | None:
    """The candidate to add: among the eligible ones the best predictor of left-out poses, unless one with
    fewer observable parameters explains the same directions (its direction lies in the best one's span)
    and the best one does not predict clearly better (:meth:`Prediction.clearly_better_than`)."""
    ok = [c for c in ranked if c.eligible]
    if not ok:
        return None
    best = max(ok, key=lambda c: c.cv_gain)
    simpler = [c for c in ok if c.score_dof < best.score_dof and _nested(c, best)
               and not best.prediction.clearly_better_than(c.prediction)]
    if simpler:
        pick = min(simpler, key=lambda c: (c.score_dof, -c.cv_gain))
        best.decision = (f"rejected: {pick.effect} ({pick.score_dof} parameter(s)) explains the same misfit and "
                         f"{best.effect} ({best.score_dof}) does not predict left-out poses clearly better")
        best = pick
    for c in ok:
        if c is not best and not c.decision:
            c.decision = f"not added: {best.effect} predicts left-out poses better"
    return best


def diagnose(
    robot: Robot,
    meas: Measurements,
    sigma: dict[str, np.ndarray],
    theta0: np.ndarray,
    poses0: np.ndarray,
    candidates: Sequence[Effect] | None = None,
    included: Sequence[Effect] = (),
    alpha: float = 0.01,
    refits: int = 3,
    max_effects: int = 2,
    noise_source: str = "given",
    reference_pose: np.ndarray | None = None,
    device_priors: bool = True,
    reference_sample: int | None = None,
) -> Diagnosis:
    """Fit, locate the misfit and rank the candidate effects (module doc). theta0/poses0: initial guess.
    With ``device_priors`` every fit holds the devices' constant errors within their datasheet accuracy
    (:class:`calib.effects.priors.DeviceAccuracy`), so an effect must exceed those to be reported."""
    if candidates is None:
        candidates = [cls() for cls in BUILTIN.values()]
    if device_priors and not any(isinstance(e, DeviceAccuracy) for e in included):
        included = [DeviceAccuracy(), *included]
    inc_names = {e.name for e in included}
    cands = [c for c in candidates if c.name not in inc_names]
    alpha_each = alpha / max(len(cands), 1)
    fit0 = fit(robot, meas, sigma, list(included), theta0, poses0)
    pred0 = predict_unseen(fit0)
    res0 = residuals(fit0.problem, fit0.theta, fit0.poses, jacobian=False)
    channels, cables, rows = _channel_tables(res0, robot.n, meas, reference_sample)
    ranking = _rank_round(fit0, pred0, cands, alpha, alpha_each, refits)
    first = {c.effect: c for c in ranking}
    steps = [_step(fit0, pred0, reference_pose)]
    selected: list[str] = []
    current, rank_now = fit0, ranking
    pred_now = pred0
    finding: Candidate | None = None
    while len(selected) < max_effects and rank_now:
        finding = implausible_finding(rank_now)
        if finding is not None:  # what explains most is out of its range: a finding, nothing that explains less
            finding.decision = ("FINDING: explains the most (delta chi2 " f"{finding.delta_chi2:.1f}) only with "
                                + "; ".join(str(v) for v in finding.implausible[:3])
                                + ": a likely error in the robot description or the setup")
            for c in rank_now:
                if c is not finding and c.eligible:
                    c.decision = f"not added: it explains less than {finding.effect}, whose value is a finding"
            break
        best = choose(rank_now)
        if best is None:
            if len(selected) + 2 > max_effects:
                break
            pair = _pair_step(current, pred_now, rank_now, {e.name: e for e in cands}, alpha, alpha_each)
            if pair is None:
                break
            (a, b), f2, pred2 = pair
            for c, f, pr in ((a, a.refit, a.prediction), (b, f2, pred2)):
                selected.append(c.effect)
                first[c.effect].decision = (
                    f"recommended (step {len(selected)}, with {b.effect if c is a else a.effect}): neither alone "
                    f"explains the misfit; together significant, within their plausible ranges, and predicting "
                    f"left-out poses better (cross-validated chi2 {pred2.gain_over(pred_now):+.1f} lower)")
                steps.append(_step(f, pr, reference_pose))
            current, pred_now = f2, pred2
        else:
            selected.append(best.effect)
            first[best.effect].decision = (f"recommended (step {len(selected)}): significant, within its "
                                           f"plausible range, predicts left-out poses better (cross-validated "
                                           f"chi2 {best.cv_gain:+.1f} lower)")
            current, pred_now = best.refit, best.prediction
            steps.append(_step(current, pred_now, reference_pose))
        rest = [c for c in cands if c.name not in selected]
        if not rest or len(selected) >= max_effects:
            break
        rank_now = _rank_round(current, pred_now, rest, alpha, alpha_each, min(refits, 2))
    p_fit = float(stats.chi2.sf(fit0.chi2, max(fit0.dof, 1)))
    more = bool(selected) and len(selected) >= max_effects and any(
        c.eligible for c in rank_now if c.effect not in selected)
    diag = Diagnosis(fit0, fit0.chi2, fit0.dof, p_fit, noise_source, channels, cables, rows, ranking, selected,
                     steps, "", alpha, res0, current, reference_sample, finding)
    diag.verdict = _verdict(diag, more)
    return diag


PAIR_POOL = 3  # candidates whose pairs the look-ahead step refits together


def _pair_step(current: Fit, pred_now: Prediction, ranked: list[Candidate], effects: dict[str, Effect],
               alpha: float, alpha_each: float) -> tuple[tuple[Candidate, Candidate], Fit, Prediction] | None:
    """One look-ahead step, when no single candidate qualifies: two effects acting at once leave each
    one's refit short of a fit. The pairs of the best PAIR_POOL candidates that are significant, plausible
    and lower the held-out chi2 are refitted together (the first's refit, then the second added); a pair
    qualifies like a single candidate (significant jointly, both plausible, lower held-out chi2, and the
    model fits with it or it predicts most left-out poses better). Returns the best pair by predictive
    gain, its fit and prediction, or None."""
    pool = sorted((c for c in ranked if c.significant and c.plausible and c.cv_gain is not None
                   and c.cv_gain > 0 and c.refit is not None), key=lambda c: -c.cv_gain)[:PAIR_POOL]
    best = None
    for i, a in enumerate(pool):
        for b in pool[i + 1:]:
            f2 = refit(a.refit, effects[b.effect], REFIT_ITER)
            if not f2.converged or any(e.implausible(f2.model.robot, f2.theta[sl])
                                       for e, sl in zip(f2.effects, f2.model.slices, strict=True)):
                continue
            q = a.score_dof + b.score_dof
            if stats.chi2.sf(max(current.chi2 - f2.chi2, 0.0), q) >= alpha_each:
                continue
            pred2 = predict_unseen(f2)
            gain = pred2.gain_over(pred_now)
            adequate = stats.chi2.sf(f2.chi2, max(f2.dof, 1)) >= alpha
            if gain > 0 and (adequate or pred2.better_p(pred_now) < LEVEL) and (best is None or gain > best[3]):
                best = ((a, b), f2, pred2, gain)
    return None if best is None else best[:3]


def _step(f: Fit, pred: Prediction, reference_pose: np.ndarray | None = None) -> dict[str, Any]:
    base = (DeviceAccuracy.name, ReferenceNoise.name)
    out = {"effects": [n for n in f.names if n not in base], "chi2": float(f.chi2), "dof": int(f.dof),
           "cv_chi2": pred.total, "converged": bool(f.converged),
           "initial_pose": [float(v) for v in f.theta[:6]],
           "params": {e: {k: _num(v) for k, v in p.items()} for e, p in f.params().items()}}
    if reference_pose is not None:
        out["eps_p"] = pose_error(f.theta, reference_pose)
    return out


def misfit_location(diag: Diagnosis, top: int = 2) -> dict[str, list[str]]:
    """Where the misfit sits: the channels by share of chi2, in each the cables (components) with the
    largest rms, and the rows (poses) with the largest chi2, named."""
    tot = sum(d["chi2"] for d in diag.channels.values()) or 1.0
    chans = sorted(diag.channels, key=lambda c: -diag.channels[c]["chi2"])
    names = {"orientation": ("roll", "pitch", "yaw")}
    out_ch, out_cab = [], []
    for c in chans[:top]:
        out_ch.append(f"{c} ({100 * diag.channels[c]['chi2'] / tot:.0f}% of chi2)")
        vals = diag.cables.get(c, [])
        worst = np.argsort(vals)[::-1][:top]
        label = names.get(c, [f"cable {i + 1}" for i in range(len(vals))])
        out_cab += [f"{c} {label[j]} (rms {vals[j]:.1f} sigma)" for j in worst]
    rows = sorted(diag.rows, key=lambda r: -r["chi2"])[:top + 1]
    out_rows = [f"{r['label']}" + (f" (sample {r['sample']})" if r["sample"] >= 0 else "")
                + f": worst {r['worst']}, rms {r['rms_normalized']:.1f} sigma" for r in rows]
    return {"channels": out_ch, "cables": out_cab, "rows": out_rows}


FINDING_RATIO = 1.5  # an implausible candidate explaining this many times the best plausible one's delta chi2


def implausible_finding(ranked: list[Candidate]) -> Candidate | None:
    """The significant candidate that explains the most (largest delta chi2) when it lies outside its
    plausible range and explains clearly more (FINDING_RATIO) than any eligible one and predicts left-out
    poses better than them: a finding (a likely error in the robot description or the setup), not a reason
    to recommend the next one."""
    fitted = [c for c in ranked if c.delta_chi2 is not None and c.significant and c.cv_gain is not None]
    if not fitted:
        return None
    top = max(fitted, key=lambda c: c.delta_chi2)
    if top.plausible or top.cv_gain <= 0:
        return None
    ok = [c for c in ranked if c.eligible]
    if any(c.delta_chi2 * FINDING_RATIO > top.delta_chi2 or c.cv_gain >= top.cv_gain for c in ok):
        return None
    return top


def _verdict(diag: Diagnosis, more: bool = False) -> str:
    text = _verdict_text(diag, more)
    f = diag.finding
    if f is None:
        return text
    lead = (f"FINDING: {f.effect} explains the most (delta chi2 {f.delta_chi2:.1f}, predicting left-out poses "
            f"better by {f.cv_gain:.1f}) with " + "; ".join(str(v) for v in f.implausible[:3])
            + ": likely an error in the robot description or the setup (check it); nothing that explains less is "
            "recommended in its place")
    return lead + (f"; {text}" if diag.selected else "")


def _verdict_text(diag: Diagnosis, more: bool = False) -> str:
    fit0, ranking, selected, final, alpha = diag.fit, diag.ranking, diag.selected, diag.final, diag.alpha
    dof = max(fit0.dof, 1)
    excess = fit0.chi2 - dof
    p0 = stats.chi2.sf(fit0.chi2, dof)
    if p0 >= alpha and not selected:
        return (f"the model fits within the noise (chi2 {fit0.chi2:.1f} on {dof} dof, p = {p0:.2g}); "
                f"no effect in the library is significant at the {alpha:g} level")
    where = misfit_location(diag)
    loc = f"the misfit sits in {', '.join(where['channels'])}; worst at {'; '.join(where['rows'][:2])}"
    implausible = [c for c in ranking if c.significant and not c.plausible]
    if not selected:
        text = f"the model does not fit (chi2 {fit0.chi2:.1f} on {dof} dof, p = {p0:.2g}): {loc}. "
        if implausible:
            c = implausible[0]
            text += (f"{c.effect} would explain {100 * min(1.0, c.delta_chi2 / excess):.0f}% of the excess only "
                     f"with {c.implausible[0]}, implausibly large: something outside the library acts there")
        else:
            text += "nothing in the library explains it and predicts left-out poses better: look for an effect "
            text += "outside it"
        return text
    first = next(c for c in ranking if c.effect == selected[0])
    share = first.delta_chi2 / excess if excess > 0 else 1.0
    if excess > 0:
        text = f"{first.effect} explains {100.0 * min(1.0, share):.0f}% of the excess"
    else:
        text = (f"{first.effect} explains a significant part (delta chi2 {first.delta_chi2:.1f}, p = "
                f"{first.p_value:.2g}) although chi2 is within the noise")
    if first.confused_with:
        text += f" (cannot be told apart from {', '.join(first.confused_with)} with this data)"
    text += f"; refit with --effects {','.join(selected)}"
    pf = stats.chi2.sf(final.chi2, max(final.dof, 1))
    if pf < alpha:
        left = final.chi2 - max(final.dof, 1)
        pct = f"{100.0 * left / excess:.0f}% of the excess" if excess > 0 else "part of the misfit"
        text += f"; chi2 {final.chi2:.1f} on {final.dof} dof remains (p = {pf:.2g}): {pct} is not explained"
        text += f" by {', '.join(selected)}"
        if more:
            text += " (other library effects still predict better: raise --max-effects"
            text += ", but no single one explains most of the misfit: it may lie outside the library)" if (
                share < PARTIAL) else ")"
        elif share < PARTIAL:
            text += (" nor by anything else in the library that predicts left-out poses better: no single effect"
                     " explains most of the misfit, it may lie outside the library")
        elif implausible:
            c = implausible[0]
            text += (f"; {c.effect} would take more only with {c.implausible[0]}, implausibly large: something "
                     "outside the library acts there")
        else:
            text += " nor by anything else in the library that predicts left-out poses better"
    elif share < PARTIAL and len(selected) > 1:
        text += f" (no single effect explains most of the misfit: {first.effect} alone {100.0 * share:.0f}%)"
    return text


PARTIAL = 0.9  # a single effect explaining less than this share of the excess only explains part of it


def diagnose_run(
    run: Any,
    noise: str = "estimate",
    candidates: Sequence[Effect] | None = None,
    included: Sequence[Effect] = (),
    alpha: float = 0.01,
    max_effects: int = 2,
    reference_pose: np.ndarray | None = None,
) -> Diagnosis:
    """:func:`diagnose` on the equilibrium windows of a run (``acquisition.runlog.Run``), rows and noise
    from :func:`run_rows` (method tlse)."""
    rows = run_rows(run, noise)
    sol = rows.solution
    if rows.reference is not None:  # the base model of base_fit: devices, the reference's noise, the included
        included = [rows.reference, *included]
    return diagnose(rows.robot, rows.meas, rows.sigma, sol.theta[:6], sol.poses, candidates, included, alpha,
                    max_effects=max_effects, noise_source=rows.source, reference_pose=reference_pose,
                    reference_sample=sol.reference_sample)
