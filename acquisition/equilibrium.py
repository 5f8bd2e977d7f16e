"""Online detection of a static equilibrium: the signals' ripple over a sliding window falls below thresholds.

The detector is fed one sample at a time (the logged samples, e.g. 10 Hz). A channel's ripple is its
standard deviation over the last ``window`` seconds, per component; the platform is at rest when every
component of every watched channel is below its threshold: the tensions below the load cells' uncertainty
(N), the cable-length changes below a fraction of a millimetre (m) (under pure force control the tensions
can be steady while the platform still swings, the encoders see it). A detection that does not come within
``timeout`` seconds of ``start`` is reported as timed out.

The thresholds adapt to the run's own noise as the offline window search does (calib.selfcal.windows):
each is the larger of its configured floor and ``noise_factor`` times the channel's sample noise, estimated
with the same robust scale of second differences (:func:`calib.selfcal.windows.sample_noise`) over the last
``history`` seconds the detector saw (kept across :meth:`EquilibriumDetector.start`, refreshed every second).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from calib.selfcal.windows import sample_noise


@dataclass(frozen=True)
class DetectorConfig:
    window: float = 1.5  # s, length of the sliding window
    thresholds: tuple[tuple[str, float], ...] = (("tau", 0.196), ("dl", 2.0e-4))  # channel, max std (SI)
    timeout: float = 40.0  # s after start
    min_wait: float = 0.0  # s after start before a detection counts
    noise_factor: float = 2.0  # a channel's std over the window may reach this many times its sample noise
    history: float = 60.0  # s of past samples its noise is estimated from

    @classmethod
    def for_robot(cls, robot, length_ripple: float = 2.0e-4, **changes) -> DetectorConfig:
        """Tension threshold = the robot's load-cell uncertainty (accuracy x full scale), N."""
        return cls(thresholds=(("tau", float(robot.sensors.load_cell_uncertainty)), ("dl", length_ripple)), **changes)

    def threshold(self, name: str) -> float:
        return dict(self.thresholds)[name]


@dataclass(frozen=True)
class DetectorState:
    settled: bool
    timed_out: bool
    elapsed: float  # s since start
    ripple: dict[str, np.ndarray]  # channel -> per-component std over the window (empty until full)


class EquilibriumDetector:
    """Sliding-window ripple detector over named channels sampled every ``sample_period`` s."""

    def __init__(self, sample_period: float, config: DetectorConfig | None = None):
        self.config = config or DetectorConfig()
        self.sample_period = float(sample_period)
        self.size = max(2, int(round(self.config.window / self.sample_period)))
        self._buffers: dict[str, np.ndarray] = {}
        self._count = 0
        self._t0 = 0.0
        self.timeout = self.config.timeout
        keep = max(10, int(round(self.config.history / self.sample_period)))
        self._past: dict[str, deque[np.ndarray]] = {name: deque(maxlen=keep) for name, _ in self.config.thresholds}
        self._refresh = max(1, int(round(1.0 / self.sample_period)))
        self.limits: dict[str, np.ndarray | float] = dict(self.config.thresholds)

    def start(self, t: float, timeout: float | None = None) -> None:
        """Forget the window; the timeout (default the configuration's, s) runs from t (s)."""
        self._buffers.clear()
        self._count = 0
        self._t0 = float(t)
        self.timeout = self.config.timeout if timeout is None else float(timeout)
        self._update_limits()

    def _update_limits(self) -> None:
        """Per channel: max(floor, noise_factor x the sample noise of the history)."""
        for name, floor in self.config.thresholds:
            past = self._past[name]
            if len(past) >= 10:
                self.limits[name] = np.maximum(floor, self.config.noise_factor * sample_noise(np.array(past)))

    def push(self, t: float, **channels: np.ndarray) -> DetectorState:
        """Add the sample taken at t (s); channels by name (arrays of any fixed size, SI units)."""
        slot = self._count % self.size
        for name, _ in self.config.thresholds:
            v = np.atleast_1d(np.asarray(channels[name], dtype=float))
            buf = self._buffers.get(name)
            if buf is None:
                buf = self._buffers[name] = np.empty((self.size, v.size))
            buf[slot] = v
            self._past[name].append(v.copy())
        self._count += 1
        if self._count % self._refresh == 0:
            self._update_limits()
        elapsed = float(t) - self._t0
        ripple: dict[str, np.ndarray] = {}
        settled = False
        if self._count >= self.size and elapsed >= self.config.min_wait:
            settled = True
            for name, _ in self.config.thresholds:
                r = self._buffers[name].std(axis=0)
                ripple[name] = r
                settled &= bool(np.all(r < self.limits[name]))
        timed_out = not settled and elapsed > self.timeout
        return DetectorState(settled, timed_out, elapsed, ripple)

    @property
    def window_samples(self) -> int:
        """Number of samples in the sliding window."""
        return self.size
