"""CiA 402 winch servo drive driver over CANopen (canopen.RemoteNode, EDS drivers/od/cia402_winch.eds).

Setup by SDO (outside the cyclic loop): NMT pre-operational, device type check, heartbeat producer time
0x1017, PDO mapping (TPDO1 = position actual 0x6064 + torque actual 0x6077 + statusword 0x6041, one 8-byte
frame at every SYNC, transmission type 1; TPDO2 = velocity actual 0x606C at every n-th SYNC, type n; RPDO1 =
controlword 0x6040 + target torque 0x6071 + target velocity 0x60FF, synchronous), mode of operation 0x6060 =
10 (cyclic synchronous torque), NMT start. The CiA 402 state machine (``drivers.cia402``) is driven by SDO writes of the
controlword (and the RPDO carries the same controlword so that a later RPDO never undoes it). Feedback: the
TPDOs answering one SYNC are assembled into one :class:`WinchReading` (``drivers.canopen_node``).
Faults: EMCY messages, the statusword fault bit, a lost heartbeat.
"""

from __future__ import annotations

import dataclasses
import math
import struct
import time
from collections.abc import Callable
from pathlib import Path

import can
import canopen
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.can_bus import SyncProducer
from drivers.canopen_node import CanopenNodeDriver, check_every, wrap_delta
from drivers.cia402 import (
    CW_DISABLE_VOLTAGE,
    CW_ENABLE,
    CW_FAULT_RESET,
    CW_QUICK_STOP,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
    FAULT,
    FAULT_REACTION_ACTIVE,
    MODE_CST,
    MODE_NAMES,
    OPERATION_ENABLED,
    QUICK_STOP_ACTIVE,
    READY_TO_SWITCH_ON,
    SW_FAULT,
    SWITCH_ON_DISABLED,
    SWITCHED_ON,
    state_of,
)
from drivers.interfaces import DeviceError, WinchDrive, WinchReading


