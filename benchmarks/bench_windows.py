"""Equilibrium windows: speed of the whole solve against scipy, and the noisy simulated runs (not collected
by pytest).

    python benchmarks/bench_windows.py [--data DIR] [--repeat R] [--seeds S] [--grid G]

1. sc_8_final (parsed .mat), side by side in this run: the whole tlse solve (windows, rows, initial guess,
   LM; median of R) and scipy.optimize.least_squares ('trf', Jacobian by 2-point finite differences) on the
   same problem from the same initial guess (:func:`calib.selfcal.prepare`), both in CPU time (the wall
   time of a shared machine swings with the other load). Target: >= 90x. Both call the same vectorised
   residual, so the ratio is bounded by counts: scipy's time is its residual evaluations (steps + steps x
   unknowns), ours at least the LM's evaluations; the bench prints both in units of one evaluation.
2. ``cdpr startup --backend sim --grid G`` with sim_backend/examples/noisy_sensors.yaml (AHRS and swivel
   encoders 15x noisier, load cells 3x, a 2 mm sway) for seeds 0..S-1: every planned window found and
   matched, and the initial pose within 2 mm of the simulator's truth. Target: S of S (skipped with
   --seeds 0; a 27-pose startup costs 20-30 s of CPU).
Exits 1 when a target is missed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from calib.robot import load_robot
from calib.selfcal import prepare, solve


def timed(fn, repeat):
    """Median CPU time (s, time.process_time: the machine's other load does not count) over repeat calls."""
    out, times = None, []
    for _ in range(repeat):
        t0 = time.process_time()
        out = fn()
        times.append(time.process_time() - t0)
    return statistics.median(times), out


def real_run(data: Path):
    import scipy.io

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        st = scipy.io.loadmat(str(data / "sc_8_final_parsed.mat"), squeeze_me=True, struct_as_record=False)["st"]
        ws = scipy.io.loadmat(str(data / "ws_selfcalibration_8_final.mat"), squeeze_me=True)
    e = st.epsilon.T
    run = SimpleNamespace(t=st.t - st.t[0], tau=st.tensions.T, tau_ref=st.target_tensions.T, dl=st.cable_length.T,
                          dsigma=st.swivel.T, roll=e[:, 0], pitch=e[:, 1], dyaw=e[:, 2])
    return run, ws["zeta_0_real"]


def against_scipy(robot, run, zeta, repeat: int) -> bool:
    from scipy.optimize import least_squares

    t_ours, sol = timed(lambda: solve(robot, run, reference_pose=zeta), repeat)
    pre = prepare(robot, run)
    problem, p = pre.problem, pre.theta0.size

    def fun(x):
        ev = problem.evaluate(x[:p], x[p:].reshape(-1, 6), derivatives=False)
        return np.concatenate([r.ravel() for _, r, _, _ in ev.groups] + [ev.r0])

    x0 = np.r_[pre.theta0, pre.poses0.ravel()]
    t_sp, ls = timed(lambda: least_squares(fun, x0, jac="2-point", method="trf"), max(1, repeat // 3))
    gap = 1e3 * np.linalg.norm(ls.x[:3] - sol.initial_pose[:3])
    ratio = t_sp / t_ours
    tm = {k: round(v * 1e3, 1) for k, v in sol.timing.items()}
    evals = sol.iterations + 1  # one evaluation (residual and analytic Jacobian) per LM iteration, and x0's
    sp_evals = ls.nfev + ls.njev * x0.size  # its steps, and x0.size more per 2-point Jacobian
    t_res, _ = timed(lambda: [fun(x0) for _ in range(20)], 5)
    t_res /= 20
    print(f"sc_8_final tlse whole solve      {t_ours * 1e3:8.1f} ms CPU ({len(sol.windows)} windows; wall ms {tm}; "
          f"the LM made {evals} evaluations)")
    print(f"scipy least_squares, 2-point FD  {t_sp * 1e3:8.1f} ms CPU ({ls.nfev} steps, {sp_evals} residual "
          f"evaluations; its zeta_0 {gap:.3f} mm from ours, cost {ls.cost:.4f} vs {sol.chi2 / 2:.4f})")
    print(f"one residual evaluation {t_res * 1e3:.2f} ms CPU: scipy's time is {t_sp / t_res:.0f} of them, our whole "
          f"solve's {t_ours / t_res:.1f}; for 90x the whole solve (windows, rows, guess and LM) would have to cost "
          f"at most {sp_evals / 90:.1f} of them, and the LM alone makes {evals}")
    print(f"speed-up {ratio:.0f}x (target >= 90x)  {'ok' if ratio >= 90 else 'MISSED'}")
    print(f"initial pose vs zeta_0_real: eps_p {sol.reference.eps_p * 1e3:.2f} mm, "
          f"eps_r {math.degrees(sol.reference.eps_r):.3f} deg")
    return ratio >= 90


def noisy_seeds(seeds: int, grid: int) -> bool:
    from acquisition.cli import main
    from sim_backend.config import example_path

    ok = 0
    for seed in range(seeds):
        with tempfile.TemporaryDirectory() as tmp:
            out, truth = Path(tmp) / "run", Path(tmp) / "truth.json"
            args = ["startup", "--backend", "sim", "--grid", str(grid), "--seed", str(seed), "--sim-config",
                    str(example_path("noisy_sensors")), "--out", str(out), "--truth", str(truth), "--no-html"]
            with open(os.devnull, "w") as null:
                stdout, sys.stdout = sys.stdout, null
                try:
                    code = main(args)
                finally:
                    sys.stdout = stdout
            if code != 0 or not (out / "solution.json").is_file():
                print(f"seed {seed}: startup exit {code}")
                continue
            sol = json.loads((out / "solution.json").read_text())
            z = json.loads(truth.read_text())["window_mean_pose"]
            ws = sol["window_search"]
            err = 1e3 * float(np.linalg.norm(np.subtract(sol["initial_pose"][:3], z[:3])))
            matched = sorted(w["setpoint"] for w in ws["found"] if w["used"])
            good = matched == list(range(ws["planned"])) and err <= 2.0
            ok += good
            print(f"seed {seed}: {ws['planned']} planned, {len(ws['found'])} found, {ws['used']} used, "
                  f"{len(ws['missing'])} missing; initial pose {err:.2f} mm from the truth  "
                  f"{'ok' if good else 'MISSED'}")
    print(f"noisy sensors and sway, grid {grid}: {ok} of {seeds} seeds (target {seeds} of {seeds})")
    return ok == seeds


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    default = Path(os.environ.get("CDPR_DATA", Path(__file__).resolve().parents[2] / "shared" / "data" / "irma4u"))
    ap.add_argument("--data", type=Path, default=default)
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--grid", type=int, default=3)
    args = ap.parse_args()
    good = True
    if (args.data / "sc_8_final_parsed.mat").is_file():
        run, zeta = real_run(args.data)
        good &= against_scipy(load_robot("irma4u"), run, zeta, args.repeat)
    else:
        print(f"note: {args.data} has no sc_8_final_parsed.mat, the side-by-side rows are skipped", file=sys.stderr)
    if args.seeds > 0:
        good &= noisy_seeds(args.seeds, args.grid)
    return 0 if good else 1


if __name__ == "__main__":
    sys.exit(main())
