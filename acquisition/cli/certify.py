"""`cdpr certify anchors` (certified enclosures of the fixed anchors) and `cdpr certify simulate` (a
simulated laser-tracker dataset in the MEASUREMENTS.csv format), see ../shared/spec/cli.md."""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

import numpy as np

from acquisition.cli.args import add_force, check_output_option, claim_output_option
from acquisition.cli.errors import OperationError, UsageError
from calib.certify import AXIS_NAMES, LOSSES, CertifyConfig, CertifyResult, certify_anchors
from calib.lasertracker import (
    read_measurements_csv,
    simulate_tracker_dataset,
    write_measurements_csv,
)
from calib.robot import builtin_robot_names, load_robot


def register(sub) -> None:
    parser = sub.add_parser("certify", help="certified interval calibration of the fixed anchor points")
    csub = parser.add_subparsers(dest="certify_command", metavar="ACTION")
    defaults = CertifyConfig()

    anchors = csub.add_parser("anchors", help="certified boxes of the fixed anchors from laser-tracker measurements")
    anchors.add_argument("measurements", metavar="MEASUREMENTS.csv", help="x,y,z,roll,pitch,yaw,l_1..l_m per line")
    anchors.add_argument("--robot", required=True, help=f"built-in robot ({', '.join(builtin_robot_names())}) or YAML")
    anchors.add_argument("--q", type=float, default=defaults.q, help="fraction of measurements that must hold")
    _tolerance_options(anchors)
    anchors.add_argument("--anchor-tol", type=float, default=defaults.anchor_tol,
                         help="half-width of the initial box about the nominal anchors, m (default 0.01)")
    anchors.add_argument("--platform-tol", type=float, default=defaults.platform_tol,
                         help="tolerance of the platform points b_i, m (default 0)")
    anchors.add_argument("--rotation-bound", choices=("centred", "naive"), default=defaults.rotation_bound,
                         help="enclosure of the orientation error: centred form (default) or naive interval product")
    anchors.add_argument("--resolution", type=float, default=defaults.resolution,
                         help="paving resolution, m (default 0.0005)")
    anchors.add_argument("--loss", choices=LOSSES, default=defaults.nwls_loss,
                         help="loss of the least-squares comparison (default linear: plain NWLS)")
    anchors.add_argument("--json", action="store_true", help="print the result as JSON")
    anchors.set_defaults(func=_anchors)

    sim = csub.add_parser("simulate", help="write a simulated laser-tracker dataset (MEASUREMENTS.csv)")
    sim.add_argument("--robot", required=True, help=f"built-in robot ({', '.join(builtin_robot_names())}) or YAML")
    sim.add_argument("-n", type=int, default=42, help="number of poses (default 42)")
    sim.add_argument("--outliers", type=float, default=0.0, help="fraction of outlier poses (lengths off by 5-20 cm)")
    sim.add_argument("--clustered", action="store_true", help="poses clustered in one region of the workspace")
    sim.add_argument("--seed", type=int, default=None, help="random seed")
    _tolerance_options(sim)
    sim.add_argument("--anchor-offset", type=float, default=0.005,
                     help="largest offset of the true anchors from the nominal ones per axis, m (default 0.005)")
    sim.add_argument("-o", "--out", "--output", dest="output", required=True, metavar="FILE",
                     help="MEASUREMENTS.csv to write (--out as in every other command; --output, its old name, "
                     "still works); an existing file is refused unless --force")
    sim.add_argument("--truth", help="also write the ground truth (true anchors, poses, outliers) as JSON; an "
                     "existing file is refused unless --force")
    add_force(sim)
    sim.set_defaults(func=_simulate)
    parser.set_defaults(func=lambda args: parser.print_help(sys.stderr) or 2)


# "--model-error -0.0006,0.0037": let argparse read a value starting with a negative number as a value
_NEGATIVE_VALUE = re.compile(r"^-\d*\.?\d+([eE][-+]?\d+)?(,[-+]?\d*\.?\d+([eE][-+]?\d+)?)?$")


def _tolerance_options(p) -> None:
    d = CertifyConfig()
    if hasattr(p, "_negative_number_matcher"):
        p._negative_number_matcher = _NEGATIVE_VALUE
    p.add_argument("--pose-tol", type=float, default=d.pose_tol,
                   help="position tolerance per axis, m (default 0.001)")
    p.add_argument("--angle-tol", type=float, default=d.angle_tol,
                   help="angle tolerance per Euler angle, rad (default 0.01)")
    p.add_argument("--model-error", default=f"{d.model_error[0]},{d.model_error[1]}", metavar="LO,HI",
                   help="cable model error [dL] = distance - length, m (default -0.0006,0.0037)")


def _model_error(text: str) -> tuple[float, float]:
    parts = text.split(",")
    try:
        lo, hi = (float(p) for p in parts)
    except ValueError:
        raise UsageError(f"option --model-error = {text!r} must be two numbers LO,HI in m.") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise UsageError(f"option --model-error = {text!r} must be finite with LO <= HI.")
    return lo, hi


def _check_options(args) -> None:
    for opt in ("pose_tol", "angle_tol"):
        v = getattr(args, opt)
        if not (math.isfinite(v) and v >= 0):
            raise UsageError(f"option --{opt.replace('_', '-')} = {v} must be a non-negative number.")


