"""A run's signals, measurement rows and noise levels: the rows the solve fits (equilibrium window means,
samples at a stride, or both), the direction each reading was approached from, and the sigmas of each noise
choice (``paper``, ``sensors``, ``estimate``)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from calib.robot import NoiseLevels, Robot
from calib.selfcal.model import CHANNELS
from calib.selfcal.noise import window_mean_noise
from calib.selfcal.options import NOISE
from calib.selfcal.problem import Measurements
from calib.selfcal.result import SelfCalFailure, SelfCalInputError
from calib.selfcal.windows import Window

SIGNALS = ("t", "tau", "dl", "dsigma", "roll", "pitch", "dyaw")
# the smallest motion that sets a direction: a cable's friction in its pulleys reverses once the rope has
# slid, i.e. after more than its elastic pre-sliding stretch (a few N of friction over EA / l ~ 20 kN/m:
# ~0.25 mm); a load cell's hysteresis loop is set by a load excursion well above the noise (0.1-0.5 N)
APPROACH_LENGTH = 5e-4  # m
APPROACH_TENSION = 2.0  # N
APPROACH_SWIVEL = 1e-3  # rad (0.06 deg, twice the swivel encoders' accuracy)


def approach_directions(x: np.ndarray, at: np.ndarray, threshold: float) -> np.ndarray:
    """Per sample index in ``at`` (m,) and channel, the sign of the last change of x (N, c) larger than
    ``threshold`` before that sample: sign(x[at] - x[j]) for the latest j < at with |x[at] - x[j]| >
    threshold; 0 where x never moved that much. (m, c)."""
    at = np.asarray(at, int)
    m, c = at.shape[0], x.shape[1]
    out = np.zeros((m, c))
    todo = np.ones((m, c), bool)
    block = 128  # backwards in blocks, every sample and channel at once: the last large change is usually near
    for lag0 in range(1, int(at.max(initial=0)) + 1, block):
        j = at[:, None] - np.arange(lag0, lag0 + block)[None, :]  # (m, block), latest first
        d = x[at][:, None, :] - x[np.maximum(j, 0)]  # (m, block, c)
        big = (np.abs(d) > threshold) & (j >= 0)[..., None] & todo[:, None, :]
        hit = big.any(axis=1)
        first = big.argmax(axis=1)[:, None, :]  # the smallest lag: the latest such j
        out[hit] = np.sign(np.take_along_axis(d, first, axis=1)[:, 0, :])[hit]
        todo &= ~hit
        if not todo.any():
            break
    return out


def sensor_noise(robot: Robot) -> dict[str, np.ndarray]:
    """Standard deviation of one reading per channel from the sensors' specifications (N, m, rad)."""
    s, n = robot.sensors, robot.n
    per_rev = np.abs(np.asarray(s.length_per_motor_rev, float)) if s.length_per_motor_rev else np.full(n, 0.03)
    length = s.motor_encoder_accuracy / (2 * math.pi) * np.broadcast_to(per_rev, (n,))
    return {
        "tension": np.full(n, s.load_cell_uncertainty),
        "length": np.maximum(length, 1e-6),
        "swivel": np.full(n, s.swivel_encoder_accuracy),
        "orientation": np.array([s.ahrs_roll_pitch_accuracy, s.ahrs_roll_pitch_accuracy, s.ahrs_yaw_accuracy]),
    }


def paper_noise(robot: Robot, levels: NoiseLevels | None = None) -> dict[str, np.ndarray]:
    """Eq. 18 noise levels (robot.noise) as per-channel arrays."""
    lv, n = levels or robot.noise, robot.n
    return {
        "tension": np.full(n, lv.tension),
        "length": np.full(n, lv.length),
        "swivel": np.full(n, lv.swivel),
        "orientation": np.full(3, lv.orientation),
    }


def run_signals(robot: Robot, run: Any) -> dict[str, np.ndarray]:
    """The run's arrays, checked: present, right shapes, finite."""
    n = robot.n
    sig: dict[str, np.ndarray] = {}
    for name in SIGNALS:
        if getattr(run, name, None) is None:
            raise SelfCalInputError(f"run: signal '{name}' is missing.")
        a = np.asarray(getattr(run, name), dtype=float)
        want = (n,) if name in ("tau", "dl", "dsigma") else ()
        if a.ndim != 1 + len(want) or a.shape[1:] != want:
            shape = f"(N, {n})" if want else "(N,)"
            raise SelfCalInputError(f"run: signal '{name}' has shape {a.shape}, expected {shape}.")
        sig[name] = a
    N = sig["t"].shape[0]
    if N < 3:
        raise SelfCalInputError(f"the run holds {N} samples; a solve needs at least 3.")
    for name, a in sig.items():
        if a.shape[0] != N:
            raise SelfCalInputError(f"run: signal '{name}' has {a.shape[0]} samples, 't' has {N}.")
        bad = ~np.isfinite(a.reshape(N, -1)).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SelfCalInputError(f"run: signal '{name}' is not a finite number at sample {i} (value {a[i]}).")
    ref = getattr(run, "tau_ref", None)
    sig["tau_ref"] = None if ref is None else np.asarray(ref, dtype=float)
    tr = sig["tau_ref"]
    if tr is not None and (tr.shape != sig["tau"].shape or not np.isfinite(tr).all()):
        sig["tau_ref"] = None
    return sig


