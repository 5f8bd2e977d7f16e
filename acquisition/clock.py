"""The control loop's clock: real (wall time, sleep to the next period) or simulated (lockstep ticks).

A clock hands out ticks: ``advance()`` returns the index of the next tick and its time since the start (s).
``lockstep`` says whether the loop must wait for the readings answering this tick's SYNC (simulated
prototype: deterministic) or take the latest readings (real robot). Both clocks send nothing themselves: the
device set sends SYNC at each tick.
"""

from __future__ import annotations

import abc
import contextlib
import ctypes
import gc
import importlib
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

LOOP_SWITCH_INTERVAL = 0.0005  # s, sys.setswitchinterval while a control loop runs (CPython's default: 0.005)
# modules a library imports on first use that the loop would otherwise import inside a tick: numpy.ma, which
# numpy imports at the first np.median (its NaN check), 10-25 ms in the tick that ends the pretension's rest
LOOP_IMPORTS = ("numpy.ma",)
# ns, the loop thread's timer slack while it runs (Linux's default for a thread of normal priority: 50 000 ns, by
# which the kernel may defer a sleep's end to merge wake-ups; a SCHED_FIFO thread has none): the sleep to each
# tick ends when asked (p50 lateness 0.05 ms instead of 0.1 ms at normal priority, docs/live.md)
LOOP_TIMER_SLACK = 1
_PR_SET_TIMERSLACK, _PR_GET_TIMERSLACK = 29, 30  # prctl(2) options (linux/prctl.h)
# bytes of heap the loop's thread faults in before the loop and keeps (no trim): numpy's temporaries, the logged
# rows and the detector's refresh then reuse resident pages instead of faulting fresh ones in a tick
LOOP_HEAP_RESERVE = 64 << 20
_MCL_CURRENT, _MCL_FUTURE = 1, 2  # mlockall(2) flags (sys/mman.h)
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4  # mallopt(3) parameters (malloc.h)
_TRIM_DEFAULT, _MMAP_MAX_DEFAULT = 128 * 1024, 65536  # glibc's defaults, restored after the loop
_CAP_IPC_LOCK = 14  # capability(7) bit: lock memory beyond RLIMIT_MEMLOCK


@dataclass(frozen=True)
class Tick:
    index: int  # 0 for the first tick after start()
    t: float  # s since start() on this clock's time base


class Clock(abc.ABC):
    """Ticks every ``period`` seconds of this clock's time."""

    def __init__(self, period: float):
        if not period > 0:
            raise ValueError(f"clock period must be positive, got {period!r} s.")
        self.period = float(period)
        self._index = -1
        self._now = 0.0  # time of the last tick handed out (0 before the first)

    @property
    @abc.abstractmethod
    def lockstep(self) -> bool:
        """True when every tick's readings must be awaited (deterministic simulation)."""

    @property
    def paced(self) -> bool:
        """True when ticks follow wall time (the robot, or a simulated prototype paced in real time): work that
        may take longer than a period goes off the loop's thread there; the simulated clock runs it in line."""
        return not isinstance(self, SimClock)

    @abc.abstractmethod
    def advance(self) -> Tick:
        """Wait for the next tick and return it."""

    @property
    def index(self) -> int:
        """Index of the last tick handed out (-1 before the first)."""
        return self._index

    def now(self) -> float:
        """Time of the last tick, s (read by every device driver at every tick: kept, not computed)."""
        return self._now

    def _hand_out(self) -> Tick:
        """The next tick: index and time advanced together."""
        self._index += 1
        self._now = t = self._index * self.period
        return Tick(self._index, t)


class SimClock(Clock):
    """Simulated time: each tick is one control period later; nothing sleeps (the simulator is in lockstep)."""

    @property
    def lockstep(self) -> bool:
        return True

    def advance(self) -> Tick:
        return self._hand_out()


@dataclass
class Overruns:
    """Ticks whose deadline had passed when the loop asked for them, and the worst lateness (s)."""

    count: int = 0
    worst: float = 0.0


