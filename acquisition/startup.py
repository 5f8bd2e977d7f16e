"""The operator's startup routine (Zoffoli Section 3.2, Fig. 3) on the robot or on the simulated prototype.

connect and check every device -> zero the relative sensors (the power-on readings are stored; the run logs
deltas since then) -> record the initial tensions -> smooth transition to tau0 -> wait for equilibrium ->
start the run log -> for each planned setpoint: quintic tension trajectory, wait until the ripple falls below
the sensors' uncertainty or the noise they show (online detector with a timeout), hold and log the window
(phase ``hold``), then any pause the plan has after it (phase ``pause``, :class:`Pause`) -> for the
kinematic method, a constant-speed path through the workspace logged throughout -> back to tau0 -> solve ->
report. The safety supervisor watches every tick; any stop ends in a safe stop (hold, then ramp down to a safe
pretension), an event in run.yaml and a :class:`StartupStopped` with one sentence.

The run log starts at rest under tau0 (phase ``pretension``, ``hold_time`` seconds), then the planned
setpoints 0..k-1 (run.yaml ``setpoints``/``ideal_poses``, as ``cdpr poses`` plans them); the return to tau0
is logged as phase ``return``; the final rest under tau0 is not logged.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.clock import Clock, loop_runtime
from acquisition.control import ControllerConfig, Rig, Snapshot, TensionController, transmission_radius
from acquisition.equilibrium import DetectorConfig, EquilibriumDetector
from acquisition.estimates import EstimateWorker, LogWorker
from acquisition.plans import Pause, Plan
from acquisition.progress import ProgressBar
from acquisition.runwriter import RunWriter
from acquisition.safety import SafeStop, SafetyLimits, SafetySupervisor
from acquisition.trajectory import PEAK_RATE, TensionTrajectory
from calib.constants import CONTROL_RATE, EXPECTED_SETTLE, HOLD_TIME, MAX_TENSION_RATE, MIN_TRANSITION
from calib.errors import CdprError
from calib.robot import Robot
from calib.sequential import OnlineSolve, WindowMean, detected_windows, sequential_acquisition

METHODS = ("equilibrium", "kinematic")


class StartupStopped(CdprError, RuntimeError):
    """The routine ended in a safe stop; the message is one sentence, ``kind`` the event's kind."""

    def __init__(self, kind: str, message: str, run: Path | None):
        super().__init__(message)
        self.kind = kind
        self.message = message
        self.run = run


@dataclass(frozen=True)
class StartupConfig:
    """Settings of the procedure (SI units)."""

    method: str = "equilibrium"
    rate: float = CONTROL_RATE  # Hz, control rate
    log_period: float = 0.1  # s, logging period (the paper's 100 ms)
    max_tension_rate: float = MAX_TENSION_RATE  # N/s, trajectory rate limit
    min_transition: float = MIN_TRANSITION  # s, shortest transition
    initial_rate: float = 20.0  # N/s, rate of the first transition from the power-on tensions to tau0
    hold_time: float = HOLD_TIME  # s logged in each equilibrium window after detection
    detector: DetectorConfig | None = None  # default: DetectorConfig.for_robot (load-cell uncertainty)
    pretension_timeout: float = 60.0  # s to come to rest under tau0 before the run log starts
    controller: ControllerConfig | None = None
    safety: SafetyLimits | None = None
    kinematic_speed: float = 0.05  # m/s along the kinematic path
    kinematic_spacing: float = 0.05  # m between path waypoints
    device_timeout: float = 1.0  # s (wall) to wait for a tick's readings in lockstep
    expected_settle: float = EXPECTED_SETTLE  # s, for the time-left estimate
    rehold: int = 2  # sequential plans: extra holds at a pose whose window the run's search finds only quasi
    # opt-in: SCHED_FIFO priority (1-99) of the loop's thread on a real clock (acquisition.clock.loop_runtime);
    # None: normal priority. Refused by the OS: a warning, and the loop runs at normal priority
    rt_priority: int | None = None
    # lock the process's memory while a paced loop runs (acquisition.clock.lock_memory); None: with rt_priority
    lock_memory: bool | None = None

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}.")
        if not 200.0 <= self.rate <= 500.0:
            raise ValueError(f"control rate must be within 200..500 Hz, got {self.rate!r}.")
        every = self.log_period * self.rate
        if abs(every - round(every)) > 1e-6 or round(every) < 1:
            raise ValueError(f"log period {self.log_period} s must be a whole number of control periods "
                             f"(1/{self.rate:g} s).")
        if self.rt_priority is not None and not 1 <= self.rt_priority <= 99:
            raise ValueError(f"real-time priority must be within 1..99, got {self.rt_priority!r}.")


