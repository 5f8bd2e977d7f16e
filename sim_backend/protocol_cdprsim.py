"""pyserial's handler of the ``cdprsim://NAME`` URLs: the driver's end of a simulated socket line
(:func:`sim_backend.pty.open_socket_line`), opened by ``serial.serial_for_url`` as a port.

pyserial finds this module by its name (``protocol_<scheme>``) in the packages of
``serial.protocol_handler_packages``, where :func:`~sim_backend.pty.open_socket_line` puts ``sim_backend``. The
port is pyserial's POSIX one on a copy of the socket's descriptor: reads, writes, timeouts, ``in_waiting``
(FIONREAD) and the non-blocking descriptor are the same as on a tty; what only a tty has (line settings,
modem lines, flushing the kernel's buffers) has nothing to act on and is skipped, as pyserial's ``socket://``
does; the input buffer is reset by reading out what is waiting.
"""

from __future__ import annotations

import fcntl
import os

import serial
from serial.serialposix import Serial as PosixSerial

from sim_backend.pty import socket_line_fd


class Serial(PosixSerial):
    """A simulated socket line as a pyserial port (the URL ``cdprsim://NAME``)."""

    def open(self) -> None:
        if self._port is None:
            raise serial.SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise serial.SerialException("Port is already open.")
        try:
            self.fd = os.dup(socket_line_fd(self.portstr))
        except (KeyError, IndexError, OSError) as exc:
            raise serial.SerialException(f"could not open port {self._port}: no such simulated line") from exc
        os.set_blocking(self.fd, False)
        self.pipe_abort_read_r, self.pipe_abort_read_w = os.pipe()
        self.pipe_abort_write_r, self.pipe_abort_write_w = os.pipe()
        for fd in (self.pipe_abort_read_r, self.pipe_abort_write_r):
            fcntl.fcntl(fd, fcntl.F_SETFL, os.O_NONBLOCK)
        self.is_open = True
        self._reset_input_buffer()

    def _reconfigure_port(self, force_update: bool = False) -> None:
        """No line settings on a socket (baud rate, parity... are the device's business)."""

    def _update_dtr_state(self) -> None:
        """No modem lines."""

    def _update_rts_state(self) -> None:
        """No modem lines."""

    def _update_break_state(self) -> None:
        """No break condition."""

    def _reset_input_buffer(self) -> None:
        """Read out and drop what is waiting."""
        while True:
            try:
                if not os.read(self.fd, 65536):
                    return
            except (BlockingIOError, InterruptedError):
                return

    def reset_output_buffer(self) -> None:
        """Nothing is held back: a write is in the socket when it returns."""

    def flush(self) -> None:
        """Nothing to drain (see :meth:`reset_output_buffer`)."""
