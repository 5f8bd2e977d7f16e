"""`cdpr poses` (calibration pose planning) and `cdpr workspace` (static workspace map and plot)."""

from __future__ import annotations

import json
import sys

import numpy as np

from acquisition.cli.args import add_force, check_output_option, claim_output_option
from acquisition.cli.errors import OperationError, UsageError
from acquisition.plans import check_grid, check_step
from calib.planning import PlanningError, kinematic_path, plan_poses
from calib.robot import load_robot


def register(sub) -> None:
    p = sub.add_parser("poses", help="plan the calibration poses and tension setpoints (Sec. 3.2.1)")
    p.add_argument("--robot", default="irma4u", help="built-in robot name or robot YAML file (default irma4u)")
    p.add_argument("--grid", type=int, default=2,
                   help="grid points per axis in the workspace bounds, 2 to 6 as for cdpr startup (default 2)")
    p.add_argument("--method", choices=("equilibrium", "kinematic"), default="equilibrium",
                   help="equilibrium: static poses (default); kinematic: a constant-speed path")
    p.add_argument("--speed", type=float, default=0.05, help="kinematic method: path speed, m/s")
    p.add_argument("--optimal", type=int, metavar="K",
                   help="choose K equilibria of the static workspace that minimise the predicted 1-sigma of the "
                        "initial position (A-optimal), shown next to the grid's")
    p.add_argument("--step", type=float, default=0.1,
                   help="--optimal, --separate: spacing of the candidate positions in the static workspace, m "
                        "(default 0.1)")
    p.add_argument("--separate", metavar="A,B",
                   help="propose the poses that would tell apart two effects the diagnosis of RUN confused")
    p.add_argument("run", nargs="?", metavar="RUN", help="--separate: the run folder that was diagnosed")
    p.add_argument("--count", type=int, default=3, help="--separate: number of poses to propose (default 3)")
    p.add_argument("--json", action="store_true", help="print JSON on stdout")
    p.set_defaults(func=_poses)
    w = sub.add_parser("workspace", help="static workspace of the robot on a grid (Appendix A)")
    w.add_argument("--robot", default="irma4u", help="built-in robot name or robot YAML file (default irma4u)")
    w.add_argument("--step", type=float, default=0.1, help="grid spacing, m (default 0.1)")
    w.add_argument("--plot", metavar="PNG",
                   help="write a plot of the boundary to this PNG file; an existing file is refused unless --force")
    w.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    add_force(w)
    w.set_defaults(func=_workspace)


def _poses(args) -> int:
    robot = load_robot(args.robot)
    check_grid(args.grid)
    if args.separate is not None:
        return _separate(args)
    if args.run:
        raise UsageError(f"the run folder {args.run} applies to --separate only.")
    if args.optimal is not None:
        return _optimal(args, robot)
    try:
        if args.method == "kinematic":
            path = kinematic_path(robot, args.grid, speed=args.speed)
            out = {
                "poses": path.poses.tolist(),
                "setpoints": path.tensions.tolist(),
                "times": path.times.tolist(),
                "speed": path.speed,
            }
        else:
            plan = plan_poses(robot, args.grid)
            out = plan.to_dict()
    except PlanningError as exc:
        raise OperationError(str(exc)) from exc
    if args.json:
        json.dump(out, sys.stdout)
        sys.stdout.write("\n")
        return 0
    _table(robot, f"{len(out['poses'])} poses ({args.method})", out)
    return 0


def _table(robot, title: str, out: dict) -> None:
    print(f"{robot.name}: {title}, visiting order")
    print(f"{'#':>3} {'x (m)':>7} {'y (m)':>7} {'z (m)':>7} {'roll°':>7} {'pitch°':>7} {'yaw°':>7}   setpoint (N)")
    for i, (z, t) in enumerate(zip(out["poses"], out["setpoints"], strict=True)):
        ang = np.degrees(z[3:])
        print(
            f"{i:>3} {z[0]:7.3f} {z[1]:7.3f} {z[2]:7.3f} {ang[0]:7.2f} {ang[1]:7.2f} {ang[2]:7.2f}   "
            + " ".join(f"{v:7.2f}" for v in t)
        )
    if "transition_cost" in out:
        print(f"home tensions tau0 = {out['tau0']} N; tour transition cost {out['transition_cost']:.1f} N")


