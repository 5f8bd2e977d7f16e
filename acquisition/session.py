"""One startup, from a request to its outcome: the path every startup takes (``cdpr startup``, ``cdpr study``,
the benchmarks), whoever asks for it.

:class:`StartupRequest` says what to do (backend, robot, plan, options; SI units, a length already in m);
:func:`run_startup` plans, opens the devices (the simulated prototype or the robot's), runs the routine
(``acquisition/startup.py``) into the run folder, solves and writes the solution, the offsets and the report,
and returns a :class:`StartupOutcome`. Bad input raises :class:`StartupRefused` before the robot moves (exit
status 2 at the command line); a safe stop, a device error or a failed solve raises :class:`StartupFailed`
(exit status 1). Both are one sentence.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.clock import RealClock, SimClock, set_realtime
from acquisition.connect import ahrs_rate_for, connect, feedback_every
from acquisition.equilibrium import DetectorConfig
from acquisition.outputs import check_output, claim_output
from acquisition.plans import PlanRequest, make_plan, parse_pause
from acquisition.progress import ProgressBar
from acquisition.report import ReportRenderer, StartupSummary, read_offsets, sequential_outcome, write_offsets
from acquisition.safety import SafetyLimits, SafetySupervisor
from acquisition.startup import StartupConfig, StartupRoutine, StartupStopped
from calib.constants import CONTROL_RATE, HOLD_TIME, MAX_TENSION_RATE
from calib.errors import CdprError

SIM_PLANT = {"auto": None, "child": True, "inline": False}  # StartupRequest.sim_plant -> SimBackend(plant_process=)


class StartupRefused(CdprError, ValueError):
    """A startup that cannot be asked for (a file, field or option value); nothing moved. One sentence."""


class StartupFailed(CdprError, RuntimeError):
    """A startup that began and failed: ``safe_stop`` True for a safe stop (the run folder keeps every sample
    and the event), False for a device error or a failed solve. One sentence."""

    def __init__(self, message: str, safe_stop: bool = False):
        super().__init__(message)
        self.safe_stop = safe_stop


# the final solve of a run with a learned model (cdpr diagnose --model-out): (run folder, run, method) -> Solution
ModelSolve = Callable[[Path, Any, str], Any]


@dataclass(frozen=True)
class StartupRequest:
    """What one startup does, as ``cdpr startup`` takes it (SI units; ``tolerance`` of the plan in m).

    ``out`` None: run-<UTC time>; ``pauses``: 'J:S' or 'J:S:home' (:func:`acquisition.plans.parse_pause`);
    ``sim_plant``: a key of :data:`SIM_PLANT`; ``model``: a learned robot model whose effects the final solve
    takes as priors, through ``model_solve``; ``progress``: the progress line on stderr; ``debug``: let the
    canopen library log its own SDO aborts."""

    backend: str = "sim"
    plan: PlanRequest = field(default_factory=PlanRequest)
    out: Path | None = None
    robot: str = "irma4u"
    config: str | None = None
    method: str = "equilibrium"
    noise: str | None = None
    sim_config: str | None = None
    truth: str | None = None
    seed: int = 0
    sim_plant: str = "auto"
    rate: float = CONTROL_RATE
    realtime: bool = False
    rt_priority: int | None = None
    offsets: str | None = None
    max_rate: float = MAX_TENSION_RATE
    hold: float = HOLD_TIME
    speed: float = 0.05
    settle_timeout: float = 40.0
    pauses: tuple[str, ...] = ()
    bus_log: str = "blf"
    live: str | None = None
    html: bool = True
    model: Path | None = None
    model_solve: ModelSolve | None = None
    force: bool = False
    progress: bool = True
    debug: bool = False

    def inputs(self) -> list[str]:
        """The input files of the request that exist: an output must not replace them."""
        return [f for f in (self.sim_config, self.config, self.robot) if f and Path(f).exists()]


@dataclass
class StartupOutcome:
    """What a finished startup gives: the summary (solution, windows, events, timing, files) and, for the
    simulated prototype with a ``truth`` file asked for, the simulator's truth document written there."""

    summary: StartupSummary
    truth: dict[str, Any] | None = None


