"""A run as an MCAP file (``cdpr export RUN --format mcap -o FILE.mcap``) for Foxglove and PlotJuggler.

Four channels of JSON messages, each with its JSON Schema (MCAP ``jsonschema`` encoding, which both viewers
decode without plug-ins); log times in ns since the Unix epoch: run.yaml's ``created`` time plus the
sample's ``t`` (the run's own clock; 0 when the run has no creation time).

- ``/samples`` (``cdpr.Sample``): one message per line of samples.csv, the columns by name (``t``, ``tau_1``..,
  ``tau_ref_1``.., ``dl_1``.., ``dsigma_1``.., ``roll``, ``pitch``, ``dyaw``, ``phase``, ``setpoint`` and the
  extra columns); SI units, radians; a missing value (NaN) is ``null``.
- ``/windows`` (``cdpr.Window``): one message per equilibrium window, at its first sample: ``first``, ``last``
  (sample indices), ``t_first``, ``t_last``, ``setpoint``; the windows of the solution when the run is solved,
  else those found in the signals (``calib.selfcal.find_windows``); ``source`` says which.
- ``/events`` (``cdpr.Event``): run.yaml's events (``t``, ``kind``, ``message``).
- ``/solution`` (``cdpr.Solution``): solution.json as one message at the last sample, when solved.

run.yaml itself is the MCAP metadata record ``run.yaml`` (key ``json``: the mapping as JSON text).
"""

from __future__ import annotations

import json
import math
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.runlog import Run, to_plain

PROFILE = ""  # no ROS profile: plain JSON channels
NUMBER_OR_NULL = {"type": ["number", "null"]}


def _schema(title: str, properties: dict[str, Any], required: list[str]) -> bytes:
    return json.dumps({"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
                       "type": "object", "properties": properties, "required": required}).encode()


def _base_ns(run: Run) -> int:
    created = run.meta.get("created")
    if isinstance(created, datetime):
        return int(created.timestamp()) * 1_000_000_000
    try:
        return int(datetime.fromisoformat(str(created).replace("Z", "+00:00")).timestamp()) * 1_000_000_000
    except ValueError:
        return 0


def _number(v: Any) -> float | None:
    x = float(v)
    return x if math.isfinite(x) else None


def _cells(columns: dict[str, np.ndarray]) -> tuple[dict[str, Any], list]:
    """The JSON Schema properties of the sample columns and, per column, a function making a JSON value."""
    props: dict[str, Any] = {}
    makers = []
    for name, col in columns.items():
        kind = col.dtype.kind
        if kind in "iub":
            props[name] = {"type": "integer"}
            makers.append(int)
        elif kind == "f":
            props[name] = NUMBER_OR_NULL
            makers.append(_number)
        else:
            props[name] = {"type": "string"}
            makers.append(str)
    return props, makers


def _windows(run: Run, solution: dict[str, Any] | None) -> tuple[list[tuple[int, int]], str]:
    if solution and solution.get("windows"):
        return [(int(a), int(b)) for a, b in solution["windows"]], "solution"
    from calib.selfcal import find_windows

    wins = find_windows(run.robot, run.t, run.tau, run.dl, run.dsigma, run.roll, run.pitch, run.tau_ref,
                        run.setpoints)
    return [(w.first, w.last) for w in wins], "signals"


def export_mcap(run: Run, solution: dict[str, Any] | None, out: Path) -> None:
    """Write ``run`` (and ``solution`` when given) to the MCAP file ``out`` (see the module docstring)."""
    from mcap.writer import Writer

    base = _base_ns(run)
    columns = run.columns()
    props, makers = _cells(columns)
    names = list(columns)
    arrays = [columns[k].tolist() for k in names]

    def ns(t: float) -> int:
        return base + max(int(round(float(t) * 1e9)), 0)

    with open(out, "wb") as fh:
        w = Writer(fh)
        w.start(profile=PROFILE, library="cdpr")
        sample_ch = w.register_channel("/samples", "json", w.register_schema(
            "cdpr.Sample", "jsonschema", _schema("cdpr.Sample", props, names)))
        window_ch = w.register_channel("/windows", "json", w.register_schema("cdpr.Window", "jsonschema", _schema(
            "cdpr.Window", {"first": {"type": "integer"}, "last": {"type": "integer"}, "t_first": {"type": "number"},
                            "t_last": {"type": "number"}, "setpoint": {"type": "integer"},
                            "source": {"type": "string"}},
            ["first", "last", "t_first", "t_last", "setpoint", "source"])))
        event_ch = w.register_channel("/events", "json", w.register_schema("cdpr.Event", "jsonschema", _schema(
            "cdpr.Event", {"t": {"type": "number"}, "kind": {"type": "string"}, "message": {"type": "string"}},
            ["t", "kind", "message"])))
        for j in range(len(run)):
            msg = {name: make(col[j]) for name, make, col in zip(names, makers, arrays, strict=True)}
            t = ns(run.t[j])
            w.add_message(sample_ch, log_time=t, publish_time=t, sequence=j, data=json.dumps(msg).encode())
        wins, source = _windows(run, solution) if len(run) else ([], "signals")
        for k, (a, b) in enumerate(wins):
            msg = {"first": a, "last": b, "t_first": float(run.t[a]), "t_last": float(run.t[b]),
                   "setpoint": int(run.setpoint[(a + b) // 2]), "source": source}
            w.add_message(window_ch, log_time=ns(run.t[a]), publish_time=ns(run.t[a]), sequence=k,
                          data=json.dumps(msg).encode())
        for k, ev in enumerate(run.events):
            msg = {"t": float(ev["t"]), "kind": str(ev["kind"]), "message": str(ev["message"])}
            w.add_message(event_ch, log_time=ns(ev["t"]), publish_time=ns(ev["t"]), sequence=k,
                          data=json.dumps(msg).encode())
        if solution:
            sol_ch = w.register_channel("/solution", "json", w.register_schema(
                "cdpr.Solution", "jsonschema", _schema("cdpr.Solution", {
                    "initial_pose": {"type": "array", "items": {"type": "number"}},
                    "initial_pose_sigma": {"type": "array", "items": {"type": "number"}},
                    "sensor_offsets": {"type": "object"}, "method": {"type": "string"}}, ["initial_pose"])))
            t = ns(run.t[-1]) if len(run) else base
            w.add_message(sol_ch, log_time=t, publish_time=t, data=json.dumps(to_plain(solution)).encode())
        w.add_metadata("run.yaml", {"json": json.dumps(to_plain(run.meta), sort_keys=True, default=str)})
        w.finish()
