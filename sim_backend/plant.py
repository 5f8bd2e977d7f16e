"""The boundary between the simulated physics and the emulated devices.

The device emulators (CAN drives and encoders, load-cell amplifier, AHRS) read the true physical state
through a :class:`Plant` and write actuator commands to it; the physics (``sim_backend.physics``)
implements it. All quantities are SI and *true* (no sensor error): each emulator adds its own sensor
model (resolution, noise, offsets) and the hidden effects of the simulation configuration.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np


class Plant(Protocol):
    n: int  # number of cables

    @property
    def time(self) -> float:
        """Simulated time since power-on, s."""

    def motor_position(self) -> np.ndarray:
        """(n,) motor shaft angles since power-on, rad."""

    def motor_velocity(self) -> np.ndarray:
        """(n,) motor shaft velocities, rad/s."""

    def motor_torque(self) -> np.ndarray:
        """(n,) torque the motors currently deliver, N m."""

    def set_motor_torque(self, i: int, torque: float) -> None:
        """Torque command for motor i, N m, applied from the next physics step on."""

    def cable_tension(self) -> np.ndarray:
        """(n,) tension at the load cells, N (0 for a slack cable)."""

    def swivel_angle(self) -> np.ndarray:
        """(n,) absolute swivel angles sigma_i, rad."""

    def orientation(self) -> np.ndarray:
        """(3,) platform roll, pitch, yaw in the robot's convention, rad (absolute)."""


def scalar_reader(plant: Plant, quantity: str, i: int) -> Callable[[], float]:
    """A zero-argument function giving ``float(getattr(plant, quantity)()[i])`` (``quantity``: a method of
    :class:`Plant` that returns an (n,) array), for the emulators' per-SYNC reads. A plant with a
    ``reader(quantity, i)`` of its own gives the same value without building the array."""
    own = getattr(plant, "reader", None)
    if own is not None:
        return own(quantity, i)
    get = getattr(plant, quantity)
    return lambda: float(get()[i])
