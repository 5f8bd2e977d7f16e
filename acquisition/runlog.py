"""Runs in the `cdpr-run/1` format (../shared/spec/run-format.md): the run in memory, its reader, the solution file.

A run is a folder with ``run.yaml`` (metadata: robot, procedure, events) and ``samples.csv`` (one line per
logged sample). SI units, angles in radians. Readers accept extra keys and columns; :func:`read_run`
validates what it knows and raises :class:`RunFormatError` with one sentence naming the file, the field or
column and the value. A ``samples.csv`` cut in the middle of a line (a crash while logging) reads back up to
its last complete line, with a warning; other damaged lines are skipped and counted the same way
(:class:`DamageLog`, the policy of docs/run-format.md, which the importers share).

Numbers are written with ``repr`` (shortest string that reads back to the same float), so writing is
lossless and deterministic: the same values give the same bytes.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from acquisition.damage import CUT, FIELDS, VALUE, DamageLog, time_order
from calib.errors import CdprError
from calib.robot import Robot, RobotDescriptionError, builtin_robot_names, load_robot, robot_from_dict

FORMAT = "cdpr-run/1"
METHODS = ("equilibrium", "kinematic")
RUN_YAML = "run.yaml"
SAMPLES_CSV = "samples.csv"
SOLUTION_JSON = "solution.json"
CABLE_GROUPS = ("tau", "tau_ref", "dl", "dsigma")
SCALAR_COLUMNS = ("roll", "pitch", "dyaw")


class RunFormatError(CdprError, ValueError):
    """A run that does not follow `cdpr-run/1`; the message names the file, field or column, and value."""


def sample_columns(n: int) -> list[str]:
    """The standard columns of samples.csv for n cables, in the order the writers use."""
    cols = ["t"]
    for g in CABLE_GROUPS:
        cols += [f"{g}_{i}" for i in range(1, n + 1)]
    return cols + list(SCALAR_COLUMNS) + ["phase", "setpoint"]


def required_columns(n: int) -> list[str]:
    """Columns a reader needs (phase and setpoint are optional: readers must not rely on them)."""
    return sample_columns(n)[:-2]


@dataclass
class Run:
    """One run in memory. Arrays: (N,) or (N, n) over the N samples; SI units, radians.

    ``meta`` is the run.yaml mapping (extra keys kept); ``extra`` holds the extra columns of samples.csv
    by name (float arrays, or str arrays for non-numeric columns).
    """

    path: Path | None
    meta: dict[str, Any]
    robot: Robot
    method: str
    sample_period: float
    setpoints: np.ndarray | None
    ideal_poses: np.ndarray | None
    events: list[dict[str, Any]]
    t: np.ndarray
    tau: np.ndarray
    tau_ref: np.ndarray
    dl: np.ndarray
    dsigma: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    dyaw: np.ndarray
    phase: np.ndarray
    setpoint: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n(self) -> int:
        """Number of cables."""
        return self.robot.n

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def source(self) -> str:
        return str(self.meta.get("source", ""))

    def subset(self, index: slice | np.ndarray) -> Run:
        """A copy holding only some samples (a slice, indices or a boolean mask); metadata shared, path None."""
        names = ("t", *CABLE_GROUPS, *SCALAR_COLUMNS, "phase", "setpoint")
        picked = {name: getattr(self, name)[index] for name in names}
        return dataclasses.replace(self, path=None, extra={k: v[index] for k, v in self.extra.items()}, **picked)

    def columns(self) -> dict[str, np.ndarray]:
        """All columns of samples.csv by name, standard ones first, then the extra ones."""
        out: dict[str, np.ndarray] = {"t": self.t}
        for g in CABLE_GROUPS:
            a = getattr(self, g)
            for i in range(self.n):
                out[f"{g}_{i + 1}"] = a[:, i]
        for name in SCALAR_COLUMNS:
            out[name] = getattr(self, name)
        out["phase"] = self.phase
        out["setpoint"] = self.setpoint
        out.update(self.extra)
        return out


def _fail(file: Path, what: str) -> RunFormatError:
    return RunFormatError(f"{file}: {what}.")


def _read_meta(folder: Path) -> dict[str, Any]:
    f = folder / RUN_YAML
    if folder.is_file():  # a log handed to solve/diagnose/export as it came from the controller or the parser
        hint = (f"; convert it first: cdpr import irma {folder} -o RUN" if folder.suffix.lower() in (".log", ".mat")
                else "")
        raise RunFormatError(f"{folder}: a file, not a run folder (a cdpr-run/1 folder holds run.yaml and "
                             f"samples.csv){hint}.")
    if not folder.is_dir():
        raise RunFormatError(f"{folder}: not a run folder (no such directory).")
    if not f.is_file():
        raise _fail(f, "missing (a cdpr-run/1 folder holds run.yaml and samples.csv)")
    try:
        meta = yaml.safe_load(f.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise _fail(f, f"not valid YAML ({str(exc).splitlines()[0]})") from exc
    if not isinstance(meta, dict):
        raise _fail(f, f"must be a mapping, got {type(meta).__name__}")
    return meta


def _number(f: Path, field_name: str, v: Any, positive: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or (positive and v <= 0):
        kind = "a positive number" if positive else "a finite number"
        raise _fail(f, f"field '{field_name}' = {v!r} must be {kind}")
    return float(v)


def _matrix(f: Path, field_name: str, v: Any, width: int) -> np.ndarray:
    if not isinstance(v, list):
        raise _fail(f, f"field '{field_name}' = {v!r} must be a list of lists of {width} numbers")
    rows = []
    for j, row in enumerate(v):
        if not isinstance(row, list) or len(row) != width:
            raise _fail(f, f"field '{field_name}[{j}]' = {row!r} must be a list of {width} numbers")
        rows.append([_number(f, f"{field_name}[{j}][{i}]", x) for i, x in enumerate(row)])
    return np.array(rows, dtype=float).reshape(len(rows), width)


def _parse_meta(folder: Path, meta: dict[str, Any]) -> tuple[Robot, str, float, Any, Any, list]:
    f = folder / RUN_YAML
    if "format" not in meta:
        raise _fail(f, "required field 'format' is missing (expected 'cdpr-run/1')")
    if meta["format"] != FORMAT:
        raise _fail(f, f"field 'format' = {meta['format']!r} is not a known format (expected '{FORMAT}')")
    if "robot" not in meta:
        raise _fail(f, "required field 'robot' is missing")
    spec = meta["robot"]
    try:
        if isinstance(spec, str):
            if spec not in builtin_robot_names():
                raise _fail(f, f"field 'robot' = {spec!r} is not a built-in robot ({', '.join(builtin_robot_names())})")
            robot = load_robot(spec)
        elif isinstance(spec, dict):
            robot = robot_from_dict(spec, f"{f} field 'robot'")
        else:
            raise _fail(f, f"field 'robot' = {spec!r} must be a built-in robot name or a description mapping")
    except RobotDescriptionError as exc:
        raise RunFormatError(str(exc)) from exc
    pro = meta.get("procedure")
    if pro is None:
        raise _fail(f, "required field 'procedure' is missing")
    if not isinstance(pro, dict):
        raise _fail(f, f"field 'procedure' = {pro!r} must be a mapping")
    if "method" not in pro:
        raise _fail(f, "required field 'procedure.method' is missing")
    method = pro["method"]
    if method not in METHODS:
        raise _fail(f, f"field 'procedure.method' = {method!r} must be one of {', '.join(METHODS)}")
    if "sample_period" not in pro:
        raise _fail(f, "required field 'procedure.sample_period' is missing")
    period = _number(f, "procedure.sample_period", pro["sample_period"], positive=True)
    setpoints = None if pro.get("setpoints") is None else _matrix(f, "procedure.setpoints", pro["setpoints"], robot.n)
    ideal = None if pro.get("ideal_poses") is None else _matrix(f, "procedure.ideal_poses", pro["ideal_poses"], 6)
    if setpoints is not None and ideal is not None and len(setpoints) != len(ideal):
        raise _fail(
            f, f"field 'procedure.ideal_poses' has {len(ideal)} poses but 'procedure.setpoints' has {len(setpoints)}"
        )
    events = meta.get("events") or []
    if not isinstance(events, list):
        raise _fail(f, f"field 'events' = {events!r} must be a list")
    for j, ev in enumerate(events):
        if not isinstance(ev, dict):
            raise _fail(f, f"field 'events[{j}]' = {ev!r} must be a mapping with t, kind, message")
        if "t" in ev:
            _number(f, f"events[{j}].t", ev["t"])
    return robot, method, period, setpoints, ideal, events


def _read_samples(folder: Path, n: int) -> tuple[list[str], list[list[str]], list[int], DamageLog]:
    """Header, the cells of the lines with the header's width, their line numbers, and what was skipped."""
    f = folder / SAMPLES_CSV
    if not f.is_file():
        raise _fail(f, "missing (a cdpr-run/1 folder holds run.yaml and samples.csv)")
    text = f.read_bytes().decode("utf-8", errors="replace")
    if not text.strip():
        raise _fail(f, "is empty (no header line)")
    damage = DamageLog(f)
    lines = text.split("\n")
    if lines[-1] == "":
        lines.pop()
    elif len(lines) > 1:
        damage.add(CUT, f"line {len(lines)}")
        lines.pop()
    else:  # the file ends inside its header: a column name may be cut short, and the header describes every line
        raise _fail(f, "header line is cut short (the file ends before its line end)")
    if "\ufffd" in lines[0]:
        raise _fail(f, "header line is not UTF-8 text")
    header = [h.strip() for h in lines[0].rstrip("\r").split(",")]
    seen = set()
    for h in header:
        if h == "":
            raise _fail(f, "header line has an empty column name")
        if h in seen:
            raise _fail(f, f"header line names column '{h}' twice")
        seen.add(h)
    for c in required_columns(n):
        if c not in seen:
            raise _fail(f, f"required column '{c}' is missing from the header (robot with {n} cables)")
    width = len(header)
    rows, numbers = [], []
    for k, line in enumerate(lines[1:], start=2):
        line = line.rstrip("\r")
        if line.strip() == "":
            continue  # a blank line holds no sample: nothing is lost
        cells = line.split(",")
        if len(cells) != width:
            damage.add(FIELDS, f"first: line {k} has {len(cells)} values, the header {width}")
            continue
        rows.append(cells)
        numbers.append(k)
    return header, rows, numbers, damage