def run_startup(request: StartupRequest, report: ReportRenderer | None = None,
                note: Callable[[str], None] | None = None) -> StartupOutcome:
    """Run one startup (see the module docstring); ``report`` renders RUN/report.html (default: one made
    here, rendered after the acquisition); ``note`` is told, in one sentence, where an output replaced with
    ``force`` was moved. Raises StartupRefused or StartupFailed."""
    return StartupSession(request, note).run(report)


class StartupSession:
    """One startup being run: :meth:`run`, and where it writes (``run_folder``, set once the run folder is
    claimed: before that nothing was written); ``note`` is told where a replaced output was moved."""

    def __init__(self, request: StartupRequest, note: Callable[[str], None] | None = None):
        self.request = request
        self.note = note or (lambda sentence: None)
        self.run_folder: Path | None = None

    def run(self, report: ReportRenderer | None = None) -> StartupOutcome:
        if report is None:
            with ReportRenderer() as own:
                return self._run(own)
        return self._run(report)

    def _run(self, report: ReportRenderer) -> StartupOutcome:
        from calib.robot import RobotDescriptionError, load_robot

        req = self.request
        if req.model is not None:  # a bad model file is refused before the robot moves
            from calib.robot_model import ModelFileError, read_model

            try:
                read_model(req.model)
            except ModelFileError as exc:
                raise StartupRefused(f"--model {exc}") from exc
        if not req.debug:  # the canopen library logs SDO aborts itself; the CLI says what failed in one sentence
            logging.getLogger("canopen").setLevel(logging.CRITICAL)
        try:
            robot = load_robot(req.robot)
        except RobotDescriptionError as exc:
            raise StartupRefused(str(exc)) from exc
        cfg = startup_config(req, robot)
        plan = make_plan(robot, req.plan, cfg.method, cfg.kinematic_speed, cfg.kinematic_spacing,
                         time_model=_time_model(cfg))
        plan.pauses = tuple(parse_pause(text, len(plan.setpoints)) for text in req.pauses)
        meta = {}
        if req.offsets and Path(req.offsets).exists():  # the last calibration, for the record of this run
            try:
                meta["previous_offsets"] = read_offsets(req.offsets)
            except ValueError as exc:
                raise StartupRefused(str(exc)) from exc
        out = Path(req.out or f"run-{_dt.datetime.now(_dt.UTC).strftime('%Y%m%dT%H%M%SZ')}")
        inputs = req.inputs()
        check_output(out, req.force, "--out", inputs)
        if req.live is not None:  # a wrong address is told before anything moves
            from acquisition.live import LiveAddress

            try:
                LiveAddress.parse(req.live)
            except ValueError as exc:
                raise StartupRefused(str(exc)) from exc
        if req.truth:
            check_output(req.truth, req.force, "--truth", inputs)
        if req.backend == "hw":
            if not req.config:
                raise StartupRefused("--backend hw needs --config FILE (the device configuration YAML).")
            if req.sim_config or req.truth:
                raise StartupRefused("--sim-config and --truth apply to --backend sim only.")
        elif req.config:
            raise StartupRefused("--config applies to --backend hw only (the simulator makes its own devices).")
        replaced = claim_output(out, req.force, "--out", inputs)
        if replaced is not None:
            self.note(replaced.sentence())
        previous = meta.get("previous_offsets")
        if replaced is not None and previous and Path(str(previous.get("run", ""))).absolute() == out.absolute():
            previous["run"] = str(replaced.kept)  # the offsets came from the run just moved aside
        self.run_folder = out
        run = _Acquisition(req, robot, plan, cfg, out, meta, report, self.note)
        return run.on_hardware() if req.backend == "hw" else run.on_simulator()


def startup_config(req: StartupRequest, robot) -> StartupConfig:
    """The routine's settings of a request. Raises StartupRefused."""
    for option, value, unit in (("--max-rate", req.max_rate, "N/s"), ("--hold", req.hold, "s"),
                                ("--speed", req.speed, "m/s"), ("--settle-timeout", req.settle_timeout, "s")):
        if not value > 0:  # the one option that is wrong, named alone
            raise StartupRefused(f"{option} {value:g} must be positive ({unit}).")
    if not 200.0 <= req.rate <= 500.0:  # StartupConfig's own check, said with the option's name
        raise StartupRefused(f"--rate {req.rate:g} is outside the control rates 200..500 Hz.")
    if req.rt_priority is not None and not 1 <= req.rt_priority <= 99:
        raise StartupRefused(f"--rt-priority {req.rt_priority} is outside the SCHED_FIFO priorities 1..99.")
    try:
        return StartupConfig(method=req.method, rate=req.rate, max_tension_rate=req.max_rate, hold_time=req.hold,
                             kinematic_speed=req.speed, rt_priority=req.rt_priority,
                             detector=DetectorConfig.for_robot(robot, timeout=req.settle_timeout))
    except ValueError as exc:
        raise StartupRefused(f"invalid option: {exc}") from exc


