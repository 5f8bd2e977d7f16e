"""Small pieces both serial drivers share: opening a port with one clear error, the reader (a thread, or polled
by the caller in lockstep), and the book-keeping of the latest reading (waiters, staleness)."""

from __future__ import annotations

import os
import select
import threading
import time
from collections.abc import Callable

import serial

from drivers.interfaces import DeviceError, LinkStats, Reading


def open_port(port: str, baud: int, what: str) -> serial.Serial:
    """Open a serial port in raw 8N1 with a short read timeout: a device path (USB adapter, pty slave) as
    ``serial.Serial`` opens it, or a pyserial URL (``socket://HOST:PORT`` of a serial device server, the simulated
    prototype's ``cdprsim://NAME``) through ``serial.serial_for_url``."""
    try:
        return serial.serial_for_url(port, baudrate=baud, timeout=0.01, write_timeout=1.0)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceError(f"{what}: cannot open serial port {port} at {baud} baud ({exc}).") from exc


def _tapped(tap: Callable[[bytes, bool], None],
            on_bytes: Callable[[bytes, float], None]) -> Callable[[bytes, float], None]:
    def both(data: bytes, t: float) -> None:
        tap(data, False)
        on_bytes(data, t)

    return both


class PortReader:
    """Reads a port and hands every chunk of bytes to ``on_bytes``: in a daemon thread, or, not ``threaded``,
    in the thread that calls :meth:`poll` (the drivers' waits do, in lockstep with a simulated prototype whose
    bytes are already written when the loop asks for them: no thread hand-off per reading). The driver writes
    through :meth:`write`. ``tap(data, sent)`` gets every chunk read (``sent`` False) first, and every chunk
    written (``sent`` True): the raw serial record, acquisition/busrecord.py."""

    def __init__(self, port: serial.Serial, on_bytes: Callable[[bytes, float], None], name: str,
                 threaded: bool = True, tap: Callable[[bytes, bool], None] | None = None) -> None:
        self.port = port
        self.tap = tap
        self.on_bytes = on_bytes if tap is None else _tapped(tap, on_bytes)
        self.threaded = threaded
        self.error: str | None = None
        self._stop = threading.Event()
        self._poll_lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._fd: int | None = None  # the descriptor read directly by a polled reader (POSIX, non-blocking)
        if not threaded:
            try:
                fd = port.fileno()
                if not os.get_blocking(fd):
                    self._fd = fd
            except (AttributeError, OSError, ValueError, serial.SerialException):
                self._fd = None

    def start(self) -> None:
        if self.threaded:
            self._thread.start()

    def write(self, data: bytes) -> None:
        """Write ``data`` to the port (the tap sees it first)."""
        if self.tap is not None:
            self.tap(data, True)
        self.port.write(data)

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

    def poll(self, timeout: float = 0.0) -> bool:
        """Polled reader: hand the bytes waiting now (waiting up to ``timeout`` s for some) to ``on_bytes``;
        whether there were any (always False with a reader thread, which reads by itself)."""
        if self.threaded:
            return False
        with self._poll_lock:
            if self._stop.is_set():
                return False
            try:
                data = self._read_now()
                if not data and timeout > 0:
                    select.select([self.port.fileno()], [], [], timeout)
                    data = self._read_now()
            except (serial.SerialException, OSError, TypeError, ValueError) as exc:
                self.error = f"serial port {self.port.port} failed while reading ({exc})"
                if timeout > 0:
                    time.sleep(min(timeout, 0.05))
                return False
            if data:
                self.on_bytes(data, time.monotonic())
            return bool(data)

    def _read_now(self) -> bytes:
        """What the port holds now, without waiting. pyserial keeps a POSIX port's descriptor non-blocking
        and its ``read`` asks select() first; one read() of the descriptor does the same in one system call
        (the polled reader runs at every control tick). Other platforms go through pyserial."""
        fd = self._fd
        if fd is None:
            n = self.port.in_waiting
            return self.port.read(n) if n else b""
        try:
            return os.read(fd, 4096)
        except BlockingIOError:
            return b""

    def until(self, done: Callable[[], bool], timeout: float) -> bool:
        """Polled reader: poll until ``done()`` (True) or ``timeout`` s have passed (False). The port is read
        once more when the time is up: bytes already waiting count, however long this thread was kept from
        running (a loaded machine), so that the answer depends on what arrived, not on when it was looked at."""
        deadline = time.monotonic() + timeout
        while not done():
            left = deadline - time.monotonic()
            if left <= 0:
                self.poll()
                return done()
            self.poll(left)
        return True


