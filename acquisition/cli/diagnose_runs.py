"""`cdpr diagnose RUN [RUN ...] [--model OLD] [--model-out NEW]`: several runs of one robot (issue 28).

The robot's effects are shared by the runs, each run keeps its own unknowns; effects are chosen by
leave-one-run-out prediction (one run: leave-one-pose-out), see calib.runselect. ``--model`` adds a learned
model's effects as priors to every fit; ``--model-out`` writes the model learned (docs/robot-model.md).
Also the ``--model`` option of `cdpr solve` (:func:`solve_with_model_file`).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

from acquisition.cli.args import check_output_option
from acquisition.cli.errors import OperationError, UsageError
from acquisition.runlog import RunFormatError, read_run


def _rows(path: Path, noise: str):
    from calib.runrows import run_rows
    from calib.selfcal import SelfCalFailure, SelfCalInputError

    try:
        run = read_run(path)
    except RunFormatError as exc:
        raise UsageError(str(exc)) from exc
    try:
        return run, run_rows(run, noise)
    except SelfCalInputError as exc:
        raise UsageError(f"{path}: {exc}") from exc
    except SelfCalFailure as exc:
        raise OperationError(f"{path}: {exc}") from exc


def load_prior(path: Path | None, robot, classes) -> list:
    """The effects of a model file as priors ([] without one); a bad file is a usage error."""
    if path is None:
        return []
    from calib.robot_model import ModelFileError, prior_effects, read_model

    try:
        return prior_effects(read_model(path), robot, classes, path)
    except ModelFileError as exc:
        raise UsageError(f"--model {exc}") from exc


def diagnose_runs(args) -> int:
    from acquisition.cli.effect_options import effect_classes, parse_effects
    from acquisition.selection_report import format_selection, selection_json
    from calib.multirun import NOT_CANDIDATES
    from calib.robot_model import model_document, write_model
    from calib.runselect import Judge, select

    if args.model_out is not None:
        check_output_option(args.model_out, args.force, "--model-out")
    for option in ("plots", "html", "reference"):
        if getattr(args, option, None) is not None:
            raise UsageError(f"--{option} applies to the diagnosis of one run without --model/--model-out.")
    if len({p.resolve() for p in args.run}) != len(args.run):
        raise UsageError("a run is named twice: " + ", ".join(str(p) for p in args.run) + ".")
    classes = effect_classes(args.effects_from)
    items, runs = [], []
    for p in args.run:
        run, rows = _rows(p, args.noise)
        runs.append(run)
        items.append((p.name or str(p), rows))
    robot = items[0][1].robot
    prior = load_prior(args.model, robot, classes)
    included = parse_effects(args.effects, classes)
    fixed = [e.name for e in prior] + [e.name for e in included]
    cands = [n for n in classes if n not in fixed and n not in NOT_CANDIDATES]

    def make(names):
        return [*[classes[n]() for n in [e.name for e in included]], *[classes[n]() for n in names]]

    judge = Judge(items, make, prior)
    from acquisition.cli.progress import Activity

    with Activity(f"diagnose: {len(items)} runs, choosing among {len(cands)} candidate effects"):
        sel = select(judge, cands, args.max_effects)
    doc = selection_json(sel, [str(p) for p in args.run])
    if args.model_out is not None:
        model = model_document(sel.final.fit, [str(p) for p in args.run], {
            "mode": sel.mode, "selected": sel.selected, "verdict": doc["verdict"],
            "prior_model": None if args.model is None else str(args.model)})
        try:
            write_model(args.model_out, model, force=args.force)
        except OSError as exc:
            raise OperationError(f"{args.model_out}: cannot write the model ({exc}).") from exc
    if args.json:
        sys.stdout.write(json.dumps(doc) + "\n")
    else:
        sys.stdout.write(format_selection(sel, [str(p) for p in args.run], args.model_out))
    return 0


def solve_with_model_file(args, run, reference, solve_kwargs: dict[str, Any]):
    """`cdpr solve RUN --model MODEL.yaml`: the run solved with the model's effects as priors and its own
    unknowns refitted (weights by variance components); the Solution and a line on the model."""
    from acquisition.cli.effect_options import effect_classes
    from calib.robot_model import solve_with_model
    from calib.runrows import run_rows
    from calib.selfcal import solve

    classes = effect_classes(getattr(args, "effects_from", []) or [])
    prior = load_prior(args.model, run.robot, classes)
    kw = {k: v for k, v in solve_kwargs.items() if k not in ("noise", "reference_pose")}
    rows = run_rows(run, "estimate", kw.get("method", "tlse"), int(kw.get("stride", 1)), kw.get("reference_sample"))
    fit = solve_with_model(rows, prior, Path(args.run).name)
    rf = fit.runs[0]
    sol = solve(rows.robot, run, model=rf.problem.model, guess=(rf.theta, rf.poses), noise=rf.sigma,
                reference_pose=reference, max_iter=0, **kw)
    sol.noise_source = "estimate (variance components)"
    sol.converged, sol.iterations = fit.converged, fit.iterations
    sol.effects = {k: {a: b for a, b in v.items() if math.isfinite(b)} for k, v in rf.params().items()}
    drift = rf.params().get("ahrs_yaw_drift", {}).get("deg_per_hour", float("nan"))
    line = (f"model {args.model}: " + ", ".join(e.name for e in prior) + f" as priors; this run's yaw drift "
            f"{drift:.1f} deg/h; the fit {fit.convergence_words()}\n")
    return sol, line
