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
here and that command's fits are the same computation (:mod:`calib.runrows`). The fit machinery is
:mod:`calib.fitting`, each candidate's evidence :mod:`calib.evidence`; the diagnosis returns reason codes and
numbers (:class:`calib.evidence.Reason`, :class:`Verdict`), whose words are :mod:`calib.diagnose_words`; the
tables and plots are in ``acquisition/diagnose_report.py``.

Significance is family-wise: an effect is significant at level ``alpha`` when its likelihood-ratio p-value
is below ``alpha / number of candidates`` (Bonferroni over the library).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy import optimize, stats

from calib.effects import BUILTIN, Effect
from calib.effects.priors import DeviceAccuracy, ReferenceNoise
from calib.evidence import OVERLAP, Candidate, Reason, _num, _rank_round
from calib.fitting import (
    REFIT_ITER,
    Fit,
    Residuals,
    fit,
    pose_error,
    predict_unseen,
    refit,
    residuals,
)
from calib.prediction import LEVEL, Prediction
from calib.robot import Robot
from calib.runrows import run_rows
from calib.selfcal.model import CHANNELS
from calib.selfcal.problem import Measurements


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
    outcome: Verdict | None
    alpha: float
    residual_data: Residuals
    final: Fit
    reference_sample: int | None = None
    finding: Candidate | None = None  # the implausible candidate that explains most (a description error?)

    @property
    def verdict(self) -> str:
        """The outcome in words (:func:`calib.diagnose_words.verdict_text`)."""
        from calib.diagnose_words import verdict_text

        return verdict_text(self)

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
        best.reason = Reason("simpler_explains", {"simpler": pick.effect, "simpler_dof": pick.score_dof})
        best = pick
    for c in ok:
        if c is not best and c.reason is None:
            c.reason = Reason("better_candidate", {"better": best.effect})
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
    with_detectable_size(ranking, {e.name: e for e in cands}, robot, alpha_each)
    first = {c.effect: c for c in ranking}
    steps = [_step(fit0, pred0, reference_pose)]
    selected: list[str] = []
    current, rank_now = fit0, ranking
    pred_now = pred0
    finding: Candidate | None = None
    while len(selected) < max_effects and rank_now:
        finding = implausible_finding(rank_now)
        if finding is not None:  # what explains most is out of its range: a finding, nothing that explains less
            finding.reason = Reason("finding")
            for c in rank_now:
                if c is not finding and c.eligible:
                    c.reason = Reason("below_finding", {"finding": finding.effect})
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
                first[c.effect].reason = Reason("recommended_pair", {
                    "step": len(selected), "partner": b.effect if c is a else a.effect,
                    "cv_gain": pred2.gain_over(pred_now)})
                steps.append(_step(f, pr, reference_pose))
            current, pred_now = f2, pred2
        else:
            selected.append(best.effect)
            first[best.effect].reason = Reason("recommended", {"step": len(selected), "cv_gain": best.cv_gain})
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
                     steps, None, alpha, res0, current, reference_sample, finding)
    diag.outcome = verdict_of(diag, more)
    return diag


DETECT_POWER = 0.8  # the probability with which the score test finds an effect of the detectable size


def detectable_factor(score: float, dof: int, alpha_each: float, power: float = DETECT_POWER) -> float:
    """How many times its expected change an effect of the same shape must be for the score test to find it
    with probability ``power`` at level ``alpha_each``: Baarda's minimal detectable bias along that
    direction, sqrt(lambda0 / score), lambda0 the noncentrality with P(chi2(dof, lambda0) > the test's
    critical value) = power. The expected change is one Gauss-Newton step, whose noncentrality is the
    score, and the noncentrality grows as the square of the effect's size. inf without a score."""
    if score <= 0 or dof <= 0:
        return math.inf
    crit = stats.chi2.isf(alpha_each, dof)
    lam = optimize.brentq(lambda v: stats.ncx2.sf(crit, dof, v) - power, 1e-9, 1e6)
    return math.sqrt(lam / score)


