"""The run's own solve of a sequential startup (:func:`calib.sequential.run_estimate`), computed beside the
control loop: in a worker process on a real clock, in line in lockstep."""

from __future__ import annotations

from collections.abc import Callable

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