class LatestBox:
    """The most recent reading, a condition to wait on it, and the staleness rule (3 silent periods).
    With a polled reader (``reader``, see :class:`PortReader`) the waits poll the port instead."""

    def __init__(self, period: float, stale_periods: float = 3.0) -> None:
        self.period = period
        self.stale_periods = stale_periods
        self.cond = threading.Condition()
        self.latest: Reading | None = None
        self.opened_at = time.monotonic()
        self.reader: PortReader | None = None  # set when the port is polled

    def attach(self, reader: PortReader) -> None:
        """The port's reader: a polled one is polled by :meth:`current` and :meth:`wait`."""
        self.reader = None if reader.threaded else reader

    def current(self) -> Reading | None:
        """The latest reading, the port polled first when no reader thread does it."""
        if self.reader is not None:
            self.reader.poll()
        return self.latest

    def put(self, reading: Reading) -> None:
        if self.reader is not None:  # polled: the waits poll, nobody waits on the condition
            self.latest = reading
            return
        with self.cond:
            self.latest = reading
            self.cond.notify_all()

    def wait(self, ok: Callable[[Reading], bool], timeout: float, what: str) -> Reading:
        reader = self.reader
        if reader is not None:
            if not reader.until(lambda: self.latest is not None and ok(self.latest), timeout):
                raise DeviceError(what)
            return self.latest
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


class SerialDevice:
    """What both serial drivers do the same way around their own protocol, as python-can's ``BusABC.recv``
    over ``_recv_internal``: open the port and its reader, close them, keep the latest reading, wait for one,
    judge the silence. A driver sets ``kind`` (its name in messages), ``tag`` (its reader thread's prefix) and
    ``counter`` (what :meth:`wait_for` counts) and implements :meth:`_on_bytes` (decode what the port gave),
    :meth:`_greet` (the exchange after opening) and :meth:`_count` (a reading's counter).

    ``config`` needs ``port``, ``baud``, ``rate_hz``, ``stale_periods``, ``polled`` and ``tap``."""

    kind = "serial device"
    tag = "serial"
    counter = "sequence"

    def __init__(self, config) -> None:
        self.config = config
        self._port: serial.Serial | None = None
        self._reader: PortReader | None = None
        self._stats = LinkStats()
        self._box = LatestBox(1.0 / config.rate_hz, config.stale_periods)

    # ---- what a driver implements ----
    def _on_bytes(self, data: bytes, t: float) -> None:
        """Decode ``data`` read at monotonic time ``t`` s and :meth:`LatestBox.put` its readings."""
        raise NotImplementedError

    def _greet(self) -> None:
        """The exchange that opening ends with (a handshake, a configuration); raises DeviceError."""
        raise NotImplementedError

    def _count(self, reading: Reading) -> int:
        """The counter of ``reading`` that :meth:`wait_for` compares."""
        raise NotImplementedError

    # ---- life cycle ----
    def open(self) -> None:
        if self._port is not None:
            return
        self._port = open_port(self.config.port, self.config.baud, self.kind)
        self._reader = PortReader(self._port, self._on_bytes, name=f"{self.tag}-{self.config.port}",
                                  threaded=not self.config.polled, tap=self.config.tap)
        self._box.attach(self._reader)
        self._reader.start()
        try:
            self._greet()
        except DeviceError:
            self.close()
            raise

    def close(self) -> None:
        if self._reader is not None:
            self._reader.stop()
            self._reader = None
        if self._port is not None:
            try:
                self._port.close()
            finally:
                self._port = None

    # ---- readings ----
    def latest(self) -> Reading | None:
        return self._box.current()

    def wait_for(self, count: int, timeout: float) -> Reading:
        """Block until a reading whose counter is >= ``count`` arrives (DeviceError after ``timeout`` s)."""
        r = self._box.latest
        if r is not None and self._count(r) >= count:  # already here (the usual case in lockstep)
            return r
        return self._box.wait(lambda r: self._count(r) >= count, timeout,
                              f"{self.kind} on {self.config.port}: no sample with {self.counter} >= "
                              f"{count} within {timeout:g} s.")

    @property
    def stats(self) -> LinkStats:
        return self._stats

    def staleness(self, now: float | None = None) -> str | None:
        """A fault sentence when no reading arrived for ``stale_periods`` periods, else None."""
        quiet = self._box.silence(now)
        if quiet is None:
            return None
        return (f"{self.kind} on {self.config.port} silent for {quiet:.3f} s (more than "
                f"{self.config.stale_periods:g} periods at {self.config.rate_hz:g} Hz).")
