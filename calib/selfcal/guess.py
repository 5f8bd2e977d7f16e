"""The start of a solve (Zoffoli Section 3.3): a run's windows, measurement rows and noise, and the initial
guess of zeta_0 and of the rows' poses; :func:`prepare` gives them without the LM solve."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.equilibrium import default_guess, direct_statics
from calib.robot import Robot
from calib.selfcal.lm import solve_poses
from calib.selfcal.model import MeasurementModel
from calib.selfcal.options import SolveOptions
from calib.selfcal.problem import Measurements, Problem
from calib.selfcal.result import TooFewWindows
from calib.selfcal.rows import measurement_rows, noise_levels, run_signals
from calib.selfcal.windows import Window, WindowSearch, search_windows


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


def prepare(robot: Robot, run: Any, options: SolveOptions | None = None, **changes: Any) -> Prepared:
    """Windows, measurement rows, noise and the initial guess of a solve (:func:`calib.selfcal.solve`, same
    ``options`` or keyword changes of them), without the LM solve (the problem a benchmark can hand to another
    solver). Raises SelfCalInputError or TooFewWindows."""
    opts = SolveOptions.of(options, **changes)
    method, noise, stride, model, guess = opts.method, opts.noise, opts.stride, opts.model, opts.guess
    reference_sample, windows, window_options = opts.reference_sample, opts.windows, opts.window_options
    if model is None and noise == "estimate":
        # the noise of window means leaves out the devices' constant errors: carry them as parameters with
        # their datasheet priors (the diagnosis's base model), or the chi2 and the sigmas would ignore them
        from calib.effects import EffectModel
        from calib.effects.priors import DeviceAccuracy

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
