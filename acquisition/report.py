"""What the operator sees of a startup: a progress line while it runs, then a text summary, a self-contained
HTML report with plots, and the new sensor offsets saved for the controller's next start.

Everything here works from arrays and plain dictionaries (the run's columns, the solver's result in the
form of ``cdpr solve --json``), so it can be tested and re-run on any run folder.
"""

from __future__ import annotations

import base64
import contextlib
import datetime as _dt
import html
import io
import math
import os
import pickle
import select
import signal
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

CHANNELS = ("tension", "length", "swivel", "orientation")
UNITS = {"tension": "N", "length": "m", "swivel": "rad", "orientation": "rad"}


@dataclass
class StartupSummary:
    """What a startup produced: status, where, the solution (``cdpr solve --json`` form) and timings."""

    status: str  # "ok" or "safe_stop"
    run: str  # the run folder
    method: str
    setpoints: int
    message: str = ""
    solution: dict[str, Any] | None = None
    windows: list[tuple[int, int]] = field(default_factory=list)  # equilibrium windows the loop held
    timing: dict[str, float] = field(default_factory=dict)  # s: acquisition (robot time), wall, solve
    events: list[dict[str, Any]] = field(default_factory=list)
    files: dict[str, str] = field(default_factory=dict)  # report.html, offsets.yaml, truth.json

    def to_dict(self) -> dict[str, Any]:
        return {
            "status": self.status,
            "message": self.message,
            "run": self.run,
            "method": self.method,
            "setpoints": self.setpoints,
            "windows": [list(map(int, w)) for w in self.windows],
            "timing": {k: round(float(v), 4) for k, v in self.timing.items()},
            "events": self.events,
            "files": self.files,
            "solution": self.solution,
        }


def sequential_outcome(seq: dict | None, final_sigma: float | None = None) -> str:
    """One sentence on why a sequential startup stopped ('' for a fixed plan). ``final_sigma`` (m): the
    position 1-sigma of the run's final solve, the one the summary prints; said in place of the stop rule's
    own (the same solve on the samples up to the last window), and said apart when the two disagree on the
    tolerance."""
    if not seq:
        return ""
    w, tol = seq["windows"], 1000 * seq["tolerance_m"]
    sigma = 1000 * w[-1]["position_sigma_m"] if w and w[-1]["position_sigma_m"] is not None else float("inf")
    if seq["stop"] == "tolerance" and final_sigma is not None and 1000 * final_sigma >= tol:
        return (f"sequential: stopped after {len(w)} poses at a 1-sigma of the initial position of {sigma:.2f} mm "
                f"< tolerance {tol:g} mm, but the whole run's solve gives {1000 * final_sigma:.2f} mm.")
    sigma = sigma if final_sigma is None else 1000 * final_sigma
    if seq["stop"] == "tolerance":
        return (f"sequential: 1-sigma of the initial position {sigma:.2f} mm < tolerance {tol:g} mm after "
                f"{len(w)} poses.")
    return (f"sequential: the plan is exhausted after {len(w)} poses with a 1-sigma of the initial position of "
            f"{sigma:.2f} mm, above the tolerance {tol:g} mm.")


def _fmt_vec(v: Sequence[float], digits: int = 4) -> str:
    return "[" + ", ".join(f"{float(x):.{digits}f}" for x in v) + "]"


def pose_lines(pose: Sequence[float], sigma: Sequence[float] | None = None) -> list[str]:
    """The pose as readable lines: mm and degrees, with 1-sigma where known."""
    names = ("x", "y", "z", "roll", "pitch", "yaw")
    out = []
    for j, name in enumerate(names):
        scale, unit = (1000.0, "mm") if j < 3 else (180.0 / math.pi, "deg")
        s = "" if sigma is None else f" +- {float(sigma[j]) * scale:.3f}"
        out.append(f"  {name:<6}{float(pose[j]) * scale:10.3f}{s} {unit}")
    return out


def misfit_lines(sol: Mapping[str, Any]) -> list[str]:
    """When the chi2 test rejects the model (``calib.selfcal.sigma_scale`` > 1): the factor and what it says
    of the printed 1-sigma, one sentence; else nothing."""
    from calib.selfcal import sigma_scale

    chi2, dof = float(sol.get("chi2", math.nan)), int(sol.get("dof") or 0)
    k = sigma_scale(chi2, dof)
    if k <= 1.0:
        return []
    return [f"  chi2 above its band: the model misses the readings by sqrt(chi2/dof) = {k:.3g} times the noise "
            f"used, so the 1-sigma bounds above are too narrow; times {k:.3g} they give the order of the error "
            "(`cdpr diagnose RUN` says what is missing)"]


