"""The diagnosis in words (as lmfit keeps its reports in printfuncs.py): each candidate's decision from its
:class:`calib.evidence.Reason`, the verdict from the :class:`calib.diagnose.Verdict`, and where the misfit sits.
Nothing here computes a statistic: the numbers are the diagnosis's (:mod:`calib.diagnose`, :mod:`calib.evidence`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

# the diagnosis's objects come in as they are (calib.evidence.Candidate, calib.diagnose.Diagnosis): this module
# imports neither, so that their properties (Candidate.decision, Diagnosis.verdict) can import it
Candidate = Diagnosis = Any


def decision_text(c: Candidate) -> str:
    """Why ``c`` is recommended, rejected or not added, in one clause ('' while it is eligible)."""
    if c.reason is None:
        return ""
    code, n = c.reason.code, c.reason.numbers
    if code == "unobservable":
        return "rejected: this data cannot observe it"
    if code == "score_not_significant":
        return (f"rejected: not significant (score test p = {c.score_p:.2g}, needs < {n['alpha_each']:.2g})"
                + detectable_text(n))
    if code == "refit_not_converged":
        return f"rejected: its refit did not converge in {n['iterations']} iterations"
    if code == "refit_stuck":
        return "rejected: its refit did not move (ill-conditioned)"
    if code == "not_significant":
        return f"rejected: not significant (p = {c.p_value:.2g}, needs < {n['alpha_each']:.2g})"
    if code == "implausible":
        return "rejected: implausibly large (" + "; ".join(str(v) for v in c.implausible[:3]) + ")"
    if code == "predicts_worse":
        return (f"rejected: does not predict left-out poses better (cross-validated chi2 "
                f"{c.cv_chi2:.1f}, {-c.cv_gain:+.1f})")
    if code == "mixed_prediction":
        return (f"rejected: the model still does not fit with it, and it predicts some left-out poses better, "
                f"others worse (cross-validated chi2 {c.cv_gain:.1f} lower in sum, signed-rank p = {c.cv_p:.2g} "
                f">= {n['level']:g})")
    if code == "simpler_explains":
        return (f"rejected: {n['simpler']} ({n['simpler_dof']} parameter(s)) explains the same misfit and "
                f"{c.effect} ({c.score_dof}) does not predict left-out poses clearly better")
    if code == "better_candidate":
        return f"not added: {n['better']} predicts left-out poses better"
    if code == "finding":
        return ("FINDING: explains the most (delta chi2 " f"{c.delta_chi2:.1f}) only with "
                + "; ".join(str(v) for v in c.implausible[:3])
                + ": a likely error in the robot description or the setup")
    if code == "below_finding":
        return f"not added: it explains less than {n['finding']}, whose value is a finding"
    if code == "recommended":
        return (f"recommended (step {n['step']}): significant, within its plausible range, predicts left-out "
                f"poses better (cross-validated chi2 {n['cv_gain']:+.1f} lower)")
    if code == "recommended_pair":
        return (f"recommended (step {n['step']}, with {n['partner']}): neither alone explains the misfit; "
                f"together significant, within their plausible ranges, and predicting left-out poses better "
                f"(cross-validated chi2 {n['cv_gain']:+.1f} lower)")
    raise ValueError(f"calib.diagnose: unknown reason code {code!r}.")


def detectable_text(n: dict[str, Any]) -> str:
    """'; this data finds it ... only from ...': the size a score test would detect
    (calib.diagnose.with_detectable_size)."""
    factor = n.get("detect_factor")
    if factor is None or not np.isfinite(factor):
        return ""
    size = ", ".join(f"{k} = {math.degrees(v):.4g} deg" if u == "rad" else f"{k} = {v:.4g}"
                     + (f" {u}" if u != "1" else "") for k, (v, u) in list(n.get("detectable", {}).items())[:4])
    return (f"; this data finds it with {100 * n['detect_power']:.0f} % probability only from {factor:.2g} times "
            "its expected change" + (f" ({size})" if size else ""))


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


def verdict_text(diag: Diagnosis) -> str:
    """The diagnosis's verdict: a finding first, then what fits, what explains the misfit and what remains."""
    v = diag.outcome
    text = _conclusion(diag)
    f = v.finding
    if f is None:
        return text
    kept = ", ".join(v.selected)
    # after a step that kept effects, the finding's figures are those of the next step: say so, and that what
    # was kept before it stands (nothing is added after the finding, nothing replaces it)
    after = f" once {kept} is in the model, {f.effect} explains the most of what is left" if kept else (
        f" {f.effect} explains the most")
    lead = (f"FINDING:{after} (delta chi2 {f.delta_chi2:.1f}, predicting left-out poses better by "
            f"{f.cv_gain:.1f}) with " + "; ".join(str(x) for x in f.implausible[:3])
            + ": likely an error in the robot description or the setup (check it); nothing that explains less is "
            + (f"added after {kept}" if kept else "recommended in its place"))
    return lead + (f". Before it: {text}" if kept else "")


def _conclusion(diag: Diagnosis) -> str:
    v = diag.outcome
    if v.code == "fits":
        return (f"the model fits within the noise (chi2 {v.chi2:.1f} on {v.dof} dof, p = {v.p:.2g}); "
                f"no effect in the library is significant at the {v.alpha:g} level")
    where = misfit_location(diag)
    loc = f"the misfit sits in {', '.join(where['channels'])}; worst at {'; '.join(where['rows'][:2])}"
    c = v.implausible
    if v.code in ("implausible", "unexplained"):
        text = f"the model does not fit (chi2 {v.chi2:.1f} on {v.dof} dof, p = {v.p:.2g}): {loc}. "
        if c is not None:
            text += (f"{c.effect} would explain {100 * min(1.0, c.delta_chi2 / v.excess):.0f}% of the excess only "
                     f"with {c.implausible[0]}, implausibly large: something outside the library acts there")
        else:
            text += "nothing in the library explains it and predicts left-out poses better: look for an effect "
            text += "outside it"
        return text
    first = v.first
    if v.excess > 0:
        text = f"{first.effect} explains {100.0 * min(1.0, v.share):.0f}% of the excess"
    else:
        text = (f"{first.effect} explains a significant part (delta chi2 {first.delta_chi2:.1f}, p = "
                f"{first.p_value:.2g}) although chi2 is within the noise")
    if first.confused_with:
        text += f" (cannot be told apart from {', '.join(first.confused_with)} with this data)"
    text += f"; refit with --effects {','.join(v.selected)}"
    if v.code == "explained_partly":
        left = v.final_chi2 - max(v.final_dof, 1)
        pct = f"{100.0 * left / v.excess:.0f}% of the excess" if v.excess > 0 else "part of the misfit"
        text += f"; chi2 {v.final_chi2:.1f} on {v.final_dof} dof remains (p = {v.final_p:.2g}): {pct} is not explained"
        text += f" by {', '.join(v.selected)}"
        if v.more:
            text += " (other library effects still predict better: raise --max-effects"
            text += ", but no single one explains most of the misfit: it may lie outside the library)" if (
                v.partial) else ")"
        elif v.partial:
            text += (" nor by anything else in the library that predicts left-out poses better: no single effect"
                     " explains most of the misfit, it may lie outside the library")
        elif c is not None:
            text += (f"; {c.effect} would take more only with {c.implausible[0]}, implausibly large: something "
                     "outside the library acts there")
        else:
            text += " nor by anything else in the library that predicts left-out poses better"
    elif v.partial and len(v.selected) > 1:
        text += f" (no single effect explains most of the misfit: {first.effect} alone {100.0 * v.share:.0f}%)"
    return text
