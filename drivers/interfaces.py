"""The device interfaces the acquisition code sees; implementations live beside this module.

One abstract class per kind of device. Every reading carries ``t`` (the driver's monotonic receive time,
s, from ``time.monotonic``) and ``seq`` (a sequence number from the device or the driver, so that gaps and
staleness can be detected). Device time stamps that come over the wire (SYNC counter, Xsens SampleTimeFine,
load-cell sequence) are kept in the readings as well, because the simulated prototype's clock is carried by
them. Units are SI at this boundary: N, m, rad, s.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

import numpy as np

from calib.errors import CdprError


class DeviceError(CdprError, RuntimeError):
    """A device that failed: a fault, an emergency message, a lost heartbeat, a silent port."""


@dataclass(frozen=True)
class Reading:
    t: float  # s, time.monotonic() when the driver received it
    seq: int  # sequence number (device counter where the wire has one)


@dataclass(frozen=True)
class WinchReading(Reading):
    """One SYNC cycle of a winch drive."""

    position_counts: int  # motor encoder, counts since power-on (signed, unwrapped)
    velocity: float  # motor velocity, rad/s (its TPDO may come less often: the last one received; NaN before)
    torque: float  # motor torque actual, N m
    statusword: int
    delta_length: float  # cable-length change since power-on, m (counts x transmission ratio)
    sync_count: int = -1  # SYNC counter the TPDO answered, -1 if the bus carries none


@dataclass(frozen=True)
class SwivelReading(Reading):
    counts: int  # raw encoder position (wraps at the encoder's resolution)
    delta_angle: float  # unwrapped swivel-angle change since power-on, rad
    sync_count: int = -1


@dataclass(frozen=True)
class TensionReading(Reading):
    tau: np.ndarray  # (n,) cable tensions, N
    device_seq: int = -1  # the amplifier's own sequence number


@dataclass(frozen=True)
class AhrsReading(Reading):
    roll: float  # rad
    pitch: float  # rad
    yaw: float  # rad, relative to the AHRS start-up heading
    packet_counter: int = -1
    sample_time_fine: int = -1  # 1/10000 s ticks


@dataclass
class LinkStats:
    """Counters a driver keeps about its link."""

    frames: int = 0
    checksum_errors: int = 0
    resyncs: int = 0
    sequence_gaps: int = 0
    bytes_discarded: int = 0
    extra: dict = field(default_factory=dict)


class Device(abc.ABC):
    """Common life cycle: open, check, close; usable as a context manager."""

    name: str = "device"

    @abc.abstractmethod
    def open(self) -> None:
        """Connect and configure; raises DeviceError with one clear sentence on failure."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the port or node; safe to call twice."""

    @abc.abstractmethod
    def status(self) -> str:
        """A one-line state for ``cdpr devices check``."""

    def fault(self) -> str | None:
        """The pending fault as one sentence, or None."""
        return None

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc):
        self.close()


class WinchDrive(Device):
    """A winch servo drive (CiA 402): state machine, cyclic torque target, SYNC-triggered feedback."""

    @abc.abstractmethod
    def enable(self) -> None:
        """Shutdown -> switch on -> operation enabled (fault reset first if needed)."""

    @abc.abstractmethod
    def disable(self) -> None:
        """Back to switch-on-disabled (torque off)."""

    @abc.abstractmethod
    def quick_stop(self) -> None:
        """CiA 402 quick stop."""

    @abc.abstractmethod
    def fault_reset(self) -> None: ...

    @abc.abstractmethod
    def set_torque(self, torque: float) -> None:
        """Cyclic torque target, N m at the motor; sent in the RPDO before the next SYNC."""

    @abc.abstractmethod
    def latest(self) -> WinchReading | None: ...

    @property
    @abc.abstractmethod
    def enabled(self) -> bool: ...


class SwivelEncoder(Device):
    @abc.abstractmethod
    def latest(self) -> SwivelReading | None: ...


class LoadCellAmplifier(Device):
    """A multi-channel load-cell amplifier streaming tension lines."""

    @abc.abstractmethod
    def latest(self) -> TensionReading | None: ...

    @abc.abstractmethod
    def wait_for(self, device_seq: int, timeout: float) -> TensionReading:
        """Block until a reading with device sequence >= device_seq arrives; DeviceError on timeout."""

    @property
    @abc.abstractmethod
    def stats(self) -> LinkStats: ...


class Ahrs(Device):
    """An attitude and heading reference system streaming Euler angles."""

    @abc.abstractmethod
    def latest(self) -> AhrsReading | None: ...

    @abc.abstractmethod
    def wait_for(self, packet_counter: int, timeout: float) -> AhrsReading:
        """Block until a reading with packet counter >= packet_counter arrives; DeviceError on timeout."""

    @property
    @abc.abstractmethod
    def stats(self) -> LinkStats: ...