def render_text(summary: StartupSummary) -> str:
    """The summary printed at the end of ``cdpr startup``."""
    lines = [f"startup {summary.status}: run {summary.run} ({summary.method}, {summary.setpoints} setpoints)"]
    if summary.message:
        lines.append(f"  {summary.message}")
    t = summary.timing
    if t:
        lines.append("  time: " + ", ".join(f"{k} {v:.2f} {'ms' if k.endswith('_ms') else 's'}" for k, v in t.items()))
    sol = summary.solution
    if sol:
        lines.append(f"initial pose (sample {sol.get('reference_sample')}):")
        lines += pose_lines(sol["initial_pose"], sol.get("initial_pose_sigma", sol.get("initial_pose_std")))
        off = sol.get("sensor_offsets", {})
        lines.append("sensor offsets (absolute = offset + reading):")
        lines.append(f"  length  {_fmt_vec(off.get('length', []))} m")
        # angles in degrees to the thousandth, as cdpr solve prints them (offsets.yaml keeps radians)
        lines.append(f"  swivel  {_fmt_vec(np.degrees(off.get('swivel', [])), 3)} deg")
        lines.append(f"  yaw     {math.degrees(float(off.get('yaw', 0.0))):.3f} deg")
        res = sol.get("residuals", {})
        if res:
            lines.append(f"residuals (chi2 {float(sol.get('chi2', float('nan'))):.3g}, dof {sol.get('dof')}):")
            lines.append(f"  {'channel':<12}{'rms':>12}     {'rms/noise':>10}")
            for ch in CHANNELS:
                if ch in res:
                    lines.append(f"  {ch:<12}{float(res[ch]['rms']):>12.5g} {UNITS[ch]:<4}"
                                 f"{float(res[ch]['rms_normalized']):>10.3f}")
            lines += misfit_lines(sol)
    if summary.windows:
        lines.append("equilibrium windows held (first, last sample): "
                     + ", ".join(f"[{a}, {b}]" for a, b in summary.windows))
    if sol and sol.get("windows") and [list(w) for w in sol["windows"]] != [list(w) for w in summary.windows]:
        # the solve finds its windows in the samples (docs/windows.md), each the whole stretch at rest around a
        # hold, so they differ from the held ones: say which the solve used
        lines.append("windows the solve used (first, last sample; solution.json, cdpr solve): "
                     + ", ".join(f"[{a}, {b}]" for a, b in sol["windows"]))
    for e in summary.events:
        lines.append(f"event at {float(e['t']):.2f} s: {e['kind']}: {e['message']}")
    for k, v in summary.files.items():
        lines.append(f"{k}: {v}")
    return "\n".join(lines) + "\n"


def offsets_document(solution: Mapping[str, Any], robot_name: str, run: str, when: _dt.datetime | None = None
                     ) -> dict[str, Any]:
    """The sensor-offset file the controller reads at the next start (plain YAML-ready data)."""
    when = when or _dt.datetime.now(_dt.UTC)
    off = solution["sensor_offsets"]
    return {
        "format": "cdpr-offsets/1",
        "robot": robot_name,
        "created": when.strftime("%Y-%m-%dT%H:%M:%SZ"),
        "run": run,
        "method": solution.get("method", ""),
        "reference_sample": int(solution.get("reference_sample", -1)),
        "lengths": [float(x) for x in off["length"]],  # m, absolute = offset + dl
        "swivels": [float(x) for x in off["swivel"]],  # rad, absolute = offset + dsigma
        "yaw": float(off.get("yaw", 0.0)),  # rad, absolute = offset + dyaw
        "pose": [float(x) for x in solution["initial_pose"]],  # [x, y, z, roll, pitch, yaw], m and rad
    }


def write_offsets(path: str | Path, solution: Mapping[str, Any], robot_name: str, run: str,
                  when: _dt.datetime | None = None) -> Path:
    """Save the new sensor offsets (YAML) atomically; returns the path."""
    path = Path(path)
    doc = offsets_document(solution, robot_name, run, when)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text("# sensor offsets found by cdpr startup; absolute = offset + reading (m, rad)\n"
                   + yaml.safe_dump(doc, sort_keys=False))
    tmp.replace(path)
    return path


