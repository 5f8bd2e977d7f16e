"""`cdpr startup`: the operator's startup routine on the simulated prototype or on the robot.

    cdpr startup --backend sim [--grid N] [--method equilibrium|kinematic] [--out RUN] [--sim-config FILE]
                 [--truth FILE] [--seed S] [--rate HZ] [--realtime] [--json] [--force]
    cdpr startup --backend hw --config DEVICES.yaml [...]

Pose planning, force-controlled acquisition into the run folder, solve, report (text on stdout or JSON with
``--json``; RUN/report.html; the new sensor offsets in RUN/offsets.yaml and, with ``--offsets FILE``, there
too). A safe stop exits with status 1 and one sentence; the run folder keeps every sample and the event.
An existing RUN is refused, or with ``--force`` moved aside (acquisition/outputs.py) before the robot moves.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import sys
from pathlib import Path

import numpy as np

from acquisition.cli import Interrupted
from acquisition.cli.args import add_force, check_grid, check_output_option, claim_output_option, parse_length
from acquisition.cli.errors import OperationError, UsageError
from acquisition.clock import RealClock, SimClock
from acquisition.equilibrium import DetectorConfig
from acquisition.report import ProgressBar, ReportRenderer, StartupSummary, read_offsets, render_text, write_offsets
from acquisition.safety import SafetyLimits, SafetySupervisor
from acquisition.startup import (
    PLANS,
    Pause,
    Plan,
    StartupConfig,
    StartupRoutine,
    StartupStopped,
    ahrs_rate_for,
    connect,
    feedback_every,
)
from calib.constants import CONTROL_RATE, HOLD_TIME, MAX_TENSION_RATE

SIM_PLANT = {"auto": None, "child": True, "inline": False}  # --sim-plant -> SimBackend(plant_process=...)


def register(sub) -> None:
    p = sub.add_parser("startup", help="run the startup self-calibration routine (simulated or real robot)")
    p.add_argument("--backend", choices=("sim", "hw"), required=True, help="simulated prototype or real robot")
    p.add_argument("--config", help="device configuration YAML (drivers/config.py), required with --backend hw")
    p.add_argument("--robot", default="irma4u", help="robot description: built-in name or YAML file")
    p.add_argument("--grid", type=int, default=2, help="calibration grid points per axis (default 2)")
    p.add_argument("--method", choices=("equilibrium", "kinematic"), default="equilibrium",
                   help="equilibrium: static poses, tlse (default); kinematic: constant-speed path, lse")
    p.add_argument("--plan", choices=PLANS, default=None,
                   help="grid (default), optimal (the A-optimal --poses poses of the static workspace) or "
                        "sequential (the default with --tolerance)")
    p.add_argument("--poses", type=int, default=None,
                   help="optimal plan: number of poses (default 8); sequential: at most this many (default 27)")
    p.add_argument("--tolerance",
                   help="sequential acquisition: stop as soon as the 1-sigma of the initial position is below "
                        "this length, unit required (e.g. 3mm, 0.5cm, 0.002m)")
    p.add_argument("--noise", choices=("estimate", "paper", "sensors"), default=None,
                   help="weights of the final solve, as cdpr solve --noise (default: estimate for the equilibrium "
                        "method, the 1-sigma the sequential stop compares with --tolerance; paper for kinematic)")
    p.add_argument("--step", type=float, default=0.1,
                   help="optimal and sequential plans: spacing of the candidate positions, m (default 0.1)")
    p.add_argument("--out", help="run folder to write (default: run-<UTC time>); an existing run or a folder "
                   "holding files is refused unless --force")
    p.add_argument("--sim-config", help="simulation configuration YAML (hidden effects, faults)")
    p.add_argument("--truth", help="write the simulator's true initial pose here (JSON); an existing file is "
                   "refused unless --force")
    p.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    p.add_argument("--sim-plant", choices=tuple(SIM_PLANT), default="auto",
                   help="where the simulated prototype's physics runs: a child process on the second core "
                        "(child), this process (inline), or child when the machine has two cores (auto, default)")
    p.add_argument("--rate", type=float, default=CONTROL_RATE, help="control rate, Hz, 200..500 (default 200)")
    p.add_argument("--realtime", action="store_true", help="pace the simulated prototype in real time")
    p.add_argument("--offsets", help="also save the new sensor offsets to this YAML file (updated in place: "
                   "its previous content is kept in RUN/run.yaml as previous_offsets)")
    p.add_argument("--max-rate", type=float, default=MAX_TENSION_RATE,
                   help="tension rate limit of the trajectories, N/s")
    p.add_argument("--hold", type=float, default=HOLD_TIME, help="logged seconds of each equilibrium window")
    p.add_argument("--speed", type=float, default=0.05, help="platform speed along the kinematic path, m/s")
    p.add_argument("--settle-timeout", type=float, default=40.0,
                   help="s to wait for the platform to come to rest at each setpoint before holding anyway")
    p.add_argument("--pause", action="append", default=[], metavar="J:S[:home]",
                   help="pause S seconds after setpoint J's window, at it or (home) under tau0 (repeatable)")
    p.add_argument("--bus-log", choices=("blf", "asc"), default="blf",
                   help="format of the raw CAN record RUN/bus.<fmt> (python-can's loggers; default blf)")
    p.add_argument("--live", metavar="[HOST:]PORT", default=None,
                   help="watch the startup live in Foxglove: a read-only WebSocket server on PORT (0: any free "
                        "port), bound to 127.0.0.1 unless HOST is named (acquisition/live.py, docs/live.md)")
    p.add_argument("--no-html", action="store_true", help="skip the HTML report")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    p.add_argument("--model", type=Path, default=None, metavar="MODEL.yaml",
                   help="a learned robot model (cdpr diagnose --model-out): the run's solve takes its effects as "
                   "priors (docs/robot-model.md)")
    add_force(p)
    p.set_defaults(func=run)


def _config(args, robot) -> StartupConfig:
    check_grid(args.grid)
    if min(args.max_rate, args.hold, args.speed, args.settle_timeout) <= 0:
        raise UsageError(f"--max-rate {args.max_rate}, --hold {args.hold}, --speed {args.speed} and "
                         f"--settle-timeout {args.settle_timeout} must be positive.")
    try:
        return StartupConfig(method=args.method, rate=args.rate, max_tension_rate=args.max_rate,
                             hold_time=args.hold, kinematic_speed=args.speed,
                             detector=DetectorConfig.for_robot(robot, timeout=args.settle_timeout))
    except ValueError as exc:
        raise UsageError(f"invalid option: {exc}") from exc


def make_plan(robot, cfg: StartupConfig, grid: int = 2, plan: str | None = None, poses: int | None = None,
              tolerance: float | None = None, step: float = 0.1) -> Plan:
    """The plan `cdpr startup` runs: ``plan`` 'grid' (``grid`` points per axis), 'optimal' (``poses`` poses,
    default 8) or 'sequential' (stop at ``tolerance`` m, at most ``poses`` poses, default 27); None: grid, or
    sequential when a tolerance is given. The window-mean noise the optimal and sequential plans are chosen with
    is the startup loop's at each pose (:data:`calib.design.LOOP_POSE_NOISE`); a sequential startup then
    weighs its choices and its stop rule with its own (its own solve of the samples so far). Raises
    UsageError."""
    from calib.design import LOOP_POSE_NOISE, TimeModel
    from calib.planning import PlanningError

    plan = plan or ("sequential" if tolerance is not None else "grid")
    if tolerance is not None and plan != "sequential":
        raise UsageError(f"--tolerance applies to the sequential plan, not to --plan {plan}.")
    if plan == "sequential" and tolerance is None:
        raise UsageError("--plan sequential needs --tolerance (e.g. --tolerance 3mm).")
    if not step > 0:
        raise UsageError(f"--step must be positive, got {step}.")
    if poses is not None and not 1 <= poses <= 100:
        raise UsageError(f"--poses {poses} is out of range: give 1 to 100 poses.")
    poses = poses or (27 if plan == "sequential" else 8)
    noise = LOOP_POSE_NOISE
    try:
        return Plan.for_robot(robot, grid, cfg.method, cfg.kinematic_speed, cfg.kinematic_spacing, plan=plan,
                              poses=poses, tolerance=tolerance, noise=noise, step=step,
                              time_model=TimeModel(cfg.max_tension_rate, cfg.min_transition, cfg.expected_settle,
                                                   cfg.hold_time))
    except PlanningError as exc:
        raise UsageError(str(exc)) from exc


def _pause(text: str, k: int) -> Pause:
    """``J:S`` or ``J:S:home`` -> a Pause after setpoint J (0..k-1) of S > 0 seconds."""
    parts = text.split(":")
    try:
        if len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] != "home"):
            raise ValueError
        pause = Pause(int(parts[0]), float(parts[1]), len(parts) == 3)
    except ValueError:
        raise UsageError(f"--pause {text!r} is not J:S or J:S:home (setpoint index, seconds).") from None
    if not 0 <= pause.after < k or not 0 < pause.seconds <= 600:
        raise UsageError(f"--pause {text!r}: the setpoint must be 0..{k - 1} and the seconds within (0, 600].")
    return pause


def run(args) -> int:
    if getattr(args, "model", None) is not None:  # a bad model file is refused before the robot moves
        from calib.robot_model import ModelFileError, read_model

        try:
            read_model(args.model)
        except ModelFileError as exc:
            raise UsageError(f"--model {exc}") from exc
    try:
        with ReportRenderer() as report:
            if not args.no_html:
                # forked first: it loads matplotlib while the robot is planned and connected. During the control
                # loop the simulated plant needs the second core, and a renderer still loading then slows it down
                report.start()
            return _print(args, _run(args, report))
    except Interrupted as stop:  # a signal outside the acquisition, whose supervisor owns the stop
        raise OperationError(f"stopped by {stop.args[0]} {_where(getattr(args, 'run_folder', None))}.") from stop


def _where(out: Path | None) -> str:
    """Where a stop outside the acquisition leaves the operator: before the run log, or after it."""
    if out is not None and (out / "samples.csv").is_file():
        return f"after the acquisition; the run log {out} is complete (cdpr solve {out})"
    return "before the acquisition started; no run was written"


def simulated_startup(out: str | Path, plan: str = "grid2", tolerance: float | None = None, poses: int | None = None,
                      seed: int = 0, sim_config: str | None = None, robot: str = "irma4u", step: float = 0.1) -> dict:
    """One simulated startup in this process, as ``cdpr startup --backend sim --no-html --json`` runs it (the
    entry point of Monte-Carlo studies): ``plan`` 'gridN' (N points per axis), 'optimal' or 'sequential'
    (``tolerance`` m), candidates every ``step`` m; returns the ``--json`` summary plus ``truth``, the
    simulator's initial pose (6,) at the solution's reference sample (also in OUT/truth.json), and
    ``truth_window_mean``, the true pose averaged over the reference window; the plant runs in this process
    (``--sim-plant inline``). Raises
    UsageError or OperationError."""
    from acquisition.cli import build_parser, modules_for

    out = Path(out)
    argv = ["startup", "--backend", "sim", "--no-html", "--out", str(out), "--seed", str(seed), "--robot", robot,
            "--truth", str(out / "truth.json"), "--step", repr(float(step)), "--sim-plant", "inline"]
    argv += ["--plan", "grid", "--grid", plan[4:] or "2"] if plan.startswith("grid") else ["--plan", plan]
    argv += [] if tolerance is None else ["--tolerance", f"{float(tolerance)!r}m"]
    argv += [] if poses is None else ["--poses", str(poses)]
    argv += [] if sim_config is None else ["--sim-config", str(sim_config)]
    args = build_parser(modules_for(argv)).parse_args(argv)  # the startup's module alone
    with ReportRenderer() as report:
        summary = _run(args, report)
    truth = json.loads((out / "truth.json").read_text())
    return summary.to_dict() | {"truth": truth["initial_pose"], "truth_window_mean": truth.get("window_mean_pose")}


def _run(args, report: ReportRenderer) -> StartupSummary:
    from calib.robot import RobotDescriptionError, load_robot

    if not args.debug:  # the canopen library logs SDO aborts itself; the CLI says what failed in one sentence
        logging.getLogger("canopen").setLevel(logging.CRITICAL)
    try:
        robot = load_robot(args.robot)
    except RobotDescriptionError as exc:
        raise UsageError(str(exc)) from exc
    cfg = _config(args, robot)
    tolerance = None if args.tolerance is None else parse_length(args.tolerance, "--tolerance")
    plan = make_plan(robot, cfg, args.grid, args.plan, args.poses, tolerance, args.step)
    plan.pauses = tuple(_pause(text, len(plan.setpoints)) for text in args.pause)
    meta = {}
    if args.offsets and Path(args.offsets).exists():  # the last calibration, for the record of this run
        try:
            meta["previous_offsets"] = read_offsets(args.offsets)
        except ValueError as exc:
            raise UsageError(str(exc)) from exc
    args.run_meta = meta
    out = Path(args.out or f"run-{_dt.datetime.now(_dt.UTC).strftime('%Y%m%dT%H%M%SZ')}")
    inputs = [f for f in (args.sim_config, args.config, args.robot) if f and Path(f).exists()]
    check_output_option(out, args.force, "--out", inputs)
    if args.live is not None:  # a wrong address is told before anything moves
        from acquisition.live import LiveAddress

        try:
            LiveAddress.parse(args.live)
        except ValueError as exc:
            raise UsageError(str(exc)) from exc
    if args.truth:
        check_output_option(args.truth, args.force, "--truth", inputs)
    if args.backend == "hw":
        if not args.config:
            raise UsageError("--backend hw needs --config FILE (the device configuration YAML).")
        if args.sim_config or args.truth:
            raise UsageError("--sim-config and --truth apply to --backend sim only.")
    elif args.config:
        raise UsageError("--config applies to --backend hw only (the simulator makes its own devices).")
    replaced = claim_output_option(out, args.force, "--out", inputs)
    previous = meta.get("previous_offsets")
    if replaced is not None and previous and Path(str(previous.get("run", ""))).absolute() == out.absolute():
        previous["run"] = str(replaced.kept)  # the offsets came from the run just moved aside
    args.run_folder = out
    if args.backend == "hw":
        return _run_hw(args, robot, plan, cfg, out, report)
    return _run_sim(args, robot, plan, cfg, out, report)


def _progress(args) -> ProgressBar:
    return ProgressBar(1.0, stream=sys.stderr)


def _run_sim(args, robot, plan, cfg, out: Path, report: ReportRenderer) -> StartupSummary:
    from sim_backend.backend import SimBackend
    from sim_backend.config import SimConfigError, load_sim_config

    try:
        sim_config = load_sim_config(args.sim_config, robot.n)
    except SimConfigError as exc:
        raise UsageError(str(exc)) from exc
    period = 1.0 / cfg.rate
    clock = RealClock(period, lockstep=True) if args.realtime else SimClock(period)
    supervisor = _supervisor(robot, cfg)
    try:
        # the simulated MTi sends at the log rate: its angles serve only the log (ahrs_rate_for)
        with SimBackend(robot, sim_config, args.seed, period, ahrs_rate=ahrs_rate_for(cfg.log_period),
                        plant_process=SIM_PLANT[args.sim_plant]) as sim:
            rig = _connect(sim.devices, robot, clock, True, period, cfg, out, args.bus_log)
            live = None
            try:
                live = _live(args, robot, cfg, supervisor)
                routine = StartupRoutine(robot, rig, clock, plan, out, cfg, source="sim", progress=_progress(args),
                                         supervisor=supervisor, meta=args.run_meta, on_tick=live.hook)
                with report.paused():
                    result = _acquire(live.started(routine))
            finally:
                if live is not None:
                    live.close()
                rig.close()
                supervisor.restore_signals()
            summary = _solve_and_report(args, robot, cfg, result, out, report)
            if args.truth and summary.solution:
                sample = int(summary.solution["reference_sample"])
                tick = int(result.ticks[sample])
                truth = sim.truth(sync_count=tick)
                claim_output_option(args.truth, args.force, "--truth")
                Path(args.truth).write_text(json.dumps({
                    "initial_pose": [float(v) for v in truth.pose], "reference_sample": sample,
                    "sync_count": tick, "sim_time": float(truth.time),
                    "window_mean_pose": _window_mean_truth(sim, result.ticks, summary.solution, sample),
                    **_sample_truth(sim, result.ticks)}) + "\n")
                summary.files["truth"] = str(args.truth)
    finally:
        supervisor.restore_signals()
    return summary


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


def _run_hw(args, robot, plan, cfg, out: Path, report: ReportRenderer) -> StartupSummary:
    from drivers.config import DeviceConfigError, load_device_config

    try:
        devices = load_device_config(args.config)
        devices.check_robot(robot.n)
    except DeviceConfigError as exc:
        raise UsageError(str(exc)) from exc
    period = 1.0 / cfg.rate
    clock = RealClock(period, lockstep=False)
    supervisor = _supervisor(robot, cfg)
    try:
        rig = _connect(devices, robot, clock, False, period, cfg, out, args.bus_log)
        live = None
        try:
            live = _live(args, robot, cfg, supervisor)
            routine = StartupRoutine(robot, rig, clock, plan, out, cfg, source="hardware", progress=_progress(args),
                                     supervisor=supervisor, meta=args.run_meta, on_tick=live.hook)
            with report.paused():
                result = _acquire(live.started(routine))
        finally:
            if live is not None:
                live.close()
            rig.close()
    finally:
        supervisor.restore_signals()
    return _solve_and_report(args, robot, cfg, result, out, report)


def _live(args, robot, cfg: StartupConfig, supervisor: SafetySupervisor):
    """The live view of ``--live`` (acquisition/live.py), or one that does nothing."""
    from acquisition.live import LiveView

    if args.live is None:
        return LiveView.off()
    try:
        return LiveView.start(args.live, robot, cfg.rate, supervisor.limits)
    except OSError as exc:
        raise OperationError(str(exc).rstrip(".") + ".") from exc


def _supervisor(robot, cfg: StartupConfig) -> SafetySupervisor:
    """The safety supervisor, its signal handlers installed now: Ctrl-C from here on is a safe stop."""
    sup = SafetySupervisor(cfg.safety or SafetyLimits.for_robot(robot), robot.n)
    sup.install_signals()
    return sup


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
        raise OperationError(f"{out}: cannot write the raw bus record ({exc.strerror}).") from exc
    try:
        rig = connect(devices, robot, clock, lockstep=lockstep, period=period, every=every, recorder=recorder)
    except DeviceConfigError as exc:
        recorder.discard()
        raise UsageError(str(exc)) from exc
    except DeviceError as exc:
        recorder.discard()
        raise OperationError(f"device check failed: {str(exc).rstrip('.')}.") from exc
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
    """Run the routine; a safe stop or a device error becomes one sentence (exit status 1)."""
    from drivers.interfaces import DeviceError

    try:
        return routine.run()
    except StartupStopped as stop:
        where = f" (run log: {stop.run})" if stop.run else ""
        raise OperationError(f"safe stop: {stop.message.rstrip('.')}{where}.") from stop
    except DeviceError as exc:
        raise OperationError(f"device error: {str(exc).rstrip('.')}.") from exc


def _solve_and_report(args, robot, cfg, result, out: Path, report: ReportRenderer) -> StartupSummary:
    import time

    from acquisition.cli.solve import default_noise
    from acquisition.runlog import read_run, write_solution
    from calib.selfcal import SelfCalFailure, SelfCalInputError, solve

    run = read_run(out)
    method = "tlse" if cfg.method == "equilibrium" else "lse"
    t0 = time.perf_counter()
    try:
        if getattr(args, "model", None) is not None and method == "tlse":  # a learned model as priors (issue 28)
            from acquisition.cli.diagnose_runs import solve_with_model_file

            args.run, args.effects_from = out, []
            sol, _ = solve_with_model_file(args, run, None, {"method": method})
        else:
            sol = solve(robot, run, method=method, noise=getattr(args, "noise", None) or default_noise(method))
    except (SelfCalFailure, SelfCalInputError) as exc:
        raise OperationError(f"the acquisition finished but the solve failed: {exc}") from exc
    solve_s = time.perf_counter() - t0
    data = sol.to_json()
    write_solution(out, data)
    summary = StartupSummary(
        status="ok", run=str(out), method=cfg.method, setpoints=len(run.setpoints) if run.setpoints is not None else 0,
        solution=data, windows=result.windows, events=list(run.events),
        timing={"acquisition_s": result.robot_time, "wall_s": result.wall_time, "solve_s": solve_s,
                "control_p99_ms": 1000 * result.control["compute_p99_s"]},
        message=sequential_outcome(result.sequential, float(np.linalg.norm(data["initial_pose_sigma"][:3]))),
    )
    summary.files["offsets"] = str(write_offsets(out / "offsets.yaml", data, robot.name, str(out)))
    if args.offsets:
        summary.files["offsets_copy"] = str(write_offsets(args.offsets, data, robot.name, str(out)))
    if not args.no_html:
        summary.files["report"] = str(report.write(out / "report.html", summary, run.t, run.tau, run.tau_ref))
    return summary


def sequential_outcome(seq: dict | None, final_sigma: float | None = None) -> str:
    """One sentence on why a sequential startup stopped ('' for a fixed plan). ``final_sigma`` (m): the
    position 1-sigma of the run's final solve, the one the summary prints; said in place of the stop rule's
    own (the same solve on the samples up to the last window), and said apart when the two disagree on the
    tolerance."""
    if not seq:
        return ""
    w, tol = seq["windows"], 1000 * seq["tolerance_m"]
    sigma = 1000 * w[-1]["position_sigma_m"] if w and w[-1]["position_sigma_m"] is not None else float("inf")
    if seq["stop"] == "tolerance" and final_sigma is not None and 1000 * final_sigma >= tol:
        return (f"sequential: stopped after {len(w)} poses at a 1-sigma of the initial position of {sigma:.2f} mm "
                f"< tolerance {tol:g} mm, but the whole run's solve gives {1000 * final_sigma:.2f} mm.")
    sigma = sigma if final_sigma is None else 1000 * final_sigma
    if seq["stop"] == "tolerance":
        return (f"sequential: 1-sigma of the initial position {sigma:.2f} mm < tolerance {tol:g} mm after "
                f"{len(w)} poses.")
    return (f"sequential: the plan is exhausted after {len(w)} poses with a 1-sigma of the initial position of "
            f"{sigma:.2f} mm, above the tolerance {tol:g} mm.")


def _print(args, summary: StartupSummary) -> int:
    if args.json:
        sys.stdout.write(json.dumps(summary.to_dict(), default=_plain) + "\n")
    else:
        sys.stdout.write(render_text(summary))
    return 0


def _plain(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
