"""The progress line of a startup (and of a study): phase, setpoint, elapsed robot time and the time left."""

from __future__ import annotations

import math
import sys
import time
from typing import TextIO


class ProgressBar:
    """One self-rewriting line on a terminal: phase, setpoint, elapsed robot time and the time left.

    Silent when the stream is not a TTY (logs and pipes get the final summary only).
    """

    def __init__(self, total: float, stream: TextIO | None = None, width: int = 28, min_interval: float = 0.1,
                 enabled: bool | None = None):
        self.stream = stream if stream is not None else sys.stderr
        self.total = max(float(total), 1e-9)
        self.width = width
        self.min_interval = min_interval
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)()) if enabled is None else enabled
        self._last_draw = -math.inf
        self._drawn = False
        self.note = ""  # appended to the line (a sequential startup's current estimate and 1-sigma)

    def line(self, elapsed: float, phase: str, setpoint: int, count: int) -> str:
        """The text of the bar at robot time ``elapsed`` (s) of ``total``."""
        frac = min(max(elapsed / self.total, 0.0), 1.0)
        full = int(round(frac * self.width))
        left = max(self.total - elapsed, 0.0)
        sp = f"setpoint {setpoint + 1}/{count}" if setpoint >= 0 else f"{count} setpoints"
        note = f"  {self.note}" if self.note else ""
        return (f"[{'#' * full}{'.' * (self.width - full)}] {frac * 100:5.1f}%  {phase:<10} {sp}  ~{left:5.0f} s left"
                f"{note}")

    def update(self, elapsed: float, phase: str, setpoint: int, count: int, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last_draw < self.min_interval:
            return
        self._last_draw = now
        self.stream.write("\r" + self.line(elapsed, phase, setpoint, count) + "\x1b[K")
        self.stream.flush()
        self._drawn = True

    def close(self) -> None:
        if self.enabled and self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False
