"""Runs in the `cdpr-run/1` format (../shared/spec/run-format.md): reader, writers, solution file.

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
import os
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import yaml

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


class DamagedInputWarning(UserWarning):
    """A reader or importer skipped damaged lines (or samples) of a file: one warning per file, counting them."""


# Why a line or sample is skipped (or repaired): the same words for every format (docs/run-format.md).
CUT = "cut short (the log was cut while writing it)"
FIELDS = "wrong number of fields"
VALUE = "a non-numeric or non-finite value"
FOREIGN = "not a record of the format"
REPEATED = "repeated (same time, same values; kept once)"
CONFLICT = "same time as another line with other values"
ORDER = "out of time order (put back in place, nothing skipped)"


@dataclass
class DamageLog:
    """What a reader skipped in one file, by reason, with the first place each reason was met.

    ``unit`` names what is counted ("line", "sample", "cycle"). :meth:`warn` issues the one
    :class:`DamagedInputWarning` line; :meth:`summary` is the same text for an error sentence.
    """

    file: Path
    counts: dict[str, int] = field(default_factory=dict)
    first: dict[str, str] = field(default_factory=dict)

    def add(self, reason: str, where: str, count: int = 1) -> None:
        """Count ``count`` damaged items for ``reason``; ``where`` says where the first was (e.g. "line 57")."""
        if count <= 0:
            return
        self.counts[reason] = self.counts.get(reason, 0) + count
        self.first.setdefault(reason, where)

    def __bool__(self) -> bool:
        return bool(self.counts)

    def summary(self) -> str:
        """'2 wrong number of fields (first: line 31 has 25 values), 1 repeated (...) (line 9)'."""
        return ", ".join(f"{c} {r} ({self.first[r]})" for r, c in self.counts.items())

    def warn(self, kept: int, stacklevel: int = 3) -> None:
        """One warning line naming the file, what was skipped and why, and how many samples were kept."""
        if self:
            warnings.warn(f"{self.file}: damaged input: {self.summary()}; {kept} samples kept.",
                          DamagedInputWarning, stacklevel=stacklevel)


def time_order(t: np.ndarray, values: np.ndarray, places: Sequence[str], damage: DamageLog) -> np.ndarray:
    """Indices of the samples to keep, in time order, under the damage policy: samples out of order are put
    back in place; a sample repeated with the same values is kept once; samples that share a time with other
    values are all skipped (which one is right cannot be told). ``values`` (N, m) finite, ``places`` (N,)
    names each sample for the message."""
    N = t.shape[0]
    if N == 0:
        return np.zeros(0, dtype=int)
    late = np.flatnonzero(t[1:] < np.maximum.accumulate(t)[:-1]) + 1
    if late.size:
        damage.add(ORDER, places[int(late[0])], late.size)
    order = np.argsort(t, kind="stable")
    ts = t[order]
    keep = np.ones(N, dtype=bool)
    repeats = np.flatnonzero(ts[1:] == ts[:-1]) + 1
    for start in np.unique(np.searchsorted(ts, ts[repeats], side="left")):
        end = int(np.searchsorted(ts, ts[start], side="right"))
        group = order[start:end]
        if np.all(values[group] == values[group[0]]):
            keep[start + 1 : end] = False
            damage.add(REPEATED, places[int(group[1])], group.size - 1)
        else:
            keep[start:end] = False
            damage.add(CONFLICT, places[int(group[0])], group.size)
    return order[keep]


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


def new_run(
    robot_spec: str | Mapping[str, Any] | Robot,
    method: str,
    sample_period: float,
    source: str,
    *,
    t: Any,
    tau: Any,
    tau_ref: Any,
    dl: Any,
    dsigma: Any,
    roll: Any,
    pitch: Any,
    dyaw: Any,
    phase: Any = None,
    setpoint: Any = None,
    setpoints: Any = None,
    ideal_poses: Any = None,
    extra: Mapping[str, Any] | None = None,
    meta_extra: Mapping[str, Any] | None = None,
) -> Run:
    """A run in memory (path None) from arrays, checked for shapes; write it with :func:`write_run`."""
    spec, robot = _robot_spec(robot_spec)
    meta = _base_meta(spec, method, sample_period, source, setpoints, ideal_poses, robot.n, meta_extra)
    tt = np.asarray(t, dtype=float).reshape(-1)
    N, n = tt.shape[0], robot.n

    def cab(name: str, a: Any) -> np.ndarray:
        arr = np.asarray(a, dtype=float)
        if arr.shape != (N, n):
            raise ValueError(f"new_run: '{name}' has shape {arr.shape}, expected ({N}, {n}).")
        return arr

    def sca(name: str, a: Any) -> np.ndarray:
        arr = np.asarray(a, dtype=float).reshape(-1)
        if arr.shape != (N,):
            raise ValueError(f"new_run: '{name}' has {arr.shape[0]} samples, expected {N}.")
        return arr

    ph = np.full(N, "", dtype=object) if phase is None else np.asarray(phase, dtype=object).reshape(-1)
    sp = np.full(N, -1, dtype=int) if setpoint is None else np.asarray(setpoint, dtype=int).reshape(-1)
    if ph.shape != (N,) or sp.shape != (N,):
        raise ValueError(f"new_run: 'phase' and 'setpoint' must have {N} samples.")
    ext = {}
    for k, v in (extra or {}).items():
        arr = np.asarray(v)
        if arr.shape != (N,):
            raise ValueError(f"new_run: extra column '{k}' has shape {arr.shape}, expected ({N},).")
        ext[k] = arr
    pro = meta["procedure"]
    return Run(
        path=None,
        meta=meta,
        robot=robot,
        method=method,
        sample_period=float(sample_period),
        setpoints=None if "setpoints" not in pro else np.array(pro["setpoints"], dtype=float),
        ideal_poses=None if "ideal_poses" not in pro else np.array(pro["ideal_poses"], dtype=float),
        events=meta["events"],
        t=tt,
        tau=cab("tau", tau),
        tau_ref=cab("tau_ref", tau_ref),
        dl=cab("dl", dl),
        dsigma=cab("dsigma", dsigma),
        roll=sca("roll", roll),
        pitch=sca("pitch", pitch),
        dyaw=sca("dyaw", dyaw),
        phase=np.array([str(p) for p in ph], dtype=str) if N else np.array([], dtype=str),
        setpoint=sp,
        extra=ext,
    )


# ----------------------------------------------------------------------------------------------- writing


def format_value(v: Any) -> str:
    """One CSV cell: ints as ints, floats with repr (round-trip exact), text as is (no commas allowed)."""
    if isinstance(v, bool | np.bool_):
        return "1" if v else "0"
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        return repr(float(v))
    s = str(v)
    if "," in s or "\n" in s or "\r" in s:
        raise ValueError(f"text value {s!r} cannot be written to samples.csv (contains a comma or newline).")
    return s


def to_plain(obj: Any) -> Any:
    """Plain Python data (lists, dicts, floats) from numpy scalars and arrays, for YAML and JSON."""
    if isinstance(obj, np.ndarray):
        return to_plain(obj.tolist())
    if isinstance(obj, Mapping):
        return {str(k): to_plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_plain(v) for v in obj]
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def _robot_spec(robot_spec: str | Mapping[str, Any] | Robot) -> tuple[Any, Robot]:
    """(what run.yaml stores under 'robot', the Robot)."""
    if isinstance(robot_spec, Robot):
        spec = to_plain(robot_spec.to_dict())
        if robot_spec.name in builtin_robot_names() and spec == to_plain(load_robot(robot_spec.name).to_dict()):
            return robot_spec.name, robot_spec  # unchanged built-in robot: its name is enough
        return spec, robot_spec
    if isinstance(robot_spec, str):
        if robot_spec not in builtin_robot_names():
            raise ValueError(
                f"robot '{robot_spec}' is not a built-in robot ({', '.join(builtin_robot_names())}); "
                "pass a full description mapping instead."
            )
        return robot_spec, load_robot(robot_spec)
    spec = to_plain(dict(robot_spec))
    return spec, robot_from_dict(spec, "<robot mapping>")


def _base_meta(
    spec: Any,
    method: str,
    sample_period: float,
    source: str,
    setpoints: Any,
    ideal_poses: Any,
    n: int,
    meta_extra: Mapping[str, Any] | None,
) -> dict[str, Any]:
    if method not in METHODS:
        raise ValueError(f"method {method!r} is not one of {', '.join(METHODS)}.")
    if not (isinstance(sample_period, int | float) and math.isfinite(sample_period) and sample_period > 0):
        raise ValueError(f"sample_period {sample_period!r} must be a positive number of seconds.")
    procedure: dict[str, Any] = {"method": method, "sample_period": float(sample_period)}
    if setpoints is not None:
        sp = np.asarray(setpoints, dtype=float)
        if sp.ndim != 2 or sp.shape[1] != n:
            raise ValueError(f"setpoints have shape {sp.shape}, expected (k, {n}).")
        procedure["setpoints"] = to_plain(sp)
    if ideal_poses is not None:
        ip = np.asarray(ideal_poses, dtype=float)
        if ip.ndim != 2 or ip.shape[1] != 6:
            raise ValueError(f"ideal_poses have shape {ip.shape}, expected (k, 6).")
        procedure["ideal_poses"] = to_plain(ip)
    meta: dict[str, Any] = {
        "format": FORMAT,
        "robot": spec,
        "created": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "source": source,
        "procedure": procedure,
        "events": [],
    }
    for k, v in (meta_extra or {}).items():
        if k in ("format", "robot", "procedure", "events"):
            raise ValueError(f"meta_extra may not replace the standard key '{k}'.")
        meta[k] = to_plain(v)
    return meta


def _dump_yaml(meta: Mapping[str, Any]) -> str:
    return yaml.safe_dump(to_plain(meta), sort_keys=False, default_flow_style=None, width=120, allow_unicode=True)


def _write_atomic(path: Path, text: str) -> None:
    """Write a file via a temporary file and os.replace, fsynced: readers never see a half-written file."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _prepare_folder(path: Path, overwrite: bool) -> None:
    if path.exists() and not path.is_dir():
        raise FileExistsError(f"{path} exists and is not a folder.")
    if (path / RUN_YAML).exists() or (path / SAMPLES_CSV).exists():
        if not overwrite:
            raise FileExistsError(f"{path} already holds a run (run.yaml or samples.csv); refusing to overwrite it.")
        (path / SOLUTION_JSON).unlink(missing_ok=True)
    path.mkdir(parents=True, exist_ok=True)


