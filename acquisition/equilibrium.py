"""Online detection of a static equilibrium: the signals' ripple over a sliding window falls below thresholds.

The detector is fed one sample at a time (the logged samples, e.g. 10 Hz). A channel's ripple is its
standard deviation over the last ``window`` seconds, per component; the platform is at rest when every
component of every watched channel is below its threshold: the tensions below the load cells' uncertainty
(N), the cable-length changes below a fraction of a millimetre (m) (under pure force control the tensions
can be steady while the platform still swings, the encoders see it). A detection that does not come within
``timeout`` seconds of ``start`` is reported as timed out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DetectorConfig:
    window: float = 1.5  # s, length of the sliding window
    thresholds: tuple[tuple[str, float], ...] = (("tau", 0.196), ("dl", 2.0e-4))  # channel, max std (SI)
    timeout: float = 40.0  # s after start
    min_wait: float = 0.0  # s after start before a detection counts

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

    def start(self, t: float) -> None:
        """Forget the past; the timeout runs from t (s)."""
        self._buffers.clear()
        self._count = 0
        self._t0 = float(t)

    def push(self, t: float, **channels: np.ndarray) -> DetectorState:
        """Add the sample taken at t (s); channels by name (arrays of any fixed size, SI units)."""
        slot = self._count % self.size
        for name, _ in self.config.thresholds:
            v = np.atleast_1d(np.asarray(channels[name], dtype=float))
            buf = self._buffers.get(name)
            if buf is None:
                buf = self._buffers[name] = np.empty((self.size, v.size))
            buf[slot] = v
        self._count += 1
        elapsed = float(t) - self._t0
        ripple: dict[str, np.ndarray] = {}
        settled = False
        if self._count >= self.size and elapsed >= self.config.min_wait:
            settled = True
            for name, limit in self.config.thresholds:
                r = self._buffers[name].std(axis=0)
                ripple[name] = r
                settled &= bool(np.all(r < limit))
        timed_out = not settled and elapsed > self.config.timeout
        return DetectorState(settled, timed_out, elapsed, ripple)

    @property
    def window_samples(self) -> int:
        """Number of samples in the sliding window."""
        return self.size
