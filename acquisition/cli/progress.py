"""The progress of a long command (diagnose, workspace): a tqdm bar on a terminal, plain lines when stderr is
redirected (a log gets one line per tenth of the work), nothing once the work is done."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """``update(done[, total])`` with ``done`` of ``total`` units (positions, fits); ``close()`` at the end."""

    def __init__(self, total: int, what: str, unit: str, stream: TextIO | None = None, tty: bool | None = None):
        self.stream = stream if stream is not None else sys.stderr
        self.total, self.what, self.unit = max(int(total), 1), what, unit
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)()) if tty is None else tty
        self._bar = None
        self._next_line = 0.1  # fraction of the work at which the next plain line is written
        self._t0 = time.monotonic()
        if self.tty:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=what, unit=f" {unit}", file=self.stream, leave=False,
                             dynamic_ncols=True)

    def update(self, done: int, total: int | None = None) -> None:
        if total is not None:
            self.total = max(int(total), 1)
            if self._bar is not None:
                self._bar.total = self.total
        done = min(int(done), self.total)
        if self._bar is not None:
            self._bar.update(done - self._bar.n)
            return
        frac = done / self.total
        if frac + 1e-12 >= self._next_line:
            elapsed = time.monotonic() - self._t0
            self.stream.write(f"cdpr: {self.what}: {done}/{self.total} {self.unit} ({100 * frac:.0f}%, "
                              f"{elapsed:.0f} s)\n")
            self.stream.flush()
            self._next_line = (int(frac * 10 + 1e-9) + 1) / 10

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Activity:
    """A long step whose amount of work is not known beforehand (a diagnosis: fits until the selection stops):
    on a terminal a tqdm line counting the seconds while it runs; redirected, a plain line every ``every``
    seconds and one when it ends, so that a step that ends (or fails) sooner writes nothing. A context
    manager."""

    def __init__(self, what: str, stream: TextIO | None = None, tty: bool | None = None, every: float = 5.0):
        self.stream = stream if stream is not None else sys.stderr
        self.what, self.every = what, every
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)()) if tty is None else tty
        self._lines = 0

    def __enter__(self) -> Activity:
        import threading

        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._bar if self.tty else self._plain, daemon=True)
        self._thread.start()
        return self

    def _bar(self) -> None:
        from tqdm import tqdm

        with tqdm(desc=self.what, total=None, file=self.stream, leave=False, bar_format="{desc}: {elapsed}") as bar:
            while not self._stop.wait(0.5):
                bar.refresh()

    def _plain(self) -> None:
        while not self._stop.wait(self.every):
            self.stream.write(f"cdpr: {self.what}: {time.monotonic() - self._t0:.0f} s\n")
            self.stream.flush()
            self._lines += 1

    def __exit__(self, exc_type, *exc) -> None:
        self._stop.set()
        self._thread.join()
        if self._lines and exc_type is None:
            self.stream.write(f"cdpr: {self.what}: done in {time.monotonic() - self._t0:.0f} s\n")
            self.stream.flush()
