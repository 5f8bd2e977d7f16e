"""An Xsens MTi-630 AHRS emulated on a pty master, speaking Xbus.

Clocked by the simulator: :meth:`XsensEmulator.emit` is called once per physics tick with the simulated
time and the platform's true roll, pitch, yaw (rad, robot convention R = Rx Ry Rz); it writes an MTData2
message when the device is in measurement mode and a sample is due at the configured output rate
(SampleTimeFine = sim_time x 10000). A reader thread answers the host's configuration messages:
GoToConfig, GoToMeasurement, ReqDID, ReqProductCode, SetOutputConfiguration (with the OutputConfiguration
acknowledgement), Reset, WakeUpAck; anything else, or a configuration message in measurement mode,
is answered with an Error message.

Sensor model (all seeded by the Generator): mounting tilt (roll, pitch, rad) composed with the platform
rotation; per-device roll/pitch biases within +-0.1 deg and white noise 0.03 deg (within the +-0.2 deg
specification); yaw relative to the start-up heading (0 at the first sample), with a constant drift
rate within +-0.001 deg/s and white noise 0.1 deg (within +-1 deg over a start-up routine).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from calib.kinematics import rotation
from drivers import xbus
from drivers.xbus import MID, XDI
from sim_backend.physics import _euler
from sim_backend.pty import GaussianBlocks, PtyEmulator, free_run, read_master

ORIENTATION_MAX_HZ = 400  # MTi-600 series orientation outputs
TIMESTAMP_MAX_HZ = 2000
SUPPORTED = {XDI.PACKET_COUNTER, XDI.SAMPLE_TIME_FINE, XDI.QUATERNION, XDI.EULER_ANGLES,
             XDI.QUATERNION | XDI.FLOAT64, XDI.EULER_ANGLES | XDI.FLOAT64}


@dataclass(frozen=True)
class XsensNoise:
    """Sensor error model, degrees and degrees per second."""

    roll_pitch_bias: float = 0.1  # bound of the uniform per-device bias
    roll_pitch_std: float = 0.03
    yaw_drift: float = 0.001  # bound of the uniform drift rate, deg/s
    yaw_std: float = 0.1
    pitch_std: float | None = None  # None: roll_pitch_std


def euler_to_quaternion(roll: float, pitch: float, yaw: float, convention: str = "xyz") -> tuple[float, ...]:
    """Unit quaternion (q0 scalar first) of R = Rx(roll) Ry(pitch) Rz(yaw) (``xyz``) or
    R = Rz(yaw) Ry(pitch) Rx(roll) (``zyx``)."""
    hx = (math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0)
    hy = (math.cos(pitch / 2), 0.0, math.sin(pitch / 2), 0.0)
    hz = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    if convention == "zyx":
        hx, hz = hz, hx

    def mul(a, b):
        return (a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
                a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
                a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
                a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0])

    return mul(mul(hx, hy), hz)


def _rotation(roll: float, pitch: float, yaw: float, convention: str) -> list[list[float]]:
    """calib.kinematics.rotation for one set of angles, as rows of plain floats."""
    c1, c2, c3 = math.cos(roll), math.cos(pitch), math.cos(yaw)
    s1, s2, s3 = math.sin(roll), math.sin(pitch), math.sin(yaw)
    if convention == "xyz":
        return [[c2 * c3, -c2 * s3, s2],
                [c1 * s3 + s1 * s2 * c3, c1 * c3 - s1 * s2 * s3, -s1 * c2],
                [s1 * s3 - c1 * s2 * c3, s1 * c3 + c1 * s2 * s3, c1 * c2]]
    if convention == "zyx":
        return [[c3 * c2, c3 * s2 * s1 - s3 * c1, c3 * s2 * c1 + s3 * s1],
                [s3 * c2, s3 * s2 * s1 + c3 * c1, s3 * s2 * c1 - c3 * s1],
                [-s2, c2 * s1, c2 * c1]]
    raise ValueError(f"unknown orientation convention {convention!r}")


def _matmul(a: list[list[float]], b: list[list[float]]) -> list[list[float]]:
    """The 3x3 product a b of rows of floats (written out: a nested comprehension costs several calls)."""
    (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = b
    return [[a0 * b00 + a1 * b10 + a2 * b20, a0 * b01 + a1 * b11 + a2 * b21, a0 * b02 + a1 * b12 + a2 * b22]
            for a0, a1, a2 in a]


_VALUE_STRUCTS = {(n, fmt): struct.Struct(f">{n}{fmt}") for n in (3, 4) for fmt in "fd"}  # Euler angles, quaternion


class XsensEmulator(PtyEmulator):
    """One emulated MTi-630 on ``master_fd`` (see the module docstring). Start with :meth:`start`."""

    thread_name = "xsens-emulator"

    def __init__(
        self,
        master_fd: int,
        rng: np.random.Generator,
        mounting_roll: float = 0.0,
        mounting_pitch: float = 0.0,
        noise: XsensNoise | None = None,
        device_id: int = 0x0630_2A17,
        product_code: str = "MTi-630-2A8G4",
        input_convention: str = "xyz",
        output_convention: str = "xyz",
    ) -> None:
        """``input_convention``: Euler convention of the true angles given to :meth:`emit` (the robot's);
        ``output_convention``: the one the device reports in (a real MTi reports ``zyx``)."""
        super().__init__(master_fd, rng)
        self.input_convention = input_convention
        self.output_convention = output_convention
        self.noise = noise or XsensNoise()
        self.device_id = device_id
        self.product_code = product_code
        self._mount_rows = rotation(np.array([mounting_roll, mounting_pitch, 0.0]))[0].tolist()
        b = self.noise.roll_pitch_bias
        self._bias_roll, self._bias_pitch = np.radians(rng.uniform(-b, b, 2)).tolist()
        self._drift = math.radians(rng.uniform(-self.noise.yaw_drift, self.noise.yaw_drift))
        self._yaw0: float | None = None
        self._t0 = 0.0
        # power-on state: measurement mode with a factory-like output configuration (no Euler angles)
        self.measuring = True
        self.config = [(XDI.PACKET_COUNTER, XDI.MAX_RATE), (XDI.SAMPLE_TIME_FINE, XDI.MAX_RATE), (XDI.QUATERNION, 100)]
        self.packet_counter = 0
        self._last_slot: dict[int, int] = {}
        self._decoder = xbus.XbusDecoder()
        self._normals = GaussianBlocks(rng, 3)  # per sample: roll, pitch, yaw noise, after the bias and drift draws

    @property
    def config(self) -> list[tuple[int, int]]:
        """The output configuration: (XDI, rate Hz) items; rate 0 or ``XDI.MAX_RATE``: with every packet."""
        return self._config

    @config.setter
    def config(self, items: list[tuple[int, int]]) -> None:
        self._config = list(items)
        self._rated = [(xdi, rate) for xdi, rate in self._config if rate not in (0, XDI.MAX_RATE)]

    # ---- faults the backend injects ----
    def disconnect(self) -> None:
        """Stop sending anything (cable pulled); the host sees a silent port."""
        self._silent = True

    def reconnect(self) -> None:
        self._silent = False

    # ---- the simulator's clock ----
    def measured_angles(self, sim_time: float, roll: float, pitch: float, yaw: float) -> np.ndarray:
        """What the sensor reports for the platform's true angles (rad): mounting, bias, drift, noise."""
        return np.array(self._measure(sim_time, roll, pitch, yaw))

    def _measure(self, sim_time: float, roll: float, pitch: float, yaw: float) -> tuple[float, float, float]:
        """:meth:`measured_angles` as plain floats: 3x3 products in Python cost a fraction of numpy's on one
        matrix (calib.kinematics.rotation / rotation_to_euler give the same angles)."""
        r = _matmul(_rotation(roll, pitch, yaw, self.input_convention), self._mount_rows)
        a_roll, a_pitch, a_yaw = _euler(r, self.output_convention)
        if self._yaw0 is None:
            self._yaw0, self._t0 = a_yaw, sim_time
        n = self.noise
        z_roll, z_pitch, z_yaw = self._normals.take()  # as rng.normal(0.0, std, 2) then rng.normal(0.0, yaw_std)
        a_roll += self._bias_roll + math.radians(0.0 + n.roll_pitch_std * z_roll)
        a_pitch += self._bias_pitch + math.radians(0.0 + (n.roll_pitch_std if n.pitch_std is None else n.pitch_std)
                                                   * z_pitch)
        a_yaw += -self._yaw0 + self._drift * (sim_time - self._t0) + math.radians(0.0 + n.yaw_std * z_yaw)
        a_yaw = (a_yaw + math.pi) % (2 * math.pi) - math.pi
        return a_roll, a_pitch, a_yaw

    def emit(self, sim_time: float, roll: float, pitch: float, yaw: float) -> int | None:
        """One physics tick: write an MTData2 if one is due and return its packet number, else None.

        The number is the packet counter before its 16-bit wrap, i.e. the ``seq`` that
        :class:`drivers.xsens.XsensMti` gives the reading (when it was connected before the first wrap), so
        the acquisition can ``wait_for`` it.
        """
        with self._lock:
            if not self.measuring or self._silent:
                return None
            items = self._due_items(sim_time)
            if not items:
                return None
            # computed (and the noise drawn) only for samples sent: the due ticks follow from the simulated
            # time alone, so the same seed still gives the same bytes
            ang = self._measure(sim_time, roll, pitch, yaw)
            number = self.packet_counter
            data = []
            for xdi in items:
                if xdi == XDI.PACKET_COUNTER:
                    data.append((xdi, (number & 0xFFFF).to_bytes(2, "big")))
                elif xdi == XDI.SAMPLE_TIME_FINE:
                    data.append((xdi, (round(sim_time * 10000) & 0xFFFFFFFF).to_bytes(4, "big")))
                else:
                    data.append((xdi, self._orientation_item(xdi, ang)))
            self.packet_counter += 1
            frame = xbus.encode(MID.MTDATA2, xbus.encode_mtdata2(data))
            frame = self._maybe_corrupt(frame)
            self._write(frame)
            return number

    def _orientation_item(self, xdi: int, ang: tuple[float, float, float]) -> bytes:
        """The data of a quaternion or Euler-angles (degrees) item for the measured angles ``ang`` (rad)."""
        if xdi & 0xFFF0 == XDI.QUATERNION:
            values = euler_to_quaternion(*ang, convention=self.output_convention)
        else:
            values = (math.degrees(ang[0]), math.degrees(ang[1]), math.degrees(ang[2]))
        return _VALUE_STRUCTS[len(values), "d" if xdi & XDI.FORMAT_MASK == XDI.FLOAT64 else "f"].pack(*values)

    def due(self, sim_time: float) -> bool:
        """Whether :meth:`emit` at ``sim_time`` (s) writes a sample: measuring, not silent, and an item with an
        explicit rate reaches a new slot of its grid (the caller can skip computing the angles otherwise)."""
        if not self.measuring or self._silent:
            return False
        last = self._last_slot
        for xdi, rate in self._rated:
            if last.get(xdi, -1) < math.floor(sim_time * rate + 1e-9):
                return True
        return False

    def _due_items(self, sim_time: float) -> list[int]:
        """Items due at this tick: each explicit rate on its own grid; 0xFFFF items ride along."""
        due = []
        for xdi, rate in self._rated:
            slot = math.floor(sim_time * rate + 1e-9)
            if self._last_slot.get(xdi, -1) < slot:
                self._last_slot[xdi] = slot
                due.append(xdi)
        if not due:
            return []
        return [xdi for xdi, rate in self.config if xdi in due or rate in (0, XDI.MAX_RATE)]

    # ---- host commands ----
    def _serve(self) -> None:
        while not self._stop.is_set():
            data = read_master(self.fd, 0.02)
            if not data:
                continue
            for msg in self._decoder.feed(data):
                reply = self.handle(msg)
                if reply and not self._silent:
                    with self._lock:
                        self._write(reply)

    def handle(self, msg: xbus.Message) -> bytes:
        """The device's answer (framed bytes) to one host message; changes the device state."""
        with self._lock:
            mid, p = msg.mid, msg.payload
            if mid == MID.GO_TO_CONFIG:
                self.measuring = False
                return xbus.encode(MID.GO_TO_CONFIG_ACK)
            if mid == MID.REQ_DID:
                return xbus.encode(MID.DEVICE_ID, self.device_id.to_bytes(4, "big"))
            if mid == MID.REQ_PRODUCT_CODE:
                return xbus.encode(MID.PRODUCT_CODE, self.product_code.encode("ascii"))
            if mid == MID.WAKE_UP:
                return b""  # the host's WakeUpAck would be the answer; a device never receives WakeUp
            if mid == MID.WAKE_UP_ACK:
                self.measuring = False
                return b""
            if mid == MID.RESET:
                self.measuring, self.packet_counter = True, 0
                self._last_slot.clear()
                return xbus.encode(MID.RESET_ACK)
            if self.measuring:
                if mid == MID.GO_TO_MEASUREMENT:
                    return xbus.encode(MID.GO_TO_MEASUREMENT_ACK)
                return xbus.encode(MID.ERROR, bytes((0x04,)))
            if mid == MID.GO_TO_MEASUREMENT:
                self.measuring = True
                self._last_slot.clear()
                return xbus.encode(MID.GO_TO_MEASUREMENT_ACK)
            if mid == MID.SET_OUTPUT_CONFIGURATION:
                return self._set_output_configuration(p)
            return xbus.encode(MID.ERROR, bytes((0x04,)))

    def _set_output_configuration(self, payload: bytes) -> bytes:
        items = xbus.decode_output_configuration(payload)
        if items is None:
            return xbus.encode(MID.ERROR, bytes((0x04,)))
        if not items:  # a request for the current configuration
            return xbus.encode(MID.OUTPUT_CONFIGURATION, xbus.encode_output_configuration(self.config))
        for xdi, rate in items:
            limit = TIMESTAMP_MAX_HZ if xdi & 0xF000 == 0x1000 else ORIENTATION_MAX_HZ
            if xdi not in SUPPORTED or not (rate == XDI.MAX_RATE or (0 < rate <= limit and limit % rate == 0)):
                return xbus.encode(MID.ERROR, bytes((0x21,)))
        self.config = list(items)
        self._last_slot.clear()
        return xbus.encode(MID.OUTPUT_CONFIGURATION, xbus.encode_output_configuration(self.config))


def main(argv: list[str] | None = None) -> int:
    """Free-running demo for operators: ``python -m sim_backend.xsens_emulator [roll pitch yaw]`` (deg).

    Creates a pty, prints its path (for ``cdpr devices read ahrs --port PATH``) and clocks the emulator
    on wall time at 400 Hz until interrupted; the simulator itself never free-runs.
    """
    import sys

    from sim_backend.pty import open_pty_pair

    args = [float(a) for a in (sys.argv[1:] if argv is None else argv)] or [2.0, -1.0, 10.0]
    roll, pitch, yaw = (math.radians(a) for a in (args + [0.0, 0.0, 0.0])[:3])
    master, path = open_pty_pair()
    print(path, flush=True)
    emu = XsensEmulator(master, np.random.default_rng(0)).start()
    return free_run(emu, lambda t: emu.emit(t, roll, pitch, yaw), ORIENTATION_MAX_HZ)


if __name__ == "__main__":
    raise SystemExit(main())