@dataclass
class StartupResult:
    run: Path
    windows: list[tuple[int, int]]  # [first, last] sample of each held window, in setpoint order
    ticks: np.ndarray  # (N,) SYNC counter of each logged sample
    robot_time: float  # s of loop time from zeroing to the end
    wall_time: float  # s
    tau_init: np.ndarray  # (n,) N, tensions at power-on
    zero: dict[str, Any]  # the power-on readings the deltas are taken from
    control: dict[str, float]  # loop statistics
    # sequential plan: per window the position 1-sigma (m) and estimate, and why it stopped ("tolerance" or
    # "exhausted"); None for a fixed plan
    sequential: dict[str, Any] | None = None


class StartupRoutine:
    """Runs the procedure on a :class:`Rig` with a :class:`Clock`; writes the run to ``out``."""

    def __init__(self, robot: Robot, rig: Rig, clock: Clock, plan: Plan, out: Path, config: StartupConfig,
                 source: str = "sim", progress: ProgressBar | None = None,
                 supervisor: SafetySupervisor | None = None,
                 on_tick: Callable[[Snapshot], None] | None = None, meta: dict[str, Any] | None = None):
        self.robot = robot
        self.rig = rig
        self.clock = clock
        self.plan = plan
        self.out = Path(out)
        self.cfg = config
        self.source = source
        self.progress = progress
        self.n = robot.n
        ctl_cfg = config.controller or ControllerConfig(rate=config.rate)
        self.controller = TensionController(transmission_radius(robot), ctl_cfg)
        self.supervisor = supervisor or SafetySupervisor(config.safety or SafetyLimits.for_robot(robot), robot.n)
        self.on_tick = on_tick
        self.meta = dict(meta or {})  # extra run.yaml keys (e.g. the previous calibration)
        self.period = 1.0 / config.rate
        self.log_every = int(round(config.log_period * config.rate))
        self.writer: RunWriter | None = None
        self._log_open = False
        self._prerun: list[tuple] = []  # samples logged before the run log starts (written on a stop)
        self._t_run0: float | None = None
        self._ticks: list[int] = []
        self._windows: list[tuple[int, int]] = []
        self._zero: dict[str, np.ndarray] = {}
        self._tau_init = np.zeros(self.n)
        self._last: Snapshot | None = None
        self._ref = np.zeros(self.n)
        self._armed = True  # slack is judged only where the reference keeps a cable taut (safety.py)
        self._phase = "pretension"
        self._setpoint = -1
        self._target = -1  # the setpoint being approached or held, for the progress line
        self._compute: list[float] = []
        self._total_estimate = 1.0
        self._detector: EquilibriumDetector | None = None
        self._held: list | None = None  # the rows logged in the window being held
        self._means: list[WindowMean] = []  # the mean readings of each held window (tau0's first)
        self._log_rows: list[tuple] = []  # the rows logged so far (sequential plan: its own noise estimate)
        self._sequential: dict[str, Any] | None = None
        self._rehold = 0  # extra holds at poses whose window was only quasi (sequential plans)
        self._estimates = EstimateWorker(clock.lockstep)  # the run's own solve after each hold (sequential)
        self._io = LogWorker()  # the run log's file system calls, off the loop's thread
        self._writer_ready = None  # the Future of the RunWriter, asked for as soon as the power-on readings are in
        self._history: list = []  # sequential plan: (candidate, calib.sequential.OnlineEstimate) after each window

    # ---- the loop -------------------------------------------------------------------------------------
    def _tick(self, tau_ref: np.ndarray, log: bool = True, detector: EquilibriumDetector | None = None):
        """One control period: clock, SYNC and readings, safety, control, command, log."""
        tk = self.clock.advance()
        snap = self.rig.tick(tk.index, tk.t, self.cfg.device_timeout)
        c0 = time.perf_counter()
        self._last = snap
        self._ref = np.asarray(tau_ref, dtype=float)
        self._supervise(snap)  # raises SafeStop unless every load cell gives a finite value
        torque = self.controller.update(self._ref, snap.tau, self.period)
        self.rig.command(torque)
        self._compute.append(time.perf_counter() - c0)
        state = None
        if tk.index % self.log_every == 0:
            if log:
                self._log(snap)
            if detector is not None:
                state = detector.push(tk.t, snap.tau, snap.dl, snap.dsigma, snap.roll, snap.pitch)
            if self.progress is not None:
                self.progress.update(tk.t, self._phase, self._target, len(self.plan.setpoints))
        if self.on_tick is not None:
            self.on_tick(snap)
        return snap, state

    def _supervise(self, snap: Snapshot) -> None:
        rig = self.rig
        ages = rig.ages(snap.t)
        for name in rig.dead:
            ages.pop(name, None)
        self.supervisor.check(snap.tau, self._ref, ages, rig.faults(), armed=self._armed)
        for name, count in rig.link_errors().items():
            if count > 0:
                raise SafeStop("corrupted_stream",
                               f"the {name} stream is corrupted: {count} bad frame(s) since the start.")
        tau = snap.tau.tolist()
        if not all(map(math.isfinite, tau)):
            i = next(i for i, v in enumerate(tau) if not math.isfinite(v))
            raise SafeStop("sensor_fault", f"load cell {i + 1} gives no value (disconnected).", (i,))

    def _row(self, snap: Snapshot) -> tuple:
        z = self._zero
        return (snap.t, snap.tau.copy(), self._ref.copy(), snap.dl - z["dl"], snap.dsigma - z["dsigma"],
                snap.roll, snap.pitch, snap.yaw - z["yaw"], self._phase, self._setpoint, snap.sync)

    def _log(self, snap: Snapshot) -> None:
        row = self._row(snap)
        if self._held is not None:
            self._held.append(row)
        if self.writer is None:
            self._prerun.append(row)
            return
        self._write(row)

    @property
    def logged(self) -> int:
        """Samples handed to the run log so far (the next one's row index in samples.csv)."""
        return len(self._ticks)

    def _write(self, row: tuple) -> None:
        t, tau, ref, dl, ds, roll, pitch, dyaw, phase, sp, sync = row
        t0 = self._t_run0 or 0.0
        line = (round(t - t0, 9), tau, ref, dl, ds, roll, pitch, dyaw, phase, sp)
        if self.clock.paced:  # a file write can wait for the file system's journal (361 ms once on a busy disk):
            self._io.submit(partial(self.writer.append, *line, tick=sync))  # the log worker writes it, in order
        else:
            self.writer.append(*line, tick=sync)
        if self.plan.sequential is not None:
            self._log_rows.append((round(t - t0, 9), *row[1:]))
        self._ticks.append(sync)

    def _follow(self, traj: TensionTrajectory, phase: str, setpoint: int = -1) -> None:
        self._phase, self._setpoint = phase, setpoint
        steps = int(math.ceil(traj.duration / self.period))
        for k in range(1, steps + 1):
            self._tick(traj.at(k * self.period))

    def _settle(self, tau: np.ndarray, phase: str, setpoint: int = -1, log: bool = True,
                timeout: float | None = None) -> bool:
        """Hold ``tau`` until the detector says the platform rests; False on its timeout (s)."""
        self._phase, self._setpoint = phase, setpoint
        if self._detector is None:  # one detector for the whole routine: it learns the sensors' noise
            # on a real clock (the robot, or a simulated prototype paced in real time) its thresholds' refresh
            # (3-15 ms) runs on the log worker, as the robot's; on the simulated clock in line (deterministic)
            self._detector = EquilibriumDetector(self.cfg.log_period,
                                                 self.cfg.detector or DetectorConfig.for_robot(self.robot),
                                                 background=self._io.submit if self.clock.paced else None)
        det = self._detector
        det.start(self.clock.now(), timeout)
        while True:
            _, state = self._tick(tau, log=log, detector=det)
            if state is not None and (state.settled or state.timed_out):
                return state.settled

    def _hold(self, tau: np.ndarray, setpoint: int, phase: str = "hold") -> tuple[int, int]:
        """Log the equilibrium window (phase hold); returns its [first, last] sample index."""
        self._phase, self._setpoint = phase, setpoint
        first = self.logged
        steps = int(round(self.cfg.hold_time / self.period))
        self._held = []
        noise, found = None, {}  # the run's own noise: from its own solve, once there is one (below)
        for extra in range(self.cfg.rehold + 1):
            for _ in range(steps):
                self._tick(tau)
            if self.plan.sequential is None:
                break
            # the run's windows, for the online solve; a pose the window search finds only a quasi window for
            # (the detector declared rest on a stretch the search does not call still) is held again, so that
            # the online and the final solve never take a quasi window (above all as the reference)
            visited = np.vstack([self.plan.tau0, self.plan.setpoints])
            found, quasi = detected_windows(self.robot, self._log_rows, visited)
            if setpoint < 0 or (setpoint + 1 in found and setpoint + 1 not in quasi):
                break
            if extra < self.cfg.rehold:
                self._rehold += 1
        estimate = None
        if self.plan.sequential is not None and setpoint >= 0:
            # the run's own solve so far, as `cdpr solve --noise estimate` will make it at the end: its 1-sigma
            # is the one the stop rule compares with the tolerance, its noise weighs the next choice (on a real
            # clock the platform stays held, and logged, while it computes)
            args = (self.robot, list(self._log_rows), self.plan.setpoints.copy(), self.plan.ideal_poses.copy())
            got = self._estimates.compute(args, lambda: self._tick(tau), self.clock.now)
            if got is not None:
                estimate, noise = got
        rows, self._held = self._held, None
        self._means.append(WindowMean(*(np.mean([r[i] for r in rows], axis=0) for i in (1, 3, 4)),
                                      np.mean([r[5:8] for r in rows], axis=0), noise, estimate))
        for k, m in found.items():  # the poses' windows as the final solve will see them (index 0: tau0)
            if 1 <= k < len(self._means):
                self._means[k] = WindowMean(*m, self._means[k].noise, self._means[k].estimate)
        last = self.logged - 1
        self._io.submit(self.writer.sync)
        return first, last

    def _pause(self, at: np.ndarray, pause: Pause) -> np.ndarray:
        """Rest for the pause (back under tau0 first if it says so); returns the tensions it ends at."""
        target = self.plan.tau0 if pause.home else at
        if pause.home:
            self._move_to(at, target, self.cfg.max_tension_rate, "pause")
        self._phase, self._setpoint = "pause", -1
        for _ in range(int(round(pause.seconds / self.period))):
            self._tick(target)
        return target

    def _move_to(self, a: np.ndarray, b: np.ndarray, rate: float, phase: str, setpoint: int = -1) -> None:
        traj = TensionTrajectory(np.stack([a, b]), np.array([max(
            TensionTrajectory.through(np.stack([a, b]), rate).duration, self.cfg.min_transition)]))
        self._follow(traj, phase, setpoint)

    # ---- the procedure ---------------------------------------------------------------------------------
    def _estimate_total(self) -> float:
        sp = np.vstack([self.plan.tau0, self.plan.setpoints, self.plan.tau0])
        moves = np.abs(np.diff(sp, axis=0)).max(axis=1)
        tr = np.maximum(PEAK_RATE * moves / self.cfg.max_tension_rate, self.cfg.min_transition).sum()
        per = self.cfg.expected_settle + self.cfg.hold_time
        total = tr + per * (len(sp) - 1) + 10.0 + sum(p.seconds for p in self.plan.pauses)
        if self.plan.sequential is not None:  # unknown in advance: the longest it may take
            total += self.plan.sequential.max_poses * (per + 2 * self.cfg.min_transition)
        if self.plan.path_times is not None:
            total += float(self.plan.path_times[-1])
        return float(total)

    def zero(self) -> Snapshot:
        """First ticks with the drives off: store the power-on readings and the initial tensions."""
        for _ in range(3):
            tk = self.clock.advance()
            snap = self.rig.tick(tk.index, tk.t, self.cfg.device_timeout)
        if not (np.all(np.isfinite(snap.tau)) and np.all(np.isfinite(snap.dl)) and np.all(np.isfinite(snap.dsigma))
                and math.isfinite(snap.yaw)):
            raise SafeStop("sensor_fault", f"the sensors did not all answer at power-on (missing: "
                           f"{', '.join(snap.missing) or 'values'}).")
        self._zero = {"dl": snap.dl.copy(), "dsigma": snap.dsigma.copy(), "yaw": snap.yaw}
        self._statuses = self.rig.statuses()
        self._tau_init = snap.tau.copy()
        self._last = snap
        return snap

    def enable(self) -> None:
        """Feed-forward of the initial tensions, then the drives' power stages on (brakes released)."""
        self.controller.reset(self._tau_init)
        self._ref = self._tau_init.copy()
        self.rig.command(self.controller.torque_for(self._tau_init))
        for d in self.rig.drives:
            d.enable()
        self._prepare_log()  # on the log worker while the pretension begins (not in the drives' enabling tick)

    def _prepare_log(self) -> None:
        """Create the run folder, run.yaml and samples.csv's header on the log worker (the RunWriter of
        :meth:`start_log`): all it needs is known once the power-on readings are in."""
        plan = self.plan
        meta = {
            "zeroing": {"dl": self._zero["dl"].tolist(), "dsigma": self._zero["dsigma"].tolist(),
                        "yaw": float(self._zero["yaw"]), "tensions": self._tau_init.tolist(),
                        "note": "power-on readings of the relative sensors; the run logs deltas since then"},
            "control": {"rate": self.cfg.rate, "max_tension_rate": self.cfg.max_tension_rate,
                        "hold_time": self.cfg.hold_time},
            "devices": list(getattr(self, "_statuses", [])),
            **({"pauses": [{"after": p.after, "seconds": p.seconds, "home": p.home} for p in plan.pauses]}
               if plan.pauses else {}),
            **self.meta,
        }
        self._writer_ready = self._io.submit(partial(
            RunWriter, self.out, self.robot, self.cfg.method, self.cfg.log_period, self.source,
            setpoints=plan.setpoints if len(plan.setpoints) else None,
            ideal_poses=plan.ideal_poses if len(plan.ideal_poses) else None,
            extra_columns=("tick",), meta_extra=meta, overwrite=True))

    def start_log(self) -> None:
        """The run log starts now (its time zero): the RunWriter :meth:`_prepare_log` asked for."""
        if self._writer_ready is None:
            self._prepare_log()
        self.writer = self._writer_ready.result()
        self._t_run0 = self.clock.now()
        self._log_open = True

    def _close_log(self) -> None:
        if self._log_open:
            self._io.submit(self.writer.close)
            self._log_open = False

    def run(self) -> StartupResult:
        """The whole procedure; raises :class:`StartupStopped` after a safe stop. The interpreter is set up for
        the loop meanwhile (:func:`acquisition.clock.loop_runtime`: no collection of the long-lived heap; the
        configuration's real-time priority and memory locking on a real clock, and then the process's other threads
        one below it)."""
        cfg, paced = self.cfg, self.clock.paced
        lock = paced and (cfg.rt_priority is not None if cfg.lock_memory is None else cfg.lock_memory)
        # under a granted priority the threads that share the interpreter lock (the log worker, the CAN notifier...)
        # run one priority below the loop's: loop_runtime
        with loop_runtime(rt_priority=cfg.rt_priority if paced else None, lock=lock):
            try:
                return self._procedure()
            finally:
                self._io.close()  # the run log's pending writes are on disk before the run or its stop is reported

    def _procedure(self) -> StartupResult:
        wall0 = time.perf_counter()
        self._total_estimate = self._estimate_total()
        if self.progress is not None:
            self.progress.total = self._total_estimate
        try:
            self._supervise(self.zero())  # a stop asked for while connecting ends here, drives still off
            self.rig.mark_links()
            self.enable()
            tau0 = self.plan.tau0
            self._move_to(self._tau_init, tau0, self.cfg.initial_rate, "pretension")
            if not self._settle(tau0, "pretension", timeout=self.cfg.pretension_timeout):
                raise SafeStop("no_equilibrium", f"the platform did not come to rest under tau0 within "
                               f"{self.cfg.pretension_timeout:g} s.")
            self.start_log()
            self._hold(tau0, -1, "pretension")
            if self.cfg.method == "kinematic":
                self._kinematic()
            else:
                prev = tau0
                for j, sp in self._setpoints():
                    self._target = j
                    self._move_to(prev, sp, self.cfg.max_tension_rate, "transition", -1)
                    self._settle(sp, "settle", -1)  # a timeout still gives a (quasi-static) window
                    self._windows.append(self._hold(sp, j))
                    prev = sp
                    for pause in (p for p in self.plan.pauses if p.after == j):
                        prev = self._pause(prev, pause)
                self._move_to(prev, tau0, self.cfg.max_tension_rate, "return", -1)
            self._io.submit(self.writer.sync)
        except SafeStop as stop:
            self._safe_stop(stop)
            raise StartupStopped(stop.kind, stop.message, self.out if self.writer else None) from None
        finally:
            self._estimates.close()
            if self.progress is not None:
                done = self._phase == "return"  # the sequence went through
                self.progress.update(self.progress.total if done else self.clock.now(), "done" if done else "stopped",
                                     -1, len(self.plan.setpoints), force=True)
                self.progress.close()
        self._finish_unlogged()
        comp = np.array(self._compute) if self._compute else np.zeros(1)
        return StartupResult(
            run=self.out, windows=list(self._windows), ticks=np.array(self._ticks), robot_time=self.clock.now(),
            wall_time=time.perf_counter() - wall0, tau_init=self._tau_init,
            zero={k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self._zero.items()},
            control={"ticks": float(len(comp)), "compute_mean_s": float(comp.mean()),
                     "compute_p99_s": float(np.percentile(comp, 99)), "compute_max_s": float(comp.max())},
            sequential=self._sequential,
        )

    def _setpoints(self):
        """(index, setpoint) to visit in order: the plan's, or for a sequential plan the next chosen after each
        window (:func:`calib.sequential.sequential_acquisition`), until the solve's position 1-sigma is below the
        tolerance or the plan is exhausted."""
        seq = self.plan.sequential
        if seq is None:
            yield from enumerate(self.plan.setpoints)
            return
        cands = seq.design.cands
        # the run's solve takes the first pose's window as the reference (the rest under tau0 is left out)
        online = OnlineSolve(self.robot, seq.noise, self._means[0], cands.home_pose, first_is_reference=True)
        history: list = []
        self._history = history  # (candidate, OnlineEstimate) after each window, for whoever watches the run
        steps = sequential_acquisition(seq.design, online, seq.tolerance, seq.max_poses, history)
        why, c = "exhausted", next(steps, None)
        while c is not None:
            self.plan.setpoints = np.vstack([self.plan.setpoints, cands.setpoints[c]])
            self.plan.ideal_poses = np.vstack([self.plan.ideal_poses, cands.poses[c]])
            self._io.submit(self.writer.update_procedure, self.plan.setpoints, self.plan.ideal_poses)
            yield len(history), cands.setpoints[c]
            online.refresh(self._means[1:-1])  # the earlier poses' windows, as found so far
            try:
                c = steps.send(self._means[-1])
            except StopIteration as stop:
                why, c = stop.value, None
            est = history[-1][1]
            if self.progress is not None:
                p, mm = est.theta[:3], 1000 * est.position_sigma
                self.progress.note = (f"x0 {p[0]:+.4f} {p[1]:+.4f} {p[2]:+.4f} m 1-sigma {mm:.2f} mm"
                                      if math.isfinite(mm) else "reference window")
        self._sequential = {"tolerance_m": seq.tolerance, "stop": why, "reholds": self._rehold, "windows": [
            {"pose": i, "position_sigma_m": e.position_sigma if math.isfinite(e.position_sigma) else None,
             "initial_pose": e.theta[:6].tolist(),
             "iterations": e.iterations} for i, (_, e) in enumerate(history)]}
        self._io.submit(partial(self.writer.update_meta, sequential=self._sequential))

    def _kinematic(self) -> None:
        """Follow the path's tensions linearly in time (quintic blends in and out), logging throughout."""
        tens, times = self.plan.path_tensions, self.plan.path_times
        tau0 = self.plan.tau0
        self._move_to(tau0, tens[0], self.cfg.max_tension_rate, "motion")
        self._phase, self._setpoint = "motion", -1
        steps = int(math.ceil(times[-1] / self.period))
        for k in range(1, steps + 1):
            t = k * self.period
            ref = np.array([np.interp(t, times, tens[:, i]) for i in range(self.n)])
            self._tick(ref)
        self._move_to(tens[-1], tau0, self.cfg.max_tension_rate, "return")

    def _finish_unlogged(self) -> None:
        """After the run log ends: let the platform come to rest under tau0, then the drives off (brakes)."""
        self._close_log()
        try:
            self._settle(self.plan.tau0, "rest", log=False, timeout=self.cfg.pretension_timeout)
        except SafeStop as stop:
            self._safe_stop(stop, log=False)
            raise StartupStopped(stop.kind, stop.message, self.out) from None
        self._disable()

    # ---- the safe stop ---------------------------------------------------------------------------------
    def _safe_stop(self, stop: SafeStop, log: bool = True) -> None:
        """Hold, ramp down to the safe pretension, drives off; the event and every sample in the run log."""
        t_now = self.clock.now()
        if log and self.writer is None and self._zero:  # stopped before the run log started: keep what was seen
            self.start_log()
            self._t_run0 = self._prerun[0][0] if self._prerun else t_now
            for row in self._prerun:
                self._write(row)
        if log and self._log_open:
            # recorded now, on the loop's thread (whoever watches the run sees the stop with its first tick);
            # run.yaml's rewrite on the log worker
            self.writer.record_event(t_now - (self._t_run0 or 0.0), stop.kind, stop.message)
            self._io.submit(self.writer.save_meta)
        self._mark_dead(stop)
        if stop.channels:
            self.controller.open_loop(np.array(stop.channels))
        plan = self.supervisor.plan(self._ref.copy(), power_on=self._tau_init)
        self._phase, self._setpoint = "safe_stop", -1
        steps = int(math.ceil(plan.duration / self.period))
        logging = log and self._log_open
        for k in range(1, steps + 1):
            try:
                tk = self.clock.advance()
                snap = self.rig.tick(tk.index, tk.t, self.cfg.device_timeout)  # dead devices are not awaited
                self._last = snap
                self._ref = plan.reference(k * self.period)
                meas = np.where(np.isfinite(snap.tau), snap.tau, self._ref)
                self.rig.command(self.controller.update(self._ref, meas, self.period))
                if logging and tk.index % self.log_every == 0:
                    self._log(snap)
                if self.on_tick is not None:  # the stop is watched too (a live view: acquisition/live.py)
                    self.on_tick(snap)
            except Exception:  # the stop goes on with what still answers
                continue
        self._disable()
        if logging:
            self._close_log()

    def _mark_dead(self, stop: SafeStop) -> None:
        faults = self.rig.faults()
        for name, f in faults.items():
            if f:
                self.rig.dead.add(name)
        ages = self.rig.ages(self.clock.now())
        for name, (age, per) in ages.items():
            if age > self.supervisor.limits.stale_periods * per:
                self.rig.dead.add(name)

    def _disable(self) -> None:
        for d in self.rig.drives:
            try:
                d.disable()
            except Exception:  # a dead drive: nothing more to do for it
                pass


