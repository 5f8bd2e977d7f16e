"""The physics and the serial devices, one control period ahead of the CAN nodes: on the second core or here.

A CiA 402 drive applies a synchronous target at the SYNC after it arrives, so the torque a master computes
from the readings of SYNC n acts from SYNC n + 1 on. The simulated prototype keeps that timing:

* at SYNC n the CAN nodes (this process) read the plant at t_n = n * period through a :class:`PlantView`
  and write their commands into it (motor torques, holding brakes);
* the :class:`PlantCore` writes the load-cell line and the AHRS sample of t_n on their ptys as the SYNC's
  first act (:meth:`PlantLink.emit`), then takes the commands: it steps the physics to t_{n+1}, injects
  the faults due at t_{n+1} and makes the load-cell line of t_{n+1} (written at SYNC n + 1);
* the state at t_{n+1} is published to the view at SYNC n + 1.

Nothing the core's step at SYNC n makes is needed before SYNC n + 1, so on a machine with two cores the core runs
in a child process (:class:`ChildPlantLink`, forked, with its serial emulators' threads): its physics step
overlaps the master's work on tick n. The two processes share one page (commands in, state out) and hand
it over with POSIX semaphores, whose atomic operations order the page's reads and writes; the waiting
side first polls its semaphore (the other side answers within microseconds in a lockstep run), then
blocks. The child polls for a kind of message (a SYNC's samples, its commands) only once its last
:data:`CHILD_SHORT` waits for that kind each ended within the poll (:data:`CHILD_POLL`): paced in real time
the next SYNC comes a period later, and it blocks at once instead of spinning on a CPU for nothing (timing
never changes what is simulated). The serial samples of SYNC n are needed at SYNC n: the child confirms each
emit once its bytes are on the lines (a third semaphore), and the SYNC handler waits for that confirmation
(:meth:`PlantLink.sent`) after its CAN nodes have answered, so that the master's reads after the SYNC find
them however late the child ran (a loaded machine, a stopped process): a lockstep run never depends on timing.
Nothing waits on wall time but the link's own guard against a child that died or hung.
:class:`InProcessPlantLink` makes the same calls in the same order in this process: both links give the same
bytes on every wire for the same seed.
An exception of the core is raised by the next :meth:`collect` in both, and again at every later one.
"""

from __future__ import annotations

import contextlib
import mmap
import multiprocessing
import os
import signal
import struct
import sys
import time
import traceback
from collections.abc import Callable
from typing import Protocol

import numpy as np

from sim_backend.config import Fault
from sim_backend.physics import CablePhysics, SimulationError, _euler, _quat_to_matrix, snapshot_parts

_EMIT = struct.Struct("<q")  # at byte 0: the SYNC count whose serial samples are to go out
_HEADER = struct.Struct("<qq")  # at _COMMAND_AT: operation, SYNC count, then the commands
_COMMAND_AT = 64
_OP_ADVANCE, _OP_STOP = 1, 3
_OK, _FAILED = 0, 1
_STATE_AT = 512  # byte offset of the state block in the shared page
_ERROR_AT = 2048  # byte offset of the error message
_PAGE = 4096
CHILD_POLL = 2e-3  # s the child polls for a message before blocking, once its last CHILD_SHORT waits for that
CHILD_SHORT = 8  # kind each ended sooner (unpaced lockstep); else (paced: a SYNC a period later) it blocks at once
PARENT_POLL = 1e-3  # s the parent polls for the state before blocking
# at byte 8: wall times (perf_counter, s) of a SYNC's hand-over: the parent's emit, the child's wake-up to it, the
# parent's advance, the child's state posted (the link's timing, never the simulation's)
_TIMES = struct.Struct("<4d")
_TIMES_AT = 8
# s without an answer from a living child before the link gives up; the time the child spends stopped (SIGSTOP,
# a debugger) does not count: a stopped plant is late, not broken, and a lockstep run waits for it
ANSWER_TIMEOUT = 30.0


