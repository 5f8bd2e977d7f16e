"""Importers of the IRMA L@B logs (the authors' IRMA4U recordings) into `cdpr-run/1` runs.

Two inputs, described in ../shared/data/irma4u/README.md:

- the authors' ``*_parsed.mat`` (MATLAB v5 struct ``st``: absolute cable lengths and swivel angles, i.e.
  with the homing values added; roll, pitch and yaw minus its homing mean, rad; tensions and targets, N);
- the controller's raw text ``.log``: type-3 lines (one per cable per cycle), type-5 AHRS lines in degrees,
  type-6 extras (ignored); a cycle's lines are stamped up to 0.1 ms apart (``acquisition/logcycles.py``).
  It starts with a recording at the homing pose, then a pause, then the experiment. The homing recording
  gives the sensors' readings at the known homing pose.

Both give a run of the prototype (robot ``irma4u``) whose relative channels are referred to the homing
pose: dl = absolute length - homing length, dsigma = absolute swivel - homing swivel, dyaw = yaw - homing
yaw. The homing values are stored in run.yaml under ``homing`` so a solve's sensor offsets can be checked
against them. Time starts at 0 at the first experiment sample; ``time_origin`` keeps the controller's time.

Damaged input follows the run reader's policy (docs/run-format.md): a damaged line of the log, or a damaged
sample of the .mat, is skipped and counted (:class:`acquisition.damage.DamageLog`), and :func:`irma_run`
says so in one warning, or refuses, nothing written, when fewer than ``MIN_HOLDS`` setpoint holds remain.

The two inputs differ in one respect (measured on sc_8_final): the authors' parser recomputes the cable
lengths from the motor counts with one transmission ratio for all winches (0.0280645 m/rev), whereas the
controller's ``cable_length`` uses each winch's own ratio (0.028807, 0.028652, 0.028448, 0.028641 m/rev,
as in the robot description). The raw-log import keeps the controller's lengths, so its dl are those of
the parsed import times 1.0265, 1.0209, 1.0137, 1.0206 per cable. All other channels agree to rounding.
The parser's lengths fit the robot's geometry better: at the authors' 8 picked samples, a pose fitted to
the 4 swivels and 4 lengths (AHRS roll and pitch fixed; weights 1 deg, 0.01 m) leaves chi2 = 5.4 with the
parser's lengths and 52 with the controller's, so the raw import carries a 1.4-2.6 % length-scale error.
Nothing here corrects it: the raw import's diagnosis finds it (length_scale), and what it does to the two
routes' solves is measured in docs/effects.md ("Two imports of one run") and benchmarks/bench_raw_parsed.py.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.damage import CUT, FIELDS, FOREIGN, VALUE, DamageLog, time_order
from acquisition.logcycles import PARTIAL as PARTIAL
from acquisition.logcycles import group_cycles
from acquisition.runlog import Run, float_or_nan, read_run
from acquisition.runwriter import new_run, write_run
from acquisition.segmentation import SetpointSegmentation, segment_targets
from calib.errors import CdprError

MISSING = "samples missing from a field"
MIN_HOLDS = 2  # steady setpoint holds a run needs to be solved (tlse: two equilibrium windows)

# Homing pose of the IRMA4U prototype: absolute values the homing procedure establishes (README).
IRMA_HOMING_LENGTHS = (2.27254824660233, 2.27300821626030, 2.27300821626030, 2.27254824660233)  # m
IRMA_HOMING_SWIVELS = (0.568104732474427, -0.568104732474427, 0.568104732474427, -0.568104732474427)  # rad
IRMA_SAMPLE_PERIOD = 0.1  # s, controller logging period
IRMA_CABLES = 4
LOG_ACTUATOR_FIELDS = (
    "op_mode",
    "motor_position",
    "motor_speed",
    "motor_torque",
    "cable_length",
    "cable_speed",
    "cable_tension",
    "target",
    "aux_position",
    "state",
    "pulley_angle",
)
# raw-log fields kept as extra columns of the run (per cable: name_1..name_4)
LOG_EXTRA_FIELDS = ("motor_position", "motor_speed", "motor_torque", "cable_speed", "aux_position", "op_mode", "state")
LOG_INT_FIELDS = ("op_mode", "motor_position", "motor_speed", "motor_torque", "aux_position", "state")


class IrmaImportError(CdprError, ValueError):
    """An IRMA file that cannot be imported; the message names the file, the field or line, and the value."""


@dataclass
class IrmaSignals:
    """The experiment part of an IRMA recording, in SI units and radians, N samples and 4 cables.

    ``dl``, ``dsigma``, ``dyaw`` are relative to the homing pose; ``t`` is the controller time (s).
    """

    t: np.ndarray
    tension: np.ndarray
    target: np.ndarray
    dl: np.ndarray
    dsigma: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    dyaw: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    homing: dict[str, Any] = field(default_factory=dict)
    damage: DamageLog | None = None  # what the reader skipped; irma_run warns or refuses


# ------------------------------------------------------------------------------------------ parsed .mat


def read_irma_parsed(file: str | Path) -> IrmaSignals:
    """Read the authors' ``*_parsed.mat`` (struct ``st``) into homing-relative signals."""
    file = Path(file)
    try:
        data = _loadmat(file)
    except Exception as exc:  # noqa: BLE001 - scipy raises many kinds on a damaged file; each is one sentence
        raise IrmaImportError(f"{file}: not a readable MATLAB v5 file ({type(exc).__name__}: {exc}).") from exc
    if "st" not in data:
        names = ", ".join(k for k in data if not k.startswith("__")) or "none"
        raise IrmaImportError(f"{file}: variable 'st' is missing (variables found: {names}).")
    st = data["st"]
    if st.dtype.names is None or st.size != 1:
        raise IrmaImportError(f"{file}: variable 'st' must be a 1x1 struct, got an array of shape {st.shape}.")
    st = st.reshape(-1)[0]

    def fld(name: str, rows: int | None) -> np.ndarray:
        if name not in st.dtype.names:
            raise IrmaImportError(f"{file}: field 'st.{name}' is missing.")
        try:
            a = np.asarray(st[name], dtype=float)
        except (TypeError, ValueError):
            raise IrmaImportError(f"{file}: field 'st.{name}' does not hold numbers.") from None
        if rows is None:
            a = a.reshape(-1)
        elif a.ndim != 2 or a.shape[0] != rows:
            raise IrmaImportError(f"{file}: field 'st.{name}' has shape {a.shape}, expected ({rows}, N).")
        return a

    arrays = {"t": fld("t", None)[None, :], "epsilon": fld("epsilon", 3)}
    for name in ("cable_length", "swivel", "tensions", "target_tensions"):
        arrays[name] = fld(name, IRMA_CABLES)
    damage = DamageLog(file)
    lengths = {name: a.shape[1] for name, a in arrays.items()}
    N = min(lengths.values())
    if N < 1:
        raise IrmaImportError(f"{file}: field 'st.{min(lengths, key=lengths.get)}' is empty.")
    longest = max(lengths, key=lengths.get)
    if lengths[longest] > N:
        short = min(lengths, key=lengths.get)
        damage.add(MISSING, f"first: field 'st.{short}' has {N} samples, 'st.{longest}' {lengths[longest]}",
                   lengths[longest] - N)
    values = np.concatenate([a[:, :N] for a in arrays.values()]).T  # (N, 20): t first
    ok = np.isfinite(values).all(axis=1)
    if not ok.all():
        j = int(np.flatnonzero(~ok)[0])
        damage.add(VALUE, f"first: sample {j} (index {j + 1} in MATLAB)", int(np.count_nonzero(~ok)))
    good = np.flatnonzero(ok)
    keep = good[time_order(values[good, 0], values[good], [f"sample {j}" for j in good], damage)]
    if keep.size == 0:
        raise IrmaImportError(f"{file}: no usable sample; damaged input: {damage.summary()}.")
    arrays = {name: a[:, keep] for name, a in arrays.items()}
    t = arrays["t"][0]
    eps = arrays["epsilon"]
    return IrmaSignals(
        t=t,
        tension=arrays["tensions"].T.copy(),
        target=arrays["target_tensions"].T.copy(),
        dl=arrays["cable_length"].T - np.array(IRMA_HOMING_LENGTHS),
        dsigma=arrays["swivel"].T - np.array(IRMA_HOMING_SWIVELS),
        roll=eps[0].copy(),
        pitch=eps[1].copy(),
        dyaw=eps[2].copy(),  # already yaw minus its homing mean
        homing={"lengths": list(IRMA_HOMING_LENGTHS), "swivels": list(IRMA_HOMING_SWIVELS), "yaw": 0.0},
        damage=damage,
    )


