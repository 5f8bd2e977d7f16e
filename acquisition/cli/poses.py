"""`cdpr poses` (calibration pose planning) and `cdpr workspace` (static workspace map and plot)."""

from __future__ import annotations

import json
import sys

import numpy as np

from acquisition.cli.args import add_force, check_grid, check_output_option, claim_output_option
from acquisition.cli.errors import OperationError, UsageError
from calib.planning import PlanningError, kinematic_path, plan_poses
from calib.robot import RobotDescriptionError, load_robot


def register(sub) -> None:
    p = sub.add_parser("poses", help="plan the calibration poses and tension setpoints (Sec. 3.2.1)")
    p.add_argument("--robot", default="irma4u", help="built-in robot name or robot YAML file (default irma4u)")
    p.add_argument("--grid", type=int, default=2,
                   help="grid points per axis in the workspace bounds, 2 to 6 as for cdpr startup (default 2)")
    p.add_argument("--method", choices=("equilibrium", "kinematic"), default="equilibrium",
                   help="equilibrium: static poses (default); kinematic: a constant-speed path")
    p.add_argument("--speed", type=float, default=0.05, help="kinematic method: path speed, m/s")
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


def _robot(name: str):
    try:
        return load_robot(name)
    except RobotDescriptionError as exc:
        raise UsageError(str(exc)) from exc


def _poses(args) -> int:
    robot = _robot(args.robot)
    check_grid(args.grid)
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
    print(f"{robot.name}: {len(out['poses'])} poses ({args.method}), visiting order")
    print(f"{'#':>3} {'x':>7} {'y':>7} {'z':>7} {'roll°':>7} {'pitch°':>7} {'yaw°':>7}   setpoint (N)")
    for i, (z, t) in enumerate(zip(out["poses"], out["setpoints"], strict=True)):
        ang = np.degrees(z[3:])
        print(
            f"{i:>3} {z[0]:7.3f} {z[1]:7.3f} {z[2]:7.3f} {ang[0]:7.2f} {ang[1]:7.2f} {ang[2]:7.2f}   "
            + " ".join(f"{v:7.2f}" for v in t)
        )
    if "transition_cost" in out:
        print(f"home tensions tau0 = {out['tau0']} N; tour transition cost {out['transition_cost']:.1f} N")
    return 0


def _workspace(args) -> int:
    from calib.workspace import plot_workspace, static_workspace

    robot = _robot(args.robot)
    if not args.step > 0:
        raise UsageError(f"--step must be positive, got {args.step}.")
    if args.plot:
        check_output_option(args.plot, args.force, "--plot")
    ws = static_workspace(robot, step=args.step)
    summary = ws.summary()
    if args.plot:
        claim_output_option(args.plot, args.force, "--plot")
        summary["plot"] = str(plot_workspace(ws, robot, args.plot))
    if args.json:
        json.dump(summary, sys.stdout)
        sys.stdout.write("\n")
    else:
        for k, v in summary.items():
            print(f"{k:>14}: {v}")
    return 0
