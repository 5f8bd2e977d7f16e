"""The sequential startup (issue 19): the next pose chosen for information per second, the online estimate
after each window and the stop rule.

The run's own estimate (:func:`run_estimate`) is ``cdpr solve --noise estimate`` on the samples logged so far;
:class:`OnlineSolve` solves the window means itself when that estimate is not available. The choice of the next
pose is :class:`SequentialDesign` over the candidates of :func:`calib.design.candidates`;
:func:`sequential_acquisition` is the loop of choice, window, estimate and stop rule, as a generator the routine
(``acquisition/startup.py``) drives. The information and the noise the choice weighs are those of
:mod:`calib.design`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from calib.design import (
    CandidateSet,
    PoseNoise,
    TimeModel,
    information,
    lateral_stiffness,
    planning_model,
    position_sigma,
)
from calib.robot import Robot
from calib.selfcal import Measurements


@dataclass
class SequentialDesign:
    """The next pose of a sequential startup, among the reachable candidates not yet visited.

    Without a tolerance: the one with the largest expected information gain per second of robot time from
    the current setpoint. The gain of a candidate is the increase of the position precision 1/sigma^2
    (1/m^2) it brings, sigma the predicted position sigma of the rows acquired so far with and without it
    (before any row, the precision is zero); the cost is the transition from where the platform is plus
    settling and holding. (On the IRMA4U this reaches a tolerance with fewer poses than the gain
    log(sigma_now / sigma_with_it).)

    With a ``tolerance`` (m, set by :func:`sequential_acquisition`): the first pose of the quickest way to
    the tolerance and back to tau0 the design can foresee. For each of the ``lookahead`` candidates of best
    gain per second (and every candidate that reaches the tolerance alone) it rolls out the gain-per-second
    choice until the predicted position sigma is below the tolerance (at most ``horizon`` poses, at least
    ``min_poses`` in all), adds the return to tau0, and takes the candidate whose roll-out ends first; the
    plain gain-per-second choice when no roll-out reaches the tolerance. With ``reference_first`` (the
    first pose's window is the solve's reference, :class:`OnlineSolve`) the first pose adds no row: its
    roll-outs start from the reference's information alone. The noise the rows are weighed
    with is the current one (:meth:`reweigh`), so the plan is replanned after every window.

    ``update`` replaces the accumulated information with that of the current solution (its poses and
    zeta_0), so the choice follows what was actually measured.
    """

    cands: CandidateSet
    time_model: TimeModel
    tolerance: float | None = None
    min_poses: int = 2
    lookahead: int = 24
    horizon: int = 6
    reference_first: bool = False  # the first pose's window is the reference: it adds no row (OnlineSolve)
    pose_noise: PoseNoise | None = None  # how the noise the candidates were weighed with depends on the pose
    visited: np.ndarray = field(init=False)
    total: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.visited = np.zeros(self.cands.size, bool)
        self.total = self.cands.info0.copy()

    def update(self, estimate: OnlineEstimate) -> None:
        """Take the information of the solve after the last window (the inverse of its covariance)."""
        self.total = np.linalg.inv(estimate.covariance)

    def reweigh(self, robot: Robot, noise: dict[str, np.ndarray], zeta0: np.ndarray) -> None:
        """Weigh the candidates with ``noise`` (the run's own window-mean sigmas so far) at the current
        estimate of zeta_0 from now on (about 0.05 s for 2300 candidates). With a ``pose_noise`` (the noise's
        dependence on the pose the candidates were chosen with), ``noise`` sets its level at the poses visited
        so far (:meth:`PoseNoise.matched`) and the candidates keep their differences."""
        if self.pose_noise is not None and self.visited.any():
            at = np.flatnonzero(self.visited)
            stiff = lateral_stiffness(robot, self.cands.poses[at], self.cands.setpoints[at])
            noise = self.pose_noise.matched(robot, stiff, noise)
        info0, info = information(robot, self.cands.poses, zeta0, noise)
        self.cands = dataclasses.replace(self.cands, info=info, info0=info0)
        if not self.visited.any():
            self.total = info0

    def _rates(self, total: np.ndarray, current: np.ndarray,
               free: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gain of precision per second from tensions ``current``, sigma after each candidate, cost (s)."""
        now = float(position_sigma(total))
        after = position_sigma(total[None] + self.cands.info)
        gain = 1.0 / after**2 - (1.0 / now**2 if np.isfinite(now) else 0.0)
        tm = self.time_model
        cost = tm.transition(current[None], self.cands.setpoints) + tm.settle + tm.hold
        return np.where(free, gain / cost, -np.inf), after, cost

    def _finish(self, c: int, total: np.ndarray, free: np.ndarray, done: int) -> float:
        """Robot time (s) from after candidate ``c``'s window to the tolerance and back to tau0 by the
        gain-per-second roll-out (``total`` includes c, ``done`` windows so far); inf if not foreseen."""
        tm, sp, tau0 = self.time_model, self.cands.setpoints, self.cands.tau0
        t, cur, free = 0.0, c, free.copy()
        for _ in range(self.horizon + 1):
            if done >= self.min_poses and float(position_sigma(total)) < self.tolerance:
                return t + float(tm.transition(sp[cur], tau0))
            if done >= self.horizon or not free.any():
                break
            rate, _, cost = self._rates(total, sp[cur], free)
            j = int(np.argmax(rate))
            t, cur, done, total = t + float(cost[j]), j, done + 1, total + self.cands.info[j]
            free[j] = False
        return math.inf

    def next(self, current: np.ndarray) -> int | None:
        """Index of the next candidate from tensions ``current`` (n,) N, or None when all are visited."""
        free = ~self.visited
        if not free.any():
            return None
        rate, after, cost = self._rates(self.total, current, free)
        j = int(np.argmax(rate))
        if self.tolerance is not None:
            done = int(self.visited.sum()) + 1
            alone = np.flatnonzero(free & (after < self.tolerance)) if done >= self.min_poses else np.array([], int)
            order = np.argsort(-rate)[: min(self.lookahead, int(free.sum()))]
            best = math.inf
            ref = self.reference_first and not self.visited.any()  # c would be the reference, not a row
            for c in dict.fromkeys([*order.tolist(), *alone.tolist()]):
                f = free.copy()
                f[c] = False
                t = float(cost[c]) + self._finish(c, self.total + (0.0 if ref else self.cands.info[c]), f, done)
                if t < best:
                    best, j = t, int(c)
        self.visited[j] = True
        return j


@dataclass(frozen=True)
class WindowMean:
    """Mean readings of one equilibrium window: tensions (n,) N, length and swivel deltas (n,) m and rad,
    roll, pitch and yaw delta (3,) rad (deltas since the sensors were zeroed); ``noise``, when given, the
    sigma of a window mean per channel estimated from the run's samples so far
    (:func:`calib.selfcal.window_mean_noise`, or the noise the run's own solve weighed its rows with), which
    the online solve and the next choice then use; ``estimate``, when given, the run's own solve with this
    window (``cdpr solve --noise estimate`` on the samples so far, planning-model parameters), which the
    online solve then takes as its estimate instead of solving the window means itself."""

    tau: np.ndarray
    dl: np.ndarray
    dsigma: np.ndarray
    orientation: np.ndarray
    noise: dict[str, np.ndarray] | None = None  # the run's window-mean sigmas from its samples so far
    estimate: OnlineEstimate | None = None  # the run's own solve with this window, when it could be made


@dataclass(frozen=True)
class OnlineEstimate:
    """The solve after a window: theta, row poses (k, 6), theta covariance (None before the first solve),
    position sigma (m, inf before the first solve), iterations."""

    theta: np.ndarray
    poses: np.ndarray
    covariance: np.ndarray | None
    position_sigma: float
    iterations: int

    @classmethod
    def of(cls, theta: np.ndarray, poses: np.ndarray, covariance: np.ndarray, iterations: int) -> OnlineEstimate:
        """An estimate with its position sigma: sqrt of the trace of the covariance's position block (m)."""
        return cls(theta, poses, covariance, float(np.sqrt(max(np.trace(covariance[:3, :3]), 0.0))), iterations)


class OnlineSolve:
    """The tau-l-sigma-epsilon solve of the windows acquired so far, warm-started from the previous solution
    (a few LM iterations per window); the window under tau0 (``reference``) is the reference (zeta_0), or,
    with ``first_is_reference``, the first pose's window, as the solve of the run does (its window search
    leaves the rest under tau0 before the sequence out): that window gives no estimate yet (its
    ``covariance`` is None, its 1-sigma inf) and zeta_0 is then the pose there."""

    def __init__(self, robot: Robot, noise: dict[str, np.ndarray], reference: WindowMean, zeta0_guess: np.ndarray,
                 first_is_reference: bool = False):
        self.robot = robot
        self.noise = noise
        self.ref = reference
        self.first_is_reference = first_is_reference
        self.rows: list[WindowMean] = []
        self.model = planning_model(robot)
        self.theta = self.model.initial_params(np.asarray(zeta0_guess, float))
        self.poses = np.zeros((0, 6))

    def refresh(self, windows: list[WindowMean]) -> None:
        """Replace the reference and the rows added so far (in order) with ``windows``, e.g. the equilibrium
        windows the run's window search finds now; ignored before the reference or on a count mismatch."""
        if self.first_is_reference or len(windows) != len(self.rows) + 1:
            return
        self.ref, self.rows = windows[0], list(windows[1:])

    def add(self, window: WindowMean, pose_guess: np.ndarray) -> OnlineEstimate:
        """Add a window (its pose guessed at ``pose_guess``, e.g. the planned ideal pose) and solve again."""
        from calib.selfcal import solve

        if window.noise is not None:
            self.noise = {c: np.asarray(v, float) for c, v in window.noise.items()}
        if self.first_is_reference:
            self.first_is_reference, self.ref = False, window
            self.theta = self.model.initial_params(np.asarray(pose_guess, float))
            return OnlineEstimate(self.theta, self.poses, None, math.inf, 0)
        self.rows.append(window)
        if window.estimate is not None:  # the run's own solve: the final solve's noise, reference and windows
            est = window.estimate
            self.theta = np.asarray(est.theta, float)
            if est.poses.shape[0] == len(self.rows):  # a warm start for a later solve of the means
                self.poses = np.asarray(est.poses, float)
            else:
                self.poses = np.vstack([self.poses, np.asarray(pose_guess, float)[None]])
            return est
        ref = self.ref
        ori = np.array([w.orientation for w in self.rows])
        ori[:, 2] -= ref.orientation[2]
        meas = Measurements(
            np.array([w.tau for w in self.rows]), np.array([w.dl for w in self.rows]) - ref.dl,
            np.array([w.dsigma for w in self.rows]) - ref.dsigma, ori, ref.tau, ref.orientation[:2],
        )
        poses0 = np.vstack([self.poses, np.asarray(pose_guess, float)[None]])
        sol = solve(self.robot, meas, method="tlse", noise=self.noise, guess=(self.theta, poses0), model=self.model)
        self.theta, self.poses = sol.theta, sol.poses
        return OnlineEstimate.of(sol.theta, sol.poses, sol.covariance, sol.iterations)


def sequential_acquisition(design: SequentialDesign, online: OnlineSolve, tolerance: float, max_poses: int,
                           history: list[tuple[int, OnlineEstimate]], min_poses: int = 2):
    """The sequential startup's choice and stop rule, as a generator: it yields the index of the next candidate
    (from the home tensions, then from the last one visited) and is sent the :class:`WindowMean` acquired
    there; after each window it solves again, appends (candidate, estimate) to ``history`` and stops when the
    position 1-sigma is below ``tolerance`` m (after at least ``min_poses`` windows: the run's solve needs
    two). Its return value (``StopIteration.value``) is why it stopped: 'tolerance' or 'exhausted'."""
    current = design.cands.tau0
    design.tolerance, design.min_poses = tolerance, min_poses
    design.reference_first = online.first_is_reference
    for j in range(max_poses):
        c = design.next(current)
        if c is None:
            break
        window = yield c
        est = online.add(window, design.cands.poses[c])
        if est.covariance is not None:
            design.update(est)
        if window.noise is not None:
            design.reweigh(online.robot, online.noise, est.theta[:6])
        history.append((c, est))
        current = design.cands.setpoints[c]
        if est.position_sigma < tolerance and j + 1 >= min_poses:
            return "tolerance"
    return "exhausted"


def drive(steps, acquire) -> str:
    """Run a :func:`sequential_acquisition` generator with ``acquire(candidate) -> WindowMean``; returns why
    it stopped."""
    try:
        c = next(steps)
        while True:
            c = steps.send(acquire(c))
    except StopIteration as stop:
        return stop.value


MIN_RUN_SOLVE_ROWS = 2  # rows (poses after the reference) before the run's own solve gives the online estimate


def _signals(rows: list[tuple]) -> dict[str, np.ndarray]:
    """The run's arrays from the rows logged so far (each a :meth:`StartupRoutine._row` tuple)."""
    names = ("t", "tau", "tau_ref", "dl", "dsigma", "roll", "pitch", "dyaw")
    return {name: np.array([r[i] for r in rows]) for i, name in enumerate(names)}


def run_estimate(robot: Robot, rows: list[tuple], setpoints: np.ndarray, ideal_poses: np.ndarray,
                 min_rows: int = MIN_RUN_SOLVE_ROWS) -> tuple[OnlineEstimate, dict[str, np.ndarray]] | None:
    """What ``cdpr solve --noise estimate`` gives on the rows logged so far (``setpoints`` (k, n) N and
    ``ideal_poses`` (k, 6) the plan's so far, as run.yaml holds them): the online estimate of a sequential
    startup with the noise, the reference's noise and the device priors the final solve will have, and the
    noise its rows were weighed with. Its theta and covariance are those of the planning model's parameters
    (:func:`calib.design.planning_model`: zeta_0 and the devices' constant errors; the reference window's
    noise marginalised out). None while the run holds fewer than ``min_rows`` rows or the solve fails."""
    from types import SimpleNamespace

    from calib.design import planning_model
    from calib.selfcal import SelfCalFailure, SelfCalInputError, solve

    run = SimpleNamespace(**_signals(rows), setpoints=np.asarray(setpoints, float),
                          ideal_poses=np.asarray(ideal_poses, float))
    try:
        sol = solve(robot, run, noise="estimate")
    except (SelfCalFailure, SelfCalInputError, np.linalg.LinAlgError):
        return None
    if sol.poses.shape[0] < min_rows:
        return None
    p = planning_model(robot).n_params
    est = OnlineEstimate.of(sol.theta[:p], sol.poses, sol.covariance[:p, :p], sol.iterations)
    return est, {c: np.asarray(v, float) for c, v in sol.noise.items()}


def detected_windows(robot: Robot, rows: list[tuple], setpoints: np.ndarray
                     ) -> tuple[dict[int, tuple], frozenset[int]]:
    """The equilibrium windows the solve's window search finds in the rows logged so far (each a
    :meth:`StartupRoutine._row` tuple; ``setpoints`` (k, n) N: tau0 and the setpoints visited), which
    ``cdpr solve`` will use at the end: per setpoint index found, the window's mean readings (tau, dl, dsigma,
    roll/pitch/yaw), and the setpoint indices whose window is only a quasi window (the stillest stretch: no
    still run long enough)."""
    from calib.selfcal import search_windows

    sig = _signals(rows)
    wins = search_windows(robot, sig["t"], sig["tau"], sig["dl"], sig["dsigma"], sig["roll"], sig["pitch"],
                          sig["tau_ref"], setpoints).used
    ori = np.stack([sig["roll"], sig["pitch"], sig["dyaw"]], 1)
    means = {w.setpoint: (sig["tau"][w.slice].mean(0), sig["dl"][w.slice].mean(0), sig["dsigma"][w.slice].mean(0),
                          ori[w.slice].mean(0)) for w in wins if w.setpoint >= 0}
    return means, frozenset(w.setpoint for w in wins if w.quasi and w.setpoint >= 0)
