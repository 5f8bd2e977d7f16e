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
import tty


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