def _floats(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Floats of a column of cells and where they are finite numbers (False for text, NaN, inf)."""
    try:
        a = np.array(cells, dtype=float)
    except ValueError:
        a = np.array([float_or_nan(c) for c in cells], dtype=float)
    return a, np.isfinite(a)


def float_or_nan(c: str) -> float:
    """float(c), or NaN for a cell that is not a number (the damage policy then skips its line)."""
    try:
        return float(c)
    except ValueError:
        return math.nan


def _setpoints(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The setpoint column as ints (-1 for an empty cell) and where the cells are integers."""
    out = np.full(cells.shape[0], -1, dtype=int)
    ok = np.ones(cells.shape[0], dtype=bool)
    for k, c in enumerate(cells):
        c = c.strip()
        if c:
            try:
                out[k] = int(c)
            except ValueError:
                ok[k] = False
    return out, ok


def read_run(path: str | Path) -> Run:
    """Read and validate a run folder. Raises RunFormatError naming file, field/column and value.

    Damaged lines of samples.csv are skipped under the damage policy (docs/run-format.md) and counted in
    one :class:`DamagedInputWarning`; a file whose every line is damaged is an error.
    """
    folder = Path(path)
    meta = _read_meta(folder)
    robot, method, period, setpoints, ideal, events = _parse_meta(folder, meta)
    n = robot.n
    f = folder / SAMPLES_CSV
    header, rows, numbers, damage = _read_samples(folder, n)
    index = {h: j for j, h in enumerate(header)}
    cells = np.array(rows, dtype=str).reshape(len(rows), len(header))
    lines = np.array(numbers, dtype=int)
    names = required_columns(n)
    values = np.empty((len(rows), len(names)))
    good = np.ones(len(rows), dtype=bool)
    first_bad: dict[int, str] = {}
    for j, name in enumerate(names):
        values[:, j], ok = _floats(cells[:, index[name]])
        for k in np.flatnonzero(~ok & good)[:1]:
            first_bad[int(k)] = f"first: line {lines[k]} column '{name}' = {str(cells[k, index[name]])!r}"
        good &= ok
    setpoint = np.full(len(rows), -1, dtype=int)
    if "setpoint" in index:
        setpoint, ok = _setpoints(cells[:, index["setpoint"]])
        for k in np.flatnonzero(~ok & good)[:1]:
            first_bad[int(k)] = f"first: line {lines[k]} column 'setpoint' = {str(cells[k, index['setpoint']])!r}"
        good &= ok
    if first_bad:
        damage.add(VALUE, first_bad[min(first_bad)], int(np.count_nonzero(~good)))
    ok_rows = np.flatnonzero(good)
    keep = ok_rows[time_order(values[ok_rows, 0], values[ok_rows], [f"line {x}" for x in lines[ok_rows]], damage)]
    if damage and keep.size == 0:
        raise _fail(f, f"holds no usable sample: {damage.summary()}")
    damage.warn(keep.size)
    cells, values, setpoint = cells[keep], values[keep], setpoint[keep]
    N = keep.size
    col = {name: values[:, j] for j, name in enumerate(names)}
    groups = {g: np.stack([col[f"{g}_{i}"] for i in range(1, n + 1)], axis=1).reshape(N, n) for g in CABLE_GROUPS}
    phase = np.char.strip(cells[:, index["phase"]]) if "phase" in index else np.full(N, "")
    known = set(sample_columns(n))
    extra: dict[str, np.ndarray] = {}
    for name in header:
        if name in known:
            continue
        cs = [c.strip() for c in cells[:, index[name]]]
        try:
            extra[name] = np.array([float(c) if c != "" else np.nan for c in cs], dtype=float)
        except ValueError:
            extra[name] = np.array(cs, dtype=str)
    return Run(
        path=folder,
        meta=meta,
        robot=robot,
        method=method,
        sample_period=period,
        setpoints=setpoints,
        ideal_poses=ideal,
        events=events,
        t=col["t"],
        tau=groups["tau"],
        tau_ref=groups["tau_ref"],
        dl=groups["dl"],
        dsigma=groups["dsigma"],
        roll=col["roll"],
        pitch=col["pitch"],
        dyaw=col["dyaw"],
        phase=np.asarray(phase, dtype=str),
        setpoint=setpoint,
        extra=extra,
    )


# ---------------------------------------------------------------------------------------------- solution


def solution_path(run_path: str | Path) -> Path:
    """Where `cdpr solve` saves its JSON result for a run: RUN/solution.json."""
    return Path(run_path) / SOLUTION_JSON


def read_solution(run_path: str | Path) -> dict[str, Any] | None:
    """The solution saved with a run (the `cdpr solve --json` object), or None when the run is not solved."""
    f = solution_path(run_path)
    if not f.is_file():
        return None
    try:
        data = json.loads(f.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise _fail(f, f"is not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise _fail(f, f"must hold a JSON object, got {type(data).__name__}")
    return data
