"""Exporters of runs (and their solutions, where solved) for researchers who solve offline.

- ``mat``: MATLAB v5 file with a struct ``st`` laid out like the IRMA authors' ``st`` (channels x samples):
  ``t`` (N,), ``epsilon`` (3, N) roll, pitch, yaw; ``cable_length``, ``swivel``, ``tensions``,
  ``target_tensions`` (n, N). Lengths, swivels and yaw are absolute (offset + delta) when the run has a
  solution, else the deltas; ``absolute`` (logical) says which. Also ``setpoints`` (n, k) and
  ``ideal_poses`` (6, k) (one column per pose, as the authors' ``out`` struct), ``phase``, ``setpoint``,
  ``extra`` (the extra columns), ``meta`` (run.yaml as JSON text) and, when solved, ``solution``.
- ``npz``: every column of samples.csv by name, plus ``meta`` (JSON text), and when solved ``solution``
  (JSON text) and the absolute columns ``length_i``, ``swivel_i``, ``yaw``.
- ``csv``: the run's columns, plus the absolute columns where solved.
- ``mcap``: samples, windows, events and the solution as MCAP channels of JSON messages with JSON Schemas,
  for Foxglove and PlotJuggler (acquisition/export_mcap.py).

SI units and radians throughout.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.runlog import Run, read_solution
from acquisition.runwriter import csv_text, to_plain
from calib.errors import CdprError

FORMATS = ("mat", "npz", "csv", "mcap")


class ExportError(CdprError, ValueError):
    """A run or solution that cannot be exported; the message names the file, field and value."""


def absolute_channels(run: Run, solution: dict[str, Any] | None) -> dict[str, np.ndarray] | None:
    """Absolute lengths (N, n) m, swivels (N, n) rad and yaw (N,) rad from a solution's sensor offsets."""
    if not solution:
        return None
    origin = f"{run.path / 'solution.json' if run.path else 'solution'}"
    off = solution.get("sensor_offsets")
    if not isinstance(off, dict):
        raise ExportError(f"{origin}: field 'sensor_offsets' = {off!r} must be a mapping with length, swivel, yaw.")

    def vec(key: str) -> np.ndarray:
        v = off.get(key)
        try:
            a = np.asarray(v, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            a = np.zeros(0)
        if a.shape != (run.n,) or not np.all(np.isfinite(a)):
            raise ExportError(f"{origin}: field 'sensor_offsets.{key}' = {v!r} must be a list of {run.n} numbers.")
        return a

    yaw = off.get("yaw", 0.0)
    if isinstance(yaw, bool) or not isinstance(yaw, int | float) or not np.isfinite(yaw):
        raise ExportError(f"{origin}: field 'sensor_offsets.yaw' = {yaw!r} must be a number.")
    return {"length": vec("length") + run.dl, "swivel": vec("swivel") + run.dsigma, "yaw": float(yaw) + run.dyaw}


def export_run(run: Run, fmt: str, out_file: str | Path, solution: dict[str, Any] | None = None) -> Path:
    """Write ``run`` in format ``fmt`` (mat | npz | csv | mcap) to ``out_file``; returns the path written.

    ``solution`` defaults to the run's saved solution (RUN/solution.json) when the run has a path.
    """
    if fmt not in FORMATS:
        raise ExportError(f"format {fmt!r} is not one of {', '.join(FORMATS)}.")
    if solution is None and run.path is not None:
        solution = read_solution(run.path)
    out = Path(out_file)
    if out.parent and not out.parent.exists():
        raise ExportError(f"{out}: the folder {out.parent} does not exist.")
    ab = absolute_channels(run, solution)
    if fmt == "mat":
        _export_mat(run, ab, solution, out)
    elif fmt == "npz":
        _export_npz(run, ab, solution, out)
    elif fmt == "mcap":
        from acquisition.export_mcap import export_mcap

        export_mcap(run, solution, out)
    else:
        _export_csv(run, ab, out)
    return out


def _absolute_columns(run: Run, ab: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    cols = {f"length_{i + 1}": ab["length"][:, i] for i in range(run.n)}
    cols.update({f"swivel_{i + 1}": ab["swivel"][:, i] for i in range(run.n)})
    cols["yaw"] = ab["yaw"]
    return cols


def _mat_name(key: str, used: set[str]) -> str:
    """A valid MATLAB field name (letter first, letters/digits/underscore, at most 63 characters)."""
    name = re.sub(r"[^A-Za-z0-9_]", "_", str(key))
    if not name or not name[0].isalpha():
        name = "x" + name
    name = name[:63]
    base, k = name, 1
    while name in used:
        suffix = f"_{k}"
        name = base[: 63 - len(suffix)] + suffix
        k += 1
    used.add(name)
    return name


def _to_matlab(obj: Any) -> Any:
    """JSON-like data to what scipy.io.savemat writes: dicts to structs, numeric lists to arrays."""
    if isinstance(obj, dict):
        used: set[str] = set()
        return {_mat_name(k, used): _to_matlab(v) for k, v in obj.items()}
    if obj is None:
        return np.zeros((0, 0))
    if isinstance(obj, bool):
        return np.array(obj)
    if isinstance(obj, int | float | str):
        return obj
    if isinstance(obj, list | tuple):
        try:
            a = np.array(obj, dtype=float)
            if a.dtype.kind == "f" and a.ndim >= 1:
                return a
        except (TypeError, ValueError):
            pass
        cell = np.empty(len(obj), dtype=object)
        for j, v in enumerate(obj):
            cell[j] = _to_matlab(v)
        return cell
    return np.asarray(obj)


def _export_mat(run: Run, ab: dict[str, np.ndarray] | None, solution: dict[str, Any] | None, out: Path) -> None:
    used: set[str] = set()
    st: dict[str, Any] = {
        "t": run.t,
        "epsilon": np.vstack([run.roll, run.pitch, ab["yaw"] if ab else run.dyaw]),
        "cable_length": (ab["length"] if ab else run.dl).T,
        "swivel": (ab["swivel"] if ab else run.dsigma).T,
        "tensions": run.tau.T,
        "target_tensions": run.tau_ref.T,
        "absolute": np.array(ab is not None),
        "setpoints": np.zeros((run.n, 0)) if run.setpoints is None else run.setpoints.T,
        "ideal_poses": np.zeros((6, 0)) if run.ideal_poses is None else run.ideal_poses.T,
        "phase": np.array(list(run.phase), dtype=object),
        "setpoint": run.setpoint.astype(np.int32),
        "extra": {_mat_name(k, used): np.asarray(v) for k, v in run.extra.items()},
        "meta": json.dumps(to_plain(run.meta), sort_keys=True),
    }
    if ab is not None:
        st["delta_length"] = run.dl.T
        st["delta_swivel"] = run.dsigma.T
        st["delta_yaw"] = run.dyaw
    if solution is not None:
        st["solution"] = _to_matlab(solution)
    import scipy.io  # here: scipy.io costs every cdpr command ~0.1 s at start-up

    scipy.io.savemat(str(out), {"st": st}, format="5", oned_as="row", long_field_names=True, do_compression=True)


def _export_npz(run: Run, ab: dict[str, np.ndarray] | None, solution: dict[str, Any] | None, out: Path) -> None:
    arrays: dict[str, np.ndarray] = {}
    for k, v in run.columns().items():
        arrays[k] = np.asarray(v, dtype=str) if v.dtype.kind in "OUS" else np.asarray(v)
    if ab is not None:
        arrays.update(_absolute_columns(run, ab))
        arrays["solution"] = np.array(json.dumps(to_plain(solution), sort_keys=True))
    arrays["meta"] = np.array(json.dumps(to_plain(run.meta), sort_keys=True))
    with open(out, "wb") as fh:  # np.savez would append '.npz' to a name lacking it
        np.savez_compressed(fh, **arrays)


def _export_csv(run: Run, ab: dict[str, np.ndarray] | None, out: Path) -> None:
    cols = run.columns()
    if ab is not None:
        cols.update(_absolute_columns(run, ab))
    out.write_text(csv_text(cols, len(run)), encoding="utf-8")