class PlantView:
    """The plant as the CAN nodes see it at a SYNC (implements ``sim_backend.plant.Plant``): the state
    published for this SYNC, and the commands the drives have given since the last one.

    n: cables; state: a :meth:`CablePhysics.snapshot` tuple; torques (n) N m and brakes (n) the commands in
    force; convention: the robot's orientation convention (for :meth:`orientation`)."""

    def __init__(self, n: int, state: tuple[float, ...], torques, brakes, convention: str) -> None:
        self.n = n
        self.convention = convention
        self.torques = [float(x) for x in torques]
        self.brakes = [bool(x) for x in brakes]
        self._parts = snapshot_parts(n)
        self.publish(state)

    def publish(self, state: tuple[float, ...]) -> None:
        """Take the state of a new SYNC (its parts are cut out when asked for)."""
        self.state = state

    @property
    def time(self) -> float:
        """Simulated time of the published state, s."""
        return self.state[0]

    def motor_position(self) -> np.ndarray:
        return np.array(self.state[self._parts["motor_position"]])

    def motor_velocity(self) -> np.ndarray:
        return np.array(self.state[self._parts["motor_velocity"]])

    def motor_torque(self) -> np.ndarray:
        """(n,) the torques commanded, N m (the motors deliver them from the next physics step on)."""
        return np.array(self.torques)

    def set_motor_torque(self, i: int, torque: float) -> None:
        self.torques[i] = float(torque)

    def reader(self, quantity: str, i: int) -> Callable[[], float]:
        """Element ``i`` of ``quantity`` (a per-cable part of the state, or ``motor_torque``), read from the
        state in force at each call (``sim_backend.plant.scalar_reader``): no array per reading."""
        per_cable = quantity == "motor_torque" or quantity in self._parts and quantity not in ("time", "xg", "q")
        if not per_cable or not 0 <= i < self.n:
            raise ValueError(f"PlantView.reader: no per-cable quantity {quantity!r} with cable {i}.")
        if quantity == "motor_torque":
            return lambda: self.torques[i]
        k = self._parts[quantity].start + i
        return lambda: self.state[k]

    def cable_tension(self) -> np.ndarray:
        return np.array(self.state[self._parts["cable_tension"]])

    def swivel_angle(self) -> np.ndarray:
        return np.array(self.state[self._parts["swivel_angle"]])

    def orientation(self) -> np.ndarray:
        return np.array(_euler(_quat_to_matrix(list(self.state[self._parts["q"]])), self.convention))

    def unstretched_lengths(self) -> np.ndarray:
        """(n,) unstretched cable lengths paid out by the winches, m."""
        return np.array(self.state[self._parts["unstretched_lengths"]])

    def set_brake(self, i: int, engaged: bool) -> None:
        """Engage or release the holding brake of winch i (from the next physics step on)."""
        self.brakes[i] = bool(engaged)

    def brake(self, i: int) -> bool:
        return self.brakes[i]


class PlantCore:
    """The physics with the devices that read it on serial lines: the load-cell amplifier and the AHRS
    (``sim_backend.loadcell_emulator``, ``sim_backend.xsens_emulator``), and the faults that act on them.

    physics: at the power-on state; period: s per SYNC; faults: the serial and cable faults, by time."""

    def __init__(self, physics: CablePhysics, loadcells, ahrs, period: float, faults: list[Fault]) -> None:
        self.physics = physics
        self.loadcells = loadcells
        self.ahrs = ahrs
        self.period = float(period)
        self.pending = sorted(faults, key=lambda f: f.t)
        self._line: bytes | None = None  # the load-cell line of the next SYNC

    def start(self) -> None:
        """Let the serial devices answer their hosts' commands (their threads)."""
        self.loadcells.start()
        self.ahrs.start()

    def close(self) -> None:
        for emu in (self.loadcells, self.ahrs):
            emu.close()

    def fds(self) -> list[int]:
        """The file descriptors the core uses (the serial devices' pty masters)."""
        return [self.loadcells.fd, self.ahrs.fd]

    def advance(self, count: int, torques, brakes) -> tuple[float, ...]:
        """Apply the commands given at SYNC ``count`` and step to its next SYNC; returns the new state. The
        faults due then are injected and that SYNC's load-cell line is made (written by :meth:`emit`)."""
        ph = self.physics
        for i, (tq, b) in enumerate(zip(torques, brakes, strict=True)):
            ph.set_motor_torque(i, tq)
            if ph.brake(i) != b:
                ph.set_brake(i, b)
        ph.step(self.period, t_end=(count + 1) * self.period)
        t = ph.time
        while self.pending and self.pending[0].t <= t + 1e-12:
            self._inject(self.pending.pop(0))
        # measured and encoded now, written at the SYNC: the line is on the wire a few microseconds after
        # the SYNC, when the master reads it, and not before
        self._line = self.loadcells.prepare(t, ph._tau_cell)
        return ph.snapshot()

    def emit(self, count: int) -> None:
        """SYNC ``count``: the serial samples of this instant go out (the load-cell line made at the last step,
        the AHRS sample when one is due); :meth:`advance` follows with the SYNC's commands."""
        line, self._line = self._line, None
        if line is not None:
            self.loadcells.send(line)
        ph = self.physics
        t = ph.time
        if self.ahrs.due(t):  # the AHRS samples at its own rate: the angles only for the ticks it sends
            self.ahrs.emit(t, *ph.euler())

    def _inject(self, f: Fault) -> None:
        if f.kind == "loadcell_stuck":
            self.loadcells.stick(f.target)
        elif f.kind == "loadcell_disconnected":
            self.loadcells.disconnect()
        elif f.kind == "ahrs_corrupt":
            self.ahrs.corrupt(f.n_bytes)
        elif f.kind == "cable_slack":
            self.physics.slip_cable(f.target, f.length)


