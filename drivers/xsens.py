"""Xsens MTi-630 AHRS driver over a serial port (Xbus, see docs/protocols/xbus.md).

``open`` puts the device in configuration mode, reads its device id, sets the output configuration
(PacketCounter and SampleTimeFine with every packet, EulerAngles float32 at ``rate_hz``) and returns it
to measurement mode; a reader thread (or, ``polled``, the thread waiting for a reading) then turns every
MTData2 into an :class:`AhrsReading` (angles in rad). Error messages from the device are surfaced: during
configuration as a DeviceError, while streaming as the pending :meth:`fault`. ``seq`` is the packet counter
unwrapped past its 16-bit roll-over.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from drivers import xbus
from drivers.interfaces import Ahrs as AhrsBase
from drivers.interfaces import AhrsReading, DeviceError
from drivers.serial_util import SerialDevice
from drivers.xbus import MID, XDI


@dataclass(frozen=True)
class XsensConfig:
    port: str
    baud: int = 115200
    rate_hz: int = 100  # EulerAngles output rate; must divide 400
    ack_timeout: float = 1.0  # s to wait for each acknowledgement
    retries: int = 3  # GoToConfig attempts (a device streaming fast may miss the first)
    stale_periods: float = 3.0
    polled: bool = False  # read the port in the waiting thread, not a reader thread (lockstep simulation)
    tap: Callable[[bytes, bool], None] | None = field(default=None, compare=False)  # raw record (PortReader)


FRAME_BYTES = 32  # our MTData2 on the wire: 4 header + 5 + 7 + 15 item bytes + 1 checksum


def config_problem(config: XsensConfig) -> str | None:
    """Why ``config`` cannot work, in one sentence, or None."""
    if not (0 < config.rate_hz <= 400 and 400 % config.rate_hz == 0):
        return f"Xsens output rate {config.rate_hz} Hz is not a divisor of 400 Hz."
    need = config.rate_hz * FRAME_BYTES * 10  # 8N1: 10 bits per byte
    if need > config.baud:
        return (f"Xsens output rate {config.rate_hz} Hz needs {need} bit/s, more than {config.baud} baud "
                f"carry.")
    return None


class XsensMti(SerialDevice, AhrsBase):
    """An MTi-630 on a serial port; implements :class:`drivers.interfaces.Ahrs`."""

    name = "ahrs"
    kind = "Xsens MTi"
    tag = "xsens"
    counter = "packet counter"

    def __init__(self, config: XsensConfig) -> None:
        problem = config_problem(config)
        if problem:
            raise ValueError(problem)
        super().__init__(config)
        self.device_id: int | None = None
        self._decoder = xbus.XbusDecoder()
        self._replies: list[xbus.Message] = []
        self._reply_cond = threading.Condition()
        self._errors: list[str] = []
        self._unwrapped = -1
        self._last_raw_pc: int | None = None

    # ---- life cycle ----
    def _greet(self) -> None:  # GoToConfig, the output configuration, GoToMeasurement
        for attempt in range(self.config.retries):
            try:
                self.request(MID.GO_TO_CONFIG, b"", MID.GO_TO_CONFIG_ACK)
                break
            except DeviceError:
                if attempt == self.config.retries - 1:
                    raise
        did = self.request(MID.REQ_DID, b"", MID.DEVICE_ID)
        self.device_id = xbus.decode_device_id(did.payload)
        wanted = [(XDI.PACKET_COUNTER, XDI.MAX_RATE), (XDI.SAMPLE_TIME_FINE, XDI.MAX_RATE),
                  (XDI.EULER_ANGLES, self.config.rate_hz)]
        ack = self.request(MID.SET_OUTPUT_CONFIGURATION, xbus.encode_output_configuration(wanted),
                           MID.OUTPUT_CONFIGURATION)
        got = xbus.decode_output_configuration(ack.payload)
        if got is None or sorted(got) != sorted(wanted):
            raise DeviceError(f"Xsens MTi on {self.config.port} applied output configuration {got} "
                              f"instead of {wanted}.")
        self._box.opened_at = time.monotonic()
        self.request(MID.GO_TO_MEASUREMENT, b"", MID.GO_TO_MEASUREMENT_ACK)
        self._box.opened_at = time.monotonic()

    def request(self, mid: int, payload: bytes, answer: int) -> xbus.Message:
        """Send one message and wait for ``answer``; an Error reply raises DeviceError naming the code."""
        if self._port is None:
            raise DeviceError(f"Xsens MTi on {self.config.port} is not open.")
        with self._reply_cond:
            self._replies.clear()
        try:
            self._reader.write(xbus.encode(mid, payload))
        except Exception as exc:  # serial.SerialException, OSError, write timeout
            raise DeviceError(f"Xsens MTi: writing {xbus.mid_name(mid)} to {self.config.port} failed ({exc}).") from exc
        deadline = time.monotonic() + self.config.ack_timeout
        polled = not self._reader.threaded
        while True:
            with self._reply_cond:
                for msg in self._replies:
                    if msg.mid == answer:
                        return msg
                    if msg.mid == MID.ERROR:
                        code = xbus.decode_error(msg.payload)
                        text = xbus.error_text(code) if code is not None else "no code"
                        raise DeviceError(f"Xsens MTi on {self.config.port} answered {xbus.mid_name(mid)} "
                                          f"with Error 0x{(code or 0):02X} ({text}).")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DeviceError(f"Xsens MTi on {self.config.port} did not acknowledge "
                                      f"{xbus.mid_name(mid)} within {self.config.ack_timeout:g} s.")
                if not polled:
                    self._reply_cond.wait(left)
                    continue
            self._reader.poll(left)

    # ---- the reader thread ----
    def _on_bytes(self, data: bytes, t: float) -> None:
        for msg in self._decoder.feed(data):
            if msg.mid == MID.MTDATA2:
                self._on_mtdata2(msg.payload, t)
                continue
            if msg.mid == MID.ERROR:
                code = xbus.decode_error(msg.payload)
                del self._errors[:-16]
                self._errors.append(f"Xsens MTi on {self.config.port} reported Error 0x{(code or 0):02X} "
                                    f"({xbus.error_text(code) if code is not None else 'no code'}).")
                self._stats.extra["device_errors"] = len(self._errors)
            with self._reply_cond:
                self._replies.append(msg)
                del self._replies[:-32]  # only the latest answers matter to a waiting request
                self._reply_cond.notify_all()
        c = self._decoder.counts
        self._stats.checksum_errors, self._stats.bytes_discarded = c.checksum_errors, c.bytes_discarded
        self._stats.resyncs = c.resyncs

    def _on_mtdata2(self, payload: bytes, t: float) -> None:
        fields = xbus.sample_fields(payload)
        if fields is None or fields[2] is None:
            self._stats.extra["incomplete_mtdata2"] = self._stats.extra.get("incomplete_mtdata2", 0) + 1
            return
        pc, stf, euler_deg, _ = fields
        if pc is not None:
            if self._last_raw_pc is None:
                self._unwrapped = pc
            else:
                step = (pc - self._last_raw_pc) & 0xFFFF
                if step == 0:  # a repeated counter: a duplicate frame, drop it
                    return
                if step > 1:
                    self._stats.sequence_gaps += step - 1
                self._unwrapped += step
            self._last_raw_pc = pc
        else:
            self._unwrapped += 1
        roll, pitch, yaw = map(math.radians, euler_deg)
        self._stats.frames += 1
        self._box.put(AhrsReading(t=t, seq=self._unwrapped, roll=roll, pitch=pitch, yaw=yaw,
                                  packet_counter=-1 if pc is None else pc,
                                  sample_time_fine=-1 if stf is None else stf))

    def _count(self, reading: AhrsReading) -> int:
        return reading.seq  # the unwrapped packet counter

    def fault(self) -> str | None:
        if self._reader is not None and self._reader.error:
            return f"Xsens MTi: {self._reader.error}."
        if self._errors:
            return self._errors[-1]
        return self.staleness()

    def clear_errors(self) -> None:
        """Forget the device errors reported so far (after the operator has seen them)."""
        self._errors.clear()

    def status(self) -> str:
        r = self.latest()
        did = f"{self.device_id:08X}" if self.device_id is not None else "?"
        if r is None:
            return f"Xsens MTi {did} on {self.config.port}: no sample yet"
        return (f"Xsens MTi {did} on {self.config.port}: roll {math.degrees(r.roll):.2f} deg, pitch "
                f"{math.degrees(r.pitch):.2f} deg, yaw {math.degrees(r.yaw):.2f} deg, packet {r.seq}, "
                f"{self._stats.frames} frames, {self._stats.checksum_errors} checksum errors")
