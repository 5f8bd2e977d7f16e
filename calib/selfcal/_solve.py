"""From a run's signals to a :class:`Solution`: windows, measurement rows, noise, initial guess, LM solve."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.equilibrium import default_guess, direct_statics
from calib.robot import NoiseLevels, Robot
from calib.selfcal.lm import levenberg_marquardt, solve_poses
from calib.selfcal.model import CHANNELS, MeasurementModel
from calib.selfcal.noise import pose_free_noise, rescaled_sigma, variance_factors, window_mean_noise
from calib.selfcal.problem import Measurements, Problem
from calib.selfcal.result import SelfCalFailure, SelfCalInputError, Solution, TooFewWindows, compare_pose
from calib.selfcal.windows import Window, WindowOptions, WindowSearch, search_windows

METHODS = ("tlse", "lse", "hybrid")
NOISE = ("paper", "estimate", "sensors")
REFINE = 2  # estimate-noise solves: pose-free kinematic noise at the solution, then the solve again, twice
VCE_ROUNDS_ROWS = 4  # then variance-component rounds on the window means (noise.rescaled_sigma; settles in 2-3)
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


def _guess(
    robot: Robot, problem: Problem, meas: Measurements, ref_tau: np.ndarray, ref_win: Window | None,
    windows: list[Window], win_of: list[int], ideal: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Section 3.3: zeta_0 from the ideal pose of its setpoint or direct statics; window poses from ideal
    poses or direct statics; other rows by pose estimation from the readings given zeta_0's guess
    (:func:`estimate_poses`)."""

    def ideal_of(w: Window | None) -> np.ndarray | None:
        if ideal is None or w is None or w.setpoint < 0 or w.setpoint >= len(ideal):
            return None
        return np.asarray(ideal[w.setpoint], float)

    home = default_guess(robot, 1)[0]
    z0 = ideal_of(ref_win)
    if z0 is None and not np.all(np.isfinite(ref_tau)):
        z0 = home
    k = meas.k
    Z = np.zeros((k, 6))
    fixed = np.zeros(k, bool)
    need_ds = []
    for i, j in enumerate(win_of):
        if j < 0:
            continue
        zi = ideal_of(windows[j])
        if zi is not None:
            Z[i], fixed[i] = zi, True
        else:
            need_ds.append(i)
    # one direct-statics solve for zeta_0 (when no ideal pose gives it) and the windows, all from home
    tau_ds = ([] if z0 is not None else [ref_tau]) + [meas.tau[i] for i in need_ds]
    if tau_ds:
        # a start for the LM: equilibrium to 1e-6 of the weight (the LM refines it)
        ds = direct_statics(robot, np.array(tau_ds), np.tile(home if z0 is None else z0, (len(tau_ds), 1)), tol=1e-6)
        poses, ok = ds.poses, ds.converged
        if z0 is None:
            z0 = poses[0] if ok[0] else home
            poses, ok = poses[1:], ok[1:]
        rows = np.array(need_ds, dtype=int)
        Z[rows[ok]] = poses[ok]
        fixed[rows[ok]] = True
    Z[~fixed] = z0
    theta0 = problem.model.initial_params(z0)
    # kinematic rows (and windows where direct statics failed): pose estimation from the readings
    free = ~fixed
    if free.any():
        order = np.argsort(meas.samples, kind="stable")
        last = z0
        for i in order:
            if fixed[i] or win_of[i] >= 0:
                last = Z[i]
            else:
                Z[i] = last
        Z = estimate_poses(problem, theta0, Z, free)
    return theta0, Z