class Durations:
    """The last ``size`` values of a duration (s), kept in a preallocated array (no object per value)."""

    def __init__(self, size: int = 1 << 16) -> None:
        self.values = np.zeros(size)
        self.count = 0

    def add(self, value: float) -> None:
        self.values[self.count % len(self.values)] = value
        self.count += 1

    def summary(self) -> dict[str, float]:
        """``count`` (all added) and the p50, p99 and worst of those kept, ms."""
        v = self.values[:min(self.count, len(self.values))]
        if not len(v):
            return {"count": 0}
        p50, p99 = np.percentile(v, [50, 99])
        return {"count": self.count, "p50_ms": 1e3 * p50, "p99_ms": 1e3 * p99, "worst_ms": 1e3 * float(v.max())}


class PlantLink(Protocol):
    """Hands the commands of a SYNC to a :class:`PlantCore` and brings back the state of the next one."""

    def emit(self, count: int) -> None:
        """SYNC ``count``: the core's :meth:`PlantCore.emit` (returns at once)."""

    def sent(self, count: int) -> None:
        """Return once the serial samples of the last :meth:`emit` (SYNC ``count``) are on their lines: a
        driver reading its port after this finds them. A child that died or hung leaves the reason for the
        next :meth:`collect` and returns."""

    def advance(self, count: int, torques, brakes) -> None:
        """The core's :meth:`PlantCore.advance` with the commands of SYNC ``count`` (returns at once); at
        power-on (``count`` 0) without an emit before it."""

    def collect(self) -> tuple[float, ...]:
        """The state the last call produced (raises ``SimulationError`` if the core failed)."""

    def close(self) -> None:
        """Stop the core and its serial devices (safe to call twice)."""


class InProcessPlantLink:
    """The core run in this process, at the same points of the SYNC as in the child."""

    def __init__(self, core: PlantCore) -> None:
        self.core = core
        self._state: tuple[float, ...] | None = None
        self._error: str | None = None
        core.start()

    def emit(self, count: int) -> None:
        if self._error is None:
            try:
                self.core.emit(count)
            except Exception as exc:  # as the child reports it: raised at the next collect
                self._error = _reason(exc)

    def sent(self, count: int) -> None:
        """Nothing to wait for: :meth:`emit` wrote the samples."""

    def advance(self, count: int, torques, brakes) -> None:
        if self._error is None:
            try:
                self._state = self.core.advance(count, torques, brakes)
            except Exception as exc:
                self._error = _reason(exc)

    def collect(self) -> tuple[float, ...]:
        if self._error is not None:
            raise SimulationError(self._error)
        return self._state

    def close(self) -> None:
        self.core.close()


