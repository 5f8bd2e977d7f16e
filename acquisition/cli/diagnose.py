"""`cdpr diagnose RUN`: compare model and measurements, rank the candidate physical effects (spec/cli.md).

Also the `--effects` support of `cdpr solve` (:func:`solve_with_effects`), which acquisition/cli/solve.py
calls: the refit with the named effects and its before/after table.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.cli.args import add_force, check_output_option, claim_output_option, parse_pose
from acquisition.cli.effect_options import effect_classes, parse_effects
from acquisition.cli.errors import OperationError, UsageError
from acquisition.runlog import RunFormatError, read_run
from calib.effects import Effect


def register(sub) -> None:
    p = sub.add_parser("diagnose", help="compare model and measurements, rank the candidate physical effects")
    p.add_argument("run", type=Path, nargs="+", metavar="RUN",
                   help="run folder; several runs of one robot: its effects shared, each run's own unknowns, "
                   "effects chosen by leave-one-run-out prediction (issue 28)")
    p.add_argument("--json", action="store_true", help="print the diagnosis as JSON (spec/cli.md)")
    p.add_argument("--model", type=Path, default=None, metavar="MODEL.yaml",
                   help="a learned robot model (docs/robot-model.md): its effects enter every fit as priors")
    p.add_argument("--model-out", type=Path, default=None, metavar="MODEL.yaml",
                   help="write the learned robot model (effects kept, values, 1-sigma, runs and weights); "
                   "diagnoses the runs jointly; an existing file is refused unless --force")
    p.add_argument(
        "--noise", choices=("estimate", "accuracy", "paper"), default="estimate",
        help="noise units: estimate (scatter inside the equilibrium windows, default), accuracy (that scatter "
        "floored at the sensors' accuracy class) or paper (eq. 18)",
    )
    p.add_argument("--plots", type=Path, default=None, metavar="DIR",
                   help="write PNG plots of the residuals into this new (or empty) folder; refused if it holds "
                   "files, unless --force")
    p.add_argument("--html", type=Path, default=None, metavar="FILE",
                   help="write an HTML report (plots embedded); an existing file is refused unless --force")
    p.add_argument(
        "--effects-from", action="append", default=[], metavar="MODULE",
        help="also consider the effects of this Python file or importable module (repeatable)",
    )
    p.add_argument("--effects", default=None, metavar="A,B", help="effects already in the model")
    p.add_argument("--max-effects", type=int, default=2, help="effects added at most by forward selection")
    p.add_argument(
        "--reference", default=None, metavar="x,y,z,r,p,y",
        help="a known initial pose (m, rad): eps_p after each added effect",
    )
    add_force(p)
    p.set_defaults(func=_diagnose)


def _read(path: Path):
    try:
        return read_run(path)
    except RunFormatError as exc:
        raise UsageError(str(exc)) from exc


def _diagnose(args) -> int:
    from acquisition.diagnose_report import format_diagnosis, html_report, parameter_units, plot_residuals
    from calib.diagnose import diagnose_run
    from calib.selfcal import SelfCalFailure, SelfCalInputError

    if args.max_effects < 0:
        raise UsageError(f"--max-effects {args.max_effects} must be 0 or more.")
    if len(args.run) > 1 or args.model is not None or args.model_out is not None:
        from acquisition.cli.diagnose_runs import diagnose_runs

        return diagnose_runs(args)
    args.run = args.run[0]
    reference = parse_pose(args.reference)
    for option, path in (("--plots", args.plots), ("--html", args.html)):
        if path is not None:
            check_output_option(path, args.force, option, [args.run])
    classes = effect_classes(args.effects_from)
    included = parse_effects(args.effects, classes)
    run = _read(args.run)
    cands = [cls() for name, cls in classes.items() if name not in {e.name for e in included}]
    from acquisition.cli.progress import Activity

    try:
        with Activity(f"diagnose: fitting the model and {len(cands)} candidate effects"):
            diag = diagnose_run(run, noise=args.noise, candidates=cands, included=included,
                                max_effects=args.max_effects, reference_pose=reference)
    except SelfCalInputError as exc:
        raise UsageError(f"{args.run}: {exc}") from exc
    except SelfCalFailure as exc:
        raise OperationError(f"{args.run}: {exc}") from exc
    units = parameter_units(cands + included, run.robot)
    pngs: list[Path] = []
    if args.plots is not None or args.html is not None:
        import tempfile

        folder = args.plots if args.plots is not None else Path(tempfile.mkdtemp(prefix="cdpr-diagnose-"))
        if args.plots is not None:
            claim_output_option(folder, args.force, "--plots", [args.run])
        try:
            with Activity("diagnose: drawing the plots"):
                pngs = plot_residuals(diag, folder)
        except OSError as exc:
            raise OperationError(f"{folder}: cannot write the plots ({exc.strerror}).") from exc
    if args.html is not None:
        claim_output_option(args.html, args.force, "--html", [args.run])
        try:
            args.html.write_text(html_report(diag, pngs, f"cdpr diagnose {args.run}", units, args.run))
        except OSError as exc:
            raise OperationError(f"{args.html}: cannot write the HTML report ({exc.strerror}).") from exc
    if args.json:
        sys.stdout.write(json.dumps(diag.to_json()) + "\n")
    else:
        sys.stdout.write(format_diagnosis(diag, units, args.run))
    return 0


# ---- cdpr solve --effects --------------------------------------------------------------------------------

def solve_with_effects(args, run, reference: np.ndarray | None, solve_kwargs: dict[str, Any]):
    """Solve with the effects of ``args.effects`` added one by one: the fits of
    :func:`calib.runrows.effect_chain` (the diagnosis's own refits: same noise, device priors and start),
    each returned as a Solution. Returns the final Solution (its ``effects`` filled) and the before/after
    table; writes the plot RUN/effects_chi2.png."""
    from acquisition.diagnose_report import parameter_units, plot_steps
    from calib.fitting import pose_error
    from calib.runrows import effect_chain, run_rows
    from calib.selfcal import solve

    classes = effect_classes(getattr(args, "effects_from", []) or [])
    effects = parse_effects(args.effects, classes)
    kw = {k: v for k, v in solve_kwargs.items() if k not in ("noise", "reference_pose")}
    rows = run_rows(run, solve_kwargs.get("noise", "paper"), kw.get("method", "tlse"), int(kw.get("stride", 1)),
                    kw.get("reference_sample"))
    sols = []
    for f in effect_chain(rows, effects):  # each fit as a Solution, not iterated further: the same numbers
        sol = solve(rows.robot, run, model=f.model, guess=(f.theta, f.poses), noise=rows.sigma,
                    reference_pose=solve_kwargs.get("reference_pose"), max_iter=0, **kw)
        sol.converged, sol.iterations = f.converged, f.iterations
        sol.noise_source = rows.source
        sol.effects = {k: {a: b for a, b in v.items() if math.isfinite(b)}
                       for k, v in f.model.report(sol.theta).items()}
        sols.append(sol)
    steps = []
    for j, s in enumerate(sols):
        st = {"effects": [e.name for e in effects[:j]], "chi2": s.chi2, "dof": s.dof}
        if reference is not None:
            st["eps_p"] = pose_error(s.initial_pose, reference)
        steps.append(st)
    try:
        plot_steps(steps, Path(args.run) / "effects_chi2.png")
    except OSError:
        pass
    units = parameter_units(f.model.effects, rows.robot)  # the last fit's model: every effect, the devices' too
    own = None
    if rows.source == "estimate" and effects:
        import warnings

        from calib.selfcal import SelfCalFailure

        try:
            own = _own_weights_solve(rows, run, effects, solve_kwargs)
        except SelfCalFailure as exc:  # the chain's fit stands: said, not hidden
            warnings.warn(f"{args.run}: the model with {args.effects} solved with its own weights failed ({exc}); "
                          "the solution keeps the base model's weights.", UserWarning, stacklevel=2)
    table = effects_table(sols, effects, reference, units, own)
    return (sols[-1] if own is None else own), table


def _own_weights_solve(rows, run, effects: list[Effect], solve_kwargs: dict[str, Any]):
    """The run solved with the effects in the model from the start of the estimate-noise procedure, so that
    each channel group's weight is the noise of the model being fitted (issue 28). The chain's fits keep the
    base model's weights, which the variance components raise to the base model's misfit where it exceeds
    the noise far (calib.selfcal.noise.rescaled_sigma): a channel an effect explains would stay weighed as if
    the effect were missing (sc_8_final's raw log: lengths at 8.0 mm with the controller's transmission
    ratios unmodelled, 1.05 mm once length_scale is in the model, as in the parsed file)."""
    from calib.effects import EffectModel
    from calib.effects.priors import DeviceAccuracy
    from calib.selfcal import solve

    model = EffectModel(rows.robot, [DeviceAccuracy(), *effects])
    kw = {k: v for k, v in solve_kwargs.items() if k != "noise"}
    sol = solve(rows.robot, run, model=model, noise="estimate", **kw)
    sol.effects = {k: {a: b for a, b in v.items() if math.isfinite(b)} for k, v in sol.effects.items()}
    return sol


def effects_table(sols, effects: list[Effect], reference: np.ndarray | None, units: dict[str, str] | None = None,
                  own=None) -> str:
    """Before/after: chi2, per-channel RMS (normalised), change of the initial pose, eps_p where known; the
    rows share the base model's weights (chi2 comparable); ``own``: the last model solved with its own weights
    (:func:`_own_weights_solve`), a last row, whose parameters are then the ones listed."""
    from calib.fitting import pose_error

    chans = list(sols[0].residuals)
    widths = [max(len(c), 7) for c in chans]
    head = f"{'model':<36} {'chi2':>10} {'dof':>4} " + " ".join(f"{c:>{w}}" for c, w in zip(chans, widths, strict=True))
    head += f" {'d zeta0 [mm]':>12}" + (f" {'eps_p [mm]':>10}" if reference is not None else "")
    lines = ["effects added one by one (rms/sigma per channel)", head]
    rows = [("base model (device errors)" if j == 0 else "+ " + effects[j - 1].name, s) for j, s in enumerate(sols)]
    if own is not None:
        rows.append(("= with this model's own weights", own))
    for name, s in rows:
        row = f"{name:<36} {s.chi2:>10.4g} {s.dof:>4} " + " ".join(
            f"{s.residuals.get(c, {}).get('rms_normalized', float('nan')):>{w}.2f}"
            for c, w in zip(chans, widths, strict=True))
        row += f" {1000 * pose_error(s.initial_pose, sols[0].initial_pose):>12.2f}"
        if reference is not None:
            row += f" {1000 * pose_error(s.initial_pose, reference):>10.2f}"
        lines.append(row)
    if own is not None:
        lines.append("  (rows above: the base model's weights, chi2 comparable; the last row and the solution: "
                     "each channel weighed by what this model leaves of it)")
    units = units or {}
    for name, params in (sols[-1] if own is None else own).effects.items():
        lines.append(f"  {name}: " + ", ".join(_with_unit(k, v, units.get(k, "")) for k, v in params.items()))
    return "\n".join(lines) + "\n"


def _with_unit(name: str, value: float, unit: str) -> str:
    """'name = value unit' of a fitted parameter: angles in degrees, a dimensionless one bare."""
    if unit == "rad":
        return f"{name} = {math.degrees(value):.4g} deg"
    return f"{name} = {value:.5g}" + ("" if unit in ("", "1") else f" {unit}")