def trilaterate(
    robot: Robot, theta0: np.ndarray, dl: np.ndarray, orientation: np.ndarray, near: np.ndarray
) -> np.ndarray:
    """Closed-form pose starts (k, 6): orientation from the AHRS (yaw = zeta_0's yaw + its variation),
    position from the cable lengths l(zeta_0) + dl as spheres about d_i - R a'_i (pulleys neglected: an
    error of the order of their radius). Differences of the sphere equations are linear in the position;
    the direction they leave undetermined (anchors nearly coplanar) is fixed by the spheres themselves,
    taking the root nearer to ``near`` (k, 6)."""
    from calib.kinematics import inverse_kinematics, rotation

    k = dl.shape[0]
    if k == 0:
        return near.copy()
    # the arc wrapped on each pulley (about a quarter turn) is not part of the straight segment
    L = inverse_kinematics(robot, theta0[None, :6]).lengths[0] + dl - robot.r * np.pi / 2  # (k, n)
    ang = orientation.copy()
    ang[:, 2] += theta0[5]
    R = rotation(ang, robot.orientation)
    c = robot.d[None] - np.einsum("kab,nb->kna", R, robot.a_local)  # (k, n, 3)
    A = 2.0 * (c[:, 1:] - c[:, :1])
    b = np.sum(c[:, 1:] ** 2, -1) - np.sum(c[:, :1] ** 2, -1) - L[:, 1:] ** 2 + L[:, :1] ** 2
    _, sv, vh = np.linalg.svd(A)
    p0 = (np.linalg.pinv(A, rcond=1e-2) @ b[..., None])[..., 0]
    nd = vh[:, -1, :] if A.shape[1] >= 3 else np.cross(vh[:, 0, :], vh[:, 1, :])
    weak = sv[:, -1] < 1e-2 * sv[:, 0] if A.shape[1] >= 3 else np.ones(k, bool)
    q = p0[:, None, :] - c  # (k, n, 3)
    bq = np.einsum("ka,kna->kn", nd, q)
    disc = np.clip(bq**2 - (np.sum(q**2, -1) - L**2), 0.0, None)
    t_lo, t_hi = -bq - np.sqrt(disc), -bq + np.sqrt(disc)
    ref = np.einsum("ka,ka->k", nd, near[:, :3] - p0)[:, None]
    t = np.where(np.abs(t_lo - ref) < np.abs(t_hi - ref), t_lo, t_hi).mean(axis=1)
    p = p0 + np.where(weak, t, 0.0)[:, None] * nd
    out = np.c_[p, ang]
    ok = np.all(np.isfinite(out), axis=1)
    out[~ok] = near[~ok]
    return out