class RealClock(Clock):
    """Wall time: ``advance`` sleeps until start + (index + 1) period; late ticks are counted, not skipped.

    ``lockstep=True`` paces a simulated prototype in real time while still waiting for each tick's readings
    (``cdpr startup --backend sim --realtime``). ``spin`` (s, default 0: off) is the hybrid wait of real-time
    loops in user space: sleep until ``spin`` before the deadline, then poll the clock until it passes, which
    trades the OS's wake-up error (measured here under SCHED_FIFO: p99 0.09 ms, worst 0.2-1.8 ms) for the CPU of
    the poll (1 ms at 200 Hz: a fifth of a core). An overrun is half a period late, so the loop does not need it
    (docs/live.md: measured with and without); at normal priority the poll is preempted and makes it worse.
    """

    def __init__(
        self,
        period: float,
        lockstep: bool = False,
        monotonic: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        spin: float = 0.0,
    ):
        super().__init__(period)
        if not 0.0 <= spin < period:
            raise ValueError(f"clock spin must be within [0, period = {period!r}) s, got {spin!r} s.")
        self._lockstep = lockstep
        self._monotonic = monotonic
        self._sleep = sleep
        self.spin = float(spin)
        self._t0: float | None = None
        self.overruns = Overruns()

    @property
    def lockstep(self) -> bool:
        return self._lockstep

    def start(self) -> None:
        """Set time zero to now (called by the first ``advance`` if not called before)."""
        self._t0 = self._monotonic()

    def advance(self) -> Tick:
        if self._t0 is None:
            self.start()
        deadline = self._t0 + (self._index + 1) * self.period
        now = self._monotonic()
        if now < deadline:
            if deadline - now > self.spin:
                self._sleep(deadline - now - self.spin)
            if self.spin > 0.0:
                while self._monotonic() < deadline:
                    pass
        elif self._index >= 0 and now - deadline > 0.5 * self.period:  # not the first tick
            lateness = now - deadline
            self.overruns.count += 1
            self.overruns.worst = max(self.overruns.worst, lateness)
        return self._hand_out()

    def elapsed(self) -> float:
        """Wall time since start, s."""
        return 0.0 if self._t0 is None else self._monotonic() - self._t0


# the cyclic collector's thresholds while a control loop runs: the young generations as CPython's defaults (a
# collection of generation 0 or 1 walks at most a few thousand young objects: well under a millisecond), the
# oldest never collected automatically
LOOP_GC_OLDEST = 2**31 - 1


def set_realtime(priority: int, pid: int = 0) -> str | None:
    """Ask the OS to run under ``SCHED_FIFO`` at ``priority`` (1-99), with ``SCHED_RESET_ON_FORK`` (no process
    forked from it inherits it): the calling thread (``pid`` 0), or every thread of process ``pid`` (a thread one
    of them starts later inherits it); None when granted, else the one sentence saying why not (Linux only;
    needs root, CAP_SYS_NICE or an rtprio limit, ``ulimit -r``). Every thread of a Python process that shares
    the interpreter lock with a real-time thread should be real-time too: a thread of normal priority that holds
    the lock when a process of normal priority preempts it keeps the real-time one waiting (bench_live.py)."""
    if not hasattr(os, "SCHED_FIFO"):
        return f"real-time priority {priority} is not available on {sys.platform}; the loop runs at normal priority."
    try:
        for tid in [0] if pid == 0 else _threads(pid):
            os.sched_setscheduler(tid, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(int(priority)))
    except OSError as exc:  # EPERM without the right, EINVAL out of range
        return (f"real-time priority {priority} (SCHED_FIFO) was refused ({exc.strerror}); the loop runs at normal "
                f"priority (grant it with an rtprio limit, e.g. ulimit -r {priority}).")
    return None