def _time_model(cfg: StartupConfig):
    from calib.design import TimeModel

    return TimeModel(cfg.max_tension_rate, cfg.min_transition, cfg.expected_settle, cfg.hold_time)


class _Acquisition:
    """The acquisition, solve and report of a checked request into its claimed run folder."""

    def __init__(self, req: StartupRequest, robot, plan, cfg: StartupConfig, out: Path, meta: dict,
                 report: ReportRenderer, note: Callable[[str], None]):
        self.req, self.robot, self.plan, self.cfg, self.out = req, robot, plan, cfg, out
        self.meta, self.report, self.note = meta, report, note

    def on_simulator(self) -> StartupOutcome:
        from sim_backend.backend import SimBackend
        from sim_backend.config import SimConfigError, load_sim_config

        req, robot, cfg = self.req, self.robot, self.cfg
        try:
            sim_config = load_sim_config(req.sim_config, robot.n)
        except SimConfigError as exc:
            raise StartupRefused(str(exc)) from exc
        # the simulated prototype as described (its cables' stretch): run.yaml records it, the solves use it
        robot = self.robot = sim_config.described_robot(robot)
        period = 1.0 / cfg.rate
        clock = RealClock(period, lockstep=True) if req.realtime else SimClock(period)
        supervisor = _supervisor(robot, cfg)
        truth = None
        try:
            # the simulated MTi sends at the log rate: its angles serve only the log (ahrs_rate_for)
            with SimBackend(robot, sim_config, req.seed, period, ahrs_rate=ahrs_rate_for(cfg.log_period),
                            plant_process=SIM_PLANT[req.sim_plant]) as sim:
                if req.realtime and cfg.rt_priority is not None and sim.plant_pid is not None:
                    # the plant stands for hardware: it gets the loop's priority too, else it waits for a CPU
                    refused = set_realtime(cfg.rt_priority, sim.plant_pid)
                    if refused is not None:
                        self.note(f"the simulated plant: {refused}")
                result = self._routine(sim.devices, clock, True, period, supervisor, "sim")
                summary = self._solve_and_report(result)
                if req.truth and summary.solution:
                    truth = _truth_document(sim, result.ticks, summary.solution)
                    replaced = claim_output(req.truth, req.force, "--truth")
                    if replaced is not None:
                        self.note(replaced.sentence())
                    Path(req.truth).write_text(json.dumps(truth) + "\n")
                    summary.files["truth"] = str(req.truth)
        finally:
            supervisor.restore_signals()
        return StartupOutcome(summary, truth)

    def on_hardware(self) -> StartupOutcome:
        from drivers.config import DeviceConfigError, load_device_config

        try:
            devices = load_device_config(self.req.config)
            devices.check_robot(self.robot.n)
        except DeviceConfigError as exc:
            raise StartupRefused(str(exc)) from exc
        period = 1.0 / self.cfg.rate
        supervisor = _supervisor(self.robot, self.cfg)
        try:
            result = self._routine(devices, RealClock(period, lockstep=False), False, period, supervisor, "hardware")
        finally:
            supervisor.restore_signals()
        return StartupOutcome(self._solve_and_report(result))

    def _routine(self, devices, clock, lockstep: bool, period: float, supervisor: SafetySupervisor, source: str):
        """Connect, run the routine with its live view, close the devices; the routine's StartupResult."""
        rig = _connect(devices, self.robot, clock, lockstep, period, self.cfg, self.out, self.req.bus_log)
        live = None
        try:
            live = _live(self.req, self.robot, self.cfg, supervisor)
            progress = ProgressBar(1.0, stream=sys.stderr) if self.req.progress else None
            routine = StartupRoutine(self.robot, rig, clock, self.plan, self.out, self.cfg, source=source,
                                     progress=progress, supervisor=supervisor, meta=self.meta, on_tick=live.hook)
            with self.report.paused():
                return _acquire(live.started(routine))
        finally:
            if live is not None:
                live.close()
            rig.close()
            supervisor.restore_signals()

    def _solve_and_report(self, result) -> StartupSummary:
        from acquisition.runlog import read_run
        from acquisition.runwriter import write_solution
        from calib.selfcal import SelfCalFailure, SelfCalInputError, default_noise, solve

        req, cfg, out = self.req, self.cfg, self.out
        run = read_run(out)
        method = "tlse" if cfg.method == "equilibrium" else "lse"
        t0 = time.perf_counter()
        try:
            if req.model is not None and req.model_solve is not None and method == "tlse":
                sol = req.model_solve(out, run, method)  # a learned model as priors (issue 28)
            else:
                sol = solve(self.robot, run, method=method, noise=req.noise or default_noise(method))
        except (SelfCalFailure, SelfCalInputError) as exc:
            raise StartupFailed(f"the acquisition finished but the solve failed: {exc}") from exc
        solve_s = time.perf_counter() - t0
        data = sol.to_json()
        write_solution(out, data)
        summary = StartupSummary(
            status="ok", run=str(out), method=cfg.method,
            setpoints=len(run.setpoints) if run.setpoints is not None else 0, solution=data,
            windows=result.windows, events=list(run.events),
            timing={"acquisition_s": result.robot_time, "wall_s": result.wall_time, "solve_s": solve_s,
                    "control_p99_ms": 1000 * result.control["compute_p99_s"]},
            message=sequential_outcome(result.sequential, float(np.linalg.norm(data["initial_pose_sigma"][:3]))),
        )
        summary.files["offsets"] = str(write_offsets(out / "offsets.yaml", data, self.robot.name, str(out)))
        if req.offsets:
            summary.files["offsets_copy"] = str(write_offsets(req.offsets, data, self.robot.name, str(out)))
        if req.html:
            summary.files["report"] = str(self.report.write(out / "report.html", summary, run.t, run.tau,
                                                            run.tau_ref))
        return summary