def measurement_rows(
    sig: dict[str, np.ndarray], windows: list[Window], method: str, stride: int, ref_sample: int | None
) -> tuple[Measurements, int, Window | None, dict[str, np.ndarray], list[int]]:
    """Measurement rows for a method; returns the rows, the reference sample, its window, the reference
    readings and, per row, the window index (or -1)."""
    N = sig["t"].shape[0]
    ref_win = None
    if ref_sample is None:
        if windows:
            ref_win = windows[0]
            ref_sample = ref_win.middle
        else:
            ref_sample = 0
    else:
        if not 0 <= ref_sample < N:
            raise SelfCalInputError(f"reference sample {ref_sample} is outside the run (0..{N - 1}).")
        ref_win = next((w for w in windows if w.first <= ref_sample <= w.last), None)
    ori = np.stack([sig["roll"], sig["pitch"], sig["dyaw"]], 1)

    def mean(x, w):
        return x[w.slice].mean(axis=0)

    if ref_win is not None:
        ref = {k: mean(sig[k], ref_win) for k in ("tau", "dl", "dsigma")} | {"ori": mean(ori, ref_win)}
    else:
        ref = {k: sig[k][ref_sample] for k in ("tau", "dl", "dsigma")} | {"ori": ori[ref_sample]}
    rows_tau, rows_dl, rows_ds, rows_ori, samples, spans, win_of = [], [], [], [], [], [], []
    if method in ("tlse", "hybrid"):
        for j, w in enumerate(windows):
            if w is ref_win:
                continue
            rows_tau.append(mean(sig["tau"], w))
            rows_dl.append(mean(sig["dl"], w))
            rows_ds.append(mean(sig["dsigma"], w))
            rows_ori.append(mean(ori, w))
            samples.append(w.middle)
            spans.append((w.first, w.last))
            win_of.append(j)
    if method in ("lse", "hybrid"):
        taken = np.zeros(N, bool)
        if ref_win is not None:
            taken[ref_win.slice] = True
        taken[ref_sample] = True
        if method == "hybrid":
            for w in windows:
                taken[w.slice] = True
        idx = np.arange(0, N, max(1, stride))
        idx = idx[~taken[idx]]
        n = sig["tau"].shape[1]
        rows_tau.extend(np.full((idx.size, n), np.nan))
        rows_dl.extend(sig["dl"][idx])
        rows_ds.extend(sig["dsigma"][idx])
        rows_ori.extend(ori[idx])
        samples.extend(idx.tolist())
        spans.extend([(-1, -1)] * idx.size)
        win_of.extend([-1] * idx.size)
    if not samples:
        raise SelfCalFailure("no measurement rows besides the reference: the run holds a single pose.")
    o = np.array(rows_ori)
    o[:, 2] -= ref["ori"][2]
    static_ref = ref_win is not None and method != "lse"
    # the directions the cables last moved (and their loads last changed) before each row's window starts
    starts = np.array([a if a >= 0 else b for (a, _), b in zip(spans, samples, strict=True)])
    at = np.r_[starts, ref_win.first if ref_win is not None else int(ref_sample)]  # the rows', then the reference's
    length_dir = approach_directions(sig["dl"], at, APPROACH_LENGTH)
    load_dir = approach_directions(sig["tau"], at, APPROACH_TENSION)
    swivel_dir = approach_directions(sig["dsigma"], at, APPROACH_SWIVEL)
    meas = Measurements(
        tau=np.array(rows_tau),
        dl=np.array(rows_dl) - ref["dl"],
        dsigma=np.array(rows_ds) - ref["dsigma"],
        orientation=o,
        ref_tau=ref["tau"] if static_ref else np.full(sig["tau"].shape[1], np.nan),
        ref_orientation=ref["ori"][:2],
        samples=np.array(samples),
        times=sig["t"][np.array(samples)] - sig["t"][int(ref_sample)],
        windows=np.array(spans),
        approach=length_dir[:-1],
        load_approach=load_dir[:-1],
        ref_approach=length_dir[-1],
        ref_load_approach=load_dir[-1],
        swivel_approach=swivel_dir[:-1],
        ref_swivel_approach=swivel_dir[-1],
    )
    return meas, int(ref_sample), ref_win, ref, win_of


def noise_levels(
    robot: Robot, noise: str | NoiseLevels | dict, sig: dict[str, np.ndarray] | None, windows: list[Window]
) -> tuple[dict[str, np.ndarray], str]:
    """Per-channel sigmas for a noise choice: 'paper' (eq. 18), 'sensors' (specifications), 'estimate'."""
    if isinstance(noise, NoiseLevels):
        return paper_noise(robot, noise), "given"
    if isinstance(noise, dict):
        missing = [c for c in CHANNELS if c not in noise]
        if missing:
            raise SelfCalInputError(f"noise: channel '{missing[0]}' is missing.")
        return {c: np.asarray(noise[c], float) for c in CHANNELS}, "given"
    if noise == "paper":
        return paper_noise(robot), noise
    if noise == "sensors":
        return sensor_noise(robot), noise
    if noise == "estimate":
        if sig is None or not windows:
            raise SelfCalInputError("noise 'estimate' needs equilibrium windows in the run; none were found.")
        return window_mean_noise(robot, sig, windows).sigma, noise
    raise SelfCalInputError(f"noise '{noise}' is not one of {', '.join(NOISE)}.")
