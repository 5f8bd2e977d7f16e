"""Is the study's 1-sigma honest per axis (issue 29, done-when 2; not collected by pytest)?

    OMP_NUM_THREADS=1 python benchmarks/bench_study_sigma.py --keep DIR [--runs 200] [--first 0] [--existing]
        [--split shrunk|own|pooled|D0] [--groups]

Simulated grid2 startups as `cdpr study --plan grid2` runs them (acquisition.study.startup_request, the
seed's sensor noise and power-on pose), kept with their truth in DIR (made once: a second call only
re-solves them, about 0.5 s of CPU a run), each re-solved with this checkout's estimate-noise solve (what
`cdpr startup` prints) and scored as the study scores it (run_result against the pose the reference
window's mean readings describe, plan_statistics). Prints the study's per-axis rms(error/sigma) and
coverage of the 1-sigma; targets 0.8-1.25 and 60-76 % on every axis. Exits 1 on a miss. Beside them, the
rms error and rms printed sigma per axis (um): whether a change makes the estimate better or only its sigma
narrower. With N runs a coverage is known to about +-sqrt(0.68 x 0.32 / N) (3.3 % at 200).

--existing scores only the seeds already kept in DIR (no new startup). --groups also prints, per channel group,
the rows' error at the truth (each row's residual at the true window-mean poses and the true initial pose, the
other parameters 0, centred per channel over the windows) against the sigma the solve gave them: which group's
sigma is honest, too wide or too narrow (docs/windows.md, "The quantisation error of a window mean").
--split is a what-if of the per-cable
swivel components (calib.selfcal.noise.cable_factors): "shrunk" the solve's empirical Bayes (default), "own"
each cable its own Helmert factor (prior dof 0), "pooled" no split, a number a fixed prior dof.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

RMS_BAND = (0.8, 1.25)
COVERAGE_BAND = (0.60, 0.76)


def kept_startup(folder: Path, seed: int) -> None:
    """The study's grid2 startup of ``seed`` in folder/run with its truth in folder/truth.json (made once)."""
    from acquisition import session
    from acquisition.study import RunTask, StudyConfig, startup_request

    if (folder / "truth.json").exists():
        return
    task = RunTask("grid2", seed, StudyConfig())
    session.run_startup(startup_request(task, str(folder / "run"), str(folder / "truth.json"), None))


def scored(folder: Path, seed: int) -> dict:
    """The run re-solved with this checkout and scored as `cdpr study` scores it (acquisition.study.run_result)."""
    from acquisition.runlog import read_run
    from acquisition.study import RunTask, StudyConfig, run_result
    from calib.selfcal import solve

    run = read_run(folder / "run")
    sol = solve(run.robot, run, noise="estimate")
    summary = {"solution": sol.to_json(), "timing": {"acquisition_s": 0.0}, "windows": [], "setpoints": 8}
    return run_result(RunTask("grid2", seed, StudyConfig()), summary, json.loads((folder / "truth.json").read_text()))


def group_errors(folder: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per channel group of the kept run in ``folder``: the mean square (per reading, SI^2) of its rows' error at
    the truth and the solve's sigma^2 for them (see --groups)."""
    from acquisition.runlog import read_run
    from calib.selfcal import solve
    from calib.selfcal.guess import prepare
    from calib.selfcal.problem import Problem

    truth = json.loads((folder / "truth.json").read_text())
    run = read_run(folder / "run")
    sol = solve(run.robot, run, noise="estimate")
    pre = prepare(run.robot, run, noise="estimate")
    meas = pre.problem.meas
    sigma = {c: np.asarray(v, float) for c, v in sol.noise.items()}
    problem = Problem(pre.problem.model, meas, sigma)
    poses = np.asarray(truth["poses"], float)
    Z = np.array([poses[int(a):int(b) + 1].mean(0) for a, b in meas.windows])
    theta = np.zeros(pre.theta0.size)
    theta[:6] = truth["window_mean_pose"]
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for g, r, _, _ in problem.evaluate(theta, Z).groups:
        err = r / np.where(g.weight > 0, g.weight, np.nan)
        for c in g.channels:
            x = err[:, g.slices[c]]
            x = x - np.nanmean(x, axis=0)
            out[c] = (np.nansum(x**2, axis=0) / np.maximum(np.sum(np.isfinite(x), axis=0) - 1, 1), sigma[c] ** 2)
    return out


def what_if_split(split: str) -> None:
    """This process's solves with the per-cable swivel components of ``split`` (see the module's doc)."""
    import calib.selfcal._solve as solve_module
    import calib.selfcal.noise as noise

    if split == "pooled":
        solve_module.PER_CABLE = ()
    elif split != "shrunk":
        d0 = 0.0 if split == "own" else float(split)
        noise.prior_dof = lambda variances, dof: d0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", required=True, help="folder of the kept startups (made on the first call)")
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--first", type=int, default=0, help="first seed")
    ap.add_argument("--existing", action="store_true", help="score only the seeds already kept in --keep")
    ap.add_argument("--split", default="shrunk", help="per-cable swivel components: shrunk, own, pooled or a prior dof")
    ap.add_argument("--groups", action="store_true",
                    help="also each channel group's error at the truth against its sigma")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    from acquisition.study import plan_statistics

    what_if_split(args.split)
    results, groups = [], {}
    for seed in range(args.first, args.first + args.runs):
        folder = Path(args.keep) / f"s{seed:05d}"
        if args.existing and not (folder / "truth.json").exists():
            continue
        kept_startup(folder, seed)
        results.append(scored(folder, seed))
        if args.groups:
            for c, v in group_errors(folder).items():
                groups.setdefault(c, []).append(v)
    axes = plan_statistics(results)["axes"]
    err = np.array([r["position_error_m"] for r in results], float) * 1e6
    sig = np.array([r["position_sigma_m"] for r in results], float) * 1e6
    ok = True
    per_axis = zip("xyz", axes["rms_error_over_sigma"], axes["coverage_1sigma"], strict=True)
    for i, (name, rms, cov) in enumerate(per_axis):
        hit = RMS_BAND[0] <= rms <= RMS_BAND[1] and COVERAGE_BAND[0] <= cov <= COVERAGE_BAND[1]
        ok &= hit
        print(f"{name}: rms(error/sigma) {rms:.2f} (target {RMS_BAND[0]}-{RMS_BAND[1]}), coverage of the 1-sigma "
              f"{100 * cov:.0f} % (target {100 * COVERAGE_BAND[0]:.0f}-{100 * COVERAGE_BAND[1]:.0f} %) "
              f"{'ok' if hit else 'MISS'}; rms error {np.sqrt(np.mean(err[:, i] ** 2)):.2f} um, "
              f"rms sigma {np.sqrt(np.mean(sig[:, i] ** 2)):.2f} um")
    for c, v in groups.items():
        err2, sig2 = np.mean([e for e, _ in v], axis=0), np.mean([s for _, s in v], axis=0)
        unit = 1e3 if c == "tension" else 1e6
        print(f"{c}: rms error at the truth {np.round(np.sqrt(err2) * unit, 2).tolist()}, rms sigma "
              f"{np.round(np.sqrt(sig2) * unit, 2).tolist()} ({'mN' if c == 'tension' else 'um, urad'}), "
              f"error / sigma {np.round(np.sqrt(err2 / sig2), 2).tolist()}")
    print(f"{'PASS' if ok else 'FAIL'}: {len(results)} grid2 startups, seeds {args.first}-{args.first + args.runs - 1}"
          f"{' (kept ones)' if args.existing else ''}, per-cable swivel split {args.split}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
