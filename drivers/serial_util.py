"""Small pieces both serial drivers share: opening a port with one clear error, the reader thread, and the
book-keeping of the latest reading (waiters, staleness)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import serial

from drivers.interfaces import DeviceError, Reading


def open_port(port: str, baud: int, what: str) -> serial.Serial:
    """Open a serial port (USB adapter or pty slave) in raw 8N1 with a short read timeout."""
    try:
        return serial.Serial(port, baudrate=baud, timeout=0.01, write_timeout=1.0)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceError(f"{what}: cannot open serial port {port} at {baud} baud ({exc}).") from exc


class PortReader:
    """A daemon thread that reads a port and hands every chunk of bytes to ``on_bytes``."""

    def __init__(self, port: serial.Serial, on_bytes: Callable[[bytes, float], None], name: str) -> None:
        self.port = port
        self.on_bytes = on_bytes
        self.error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.port.read(max(1, self.port.in_waiting))
            except (serial.SerialException, OSError, TypeError) as exc:
                if self._stop.is_set():
                    return
                self.error = f"serial port {self.port.port} failed while reading ({exc})"
                time.sleep(0.05)
                continue
            if data:
                self.on_bytes(data, time.monotonic())


class LatestBox:
    """The most recent reading, a condition to wait on it, and the staleness rule (3 silent periods)."""

    def __init__(self, period: float, stale_periods: float = 3.0) -> None:
        self.period = period
        self.stale_periods = stale_periods
        self.cond = threading.Condition()
        self.latest: Reading | None = None
        self.opened_at = time.monotonic()

    def put(self, reading: Reading) -> None:
        with self.cond:
            self.latest = reading
            self.cond.notify_all()

    def wait(self, ok: Callable[[Reading], bool], timeout: float, what: str) -> Reading:
        deadline = time.monotonic() + timeout
        with self.cond:
            while self.latest is None or not ok(self.latest):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DeviceError(what)
                self.cond.wait(left)
            return self.latest

    def silence(self, now: float | None = None) -> float | None:
        """Seconds without a frame when that exceeds ``stale_periods`` periods, else None."""
        now = time.monotonic() if now is None else now
        last = self.latest.t if self.latest is not None else self.opened_at
        quiet = now - last
        return quiet if quiet > self.stale_periods * self.period else None