def read_offsets(path: str | Path) -> dict[str, Any]:
    """Read an offsets file written by :func:`write_offsets`; ValueError naming file, field and value."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read the sensor offsets ({exc}).") from exc
    if not isinstance(doc, dict) or doc.get("format") != "cdpr-offsets/1":
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise ValueError(f"{path}: field 'format' = {got!r} is not 'cdpr-offsets/1'.")
    for key, size in (("lengths", None), ("swivels", None), ("pose", 6)):
        v = doc.get(key)
        if not isinstance(v, list) or (size and len(v) != size) or not all(isinstance(x, int | float) for x in v):
            raise ValueError(f"{path}: field '{key}' = {v!r} must be a list of {size or 'n'} numbers.")
    if len(doc["swivels"]) != len(doc["lengths"]):
        raise ValueError(f"{path}: field 'swivels' has {len(doc['swivels'])} values, 'lengths' {len(doc['lengths'])}.")
    if not isinstance(doc.get("yaw"), int | float):
        raise ValueError(f"{path}: field 'yaw' = {doc.get('yaw')!r} must be a number.")
    return doc


def _svg(fig) -> str:
    """The figure as a data URI of an SVG image: vector, so the operator can zoom into a window, and about
    half the time and size of a PNG of the tension plot. The figures set their own margins: a "tight"
    bounding box would draw each one twice (0.12 s against 0.06 s for the tension plot of a startup)."""
    import matplotlib

    buf = io.BytesIO()
    with matplotlib.rc_context({"svg.hashsalt": "cdpr-report"}):  # the same page for the same run, byte for byte
        fig.savefig(buf, format="svg", metadata={"Date": None})
    return "data:image/svg+xml;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def plot_tensions(t: np.ndarray, tau: np.ndarray, tau_ref: np.ndarray, windows: Sequence[tuple[int, int]]):
    """Figure: measured tensions (N) against the reference, equilibrium windows shaded."""
    from matplotlib.figure import Figure  # no pyplot: no figure manager, and 0.1 s less to import

    fig = Figure(figsize=(10, 4))
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.12, top=0.92)
    ax = fig.add_subplot()
    for i in range(tau.shape[1]):
        line = ax.plot(t, tau[:, i], lw=0.8, label=f"tau_{i + 1}")[0]
        ax.plot(t, tau_ref[:, i], lw=0.8, ls="--", color=line.get_color())
    for a, b in windows:
        if 0 <= a <= b < len(t):
            ax.axvspan(t[a], t[b], color="0.85", zorder=0)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("tension (N)")
    ax.set_title("measured (solid) and reference (dashed) tensions; equilibrium windows shaded", loc="left",
                 fontsize=10)
    # above the axes, beside the title: never over the data, and no "best" place to search for
    ax.legend(ncol=min(tau.shape[1], 4), fontsize=8, loc="lower right", bbox_to_anchor=(1.0, 1.0), frameon=False,
              borderaxespad=0.1)
    return fig


def plot_residuals(residuals: Mapping[str, Any]):
    """Figure: normalised residual RMS per channel (1 = the noise level used in the weights)."""
    from matplotlib.figure import Figure

    names = [c for c in CHANNELS if c in residuals]
    vals = [float(residuals[c]["rms_normalized"]) for c in names]
    fig = Figure(figsize=(5, 3))
    fig.subplots_adjust(left=0.14, right=0.97, bottom=0.12, top=0.89)
    ax = fig.add_subplot()
    ax.bar(names, vals, color="tab:blue")
    ax.axhline(1.0, color="k", lw=0.8, ls=":")
    ax.set_ylabel("RMS / noise")
    ax.set_title("residuals per channel")
    return fig


def render_html(summary: StartupSummary, t: np.ndarray, tau: np.ndarray, tau_ref: np.ndarray) -> str:
    """A self-contained HTML page (plots embedded as base64 SVG)."""
    esc = html.escape
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>cdpr startup report</title>",
        "<style>body{font-family:sans-serif;max-width:1000px;margin:auto}td,th{padding:2px 10px;text-align:right}"
        "table{border-collapse:collapse}tr:nth-child(even){background:#f4f4f4}pre{background:#f8f8f8}</style>",
        "</head><body>",
        f"<h1>Startup {esc(summary.status)}</h1>",
        f"<p>run <code>{esc(summary.run)}</code>, method {esc(summary.method)}, {summary.setpoints} setpoints</p>",
    ]
    if summary.message:
        parts.append(f"<p><b>{esc(summary.message)}</b></p>")
    sol = summary.solution
    if sol:
        sig = sol.get("initial_pose_sigma", sol.get("initial_pose_std"))
        parts.append(f"<h2>Initial pose (sample {esc(str(sol.get('reference_sample')))})</h2><table>"
                     "<tr><th>coordinate</th><th>value</th><th>1&sigma;</th></tr>")
        for j, name in enumerate(("x (mm)", "y (mm)", "z (mm)", "roll (deg)", "pitch (deg)", "yaw (deg)")):
            scale = 1000.0 if j < 3 else 180.0 / math.pi
            s = "" if sig is None else f"{float(sig[j]) * scale:.3f}"
            parts.append(f"<tr><td>{name}</td><td>{float(sol['initial_pose'][j]) * scale:.3f}</td><td>{s}</td></tr>")
        parts.append("</table>")
        off = sol.get("sensor_offsets", {})
        parts.append("<h2>Sensor offsets</h2><table><tr><th>cable</th><th>length (m)</th><th>swivel (rad)</th></tr>")
        for i, (a, b) in enumerate(zip(off.get("length", []), off.get("swivel", []), strict=False)):
            parts.append(f"<tr><td>{i + 1}</td><td>{float(a):.5f}</td><td>{float(b):.5f}</td></tr>")
        parts.append(f"</table><p>yaw offset {float(off.get('yaw', 0.0)):.5f} rad</p>")
        res = sol.get("residuals", {})
        if res:
            parts.append("<h2>Residuals</h2><table><tr><th>channel</th><th>RMS</th><th>RMS / noise</th></tr>")
            for ch in CHANNELS:
                if ch in res:
                    parts.append(f"<tr><td>{ch}</td><td>{float(res[ch]['rms']):.4g} {UNITS[ch]}</td>"
                                 f"<td>{float(res[ch]['rms_normalized']):.3f}</td></tr>")
            parts.append("</table>")
            parts.append(f"<img alt='residuals' src='{_svg(plot_residuals(res))}'>")
    if len(t):
        fig = plot_tensions(t, tau, tau_ref, summary.windows)
        parts.append(f"<h2>Tensions</h2><img alt='tensions' src='{_svg(fig)}'>")
    if summary.windows:
        parts.append("<h2>Equilibrium windows</h2><table><tr><th>#</th><th>first sample</th><th>last sample</th>"
                     "<th>from (s)</th><th>to (s)</th></tr>")
        for j, (a, b) in enumerate(summary.windows):
            ta = f"{t[a]:.2f}" if 0 <= a < len(t) else ""
            tb = f"{t[b]:.2f}" if 0 <= b < len(t) else ""
            parts.append(f"<tr><td>{j}</td><td>{a}</td><td>{b}</td><td>{ta}</td><td>{tb}</td></tr>")
        parts.append("</table>")
    if summary.events:
        parts.append("<h2>Events</h2><ul>")
        parts += [f"<li>{float(e['t']):.2f} s {esc(e['kind'])}: {esc(e['message'])}</li>" for e in summary.events]
        parts.append("</ul>")
    parts.append("<h2>Timing</h2><table>" + "".join(
        f"<tr><td>{esc(k)}</td><td>{float(v):.3g} {'ms' if k.endswith('_ms') else 's'}</td></tr>"
        for k, v in summary.timing.items()) + "</table></body></html>")
    return "\n".join(parts)


def write_html(path: str | Path, summary: StartupSummary, t: np.ndarray, tau: np.ndarray,
               tau_ref: np.ndarray) -> Path:
    path = Path(path)
    path.write_text(render_html(summary, t, tau, tau_ref), encoding="utf-8")
    return path


class ReportRenderer:
    """Writes report.html from a child process forked ahead of time (:meth:`start`, before the robot is
    planned): the child imports matplotlib and draws a first figure (~0.4 s of CPU) while the routine plans
    and connects (stopped during the control loop, :meth:`paused`), then waits. :meth:`write` hands it the
    run's data through a pipe once the solve is done; when the child is not there or fails, the page is
    rendered in this process instead. The child runs in its own session (Ctrl-C is the control loop's, not
    its), keeps no file of this process but its pipe (stdout and stderr go to /dev/null) and ends with the
    page. As a context manager it ends the child on the way out (:meth:`close`)."""

    def __init__(self) -> None:
        self.pid: int | None = None
        self._pipe: int | None = None  # the write end of the child's data pipe

    def __enter__(self) -> ReportRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> ReportRenderer:
        if self.pid is not None or not hasattr(os, "fork"):
            return self
        r, w = os.pipe()
        ready_r, ready_w = os.pipe()  # the child says when it is set to die with this process
        parent = os.getpid()
        try:
            pid = os.fork()
        except OSError:  # no child: write() renders here
            for fd in (r, w, ready_r, ready_w):
                os.close(fd)
            return self
        if pid == 0:  # the child: never returns
            code = 1
            try:
                _die_with_parent(parent)  # even while stopped (paused): a killed routine leaves no renderer
                os.write(ready_w, b"1")
                os.setsid()
                null = os.open(os.devnull, os.O_RDWR)
                for fd in (1, 2):
                    os.dup2(null, fd)
                os.dup2(r, 0)
                os.closerange(3, os.sysconf("SC_OPEN_MAX"))  # one close_range call on Linux
                code = serve_report()
            finally:
                os._exit(code)
        os.close(r)
        os.close(ready_w)
        try:  # a millisecond or two: not stopped (paused) before it can die with this process
            select.select([ready_r], [], [], 2.0)
        finally:
            os.close(ready_r)
        self.pid, self._pipe = pid, w
        return self

    @contextlib.contextmanager
    def paused(self):
        """The child stopped (SIGSTOP) for the duration, continued (SIGCONT) after: around the control loop, where
        a renderer still loading matplotlib on a two-core machine takes CPU from the loop (and from the
        simulated plant's process), and where a real robot's loop wants no jitter."""
        pid = self.pid
        if pid is not None:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGSTOP)
        try:
            yield self
        finally:
            if pid is not None and self.pid == pid:
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGCONT)

    def alive(self) -> bool:
        """Whether the child still runs."""
        return self.pid is not None and os.waitpid(self.pid, os.WNOHANG)[0] == 0

    def write(self, path: str | Path, summary: StartupSummary, t: np.ndarray, tau: np.ndarray,
              tau_ref: np.ndarray) -> Path:
        """report.html at ``path``, as :func:`write_html` writes it."""
        pid, pipe = self.pid, self._pipe
        self.pid = self._pipe = None
        if pid is not None:
            try:
                with os.fdopen(pipe, "wb") as f:
                    pipe = None
                    f.write(pickle.dumps((str(path), summary, t, tau, tau_ref)))
                if _wait(pid, 120.0) == 0:
                    return Path(path)
            except OSError:  # the child has gone (broken pipe): render here
                pass
            _end(pid, pipe)
        return write_html(path, summary, t, tau, tau_ref)

    def close(self) -> None:
        """End the child if no report was written (a stopped routine)."""
        pid, pipe = self.pid, self._pipe
        self.pid = self._pipe = None
        if pid is not None:
            _end(pid, pipe)


def _die_with_parent(parent: int) -> None:
    """This process gets SIGKILL when its parent ends (Linux's PR_SET_PDEATHSIG; elsewhere nothing), or exits
    now if the parent has already gone."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # no prctl: not Linux
        pass
    if os.getppid() != parent:
        os._exit(1)


def _wait(pid: int, timeout: float) -> int | None:
    """The child's exit code once it ends within ``timeout`` s, else None (it still runs)."""
    end = time.monotonic() + timeout
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return os.waitstatus_to_exitcode(status)
        if time.monotonic() > end:
            return None
        time.sleep(0.002)


def _end(pid: int, pipe: int | None) -> None:
    """Kill the child if it still runs, reap it and close its pipe."""
    if pipe is not None:
        try:
            os.close(pipe)
        except OSError:
            pass
    try:
        if os.waitpid(pid, os.WNOHANG)[0] == 0:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
    except ChildProcessError:  # already reaped
        pass


def serve_report() -> int:
    """The :class:`ReportRenderer` child: import matplotlib and draw once now, then render the pickled
    (path, summary, t, tau, tau_ref) that stdin brings to report.html. Exit status 0 when written (or when
    nothing came); an exception exits non-zero and the parent renders the page itself."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(2, 1))  # fonts and renderer loaded before they are needed
    ax = fig.add_subplot()
    ax.plot([0.0, 1.0], [0.0, 1.0], label="x")
    ax.legend(loc="upper left")
    _svg(fig)
    with os.fdopen(0, "rb", closefd=False) as stdin:
        data = stdin.read()
    if not data:
        return 0
    path, summary, t, tau, tau_ref = pickle.loads(data)  # from the parent process only
    write_html(path, summary, t, tau, tau_ref)
    return 0
