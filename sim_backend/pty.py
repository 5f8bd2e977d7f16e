"""The simulated serial lines: pseudo-terminal pairs, or socket pairs, standing in for USB serial adapters.

A pty: the emulated device owns the master side; the driver opens the slave path (``/dev/pts/N``) with pyserial
exactly as it opens ``/dev/ttyUSB0`` on the robot. The line is put in raw mode (no echo, no CR/LF
translation, 8 bits) before anyone opens it, and the master is non-blocking: when nobody reads, the
kernel buffer fills and further bytes are dropped, as a UART with no listener drops them.

A socket line (:func:`open_socket_line`, the simulated prototype's): a Unix stream socket pair, the device's
end non-blocking as a pty master; the driver opens the URL ``cdprsim://NAME`` through pyserial's
``serial_for_url`` (handler: :mod:`sim_backend.protocol_cdprsim`). A pty hands the master's bytes to the slave's
reader through the kernel's tty buffer work, run by a kernel worker thread of normal priority: on a loaded
machine 5-150 ms late (benchmarks/bench_serial_latency.py), which a control loop paced in real time in lockstep
waits for at every tick; a socket's write wakes its reader itself, like a pipe's. Same bytes, same order.
"""

from __future__ import annotations

import errno
import itertools
import os
import select
import socket
import threading
import time
import tty
from collections.abc import Callable

import numpy as np
import serial


def open_pty_pair() -> tuple[int, str]:
    """Create a raw pty pair; returns (master_fd, slave_path). Close master_fd with ``os.close`` when done."""
    master, slave = os.openpty()
    try:
        tty.setraw(slave)
        path = os.ttyname(slave)
    finally:
        os.close(slave)
    os.set_blocking(master, False)
    return master, path


SOCKET_SCHEME = "cdprsim"  # the pyserial URL scheme of a socket line: cdprsim://NAME
_socket_lines: dict[str, int] = {}  # NAME -> the driver's end of each open socket line (this process)
_line_ids = itertools.count(1)


def open_socket_line(name: str) -> tuple[int, str]:
    """A serial line over a Unix socket pair: (the device's fd, non-blocking; the URL the driver opens with
    ``serial.serial_for_url``). Close it with :func:`close_socket_line` (the URL) and ``os.close`` (the fd)."""
    if __package__ not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(__package__)  # pyserial's documented plug-in list
    device, driver = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    key = f"{name}-{os.getpid()}-{next(_line_ids)}"
    _socket_lines[key] = driver.detach()
    fd = device.detach()
    os.set_blocking(fd, False)
    return fd, f"{SOCKET_SCHEME}://{key}"


def socket_line_fd(url: str) -> int:
    """The driver's end of the open socket line ``url`` (KeyError when none)."""
    return _socket_lines[url.split("://", 1)[1]]


def close_socket_line(url: str) -> None:
    """Close the driver's end held for ``url`` (a driver that opened it holds its own copy)."""
    fd = _socket_lines.pop(url.split("://", 1)[1], None)
    if fd is not None:
        os.close(fd)


def write_master(fd: int, data: bytes) -> int:
    """Write to a pty master (or a socket line's device end) without blocking; returns the bytes accepted (the
    rest is dropped)."""
    done = 0
    while done < len(data):
        try:
            done += os.write(fd, data[done:])
        except (BlockingIOError, InterruptedError):
            break
        except OSError as exc:  # no slave open (EIO), no driver's end left (EPIPE) or fd closed: the bytes go nowhere
            if exc.errno in (errno.EIO, errno.EBADF, errno.EPIPE, errno.ECONNRESET):
                break
            raise
    return done


def read_master(fd: int, timeout: float) -> bytes:
    """Bytes the driver wrote to the slave, waiting up to ``timeout`` s; b"" when none (or no slave open)."""
    try:
        ready, _, _ = select.select([fd], [], [], timeout)
    except (OSError, ValueError):
        return b""
    if not ready:
        return b""
    try:
        data = os.read(fd, 4096)
    except (BlockingIOError, InterruptedError):
        return b""
    except OSError as exc:
        if exc.errno in (errno.EIO, errno.EBADF, errno.ECONNRESET):  # slave closed: select keeps reporting it
            select.select([], [], [], timeout)
            return b""
        raise
    if not data:  # a socket line's every driver's end closed: readable for ever, nothing to read
        select.select([], [], [], timeout)
    return data