def _supervisor(robot, cfg: StartupConfig) -> SafetySupervisor:
    """The safety supervisor, its signal handlers installed now: Ctrl-C from here on is a safe stop."""
    sup = SafetySupervisor(cfg.safety or SafetyLimits.for_robot(robot), robot.n)
    sup.install_signals()
    return sup


def _live(req: StartupRequest, robot, cfg: StartupConfig, supervisor: SafetySupervisor):
    """The live view of ``live`` (acquisition/live.py), or one that does nothing."""
    from acquisition.live import LiveView

    if req.live is None:
        return LiveView.off()
    try:
        return LiveView.start(req.live, robot, cfg.rate, supervisor.limits)
    except OSError as exc:
        raise StartupFailed(str(exc).rstrip(".") + ".") from exc


def _connect(devices, robot, clock, lockstep: bool, period: float, cfg, out: Path, bus_log: str):
    """The rig, its raw bus record (RUN/bus.<bus_log>, RUN/serial.rec) started first and closed last."""
    from acquisition.busrecord import BusRecorder, record_settings
    from drivers.config import DeviceConfigError
    from drivers.interfaces import DeviceError

    log_every = int(round(cfg.log_period * cfg.rate))
    every = feedback_every(cfg.rate, log_every, devices.can.sync_overflow)
    try:
        recorder = BusRecorder(out, record_settings(devices, every, cfg.rate, lockstep), bus_log)
    except OSError as exc:
        raise StartupFailed(f"{out}: cannot write the raw bus record ({exc.strerror}).") from exc
    try:
        rig = connect(devices, robot, clock, lockstep=lockstep, period=period, every=every, recorder=recorder)
    except DeviceConfigError as exc:
        recorder.discard()
        raise StartupRefused(str(exc)) from exc
    except DeviceError as exc:
        recorder.discard()
        raise StartupFailed(f"device check failed: {str(exc).rstrip('.')}.") from exc
    except BaseException:
        recorder.discard()
        raise
    close_devices = rig.closer

    def close() -> None:
        close_devices()
        recorder.stop()

    rig.closer = close
    return rig


