"""The words and tables of `cdpr diagnose RUN RUN ...`, several runs of one robot (issue 28): the verdict of
the leave-one-run-out selection, the shared values and what each run keeps, and its JSON (the statistics are
calib.runselect's and calib.multirun's; the one-run diagnosis's report is acquisition/diagnose_report.py)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.diagnose_report import UNITS, fmt_value, parameter_units
from calib.fitting import residuals


def _names(t) -> str:
    return ",".join(t.names) if t.names else "(base: own unknowns only)"


def shared_values_text(fit, name: str) -> str:
    """'k = value ± sigma unit, ...' of a shared effect, with the units the one-run report gives them."""
    vals = fit.shared_params().get(name, {})
    sig = fit.shared_sigmas().get(name, {})
    units = parameter_units(fit.shared, fit.runs[0].rows.robot)

    def one(k: str, v: float) -> str:
        unit = units.get(k, UNITS.get(k, ""))
        if k not in sig:
            return f"{k} = {fmt_value(v, unit)}"
        if unit == "rad":
            return f"{k} = {math.degrees(v):.4g} ± {math.degrees(sig[k]):.2g} deg"
        return f"{k} = {v:.4g} ± {sig[k]:.2g}" + ("" if unit in ("1", "") else f" {unit}")

    return ", ".join(one(k, v) for k, v in vals.items())


def window_chi2(rf) -> tuple[float, int, float]:
    """chi2 of a fitted run against its window-scatter noise (the weights before the variance components),
    its degrees of freedom and p-value: the test of the model reported beside the variance components."""
    from scipy import stats

    from calib.selfcal.problem import Problem

    res = residuals(Problem(rf.problem.model, rf.rows.meas, rf.rows.sigma), rf.theta, rf.poses, jacobian=False)
    dof = max(int(res.r.shape[0]) - rf.theta.shape[0] - rf.poses.size, 1)
    chi2 = float(res.r @ res.r)
    return chi2, dof, float(stats.chi2.sf(chi2, dof))


def selection_verdict(sel) -> str:
    """The verdict: a finding (implausible best candidate) first, then what is recommended."""
    text = ""
    if sel.finding is not None:
        bad = "; ".join(str(v) for v in sel.finding.implausible)
        # effects chosen at the steps before the finding stand: say that nothing is added to them, not that
        # nothing is recommended (the verdict then recommends them)
        instead = (f"added to {','.join(sel.selected)}, chosen at the steps before it" if sel.selected else
                   "recommended in its place")
        text += (f"FINDING: {_names(sel.finding)} predicts best ({sel.mode} score {sel.finding.score:.1f}) only "
                 f"with {bad}: a likely error in the robot description or the setup (check it); nothing that "
                 f"explains less is {instead}. ")
        if sel.finding.spread is not None:
            text += finding_agreement(sel.finding) + " "
    if sel.selected:
        text += f"recommended: {','.join(sel.selected)} (by {sel.mode} prediction)"
    elif sel.finding is None:
        text += "nothing in the library predicts the left-out data better"
    else:
        text += "recommended: nothing"
    return text


def finding_agreement(t) -> str:
    """Whether the runs agree on a finding's out-of-range effects (each run fitted alone), with each run's
    value of every parameter out of its range (and its 1-sigma where it is a fitted parameter, not a
    reported one such as a pulley's offset): runs that agree are consistent with one fixed property of the
    robot as set up, runs that disagree point to a model error each run absorbs its own way (issue 28). A
    per-run value at its parameter's hard bound is marked: its 1-sigma measures nothing."""
    from calib.runselect import CONSISTENT_P

    sp = t.spread
    robot = t.fit.runs[0].rows.robot
    bad = {v.param for v in t.implausible}
    parts, pos = [], 0
    for e in t.fit.shared:
        specs = e.params(robot)
        if not any(n.startswith(e.name + ".") for n in bad):
            continue
        block, var = sp.values[:, pos:pos + len(specs)], sp.cov[:, range(pos, pos + len(specs)),
                                                                   range(pos, pos + len(specs))]
        pos += len(specs)
        reps = [e.report(robot, v) for v in block]
        own = {s.name: j for j, s in enumerate(specs)}
        for name in sorted(n.split(".", 1)[1] for n in bad if n.startswith(e.name + ".")):
            vals = []
            for r, rep in enumerate(reps):
                text = f"{rep.get(name, float('nan')):.3g}"
                if name in own:
                    j, s = own[name], specs[own[name]]
                    text += f" ± {math.sqrt(max(var[r, j], 0.0)):.2g}"
                    if np.isclose(block[r, j], s.lower) or np.isclose(block[r, j], s.upper):
                        text += " (at its bound)"
                vals.append(text)
            parts.append(f"{name} " + ", ".join(vals))
    if sp.p >= CONSISTENT_P:
        what = (f"the runs do not disagree on them ({_spread(sp)}): consistent with one fixed property of the "
                "robot as it is set up (its description, a sensor's calibration or mounting), to be checked on it")
    else:
        what = (f"the runs disagree on them ({_spread(sp)}): not one property of the robot, a model error each "
                "run's fit absorbs its own way")
    return f"Its out-of-range effects fitted on each run alone ({', '.join(sp.runs)}): {what}; per run: " \
           + "; ".join(parts) + "."


def selection_json(sel, paths: Sequence[str]) -> dict[str, Any]:
    """The JSON of a several-run diagnosis."""
    def trial(t):
        return {"effects": list(t.names), "n_params": t.n_params, "fit_score": t.fit_score, "score": t.score,
                "plausible": t.plausible, "implausible": [str(v) for v in t.implausible],
                "folds": t.folds, "values": t.fit.shared_params(), "sigma": t.fit.shared_sigmas(),
                "convergence": t.fit.convergence()}

    runs = []
    for rf0, rf in zip(sel.base.fit.runs, sel.final.fit.runs, strict=True):
        chi2, dof, p = window_chi2(rf)
        runs.append({"name": rf.name, "rms_base": rf0.rms(), "rms": rf.rms(), "initial_pose": list(rf.theta[:6]),
                     "yaw_drift_deg_per_hour": rf.params().get("ahrs_yaw_drift", {}).get("deg_per_hour"),
                     "window_chi2": chi2, "window_dof": dof, "window_p": p})
    return _json_safe({
        "runs": list(paths), "mode": sel.mode, "selected": sel.selected,
        "finding": None if sel.finding is None else {**trial(sel.finding), "runs_agree": None if sel.finding.spread
                                                     is None else _spread_json(sel.finding)},
        "verdict": selection_verdict(sel), "base": trial(sel.base), "final": trial(sel.final),
        "steps": [{"options": [trial(t) for t in st["options"]],
                   "chosen": None if st["chosen"] is None else list(st["chosen"].names),
                   "confused_with_chosen": [list(n) for n in st.get("confused", [])],
                   "absorbed_finding": None if st.get("absorbed") is None else list(st["absorbed"].names),
                   "inconsistent": [{"effects": list(t.names), "chi2": t.spread.chi2, "dof": t.spread.dof,
                                     "p": t.spread.p} for t in st.get("inconsistent", [])]} for st in sel.steps],
        "per_run": runs, "weights_rounds": sel.final.fit.history,
    })


def _spread_json(t) -> dict[str, Any]:
    """The runs' agreement on a finding's out-of-range effects: the consistency test and each run's values."""
    from calib.runselect import CONSISTENT_P, finding_params

    sp = t.spread
    _, names = finding_params(t, t.fit.runs[0].rows.robot)
    return {"chi2": sp.chi2, "dof": sp.dof, "p": sp.p, "agree": bool(sp.p >= CONSISTENT_P), "runs": sp.runs,
            "values": {n: list(sp.values[:, j]) for j, n in enumerate(names)},
            "sigma": {n: list(np.sqrt(np.clip(sp.cov[:, j, j], 0, None))) for j, n in enumerate(names)}}


def _json_safe(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_json_safe(x) for x in v]
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(float(v)) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def _spread(sp) -> str:
    return f"per-run fits' chi2 {sp.chi2:.1f} on {sp.dof} dof, p = {sp.p:.2g}"


def format_selection(sel, paths: Sequence[str], model_out: Path | None = None) -> str:
    """The console report of a several-run diagnosis."""
    out = [f"cdpr diagnose {' '.join(paths)}: effects shared by the runs, chosen by {sel.mode} prediction",
           selection_verdict(sel), ""]
    for name in sel.selected:
        out.append(f"  {name}: {shared_values_text(sel.final.fit, name)}")
    if sel.selected:
        out.append("  (±: the joint fit's 1-sigma of the shared value; a new run's 1-sigma, the `sigma` that "
                   "--model-out writes and --model uses, adds the between-run spread: docs/robot-model.md)")
    out.append(f"  the joint fit of {_names(sel.final)}: {sel.final.fit.convergence_words()}")
    loose = [t for st in sel.steps for t in st["options"] if not t.fit.converged]
    if loose:
        out.append("  WARNING: options judged on joint fits that did not converge (their scores are where the "
                   "fit stopped): " + "; ".join(f"{_names(t)} ({t.fit.stop.reason}, "
                                                 f"{t.fit.stop.remaining:.2g} chi2 left)" for t in loose))
    out += ["", "options judged (score: held-out -2 log-likelihood with each channel group's own variance, "
            "lower is better; J per left-out run: sum (rms/w)^2, w = 1 N, 0.5 mm, 0.1 deg, 0.2 deg)"]
    out.append(f"  {'effects':<52} {'params':>6} {'score':>9} {'gain':>8}  folds J / plausible")
    base = sel.base
    out.append(f"  {_names(base):<52} {base.n_params:>6} {base.score:>9.1f} {0.0:>8.1f}  "
               + " ".join(f"{f.get('J', f['score']):.1f}" for f in base.folds))
    for i, st in enumerate(sel.steps):
        cur = st["current"]
        for t in sorted(st["options"], key=lambda t: t.score):
            mark = "<- chosen" if t is st["chosen"] else ("" if t.plausible else "implausible: " + "; ".join(
                str(v) for v in t.implausible[:2]))
            out.append(f"  {'step ' + str(i + 1) + ': ' + _names(t):<52} {t.n_params:>6} {t.score:>9.1f} "
                       f"{cur.score - t.score:>8.1f}  " + " ".join(f"{f.get('J', f['score']):.1f}" for f in t.folds)
                       + f"  {mark}")
        if st.get("confused"):
            out.append("  confused with the chosen (fewest parameters kept): "
                       + "; ".join(",".join(n) for n in st["confused"]))
        for t in st.get("inconsistent", []):
            out.append(f"  set aside, the runs disagree on its value: {_names(t)} ({_spread(t.spread)})")
        if st.get("extensions"):  # the finding judged with one more effect (calib.runselect.extend_finding)
            out.append(f"  the finding judged with one more effect ({len(st['extensions'])} options above): " + (
                f"{_names(st['chosen'])} brings it into range and predicts better (no finding)" if st.get("absorbed")
                else "none is plausible, converged, with its values in range and predicting better: it stands"))
        if st["chosen"] is not None and st["chosen"].spread is not None:
            out.append(f"  the runs agree on the chosen's value: {_spread(st['chosen'].spread)}")
    out += ["", "per run: rms per channel, base -> with the selected effects (tension N, length mm, swivel deg, "
            "orientation deg); chi2 against the window-scatter noise"]
    for rf0, rf in zip(sel.base.fit.runs, sel.final.fit.runs, strict=True):
        a, b = rf0.rms(), rf.rms()
        conv = {"tension": 1.0, "length": 1e3, "swivel": 180 / math.pi, "orientation": 180 / math.pi}
        chi2, dof, p = window_chi2(rf)
        drift = rf.params().get("ahrs_yaw_drift", {}).get("deg_per_hour", float("nan"))
        out.append(f"  {rf.name}: " + ", ".join(f"{c} {a[c] * conv[c]:.3g} -> {b[c] * conv[c]:.3g}" for c in b)
                   + f"; yaw drift {drift:.1f} deg/h; chi2 {chi2:.1f} on {dof} dof (p = {p:.2g})")
    out += ["", "the initial pose as the weights move (variance-component rounds; x, y, z mm):"]
    for name in [rf.name for rf in sel.final.fit.runs]:
        seq = [h[name]["initial_pose"] for h in sel.final.fit.history if name in h]
        out.append(f"  {name}: " + " -> ".join(f"({1e3 * p[0]:.1f}, {1e3 * p[1]:.1f}, {1e3 * p[2]:.1f})"
                                               for p in seq))
    if model_out is not None:
        out += ["", f"model written to {model_out}; use it with cdpr solve RUN --model {model_out}"]
    return "\n".join(out) + "\n"
