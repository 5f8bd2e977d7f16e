"""The words, tables, plots and HTML of `cdpr diagnose` (the statistics are calib.diagnose's).

In a lab engineer's terms: where the model fails (channels, cables and poses, named), the candidate effects
with their units, plausible ranges and predictive gain, what is recommended and why, what was rejected and
why, and the recommendation as a command to paste. Plots: residuals against the quantities that reveal an
effect, residuals by channel and pose before and after the recommended effects, and the error falling as
they are added.
"""

from __future__ import annotations

import base64
import html
import math
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from calib.diagnose import Diagnosis
from calib.diagnose_words import misfit_location
from calib.evidence import Candidate
from calib.fitting import residuals
from calib.kinematics import inverse_kinematics
from calib.robot import Robot
from calib.selfcal import CHANNELS, Measurements


def reveal_quantities(robot: Robot, poses: np.ndarray, zeta0: np.ndarray, meas: Measurements) -> dict[str, Any]:
    """Per row (k,) the quantities against which residuals reveal effects: tension (k, n) N, cable length
    (k, n) m, height z (k,) m, swivel angle (k, n) rad, tilt (k,) rad; the reference row appended last."""
    Z = np.vstack([poses, np.asarray(zeta0)[None, :6]])
    kin = inverse_kinematics(robot, Z)
    tau = np.vstack([meas.tau, meas.ref_tau[None]])
    tilt = np.hypot(Z[:, 3], Z[:, 4])
    return {"tension": tau, "length": kin.lengths, "height": Z[:, 2], "swivel": kin.swivel, "tilt": tilt}




QUANTITIES = {
    "tension": ("tension [N]", True),
    "length": ("cable length [m]", True),
    "height": ("platform height z [m]", False),
    "swivel": ("swivel angle [rad]", True),
    "tilt": ("tilt [rad]", False),
}