def write_run(path: str | Path, run: Run, overwrite: bool = False) -> Run:
    """Write a run folder (run.yaml then samples.csv) and return the run with its path set."""
    path = Path(path)
    _prepare_folder(path, overwrite)
    meta = dict(run.meta)
    meta["format"] = FORMAT
    _write_atomic(path / RUN_YAML, _dump_yaml(meta))
    _write_atomic(path / SAMPLES_CSV, csv_text(run.columns(), len(run)))
    run.path = path
    run.meta = meta
    return run


def csv_text(columns: Mapping[str, np.ndarray], count: int) -> str:
    """CSV text (header and one line per sample) of equally long columns, formatted as samples.csv is."""
    names = list(columns)
    arrays = [columns[k] for k in names]
    kinds = [column_kind(a) for a in arrays]
    lines = [",".join(names)]
    for j in range(count):
        lines.append(",".join(format_cell(a[j], kd) for a, kd in zip(arrays, kinds, strict=True)))
    return "\n".join(lines) + "\n"


def column_kind(a: np.ndarray) -> str:
    """'i' for integer/bool columns, 'f' for float columns, 's' for text."""
    if a.dtype.kind in "iub":
        return "i"
    if a.dtype.kind == "f":
        return "f"
    return "s"


def format_cell(v: Any, kind: str) -> str:
    """One CSV cell of a column of the given kind (see column_kind)."""
    if kind == "i":
        return str(int(v))
    if kind == "f":
        return repr(float(v))
    return format_value(str(v))