def raise_lock_sharers(priority: int) -> list[tuple[int, int, os.sched_param]]:
    """Every other thread of this process under ``SCHED_FIFO`` at ``priority`` (they share the interpreter lock
    with the calling real-time thread: the run log's worker, python-can's notifier that receives every CAN frame
    on the robot, a serial reader); returns (thread ID, policy, parameter) of each raised, to restore with
    :func:`restore_threads`. A thread the OS refuses or that has ended is left out."""
    me, raised = threading.get_native_id(), []
    for tid in _threads(os.getpid()):
        if tid == me:
            continue
        try:
            old = (tid, os.sched_getscheduler(tid), os.sched_getparam(tid))
            os.sched_setscheduler(tid, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(int(priority)))
        except OSError:
            continue
        raised.append(old)
    return raised


def restore_threads(saved: list[tuple[int, int, os.sched_param]]) -> None:
    """Give each thread of ``saved`` (:func:`raise_lock_sharers`) its policy back (an ended one is skipped)."""
    for tid, policy, param in saved:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(tid, policy, param)


def _threads(pid: int) -> list[int]:
    """The thread IDs of process ``pid`` (Linux's /proc; the process itself elsewhere), read twice so that a
    thread started meanwhile is in."""
    try:
        first = os.listdir(f"/proc/{pid}/task")
        return sorted({int(t) for t in first + os.listdir(f"/proc/{pid}/task")})
    except OSError:
        return [pid]


def _prctl() -> Callable[..., int] | None:
    """libc's prctl (Linux), None elsewhere."""
    libc = _libc()
    return None if libc is None else getattr(libc, "prctl", None)


def set_timer_slack(ns: int) -> int | None:
    """Set the calling thread's timer slack to ``ns`` (Linux's ``PR_SET_TIMERSLACK``; 0 restores the thread's
    default); returns the slack it had (ns), or None where there is none to set."""
    prctl = _prctl()
    if prctl is None:
        return None
    old = prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0)
    if old < 0 or prctl(_PR_SET_TIMERSLACK, int(ns), 0, 0, 0) != 0:
        return None
    return int(old)


def _libc() -> ctypes.CDLL | None:
    """The C library (Linux), None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None


def _may_lock_all() -> str | None:
    """None when this process may lock all its memory, now and future (RLIMIT_MEMLOCK unlimited, or
    CAP_IPC_LOCK), else the reason in a few words."""
    import resource

    soft = resource.getrlimit(resource.RLIMIT_MEMLOCK)[0]
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/status") as f:
            caps = next((line.split()[1] for line in f if line.startswith("CapEff:")), "0")
        if int(caps, 16) >> _CAP_IPC_LOCK & 1:
            return None
    except (OSError, ValueError):
        pass
    return f"RLIMIT_MEMLOCK is {soft // 1024} KiB, not unlimited, and no CAP_IPC_LOCK"


def lock_memory(reserve: int = LOOP_HEAP_RESERVE) -> str | None:
    """Keep the process's memory resident for a real-time loop (the practice of real-time Linux: a page fault
    or the memory compaction behind it can stall a thread for tens of ms): malloc keeps what is freed (no
    trim) and takes large blocks from the heap too (no mmap per numpy array), ``reserve`` bytes of heap are
    faulted in by the calling thread and kept, then ``mlockall(MCL_CURRENT | MCL_FUTURE)`` (every page mapped
    now, and later at its mapping). None when done, else the one sentence saying why not (Linux with glibc;
    needs ``ulimit -l unlimited`` or CAP_IPC_LOCK: with a finite limit a later allocation would fail)."""
    libc = _libc()
    why = "memory locking is available only on Linux" if libc is None else _may_lock_all()
    if why is None:
        libc.malloc.restype = ctypes.c_void_p
        libc.free.argtypes = [ctypes.c_void_p]
        libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)
        libc.mallopt(_M_MMAP_MAX, 0)
        block = libc.malloc(ctypes.c_size_t(reserve))
        if block:
            ctypes.memset(block, 1, reserve)  # every page of it faulted in, then back to malloc's free list
            libc.free(block)
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0:
            return None
        why = os.strerror(ctypes.get_errno())
        unlock_memory()
    return (f"memory locking (mlockall) was not done ({why}); the loop's memory may page-fault (allow it with "
            f"ulimit -l unlimited).")


def unlock_memory() -> None:
    """Undo :func:`lock_memory`: ``munlockall`` and glibc's default trim and mmap settings."""
    libc = _libc()
    if libc is not None:
        libc.munlockall()
        libc.mallopt(_M_MMAP_MAX, _MMAP_MAX_DEFAULT)
        libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_DEFAULT)