def estimate_poses(problem: Problem, theta0: np.ndarray, Z: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Pose estimation of the ``free`` rows from their kinematic readings (lengths, swivels, AHRS) with
    theta fixed, from the starts in Z; rows left far from their readings restart from the nearest row (in
    time) that converged."""
    meas, k = problem.meas, problem.k
    Z = Z.copy()
    rows = np.flatnonzero(free)
    Z[rows] = trilaterate(problem.model.robot, theta0, meas.dl[rows], meas.orientation[rows], Z[rows])
    kin = Problem(problem.model, _kinematic_only(meas), problem.sigma)
    Z, cost = solve_poses(kin, theta0, Z, rows)
    # rows left far from their readings restart from the nearest (in time) row that converged
    for _ in range(4):
        c = cost[rows]
        bad = rows[c > max(50.0, 20.0 * float(np.median(c)))]
        good = np.setdiff1d(rows, bad)
        if not bad.size or not good.size:
            break
        when = meas.samples if meas.samples is not None else np.arange(k)
        near = good[np.abs(when[bad][:, None] - when[good][None, :]).argmin(axis=1)]
        Z[bad] = Z[near]
        Z, c_bad = solve_poses(kin, theta0, Z, bad)
        cost[bad] = c_bad[bad]
    return Z


def _kinematic_only(meas: Measurements) -> Measurements:
    return Measurements(
        np.full_like(meas.tau, np.nan), meas.dl, meas.dsigma, meas.orientation,
        np.full_like(meas.ref_tau, np.nan), meas.ref_orientation, meas.samples, meas.windows, meas.times,
        meas.approach, meas.load_approach, meas.ref_approach, meas.ref_load_approach,
    )


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


@dataclass
class Prepared:
    """A run made ready for the solve: the problem, its start (theta0 (p,), poses0 (k, 6)), the windows and
    what the solution reports of them, and the time marks (perf_counter s) of each step."""

    problem: Problem
    theta0: np.ndarray
    poses0: np.ndarray
    windows: list[Window]
    search: WindowSearch | None
    ref: dict[str, np.ndarray] | None
    ref_sample: int
    noise_source: str
    marks: tuple[float, float, float]  # start, rows done, guess done
    signals: dict[str, np.ndarray] | None = None  # the run's checked arrays (None for rows given directly)


def prepare(
    robot: Robot,
    run: Any,
    method: str = "tlse",
    noise: str | NoiseLevels | dict = "paper",
    stride: int = 1,
    reference_sample: int | None = None,
    windows: list[Window] | None = None,
    window_options: WindowOptions | None = None,
    model: MeasurementModel | None = None,
    guess: tuple[np.ndarray, np.ndarray] | None = None,
) -> Prepared:
    """Windows, measurement rows, noise and the initial guess of :func:`solve_run`, without the LM solve (the
    problem a benchmark can hand to another solver)."""
    if method not in METHODS:
        raise SelfCalInputError(f"method '{method}' is not one of {', '.join(METHODS)}.")
    if int(stride) < 1:
        raise SelfCalInputError(f"stride {stride} must be a positive integer.")
    if model is None and noise == "estimate":
        # the noise of window means leaves out the devices' constant errors: carry them as parameters with
        # their datasheet priors (the diagnosis's base model), or the chi2 and the sigmas would ignore them
        from calib.effects import EffectModel
        from calib.effects.builtin import DeviceAccuracy

        model = EffectModel(robot, [DeviceAccuracy()])
    model = model or MeasurementModel(robot)
    t_start = time.perf_counter()
    search: WindowSearch | None = None
    if isinstance(run, Measurements):
        meas, sig, wins, ref_sample, ref_win, win_of = run, None, list(windows or []), -1, None, [-1] * run.k
        ref = None
    else:
        sig = run_signals(robot, run)
        if windows is None:
            search = search_windows(
                robot, sig["t"], sig["tau"], sig["dl"], sig["dsigma"], sig["roll"], sig["pitch"],
                sig["tau_ref"], getattr(run, "setpoints", None), window_options,
            )
            wins = list(search.used)
        else:
            wins = list(windows)
        if method in ("tlse", "hybrid") and len(wins) < 2:
            failed = "" if search is None else "".join(" " + m.reason for m in search.missing)
            raise TooFewWindows(
                f"{len(wins)} equilibrium window(s) found in the run; method '{method}' needs at least 2.{failed}",
                len(wins),
            )
        meas, ref_sample, ref_win, ref, win_of = measurement_rows(sig, wins, method, int(stride), reference_sample)
    t_rows = time.perf_counter()
    sigma, source = noise_levels(robot, noise, sig, wins)
    problem = Problem(model, meas, sigma)
    if guess is None:
        ref_tau = ref["tau"] if ref is not None else meas.ref_tau
        ideal = getattr(run, "ideal_poses", None)
        theta0, Z0 = _guess(robot, problem, meas, ref_tau, ref_win, wins, win_of, ideal)
    else:
        theta0 = np.asarray(guess[0], float)
        if theta0.shape[0] < model.n_params:
            theta0 = model.initial_params(theta0)
        if guess[1] is None:
            Z0 = estimate_poses(problem, theta0, np.tile(theta0[:6], (meas.k, 1)), np.ones(meas.k, bool))
        else:
            Z0 = np.asarray(guess[1], float).reshape(-1, 6)
    return Prepared(problem, theta0, Z0, wins, search, ref, ref_sample, source,
                    (t_start, t_rows, time.perf_counter()), sig)


def _with_reference_noise(robot: Robot, model, theta: np.ndarray, sigma: dict[str, np.ndarray],
                          windows: np.ndarray | None, ref_size: int):
    """The model with the reference window's noise for these sigmas (builtin.ReferenceNoise.for_rows, in
    place of any earlier one) and theta to match (its values start at 0)."""
    from calib.effects import EffectModel
    from calib.effects.builtin import ReferenceNoise

    kept = [e for e in getattr(model, "effects", []) if not isinstance(e, ReferenceNoise)]
    n_kept = EffectModel(robot, kept).n_params if kept else 6
    new = EffectModel(robot, [*kept, ReferenceNoise.for_rows(sigma, windows, ref_size)])
    return new, np.r_[theta[:n_kept], np.zeros(new.n_params - n_kept)]


def solve_run(
    robot: Robot,
    run: Any,
    method: str = "tlse",
    noise: str | NoiseLevels | dict = "paper",
    stride: int = 1,
    reference_sample: int | None = None,
    windows: list[Window] | None = None,
    window_options: WindowOptions | None = None,
    model: MeasurementModel | None = None,
    guess: tuple[np.ndarray, np.ndarray] | None = None,
    reference_pose: np.ndarray | None = None,
    max_iter: int = 200,
) -> Solution:
    """See :func:`calib.selfcal.solve`."""
    pre = prepare(robot, run, method, noise, stride, reference_sample, windows, window_options, model, guess)
    problem, theta0, Z0, wins, search, ref = pre.problem, pre.theta0, pre.poses0, pre.windows, pre.search, pre.ref
    model, meas, ref_sample, source = problem.model, problem.meas, pre.ref_sample, pre.noise_source
    t_start, t_rows, t_guess = pre.marks
    res = levenberg_marquardt(problem, theta0, Z0, max_iter=max_iter)
    if source == "estimate" and method == "tlse" and ref is not None and res.converged and max_iter > 0:
        # the kinematic channels' window-mean noise without the platform's motion (which the rows' poses
        # absorb), estimated at the solution; a second pass at the better solution settles it
        sig = pre.signals
        base = window_mean_noise(robot, sig, wins)
        ref_win = next(w for w in wins if w.first <= ref_sample <= w.last)
        for _ in range(REFINE):
            spans = [(ref_win.slice, res.theta[:6])] + [
                (slice(int(a), int(b) + 1), z) for (a, b), z in zip(meas.windows, res.poses, strict=True)]
            noise = pose_free_noise(model, sig, spans, ref, res.theta, base).noise
            model, theta = _with_reference_noise(robot, model, res.theta, noise.sigma, meas.windows, ref_win.size)
            problem = Problem(model, meas, noise.sigma)
            res = levenberg_marquardt(problem, theta, res.poses, max_iter=max_iter)
        # the within-window sigmas bound each group's noise of a mean from above (they include motion the
        # means average out, e.g. the force control's ripple, and the share the rows' poses absorb): where
        # the window means scatter less around the fit, variance components bring them down; up only where
        # the model misses a group far beyond its noise (model error, noise.rescaled_sigma); the reference's
        # noise keeps its within-window prior (the fit cannot see the reference's own error)
        within, floor = noise.sigma, sensor_noise(robot)
        for _ in range(VCE_ROUNDS_ROWS):
            shrunk = rescaled_sigma(problem.sigma, variance_factors(problem, res.theta, res.poses), floor)
            if shrunk is None:
                break
            model, theta = _with_reference_noise(robot, model, res.theta, within, meas.windows, ref_win.size)
            problem = Problem(model, meas, shrunk)
            res = levenberg_marquardt(problem, theta, res.poses, max_iter=max_iter)
    t_end = time.perf_counter()
    if max_iter == 0 and np.isfinite(res.cost):  # the guess is a solution already (a converged fit's)
        res.converged, res.message = True, "the given solution, not iterated"
    if not np.isfinite(res.cost) or not res.converged:
        raise SelfCalFailure(f"the solve did not converge after {res.iterations} iterations ({res.message}).")
    dof = problem.n_residuals - (model.n_params + 6 * meas.k)
    resid = {}
    for c, (si, nz) in problem.channel_residuals(res.theta, res.poses, res.evaluation).items():
        if si.size:
            resid[c] = {"rms": float(np.sqrt(np.mean(si**2))), "rms_normalized": float(np.sqrt(np.mean(nz**2)))}
    absolute = model.absolute_readings(res.theta)
    if ref is None:
        offsets = absolute
    else:
        offsets = {
            "length": absolute["length"] - ref["dl"],
            "swivel": absolute["swivel"] - ref["dsigma"],
            "yaw": float(absolute["yaw"] - ref["ori"][2]),
        }
    report = getattr(model, "report", None)
    effects = report(res.theta) if callable(report) else {}
    comparison = None if reference_pose is None else compare_pose(res.theta[:6], reference_pose, robot.orientation)
    return Solution(
        method=method,
        initial_pose=res.theta[:6].copy(),
        initial_pose_sigma=np.sqrt(np.clip(np.diag(res.cov_theta)[:6], 0, None)),
        reference_sample=ref_sample,
        sensor_offsets=offsets,
        poses=res.poses,
        poses_sigma=np.sqrt(np.clip(np.diagonal(res.cov_poses, axis1=1, axis2=2), 0, None)),
        samples=meas.samples if meas.samples is not None else np.full(meas.k, -1),
        windows=wins,
        theta=res.theta,
        param_names=model.param_names,
        covariance=res.cov_theta,
        chi2=2.0 * res.cost,
        dof=int(dof),
        residuals=resid,
        noise={c: [float(v) for v in s] for c, s in problem.sigma.items()},
        noise_source=source,
        iterations=res.iterations,
        converged=res.converged,
        message=res.message,
        timing={
            "solve_s": t_end - t_start,
            "rows_s": t_rows - t_start,
            "guess_s": t_guess - t_rows,
            "lm_s": t_end - t_guess,
        },
        effects=effects,
        reference=comparison,
        window_search=search,
        reference_noise=next((dict(e.sd) for e in getattr(model, "effects", []) if e.name == "reference_noise"), None),
    )
