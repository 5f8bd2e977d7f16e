"""A run as an MCAP file (``cdpr export RUN --format mcap -o FILE.mcap``) for Foxglove and PlotJuggler.

The channels and schemas of the live view (acquisition/scene.py, acquisition/live.py), so that a recorded run
opens in the layout a live startup is watched in (docs/foxglove-layout.json); log times in ns since the Unix
epoch: run.yaml's ``created`` time plus the sample's ``t`` (the run's own clock; 0 when the run has no
creation time). JSON channels, each with its JSON Schema (MCAP ``jsonschema`` encoding, which both viewers
decode without plug-ins):

- ``/samples`` (``cdpr.Sample``): one message per line of samples.csv, the columns by name (``t``, ``tau_1``..,
  ``tau_ref_1``.., ``dl_1``.., ``dsigma_1``.., ``roll``, ``pitch``, ``dyaw``, ``phase``, ``setpoint`` and the
  extra columns); SI units, radians; a missing value (NaN) is ``null``.
- ``/windows`` (``cdpr.Window``): one message per equilibrium window, at its first sample: ``first``, ``last``
  (sample indices), ``t_first``, ``t_last``, ``setpoint``; the windows of the solution when the run is solved,
  else those found in the signals (``calib.selfcal.find_windows``); ``source`` says which.
- ``/events`` (``cdpr.Event``): run.yaml's events (``t``, ``kind``, ``message``).
- ``/estimate`` (``cdpr.Estimate``): a sequential startup's online estimates (run.yaml ``sequential``), each at
  the end of its pose's window.
- ``/supervisor`` (``cdpr.Supervisor``): the supervisor's state (``watching``, ``stopping`` during a safe
  stop, ``stopped`` at the end), its tension bounds, the stop's sentence.
- ``/solution`` (``cdpr.Solution``): solution.json as one message at the last sample, when solved.

Foxglove's well-known schemas (protobuf, as the SDK encodes them): ``/scene`` (``foxglove.SceneUpdate``) at
every sample, the platform at the direct statics of the sample's measured tensions and, in a solved run,
from the reference sample on, the solve's initial pose (entity ``solution``); ``/tf``
(``foxglove.FrameTransform``, world -> platform); ``/log`` (``foxglove.Log``: phases, windows, estimates,
stops).

run.yaml itself is the MCAP metadata record ``run.yaml`` (key ``json``: the mapping as JSON text).
"""

from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.runlog import Run
from acquisition.runwriter import to_plain
from acquisition.scene import json_schema, number

PROFILE = ""  # no ROS profile: plain JSON channels


def _base_ns(run: Run) -> int:
    created = run.meta.get("created")
    if isinstance(created, datetime):
        return int(created.timestamp()) * 1_000_000_000
    try:
        return int(datetime.fromisoformat(str(created).replace("Z", "+00:00")).timestamp()) * 1_000_000_000
    except ValueError:
        return 0


def _makers(columns: dict[str, np.ndarray]) -> list:
    """Per column, the function making its JSON value (as ``acquisition.scene.sample_schema`` types it)."""
    return [int if col.dtype.kind in "iub" else number if col.dtype.kind == "f" else str for col in columns.values()]


def _windows(run: Run, solution: dict[str, Any] | None) -> tuple[list[tuple[int, int]], str]:
    if solution and solution.get("windows"):
        return [(int(a), int(b)) for a, b in solution["windows"]], "solution"
    from calib.selfcal import find_windows

    wins = find_windows(run.robot, run.t, run.tau, run.dl, run.dsigma, run.roll, run.pitch, run.tau_ref,
                        run.setpoints)
    return [(w.first, w.last) for w in wins], "signals"


def window_setpoint(run: Run, first: int, last: int) -> int:
    """The planned setpoint a window [first, last] holds: the one most of its samples are logged at (-1: none;
    a solution's window may reach into the settling before the hold)."""
    sp = np.asarray(run.setpoint[first:last + 1])
    sp = sp[sp >= 0]
    return int(np.bincount(sp).argmax()) if len(sp) else -1


