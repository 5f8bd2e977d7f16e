"""Sequential startup against the 8-pose grid on the simulated prototype (issue 19, done-when 1; not collected
by pytest).

    python benchmarks/bench_sequential.py [--seeds 20] [--step 0.1]

For each seed, a simulated startup (the full loop: force control, detector, sensors of sim_backend) with the
2x2x2 grid, then one with ``--plan sequential --tolerance TOL`` where TOL is the error the grid reaches: the
root-mean-square over the seeds of the grid's initial-position error. Every run is solved by the same
estimator (the planning model of calib.design with its window-mean noise) and compared with the simulator's
true initial pose. Prints both distributions (error and robot time: median, 10th and 90th percentiles).
Target: median robot time of the sequential startup <= 0.5 x the grid's, with an RMS error <= TOL.
Exit status 1 when missed.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from acquisition.cli.startup import simulated_startup
from acquisition.runlog import read_run
from calib.design import planning_model, window_mean_noise
from calib.robot import load_robot
from calib.selfcal import solve

TARGET = 0.5


def error(robot, out: dict) -> float:
    """Initial-position error (m) of the planning estimator on the run against the simulator's truth."""
    sol = solve(robot, read_run(out["run"]), noise=window_mean_noise(robot), model=planning_model(robot))
    return float(np.linalg.norm(sol.initial_pose[:3] - np.asarray(out["truth"][:3])))


def describe(name: str, err: np.ndarray, t: np.ndarray) -> str:
    q = np.percentile
    return (f"{name:<26} error mm: median {1000 * np.median(err):.3f} p10 {1000 * q(err, 10):.3f} "
            f"p90 {1000 * q(err, 90):.3f} rms {1000 * np.sqrt(np.mean(err**2)):.3f} | robot time s: median "
            f"{np.median(t):.1f} p10 {q(t, 10):.1f} p90 {q(t, 90):.1f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--step", type=float, default=0.1, help="candidate spacing of the sequential plan, m")
    args = ap.parse_args()
    robot = load_robot("irma4u")
    with tempfile.TemporaryDirectory() as tmp:
        grid = [simulated_startup(Path(tmp) / f"grid-{s}", "grid2", seed=s) for s in range(args.seeds)]
        e_grid = np.array([error(robot, o) for o in grid])
        t_grid = np.array([o["timing"]["acquisition_s"] for o in grid])
        tol = float(np.sqrt(np.mean(e_grid**2)))
        print(f"tolerance (RMS error of the grid over {args.seeds} seeds): {1000 * tol:.3f} mm", flush=True)
        seq = [simulated_startup(Path(tmp) / f"seq-{s}", "sequential", tolerance=tol, seed=s, step=args.step)
               for s in range(args.seeds)]
        e_seq = np.array([error(robot, o) for o in seq])
        t_seq = np.array([o["timing"]["acquisition_s"] for o in seq])
        poses = [o["setpoints"] for o in seq]
    print(describe("grid 2x2x2 (8 poses)", e_grid, t_grid))
    print(describe(f"sequential ({min(poses)}-{max(poses)} poses)", e_seq, t_seq))
    print("grid robot times s:       " + " ".join(f"{v:.1f}" for v in t_grid))
    print("sequential robot times s: " + " ".join(f"{v:.1f}" for v in t_seq))
    ratio = float(np.median(t_seq) / np.median(t_grid))
    rms = float(np.sqrt(np.mean(e_seq**2)))
    ok = ratio <= TARGET and rms <= tol
    print(f"median robot time sequential / grid: {ratio:.3f} (target <= {TARGET}); RMS error {1000 * rms:.3f} mm "
          f"(target <= {1000 * tol:.3f} mm) {'ok' if ok else 'MISSED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
