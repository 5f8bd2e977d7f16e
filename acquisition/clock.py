"""The control loop's clock: real (wall time, sleep to the next period) or simulated (lockstep ticks).

A clock hands out ticks: ``advance()`` returns the index of the next tick and its time since the start (s).
``lockstep`` says whether the loop must wait for the readings answering this tick's SYNC (simulated
prototype: deterministic) or take the latest readings (real robot). Both clocks send nothing themselves: the
device set sends SYNC at each tick.
"""

from __future__ import annotations

import abc
import gc
import importlib
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

LOOP_SWITCH_INTERVAL = 0.0005  # s, sys.setswitchinterval while a control loop runs (CPython's default: 0.005)
# modules a library imports on first use that the loop would otherwise import inside a tick: numpy.ma, which
# numpy imports at the first np.median (its NaN check), 10-25 ms in the tick that ends the pretension's rest
LOOP_IMPORTS = ("numpy.ma",)


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
    (``cdpr startup --backend sim --realtime``).
    """

    def __init__(
        self,
        period: float,
        lockstep: bool = False,
        monotonic: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        super().__init__(period)
        self._lockstep = lockstep
        self._monotonic = monotonic
        self._sleep = sleep
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
            self._sleep(deadline - now)
        elif self._index >= 0 and now - deadline > 0.5 * self.period:  # not the first tick
            lateness = now - deadline
            self.overruns.count += 1
            self.overruns.worst = max(self.overruns.worst, lateness)
        return self._hand_out()

    def elapsed(self) -> float:
        """Wall time since start, s."""
        return 0.0 if self._t0 is None else self._monotonic() - self._t0


@contextmanager
def loop_runtime(switch_interval: float = LOOP_SWITCH_INTERVAL) -> Iterator[None]:
    """The interpreter set up for a control loop, restored on exit.

    Collects once and freezes what exists (``gc.freeze``): the cyclic collector then never walks the
    interpreter's, numpy's, scipy's, canopen's... tens of thousands of long-lived objects inside the loop (a
    full collection of them took 40-100 ms in one tick at 200 Hz; the young objects the loop makes are
    collected as before). The thread switch interval is ``switch_interval`` s, so that the loop's thread,
    waking from its sleep or from a device wait, waits at most about that long for another thread (a live
    view's publisher, a run-log writer) to give up the interpreter. The modules of :data:`LOOP_IMPORTS` are
    imported first (and frozen with the rest). Nested use is harmless."""
    for name in LOOP_IMPORTS:
        importlib.import_module(name)
    frozen = gc.get_freeze_count() == 0
    switch = sys.getswitchinterval()
    if frozen:
        gc.collect()
        gc.freeze()
    sys.setswitchinterval(min(switch, switch_interval))
    try:
        yield
    finally:
        sys.setswitchinterval(switch)
        if frozen:
            gc.unfreeze()