def _acquire(routine: StartupRoutine):
    """Run the routine; a safe stop or a device error becomes one sentence (StartupFailed)."""
    from drivers.interfaces import DeviceError

    try:
        return routine.run()
    except StartupStopped as stop:
        where = f" (run log: {stop.run})" if stop.run else ""
        raise StartupFailed(f"safe stop: {stop.message.rstrip('.')}{where}.", safe_stop=True) from stop
    except DeviceError as exc:
        raise StartupFailed(f"device error: {str(exc).rstrip('.')}.") from exc


# ---- the simulator's truth ----------------------------------------------------------------------------------


def _truth_document(sim, ticks, solution: dict) -> dict[str, Any]:
    """The simulator's truth of a run (the --truth file): the initial pose at the solution's reference sample,
    the pose averaged over the reference window, and the truth at every logged sample."""
    sample = int(solution["reference_sample"])
    tick = int(ticks[sample])
    truth = sim.truth(sync_count=tick)
    return {"initial_pose": [float(v) for v in truth.pose], "reference_sample": sample, "sync_count": tick,
            "sim_time": float(truth.time), "window_mean_pose": _window_mean_truth(sim, ticks, solution, sample),
            **_sample_truth(sim, ticks)}


def _sample_truth(sim, ticks) -> dict[str, list]:
    """The true pose (6,) m/rad at every logged sample (truth.json ``poses``), and the pose, the load-cell
    tensions (n,) N and the sway's push (2,) N averaged over the control periods since the sample before
    (``mean_poses``, ``tensions``, ``push``; the stiff cables ring within a period): what a benchmark needs
    to tell a window at rest from one still moving."""
    ticks = [int(t) for t in ticks]
    got = [sim.truth(sync_count=t) for t in ticks]
    mean_poses, tensions, push = [], [], []
    for a, b in zip([ticks[0] - 1, *ticks[:-1]], ticks, strict=True):
        each = [sim.truth(sync_count=t) for t in range(max(a + 1, 0), b + 1)] or [got[len(tensions)]]
        mean_poses.append(np.mean([s.pose for s in each], axis=0).tolist())
        tensions.append(np.mean([s.tensions for s in each], axis=0).tolist())
        push.append(sim.sway_push([s.time for s in each]).mean(axis=0).tolist())
    return {"poses": [s.pose.tolist() for s in got], "mean_poses": mean_poses, "tensions": tensions, "push": push}


def _window_mean_truth(sim, ticks, solution: dict, sample: int) -> list[float] | None:
    """The true pose averaged over the reference window's samples (the solve estimates the pose of a window
    mean; a platform still creeping inside the window makes it differ from the pose at its middle sample)."""
    span = next(((a, b) for a, b in solution.get("windows", []) if a <= sample <= b), None)
    if span is None:
        return None
    poses = np.array([sim.truth(sync_count=int(ticks[i])).pose for i in range(span[0], span[1] + 1)])
    return [float(v) for v in poses.mean(axis=0)]


def simulated_startup(out: str | Path, plan: str = "grid2", tolerance: float | None = None, poses: int | None = None,
                      seed: int = 0, sim_config: str | None = None, robot: str = "irma4u", step: float = 0.1) -> dict:
    """One simulated startup in this process, as ``cdpr startup --backend sim --no-html --json`` runs it (the
    entry point of Monte-Carlo studies and benchmarks): ``plan`` 'gridN' (N points per axis), 'optimal' or
    'sequential' (``tolerance`` m), candidates every ``step`` m; returns the ``--json`` summary plus ``truth``,
    the simulator's initial pose (6,) at the solution's reference sample (also in OUT/truth.json), and
    ``truth_window_mean``, the true pose averaged over the reference window; the plant runs in this process.
    Raises StartupRefused or StartupFailed."""
    out = Path(out)
    kind = "grid" if plan.startswith("grid") else plan
    request = StartupRequest(
        backend="sim", out=out, robot=robot, seed=seed, truth=str(out / "truth.json"), sim_config=sim_config,
        sim_plant="inline", html=False,
        plan=PlanRequest.of(kind, int(plan[4:] or 2) if kind == "grid" else 2, poses, tolerance, float(step)))
    outcome = run_startup(request)
    truth = outcome.truth
    return outcome.summary.to_dict() | {"truth": truth["initial_pose"],
                                        "truth_window_mean": truth.get("window_mean_pose")}
