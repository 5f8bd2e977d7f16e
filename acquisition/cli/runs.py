"""`cdpr import irma FILE -o RUN` and `cdpr export RUN --format mat|npz|csv|mcap -o FILE`."""

from __future__ import annotations

import sys
from pathlib import Path

from acquisition.cli.args import add_force, check_output_option, claim_output_option
from acquisition.cli.errors import OperationError, UsageError
from acquisition.export import FORMATS, export_run
from acquisition.importers import irma_run
from acquisition.runlog import read_run
from acquisition.runwriter import write_run


def register(sub) -> None:
    imp = sub.add_parser("import", help="convert another log format into a run")
    isub = imp.add_subparsers(dest="import_format", metavar="FORMAT")
    irma = isub.add_parser("irma", help="an IRMA L@B log: the authors' *_parsed.mat or the controller's raw .log")
    irma.add_argument("file", type=Path, help="*_parsed.mat or raw .log file")
    irma.add_argument("-o", "--out", type=Path, required=True, metavar="RUN",
                      help="run folder to create; an existing one is refused unless --force")
    irma.add_argument(
        "--targets",
        type=Path,
        metavar="FILE",
        help="the planned setpoints of the same experiment: sc_control_target_*.mat (with the ideal poses) or "
        "the controller's tension_target_*.csv (docs/run-format.md); a file whose setpoints the run's holds "
        "do not follow is refused",
    )
    add_force(irma)
    irma.set_defaults(func=_import_irma)

    exp = sub.add_parser("export", help="export a run (and its solution, where solved) for offline solving")
    exp.add_argument("run", type=Path, metavar="RUN", help="run folder")
    exp.add_argument("--format", required=True, choices=FORMATS,
                     help="mat (MATLAB v5), npz, csv or mcap (Foxglove, PlotJuggler)")
    exp.add_argument("-o", "--out", type=Path, required=True, metavar="FILE",
                     help="file to write; an existing one is refused unless --force")
    add_force(exp)
    exp.set_defaults(func=_export)


def _import_irma(args) -> int:
    if not args.file.is_file():
        raise UsageError(f"{args.file}: no such file.")
    if args.targets is not None and not args.targets.is_file():
        raise UsageError(f"{args.targets}: no such file (--targets).")
    inputs = [f for f in (args.file, args.targets) if f is not None]
    check_output_option(args.out, args.force, "-o", inputs)
    run = irma_run(args.file, targets=args.targets)
    claim_output_option(args.out, args.force, "-o", inputs)
    try:
        write_run(args.out, run)
        run = read_run(args.out)
    except OSError as exc:
        raise OperationError(f"{args.out}: cannot write the run ({exc.strerror}).") from exc
    k = 0 if run.setpoints is None else len(run.setpoints)
    sys.stdout.write(
        f"{args.out}: {len(run)} samples over {run.t[-1]:.1f} s from {args.file.name} ({run.source}), "
        f"{k} setpoints\n"
    )
    return 0


def _export(args) -> int:
    _check_extension(args.out, args.format)
    check_output_option(args.out, args.force, "-o", [args.run])
    run = read_run(args.run)
    claim_output_option(args.out, args.force, "-o", [args.run])
    try:
        out = export_run(run, args.format, args.out)
    except OSError as exc:
        raise OperationError(f"{args.out}: cannot write the export ({exc.strerror}).") from exc
    solved = _which_solution(args.run / "solution.json", args.format)
    sys.stdout.write(f"{out}: {len(run)} samples of {args.run}, {solved}\n")
    return 0


def _check_extension(out: Path, fmt: str) -> None:
    """An output named for another format (``--format mat -o x.npz``) is refused: the reader picks its loader
    by the name. Any other name (none, ``.txt``...) is the user's choice."""
    ext = out.suffix.lower().lstrip(".")
    if ext in FORMATS and ext != fmt:
        raise UsageError(f"-o {out}: the name says {ext} but --format is {fmt}; name it {out.stem}.{fmt} or give "
                         f"--format {ext}.")


def _which_solution(path: Path, fmt: str = "mat") -> str:
    """What `export` says of the solution it carried: the file and how it was solved, or 'not solved'. A CSV
    holds samples only: the solution's absolute channels, not the solution itself."""
    import json

    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return "not solved"
    effects = ", ".join(doc.get("effects") or {}) or "none"
    noise = doc.get("noise")
    noise = noise.get("source", "?") if isinstance(noise, dict) else noise
    how = f"(method {doc.get('method', '?')}, noise {noise}, effects {effects})"
    if fmt == "csv":
        return (f"with the absolute channels of its solution {path} {how}; the solution itself (initial pose, "
                f"1-sigma, offsets) is not in a CSV: read {path}")
    return f"with its solution {path} {how} and the absolute channels"
