"""The words and figures of a study (``cdpr study``): the table of its statistics
(:func:`acquisition.study.study_statistics`), three figures and the self-contained HTML page."""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import yaml

from acquisition.report import _svg
from acquisition.study import COVERAGE_EXPECTED, StudyConfig


def _fmt(q: dict[str, float] | None, key: str, digits: int) -> str:
    return "-" if q is None else f"{q[key]:.{digits}f}"


def render_table(stats: dict[str, dict[str, Any]]) -> str:
    """The console table of :func:`study_statistics`."""
    head = (f"{'plan':<11}{'ok/runs':>9} | {'position error (mm)':^34} | {'printed':>7} {'rms/':>5} | "
            f"{'coverage':^11} | {'robot time (s)':^27}")
    sub = (f"{'':<11}{'':>9} | {'median':>6} {'q1':>6} {'q3':>6} {'p90':>6} {'rms':>6} | {'rms 1σ':>7} {'1σ':>5} | "
           f"{'1σ':>5} {'2σ':>5} | {'median':>6} {'q1':>6} {'q3':>6} {'p90':>6}")
    lines = [head, sub]
    for plan, s in stats.items():
        e, t = s["error_mm"], s["robot_time_s"]
        r = s["rms_error_over_sigma"]
        c1, c2 = s["coverage_1sigma"], s["coverage_2sigma"]
        lines.append(
            f"{plan:<11}{s['ok']:>4}/{s['runs']:<4} | " + " ".join(_fmt(e, k, 2).rjust(6) for k in
                                                                 ("median", "q1", "q3", "p90", "rms"))
            + f" | {_fmt(s['sigma_mm'], 'rms', 2):>7} {'-' if r is None else f'{r:.2f}':>5} | "
            + f"{'-' if c1 is None else f'{100 * c1:.0f}%':>5} {'-' if c2 is None else f'{100 * c2:.0f}%':>5} | "
            + " ".join(_fmt(t, k, 1).rjust(6) for k in ("median", "q1", "q3", "p90")))
    for plan, s in stats.items():
        a = s.get("axes")
        if a:
            lines.append(f"{plan}: per axis x, y, z: rms(error/σ) "
                         + " / ".join(f"{v:.2f}" for v in a["rms_error_over_sigma"]) + ", coverage of the 1σ "
                         + " / ".join(f"{100 * v:.0f}%" for v in a["coverage_1sigma"]) + ", of the 2σ "
                         + " / ".join(f"{100 * v:.0f}%" for v in a["coverage_2sigma"]))
    lines.append(f"coverage: share of |error| within the printed 1σ and 2σ per axis (calibrated: "
                 f"{100 * COVERAGE_EXPECTED[0]:.0f}% and {100 * COVERAGE_EXPECTED[1]:.0f}%); rms/1σ: RMS error over "
                 f"the RMS printed 1σ of the position (calibrated: 1)")
    return "\n".join(lines) + "\n"


def _ok(results: Sequence[dict[str, Any]], plan: str) -> list[dict[str, Any]]:
    return [r for r in results if r["plan"] == plan and r["status"] == "ok"]


def plot_errors(results: Sequence[dict[str, Any]], plans: Sequence[str]):
    """Figure: the distribution of the initial-position error (mm) per plan, medians dashed."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 3.5))
    fig.subplots_adjust(left=0.1, right=0.97, bottom=0.15, top=0.9)
    ax = fig.add_subplot()
    errors = {plan: np.array([r["error_m"] for r in _ok(results, plan)]) * 1000.0 for plan in plans}
    every = np.concatenate([np.zeros(0), *errors.values()])
    bins = np.histogram_bin_edges(every, bins=max(5, min(40, len(every) // (4 * len(plans)))))
    for plan, e in errors.items():
        if len(e):
            line = ax.hist(e, bins=bins, histtype="step", lw=1.2, label=plan)[2][0]
            ax.axvline(float(np.median(e)), ls="--", lw=0.8, color=line.get_edgecolor())
    ax.set_xlabel("initial-position error |p - p_true| (mm)")
    ax.set_ylabel("runs")
    ax.set_title("initial-position error per plan (medians dashed)", loc="left", fontsize=10)
    ax.legend(fontsize=8, frameon=False)
    return fig


def plot_robot_time(results: Sequence[dict[str, Any]], plans: Sequence[str]):
    """Figure: the robot time (s) of the startups per plan (box: quartiles, whiskers: 10th-90th percentile)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 3.5))
    fig.subplots_adjust(left=0.1, right=0.97, bottom=0.1, top=0.9)
    ax = fig.add_subplot()
    data = [[r["robot_time_s"] for r in _ok(results, p)] for p in plans]
    keep = [(p, d) for p, d in zip(plans, data, strict=True) if d]
    if keep:
        ax.boxplot([d for _, d in keep], whis=(10, 90))
        ax.set_xticks(range(1, len(keep) + 1), [p for p, _ in keep])
    ax.set_ylabel("robot time of the startup (s)")
    ax.set_title("robot time per plan", loc="left", fontsize=10)
    return fig