class RunWriter:
    """Streams a run to disk during a live acquisition: one flushed line per sample.

    ``append`` writes and flushes one line, ``sync`` fsyncs (call it at each equilibrium window),
    ``add_event`` and ``update_meta`` rewrite run.yaml atomically, ``close`` ends the run. Tensions in N,
    lengths in m, angles in rad, time in s since the start of the run.
    """

    def __init__(
        self,
        path: str | Path,
        robot_spec: str | Mapping[str, Any] | Robot,
        method: str,
        sample_period: float,
        source: str,
        setpoints: Any = None,
        ideal_poses: Any = None,
        extra_columns: Sequence[str] = (),
        meta_extra: Mapping[str, Any] | None = None,
        overwrite: bool = False,
    ):
        self.path = Path(path)
        spec, self.robot = _robot_spec(robot_spec)
        self.meta = _base_meta(spec, method, sample_period, source, setpoints, ideal_poses, self.robot.n, meta_extra)
        self.extra_columns = tuple(extra_columns)
        std = sample_columns(self.robot.n)
        for c in self.extra_columns:
            if c in std or "," in c or not c:
                raise ValueError(f"extra column name {c!r} is empty, has a comma, or is a standard column.")
        self.columns = std + list(self.extra_columns)
        _prepare_folder(self.path, overwrite)
        _write_atomic(self.path / RUN_YAML, _dump_yaml(self.meta))
        self._fh = open(self.path / SAMPLES_CSV, "w", encoding="utf-8", newline="\n")  # noqa: SIM115
        self._fh.write(",".join(self.columns) + "\n")
        self._fh.flush()
        self.count = 0

    def append(
        self,
        t: float,
        tau: Iterable[float],
        tau_ref: Iterable[float],
        dl: Iterable[float],
        dsigma: Iterable[float],
        roll: float,
        pitch: float,
        dyaw: float,
        phase: str = "",
        setpoint: int = -1,
        **extra: Any,
    ) -> None:
        """Write one sample (one line) and flush it."""
        if self._fh is None:
            raise ValueError(f"{self.path}: the run is closed; no more samples can be appended.")
        n = self.robot.n
        cells = [repr(float(t))]
        for name, vec in (("tau", tau), ("tau_ref", tau_ref), ("dl", dl), ("dsigma", dsigma)):
            v = np.asarray(vec, dtype=float).reshape(-1)
            if v.shape[0] != n:
                raise ValueError(f"{self.path}: '{name}' has {v.shape[0]} values, expected {n}.")
            cells += [repr(float(x)) for x in v]
        cells += [repr(float(roll)), repr(float(pitch)), repr(float(dyaw))]
        cells += [format_value(str(phase)), str(int(setpoint))]
        unknown = set(extra) - set(self.extra_columns)
        if unknown:
            raise ValueError(f"{self.path}: unknown extra column(s) {sorted(unknown)}; declare them in extra_columns.")
        cells += [format_value(extra[c]) if c in extra else "" for c in self.extra_columns]
        self._fh.write(",".join(cells) + "\n")
        self._fh.flush()
        self.count += 1

    def sync(self) -> None:
        """Force the lines written so far to the disk (fsync)."""
        if self._fh is not None:
            self._fh.flush()
            os.fsync(self._fh.fileno())

    def add_event(self, t: float, kind: str, message: str) -> None:
        """Append an event {t, kind, message} to run.yaml (atomic rewrite)."""
        self.meta["events"].append({"t": float(t), "kind": str(kind), "message": str(message)})
        _write_atomic(self.path / RUN_YAML, _dump_yaml(self.meta))

    def update_procedure(self, setpoints: Any, ideal_poses: Any) -> None:
        """Replace the planned setpoints (k, n) and ideal poses (k, 6) (a sequential plan grows as it goes)."""
        m, pro = self.meta, self.meta["procedure"]
        fresh = _base_meta(m["robot"], pro["method"], pro["sample_period"], m["source"], setpoints, ideal_poses,
                           self.robot.n, None)
        m["procedure"] = fresh["procedure"]
        _write_atomic(self.path / RUN_YAML, _dump_yaml(m))

    def update_meta(self, **keys: Any) -> None:
        """Add or replace extra top-level keys of run.yaml (e.g. where the sensors were zeroed)."""
        for k in keys:
            if k in ("format", "robot", "procedure", "events"):
                raise ValueError(f"update_meta may not replace the standard key '{k}'.")
        self.meta.update(to_plain(keys))
        _write_atomic(self.path / RUN_YAML, _dump_yaml(self.meta))

    def close(self) -> None:
        """Flush, fsync and close samples.csv."""
        if self._fh is not None:
            self.sync()
            self._fh.close()
            self._fh = None

    def __enter__(self) -> RunWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


# ----------------------------------------------------------------------------------------------- reading


def _fail(file: Path, what: str) -> RunFormatError:
    return RunFormatError(f"{file}: {what}.")


def _read_meta(folder: Path) -> dict[str, Any]:
    f = folder / RUN_YAML
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


def write_solution(run_path: str | Path, solution: Mapping[str, Any]) -> Path:
    """Save a solution next to the run (atomic write), deterministic JSON with sorted keys."""
    f = solution_path(run_path)
    _write_atomic(f, json.dumps(to_plain(solution), indent=2, sort_keys=True, allow_nan=False) + "\n")
    return f
