"""How late a byte written to a simulated serial line reaches its reader: socket pair, pty, pipe (not collected by
pytest).

    python benchmarks/bench_serial_latency.py [--seconds 15] [--rt-priority 40]

The paced simulated prototype (bench_live.py) waits at each tick for the load-cell line and the AHRS sample
that the plant's process writes to their serial lines (sim_backend/pty.py): Unix socket pairs since
2026-11-27, ptys before (``SimBackend(serial_lines="pty")``). A pty hands what is written on its master to the
reader of its slave through the kernel's tty buffer work, run by a kernel worker thread of normal priority; a
socket pair or a pipe wakes its reader from the write itself. This benchmark measures the three at the control
rate (a writer process every 5 ms, the reader timing each line from write to readable), both ends under
SCHED_FIFO when the OS grants it (else at normal priority), so that what is left is the transport's own
latency under the machine's load. Target: 99 % of the lines within half a control period (2.5 ms) and none
over a period (5 ms). Exits 1 when the socket pair (the simulator's line) misses it; the pipe is the
reference and the pty is shown for comparison (the cause bench_live's table named "blocked: serial lines").
"""

from __future__ import annotations

import argparse
import os
import pty
import select
import socket
import sys
import time
import tty

import numpy as np

PERIOD = 0.005  # s, the control period at 200 Hz


def _realtime(priority: int | None) -> bool:
    if priority is None or not hasattr(os, "SCHED_FIFO"):
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError:
        return False
    return True


def latencies(kind: str, count: int, priority: int | None) -> tuple[np.ndarray, bool]:
    """(count,) s from each write to its line being readable, over a pty, a socket pair or a pipe; whether under
    SCHED_FIFO."""
    if kind == "pty":
        master, slave = pty.openpty()
        tty.setraw(slave)
        write_fd, read_fd = master, slave
    elif kind == "socket":
        a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        write_fd, read_fd = a.detach(), b.detach()
    else:
        read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # the writer: one time-stamped line per period
        try:
            _realtime(priority)
            for _ in range(count):
                time.sleep(PERIOD)
                os.write(write_fd, b"%.9f\n" % time.perf_counter())
        finally:
            os._exit(0)
    rt = _realtime(priority)
    out, buf = [], b""
    while len(out) < count:
        select.select([read_fd], [], [], 1.0)
        now = time.perf_counter()
        buf += os.read(read_fd, 4096)
        *lines, buf = buf.split(b"\n")
        out += [now - float(x) for x in lines]
    os.waitpid(pid, 0)
    for fd in {read_fd, write_fd}:
        os.close(fd)
    return np.array(out[:count]), rt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=15.0, help="length of each measurement (default 15 s)")
    ap.add_argument("--rt-priority", type=int, default=40, help="SCHED_FIFO priority of both ends (0: normal)")
    args = ap.parse_args()
    count = int(args.seconds / PERIOD)
    ok = True
    for kind in ("pipe", "socket", "pty"):
        lat, rt = latencies(kind, count, args.rt_priority or None)
        ms = lat * 1e3
        within = float(np.mean(ms <= 0.5e3 * PERIOD))
        good = within >= 0.99 and ms.max() <= 1e3 * PERIOD
        print(f"{kind:6s}: {count} lines at {1 / PERIOD:g} Hz, {'SCHED_FIFO' if rt else 'normal priority'}, load "
              f"average {os.getloadavg()[0]:.2f}: p50 {np.median(ms):.3f} ms p99 {np.percentile(ms, 99):.3f} ms "
              f"worst {ms.max():.3f} ms; within 2.5 ms {100 * within:.1f} % (target >= 99 %, none over 5 ms)  "
              f"{'ok' if good else 'MISS'}")
        ok &= good or kind != "socket"  # the socket pair is the simulator's line; the others are references
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
