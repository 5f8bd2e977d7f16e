"""`cdpr replay RUN --out NEW_RUN [--force]`: the run's raw record back through the drivers (acquisition/replay.py)."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

from acquisition.cli.args import add_force, check_output_option, claim_output_option
from acquisition.cli.errors import OperationError, UsageError


def register(sub) -> None:
    p = sub.add_parser("replay", help="rebuild a run's samples from its raw bus record through the drivers")
    p.add_argument("run", type=Path, metavar="RUN", help="run folder with bus.blf (or bus.asc) and serial.rec")
    p.add_argument("--out", type=Path, required=True, metavar="NEW_RUN",
                   help="run folder to write; an existing one is refused unless --force")
    add_force(p)
    p.set_defaults(func=run)


def run(args) -> int:
    import logging

    from acquisition.busrecord import SERIAL_RECORD, RecordError, can_record_path
    from acquisition.replay import replay_run
    from acquisition.runlog import RunFormatError
    from drivers.interfaces import DeviceError

    if not args.debug:  # a replay ends with SDO requests the record does not answer; canopen would log each
        logging.getLogger("canopen").setLevel(logging.CRITICAL)
    for need in (can_record_path(args.run), args.run / SERIAL_RECORD):
        if not need.is_file():
            raise UsageError(f"{need}: no such file; only runs recorded by `cdpr startup` can be replayed.")
    check_output_option(args.out, args.force, "--out", [args.run])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            claim_output_option(args.out, args.force, "--out", [args.run])
            res = replay_run(args.run, args.out)
        except (RecordError, RunFormatError, ValueError) as exc:
            raise UsageError(str(exc)) from exc
        except DeviceError as exc:
            raise OperationError(f"the replay could not open the recorded devices: {str(exc).rstrip('.')}.") from exc
        except OSError as exc:
            raise OperationError(f"{args.out}: cannot write the replayed run ({exc.strerror}).") from exc
    for w in caught:
        sys.stderr.write(f"cdpr: warning: {w.message}\n")
    sys.stdout.write(f"{res.out}: {res.samples} of {res.original} samples rebuilt from {res.frames} CAN frames "
                     f"({res.syncs} SYNCs) of {args.run}\n")
    return 0
