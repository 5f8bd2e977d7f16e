"""What the load cells' apparent gains are (issue 28, the tension_gain finding of the three real runs): the
measurements behind docs/effects.md, "The load cells' apparent gains" (not collected by pytest).

1. ``cable_elasticity, tension_offset, tension_gain`` fitted on each real run alone (its own weights by
   variance components) and on the three together: the four gains per run, and whether the runs agree on
   them (:func:`calib.spread.consistency`): one value on every run is a property of the robot as set up,
   values that differ are a model error each run absorbs its own way.
2. The tension residuals of the three runs' joint ``cable_elasticity, tension_offset`` fit (reading - model),
   per cable: the mean after the cable was last paid out and after it was last reeled in (a friction
   between the cell and the platform reads low after paying out: a difference of -2 (f + mu tau)), the
   slope against the reading's own tension per run (a gain), against the swivel angle's change and the
   swivel pulley's wrap angle pi - psi (a routing whose geometry changes with the pose).
3. Each direction-dependent or transmission effect of the library added to ``cable_elasticity,
   tension_offset`` on the three runs: its values, the tension rms per run, and the gains fitted with it
   (how much of the finding it takes), with their joint distance to the +-3 % box
   (:func:`calib.runselect.box_chi2`).

    OMP_NUM_THREADS=1 python benchmarks/bench_diagnose_tension.py [--data DIR]

Prints the tables; exits 1 when the runs disagree on the gains (p < 0.01: then the finding is no property
of the robot and the docs' reading of it no longer holds), 0 otherwise.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

BASE = ("cable_elasticity", "tension_offset")
GAIN = "tension_gain"
ADDED = ("pulley_friction", "swivel_friction", "loadcell_hysteresis", "cable_sag")
AGREE_P = 0.01  # calib.runselect.CONSISTENT_P


def fit(items, names, rounds=None):
    from calib.effects import make_effects
    from calib.multirun import ROUNDS, fit_runs

    return fit_runs(items, make_effects(list(names)), rounds=ROUNDS if rounds is None else rounds)


def block(f, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Values and covariance of one shared effect of a joint fit."""
    robot = f.runs[0].rows.robot
    q = 0
    for e in f.shared:
        n = len(e.params(robot))
        if e.name == name:
            return f.values[q:q + n], f.cov[q:q + n, q:q + n]
        q += n
    raise KeyError(name)


def gains(items) -> bool:
    """Section 1; whether the runs agree on the gains."""
    from calib.spread import consistency

    names = (*BASE, GAIN)
    vals, covs = [], []
    print(f"1. {', '.join(names)}: load-cell gains (%), each run alone (own weights) and the three together")
    for it in items:
        g, c = block(fit([it], names), GAIN)
        vals.append(g)
        covs.append(c)
        print(f"   {it[0]:<16} " + "  ".join(f"g_{i + 1} {100 * v:+6.1f} ± {100 * np.sqrt(c[i, i]):4.1f}"
                                            for i, v in enumerate(g)))
    g, c = block(fit(items, names), GAIN)
    print(f"   {'three runs':<16} " + "  ".join(f"g_{i + 1} {100 * v:+6.1f} ± {100 * np.sqrt(c[i, i]):4.1f}"
                                           for i, v in enumerate(g)))
    from calib.chi2 import chi2_sf

    chi2, dof = consistency(np.array(vals), np.array(covs))
    p = chi2_sf(chi2, dof)
    print(f"   do the runs agree on the four gains? chi2 {chi2:.1f} on {dof} dof, p = {p:.2g} "
          f"({'yes' if p >= AGREE_P else 'no'}: {'a property of the robot' if p >= AGREE_P else 'model error'})")
    return p >= AGREE_P


