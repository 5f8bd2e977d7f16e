"""The safety supervisor: it owns the decision to stop, and the safe-stop plan.

Every control tick the loop hands the supervisor what it saw (measured tensions, the commanded reference,
the age of each sensor's last reading, each drive's pending fault); the supervisor raises
:class:`SafeStop` with one clear sentence when any of these holds:

* the operator asked (Ctrl-C / SIGINT or SIGTERM, through :meth:`SafetySupervisor.install_signals`);
* a drive reports a fault (CiA 402 fault, emergency message, lost heartbeat);
* a sensor is stale (no new reading for ``stale_periods`` of its own period) or stuck (a load-cell channel
  repeating the very same value for ``stuck_samples`` ticks);
* a cable is slack (measured tension under ``slack`` N while the command keeps it taut) or overloaded
  (above ``overload`` N).

The stop itself (:class:`SafeStopPlan`): hold the tensions for ``hold_time`` s, then ramp them down at
``ramp_rate`` N/s to a safe pretension, then switch the drives off. The loop executes it.
"""

from __future__ import annotations

import signal
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from calib.errors import CdprError
from calib.robot import Robot


class SafeStop(CdprError):
    """A reason to stop, as one sentence; ``kind`` is a short word for the run log's event."""

    def __init__(self, kind: str, message: str, channels: tuple[int, ...] = ()):
        super().__init__(message)
        self.kind = kind
        self.message = message
        self.channels = channels  # 0-based cables whose load cell must no longer be trusted


@dataclass(frozen=True)
class SafetyLimits:
    slack: float = 8.0  # N, a measured tension below this is a slack cable
    overload: float = 300.0  # N, a measured tension above this is an overload
    stale_periods: float = 3.0  # a sensor silent for this many of its periods is stale
    stuck_samples: int = 250  # identical load-cell values in a row that make a channel stuck
    hold_time: float = 0.5  # s, tensions held before the ramp down
    ramp_rate: float = 40.0  # N/s, ramp down rate
    safe_pretension: float = 40.0  # N, the ramp's target (raised to the power-on tensions' level if lower)

    @classmethod
    def for_robot(cls, robot: Robot, **changes) -> SafetyLimits:
        """Margins from the robot's tension limits: slack at 30 % of tau_min, overload at 150 % of tau_max."""
        base = dict(slack=0.3 * robot.tau_min, overload=1.5 * robot.tau_max, safe_pretension=robot.tau_min)
        base.update(changes)
        return cls(**base)


@dataclass(frozen=True)
class SafeStopPlan:
    """Tension references of a safe stop: hold ``start`` (n,) N, then ramp to ``target`` (n,) N."""

    start: np.ndarray
    target: np.ndarray
    hold_time: float
    ramp_rate: float

    @property
    def duration(self) -> float:
        """s, hold plus ramp."""
        span = float(np.max(np.abs(self.target - self.start), initial=0.0))
        return self.hold_time + span / self.ramp_rate

    def reference(self, t: float) -> np.ndarray:
        """Tension reference (n,) N at t s after the stop began."""
        if t <= self.hold_time:
            return self.start.copy()
        step = self.ramp_rate * (t - self.hold_time)
        delta = self.target - self.start
        return self.start + np.clip(delta, -step, step)


@dataclass
class SafetySupervisor:
    """Checks each tick; holds the operator's stop request set by a signal handler."""

    limits: SafetyLimits
    n: int
    requested: str | None = None
    _previous_handlers: dict = field(default_factory=dict)
    _last_tau: list[float] | None = None  # N, the previous tick's tensions
    _same: list[int] | None = None  # ticks in a row with the same value, per channel

    def install_signals(self) -> None:
        """Route SIGINT and SIGTERM to a stop request (main thread only); restore with :meth:`restore_signals`."""
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous_handlers[sig] = signal.signal(sig, self._on_signal)

    def restore_signals(self) -> None:
        for sig, handler in self._previous_handlers.items():
            signal.signal(sig, handler)
        self._previous_handlers.clear()

    def _on_signal(self, signum, frame) -> None:
        name = signal.Signals(signum).name
        if self.requested is None:
            self.requested = f"stopped by the operator ({name})"

    def check(
        self,
        tau: np.ndarray,
        tau_ref: np.ndarray,
        ages: Mapping[str, tuple[float, float]],
        faults: Mapping[str, str | None],
        armed: bool = True,
    ) -> None:
        """Raise :class:`SafeStop` if anything is wrong.

        tau, tau_ref: (n,) N measured and commanded; ages: sensor name -> (seconds since its last new
        reading, its nominal period in s); faults: device name -> fault sentence or None; armed: False while
        the tensions are still being established (the slack check is skipped).
        """
        if self.requested is not None:
            raise SafeStop("operator", f"{self.requested}.")
        for name, fault in faults.items():
            if fault:
                kind = "drive_fault" if "drive" in name or "winch" in name else "sensor_fault"
                lost = tuple(range(self.n)) if name.startswith("load") else ()
                raise SafeStop(kind, f"{name}: {fault.rstrip('.')}.", lost)
        for name, (age, period) in ages.items():
            if age > self.limits.stale_periods * period:
                raise SafeStop(
                    "stale_sensor",
                    f"{name} silent for {age:.3f} s, more than {self.limits.stale_periods:g} periods of {period:g} s.",
                    tuple(range(self.n)) if name.startswith("load") else (),
                )
        vals = np.asarray(tau, dtype=float).tolist()  # n <= 8 floats: plain comparisons beat ufunc calls
        self._check_stuck(vals)
        lim = self.limits
        for i, v in enumerate(vals):
            if v > lim.overload:
                raise SafeStop(
                    "overload",
                    f"cable {i + 1} overloaded: {v:.1f} N measured, above the {lim.overload:g} N limit.",
                )
        if armed:
            refs = np.asarray(tau_ref, dtype=float).tolist()
            for i, v in enumerate(vals):
                if v < lim.slack and refs[i] > 2.0 * lim.slack:
                    raise SafeStop(
                        "slack",
                        f"cable {i + 1} slack: {v:.1f} N measured for {refs[i]:.1f} N commanded, "
                        f"below the {lim.slack:g} N slack limit.",
                    )

    def _check_stuck(self, vals: list[float]) -> None:
        """Count, per channel, the ticks in a row with the very same value (N); raise at ``stuck_samples``."""
        last, self._last_tau = self._last_tau, list(vals)
        if last is None:
            self._same = [0] * self.n
            return
        same = self._same
        for i, v in enumerate(vals):
            same[i] = same[i] + 1 if v == last[i] else 0
        for i, count in enumerate(same):
            if count >= self.limits.stuck_samples:
                raise SafeStop(
                    "stuck_sensor",
                    f"load cell {i + 1} stuck at {vals[i]:.2f} N for {count} samples in a row.",
                    (i,),
                )

    def plan(self, tau_now: np.ndarray, power_on: np.ndarray | None = None) -> SafeStopPlan:
        """The safe stop from the tensions now (n,) N: hold, then ramp to the safe pretension.

        The target is ``safe_pretension`` (or the power-on tensions where higher, the state the robot rested in),
        never below twice the slack limit.
        """
        tau_now = np.asarray(tau_now, dtype=float)
        target = np.full(self.n, self.limits.safe_pretension)
        if power_on is not None:
            target = np.maximum(target, np.asarray(power_on, dtype=float))
        target = np.maximum(target, 2.0 * self.limits.slack)
        target = np.minimum(target, np.maximum(tau_now, 2.0 * self.limits.slack))
        return SafeStopPlan(tau_now.copy(), target, self.limits.hold_time, self.limits.ramp_rate)