# ------------------------------------------------------------------------------------------- raw .log


def read_irma_log(file: str | Path, min_pause: float = 1.0) -> IrmaSignals:
    """Read the controller's raw log: homing recording, pause (> ``min_pause`` s), then the experiment.

    A logging cycle is the 4 cable lines and the AHRS line stamped together, up to 1-2 ms apart
    (:func:`acquisition.logcycles.group_cycles`), at its AHRS line's time; a cycle lacking a line is skipped.
    Cable lengths are the controller's (m), pulley angles change sign to become swivel angles, AHRS angles
    go from degrees to radians. The homing means of length, pulley angle and yaw define the zeros.
    """
    file = Path(file)
    damage = DamageLog(file)
    lines = file.read_bytes().decode("ascii", errors="replace").split("\n")
    if lines[-1] == "":
        lines.pop()
    else:
        damage.add(CUT, f"line {len(lines)}")
        lines.pop()
    stamps: list[float] = []
    keys: list[int] = []  # cable 0..3, AHRS 4
    numbers: list[int] = []
    readings: list[list[float]] = []
    ahrs_lines = 0  # type-5 lines, damaged ones included: none at all is said plainly
    for k, line in enumerate(lines, start=1):
        line = line.strip()
        if not line:
            continue  # a blank line holds no reading: nothing is lost
        cells = line.split(",")
        kind = cells[0].strip()
        ahrs_lines += kind == "5"
        if kind == "6":
            continue  # type 6: extras, not used
        if kind not in ("3", "5"):
            damage.add(FOREIGN, f"first: line {k} of type {kind[:20]!r}")
            continue
        expected = 14 if kind == "3" else 5
        if len(cells) != expected:
            damage.add(FIELDS, f"first: line {k} (type {kind}) has {len(cells)} fields, expected {expected}")
            continue
        vals = [float_or_nan(c) for c in cells[1:]]
        if not all(math.isfinite(v) for v in vals):
            bad = next(c for c, v in zip(cells[1:], vals, strict=True) if not math.isfinite(v))
            damage.add(VALUE, f"first: line {k} has the value {bad.strip()!r}")
            continue
        if kind == "3":
            cid = int(vals[1])
            if vals[1] != cid or not 0 <= cid < IRMA_CABLES:
                damage.add(FOREIGN, f"first: line {k} has actuator id {cells[2].strip()!r}, expected 0..3")
                continue
            keys.append(cid)
            readings.append(vals[2:])
        else:
            keys.append(IRMA_CABLES)
            readings.append(vals[1:] + [0.0] * (len(LOG_ACTUATOR_FIELDS) - 3))  # roll, pitch, yaw; padded
        stamps.append(vals[0])
        numbers.append(k)
    key = np.array(keys, dtype=int)
    values = np.array(readings, dtype=float).reshape(len(keys), len(LOG_ACTUATOR_FIELDS))
    cycles = group_cycles(np.array(stamps), key, np.array(numbers, dtype=int), values, IRMA_CABLES + 1, damage)
    if np.any(key < IRMA_CABLES) and not ahrs_lines:
        raise IrmaImportError(
            f"{file}: the log has no AHRS line (type 5) at all, only cable lines, so it holds no roll, pitch or yaw "
            "and cannot be imported."
        )
    if not cycles.t.size:
        raise IrmaImportError(
            f"{file}: no complete logging cycle (4 type-3 lines and a type-5 line stamped together)"
            + (f"; damaged input: {damage.summary()}." if damage else ".")
        )
    t_all = cycles.t
    A = values[cycles.rows[:, :IRMA_CABLES]]  # (cycles, 4, 11)
    E = np.radians(values[cycles.rows[:, IRMA_CABLES], :3])  # (cycles, 3) rad
    gaps = np.flatnonzero(np.diff(t_all) > min_pause)
    if gaps.size == 0:
        raise IrmaImportError(
            f"{file}: no pause longer than {min_pause} s, so no homing recording before the experiment was found."
        )
    split = int(gaps[0]) + 1
    hom, exp = slice(0, split), slice(split, None)
    f = {name: A[:, :, j] for j, name in enumerate(LOG_ACTUATOR_FIELDS)}
    length_hom = f["cable_length"][hom].mean(axis=0)
    pulley_hom = f["pulley_angle"][hom].mean(axis=0)
    yaw_hom = E[hom, 2].mean()
    extra: dict[str, np.ndarray] = {}
    for name in LOG_EXTRA_FIELDS:
        col = f[name][exp]
        for i in range(IRMA_CABLES):
            c = col[:, i]
            extra[f"{name}_{i + 1}"] = c.astype(np.int64) if name in LOG_INT_FIELDS and np.all(c == np.round(c)) else c
    homing = {
        "lengths": list(IRMA_HOMING_LENGTHS),
        "swivels": list(IRMA_HOMING_SWIVELS),
        "yaw": 0.0,
        "recording": {
            "t": [float(t_all[0]), float(t_all[split - 1])],
            "samples": split,
            "cable_length": [float(x) for x in length_hom],
            "pulley_angle": [float(x) for x in pulley_hom],
            "yaw_deg": math.degrees(float(yaw_hom)),
        },
    }
    return IrmaSignals(
        damage=damage,
        t=t_all[exp],
        tension=f["cable_tension"][exp],
        target=f["target"][exp],
        dl=f["cable_length"][exp] - length_hom,
        dsigma=-(f["pulley_angle"][exp] - pulley_hom),  # the pulley angle has the opposite sign
        roll=E[exp, 0],
        pitch=E[exp, 1],
        dyaw=E[exp, 2] - yaw_hom,
        extra=extra,
        homing=homing,
    )