class GaussianBlocks:
    """Standard normal values of a Generator served ``group`` at a time from blocks of ``per_block`` groups: one
    Generator call per block instead of one per group (a call costs microseconds), and the same values in the same
    order as drawing them group by group.

    The generator may have other users: :meth:`release` first puts it back just after the last value served (it
    draws the block again from the block's start state, up to there) and drops the rest of the block.
    """

    def __init__(self, rng: np.random.Generator, group: int, per_block: int = 64) -> None:
        self._rng = rng
        self._group = group
        self._size = group * per_block
        self._values: list[float] = []
        self._next = 0  # index of the next value to serve
        self._start: dict | None = None  # the bit generator's state before the block was drawn

    def take(self) -> list[float]:
        """The next ``group`` standard normal values."""
        i = self._next
        if i == len(self._values):
            self._start = self._rng.bit_generator.state
            self._values = self._rng.standard_normal(self._size).tolist()
            i = 0
        self._next = i + self._group
        return self._values[i:self._next]

    def release(self) -> None:
        """Rewind the generator to just after the last value served, for another use of it."""
        if self._start is None:
            return
        self._rng.bit_generator.state = self._start
        self._rng.standard_normal(self._next)
        self._values, self._next, self._start = [], 0, None


class PtyEmulator:
    """What every emulated serial device shares: the pty master it owns, a thread answering the host's
    commands (``_serve``, implemented by the device), injected corruption (bit flips drawn from the
    device's seeded generator) and byte counters. A device that draws noise at every sample takes it from
    ``self._normals`` (a :class:`GaussianBlocks` on the same generator); :attr:`rng` is then given back in step."""

    thread_name = "pty-emulator"

    def __init__(self, master_fd: int, rng: np.random.Generator) -> None:
        self.fd = master_fd
        self._rng = rng
        self._normals: GaussianBlocks | None = None
        self._corrupt_left = 0
        self._silent = False
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.bytes_written = 0
        self.bytes_dropped = 0

    @property
    def rng(self) -> np.random.Generator:
        """The device's seeded generator, just after every value drawn so far (block-drawn noise included)."""
        if self._normals is not None:
            self._normals.release()
        return self._rng

    # ---- life cycle ----
    def start(self):
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._serve, name=self.thread_name, daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop answering the host (the pty master stays open: its owner closes it)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    def _serve(self) -> None:
        raise NotImplementedError

    # ---- the line ----
    def corrupt(self, n_bytes: int) -> None:
        """Damage the next ``n_bytes`` bytes sent (bit flips)."""
        with self._lock:
            self._corrupt_left += int(n_bytes)

    def _maybe_corrupt(self, data: bytes) -> bytes:
        if self._corrupt_left <= 0:
            return data
        k = min(self._corrupt_left, len(data))
        self._corrupt_left -= k
        b = bytearray(data)
        idx = self.rng.choice(len(b), size=k, replace=False)
        flips = self.rng.integers(1, 256, size=k)
        for i, x in zip(idx, flips, strict=True):
            b[int(i)] ^= int(x)
        return bytes(b)

    def _write(self, data: bytes) -> None:
        n = write_master(self.fd, data)
        self.bytes_written += n
        self.bytes_dropped += len(data) - n


def free_run(emulator: PtyEmulator, emit: Callable[[float], object], rate_hz: float) -> int:
    """Drive an emulator on wall time (the demos' ``python -m``): ``emit(t)`` every 1/rate_hz s until Ctrl-C."""
    t0 = time.monotonic()
    try:
        while True:
            emit(time.monotonic() - t0)
            time.sleep(1.0 / rate_hz)
    except KeyboardInterrupt:
        return 0
    finally:
        emulator.close()
