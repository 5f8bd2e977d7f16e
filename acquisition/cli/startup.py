"""`cdpr startup`: the operator's startup routine on the simulated prototype or on the robot.

    cdpr startup --backend sim [--grid N] [--method equilibrium|kinematic] [--out RUN] [--sim-config FILE]
                 [--truth FILE] [--seed S] [--rate HZ] [--realtime] [--rt-priority N] [--json] [--force]
    cdpr startup --backend hw --config DEVICES.yaml [...]

Pose planning, force-controlled acquisition into the run folder, solve, report (text on stdout or JSON with
``--json``; RUN/report.html; the new sensor offsets in RUN/offsets.yaml and, with ``--offsets FILE``, there
too). A safe stop exits with status 1 and one sentence; the run folder keeps every sample and the event.
An existing RUN is refused, or with ``--force`` moved aside (acquisition/outputs.py) before the robot moves.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from acquisition.cli import Interrupted
from acquisition.cli.args import add_force
from acquisition.cli.errors import OperationError
from acquisition.plans import PLANS, PlanRequest, parse_length
from acquisition.report import ReportRenderer, StartupSummary, render_text
from acquisition.session import SIM_PLANT, StartupRequest, StartupSession
from calib.constants import CONTROL_RATE, HOLD_TIME, MAX_TENSION_RATE


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
    p.add_argument("--rt-priority", type=int, default=None, metavar="N",
                   help="run the control loop's thread (and a paced simulated plant) under SCHED_FIFO at priority N "
                        "(1-99; Linux, needs an rtprio limit or CAP_SYS_NICE; refused: a warning, normal priority), "
                        "the process's other threads at N-1, and lock its memory (needs ulimit -l unlimited; "
                        "refused: a warning)")
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


def request_of(args) -> StartupRequest:
    """The startup the parsed command line asks for (acquisition/session.py). Raises a CdprError (exit 2) for
    a value the parser cannot check."""
    tolerance = None if args.tolerance is None else parse_length(args.tolerance, "--tolerance")
    model = getattr(args, "model", None)
    return StartupRequest(
        backend=args.backend, out=Path(args.out) if args.out else None, robot=args.robot, config=args.config,
        plan=PlanRequest.of(args.plan, args.grid, args.poses, tolerance, args.step), method=args.method,
        noise=getattr(args, "noise", None), sim_config=args.sim_config, truth=args.truth, seed=args.seed,
        sim_plant=args.sim_plant, rate=args.rate, realtime=args.realtime,
        rt_priority=args.rt_priority, offsets=args.offsets,
        max_rate=args.max_rate, hold=args.hold, speed=args.speed, settle_timeout=args.settle_timeout,
        pauses=tuple(args.pause), bus_log=args.bus_log, live=args.live, html=not args.no_html, model=model,
        model_solve=None if model is None else _model_solve(model), force=args.force, debug=args.debug)


def _model_solve(model: Path):
    """The final solve with a learned model's effects as priors (cdpr solve --model, issue 28)."""

    def solve(out: Path, run, method: str):
        from acquisition.cli.diagnose_runs import solve_with_model_file

        ns = argparse.Namespace(model=model, run=out, effects_from=[])
        return solve_with_model_file(ns, run, None, {"method": method})[0]

    return solve


def run(args) -> int:
    session = StartupSession(request_of(args), note=lambda sentence: sys.stderr.write(f"cdpr: note: {sentence}\n"))
    try:
        with ReportRenderer() as report:
            if not args.no_html:
                # forked first: it loads matplotlib while the robot is planned and connected. During the control
                # loop the simulated plant needs the second core, and a renderer still loading then slows it down
                report.start()
            return _print(args, session.run(report).summary)
    except Interrupted as stop:  # a signal outside the acquisition, whose supervisor owns the stop
        raise OperationError(f"stopped by {stop.args[0]} {_where(session.run_folder)}.") from stop


def _where(out: Path | None) -> str:
    """Where a stop outside the acquisition leaves the operator: before the run log, or after it."""
    if out is not None and (out / "samples.csv").is_file():
        return f"after the acquisition; the run log {out} is complete (cdpr solve {out})"
    return "before the acquisition started; no run was written"


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