def _optimal(args, robot) -> int:
    from calib.design import LOOP_POSE_NOISE, TimeModel, candidates, optimal_plan, predict_loop

    if args.optimal < 1:
        raise UsageError(f"--optimal must be a positive number of poses, got {args.optimal}.")
    check_step(args.step)
    noise, times = LOOP_POSE_NOISE, TimeModel()
    try:
        grid = plan_poses(robot, args.grid)
        if sys.stderr.isatty():
            sys.stderr.write(f"evaluating the static workspace every {args.step:g} m ...\r")
        cands = candidates(robot, noise, args.step)
        plan = optimal_plan(robot, args.optimal, noise, cands=cands)
    except PlanningError as exc:
        raise OperationError(str(exc)) from exc
    a_opt, a_grid = predict_loop(robot, plan, times, noise), predict_loop(robot, grid, times, noise)
    out = plan.to_dict() | {"predicted": a_opt.to_dict(), "grid": {"poses": len(grid.poses), **a_grid.to_dict()},
                            "candidates": cands.size}
    if args.json:
        json.dump(out, sys.stdout)
        sys.stdout.write("\n")
        return 0
    _table(robot, f"{len(plan.poses)} poses (A-optimal among {cands.size} reachable equilibria)", out)
    for name, a, k in (("optimal", a_opt, len(plan.poses)), (f"grid {args.grid}", a_grid, len(grid.poses))):
        print(f"{name:>10}: {k:2d} poses, predicted 1-sigma of the initial position {1000 * a.position_sigma:.3f} mm, "
              f"robot time {a.robot_time:.0f} s")
    return 0


def _separate(args) -> int:
    from acquisition.runlog import read_run
    from calib.design import candidates, separating_poses
    from calib.diagnose import diagnose_run
    from calib.effects import make_effects
    from calib.selfcal import SelfCalFailure, SelfCalInputError

    names = [n.strip() for n in args.separate.split(",") if n.strip()]
    if len(names) != 2 or names[0] == names[1]:
        raise UsageError(f"--separate needs two different effect names A,B, got '{args.separate}'.")
    if not args.run:
        raise UsageError("--separate needs the run folder that was diagnosed (cdpr poses --separate A,B RUN).")
    if args.count < 1:
        raise UsageError(f"--count must be a positive number of poses, got {args.count}.")
    effects = tuple(make_effects(names))
    run = read_run(args.run)
    robot = run.robot
    status = sys.stderr.isatty()
    try:
        if status:
            sys.stderr.write(f"fitting {names[0]} and {names[1]} to {args.run} ...\r")
        base = diagnose_run(run, candidates=[], max_effects=0).fit
        meas, noise = base.problem.meas, base.problem.sigma
        cands = candidates(robot, noise, args.step)
        sep = separating_poses(robot, meas, noise, base.theta[:6], base.poses, effects, cands, args.count)
    except (SelfCalFailure, SelfCalInputError) as exc:
        raise OperationError(f"{args.run}: the run cannot be fitted: {exc}") from exc
    except PlanningError as exc:
        raise OperationError(str(exc)) from exc
    out = sep.to_dict()
    if args.json:
        json.dump(out, sys.stdout)
        sys.stdout.write("\n")
        return 0
    print(f"{robot.name}: {len(sep.poses)} poses that tell {names[0]} from {names[1]} (add them to the plan, "
          "run it and diagnose again)")
    print(f"{'#':>3} {'x (m)':>7} {'y (m)':>7} {'z (m)':>7}  {'expected delta chi2':>19}   setpoint (N)")
    for i, (z, t, sc) in enumerate(zip(sep.poses, sep.setpoints, sep.score, strict=True)):
        print(f"{i:>3} {z[0]:7.3f} {z[1]:7.3f} {z[2]:7.3f}  {sc:19.1f}   " + " ".join(f"{v:7.2f}" for v in t))
    return 0


def _workspace(args) -> int:
    from calib.workspace import plot_workspace, static_workspace

    robot = load_robot(args.robot)
    check_step(args.step)
    if args.plot:
        check_output_option(args.plot, args.force, "--plot")
    from acquisition.cli.progress import Progress

    with Progress(1, "workspace", "positions") as bar:
        ws = static_workspace(robot, step=args.step, progress=bar.update)
    summary = ws.summary()
    if args.plot:
        claim_output_option(args.plot, args.force, "--plot")
        summary["plot"] = str(plot_workspace(ws, robot, args.plot))
    if args.json:
        json.dump(summary, sys.stdout)
        sys.stdout.write("\n")
    else:
        sys.stdout.write(workspace_text(summary, args.step))
    return 0


def workspace_text(summary: dict, step: float) -> str:
    """The workspace summary for a reader: counts, and the extent in m to the millimetre (the JSON keeps the
    full floats)."""
    lines = [f"grid positions: {summary['points']} (step {step:g} m)",
             f"  in the static workspace: {summary['in_workspace']}, on its boundary: {summary['boundary']}"]
    lo, hi = summary.get("extent_lower"), summary.get("extent_upper")
    if lo is None:
        lines.append("  extent: none (no position of the grid is in the static workspace)")
    else:
        lines.append("  extent (m): " + ", ".join(f"{a} {lo[j]:.3f} .. {hi[j]:.3f}" for j, a in enumerate("xyz")))
    if "plot" in summary:
        lines.append(f"plot: {summary['plot']}")
    return "\n".join(lines) + "\n"
