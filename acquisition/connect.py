"""Connecting the devices of a startup: open and check every device of a device configuration and give the
:class:`acquisition.control.Rig` the routine drives, with how often each device sends its readings."""

from __future__ import annotations

import math

from acquisition.clock import Clock
from acquisition.control import Rig
from calib.robot import Robot


def feedback_every(rate: float, log_every: int, overflow: int = 240) -> tuple[int, int]:
    """How often (in SYNCs) the winch drives and the swivel encoders send their readings: (drives, encoders).

    The loop closes on the load cells at every tick; the drives' position, torque and statusword serve the
    log, the equilibrium detector (at the log ticks) and the fault checks (EMCY comes at once anyway), the
    swivel angles only the log. So the encoders send at every log tick and the drives as often as that
    allows at 50 Hz or more; both periods divide the log period and the SYNC counter overflow, and the
    first SYNC after connecting (counter 1) carries them all (the log ticks are those SYNCs too).
    Halves the CAN frames per tick at 200 Hz (13.6 -> 6.8, heartbeats included).
    """
    base = math.gcd(int(log_every), int(overflow)) if overflow else 1
    encoders = base
    drives = max(d for d in range(1, base + 1) if base % d == 0 and rate / d >= 50.0)
    return drives, encoders


def ahrs_rate_for(log_period: float, base: int = 400) -> int:
    """The AHRS output rate (Hz) the routine needs: the lowest rate the MTi offers (a divisor of its ``base``
    rate) that puts a sample on every log tick, i.e. a whole number of samples per log period (s); the roll,
    pitch and yaw serve only the log. 10 Hz for the paper's 100 ms; 100 Hz when no divisor fits."""
    for rate in range(1, base + 1):
        k = rate * log_period
        if base % rate == 0 and k > 1.0 - 1e-9 and abs(k - round(k)) < 1e-9:
            return rate
    return 100


def connect(devices, robot: Robot, clock: Clock, lockstep: bool, period: float, timeout: float = 0.5,
            every: tuple[int, int] = (1, 1), recorder=None, bus=None) -> Rig:
    """Open and check every device of a :class:`drivers.config.DeviceConfig`; a :class:`Rig` over them.
    ``every``: the drives and the encoders send their readings every n-th SYNC (see :func:`feedback_every`).
    ``recorder``: an ``acquisition.busrecord.BusRecorder`` that gets every CAN frame and serial byte from the
    first on; ``bus``: a python-can bus to use instead of the one ``devices.can`` names (a replay's).

    The CAN drivers take their time stamps (heartbeat supervision) from the loop's clock; in lockstep the
    serial drivers' own wall-time staleness rule is switched off (the supervisor judges staleness on the
    loop's clock) and they read their ports in the loop's thread when it waits for a reading (no reader
    thread to wake at every tick). Raises ``drivers.interfaces.DeviceError`` (one sentence) when a device does
    not answer.
    """
    from drivers.interfaces import DeviceError
    from drivers.open import open_devices

    devices.check_robot(robot.n)
    if devices.loadcells is None or devices.ahrs is None:
        raise DeviceError(f"{devices.source}: the device configuration needs 'loadcells' and 'ahrs'.")
    opened = open_devices(devices, robot.sensors.length_per_motor_rev, robot.sensors.swivel_counts_per_rev,
                          clock=clock.now, every=every, control_period=period, polled=lockstep,
                          stale_periods=1e9 if lockstep else 3.0, bus=bus, listener=recorder,
                          serial_tap=None if recorder is None else recorder.serial_tap)
    rig = Rig(opened.drives, opened.encoders, opened.loadcells, opened.ahrs, opened.send_sync, period, lockstep,
              ahrs_period=1.0 / float(devices.ahrs.rate), timeout=timeout)
    rig.closer = opened.close
    return rig