def _anchors(args) -> int:
    _check_options(args)
    robot = load_robot(args.robot)
    if not 0.0 < args.q <= 1.0:
        raise UsageError(f"option --q = {args.q} must be a fraction in (0, 1].")
    for opt in ("anchor_tol", "resolution"):
        v = getattr(args, opt)
        if not (math.isfinite(v) and v > 0):
            raise UsageError(f"option --{opt.replace('_', '-')} = {v} must be a positive number.")
    if not (math.isfinite(args.platform_tol) and args.platform_tol >= 0):
        raise UsageError(f"option --platform-tol = {args.platform_tol} must be a non-negative number.")
    config = CertifyConfig(q=args.q, pose_tol=args.pose_tol, angle_tol=args.angle_tol,
                           model_error=_model_error(args.model_error), anchor_tol=args.anchor_tol,
                           platform_tol=args.platform_tol, rotation_bound=args.rotation_bound,
                           resolution=args.resolution, nwls_loss=args.loss)
    poses, lengths = read_measurements_csv(args.measurements, robot.n)
    try:
        result = certify_anchors(robot, poses, lengths, config)
    except ValueError as exc:
        raise OperationError(f"{args.measurements}: {exc}") from exc
    if args.json:
        sys.stdout.write(json.dumps(result.to_json()) + "\n")
    else:
        sys.stdout.write(format_result(result))
    return 0


def format_result(result: CertifyResult) -> str:
    """The text report: a table of boxes, widths and the NWLS estimate, outliers and warnings."""
    lines = [
        f"robot {result.robot}: {result.n_measurements} measurements, q = {result.q:g} "
        f"(at least {result.required} must hold), [dL] = [{result.model_error[0] * 1e3:.2f}, "
        f"{result.model_error[1] * 1e3:.2f}] mm"
        + ("" if result.pulley_error is None else
           f" including the pulley effect [{result.pulley_error[0] * 1e3:.2f}, {result.pulley_error[1] * 1e3:.2f}] mm"),
        "",
        f"{'cable':>5} {'axis':>4}  {'box lo (m)':>11} {'box hi (m)':>11} {'width (mm)':>10}  {'NWLS (m)':>10}",
    ]
    warnings = []
    for a in result.anchors:
        for j, ax in enumerate(AXIS_NAMES):
            if a.box is None:
                box = f"{'empty':>11} {'':>11} {'':>10}"
            else:
                box = f"{a.box[j, 0]:11.5f} {a.box[j, 1]:11.5f} {(a.box[j, 1] - a.box[j, 0]) * 1e3:10.2f}"
            tag = ("inside" if a.nwls_inside else "OUTSIDE") if j == 0 else ""
            lines.append(f"{a.cable if j == 0 else '':>5} {ax:>4}  {box}  {a.nwls[j]:10.5f} {tag}")
        if a.box is None:
            warnings.append(f"cable {a.cable}: empty enclosure: fewer than {result.required} measurements are "
                            "consistent; lower --q or add measurements.")
        else:
            named = ", ".join(map(str, a.outliers)) if a.outliers else "none"
            lines.append(f"{'':>5} outlier poses (0-based rows): {named}")
            if a.uncontracted:
                warnings.append(f"cable {a.cable}: {', '.join(a.uncontracted)} not contracted (identifiability: the "
                                "poses do not constrain these directions; spread them over the workspace).")
            if a.exhausted:
                warnings.append(f"cable {a.cable}: paving budget exhausted; the box is guaranteed but not tight.")
    lines.append("")
    lines += [f"warning: {w}" for w in warnings]
    lines.append(f"time {result.seconds:.2f} s")
    return "\n".join(lines) + "\n"


def _simulate(args) -> int:
    _check_options(args)
    for option, path in (("-o", args.output), ("--truth", args.truth)):
        if path:
            check_output_option(path, args.force, option)
    robot = load_robot(args.robot)
    if args.n < 1:
        raise UsageError(f"option -n = {args.n} must be at least 1.")
    if not 0.0 <= args.outliers < 1.0:
        raise UsageError(f"option --outliers = {args.outliers} must be a fraction in [0, 1).")
    try:
        ds = simulate_tracker_dataset(robot, args.n, seed=args.seed, outliers=args.outliers, clustered=args.clustered,
                                      pose_tol=args.pose_tol, angle_tol=args.angle_tol,
                                      model_error=_model_error(args.model_error), anchor_offset=args.anchor_offset)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    try:
        claim_output_option(args.output, args.force, "-o")
        write_measurements_csv(args.output, ds.poses, ds.lengths)
        if args.truth:
            claim_output_option(args.truth, args.force, "--truth")
            Path(args.truth).write_text(json.dumps({
                "robot": robot.name,
                "true_anchors": np.asarray(ds.true_anchors).tolist(),
                "true_poses": np.asarray(ds.true_poses).tolist(),
                "outliers": list(ds.outliers),
            }) + "\n")
    except OSError as exc:
        raise OperationError(f"cannot write {exc.filename}: {exc.strerror}.") from exc
    truth = f"; truth: {args.truth}" if args.truth else ""
    sys.stdout.write(f"{args.output}: {args.n} simulated poses of {robot.name} ({len(ds.outliers)} outliers), one a "
                     f"line under the header x,y,z,roll,pitch,yaw,l_1..l_{robot.n} (m, rad){truth}\n")
    return 0