class CanopenWinchDrive(CanopenNodeDriver, WinchDrive):
    """One CiA 402 winch drive in cyclic synchronous torque mode.

    ``length_per_motor_rev`` (m of cable per motor revolution, the robot description's
    ``sensors.length_per_motor_rev[i]``) turns motor counts into cable-length change; the motor encoder
    has ``counts_per_rev`` increments per revolution (20 bits). Position, torque and statusword come every
    ``every``-th SYNC (1: all), the velocity actual every ``velocity_every``-th (10 Hz at a 200 Hz loop by
    default: the loop does not use it, the status and checks do); a reading has NaN velocity until the first.
    """

    profile = 402
    eds_name = "cia402_winch.eds"

    def __init__(self, network: canopen.Network, node_id: int, sync: SyncProducer, length_per_motor_rev: float,
                 name: str | None = None, clock: Callable[[], float] = time.monotonic,
                 heartbeat_period: float = 0.1, counts_per_rev: int = 1 << 20, mode: int = MODE_CST,
                 state_timeout: float = 1.0, eds: str | Path | None = None, velocity_every: int | None = None,
                 every: int = 1):
        super().__init__(network, node_id, sync, name or f"winch drive {node_id}", clock, heartbeat_period,
                         eds=eds, every=every)
        if velocity_every is None:  # 20 where the SYNC counter allows it (it needs a start value), else every SYNC
            velocity_every = 20 if sync.overflow and sync.overflow % 20 == 0 else 1
        self.velocity_every = check_every(velocity_every, sync, self.name, "velocity")
        self.length_per_motor_rev = float(length_per_motor_rev)
        self.counts_per_rev = int(counts_per_rev)
        self.mode = mode
        self.state_timeout = state_timeout
        self.rated_torque = 0.0  # N m, from 0x6076 at open
        self.max_torque = 0.0  # N m, from 0x6072
        self.controlword = CW_DISABLE_VOLTAGE
        self.target_torque = 0  # per mille of rated torque
        self.target_velocity = 0  # increments/s
        self._rpdo_cob = 0x200 + self.node_id
        self._rpdo = struct.Struct("<Hhi")
        self._last_raw: int | None = None
        self._unwrapped = 0

    # -- open / close ---------------------------------------------------------------------------------
    def open(self) -> None:
        """Configure the drive by SDO and start it (NMT operational); the power stage stays disabled."""
        try:
            self._open_node()
            self.rated_torque = self.sdo_read(0x6076) / 1000.0
            if self.rated_torque <= 0:
                raise DeviceError(f"{self.name} (CAN node {self.node_id}) reports a rated torque 0x6076 of 0")
            self.max_torque = self.sdo_read(0x6072) / 1000.0 * self.rated_torque
            incr = self.sdo_read(0x608F, 1) if 0x608F in self.node.object_dictionary else self.counts_per_rev
            revs = self.sdo_read(0x608F, 2) if 0x608F in self.node.object_dictionary else 1
            if revs and incr // revs != self.counts_per_rev:
                raise DeviceError(f"{self.name} (CAN node {self.node_id}) reports {incr // revs} encoder "
                                  f"increments per revolution (0x608F), expected {self.counts_per_rev}")
            self._map_tpdo(1, [(0x6064, 32), (0x6077, 16), (0x6041, 16)], every=self.every)
            self._map_tpdo(2, [(0x606C, 32)], every=self.velocity_every)
            for k in (3, 4):
                self._disable_pdo(0x1800 + k - 1, 0x180, k)
            rpdo = self.node.rpdo[1]
            rpdo.clear()
            rpdo.add_variable(0x6040, 0, 16)
            rpdo.add_variable(0x6071, 0, 16)
            rpdo.add_variable(0x60FF, 0, 32)
            rpdo.cob_id = self._rpdo_cob
            rpdo.trans_type = 1
            rpdo.enabled = True
            try:
                rpdo.save()
            except (SdoCommunicationError, SdoAbortedError) as exc:
                raise self._sdo_fail("mapping RPDO1", exc) from exc
            for k in (2, 3, 4):
                self._disable_pdo(0x1400 + k - 1, 0x200, k)
            self.set_mode(self.mode)
            self.controlword = self.sdo_read(0x6040)
            self._start()
        except Exception:
            self.close()
            raise

    def close(self) -> None:
        """Disable the power stage if it is enabled (the winch brake holds), then stop the node."""
        if self.node is not None and self.operational:
            try:
                if self.state() in (OPERATION_ENABLED, QUICK_STOP_ACTIVE):
                    self._command(CW_DISABLE_VOLTAGE)
            except (DeviceError, RuntimeError, can.CanError, OSError):
                pass  # the node or the bus no longer answers: nothing left to disable
        super().close()

    def set_mode(self, mode: int) -> None:
        """Mode of operation 0x6060 (10 CST, 9 CSV), by SDO, checked on 0x6061."""
        if mode not in MODE_NAMES:
            raise ValueError(f"mode of operation {mode} is not supported (9 CSV, 10 CST)")
        self.sdo_write(0x6060, mode)
        shown = self.sdo_read(0x6061)
        if shown != mode:
            raise DeviceError(f"{self.name} (CAN node {self.node_id}) stays in mode {shown} after mode {mode} "
                              f"was requested")
        self.mode = mode

    # -- state machine (outside the cyclic loop) -----------------------------------------------------------
    def statusword(self) -> int:
        """Statusword read now by SDO."""
        return self.sdo_read(0x6041)

    def state(self) -> str:
        return state_of(self.statusword())

    def _command(self, cw: int) -> None:
        self.controlword = cw
        self._send_rpdo()
        self.sdo_write(0x6040, cw)

    def _expect(self, *states: str) -> str:
        deadline = time.monotonic() + self.state_timeout
        while True:
            s = self.state()
            if s in states:
                return s
            if time.monotonic() > deadline:
                raise DeviceError(f"{self.name} (CAN node {self.node_id}) is in state '{s}', expected "
                                  f"'{' or '.join(states)}' within {self.state_timeout} s")
            time.sleep(0.002)

    def enable(self) -> None:
        """Shutdown -> switch on -> operation enabled (fault reset first if needed); the RPDO target
        (last :meth:`set_torque`) applies from the next SYNC."""
        s = self.state()
        if s in (FAULT, FAULT_REACTION_ACTIVE):
            self.fault_reset()
        elif s == QUICK_STOP_ACTIVE:
            self._command(CW_DISABLE_VOLTAGE)
            self._expect(SWITCH_ON_DISABLED)
        if self.state() != OPERATION_ENABLED:
            self._command(CW_SHUTDOWN)
            self._expect(READY_TO_SWITCH_ON)
            self._command(CW_SWITCH_ON)
            self._expect(SWITCHED_ON)
            self._command(CW_ENABLE)
            self._expect(OPERATION_ENABLED)

    def disable(self) -> None:
        """Disable voltage: switch on disabled, torque off."""
        self._command(CW_DISABLE_VOLTAGE)
        self._expect(SWITCH_ON_DISABLED, FAULT)

    def quick_stop(self) -> None:
        """CiA 402 quick stop (the drive stops and holds, option code 0x605A)."""
        self._command(CW_QUICK_STOP)
        self._expect(QUICK_STOP_ACTIVE, SWITCH_ON_DISABLED, FAULT)

    def fault_reset(self) -> None:
        """Rising edge of controlword bit 7; the drive goes to switch on disabled."""
        if self.controlword & CW_FAULT_RESET:
            self._command(CW_DISABLE_VOLTAGE)
        self.emcy_faults.clear()
        self._command(CW_FAULT_RESET)
        self._expect(SWITCH_ON_DISABLED)
        self._command(CW_DISABLE_VOLTAGE)
        if self.node is not None:
            self.node.emcy.reset()

    # -- cyclic -----------------------------------------------------------------------------------------
    def torque_to_permille(self, torque: float) -> int:
        """Target torque 0x6071 for ``torque`` N m: per mille of the rated torque, saturated at the maximum torque
        0x6072 (at 32.767 rated torques without one) and at the 16-bit range."""
        limit = self.max_torque if self.max_torque > 0 else 32.767 * self.rated_torque
        tq = float(torque)
        if tq > limit:
            tq = limit
        elif tq < -limit:
            tq = -limit
        permille = round(tq / self.rated_torque * 1000.0)
        return -32768 if permille < -32768 else 32767 if permille > 32767 else permille

    def set_torque(self, torque: float) -> None:
        """Torque target, N m at the motor (saturated at 0x6072), sent now in RPDO1 (effective at SYNC)."""
        if not math.isfinite(torque):
            raise ValueError(f"{self.name}: torque target must be finite, got {torque}")
        self.target_torque = self.torque_to_permille(torque)
        self._send_rpdo()

    def set_velocity(self, velocity: float) -> None:
        """Velocity target, rad/s at the motor (cyclic synchronous velocity mode), sent now in RPDO1."""
        if not math.isfinite(velocity):
            raise ValueError(f"{self.name}: velocity target must be finite, got {velocity}")
        v = int(round(velocity * self.counts_per_rev / (2 * math.pi)))
        self.target_velocity = max(-(1 << 31), min((1 << 31) - 1, v))
        self._send_rpdo()

    def _send_rpdo(self) -> None:
        if self.node is None:
            raise DeviceError(f"{self.name} (CAN node {self.node_id}) is not open")
        if self.operational:
            data = self._rpdo.pack(self.controlword, self.target_torque, self.target_velocity)
            try:
                self.network.send_message(self._rpdo_cob, data)
            except (can.CanError, OSError, RuntimeError) as exc:
                raise DeviceError(f"{self.name} (CAN node {self.node_id}): sending RPDO1 failed: {exc}") from exc

    def _make_reading(self, t, seq, sync_count, values):
        raw = values[0x6064]
        if self._last_raw is None:
            self._unwrapped = raw
        else:
            self._unwrapped += wrap_delta(raw, self._last_raw, 32)
        self._last_raw = raw
        counts = self._unwrapped
        return WinchReading(
            t=t, seq=seq, position_counts=counts,
            velocity=values[0x606C] * 2 * math.pi / self.counts_per_rev if 0x606C in values else math.nan,
            torque=values[0x6077] / 1000.0 * self.rated_torque,
            statusword=values[0x6041],
            delta_length=counts / self.counts_per_rev * self.length_per_motor_rev,
            sync_count=sync_count,
        )

    def _refresh(self, reading, slow):
        if 0x606C not in slow:
            return reading
        return dataclasses.replace(reading, velocity=slow[0x606C] * 2 * math.pi / self.counts_per_rev)

    # -- state ------------------------------------------------------------------------------------------
    @property
    def enabled(self) -> bool:
        r = self._latest
        return r is not None and state_of(r.statusword) == OPERATION_ENABLED and self.fault() is None

    def fault(self) -> str | None:
        """EMCY, statusword fault bit or lost heartbeat, as one sentence; None when healthy."""
        link = self._link_fault()
        if link:
            return link
        r = self._latest
        if r is not None and r.statusword & SW_FAULT:
            return (f"{self.name} (CAN node {self.node_id}) reports a fault in its statusword "
                    f"0x{r.statusword:04X}")
        return None

    def status(self) -> str:
        if self.node is None:
            return f"{self.name}: CAN node {self.node_id}, closed"
        r = self._latest
        if r is None:
            try:
                drive = self.state()
            except DeviceError:
                drive = "no SDO answer"
            feedback = "no PDO yet"
        else:
            drive = state_of(r.statusword)
            feedback = f"position {r.position_counts} counts, torque {r.torque:.3f} N m, SYNC {r.sync_count}"
        fault = self.fault()
        return (f"{self.name}: CAN node {self.node_id}, NMT {self.nmt_state()}, {drive}, "
                f"{MODE_NAMES.get(self.mode, self.mode)}, {feedback}" + (f"; FAULT: {fault}" if fault else ""))
