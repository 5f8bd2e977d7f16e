"""Speed of the self-calibration solves (not collected by pytest).

    python benchmarks/bench_solve.py [--data DIR] [--repeat R]

Measures (median wall time over R repeats):
- tlse, 8 poses: the authors' picked samples and guess (ws_selfcalibration_8_final.mat), LM alone, and the
  whole solve of the real run from its arrays (windows, guess, LM);
- tlse, 27 poses: synthetic 3x3x3 grid, model readings plus sensor noise, guess 2 cm / 2 deg off;
- lse, k = 250, 500, 1000, 2000 samples: synthetic poses over the workspace, from a guess 2 cm / 2 deg off
  (LM alone) and with the per-sample pose estimation of the initial guess (total);
- lse and hybrid on the real run, every sample.
Targets: tlse 8 poses <= 20 ms, 27 poses <= 60 ms, lse 1000 samples <= 1 s, time linear in k.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import statistics
import sys
import time
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import scipy.io

from calib.kinematics import convert_euler, inverse_kinematics
from calib.robot import load_robot
from calib.selfcal import Measurements, sensor_noise, solve
from calib.statics import tension_model


def timed(fn, repeat):
    out, times = None, []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def synthetic(robot, poses, rng, static=True):
    sig = sensor_noise(robot)
    kin = inverse_kinematics(robot, poses)
    tau = tension_model(robot, poses, derivatives=False).tau if static else np.full((len(poses), robot.n), np.nan)
    ori = convert_euler(poses[:, 3:], robot.orientation, robot.ahrs_convention)[0]  # what the AHRS reads
    ori[:, 2] -= ori[0, 2]
    noise = {c: rng.normal(0, 1, s) * sig[c] for c, s in
             (("tension", tau.shape), ("length", kin.lengths.shape), ("swivel", kin.swivel.shape),
              ("orientation", ori.shape))}
    tau = tau + noise["tension"]
    dl = kin.lengths - kin.lengths[0] + noise["length"]
    ds = kin.swivel - kin.swivel[0] + noise["swivel"]
    ori = ori + noise["orientation"]
    ref_tau = tau[0] if static else np.full(robot.n, np.nan)
    return Measurements(tau[1:], dl[1:], ds[1:], ori[1:], ref_tau, ori[0, :2]), sig


def random_poses(k, rng):
    p = rng.uniform([-0.4, -0.4, 0.6], [0.4, 0.4, 1.2], (k, 3))
    a = rng.uniform(-0.15, 0.15, (k, 3)) * [1, 1, 0.2]
    return np.c_[p, a]


def off(z, rng):
    return z + np.r_[rng.normal(0, 0.02, 3), rng.normal(0, math.radians(2), 3)] * np.ones_like(z)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    default = Path(os.environ.get("CDPR_DATA", Path(__file__).resolve().parents[2] / "shared" / "data" / "irma4u"))
    ap.add_argument("--data", type=Path, default=default)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    robot = load_robot("irma4u")
    rng = np.random.default_rng(1)
    R = args.repeat
    rows = []
    ws_file = args.data / "ws_selfcalibration_8_final.mat"
    if ws_file.is_file():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            w = scipy.io.loadmat(str(ws_file), squeeze_me=True, struct_as_record=False)
            st = scipy.io.loadmat(str(args.data / "sc_8_final_parsed.mat"), squeeze_me=True,
                                  struct_as_record=False)["st"]
        meas = Measurements(w["loadcell_meas"].T, w["delta_length_meas"].T, w["delta_swivel_meas"].T,
                            np.c_[w["roll_meas"], w["pitch_meas"], w["delta_yaw_meas"]],
                            np.full(4, np.nan), np.full(2, np.nan))
        x = w["X_guess"]
        authors = robot.replace(sensors=dataclasses.replace(robot.sensors, ahrs_convention="xyz"))  # their model
        t, sol = timed(lambda: solve(authors, meas, guess=(x[:6], x[6:].reshape(-1, 6)),
                                     reference_pose=w["zeta_0_real"]), R)
        rows.append(("tlse, 8 poses, authors' samples (LM)", t, f"eps_p {sol.reference.eps_p * 1e3:.2f} mm, "
                     f"eps_r {math.degrees(sol.reference.eps_r):.3f} deg, {sol.iterations} it"))
        e = st.epsilon.T
        run = SimpleNamespace(t=st.t - st.t[0], tau=st.tensions.T, tau_ref=st.target_tensions.T,
                              dl=st.cable_length.T, dsigma=st.swivel.T, roll=e[:, 0], pitch=e[:, 1], dyaw=e[:, 2])
        for method in ("tlse", "lse", "hybrid"):
            t, sol = timed(lambda m=method: solve(robot, run, method=m, reference_pose=w["zeta_0_real"]), R)
            rows.append((f"{method}, real run, every sample ({len(sol.poses) + 1} poses, whole solve)", t,
                         f"eps_p {sol.reference.eps_p * 1e3:.1f} mm, eps_r {math.degrees(sol.reference.eps_r):.2f}"
                         f" deg, geodesic {math.degrees(sol.reference.geodesic):.2f} deg"))
    else:
        print(f"note: {ws_file} not found, real-data rows skipped", file=sys.stderr)
    grid = np.array([[x_, y_, z_] for z_ in (1.2, 0.9, 0.6) for x_ in (0.4, 0.0, -0.4) for y_ in (0.4, 0.0, -0.4)])
    poses = np.c_[grid, rng.uniform(-0.15, 0.15, (27, 3)) * [1, 1, 0.1]]
    meas, sig = synthetic(robot, poses, rng)
    g = (off(poses[0], rng), np.array([off(p, rng) for p in poses[1:]]))
    t, sol = timed(lambda: solve(robot, meas, noise=sig, guess=g), R)
    rows.append(("tlse, 27 poses, synthetic (LM)", t,
                 f"error {np.linalg.norm(sol.initial_pose[:3] - poses[0, :3]) * 1e3:.3f} mm, {sol.iterations} it"))
    for k in (250, 500, 1000, 2000):
        poses = random_poses(k + 1, rng)
        meas, sig = synthetic(robot, poses, rng, static=False)
        z0 = off(poses[0], rng)
        g = (z0, np.array([off(p, rng) for p in poses[1:]]))
        t, sol = timed(lambda m=meas, s=sig, gg=g: solve(robot, m, noise=s, guess=gg), R)

        def total(m=meas, s=sig, z=z0):  # the poses estimated from the readings (trilateration, then LM)
            return solve(robot, m, noise=s, guess=(z, None))

        t2, sol2 = timed(total, max(1, R // 2))
        rows.append((f"lse, {k} samples, synthetic (LM / with pose-estimation guess)", t,
                     f"total {t2 * 1e3:.0f} ms, error {np.linalg.norm(sol2.initial_pose[:3] - poses[0, :3]) * 1e3:.3f}"
                     f" mm, {sol.iterations} it"))
    width = max(len(r[0]) for r in rows)
    for name, t, note in rows:
        print(f"{name:<{width}}  {t * 1e3:9.1f} ms   {note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
