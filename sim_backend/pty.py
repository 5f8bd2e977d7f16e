"""Pseudo-terminal pairs standing in for USB serial adapters.

The emulated device owns the master side; the driver opens the slave path (``/dev/pts/N``) with pyserial
exactly as it opens ``/dev/ttyUSB0`` on the robot. The line is put in raw mode (no echo, no CR/LF
translation, 8 bits) before anyone opens it, and the master is non-blocking: when nobody reads, the
kernel buffer fills and further bytes are dropped, as a UART with no listener drops them.
"""

from __future__ import annotations

import errno
import os
import select
import threading
import time
import tty
from collections.abc import Callable

import numpy as np


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


def write_master(fd: int, data: bytes) -> int:
    """Write to a pty master without blocking; returns the bytes accepted (the rest is dropped)."""
    done = 0
    while done < len(data):
        try:
            done += os.write(fd, data[done:])
        except (BlockingIOError, InterruptedError):
            break
        except OSError as exc:  # no slave open (EIO) or fd closed: the bytes go nowhere
            if exc.errno in (errno.EIO, errno.EBADF):
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
        return os.read(fd, 4096)
    except (BlockingIOError, InterruptedError):
        return b""
    except OSError as exc:
        if exc.errno in (errno.EIO, errno.EBADF):  # slave closed: select keeps reporting it readable
            select.select([], [], [], timeout)
            return b""
        raise


class PtyEmulator:
    """What every emulated serial device shares: the pty master it owns, a thread answering the host's
    commands (``_serve``, implemented by the device), injected corruption (bit flips drawn from the
    device's seeded generator) and byte counters."""

    thread_name = "pty-emulator"

    def __init__(self, master_fd: int, rng: np.random.Generator) -> None:
        self.fd = master_fd
        self.rng = rng
        self._corrupt_left = 0
        self._silent = False
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.bytes_written = 0
        self.bytes_dropped = 0

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
