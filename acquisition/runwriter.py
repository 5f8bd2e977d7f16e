"""Making and writing runs in the `cdpr-run/1` format (../shared/spec/run-format.md): a run from arrays and
its metadata (:func:`new_run`), a whole run written (:func:`write_run`), a run as it is logged
(:class:`RunWriter`, fsynced at every window) and the solution file (:func:`write_solution`).

Numbers are written with ``repr`` (shortest string that reads back to the same float), so writing is
lossless and deterministic: the same values give the same bytes.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from acquisition.runlog import (
    FORMAT,
    METHODS,
    RUN_YAML,
    SAMPLES_CSV,
    SOLUTION_JSON,
    Run,
    sample_columns,
    solution_path,
)
from calib.robot import Robot, builtin_robot_names, load_robot, robot_from_dict


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
        self.save_meta()
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
        self.record_event(t, kind, message)
        self.save_meta()

    def record_event(self, t: float, kind: str, message: str) -> None:
        """Append an event {t, kind, message} to the run's metadata in memory; :meth:`save_meta` writes it
        (the control loop records on its own thread and leaves the rewrite to its log worker)."""
        self.meta["events"].append({"t": float(t), "kind": str(kind), "message": str(message)})

    def save_meta(self) -> None:
        """Rewrite run.yaml from the metadata in memory (atomic)."""
        _write_atomic(self.path / RUN_YAML, _dump_yaml(self.meta))

    def update_procedure(self, setpoints: Any, ideal_poses: Any) -> None:
        """Replace the planned setpoints (k, n) and ideal poses (k, 6) (a sequential plan grows as it goes)."""
        m, pro = self.meta, self.meta["procedure"]
        fresh = _base_meta(m["robot"], pro["method"], pro["sample_period"], m["source"], setpoints, ideal_poses,
                           self.robot.n, None)
        m["procedure"] = fresh["procedure"]
        self.save_meta()

    def update_meta(self, **keys: Any) -> None:
        """Add or replace extra top-level keys of run.yaml (e.g. where the sensors were zeroed)."""
        for k in keys:
            if k in ("format", "robot", "procedure", "events"):
                raise ValueError(f"update_meta may not replace the standard key '{k}'.")
        self.meta.update(to_plain(keys))
        self.save_meta()

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



def write_solution(run_path: str | Path, solution: Mapping[str, Any]) -> Path:
    """Save a solution next to the run (atomic write), deterministic JSON with sorted keys."""
    f = solution_path(run_path)
    _write_atomic(f, json.dumps(to_plain(solution), indent=2, sort_keys=True, allow_nan=False) + "\n")
    return f
