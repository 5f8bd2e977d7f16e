"""`cdpr solve RUN`: initial-pose self-calibration of a run (spec/cli.md).

RUN/solution.json is the run's solution, what `cdpr export` carries: the first solve with the default options
writes it, `--save` makes any solve the run's solution; every other solve explores and writes nothing."""

from __future__ import annotations

import json
import math
import sys
import warnings
from pathlib import Path

from acquisition.cli.args import add_effect_options, parse_pose
from acquisition.cli.errors import OperationError, UsageError
from acquisition.runlog import read_run
from calib.chi2 import chi2_sf
from calib.selfcal import METHODS, SelfCalFailure, SelfCalInputError, Solution, TooFewWindows, default_noise, solve

SOLUTION_FILE = "solution.json"


def register(sub) -> None:
    p = sub.add_parser("solve", help="initial-pose self-calibration of a run")
    p.add_argument("run", type=Path, metavar="RUN", help="run folder")
    p.add_argument("--method", choices=METHODS, default="tlse", help="tlse (default), lse or hybrid")
    p.add_argument(
        "--noise", choices=("paper", "estimate", "estimate+sway", "sensors"), default=None,
        help="weights: estimate (the run's own noise of a window mean: the honest 1-sigma; default for tlse and "
             "hybrid), estimate+sway (the same, its tension rows also carrying the platform's sway under force "
             "control, opt-in: docs/windows.md), paper (eq. 18; default for lse, whose rows are single samples), "
             "sensors (specifications)",
    )
    p.add_argument("--stride", type=int, default=1, help="lse/hybrid: use every S-th sample (default 1)")
    p.add_argument("--reference-sample", type=int, default=None, help="sample whose pose is the initial pose")
    p.add_argument(
        "--reference", default=None, metavar="x,y,z,r,p,y",
        help="a known initial pose (m, rad) to compare with: eps_p, eps_r (eq. 20) and the geodesic angle",
    )
    p.add_argument("--json", action="store_true", help="print the solution as JSON")
    p.add_argument("--save", action="store_true",
                   help="make this solve the run's solution (RUN/solution.json, what export carries); without it "
                   "only the first solve with the default options writes it, and exploring (--effects, --model, "
                   "--noise, --method...) changes nothing")
    add_effect_options(p)
    p.add_argument("--model", type=Path, default=None, metavar="MODEL.yaml",
                   help="a learned robot model (cdpr diagnose --model-out): its effects as priors, this run's own "
                   "unknowns refitted, weights by variance components (docs/robot-model.md)")
    p.set_defaults(func=_solve)


def _effects_model(robot, effects):
    """The measurement model with the effects named by ``--effects`` (an option the effect library adds to
    this command), or None for the rigid model."""
    if not effects:
        return None
    names = [e.strip() for e in effects.split(",")] if isinstance(effects, str) else [str(e) for e in effects]
    names = [e for e in names if e]
    if not names:
        return None
    from calib.effects import EffectLoadError, EffectModel, make_effects

    try:
        return EffectModel(robot, make_effects(names))
    except EffectLoadError as exc:
        raise UsageError(str(exc)) from exc