# ------------------------------------------------------------------------------------------- setpoints


def read_irma_targets(file: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """The planned setpoints (k, 4) N and ideal poses (k, 6), or None, of an experiment: the authors'
    ``sc_control_target_*.mat`` (struct ``out``) or the controller's ``tension_target_*.csv``
    (:func:`read_tension_targets`, setpoints only)."""
    file = Path(file)
    with open(file, "rb") as fh:
        if not fh.read(10).startswith(b"MATLAB"):
            return read_tension_targets(file), None
    try:
        data = _loadmat(file)
    except (ValueError, TypeError, OSError, NotImplementedError) as exc:
        raise IrmaImportError(f"{file}: not a readable MATLAB v5 file ({exc}).") from exc
    if "out" not in data or data["out"].dtype.names is None:
        raise IrmaImportError(f"{file}: struct variable 'out' is missing.")
    out = data["out"].reshape(-1)[0]
    for name in ("static_tensions", "opt_meas_config"):
        if name not in out.dtype.names:
            raise IrmaImportError(f"{file}: field 'out.{name}' is missing.")
    tens = np.asarray(out["static_tensions"], dtype=float)
    poses = np.asarray(out["opt_meas_config"], dtype=float)
    if tens.ndim != 2 or tens.shape[0] != IRMA_CABLES:
        raise IrmaImportError(f"{file}: field 'out.static_tensions' has shape {tens.shape}, expected (4, k).")
    if poses.shape != (6, tens.shape[1]):
        raise IrmaImportError(
            f"{file}: field 'out.opt_meas_config' has shape {poses.shape}, expected (6, {tens.shape[1]})."
        )
    return tens.T.copy(), poses.T.copy()


def read_tension_targets(file: str | Path) -> np.ndarray:
    """The controller's setpoint file ``tension_target_*.csv``: one line per cable (4), one comma-separated
    column per setpoint in the order applied, N, no header. Returns the setpoints (k, 4)."""
    file = Path(file)
    rows = [line for line in file.read_bytes().decode("ascii", errors="replace").splitlines() if line.strip()]
    if len(rows) != IRMA_CABLES:
        raise IrmaImportError(f"{file}: {len(rows)} lines, expected {IRMA_CABLES} (--targets takes a "
                              "sc_control_target_*.mat, or a tension_target_*.csv: one line of setpoint tensions "
                              "per cable, as the controller reads it).")
    cells = [r.split(",") for r in rows]
    k = len(cells[0])
    for i, c in enumerate(cells, start=1):
        if len(c) != k:
            raise IrmaImportError(f"{file}: line {i} has {len(c)} values, line 1 has {k}.")
        bad = next((v for v in c if not 0.0 < float_or_nan(v) < math.inf), None)
        if bad is not None:
            raise IrmaImportError(f"{file}: line {i} has the value {bad.strip()[:20]!r}, not a tension in N.")
    return np.array([[float(v) for v in c] for c in cells]).T.copy()


def _check_targets(file: Path, targets: Path, seg: SetpointSegmentation, t: np.ndarray) -> None:
    """Refuse a target list whose setpoints the run's holds do not follow (another experiment's file)."""
    unmatched = [(a, b) for a, b in seg.plateaus if seg.index[a] < 0]
    if unmatched:
        a = unmatched[0][0]
        raise IrmaImportError(
            f"{targets}: its {len(seg.setpoints)} setpoints do not match {file.name}: {len(unmatched)} of the run's "
            f"{len(seg.plateaus)} holds follow none of them (the first at {t[a] - t[0]:.1f} s); give the targets "
            "of this experiment."
        )


def _setpoint_doubts(file: Path, seg: SetpointSegmentation, t: np.ndarray) -> str | None:
    """One sentence on what the setpoints found without targets may have wrong, or None."""
    said = []
    if seg.rest is not None:
        a, b = seg.rest
        said.append(f"the hold at {t[a] - t[0]:.1f}-{t[b] - t[0]:.1f} s, entered by a jump of the reference from the "
                    "pretension, is taken for the rest before the sequence, not a setpoint")
    if seg.dropped:
        when = ", ".join(f"{t[a] - t[0]:.1f} s" for a, _ in seg.dropped)
        said.append(f"{len(seg.dropped)} move(s) cut short (at {when}) whose destination is in doubt are not "
                    "taken for setpoints")
    if not said:
        return None
    return (f"{file}: setpoints found without --targets: {'; '.join(said)}; {len(seg.setpoints)} setpoints kept "
            "(give --targets to check them).")


# ------------------------------------------------------------------------------------------------ import


def detect_irma_format(file: str | Path) -> str:
    """'parsed' for a MATLAB v5 file, 'log' for the controller's text log."""
    file = Path(file)
    if not file.is_file():
        raise IrmaImportError(f"{file}: no such file.")
    with open(file, "rb") as fh:
        head = fh.read(1024)
    if head.startswith(b"MATLAB 5.0"):
        return "parsed"
    if head.startswith(b"MATLAB 7.3") or head[:8] == b"\x89HDF\r\n\x1a\n":
        raise IrmaImportError(f"{file}: MATLAB v7.3 (HDF5) files are not supported; save the struct with -v7.")
    if not head.strip():
        raise IrmaImportError(f"{file}: the file is empty (neither a MATLAB v5 *_parsed.mat nor a controller log).")
    first = head.split(b"\n", 1)[0].strip()
    if any(line.strip()[:2] in (b"3,", b"5,", b"6,") for line in head.split(b"\n")[:-1]):
        return "log"  # a record among the first lines (a damaged first line is the reader's to skip)
    raise IrmaImportError(
        f"{file}: neither a MATLAB v5 *_parsed.mat nor a controller log (it starts with {first[:20]!r})."
    )


def irma_run(file: str | Path, targets: str | Path | None = None) -> Run:
    """An IRMA recording (``*_parsed.mat`` or raw ``.log``) as a run in memory (path None).

    ``targets`` (optional): the ``sc_control_target_*.mat`` (planned setpoints and ideal poses) or the
    ``tension_target_*.csv`` (setpoints) of the same experiment; every hold of the run must follow one of its
    setpoints, else the import is refused. Without it the setpoints are those found steady in the target
    tensions, and one warning says which of them are in doubt (:func:`segment_targets`).
    """
    file = Path(file)
    kind = detect_irma_format(file)
    sig = read_irma_parsed(file) if kind == "parsed" else read_irma_log(file)
    planned = read_irma_targets(targets) if targets is not None else None
    from calib.robot import load_robot

    seg = segment_targets(sig.target, IRMA_SAMPLE_PERIOD, setpoints=None if planned is None else planned[0],
                          bounds=(0.0, load_robot("irma4u").tau_max), measured=sig.tension)
    if len(seg.plateaus) < MIN_HOLDS:
        damaged = f"; damaged input: {sig.damage.summary()}" if sig.damage else ""
        raise IrmaImportError(
            f"{file}: {len(seg.plateaus)} steady setpoint hold(s) in the experiment ({len(sig.t)} samples), a solve "
            f"needs at least {MIN_HOLDS}{damaged}."
        )
    if planned is not None:
        _check_targets(file, Path(targets), seg, sig.t)
    if sig.damage:
        sig.damage.warn(len(sig.t), stacklevel=2)
    doubts = None if planned is not None else _setpoint_doubts(file, seg, sig.t)
    if doubts:
        warnings.warn(doubts, UserWarning, stacklevel=2)
    t0 = float(sig.t[0])
    meta_extra: dict[str, Any] = {
        "homing": sig.homing,
        "time_origin": t0,
        "imported_from": file.name,
        "zeroing": "relative channels referred to the homing pose (dl, dsigma, dyaw = value - homing value)",
    }
    if planned is not None:
        meta_extra["targets_from"] = Path(targets).name
    return new_run(
        "irma4u",
        "equilibrium",
        IRMA_SAMPLE_PERIOD,
        f"import:irma-{kind}",
        t=np.round(sig.t - t0, 6),
        tau=sig.tension,
        tau_ref=sig.target,
        dl=sig.dl,
        dsigma=sig.dsigma,
        roll=sig.roll,
        pitch=sig.pitch,
        dyaw=sig.dyaw,
        phase=seg.phase,
        setpoint=seg.index,
        setpoints=seg.setpoints if len(seg.setpoints) else None,
        ideal_poses=None if planned is None else planned[1],
        extra=sig.extra,
        meta_extra=meta_extra,
    )


def import_irma(
    file: str | Path,
    out_dir: str | Path,
    targets: str | Path | None = None,
    overwrite: bool = False,
) -> Run:
    """Convert an IRMA recording into a run folder (see :func:`irma_run`) and return it as read back."""
    write_run(out_dir, irma_run(file, targets), overwrite=overwrite)
    return read_run(out_dir)


def _loadmat(file: Path):
    """scipy.io.loadmat as the importers call it (scipy.io imported here: ~0.1 s that other commands skip)."""
    import scipy.io

    with warnings.catch_warnings():
        # a MATLAB workspace saved whole (the authors' ws_selfcalibration_*.mat holds `st` beside function handles
        # and objects) has variables scipy cannot name: it warns "Duplicate variable name 'None'" for each, in
        # two lines. The importers read `st` or `out` alone, which such a variable never is.
        warnings.filterwarnings("ignore", message="Duplicate variable name", category=scipy.io.matlab.MatReadWarning)
        return scipy.io.loadmat(str(file), squeeze_me=False, struct_as_record=True)
