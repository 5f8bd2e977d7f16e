"""Honest noise of window means: chi2 and printed 1-sigma of `cdpr solve --noise estimate` on effect-free
simulated startups (not collected by pytest).

For each seed and each configuration, a whole simulated startup (`cdpr startup --backend sim`, the
prototype's devices and their power-on errors, no hidden effect) then `calib.selfcal.solve(noise="estimate")`,
the computation of `cdpr solve --noise estimate`:
- ``white``: sim_backend/examples/rigid.yaml, the prototype's sensors (white noise and the encoders' counts);
- ``sway``: sim_backend/examples/rigid_sway.yaml (load cells ~1 N, encoders ~0.2 mm, AHRS ~0.02 deg and a
  slow sway of the platform inside the windows).
Both with rigid cables: the simulator's nominal EA (2e6 N) is the library's cable_elasticity, an effect.
Counted: the chi2 inside its two-sided 99 % band (target: >= 95 % of the seeds) and, over the seeds, the rms of
(initial-position error / printed sigma) over the three axes (target 0.8-1.25). The truth is the simulator's
pose averaged over the reference window (what a window mean estimates). Exit code 1 on a miss.

    python benchmarks/bench_noise.py [--seeds 100] [--first 0] [--grid 2] [--configs white,sway] [--workers 2]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy import stats

CONFIGS = {"white": "rigid", "sway": "rigid_sway"}


def one(config: str, seed: int, grid: int) -> dict | None:
    """One simulated startup and its estimate-noise solve: chi2, dof, error and sigma of the position (m)."""
    from acquisition.cli.errors import OperationError, UsageError
    from acquisition.runlog import read_run
    from acquisition.session import simulated_startup
    from calib.selfcal import solve
    from sim_backend.config import example_path

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        try:
            doc = simulated_startup(out, f"grid{grid}", seed=seed, sim_config=str(example_path(CONFIGS[config])))
        except (UsageError, OperationError):
            return None
        ref = np.asarray(doc["truth_window_mean"] or doc["truth"], float)
        run = read_run(out)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sol = solve(run.robot, run, noise="estimate")
    err = np.asarray(sol.initial_pose[:3]) - ref[:3]
    return {"config": config, "seed": seed, "chi2": float(sol.chi2), "dof": int(sol.dof),
            "err": err.tolist(), "sigma": list(map(float, sol.initial_pose_sigma[:3]))}


def chi2_band(rs: list[dict]) -> tuple[int, int, np.ndarray]:
    """Of runs with ``chi2``, ``dof``, ``err`` and ``sigma``: how many chi2 fall below and above the two-sided
    99 % band, and the (runs, 3) errors over their printed sigmas."""
    below = sum(r["chi2"] < stats.chi2.ppf(0.005, r["dof"]) for r in rs)
    above = sum(r["chi2"] > stats.chi2.ppf(0.995, r["dof"]) for r in rs)
    return below, above, np.array([np.divide(r["err"], r["sigma"]) for r in rs])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--grid", type=int, default=2)
    ap.add_argument("--configs", default="white,sway")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = ap.parse_args()
    configs = [c.strip() for c in args.configs.split(",")]
    bad = [c for c in configs if c not in CONFIGS]
    if bad:
        print(f"--configs: '{bad[0]}' is not one of {', '.join(CONFIGS)}.")
        return 2
    t0 = time.perf_counter()
    jobs = [(c, s, args.grid) for c in configs for s in range(args.first, args.first + args.seeds)]
    with ProcessPoolExecutor(max_workers=max(1, args.workers)) as pool:
        results = list(pool.map(one, *zip(*jobs, strict=True)))
    ok = True
    for c in configs:
        rs = [r for r in results if r is not None and r["config"] == c]
        failed = sum(1 for (cc, _, _), r in zip(jobs, results, strict=True) if cc == c and r is None)
        if not rs:
            print(f"{c}: no run finished")
            ok = False
            continue
        below, above, zs = chi2_band(rs)
        inside = len(rs) - below - above
        rms = float(np.sqrt(np.mean(zs**2)))
        per_axis = np.sqrt(np.mean(zs**2, axis=0))
        errs = 1e3 * np.linalg.norm([r["err"] for r in rs], axis=1)
        band_ok = inside >= math.ceil(0.95 * len(rs))
        rms_ok = 0.8 <= rms <= 1.25
        ok &= band_ok and rms_ok and failed == 0
        print(f"{c:6s} {len(rs)} runs ({failed} failed): chi2 inside its 99% band in {inside}/{len(rs)} "
              f"(target >= 95%) {'ok' if band_ok else 'MISSED'} ({below} below, {above} above); median chi2/dof "
              f"{np.median([r['chi2'] / r['dof'] for r in rs]):.2f}")
        print(f"       rms(error/sigma) {rms:.2f} (x {per_axis[0]:.2f}, y {per_axis[1]:.2f}, z {per_axis[2]:.2f}; "
              f"target 0.8-1.25) {'ok' if rms_ok else 'MISSED'}; position error median {np.median(errs):.3f} mm, "
              f"max {errs.max():.3f} mm")
    print(f"{len(jobs)} startups in {time.perf_counter() - t0:.0f} s")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
