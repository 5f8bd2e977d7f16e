"""`cdpr replay RUN --out NEW_RUN [--force]`: the run's raw record back through the drivers (acquisition/replay.py);
`cdpr replay RUN --live [HOST:]PORT [--speed X]`: the run played to a live Foxglove view at its pace."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

from acquisition.cli.args import add_force, check_output_option, claim_output_option
from acquisition.cli.errors import OperationError, UsageError


def register(sub) -> None:
    p = sub.add_parser("replay", help="rebuild a run's samples from its raw bus record through the drivers, or "
                       "play a run to a live Foxglove view")
    p.add_argument("run", type=Path, metavar="RUN", help="run folder (--out: with bus.blf or bus.asc and serial.rec)")
    p.add_argument("--out", type=Path, metavar="NEW_RUN",
                   help="run folder to write; an existing one is refused unless --force")
    p.add_argument("--live", metavar="[HOST:]PORT",
                   help="play the run to a read-only live view on PORT (127.0.0.1 unless HOST is named), at its "
                        "real pace (docs/live.md)")
    p.add_argument("--speed", type=float, default=1.0, help="with --live: play X times faster (default 1)")
    add_force(p)
    p.set_defaults(func=run)


def run(args) -> int:
    if (args.out is None) == (args.live is None):
        raise UsageError("cdpr replay needs one of --out NEW_RUN (rebuild from the raw record) or --live PORT.")
    if args.live is not None:
        return _live(args)
    import logging

    from acquisition.busrecord import SERIAL_RECORD, RecordError, can_record_path
    from acquisition.replay import replay_run
    from acquisition.runlog import RunFormatError
    from drivers.interfaces import DeviceError

    if not args.debug:  # a replay ends with SDO requests the record does not answer; canopen would log each
        logging.getLogger("canopen").setLevel(logging.CRITICAL)
    if not args.run.is_dir():  # as every command that reads a run says it, before naming the record it lacks
        raise UsageError(f"{args.run}: not a run folder ({'a file' if args.run.exists() else 'no such directory'}).")
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


def _live(args) -> int:
    import math

    from acquisition.live import LiveAddress, LiveServer
    from acquisition.replay import replay_live
    from acquisition.runlog import RunFormatError, read_run

    if not (math.isfinite(args.speed) and args.speed > 0):
        raise UsageError(f"--speed {args.speed} must be a positive number.")
    try:
        address = LiveAddress.parse(args.live)
        n = read_run(args.run).n
    except (RunFormatError, ValueError) as exc:
        raise UsageError(str(exc)) from exc
    try:
        server = LiveServer(address, n)
    except OSError as exc:
        raise OperationError(str(exc).rstrip(".") + ".") from exc
    def wait() -> None:
        sys.stderr.write("cdpr: waiting for a viewer to subscribe (Ctrl-C to give up)\n")
        server.wait_for_viewer()

    with server:
        res = replay_live(args.run, server, args.speed, wait=wait)
    sys.stdout.write(f"{args.run}: {res.samples} samples ({res.run_time:.1f} s of run) played live in "
                     f"{res.wall_time:.1f} s, {res.messages} messages\n")
    return 0