def patterns(items) -> None:
    """Section 2."""
    from calib.kinematics import inverse_kinematics

    f = fit(items, BASE)
    rows = []  # run, cable, residual, direction, tension, swivel change, wrap angle
    for rf in f.runs:
        m = rf.rows.meas
        pred = rf.problem.model.predict(rf.poses, rf.theta, ["tension"], m.times)["tension"].value
        kin = inverse_kinematics(rf.rows.robot, rf.poses)
        a = np.zeros_like(m.tau) if m.approach is None else m.approach
        for c in range(m.tau.shape[1]):
            for i in range(m.k):
                rows.append((rf.name, c, m.tau[i, c] - pred[i, c], a[i, c], m.tau[i, c], m.dsigma[i, c],
                             np.pi - kin.psi[i, c]))
    print(f"\n2. tension residuals of the joint {', '.join(BASE)} fit (reading - model, N), per cable")
    print(f"   {'cable':<6} {'paid out: n, mean':>18} {'reeled in: n, mean':>19} {'difference':>14} "
          f"{'slope/tension per run':>26} {'r(tension)':>10} {'N/deg swivel':>12} {'N/deg wrap':>10}")
    names = list(dict.fromkeys(r[0] for r in rows))
    for c in sorted({r[1] for r in rows}):
        R = [r for r in rows if r[1] == c]
        y = np.array([r[2] for r in R])
        a = np.array([r[3] for r in R])
        tau = np.array([r[4] for r in R])
        out, inn = y[a > 0], y[a < 0]
        se = np.sqrt(out.var(ddof=1) / out.size + inn.var(ddof=1) / inn.size) if out.size > 1 and inn.size > 1 \
            else np.nan
        slopes = []
        for name in names:
            t = np.array([r[4] for r in R if r[0] == name])
            slopes.append(np.polyfit(t, np.array([r[2] for r in R if r[0] == name]), 1)[0])
        ds = np.degrees(np.array([r[5] for r in R]))
        wrap = np.degrees(np.array([r[6] for r in R]))
        print(f"   {c + 1:<6} {out.size:>5} {out.mean():>+8.2f}     {inn.size:>5} {inn.mean():>+8.2f}    "
              f"{out.mean() - inn.mean():>+6.2f} ± {se:4.2f} {', '.join(f'{s:+.3f}' for s in slopes):>26} "
              f"{np.corrcoef(y, tau)[0, 1]:>10.2f} {np.polyfit(ds, y, 1)[0]:>+12.3f} "
              f"{np.polyfit(wrap, y, 1)[0]:>+10.3f}")
    print(f"   (slope per run: {', '.join(names)})")


def effects(items) -> None:
    """Section 3."""
    from calib.runselect import box_chi2

    print(f"\n3. added to {', '.join(BASE)} on the three runs: the effect's values, tension rms per run (N); "
          f"with {GAIN} too: the gains (%) and their distance to the +-3 % box")
    for extra in ("", *ADDED):
        names = (*BASE, extra) if extra else BASE
        f = fit(items, names)
        vals = ", ".join(f"{k} {v:.3g}" for k, v in f.shared_params().get(extra, {}).items()) if extra else ""
        rms = ", ".join(f"{rf.rms()['tension']:.2f}" for rf in f.runs)
        g = fit(items, (*names, GAIN))
        gv, gc = block(g, GAIN)
        d2, k = box_chi2(gv, gc, np.full(4, -0.03), np.full(4, 0.03))
        grms = ", ".join(f"{rf.rms()['tension']:.2f}" for rf in g.runs)
        print(f"   {'+ ' + extra if extra else '(none)':<22} {vals:<32} tension rms {rms}")
        print(f"   {'':<22} + {GAIN}: " + " ".join(f"{100 * v:+.1f}" for v in gv)
              + f" % (box chi2 {d2:.1f} on {k}); tension rms {grms}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(os.environ.get("CDPR_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
                                  / "irma4u"))
    ap.add_argument("--data", type=Path, default=default)
    args = ap.parse_args()
    from bench_diagnose_runs import import_runs

    from acquisition.runlog import read_run
    from calib.runrows import run_rows

    with tempfile.TemporaryDirectory(prefix="bench-tension-") as tmp:
        items = [(p.name, run_rows(read_run(p))) for p in import_runs(args.data, Path(tmp))]
    agree = gains(items)
    patterns(items)
    effects(items)
    return 0 if agree else 1


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    sys.exit(main())
