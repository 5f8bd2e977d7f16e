"""Joint-space force control: one tension controller per winch on load-cell feedback, vectorised over winches.

The command of winch i is a motor torque (N m). A cable tension tau (N) needs the motor torque
radius_i * tau, where radius_i = -length_per_motor_rev_i / (2 pi) is the signed transmission radius (m/rad):
the cable pulls the drum towards paying out, so the motor must push the other way. The controller works in
tension units and converts at the end:

    u = tau_ref + kp (tau_ref - tau_meas) + I,    dI/dt = ki (tau_ref - tau_meas)   (N)
    torque = rate_limit(clip(radius u, torque_min, torque_max))                     (N m)

Anti-windup by conditional integration (the integral is frozen while the command is held by the bounds or
the rate limit and the error would push it further) and a bound on the integral itself. Cables only pull:
the tension command is never below ``min_command``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.robot import Robot


@dataclass(frozen=True)
class ControllerConfig:
    """Gains and limits of the tension controller. Tension-equivalent units unless named otherwise."""

    rate: float = 500.0  # Hz, control rate (200-500)
    kp: float = 1.0  # N of command per N of tension error
    ki: float = 30.0  # N of command per N s of error (1/s)
    integral_limit: float = 60.0  # N, bound of |I|
    min_command: float = 5.0  # N, lowest tension command (cables only pull)
    max_command: float = 400.0  # N, highest tension command
    max_command_rate: float = 1500.0  # N/s, rate limit of the torque command expressed in tension

    def __post_init__(self) -> None:
        if not 50.0 <= self.rate <= 2000.0:
            raise ValueError(f"controller rate must be within 50..2000 Hz, got {self.rate!r}.")
        for name in ("kp", "ki", "integral_limit", "min_command", "max_command_rate"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"controller field '{name}' must be non-negative, got {getattr(self, name)!r}.")
        if self.max_command <= self.min_command:
            raise ValueError(f"controller max_command {self.max_command} must exceed min_command {self.min_command}.")

    @property
    def period(self) -> float:
        return 1.0 / self.rate


def transmission_radius(robot: Robot) -> np.ndarray:
    """Signed transmission radius (n,) m/rad: motor torque = radius * cable tension."""
    lpr = np.asarray(robot.sensors.length_per_motor_rev, dtype=float)
    if lpr.shape != (robot.n,):
        raise ValueError(
            f"robot '{robot.name}': field 'sensors.length_per_motor_rev' must give one value per cable ({robot.n})."
        )
    return -lpr / (2.0 * math.pi)


class TensionController:
    """PI tension control with feed-forward, anti-windup and torque rate limits, for n winches at once."""

    def __init__(self, radius: np.ndarray, config: ControllerConfig | None = None):
        self.radius = np.asarray(radius, dtype=float).copy()
        if np.any(self.radius == 0) or self.radius.ndim != 1:
            raise ValueError(f"transmission radii must be a non-zero vector, got {self.radius.tolist()}.")
        self.config = config or ControllerConfig()
        self.n = len(self.radius)
        self.integral = np.zeros(self.n)
        self.command = np.zeros(self.n)  # last tension-equivalent command, N
        self.feedback = np.ones(self.n, dtype=bool)  # channels whose load cell is trusted
        self.saturated = np.zeros(self.n, dtype=bool)

    def reset(self, command: np.ndarray | None = None) -> None:
        """Zero the integral; the rate limit starts from ``command`` (N, tension-equivalent) or zero."""
        self.integral[:] = 0.0
        self.command[:] = 0.0 if command is None else np.asarray(command, dtype=float)

    def open_loop(self, channels: np.ndarray) -> None:
        """Stop using the load cells of ``channels`` (bool or index array): feed-forward only, integral kept."""
        self.feedback[channels] = False

    def update(self, tau_ref: np.ndarray, tau_meas: np.ndarray, dt: float) -> np.ndarray:
        """One control step: references and measurements (n,) N, step dt (s); returns motor torques (n,) N m."""
        c = self.config
        err = np.where(self.feedback, tau_ref - tau_meas, 0.0)
        raw = tau_ref + c.kp * err + self.integral
        bounded = np.clip(raw, c.min_command, c.max_command)
        step = c.max_command_rate * dt
        limited = np.clip(bounded, self.command - step, self.command + step)
        high = (limited < raw) & (err > 0)
        low = (limited > raw) & (err < 0)
        self.saturated = high | low
        integrate = ~self.saturated & self.feedback
        self.integral = np.where(integrate, self.integral + c.ki * err * dt, self.integral)
        np.clip(self.integral, -c.integral_limit, c.integral_limit, out=self.integral)
        self.command = limited
        return self.radius * limited

    def torque_for(self, tension: np.ndarray) -> np.ndarray:
        """Feed-forward torque (n,) N m for tensions (n,) N."""
        return self.radius * np.asarray(tension, dtype=float)
