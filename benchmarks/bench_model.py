"""Benchmark: inverse kinematics plus analytic Jacobians (lengths, swivel angles, tensions) for many poses.

Target (issue 2): <= 20 ms for 10,000 poses on the 2-core machine. Run: python benchmarks/bench_model.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from calib.equilibrium import inverse_geometrico_static
from calib.kinematics import inverse_kinematics, kinematic_jacobians
from calib.robot import load_robot
from calib.statics import tension_model


def best_of(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times), float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--poses", type=int, default=10_000)
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args()
    robot = load_robot("irma4u")
    rng = np.random.default_rng(0)
    eq = inverse_geometrico_static(robot, rng.uniform(robot.workspace_lower, robot.workspace_upper, (args.poses, 3)))
    z = eq.poses + np.c_[np.zeros((args.poses, 3)), rng.uniform(-0.05, 0.05, (args.poses, 3))]

    def ik_and_kinematic_jacobians():
        kin = inverse_kinematics(robot, z)
        return kinematic_jacobians(robot, kin)

    def full():
        kin = inverse_kinematics(robot, z)
        jac = kinematic_jacobians(robot, kin)
        return tension_model(robot, kin=kin, jac=jac)

    for name, fn in [
        ("IK only", lambda: inverse_kinematics(robot, z)),
        ("IK + length/swivel Jacobians", ik_and_kinematic_jacobians),
        ("IK + length/swivel/tension Jacobians", full),
    ]:
        best, med = best_of(fn, args.repeat)
        print(f"{name:40s} {args.poses} poses: best {best * 1e3:7.2f} ms, median {med * 1e3:7.2f} ms")


if __name__ == "__main__":
    main()
