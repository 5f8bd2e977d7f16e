"""Several real runs, one robot (issue 28, done-when 1 and 6): the three-run diagnosis's CPU time and the
leave-one-run-out table (not collected by pytest).

1. The diagnosis of the three real runs (parsed .mat with targets) on one core: rows of every run (their
   rigid solves) and the selection by leave-one-run-out prediction; target <= 10 s CPU.
2. For each run left out: the diagnosis of the other two writes a model (``--model-out``), the left-out run
   is solved with it (``cdpr solve RUN --model``: the robot's effects as priors, only its own unknowns
   refitted) and plainly (``cdpr solve RUN``); J = sum over channels of (rms residual / w)^2, w = 1 N,
   0.5 mm, 0.1 deg, 0.2 deg. Target: J with the model <= 0.35 of the plain J, no channel's rms up > 20 %.
3. Every reported model is a converged fit: the three runs' final joint fit, each fold's learning fit and each
   left-out run's solve with the model (``JointFit.convergence``); one that stopped at its cap is a miss.

    OMP_NUM_THREADS=1 python benchmarks/bench_diagnose_runs.py [--data DIR] [--max-effects 4] [--raw]

``--raw`` imports the three runs from their raw ``.log`` files (with the same targets) instead of the parsed
``.mat``; everything else is the same (the raw route's folds, docs/effects.md).

Exits 1 on a miss.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

RUNS = {"sc_8_final": "sc_control_target_8_final.mat", "sc_8_medium_a": "sc_control_target_8.mat",
        "sc_27_medium_a": "sc_control_target_27.mat"}
RATIO, GROWTH, CPU = 0.35, 1.20, 10.0


def import_runs(data: Path, out: Path, raw: bool = False) -> list[Path]:
    """The three runs imported into ``out``: from ``NAME_parsed.mat``, or from ``NAME.log`` when ``raw``."""
    from acquisition.importers import import_irma

    paths = []
    for name, targets in RUNS.items():
        dst = out / name
        if not dst.exists():
            import_irma(data / (f"{name}.log" if raw else f"{name}_parsed.mat"), dst, targets=data / targets)
        paths.append(dst)
    return paths


def diagnose(paths, max_effects, marks: list[float] | None = None):
    """The diagnosis of the runs (imports, each run's rows, the selection); ``marks`` receives the CPU time
    after the rows."""
    from acquisition.runlog import read_run
    from calib.effects import available_effects
    from calib.multirun import NOT_CANDIDATES
    from calib.runrows import run_rows
    from calib.runselect import Judge, select

    classes = available_effects()
    items = [(p.name, run_rows(read_run(p))) for p in paths]
    if marks is not None:
        marks.append(time.process_time())
    judge = Judge(items, lambda names: [classes[n]() for n in names])
    return select(judge, [n for n in classes if n not in NOT_CANDIDATES], max_effects)


def solved_rms(path: Path, model: Path | None):
    """rms per channel (N, m, rad) of `cdpr solve RUN` (paper weights) or `cdpr solve RUN --model MODEL`,
    the initial pose and whether the solve converged."""
    from acquisition.runlog import read_run
    from calib.selfcal import solve

    run = read_run(path)
    if model is None:
        sol = solve(run.robot, run)
    else:
        from acquisition.cli.diagnose_runs import solve_with_model_file

        sol, _ = solve_with_model_file(argparse.Namespace(model=model, run=path, effects_from=[]), run, None,
                                       {"method": "tlse"})
    return {c: v["rms"] for c, v in sol.residuals.items()}, sol.initial_pose, bool(sol.converged)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(os.environ.get("CDPR_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
                                  / "irma4u"))
    ap.add_argument("--data", type=Path, default=default)
    ap.add_argument("--max-effects", type=int, default=4)
    ap.add_argument("--raw", action="store_true", help="import the runs from their raw .log files, not the parsed .mat")
    args = ap.parse_args()
    from calib.multirun import WEIGHTS, misfit_j
    from calib.robot_model import model_document, write_model

    ok = True
    with tempfile.TemporaryDirectory(prefix="bench-runs-") as tmp:
        print(f"imports: {'raw .log' if args.raw else 'parsed .mat'} files of {args.data}")
        paths = import_runs(args.data, Path(tmp), args.raw)
        t0, marks = time.process_time(), []
        sel = diagnose(paths, args.max_effects, marks)
        cpu = time.process_time() - t0
        load = ", ".join(f"{v:.1f}" for v in os.getloadavg())  # a shared machine's CPU figure depends on it
        print(f"three-run diagnosis: {cpu:.1f} s CPU (target <= {CPU:.0f} s) "
              f"{'ok' if cpu <= CPU else 'MISS'} (imports and rows {marks[0] - t0:.1f} s, selection "
              f"{cpu - marks[0] + t0:.1f} s; load average {load}); selected {','.join(sel.selected) or 'nothing'}"
              + ("" if sel.finding is None else f"; finding {','.join(sel.finding.names)}"))
        ok &= cpu <= CPU
        print(f"  its final joint fit: {sel.final.fit.convergence_words()}")
        ok &= sel.final.fit.converged
        loose = [t for st in sel.steps for t in st["options"] if not t.fit.converged]
        print(f"  options judged: {sum(len(st['options']) for st in sel.steps)}, on fits not converged: "
              + (", ".join(f"{','.join(t.names)} ({t.fit.stop.reason})" for t in loose) or "none"))
        print(f"{'left out':<16} {'learned':<44} {'J plain':>8} {'J model':>8} {'ratio':>6}  rms plain -> model "
              "(N, mm, deg, deg)")
        for j, p in enumerate(paths):
            train = [q for i, q in enumerate(paths) if i != j]
            s2 = diagnose(train, args.max_effects)
            mfile = Path(tmp) / f"model_without_{p.name}.yaml"
            write_model(mfile, model_document(s2.final.fit, [str(q) for q in train]), force=True)
            a, _, _ = solved_rms(p, None)
            b, _, solved = solved_rms(p, mfile)
            ja, jb = misfit_j(a), misfit_j(b)
            grow = [c for c in WEIGHTS if c in a and b[c] > GROWTH * a[c]]
            learned = s2.final.fit
            good = jb <= RATIO * ja and not grow and learned.converged and solved
            ok &= good
            conv = {"tension": 1.0, "length": 1e3, "swivel": 57.29577951308232, "orientation": 57.29577951308232}
            rms = ", ".join(f"{c[:3]} {a[c] * conv[c]:.3g}->{b[c] * conv[c]:.3g}" for c in WEIGHTS if c in a)
            print(f"{p.name:<16} {','.join(s2.selected) or '-':<44} {ja:>8.1f} {jb:>8.1f} {jb / ja:>6.3f}  {rms}"
                  f"  {'ok' if good else 'MISS' + (' (grows: ' + ','.join(grow) + ')' if grow else '')}")
            ea = learned.shared_params().get("cable_elasticity", {}).get("EA", float("nan"))
            print(f"{'':<16} learning fit (EA {ea / 1e3:.2f} kN): {learned.convergence_words()}; the solve with "
                  f"the model: {'converged' if solved else 'NOT converged'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