def _solve(args) -> int:
    reference = parse_pose(args.reference)
    if args.stride < 1:
        raise UsageError(f"--stride {args.stride} must be a positive integer.")
    run = read_run(args.run)
    with_effects = bool(getattr(args, "effects", None))
    if getattr(args, "effects_from", None) and not with_effects:
        from acquisition.cli.effect_options import effect_classes

        names = sorted(set(effect_classes(args.effects_from)) - set(effect_classes([])))
        warnings.warn(f"--effects-from defines {', '.join(names) or 'no new effect'}; without --effects none "
                      "of them enters the model.", stacklevel=1)
    if args.noise is None:
        args.noise = default_noise(args.method)
    sway = args.noise == "estimate+sway"  # the estimate noise with the sway term (SolveOptions.sway)
    if sway and (with_effects or getattr(args, "model", None) is not None):
        raise UsageError("--noise estimate+sway is a plain solve's weighting; with --effects or --model the "
                         "weights are the diagnosis's (use --noise estimate).")
    model = None if with_effects else _effects_model(run.robot, getattr(args, "effects", None))
    table = ""
    try:
        if getattr(args, "model", None) is not None:  # a learned robot model as priors (issue 28)
            from acquisition.cli.diagnose_runs import solve_with_model_file

            if with_effects:
                raise UsageError("--model and --effects: put the effects in the model (cdpr diagnose --model-out).")
            kw = dict(method=args.method, stride=args.stride, reference_sample=args.reference_sample)
            sol, table = solve_with_model_file(args, run, reference, kw)
        elif with_effects:  # effects added one by one, with the before/after table (issue 7)
            from acquisition.cli.diagnose import solve_with_effects

            kw = dict(method=args.method, noise=args.noise, stride=args.stride,
                      reference_sample=args.reference_sample, reference_pose=reference)
            sol, table = solve_with_effects(args, run, reference, kw)
        else:
            sol = solve(
                run.robot, run, method=args.method, noise="estimate" if sway else args.noise, stride=args.stride,
                reference_sample=args.reference_sample, reference_pose=reference, model=model, sway=sway,
            )
    except SelfCalInputError as exc:
        raise UsageError(f"{args.run}: {exc}") from exc
    except TooFewWindows as exc:
        raise OperationError(f"{args.run}: {str(exc).rstrip('.')}; {_too_few_windows_hint(run)}.") from exc
    except SelfCalFailure as exc:
        raise OperationError(f"{args.run}: {exc}") from exc
    doc = sol.to_json()
    path = Path(args.run) / SOLUTION_FILE
    save = args.save or (not path.exists() and _default_options(args))
    if save:
        try:
            path.write_text(json.dumps(doc, indent=2) + "\n")
        except OSError as exc:
            raise OperationError(f"{path}: cannot write the solution ({exc.strerror}).") from exc
    if args.json:
        sys.stdout.write(json.dumps(doc) + "\n")
    else:
        said = (f"saved as the run's solution: {path}" if save else
                f"not saved: {path} is damaged, so the run has no solution that export can carry (--save to "
                "replace it)" if path.exists() and not _readable(path) else
                f"not saved: {path} stays the run's solution (--save to replace it)" if path.exists() else
                "not saved: the run has no solution yet (--save to make this one, or solve with the default options)")
        sys.stdout.write(format_solution(sol) + table + said + "\n")
    return 0


def _readable(path: Path) -> bool:
    """True when the saved solution reads back as JSON (what `cdpr export` needs of it)."""
    try:
        return isinstance(json.loads(path.read_text()), dict)
    except (OSError, ValueError):
        return False


def _default_options(args) -> bool:
    """True for a solve with every option at its default: the solve `cdpr startup` makes, not an exploration."""
    return (args.method == "tlse" and args.noise == default_noise(args.method) and args.stride == 1
            and args.reference_sample is None
            and not getattr(args, "effects", None) and not getattr(args, "effects_from", None)
            and getattr(args, "model", None) is None)


def _too_few_windows_hint(run) -> str:
    """What to do when a run holds fewer windows than tlse/hybrid need. lse is the method of kinematic runs;
    on an equilibrium run it fits the few moving samples between holds and converges far from the truth
    (IRMA4U run cut to its first 200 samples: 534 mm from the authors' initial pose, with a 1-sigma of
    20 mm), so it is not offered there."""
    if run.method == "kinematic":
        return "a kinematic run is solved with --method lse"
    return ("fewer than two held poses do not fix the initial pose and the sensor offsets, and lse on the few "
            "moving samples between holds is not reliable, so nothing can be solved: the run needs at least 2 "
            "held setpoints")


