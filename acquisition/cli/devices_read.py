"""`cdpr devices read ahrs|loadcells --port PORT [--baud B] [--count N] [--json]`: read one serial device.

``--json`` prints one object per sample on stdout: AHRS ``{"t", "roll", "pitch", "yaw", "seq"}`` (rad),
load cells ``{"t", "tau": [..], "seq"}`` (N); ``t`` is the host's monotonic receive time, s.
"""

from __future__ import annotations

import json
import math
import os
import sys

from acquisition.cli.errors import OperationError, UsageError
from drivers.interfaces import DeviceError


def register(devsub) -> None:
    p = devsub.add_parser("read", help="read samples from one serial device (AHRS or load-cell amplifier)")
    p.add_argument("device", choices=("ahrs", "loadcells"), help="which device is on the port")
    p.add_argument("--port", required=True, help="serial port, e.g. /dev/ttyUSB0 or a pty such as /dev/pts/3")
    p.add_argument("--baud", type=int, default=115200, help="baud rate (default 115200)")
    p.add_argument("--count", type=int, default=10, help="number of samples to read (default 10)")
    p.add_argument("--json", action="store_true", help="one JSON object per sample on stdout")
    p.add_argument("--rate", type=int, default=100,
                   help="AHRS: output rate to configure, Hz, a divisor of 400; load cells: expected rate")
    p.add_argument("--channels", type=int, default=4, help="load cells: number of channels (default 4)")
    p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for each sample (default 2)")
    p.set_defaults(func=run)


def _check(args) -> None:
    if args.count < 1:
        raise UsageError(f"--count must be at least 1, got {args.count}.")
    if args.baud < 1:
        raise UsageError(f"--baud must be a positive baud rate, got {args.baud}.")
    if args.timeout <= 0 or not math.isfinite(args.timeout):
        raise UsageError(f"--timeout must be a positive number of seconds, got {args.timeout}.")
    if args.channels < 1:
        raise UsageError(f"--channels must be at least 1, got {args.channels}.")
    if args.device == "ahrs" and not (0 < args.rate <= 400 and 400 % args.rate == 0):
        raise UsageError(f"--rate {args.rate} Hz is not an MTi output rate (a divisor of 400 Hz).")
    if args.device == "ahrs":
        from drivers.xsens import XsensConfig, config_problem

        problem = config_problem(XsensConfig(port=args.port, baud=args.baud, rate_hz=args.rate))
        if problem:
            raise UsageError(f"--rate {args.rate} with --baud {args.baud}: {problem}")
    if args.device == "loadcells" and args.rate <= 0:
        raise UsageError(f"--rate must be positive, got {args.rate}.")
    if not os.path.exists(args.port):
        raise UsageError(f"--port {args.port}: no such serial port.")


def _device(args):
    if args.device == "ahrs":
        from drivers.xsens import XsensConfig, XsensMti

        return XsensMti(XsensConfig(port=args.port, baud=args.baud, rate_hz=args.rate))
    from drivers.loadcell import LoadCellConfig, LoadCellDriver

    return LoadCellDriver(LoadCellConfig(port=args.port, baud=args.baud, channels=args.channels,
                                         rate_hz=float(args.rate)))


def _line(device: str, r, as_json: bool, t0: float = 0.0) -> str:
    """One reading as text or JSON; ``t`` is seconds since the first reading printed (receive times)."""
    t = r.t - t0
    if device == "ahrs":
        if as_json:
            return json.dumps({"t": t, "roll": r.roll, "pitch": r.pitch, "yaw": r.yaw, "seq": r.seq})
        return (f"t={t:.4f} s  seq={r.seq}  roll={math.degrees(r.roll):+.3f} deg  "
                f"pitch={math.degrees(r.pitch):+.3f} deg  yaw={math.degrees(r.yaw):+.3f} deg")
    tau = [None if math.isnan(v) else float(v) for v in r.tau]
    if as_json:
        return json.dumps({"t": t, "tau": tau, "seq": r.seq})
    text = "  ".join("  --  " if v is None else f"{v:8.2f}" for v in tau)
    return f"t={t:.4f} s  seq={r.seq}  tau=[{text}] N"


def run(args) -> int:
    _check(args)
    dev = _device(args)
    try:
        dev.open()
    except DeviceError as exc:
        raise OperationError(str(exc)) from exc
    try:
        first = dev.wait_for(-1, args.timeout)  # whatever sample comes first
        reading = first
        for i in range(args.count):
            if i:
                reading = dev.wait_for(reading.seq + 1, args.timeout)
            sys.stdout.write(_line(args.device, reading, args.json, first.t) + "\n")
            sys.stdout.flush()
        if not args.json:
            s = dev.stats
            sys.stderr.write(f"{s.frames} frames, {s.checksum_errors} bad, {s.sequence_gaps} missing, "
                             f"{s.bytes_discarded} bytes discarded\n")
            fault = dev.fault()
            if fault:
                sys.stderr.write(f"fault: {fault}\n")
    except DeviceError as exc:
        raise OperationError(str(exc)) from exc
    finally:
        dev.close()
    return 0