@contextmanager
def loop_runtime(switch_interval: float = LOOP_SWITCH_INTERVAL, rt_priority: int | None = None,
                 lock: bool = False) -> Iterator[bool]:
    """The interpreter set up for a control loop, restored on exit; yields whether the loop's thread runs under
    real-time priority.

    The garbage collector's policy for the loop: collect once and freeze what exists (``gc.freeze``: the
    interpreter's, numpy's, scipy's, canopen's... tens of thousands of long-lived objects are never walked
    again; a full collection of them took 40-100 ms in one tick at 200 Hz), and no automatic collection of the
    oldest generation while the loop runs (its threshold :data:`LOOP_GC_OLDEST`): the objects the loop keeps
    (the logged rows, the truth record, the windows) accumulate there, and in a long run an automatic full
    collection of them would fall inside one tick (an 8-pose startup keeps too few to start one even at
    CPython's default threshold: bench_live.py's probe; docs/live.md). The young generations are
    collected as before, so garbage the loop makes and drops is freed within a few hundred allocations; a
    cycle that lives long enough to be promoted waits for the first full collection after the loop.

    The thread switch interval is ``switch_interval`` s, so that the loop's thread, waking from its sleep or
    from a device wait, waits at most about that long for another thread (a run-log writer) to give up the
    interpreter. The modules of :data:`LOOP_IMPORTS` are imported first (and frozen with the rest). Nested
    use is harmless (only the outermost sets up and restores).

    ``rt_priority`` (opt-in, for a loop paced by a real clock): the calling thread runs under ``SCHED_FIFO`` at
    that priority (:func:`set_realtime`), so that no process of normal priority keeps it waiting for a CPU, and
    every other thread of the process one priority below it (:func:`raise_lock_sharers`: a thread of normal
    priority preempted while it holds the interpreter lock would keep the loop waiting), all restored on exit;
    where the OS refuses, a warning says so in one sentence and the loop runs as without it. The calling thread's
    timer slack is :data:`LOOP_TIMER_SLACK` meanwhile (:func:`set_timer_slack`). ``lock``: the process's
    memory is locked and a heap reserve faulted in meanwhile (:func:`lock_memory`; refused, a warning)."""
    for name in LOOP_IMPORTS:
        importlib.import_module(name)
    outer = gc.get_freeze_count() == 0
    switch = sys.getswitchinterval()
    thresholds = gc.get_threshold()
    if outer:
        gc.collect()
        gc.freeze()
        gc.set_threshold(thresholds[0], thresholds[1], LOOP_GC_OLDEST)
    sys.setswitchinterval(min(switch, switch_interval))
    policy = os.sched_getscheduler(0) if rt_priority is not None and hasattr(os, "sched_getscheduler") else None
    param = os.sched_getparam(0) if policy is not None else None
    refused = None if rt_priority is None else set_realtime(rt_priority)
    if refused is not None:
        logging.getLogger(__name__).warning(refused)
    realtime = rt_priority is not None and refused is None
    sharers = raise_lock_sharers(max(1, rt_priority - 1)) if realtime else []
    unlocked = lock_memory() if lock else "not asked"
    if lock and unlocked is not None:
        logging.getLogger(__name__).warning(unlocked)
    slack = set_timer_slack(LOOP_TIMER_SLACK)
    try:
        yield realtime
    finally:
        if unlocked is None:
            unlock_memory()
        if slack is not None:
            set_timer_slack(slack)
        sys.setswitchinterval(switch)
        if realtime:
            restore_threads(sharers)
            os.sched_setscheduler(0, policy, param)
        if outer:
            gc.set_threshold(*thresholds)
            gc.unfreeze()