def cores_available() -> int:
    """CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def child_process_possible() -> bool:
    """Whether a :class:`ChildPlantLink` can run here: Linux (a fork without exec is safe there; macOS's
    system libraries are not fork-safe) and a second core to run it on."""
    return sys.platform.startswith("linux") and cores_available() >= 2


class ChildPlantLink:
    """The core in a forked child process, on the other core; see the module docstring for the protocol.

    The child keeps only the file descriptors the core needs (its ptys, and stdin, stdout and stderr): a pipe
    the parent holds to some other child must see its end when the parent closes it. It ignores SIGINT
    (Ctrl-C stops the run in the parent, which then closes the link) and exits when the parent does.
    ``pid`` is the child's process ID."""

    def __init__(self, core: PlantCore) -> None:
        n = core.physics.n
        self._command = struct.Struct(f"<{n}d{n}?")
        self._state = struct.Struct(f"<q{snapshot_parts(n)['q'].stop}d")  # status, then the snapshot
        self._page = mmap.mmap(-1, _PAGE)  # anonymous and shared: the child sees the same page
        _EMIT.pack_into(self._page, 0, -1)
        ctx = multiprocessing.get_context("fork")
        self._to_child = ctx.Semaphore(0)
        self._to_parent = ctx.Semaphore(0)  # the state (or the error) after an advance
        self._emitted = ctx.Semaphore(0)  # a SYNC's serial samples are on their lines
        self._error: str | None = None
        self._closed = False
        self._waiting = False  # a command is out and its answer not yet collected
        self._unsent: int | None = None  # the SYNC whose emit is out and not yet confirmed
        self._exit: int | None = None  # the child's wait status once reaped
        self.waited = 0.0  # s the parent spent waiting for the child's answers (beyond a first look)
        # per SYNC, s: the emit to the child running, the wait in sent, the advance to the state posted, the wait
        # for the state (SimBackend.plant_timing)
        self.timing = {k: Durations() for k in ("wake", "confirm", "step", "collect")}
        parent = os.getpid()
        keep = sorted({0, 1, 2, *core.fds()})
        self.pid = os.fork()
        if self.pid == 0:  # the child: never returns
            code = 1
            try:
                _close_fds_but(keep)
                _child_main(core, self._page, (self._to_child, self._to_parent, self._emitted), parent,
                            self._command, self._state)
                code = 0
            except BaseException:
                with contextlib.suppress(BaseException):
                    traceback.print_exc()
            finally:
                os._exit(code)

    def emit(self, count: int) -> None:
        if self._error is not None or self._closed:
            return
        if self._waiting:  # the previous answer was never collected: take it now, in order
            self._receive()
        if self._unsent is not None:  # nor the last emit's confirmation: one confirmation per emit
            self.sent(self._unsent)
        if self._error is not None:
            return
        _EMIT.pack_into(self._page, 0, count)
        struct.pack_into("<d", self._page, _TIMES_AT, time.perf_counter())
        self._unsent = count
        self._to_child.release()

    def sent(self, count: int) -> None:
        if self._unsent != count or self._error is not None or self._closed:
            return
        self._unsent = None
        start = time.perf_counter()
        if self._await(self._emitted, f"the serial samples of SYNC {count}"):
            posted, woke, _, _ = _TIMES.unpack_from(self._page, _TIMES_AT)
            self.timing["confirm"].add(time.perf_counter() - start)
            self.timing["wake"].add(woke - posted)

    def advance(self, count: int, torques, brakes) -> None:
        if self._error is not None or self._closed:
            return
        if self._waiting:
            self._receive()
        _HEADER.pack_into(self._page, _COMMAND_AT, _OP_ADVANCE, count)
        self._command.pack_into(self._page, _COMMAND_AT + _HEADER.size, *torques, *brakes)
        struct.pack_into("<d", self._page, _TIMES_AT + 16, time.perf_counter())
        self._waiting = True
        self._to_child.release()

    def _await(self, sem, what: str) -> bool:
        """Take ``sem`` (the child's answer: ``what``), polling first, then blocking; False (with the reason in
        ``_error``) if the child died or fell silent."""
        if sem.acquire(False):
            return True
        start = time.perf_counter()
        end = start + PARENT_POLL
        try:
            while not sem.acquire(False):
                if time.perf_counter() > end:
                    return self._block(sem, what)
        finally:
            self.waited += time.perf_counter() - start
        return True

    def _receive(self) -> None:
        self._waiting = False
        start = time.perf_counter()
        if not self._await(self._to_parent, "the state of the next SYNC"):
            return
        self.timing["collect"].add(time.perf_counter() - start)
        _, _, posted, done = _TIMES.unpack_from(self._page, _TIMES_AT)
        self.timing["step"].add(done - posted)
        block = self._state.unpack_from(self._page, _STATE_AT)  # status, then the state
        if block[0] != _OK:
            (size,) = struct.unpack_from("<q", self._page, _ERROR_AT)
            self._error = bytes(self._page[_ERROR_AT + 8:_ERROR_AT + 8 + size]).decode("utf-8", "replace")
        else:
            self._last = block[1:]

    def alive(self) -> bool:
        """Whether the child still runs (reaps it once it has ended)."""
        if self._exit is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid == 0:
                return True
            self._exit = status
        return False

    def _block(self, sem, what: str) -> bool:
        """Wait for the child's answer (``what``); False (with the reason in ``_error``) if it died or fell
        silent."""
        waited = 0.0
        while not sem.acquire(True, 0.1):
            waited += 0.0 if _stopped(self.pid) else 0.1
            if not self.alive():
                self._error = (f"the simulated plant's process (pid {self.pid}) ended "
                               f"({_describe(self._exit)}) without sending {what}")
                return False
            if waited >= ANSWER_TIMEOUT:
                self._error = (f"the simulated plant's process (pid {self.pid}) did not send {what} in "
                               f"{waited:.0f} s")
                return False
        return True

    def collect(self) -> tuple[float, ...]:
        if self._waiting and self._error is None:
            self._receive()
        if self._error is not None:
            raise SimulationError(self._error)
        return self._last

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.alive():
            with contextlib.suppress(Exception):
                if self._waiting and self._error is None:
                    self._receive()
                _HEADER.pack_into(self._page, _COMMAND_AT, _OP_STOP, 0)
                self._to_child.release()
            end = time.monotonic() + 5.0
            while self.alive() and time.monotonic() < end:
                time.sleep(0.005)
            if self.alive():
                os.kill(self.pid, signal.SIGKILL)
                os.waitpid(self.pid, 0)
        self._page.close()


