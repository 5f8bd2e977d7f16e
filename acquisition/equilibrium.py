"""Online detection of a static equilibrium with the offline window search's own stillness test.

The detector is fed one sample at a time (the logged samples, e.g. 10 Hz): tensions, cable lengths, swivel
angles, roll and pitch. It judges its most recent span of samples with
:class:`calib.selfcal.windows.Stillness` (the object the offline search of a run uses): every length, swivel,
roll and pitch stays within its range over the span and the tension ripple (standard deviation over the
span) within its tolerance. The thresholds are those of the offline search, computed by
:meth:`Stillness.of_samples` from the samples seen so far (the last ``history`` seconds, kept across
:meth:`EquilibriumDetector.start`, refreshed every second): the larger of the floors of
:class:`calib.selfcal.windows.WindowOptions` and the run's own noise and drift; the ripple tolerance the
load cells' uncertainty or, if larger, a multiple of the tensions' noise floor. The platform rests once
the spans judged still since :meth:`EquilibriumDetector.start` cover ``min_duration_s`` of consecutive
samples, as an offline window needs. A detection that does not come within ``timeout`` seconds of
``start`` is reported as timed out.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field, replace

import numpy as np

from calib.selfcal.windows import Stillness, WindowOptions, min_samples, span_samples, still_channels


@dataclass(frozen=True)
class DetectorConfig:
    """Stillness options (the offline search's), the ripple floor (N), timeout and wait (s after start),
    and the seconds of past samples the noise estimates come from."""

    options: WindowOptions = field(default_factory=WindowOptions)
    ripple_floor: float = 0.196  # N: the load cells' uncertainty (accuracy x full scale)
    timeout: float = 40.0  # s after start
    min_wait: float = 0.0  # s after start before a detection counts
    history: float = 600.0  # s of past samples the thresholds are estimated from
    stillness: Stillness | None = None  # fixed thresholds (e.g. a recorded run's) instead of learning them

    @classmethod
    def for_robot(cls, robot, **changes) -> DetectorConfig:
        """Ripple floor = the robot's load-cell uncertainty, as offline."""
        return cls(ripple_floor=float(robot.sensors.load_cell_uncertainty), **changes)


@dataclass(frozen=True)
class DetectorState:
    """After a sample: settled, timed out, elapsed s since start, whether the latest span is still and its
    scores (largest range over its limit, tension ripple over its tolerance; NaN until a span is full)."""

    settled: bool
    timed_out: bool
    elapsed: float
    still: bool = False
    scores: tuple[float, float] = (float("nan"), float("nan"))


class EquilibriumDetector:
    """The offline stillness test on a sliding span of samples taken every ``sample_period`` s; ``background``:
    submits a call to a worker and returns its Future (the thresholds' refresh off the caller's thread)."""

    def __init__(self, sample_period: float, config: DetectorConfig | None = None,
                 background: Callable[..., Future] | None = None):
        self.config = config or DetectorConfig()
        self.background = background
        self._refreshing: Future | None = None
        self.sample_period = float(sample_period)
        # the offline ends test, on here even where the offline search leaves it off (the recordings' default),
        # a sway's wander allowed over the settle_s block it judges; the settle test is the search's, as it is
        given = self.config.options
        opt = replace(given, ends_p=given.ends_p or given.settle_p,
                      ends_reach_s=max(given.ends_reach_s, 0.5 * given.settle_s))
        self.options = opt
        self.span = span_samples(opt, self.sample_period)
        # consecutive still judgements that make a rest: a window's length, and at least settle_s
        self.needed = max(min_samples(opt, self.sample_period), int(math.ceil(opt.settle_s / self.sample_period)))
        keep = max(2 * self.span, int(round(self.config.history / self.sample_period)))
        self._past: deque[np.ndarray] = deque(maxlen=keep)  # rows [tau, dl, dsigma, roll, pitch]
        # the same rows since start, a window's worth: the latest span is judged, the whole block's ends
        self._recent: deque[np.ndarray] = deque(maxlen=self.span - 1 + self.needed)
        self._n = 0
        self._count = 0
        self._run = 0
        self._t0 = 0.0
        self.timeout = self.config.timeout
        self._refresh = max(1, int(round(1.0 / self.sample_period)))
        floors = {"length": opt.length_tol, "swivel": opt.swivel_tol, "tilt": opt.tilt_tol}
        self.stillness = self.config.stillness or Stillness(
            self.span, {c: np.atleast_1d(v) for c, v in floors.items()}, self.config.ripple_floor)

    def start(self, t: float, timeout: float | None = None) -> None:
        """Forget the span; the timeout (default the configuration's, s) runs from t (s)."""
        self._recent.clear()
        self._run = 0
        self._t0 = float(t)
        self.timeout = self.config.timeout if timeout is None else float(timeout)
        self._refresh_thresholds()

    def _split(self, rows: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        n = self._n
        return rows[:, :n], still_channels(rows[:, n : 2 * n], rows[:, 2 * n : 3 * n], rows[:, 3 * n],
                                           rows[:, 3 * n + 1])

    def update_thresholds(self) -> None:
        """The offline thresholds (:meth:`Stillness.of_samples`) of the samples kept in the history."""
        if len(self._past) >= 3 and self.config.stillness is None:
            self.stillness = self._thresholds_of(list(self._past))

    def _thresholds_of(self, rows: list[np.ndarray]) -> Stillness:
        """Stillness.of_samples of the rows (pure: the worker's call)."""
        tau, ch = self._split(np.array(rows))
        return Stillness.of_samples(tau, ch, self.span, self.options, self.config.ripple_floor)

    def _refresh_thresholds(self) -> None:
        """In line (no ``background``), else asked of the worker unless a refresh is already on its way."""
        if self.background is None:
            self.update_thresholds()
        elif self._refreshing is None and len(self._past) >= 3 and self.config.stillness is None:
            self._refreshing = self.background(self._thresholds_of, list(self._past))

    def _take_thresholds(self) -> None:
        """The worker's thresholds once they are ready (never waits)."""
        if self._refreshing is not None and self._refreshing.done():
            done, self._refreshing = self._refreshing, None
            self.stillness = done.result()

    def push(self, t: float, tau: np.ndarray, dl: np.ndarray, dsigma: np.ndarray, roll: float,
             pitch: float) -> DetectorState:
        """Add the sample taken at t (s): tensions (n,) N, lengths (n,) m, swivels (n,) rad, roll, pitch rad."""
        row = np.r_[np.asarray(tau, float), np.asarray(dl, float), np.asarray(dsigma, float), roll, pitch]
        self._n = np.asarray(tau).size
        self._past.append(row)
        self._recent.append(row)
        self._count += 1
        self._take_thresholds()
        if self._count % self._refresh == 0:
            self._refresh_thresholds()
        elapsed = float(t) - self._t0
        still, scores = False, (float("nan"), float("nan"))
        if len(self._recent) >= self.span:
            tau_b, ch = self._split(np.array(self._recent)[-self.span:])
            scores = self.stillness.judge(tau_b, ch)
            still = scores[0] <= 1.0 and scores[1] <= 1.0
        self._run = self._run + 1 if still else 0
        settled = self._run >= self.needed and elapsed >= self.config.min_wait and self._rests()
        timed_out = not settled and elapsed > self.timeout
        return DetectorState(settled, timed_out, elapsed, still, scores)

    def _rests(self) -> bool:
        """Whether the samples the still spans cover rest from end to end: the offline search's cut of a
        window's moving ends (:meth:`Stillness.trim`) leaves them whole."""
        block = np.array(self._recent)[-(self.span - 1 + self._run):]
        tau_b, ch = self._split(block)
        return self.stillness.trim(tau_b, ch, block.shape[0]) == (0, 0)
