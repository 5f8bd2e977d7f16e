"""`cdpr import irma FILE -o RUN` and `cdpr export RUN --format mat|npz|csv|mcap -o FILE`."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

from acquisition.cli.errors import OperationError, UsageError
from acquisition.export import FORMATS, ExportError, export_run
from acquisition.importers import IrmaImportError, import_irma
from acquisition.runlog import RunFormatError, read_run


def register(sub) -> None:
    imp = sub.add_parser("import", help="convert another log format into a run")
    isub = imp.add_subparsers(dest="import_format", metavar="FORMAT")
    irma = isub.add_parser("irma", help="an IRMA L@B log: the authors' *_parsed.mat or the controller's raw .log")
    irma.add_argument("file", type=Path, help="*_parsed.mat or raw .log file")
    irma.add_argument("-o", "--out", type=Path, required=True, metavar="RUN", help="run folder to create")
    irma.add_argument(
        "--targets",
        type=Path,
        metavar="MAT",
        help="sc_control_target_*.mat of the same experiment: planned setpoints and ideal poses",
    )
    irma.add_argument("--force", action="store_true", help="overwrite RUN if it already holds a run")
    irma.set_defaults(func=_import_irma)

    exp = sub.add_parser("export", help="export a run (and its solution, where solved) for offline solving")
    exp.add_argument("run", type=Path, metavar="RUN", help="run folder")
    exp.add_argument("--format", required=True, choices=FORMATS,
                     help="mat (MATLAB v5), npz, csv or mcap (Foxglove, PlotJuggler)")
    exp.add_argument("-o", "--out", type=Path, required=True, metavar="FILE", help="file to write")
    exp.set_defaults(func=_export)


def _import_irma(args) -> int:
    if not args.file.is_file():
        raise UsageError(f"{args.file}: no such file.")
    if args.targets is not None and not args.targets.is_file():
        raise UsageError(f"{args.targets}: no such file (--targets).")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            run = import_irma(args.file, args.out, targets=args.targets, overwrite=args.force)
        except (IrmaImportError, RunFormatError) as exc:
            raise UsageError(str(exc)) from exc
        except FileExistsError as exc:
            raise UsageError(f"{exc} Use --force to replace it.") from exc
        except OSError as exc:
            raise OperationError(f"{args.out}: cannot write the run ({exc.strerror}).") from exc
    for w in caught:
        sys.stderr.write(f"cdpr: warning: {w.message}\n")
    k = 0 if run.setpoints is None else len(run.setpoints)
    sys.stdout.write(
        f"{args.out}: {len(run)} samples over {run.t[-1]:.1f} s from {args.file.name} ({run.source}), "
        f"{k} setpoints\n"
    )
    return 0


def _export(args) -> int:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            run = read_run(args.run)
            out = export_run(run, args.format, args.out)
        except (RunFormatError, ExportError) as exc:
            raise UsageError(str(exc)) from exc
        except OSError as exc:
            raise OperationError(f"{args.out}: cannot write the export ({exc.strerror}).") from exc
    for w in caught:
        sys.stderr.write(f"cdpr: warning: {w.message}\n")
    solved = "with its solution (absolute channels)" if (args.run / "solution.json").is_file() else "not solved"
    sys.stdout.write(f"{out}: {len(run)} samples of {args.run}, {solved}\n")
    return 0
