"""Noise models judged by what they predict on held-out real windows (issue 29 point 2; not collected by pytest).

For each real import (sc_8_final's raw .log and parsed .mat, sc_8_medium_a and sc_27_medium_a parsed, each with
its targets) and each noise model (``paper``: eq. 18; ``estimate``: the run's own noise of a window mean, the
default; ``estimate+sway``: the same with the sway term in the statics rows, SolveOptions.sway), every
equilibrium window but the reference's is left out in turn: the run is solved on the other windows with that
noise model (same windows, same reference sample), then the left-out window's readings are predicted with
every parameter of that fold held (theta, the reference's means) and only the window's own pose fitted to them.
Two scores per fold, summed over the folds:

- J: the window's misfit, sum over the channels (tension, length, swivel, orientation) of (rms residual / w)^2
  with issue 28's fixed w (1 N, 0.5 mm, 0.1 deg, 0.2 deg: calib.multirun.misfit_j), the pose fitted under the
  model's own sigmas (what that model would do with the window);
- NLPD: the negative log predictive density of the window's readings (SI units) under the model's own
  sigmas: Gaussian, covariance diag(sigma^2) + G Cov(theta) G^T (the fold's parameter uncertainty through the
  row's theta Jacobian G), the unknown pose integrated out under a flat prior (the restricted density: pose
  fitted by generalised least squares, plus 0.5 log det of its information); lower is better. A sigma too
  narrow for what it predicts pays in chi2, one too wide in log det. Printed with it: the mean squared
  normalised prediction error (chi2 / rows, 1 when the sigma fits the prediction).

Printed per run and model, then summed; also each model's full-run initial position and its distance to
``zeta_0_real`` (sc_8_final only, for information: that reference is uncertain by several mm).

    OMP_NUM_THREADS=1 python benchmarks/bench_noise_prediction.py --data ../shared/data/irma4u [--runs NAME,...]
        [--json FILE]

Exits 0 (a measurement, no target: the decision it informs is in docs/windows.md, "Sway in the statics rows").
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from bench_raw_parsed import zeta_0_real  # this folder: sys.path[0] when run as a script

IMPORTS = {  # name: (file, targets)
    "sc_8_final raw": ("sc_8_final.log", "sc_control_target_8_final.mat"),
    "sc_8_final parsed": ("sc_8_final_parsed.mat", "sc_control_target_8_final.mat"),
    "sc_8_medium_a": ("sc_8_medium_a_parsed.mat", "sc_control_target_8.mat"),
    "sc_27_medium_a": ("sc_27_medium_a_parsed.mat", "sc_control_target_27.mat"),
}
MODELS = {"paper": {"noise": "paper"}, "estimate": {"noise": "estimate"},
          "estimate+sway": {"noise": "estimate", "sway": True}}


def fold_model(robot, sol):
    """The measurement model a solve ended with, rebuilt from its Solution (the rigid model for the paper's
    weights; the device accuracies and the reference window's noise for an estimate solve)."""
    from calib.effects import EffectModel
    from calib.effects.priors import DeviceAccuracy, ReferenceNoise
    from calib.selfcal import MeasurementModel

    if sol.reference_noise is None:
        model = MeasurementModel(robot)
    else:
        rn = sol.reference_noise
        model = EffectModel(robot, [DeviceAccuracy(), ReferenceNoise(rn["length"], rn["swivel"], rn["yaw"])])
    if list(model.param_names) != list(sol.param_names):
        raise RuntimeError(f"rebuilt model's parameters {model.param_names} are not the solve's {sol.param_names}")
    return model


def predict_window(run, sol, window, ref_win, ref_sample: int, start: np.ndarray) -> dict:
    """The left-out ``window``'s readings predicted by a fold's solution ``sol``: J (fixed w), NLPD and
    chi2 / rows (module doc). ``start``: a pose (6,) to fit the window's pose from."""
    from calib.multirun import misfit_j
    from calib.selfcal import prepare
    from calib.selfcal.lm import solve_poses

    model = fold_model(run.robot, sol)
    sigma = {c: np.asarray(v, float) for c, v in sol.noise.items()}
    pre = prepare(run.robot, run, model=model, noise=sigma, windows=[ref_win, window], reference_sample=ref_sample)
    problem, theta = pre.problem, np.asarray(sol.theta, float)
    if problem.k != 1:
        raise RuntimeError(f"expected one row for window [{window.first}, {window.last}], got {problem.k}")
    Z, _ = solve_poses(problem, theta, np.asarray(start, float)[None], max_iter=100, tol=1e-12)
    ev = problem.evaluate(theta, Z)
    rms: dict[str, float] = {}
    rs, Js, Gs, logsig = [], [], [], 0.0
    for g, r, J, G in ev.groups:
        for c in g.channels:
            w, rr = g.weight[0, g.slices[c]], r[0, g.slices[c]]
            ok = w > 0
            rms[c] = float(np.sqrt(np.mean((rr[ok] / w[ok]) ** 2)))
        keep = g.weight[0] > 0
        rs.append(r[0, keep])
        Js.append(J[0, keep])
        Gs.append(G[0, keep])
        logsig -= float(np.sum(np.log(g.weight[0, keep])))
    r, J, G = np.concatenate(rs), np.vstack(Js), np.vstack(Gs)
    m = r.size
    C = np.eye(m) + G @ np.asarray(sol.covariance, float) @ G.T
    L = np.linalg.cholesky(C)
    rt, Jt = np.linalg.solve(L, r), np.linalg.solve(L, J)
    step = np.linalg.lstsq(Jt, rt, rcond=None)[0]
    e = rt - Jt @ step
    chi2 = float(e @ e)
    logdet_c = 2.0 * float(np.sum(np.log(np.diag(L))))
    logdet_p = float(np.linalg.slogdet(Jt.T @ Jt)[1])
    nlpd = 0.5 * (chi2 + (m - 6) * math.log(2.0 * math.pi) + logdet_c + logdet_p) + logsig
    return {"J": misfit_j(rms), "nlpd": nlpd, "chi2_per_row": chi2 / max(m - 6, 1), "rms": rms}


def run_imports(data: Path, out: Path, names: list[str]) -> dict:
    from acquisition.importers import import_irma

    runs = {}
    for name in names:
        f, targets = IMPORTS[name]
        with contextlib.redirect_stderr(io.StringIO()):
            runs[name] = import_irma(data / f, out / name.replace(" ", "_"), targets=data / targets)
    return runs


def one_run(name: str, run, models: list[str], z0: np.ndarray | None) -> dict:
    """Leave-one-window-out prediction of one import under each model (module doc)."""
    from calib.selfcal import SelfCalFailure, solve

    base = solve(run.robot, run, noise="estimate")
    wins, ref_sample = list(base.windows), int(base.reference_sample)
    ref_win = next(w for w in wins if w.first <= ref_sample <= w.last)
    start = {(w.first, w.last): z for w, z in zip([w for w in wins if w is not ref_win], base.poses, strict=True)}
    out: dict = {"windows": len(wins), "models": {}}
    for mname in models:
        kw = MODELS[mname]
        t0 = time.process_time()
        full = solve(run.robot, run, windows=wins, reference_sample=ref_sample, **kw)
        folds, failed = [], 0
        for w in wins:
            if w is ref_win:
                continue
            rest = [v for v in wins if v is not w]
            try:
                sol = solve(run.robot, run, windows=rest, reference_sample=ref_sample, **kw)
            except SelfCalFailure:
                failed += 1
                continue
            folds.append(predict_window(run, sol, w, ref_win, ref_sample, start[(w.first, w.last)]) |
                         {"window": [w.first, w.last], "fold_chi2_dof": sol.chi2 / sol.dof,
                          "fold_sigma": {c: float(np.mean(v)) for c, v in sol.noise.items()}})
        res = {
            "J": float(sum(f["J"] for f in folds)), "nlpd": float(sum(f["nlpd"] for f in folds)),
            "chi2_per_row": float(np.mean([f["chi2_per_row"] for f in folds])), "folds": folds, "failed": failed,
            "pose_mm": (1e3 * full.initial_pose[:3]).tolist(), "sigma_mm": (1e3 * full.initial_pose_sigma[:3]).tolist(),
            "tension_sigma": float(np.mean(full.noise["tension"])), "chi2_dof": full.chi2 / full.dof,
            "cpu_s": time.process_time() - t0,
        }
        if z0 is not None:
            res["from_zeta_0_real_mm"] = float(1e3 * np.linalg.norm(full.initial_pose[:3] - z0))
        out["models"][mname] = res
    return out


def report(results: dict, models: list[str]) -> list[str]:
    lines = [f"{'run':<18} {'model':<14} {'folds':>5} {'sum J':>9} {'sum NLPD':>10} {'chi2/row':>8} "
             f"{'tension sd N':>12} {'x0, y0, z0 mm (1-sigma)':>44} {'to zeta_0_real':>14}"]
    for name, r in results.items():
        for m in models:
            v = r["models"][m]
            sd = " ".join(f"{s:.2f}" for s in v["sigma_mm"])
            pose = " ".join(f"{p:8.2f}" for p in v["pose_mm"]) + f" ({sd})"
            far = f"{v['from_zeta_0_real_mm']:.2f} mm" if "from_zeta_0_real_mm" in v else "-"
            lines.append(f"{name:<18} {m:<14} {len(v['folds']):>5} {v['J']:>9.1f} {v['nlpd']:>10.1f} "
                         f"{v['chi2_per_row']:>8.2f} {v['tension_sigma']:>12.3f} {pose:>44} {far:>14}"
                         + (f"  ({v['failed']} folds failed)" if v["failed"] else ""))
    lines.append("summed over the runs:")
    for m in models:
        J = sum(r["models"][m]["J"] for r in results.values())
        nl = sum(r["models"][m]["nlpd"] for r in results.values())
        lines.append(f"  {m:<14} J {J:9.1f}   NLPD {nl:10.1f}")
    lines.append("folds whose own solve ends with chi2/dof above 2 (its sigma then not what its rows scatter by):")
    for name, r in results.items():
        for m in models:
            hi = [f"[{f['window'][0]}, {f['window'][1]}] {f['fold_chi2_dof']:.2f}" for f in r["models"][m]["folds"]
                  if f["fold_chi2_dof"] > 2.0]
            if hi and m != "paper":
                lines.append(f"  {name} {m}: " + "; ".join(hi))
    if "estimate" in models and "estimate+sway" in models:
        better = sum(f2["J"] < f1["J"] for r in results.values() for f1, f2 in
                     zip(r["models"]["estimate"]["folds"], r["models"]["estimate+sway"]["folds"], strict=True))
        better_nl = sum(f2["nlpd"] < f1["nlpd"] for r in results.values() for f1, f2 in
                        zip(r["models"]["estimate"]["folds"], r["models"]["estimate+sway"]["folds"], strict=True))
        total = sum(len(r["models"]["estimate"]["folds"]) for r in results.values())
        lines.append(f"estimate+sway against estimate, folds predicted better: J {better}/{total}, "
                     f"NLPD {better_nl}/{total}")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data/irma4u"))
    ap.add_argument("--runs", default=",".join(IMPORTS), help="comma-separated names of " + ", ".join(IMPORTS))
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--json", type=Path, help="write the per-fold figures here (refused if it exists)")
    args = ap.parse_args()
    names = [n.strip() for n in args.runs.split(",") if n.strip()]
    models = [m.strip() for m in args.models.split(",") if m.strip()]
    bad = [n for n in names if n not in IMPORTS] + [m for m in models if m not in MODELS]
    if bad:
        print(f"--runs/--models: {', '.join(bad)} not known (runs: {', '.join(IMPORTS)}; models: "
              f"{', '.join(MODELS)}).", file=sys.stderr)
        return 2
    if not (args.data / "README.md").exists():
        print(f"--data {args.data}: no README.md there, not the irma4u recordings.", file=sys.stderr)
        return 2
    if args.json is not None and args.json.exists():
        print(f"--json {args.json}: exists; not overwritten.", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    z0 = zeta_0_real(args.data)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        runs = run_imports(args.data, Path(tmp), names)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for name in names:
                results[name] = one_run(name, runs[name], models, z0 if name.startswith("sc_8_final") else None)
                print(f"{name}: done ({time.perf_counter() - t0:.0f} s)", flush=True)
    print("\n".join(report(results, models)))
    print(f"{time.perf_counter() - t0:.0f} s wall")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
