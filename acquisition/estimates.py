"""Work beside the control loop: the run's own solve of a sequential startup (:func:`calib.sequential.run_estimate`,
in a worker process on a real clock, in line in lockstep) and the run log's slow file system calls
(:class:`LogWorker`, on a thread)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from calib.sequential import run_estimate

ESTIMATE_TIMEOUT = 30.0  # s the platform is held at most while the run's own solve computes on a real clock


def _ignore_interrupts() -> None:
    """In the estimate worker: SIGINT and SIGTERM are the routine's (its safe stop), not the worker's."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


class EstimateWorker:
    """The run's own solve (:func:`run_estimate`) of a sequential startup. On a real clock it is computed in a
    worker process while the control loop keeps ticking at the held tensions (the drives keep their SYNC, the
    supervisor its readings; the solve of a long run takes a second or more); in lockstep (the simulated
    prototype, which waits for every tick) in line, which keeps the run deterministic."""

    def __init__(self, lockstep: bool):
        self.lockstep = lockstep
        self._pool = None

    def compute(self, args: tuple, tick: Callable[[], object], now: Callable[[], float],
                timeout: float = ESTIMATE_TIMEOUT):
        """run_estimate(*args); on a real clock ``tick()`` is called until it is ready (None after ``timeout``
        s of ``now()`` or if the worker died)."""
        if self.lockstep:
            return run_estimate(*args)
        from concurrent.futures.process import BrokenProcessPool

        if self._pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            # spawned, not forked: the process has the bus's threads running; Ctrl-C is the routine's to handle
            self._pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=_ignore_interrupts)
        future = self._pool.submit(run_estimate, *args)
        t0 = now()
        while not future.done():
            if now() - t0 > timeout:
                future.cancel()
                return None
            tick()
        try:
            return future.result()
        except BrokenProcessPool:
            self._pool = None
            return None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None


class LogWorker:
    """The run log's slow calls off the control loop's thread: creating the run folder and run.yaml, the fsync
    at each window, run.yaml's rewrites (a sequential plan's setpoints, an event) and the final close, each a
    yaml dump and an fsync (10-15 ms of interpreter time on the lab PC, more on a slow disk), and on a real
    clock the equilibrium detector's refresh of its thresholds (acquisition/equilibrium.py). One thread
    does them in the order they are asked for; on a real clock it also writes and flushes each samples.csv
    line (a write can wait for the file system's journal), on the simulated clock the loop writes them itself.
    A failure is raised by the next :meth:`submit` or by :meth:`close`."""

    def __init__(self) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="cdpr-runlog")
        self._pool.submit(int).result()  # its thread started now, not by the first call (in a tick: 5-9 ms)
        self._pending: list = []

    def submit(self, fn: Callable[..., Any], *args: Any):
        """Run ``fn(*args)`` after what was submitted before; its Future."""
        self._check()
        future = self._pool.submit(fn, *args)
        self._pending.append(future)
        return future

    def _check(self) -> None:
        done = [f for f in self._pending if f.done()]
        self._pending = [f for f in self._pending if not f.done()]
        for f in done:
            f.result()  # raises what the call raised

    def close(self) -> None:
        """Wait for every call submitted; raise the first failure."""
        self._pool.shutdown(wait=True)
        pending, self._pending = self._pending, []
        for f in pending:
            f.result()