def _reason(exc: Exception) -> str:
    """The message a failure of the core is raised with (a ``SimulationError`` keeps its own)."""
    return str(exc) if isinstance(exc, SimulationError) else f"{type(exc).__name__}: {exc}"


def _stopped(pid: int) -> bool:
    """Whether process ``pid`` is stopped (by a signal or a tracer; Linux's /proc, else False)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return False
    return stat[stat.rfind(b")") + 2:][:1] in (b"T", b"t")


def _describe(status: int | None) -> str:
    if status is None:
        return "status unknown"
    if os.WIFSIGNALED(status):
        return f"killed by signal {os.WTERMSIG(status)}"
    return f"exit code {os.waitstatus_to_exitcode(status)}"


def _close_fds_but(keep: list[int]) -> None:
    """Close every file descriptor of this process except ``keep`` (sorted)."""
    lo = 0
    for fd in keep:
        if fd > lo:
            os.closerange(lo, fd)
        lo = fd + 1
    os.closerange(lo, os.sysconf("SC_OPEN_MAX"))  # one close_range call on Linux


def _child_main(core: PlantCore, page: mmap.mmap, sems: tuple, parent: int, command: struct.Struct,
                state: struct.Struct) -> None:
    """The child's loop: wait for a message; a new emit count sends that SYNC's serial samples and confirms
    them, otherwise the command block is read: advance the core and post the state (or the error), or stop.
    ``sems``: (to the child, the state to the parent, the samples sent)."""
    to_child, to_parent, sent = sems
    # waits in a row that ended within CHILD_POLL, by what they waited for (a SYNC's samples, its commands)
    short, awaited = [0, 0], 0
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it stops the run and closes us
    sys.setswitchinterval(1e-4)  # the serial devices' threads get the interpreter soon while this one polls
    core.start()
    failed = False
    emitted = -1

    def fail(exc: Exception) -> None:
        msg = _reason(exc).encode()[:_PAGE - _ERROR_AT - 8]
        struct.pack_into("<q", page, _STATE_AT, _FAILED)
        struct.pack_into(f"<q{len(msg)}s", page, _ERROR_AT, len(msg), msg)

    try:
        while True:
            start = time.perf_counter()
            if not _wait_for_command(to_child, parent, CHILD_POLL if short[awaited] >= CHILD_SHORT else 0.0):
                break
            woke = time.perf_counter()
            # a poll that runs out (a paced run's next SYNC comes a period later) costs a busy CPU and answers no
            # sooner than a block
            short[awaited] = short[awaited] + 1 if woke - start < CHILD_POLL else 0
            (count,) = _EMIT.unpack_from(page, 0)
            if count != emitted:  # a SYNC: its samples first; its commands come with the next message
                awaited = 1
                struct.pack_into("<d", page, _TIMES_AT + 8, woke)
                emitted = count
                if not failed:
                    try:
                        core.emit(count)
                    except Exception as exc:  # reported with the answer to the SYNC's commands
                        failed = True
                        fail(exc)
                sent.release()  # the bytes are in the lines' buffers (or the failure is on the page)
                continue
            awaited = 0
            op, count = _HEADER.unpack_from(page, _COMMAND_AT)
            if op == _OP_STOP:
                break
            if not failed:
                values = command.unpack_from(page, _COMMAND_AT + _HEADER.size)
                n = len(values) // 2
                try:
                    state.pack_into(page, _STATE_AT, _OK, *core.advance(count, values[:n], values[n:]))
                except Exception as exc:
                    failed = True
                    fail(exc)
            struct.pack_into("<d", page, _TIMES_AT + 24, time.perf_counter())
            to_parent.release()
    finally:
        core.close()


def _wait_for_command(sem, parent: int, poll: float) -> bool:
    """Poll for ``poll`` s, then block for the next command; False when the parent has gone."""
    if sem.acquire(False):
        return True
    end = time.perf_counter() + poll
    while time.perf_counter() < end:
        for _ in range(64):
            if sem.acquire(False):
                return True
    while not sem.acquire(True, 0.1):
        if os.getppid() != parent:
            return False
    return True