def with_detectable_size(ranked: list[Candidate], effects: dict[str, Effect], robot: Robot, alpha_each: float,
                         power: float = DETECT_POWER) -> None:
    """Give every candidate rejected by its score test the size this data would find with probability
    ``power`` (:func:`detectable_factor` times its expected change: ``detectable``, name -> (value, unit) of
    the effect's own parameters, empty where the change is reported in others), into its reason's numbers: a
    run that cannot see an effect says from what size it would (issue 28: sc_8_final alone sees a length
    scale of the shape it carries only from k = 0.8-1.5 %)."""
    for c in ranked:
        if c.reason is None or c.reason.code != "score_not_significant" or c.effect not in effects:
            continue
        factor = detectable_factor(c.score, c.score_dof, alpha_each, power)
        specs = effects[c.effect].params(robot)
        size: dict[str, tuple[float, str]] = {}
        if math.isfinite(factor) and all(sp.name in c.epc for sp in specs):
            size = {sp.name: (float(sp.absent + factor * (c.epc[sp.name] - sp.absent)), sp.unit) for sp in specs}
        c.reason = replace(c.reason, numbers={**c.reason.numbers, "detect_factor": factor, "detect_power": power,
                                              "detectable": size})


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


@dataclass(frozen=True)
class Verdict:
    """What the diagnosis concludes, in numbers and names; :func:`calib.diagnose_words.verdict_text` says it.

    ``code``: 'fits' (the model fits within the noise, nothing selected), 'unexplained' (it does not fit and
    nothing in the library explains it), 'implausible' (it does not fit and ``implausible`` would explain it
    only outside its plausible range), 'explained' (``first`` and the rest of ``selected`` explain it and the
    final model fits), 'explained_partly' (the final model still does not fit). ``chi2``, ``dof``, ``p``: the
    base fit's test (dof at least 1), ``excess`` = chi2 - dof; ``share``: the first selected effect's delta
    chi2 over the excess (1 when there is none); ``final_chi2``, ``final_dof``, ``final_p``: the final fit's;
    ``more``: other eligible effects remain after ``max_effects``; ``partial``: ``share`` below PARTIAL;
    ``finding``: the implausible candidate that explains most, said first."""

    code: str
    chi2: float
    dof: int
    p: float
    alpha: float
    excess: float
    selected: tuple[str, ...] = ()
    first: Candidate | None = None
    share: float = 1.0
    final_chi2: float = math.nan
    final_dof: int = 0
    final_p: float = math.nan
    more: bool = False
    partial: bool = False
    implausible: Candidate | None = None
    finding: Candidate | None = None


def verdict_of(diag: Diagnosis, more: bool = False) -> Verdict:
    """The :class:`Verdict` of a diagnosis; ``more``: eligible effects remain beyond ``max_effects``."""
    fit0, ranking, selected, final, alpha = diag.fit, diag.ranking, diag.selected, diag.final, diag.alpha
    dof = max(fit0.dof, 1)
    excess = fit0.chi2 - dof
    p0 = float(stats.chi2.sf(fit0.chi2, dof))
    implausible = next((c for c in ranking if c.significant and not c.plausible), None)
    base = {"chi2": fit0.chi2, "dof": dof, "p": p0, "alpha": alpha, "excess": excess, "finding": diag.finding,
            "implausible": implausible, "selected": tuple(selected)}
    if p0 >= alpha and not selected:
        return Verdict("fits", **base)
    if not selected:
        return Verdict("implausible" if implausible is not None else "unexplained", **base)
    first = next(c for c in ranking if c.effect == selected[0])
    share = first.delta_chi2 / excess if excess > 0 else 1.0
    pf = float(stats.chi2.sf(final.chi2, max(final.dof, 1)))
    return Verdict("explained_partly" if pf < alpha else "explained", **base, first=first, share=share,
                   final_chi2=final.chi2, final_dof=final.dof, final_p=pf, more=more, partial=share < PARTIAL)


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