def view_messages(run: Run, solution: dict[str, Any] | None, base_ns: int, speed: float = 1.0,
                  samples: bool = False, poses: np.ndarray | None = None) -> list[tuple[int, str, Any]]:
    """(log time ns, topic, message) of the view channels of ``run`` (all but /solution; /samples, as the live
    view sends them, when ``samples``), in time order: per sample its scene, transform and log lines; the
    windows, events, estimates and the supervisor's state at their times. Sample time t is at
    ``base_ns + t / speed``; ``poses`` (N, 6): the platform's (default: the statics of the measured tensions)."""
    from acquisition.live import Frame, RunView
    from acquisition.safety import SafetyLimits
    from acquisition.scene import static_poses

    robot = run.robot
    limits = SafetyLimits.for_robot(robot)
    ghosts = run.ideal_poses
    if ghosts is None and run.setpoints is not None:  # an imported run: the planned poses are the setpoints' statics
        ghosts = static_poses(robot, run.setpoints)
        ghosts = ghosts[np.all(np.isfinite(ghosts), 1)]
    view = RunView(robot, ghosts, limits.slack, limits.overload)
    N = len(run)

    def ns(t: float) -> int:
        return base_ns + max(int(round(float(t) * 1e9 / speed)), 0)

    if poses is None:
        poses = static_poses(robot, run.tau) if N else np.empty((0, 6))
    solved = np.asarray(solution["initial_pose"], float) if solution and solution.get("initial_pose") else None
    ref = int(solution.get("reference_sample", 0)) if solved is not None else N
    out: list[tuple[int, int, str, Any]] = []  # (time, order, topic, message)
    wins, source = _windows(run, solution) if N else ([], "signals")
    for a, b in wins:
        sp = window_setpoint(run, a, b)
        out += [(ns(run.t[a]), 1, tp, m) for tp, m in view.window(ns(run.t[a]), a, b, run.t[a], run.t[b], sp, source)]
    for ev in run.events:
        out += [(ns(ev["t"]), 2, tp, m) for tp, m in view.event(ns(ev["t"]), ev)]
    seq = run.meta.get("sequential") or {}
    ends = {window_setpoint(run, a, b): b for a, b in wins}
    for est in seq.get("windows", []) if N else []:
        j = ends.get(int(est["pose"]), N - 1)
        out += [(ns(run.t[j]), 3, tp, m) for tp, m in view.estimate(
            ns(run.t[j]), int(est["pose"]), run.t[j], est["initial_pose"], None, est.get("position_sigma_m"))]
    stop = str(run.events[-1]["message"]) if run.events else None
    cols = run.columns()
    tick = cols.get("tick", np.full(N, -1))
    for j in range(N):
        t = ns(run.t[j])
        f = Frame(t, float(run.t[j]), run.tau[j], run.tau_ref[j], run.dl[j], run.dsigma[j], float(run.roll[j]),
                  float(run.pitch[j]), float(run.dyaw[j]), str(run.phase[j]), int(run.setpoint[j]), int(tick[j]),
                  samples)
        pose = poses[j] if np.all(np.isfinite(poses[j])) else None
        out += [(t, 0, tp, m) for tp, m in view.frame(f, pose, solved=solved if j >= ref else None)]
        state = "stopping" if run.phase[j] == "safe_stop" else "watching"
        out += [(t, 4, tp, m) for tp, m in view.supervisor(t, run.t[j], state, stop if state != "watching" else None)]
    if N:
        t = ns(run.t[-1])
        out += [(t, 5, tp, m) for tp, m in view.supervisor(t, run.t[-1], "stopped", stop, every_ns=0)]
    out.sort(key=lambda x: (x[0], x[1]))
    return [(t, tp, m) for t, _, tp, m in out]


def export_mcap(run: Run, solution: dict[str, Any] | None, out: Path) -> None:
    """Write ``run`` (and ``solution`` when given) to the MCAP file ``out`` (see the module docstring)."""
    from mcap.writer import Writer

    from acquisition.live import channel_specs, encode

    base = _base_ns(run)
    columns = run.columns()
    makers = _makers(columns)
    names = list(columns)
    arrays = [columns[k].tolist() for k in names]

    def ns(t: float) -> int:
        return base + max(int(round(float(t) * 1e9)), 0)

    with open(out, "wb") as fh:
        w = Writer(fh)
        w.start(profile=PROFILE, library="cdpr")
        chans = {}
        for topic, (sname, senc, sdata, menc) in channel_specs({k: c.dtype.kind for k, c in columns.items()}).items():
            chans[topic] = w.register_channel(topic, menc, w.register_schema(sname, senc, sdata))
        for j in range(len(run)):
            msg = {name: make(col[j]) for name, make, col in zip(names, makers, arrays, strict=True)}
            t = ns(run.t[j])
            w.add_message(chans["/samples"], log_time=t, publish_time=t, sequence=j, data=json.dumps(msg).encode())
        counts = dict.fromkeys(chans, 0)
        for t, topic, msg in view_messages(run, solution, base):
            w.add_message(chans[topic], log_time=t, publish_time=t, sequence=counts[topic], data=encode(msg))
            counts[topic] += 1
        if solution:
            sol_ch = w.register_channel("/solution", "json", w.register_schema(
                "cdpr.Solution", "jsonschema", json_schema("cdpr.Solution", {
                    "initial_pose": {"type": "array", "items": {"type": "number"}},
                    "initial_pose_sigma": {"type": "array", "items": {"type": "number"}},
                    "sensor_offsets": {"type": "object"}, "method": {"type": "string"}}, ["initial_pose"])))
            t = ns(run.t[-1]) if len(run) else base
            w.add_message(sol_ch, log_time=t, publish_time=t, data=json.dumps(to_plain(solution)).encode())
        w.add_metadata("run.yaml", {"json": json.dumps(to_plain(run.meta), sort_keys=True, default=str)})
        w.finish()