def format_solution(sol: Solution) -> str:
    """A readable table of a solution."""
    z, s, k = sol.initial_pose, sol.initial_pose_sigma, sol.sigma_scale
    lines = [
        f"method {sol.method}, {len(sol.poses) + 1} poses, reference sample {sol.reference_sample}, "
        f"noise {sol.noise_source}, {sol.iterations} iterations, {sol.timing['solve_s'] * 1000:.1f} ms",
        "initial pose       value         1-sigma" + (f"       x {k:.3g} (*)" if k > 1 else ""),
    ]
    for j, name in enumerate("xyz"):  # positions and their 1-sigma in mm to the micrometre, as cdpr startup prints
        scaled = f"  {1000 * k * s[j]:>10.3f} mm" if k > 1 else ""
        lines.append(f"  {name:<14} {1000 * z[j]:>10.3f} mm  {1000 * s[j]:>10.3f} mm{scaled}")
    for j, name in enumerate(("roll", "pitch", "yaw")):
        scaled = f"  {math.degrees(k * s[3 + j]):>10.3f} deg" if k > 1 else ""
        lines.append(f"  {name:<14} {math.degrees(z[3 + j]):>10.3f} deg {math.degrees(s[3 + j]):>10.3f} deg{scaled}")
    off = sol.sensor_offsets
    lines.append("sensor offsets (absolute = offset + reading)")
    lines.append("  length [m]     " + "  ".join(f"{v:.4f}" for v in off["length"]))
    lines.append("  swivel [deg]   " + "  ".join(f"{math.degrees(v):.3f}" for v in off["swivel"]))
    lines.append(f"  yaw [deg]      {math.degrees(off['yaw']):.3f}")
    lines.extend(format_windows(sol))
    lines.append(f"chi2 {sol.chi2:.3g} on {sol.dof} dof")
    if sol.noise_source in ("estimate", "estimate+sway", "sensors") and k > 1:  # the chi2 test rejects the model
        lines.append(f"the model does not fit these readings within their own noise (p = "
                     f"{chi2_sf(sol.chi2, sol.dof):.2g}): the 1-sigma bounds hold only for a model that does; "
                     "`cdpr diagnose RUN` says where it fails and what is missing, and --noise paper weighs the "
                     "channels by the errors the paper expects of the rigid model (eq. 18)")
    if k > 1:
        lines.append(f"(*) the 1-sigma times sqrt(chi2/dof) = {k:.3g}, the misfit counted as noise: the order of "
                     "the error it leaves; a model error is not noise, so even these bounds can be too narrow")
    lines.append("residuals          rms (SI)   rms/sigma")
    for c, d in sol.residuals.items():
        lines.append(f"  {c:<14} {d['rms']:>10.4g}  {d['rms_normalized']:>10.3f}")
    if sol.reference is not None:
        r = sol.reference
        lines.append(
            f"vs reference: eps_p {r.eps_p * 1000:.1f} mm, eps_r {math.degrees(r.eps_r):.2f} deg, "
            f"geodesic {math.degrees(r.geodesic):.2f} deg"
        )
    return "\n".join(lines) + "\n"


def format_windows(sol: Solution) -> list[str]:
    """The equilibrium windows: planned, found and used, each found one with its setpoint, and the planned
    setpoints without a window with their reason."""
    ws = sol.window_search
    if ws is None:
        return [f"windows (given) {' '.join(f'[{w.first},{w.last}]' for w in sol.windows)}"]
    planned = f"{ws.planned} planned, " if ws.planned else "no plan, "
    lines = [f"windows: {planned}{len(ws.found)} found, {len(ws.used)} used"]
    for w in ws.found:
        what = f"setpoint {w.setpoint}" if w.setpoint >= 0 else "no setpoint"
        lines.append(f"  [{w.first},{w.last}] {what}{' (quasi)' if w.quasi else ''}"
                     f"{'' if w in ws.used else ' - not used'}")
    lines.extend(f"  {m.reason}" for m in ws.missing)
    return lines
