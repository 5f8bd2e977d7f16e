"""The evidence for each candidate effect at a fit (steps 3-5 of :mod:`calib.diagnose`): its score test, the
refit of the significant ones (delta chi2, likelihood-ratio p, AIC, BIC, fitted values against their plausible
range, the share of each channel's chi2 it removes, how much better it predicts left-out poses), which
candidates this data cannot tell apart, and why a candidate is not eligible (:class:`Reason`, a code and its
numbers; the words are :mod:`calib.diagnose_words`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from calib.effects import Effect, Implausible, Projected
from calib.fitting import REFIT_ITER, Fit, refit, residuals, score_basis, score_test
from calib.prediction import LEVEL, Prediction, leave_one_pose_out
from calib.robot import Robot
from calib.selfcal.model import CHANNELS

OVERLAP = 0.95  # share of an explained direction another candidate must reproduce to be a confusion


@dataclass(frozen=True)
class Reason:
    """Why a candidate is where the diagnosis left it: a ``code`` (:data:`REASONS`) and the numbers and names
    that code quotes (``numbers``), beside the candidate's own evidence; the words are
    :func:`calib.diagnose_words.decision_text`'s."""

    code: str
    numbers: dict[str, Any] = field(default_factory=dict)


REASONS = (
    "unobservable",  # this data cannot observe it
    "score_not_significant",  # score test p >= alpha_each: not refitted
    "refit_not_converged",  # its refit did not converge in REFIT_ITER iterations
    "refit_stuck",  # its refit did not move (ill-conditioned)
    "not_significant",  # likelihood-ratio p >= alpha_each
    "implausible",  # fitted outside its plausible range
    "predicts_worse",  # the leave-one-pose-out chi2 is not lower with it
    "mixed_prediction",  # the model still does not fit, and it predicts some left-out poses better, others worse
    "simpler_explains",  # a candidate with fewer parameters explains the same and predicts about as well
    "better_candidate",  # eligible, but another predicts left-out poses better
    "finding",  # explains the most only outside its plausible range: a likely description or setup error
    "below_finding",  # eligible, but explains less than the finding
    "recommended",  # added at step ``step``
    "recommended_pair",  # added at step ``step`` together with ``partner``
)


@dataclass
class Candidate:
    """One candidate effect's evidence. ``score``/``score_dof``/``score_p``: the LM test at the current
    solution, ``epc``: the expected parameter change of that test (one Gauss-Newton step, as reported);
    ``delta_chi2``/``p_value``/``delta_aic``/``delta_bic``: from the refit (None when not refitted);
    ``params`` and ``params_sigma`` as fitted, ``implausible``: the fitted values outside their plausible
    ranges; ``cv_gain``: how much lower the leave-one-pose-out chi2 is with the effect (positive: it
    predicts unseen equilibrium poses better); ``channels``: share of each channel's chi2 removed;
    ``confused_with``: candidates that explain the same thing with this data; ``reason``: why it is
    recommended or rejected (:class:`Reason`; ``decision`` says it in words)."""

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
    reason: Reason | None = None  # why it is recommended, rejected or not added (None: eligible, undecided)
    refit: Fit | None = field(default=None, repr=False)
    prediction: Prediction | None = field(default=None, repr=False)
    span: np.ndarray | None = field(default=None, repr=False)
    direction: np.ndarray | None = field(default=None, repr=False)

    @property
    def plausible(self) -> bool:
        return not self.implausible

    @property
    def decision(self) -> str:
        """The reason in words (:func:`calib.diagnose_words.decision_text`)."""
        from calib.diagnose_words import decision_text

        return decision_text(self)

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
        c.reason = rejection(c, alpha_each)

    def key(c: Candidate):
        if c.eligible:
            return (0, -c.cv_gain)
        if c.delta_chi2 is not None and not c.refit_failed:
            return (1, -c.delta_aic)
        if c.delta_chi2 is None:
            return (2, c.score_p)
        return (3, -c.delta_aic)

    return sorted(out, key=key)


def rejection(c: Candidate, alpha_each: float) -> Reason | None:
    """Why a candidate is not (yet) recommended; None when it is eligible."""
    if c.score_dof == 0:
        return Reason("unobservable")
    if c.delta_chi2 is None:
        return Reason("score_not_significant", {"alpha_each": alpha_each})
    if c.refit_failed:
        return (Reason("refit_not_converged", {"iterations": REFIT_ITER}) if not c.refit.converged
                else Reason("refit_stuck"))
    if not c.significant:
        return Reason("not_significant", {"alpha_each": alpha_each})
    if not c.plausible:
        return Reason("implausible")
    if c.cv_gain is not None and c.cv_gain <= 0:
        return Reason("predicts_worse")
    if not c.adequate and c.cv_p is not None and c.cv_p >= LEVEL:
        return Reason("mixed_prediction", {"level": LEVEL})
    return None