def plot_residuals(diag: Diagnosis, outdir: str | Path) -> list[Path]:
    """PNG files (matplotlib, Agg) of the normalised residuals against tension, cable length, height,
    swivel angle and tilt, one file per quantity with a panel per channel, and the chi2 of each step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    f0 = diag.fit
    robot = f0.model.true_robot(f0.theta)
    q = reveal_quantities(robot, f0.poses, f0.theta, f0.problem.meas)
    res = diag.residual_data
    k = f0.poses.shape[0]
    rowpos = np.where(res.row < 0, k, res.row)
    files = []
    for name, (label, per_cable) in QUANTITIES.items():
        fig, axes = plt.subplots(1, 4, figsize=(16, 3.6), sharex=False)
        for ax, c in zip(axes, CHANNELS, strict=True):
            m = res.channel == c
            if not m.any():
                ax.set_visible(False)
                continue
            x = q[name]
            comp = res.index[m]
            if per_cable and c != "orientation":
                xv = x[rowpos[m], comp]
            elif per_cable:
                xv = x[rowpos[m]].mean(axis=1)
            else:
                xv = x[rowpos[m]]
            width = 3 if c == "orientation" else robot.n
            labels = ("roll", "pitch", "yaw") if c == "orientation" else [f"cable {i + 1}" for i in range(width)]
            for a in range(width):
                sel = comp == a
                if sel.any():
                    ax.plot(xv[sel], res.r[m][sel], "o", ms=4, label=labels[a])
            ax.axhline(0.0, color="k", lw=0.6)
            ax.set_title(c)
            ax.set_xlabel(label)
            ax.set_ylabel("residual / sigma")
            ax.legend(fontsize=7)
        fig.tight_layout()
        path = out / f"residuals_vs_{name}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        files.append(path)
    files.append(plot_before_after(diag, out / "residuals_by_pose.png"))
    files.append(plot_steps(diag.steps, out / "chi2_by_effect.png"))
    return files


def plot_before_after(diag: Diagnosis, path: str | Path) -> Path:
    """Residuals (in sigma) by channel and pose, of the base model and, where effects are recommended, of
    the model with them: one panel per channel, the poses along x (the reference pose first)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fits = [("base model", diag.fit, diag.residual_data)]
    if diag.selected:
        f = diag.final
        fits.append(("+ " + ", ".join(diag.selected), f, residuals(f.problem, f.theta, f.poses, jacobian=False)))
    k = diag.fit.poses.shape[0]
    ticks = ["ref"] + [str(i + 1) for i in range(k)]
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6))
    for ax, c in zip(axes, CHANNELS, strict=True):
        for j, (label, _, res) in enumerate(fits):
            m = res.channel == c
            x = np.where(res.row[m] < 0, 0, res.row[m] + 1) + (0.15 * j - 0.075 * (len(fits) - 1))
            ax.plot(x, res.r[m], "o" if j == 0 else "s", ms=4, alpha=0.8, label=label)
        ax.axhline(0.0, color="k", lw=0.6)
        every = -(-(k + 1) // 12)  # at most 12 labels: 27 poses' labels would overlap
        ax.set_xticks(range(0, k + 1, every), ticks[::every], fontsize=7)
        ax.set_title(c)
        ax.set_xlabel("pose")
        ax.set_ylabel("residual / sigma")
        ax.legend(fontsize=7)
    fig.tight_layout()
    p = Path(path)
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p


def plot_steps(steps: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """The error falling as effects are added one by one: chi2 (log) and, where known, eps_p per step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = ["base model"] + ["+ " + s["effects"][-1] for s in steps[1:]]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(range(len(steps)), [max(s["chi2"], 1e-9) for s in steps], "o-", label="chi2")
    ax.plot(range(len(steps)), [max(s["dof"], 1) for s in steps], "k--", marker="_", ms=24, lw=0.8,
            label="dof")  # the marker shows the dof of a single step (no effect added) too
    ax.set_xlim(-0.5, len(steps) - 0.5)
    ax.set_yscale("log")
    ax.set_xticks(range(len(steps)), labels, rotation=15, fontsize=8)
    ax.set_ylabel("chi2")
    if all("cv_chi2" in s for s in steps):
        ax.plot(range(len(steps)), [max(s["cv_chi2"], 1e-9) for s in steps], "^-", label="chi2 of left-out poses")
    if all("eps_p" in s for s in steps):
        ax2 = ax.twinx()
        ax2.plot(range(len(steps)), [1000 * s["eps_p"] for s in steps], "s-", color="tab:red", label="eps_p")
        ax2.set_ylabel("eps_p [mm]", color="tab:red")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p



UNITS = {"EA": "N", "deg_per_hour": "deg/h"}


def fmt_value(v: float, unit: str) -> str:
    """A parameter's value with its unit (radians shown in degrees)."""
    if unit == "rad":
        return f"{math.degrees(v):.3g} deg"
    return f"{v:.4g} {unit}".rstrip() if unit not in ("1", "") else f"{v:.4g}"


def _param_cell(c: Candidate, units: dict[str, str], top: int = 4) -> str:
    """'name = value +- sigma unit [lo, hi]' for the first parameters of a candidate's refit."""
    out = []
    for name, v in list(c.params.items())[:top]:
        unit = units.get(name, UNITS.get(name, ""))
        sd = c.params_sigma.get(name)
        text = f"{name} = {fmt_value(v, unit)}"
        if sd is not None and math.isfinite(sd) and name in units:
            text += f" +- {fmt_value(sd, unit)}"
        if name in c.bounds:
            lo, hi = c.bounds[name]
            text += f" [{fmt_value(lo, unit)}, {fmt_value(hi, unit)}]"
        out.append(text)
    return "; ".join(out)


def recommendation_command(diag: Diagnosis, run: str | Path = "RUN") -> str | None:
    """The command that refits the recommended effects (the diagnosis's own refit), or None."""
    if not diag.selected:
        return None
    return (f"cdpr solve {shlex.quote(str(run))} --noise {diag.noise_source} "
            f"--effects {','.join(diag.selected)}")


def format_diagnosis(diag: Diagnosis, units: dict[str, str] | None = None, run: str | Path = "RUN") -> str:
    """A readable report of a diagnosis; ``units`` maps parameter names to their units
    (:func:`parameter_units`)."""
    units = units or {}
    lines = [f"chi2 {diag.chi2:.3g} on {diag.dof} dof (p = {diag.p_value:.3g}), noise {diag.noise_source}"]
    where = misfit_location(diag)
    if diag.p_value < diag.alpha and diag.noise_source == "estimate":  # one name, two weightings: say which
        lines.append("  (noise estimate here is the windows' own scatter; cdpr solve's estimate also weighs a channel "
                     "the model misses by that misfit, so its chi2 of this run can be smaller and its 1-sigma wider)")
    if diag.p_value < diag.alpha:
        lines.append("where the model fails: " + "; ".join(where["channels"]))
        lines.append("  worst cables: " + "; ".join(where["cables"]))
        lines.append("  worst poses: " + "; ".join(where["rows"]))
    lines.append("channel        rms/sigma   max/sigma   chi2     per cable (rms/sigma)")
    for c, d in diag.channels.items():
        cab = "  ".join(f"{v:.2f}" for v in diag.cables.get(c, []))
        lines.append(f"  {c:<12} {d['rms_normalized']:>9.2f}  {d['max_normalized']:>9.2f}  {d['chi2']:>8.1f}  {cab}")
    dev = diag.fit.params().get("device_accuracy")
    if dev:
        lines.append(device_errors_line(diag.fit.model.robot, dev))
    lines.append("pose             sample  rms/sigma  max/sigma  worst")
    for r in diag.rows:
        sample = str(r["sample"]) if r["sample"] >= 0 else "-"
        lines.append(f"  {r['label']:<15} {sample:>6}  {r['rms_normalized']:>9.2f}  {r['max_normalized']:>9.2f}  "
                     f"{r['worst']}")
    lines.append("candidates (score test at the base fit; refit: delta chi2, fitted value +- 1 sigma [plausible "
                 "range]; CV: chi2 of left-out poses saved, signed-rank p)")
    lines.append(f"  {'effect':<17} {'score (dof)':>12} {'p':>8} {'d chi2':>9} {'CV gain':>9} {'CV p':>6}  "
                 "parameters")
    for c in diag.ranking:
        d = "" if c.delta_chi2 is None else f"{c.delta_chi2:.1f}"
        cv = "" if c.cv_gain is None else f"{c.cv_gain:.1f}"
        cvp = "" if c.cv_p is None else f"{c.cv_p:.2g}"
        p = c.score_p if c.p_value is None else c.p_value
        flag = "*" if c.effect in diag.selected else " "
        lines.append(f" {flag}{c.effect:<17} {c.score:>8.1f} ({c.score_dof:>2}) {p:>8.2g} {d:>9} {cv:>9} {cvp:>6}  "
                     + (_param_cell(c, units) or "expected change: " + ", ".join(
                         f"{k} = {fmt_value(v, units.get(k, UNITS.get(k, '')))}" for k, v in list(c.epc.items())[:4])))
        why = c.decision + (f"; cannot be told apart from {', '.join(c.confused_with)}" if c.confused_with else "")
        lines.append(f"      {why}")
    if len(diag.steps) > 1:
        lines.append("as effects are added: " + " -> ".join(
            f"chi2 {s['chi2']:.1f}, left-out {s['cv_chi2']:.1f}"
            + (f", eps_p {1000 * s['eps_p']:.1f} mm" if "eps_p" in s else "") for s in diag.steps))
    elif "eps_p" in diag.steps[0]:
        lines.append(f"eps_p of the base model: {1000 * diag.steps[0]['eps_p']:.1f} mm")
    lines.append("verdict: " + diag.verdict)
    cmd = recommendation_command(diag, run)
    if cmd:
        lines.append("recommended: " + cmd)
    return "\n".join(lines) + "\n"


def parameter_units(effects: Sequence[Any], robot: Robot) -> dict[str, str]:
    """Unit of every parameter the effects declare, by name."""
    out = {}
    for e in effects:
        inner = getattr(e, "inner", e)
        out.update({s.name: s.unit for s in inner.params(robot)})
    return out


def html_report(diag: Diagnosis, pngs: Sequence[str | Path], title: str = "cdpr diagnose",
                units: dict[str, str] | None = None, run: str | Path = "RUN") -> str:
    """A self-contained HTML page: the verdict, the command to paste, the tables of
    :func:`format_diagnosis` and the plots (embedded)."""
    imgs = []
    for p in pngs:
        data = base64.b64encode(Path(p).read_bytes()).decode("ascii")
        imgs.append(f'<h3>{html.escape(Path(p).stem)}</h3><img src="data:image/png;base64,{data}"/>')
    cmd = recommendation_command(diag, run)
    rec = f"<p><b>Recommended:</b> <code>{html.escape(cmd)}</code></p>" if cmd else ""
    return (
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title></head><body>"
        f"<h1>{html.escape(title)}</h1><p><b>Verdict:</b> {html.escape(diag.verdict)}</p>{rec}"
        f"<pre>{html.escape(format_diagnosis(diag, units, run))}</pre>{''.join(imgs)}</body></html>\n"
    )


def device_errors_line(robot, dev: dict[str, float]) -> str:
    """The devices' fitted constant errors against their datasheet bounds (load cells N, AHRS tilt deg, AHRS
    yaw drift deg/h); an error outside its bound is named with how many times the bound it is: the base
    model does not hold there."""
    from calib.effects.priors import YAW_RATE_BOUND

    sn = robot.sensors
    parts, outside = [], []
    for k, v in dev.items():
        if k == "yaw_rate":
            bound, factor, unit = YAW_RATE_BOUND, math.degrees(1.0) * 3600.0, "deg/h"
        elif k.endswith(("roll", "pitch")):
            bound, factor, unit = sn.ahrs_roll_pitch_accuracy, math.degrees(1.0), "deg"
        else:
            bound, factor, unit = sn.load_cell_uncertainty, 1.0, "N"
        val, b = v * factor, bound * factor
        parts.append(f"{k}={val:.3g} {unit}")
        if abs(v) > bound:
            outside.append(f"{k} = {val:.3g} {unit} is {abs(v) / bound:.0f}x its datasheet bound +-{b:.3g} {unit}")
    if not outside:
        return "devices' constant errors, fitted within their datasheet accuracy: " + ", ".join(parts)
    return ("devices' constant errors, fitted: " + ", ".join(parts) + "; outside the datasheet: "
            + "; ".join(outside) + " (the rigid model pushes its misfit there)")
