"""The A-optimal 8-pose plan against the 2x2x2 grid (issue 19, done-when 2; not collected by pytest).

    python benchmarks/bench_plans.py [--poses 8] [--runs 40] [--loop [--cache DIR] [--workers 2]]

Prints, for both plans, the predicted 1-sigma of the initial position (sqrt of the trace of its covariance,
window-mean noise of calib.design plus the devices' constant errors) and the robot time, then checks the
prediction by Monte Carlo: ``--runs`` simulated sets of window means at the plan's poses
(sim_backend.equilibrium_rows: the same noise, the load cells' and the AHRS's constant errors drawn per run),
each solved with the planning model; the RMS position error should match the predicted 1-sigma.
``--loop``: the Monte Carlo with full simulated startups of both plans instead (benchmarks/loop_runs.py:
realistic noise, sim_backend/examples/rigid_sway.yaml; the estimate-noise solve against the pose averaged
over the reference window; 8 poses only, the startup's --plan optimal), against the loop's prediction
(calib.design.predict_loop: the first pose's window is the reference, as in the run's solve, and each
window has the loop's noise at its pose, calib.design.LOOP_POSE_NOISE, scaled on the grid's runs only).
Target: optimal / grid predicted 1-sigma <= 0.7, and the optimal plan's RMS error within 20 % of its predicted
1-sigma. Exit status 1 when missed.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from loop_runs import runs

from calib.design import LOOP_POSE_NOISE, TimeModel, assess, loop_noise, optimal_plan, planning_model, predict_loop
from calib.planning import plan_poses
from calib.robot import load_robot
from calib.selfcal import solve
from sim_backend.config import load_sim_config
from sim_backend.equilibrium_rows import simulated_rows

TARGET = 0.7
MC_TARGET = 0.20  # relative difference of the RMS error from the predicted 1-sigma


def monte_carlo(robot, plan, noise, runs: int) -> np.ndarray:
    """Position errors (runs,) m of the planning model's solve on simulated window means at the plan."""
    config = load_sim_config(None, robot.n)
    model = planning_model(robot)
    err = []
    for seed in range(runs):
        rows = simulated_rows(robot, config, seed=seed, noise=noise, plan=plan)
        sol = solve(robot, rows.meas, noise=noise, model=model, guess=(rows.guess_zeta0, rows.guess_poses))
        err.append(np.linalg.norm(sol.initial_pose[:3] - rows.zeta0[:3]))
    return np.array(err)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=8)
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--loop", action="store_true", help="full simulated startups instead of window means")
    ap.add_argument("--cache", help="--loop: folder of the runs' results (reused; shared with bench_sequential.py)")
    ap.add_argument("--workers", type=int, default=2, help="--loop: startups in parallel")
    args = ap.parse_args()
    robot = load_robot("irma4u")
    noise, times = loop_noise(robot), TimeModel()
    # the loop's optimal plan is the startup's: chosen with the loop's noise at each pose
    chosen_with = LOOP_POSE_NOISE if args.loop else noise
    plans = {"grid 2x2x2": plan_poses(robot, 2), f"optimal {args.poses}": optimal_plan(robot, args.poses, chosen_with)}
    sig, rms = {}, {}
    print(f"{'plan':<12} {'poses':>5} {'predicted 1-sigma':>18} {'MC rms error':>13} {'ratio':>6} {'robot time':>11}")
    for (name, plan), key in zip(plans.items(), ("grid2", "optimal"), strict=True):
        a = predict_loop(robot, plan, times) if args.loop else assess(robot, plan, noise, times)
        if args.loop:
            res = runs(key, args.runs, cache=args.cache, workers=args.workers)
            err = np.array([r["error_m"] for r in res])
            t = f"{np.median([r['robot_time_s'] for r in res]):>9.0f} s (loop median)"
        else:
            err = monte_carlo(robot, plan, noise, args.runs)
            t = f"{a.robot_time:>9.0f} s"
        sig[name], rms[name] = a.position_sigma, float(np.sqrt(np.mean(err**2)))
        print(f"{name:<12} {len(plan.poses):>5} {1000 * a.position_sigma:>15.3f} mm "
              f"{1000 * rms[name]:>10.3f} mm {rms[name] / a.position_sigma:>6.2f} {t}")
    grid, opt = sig.values()
    ratio = opt / grid
    mc = list(rms.values())[1] / opt
    ok = ratio <= TARGET and abs(mc - 1.0) <= MC_TARGET
    print(f"optimal / grid predicted 1-sigma: {ratio:.3f} (target <= {TARGET}); optimal RMS error / predicted "
          f"1-sigma: {mc:.2f} (target 1 +- {MC_TARGET:.2f}, {args.runs} runs) {'ok' if ok else 'MISSED'}")
    return 0 if ok else 1

if __name__ == "__main__":
    sys.exit(main())