def plot_error_vs_sigma(results: Sequence[dict[str, Any]], plans: Sequence[str]):
    """Figure: each run's position error against its printed 1-sigma (both the norm over x, y, z, mm; log
    axes, a printed sigma may be off by orders of magnitude); a calibrated sigma puts the RMS of the errors on
    the diagonal."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 4.5))
    fig.subplots_adjust(left=0.13, right=0.97, bottom=0.12, top=0.92)
    ax = fig.add_subplot()
    span = [math.inf, 0.0]
    for plan in plans:
        ok = _ok(results, plan)
        s = np.array([r["sigma_m"] for r in ok]) * 1000.0
        e = np.array([r["error_m"] for r in ok]) * 1000.0
        if len(e):
            ax.scatter(s, e, s=10, alpha=0.7, label=plan)
            both = np.concatenate([s, e])
            both = both[both > 0]
            span = [min(span[0], float(both.min(initial=math.inf))), max(span[1], float(both.max(initial=0.0)))]
    if span[1] > 0:
        ax.plot(span, span, color="k", lw=0.8, ls=":", label="error = 1σ")
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel("printed 1σ of the position (mm)")
    ax.set_ylabel("position error (mm)")
    ax.set_title("error against the printed 1σ", loc="left", fontsize=10)
    ax.legend(fontsize=8, frameon=False)
    return fig


def render_study_html(stats: dict[str, dict[str, Any]], results: Sequence[dict[str, Any]],
                      config: StudyConfig, seeds: Sequence[int]) -> str:
    """The study's self-contained HTML page: the table and three figures (SVG embedded)."""
    esc = html.escape
    plans = list(stats)
    rows = []
    for plan, s in stats.items():
        e, t = s["error_mm"], s["robot_time_s"]
        cells = [plan, f"{s['ok']}/{s['runs']}", *(_fmt(e, k, 2) for k in ("median", "q1", "q3", "p90", "rms")),
                 _fmt(s["sigma_mm"], "rms", 2),
                 "-" if s["rms_error_over_sigma"] is None else f"{s['rms_error_over_sigma']:.2f}",
                 *("-" if s[k] is None else f"{100 * s[k]:.0f}%" for k in ("coverage_1sigma", "coverage_2sigma")),
                 *(_fmt(t, k, 1) for k in ("median", "q1", "q3", "p90"))]
        rows.append("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in cells) + "</tr>")
    failures = [r for r in results if r["status"] != "ok"]
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>cdpr study</title>",
        "<style>body{font-family:sans-serif;max-width:1000px;margin:auto}td,th{padding:2px 8px;text-align:right}"
        "table{border-collapse:collapse}tr:nth-child(even){background:#f4f4f4}pre{background:#f8f8f8}</style>",
        "</head><body><h1>Monte-Carlo study of the startup</h1>",
        f"<p>robot {esc(config.robot)}, seeds {min(seeds)}..{max(seeds)}, plans {esc(', '.join(plans))}"
        + (f", tolerance {esc(config.tolerance)}" if config.tolerance else "") + "</p>",
        "<table><tr><th>plan</th><th>ok/runs</th><th colspan='5'>position error (mm): median, q1, q3, p90, RMS</th>"
        "<th>RMS printed 1&sigma; (mm)</th><th>RMS error / 1&sigma;</th>"
        "<th>within 1&sigma;</th><th>within 2&sigma;</th>"
        "<th colspan='4'>robot time (s): median, q1, q3, p90</th></tr>",
        *rows, "</table>",
        "<p>Within 1&sigma;/2&sigma;: the share of the per-axis errors inside the printed bounds (68% and 95% when "
        "the printed 1&sigma; is right).</p>",
        f"<img alt='error distribution' src='{_svg(plot_errors(results, plans))}'>",
        f"<img alt='robot time' src='{_svg(plot_robot_time(results, plans))}'>",
        f"<img alt='error against sigma' src='{_svg(plot_error_vs_sigma(results, plans))}'>",
        "<h2>Simulation configuration</h2>",
        f"<pre>{esc(yaml.safe_dump(config.sim_config) if config.sim_config else 'nominal')}</pre>",
    ]
    if failures:
        parts.append("<h2>Runs without a solution</h2><ul>")
        parts += [f"<li>{esc(r['plan'])} seed {r['seed']}: {esc(r['status'])}: {esc(r['message'])}</li>"
                  for r in failures]
        parts.append("</ul>")
    parts.append("</body></html>")
    return "\n".join(parts)
