"""CiA 402 winch servo drive driver over CANopen (canopen.RemoteNode, EDS drivers/od/cia402_winch.eds).

Setup by SDO (outside the cyclic loop): NMT pre-operational, device type check, heartbeat producer time
0x1017, PDO mapping (TPDO1 = position actual 0x6064 + torque actual 0x6077 + statusword 0x6041, one 8-byte
frame at every SYNC, transmission type 1; TPDO2 = velocity actual 0x606C at every n-th SYNC, type n; RPDO1 =
controlword 0x6040 + target torque 0x6071 + target velocity 0x60FF, synchronous), mode of operation 0x6060 =
10 (cyclic synchronous torque), NMT start. The CiA 402 state machine is driven by SDO writes of the
controlword (and the RPDO carries the same controlword so that a later RPDO never undoes it). Feedback: the
TPDOs answering one SYNC are assembled into one :class:`WinchReading` stamped with that SYNC's counter (from
the shared :class:`SyncProducer`); the frames are decoded by COB-ID with one struct call each.
Faults: EMCY messages, the statusword fault bit, a lost heartbeat.
"""

from __future__ import annotations

import dataclasses
import math
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

import can
import canopen
from canopen.objectdictionary import datatypes
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.can_bus import NMT_STATE_NAMES, HeartbeatMonitor, SyncProducer
from drivers.config import eds_path
from drivers.interfaces import DeviceError, WinchDrive, WinchReading

MODE_CSV = 9
MODE_CST = 10
MODE_NAMES = {MODE_CSV: "cyclic synchronous velocity", MODE_CST: "cyclic synchronous torque"}

CW_SHUTDOWN = 0x06
CW_SWITCH_ON = 0x07
CW_ENABLE = 0x0F
CW_DISABLE_VOLTAGE = 0x00
CW_QUICK_STOP = 0x02
CW_FAULT_RESET = 0x80


def cia402_state(statusword: int) -> str:
    """Name of the CiA 402 state encoded in a statusword."""
    sw = statusword & 0x6F
    if statusword & 0x4F == 0x00:
        return "not ready to switch on"
    if statusword & 0x4F == 0x40:
        return "switch on disabled"
    if sw == 0x21:
        return "ready to switch on"
    if sw == 0x23:
        return "switched on"
    if sw == 0x27:
        return "operation enabled"
    if sw == 0x07:
        return "quick stop active"
    if statusword & 0x4F == 0x0F:
        return "fault reaction active"
    if statusword & 0x4F == 0x08:
        return "fault"
    return f"unknown (statusword 0x{statusword:04X})"


def check_every(every: int, sync: SyncProducer, name: str, what: str) -> int:
    """A TPDO transmission type n (every n-th SYNC), checked: 1..240, and with n > 1 a SYNC counter whose
    overflow n divides (the master then knows from the counter which SYNCs carry the TPDO)."""
    n = int(every)
    if not 1 <= n <= 240:
        raise ValueError(f"{name}: {what} TPDO transmission type must be 1..240 SYNCs, got {every}")
    if n > 1 and (not sync.overflow or sync.overflow % n):
        raise ValueError(f"{name}: {what} every {n} SYNCs needs a SYNC counter overflow that {n} divides, "
                         f"not {sync.overflow}")
    return n


def wrap_delta(new: int, old: int, bits: int) -> int:
    """Signed difference new - old of two counters that wrap at 2**bits."""
    half = 1 << (bits - 1)
    return (new - old + half) % (1 << bits) - half


class CanopenNodeDriver:
    """What the CANopen drivers share: the RemoteNode, SDO helpers, heartbeat monitor, EMCY log, NMT start,
    TPDO mapping by SDO and assembly of the TPDOs of one SYNC into one reading."""

    profile = 0
    eds_name = ""

    def __init__(self, network: canopen.Network, node_id: int, sync: SyncProducer, name: str,
                 clock: Callable[[], float] = time.monotonic, heartbeat_period: float = 0.1,
                 heartbeat_factor: float = 2.5, eds: str | Path | None = None, every: int = 1):
        self.network = network
        self.every = check_every(every, sync, name or f"CAN node {node_id}", "feedback")
        self._first_due: int | None = None  # the first SYNC count at which the readings come, once started
        self.node_id = int(node_id)
        self.sync = sync
        self.name = name
        self.clock = clock
        self.heartbeat_period = float(heartbeat_period)
        self.heartbeat_factor = float(heartbeat_factor)
        self.eds = str(eds or eds_path(self.eds_name))
        self.node: canopen.RemoteNode | None = None
        self.heartbeat: HeartbeatMonitor | None = None
        self.emcy_faults: list[str] = []
        self._cond = threading.Condition()
        self._waiters = 0  # threads in wait_for_sync's wait on _cond (under it): a new reading notifies only them
        self._parts: dict[int, tuple] = {}  # cob_id -> decoded values, TPDOs of the pending SYNC
        self._parts_sync = -1  # the SYNC they answer
        self._decoders: dict[int, tuple[struct.Struct, tuple[int, ...], int]] = {}  # cob_id -> struct, indices, every
        self._cyclic = 0  # TPDOs that make a reading: those sent at the node's feedback SYNCs (every ``every``-th)
        self._slow: dict[int, int] = {}  # latest values of the TPDOs sent every n-th SYNC, by OD index
        self.malformed = 0  # TPDO frames shorter than their mapping
        self._latest = None
        self._seq = 0
        self.frames = 0
        self.incomplete = 0  # SYNCs for which some TPDO never came
        self.operational = False

    # -- life cycle ----------------------------------------------------------------------------------
    def _sdo_fail(self, what: str, exc: Exception) -> DeviceError:
        return DeviceError(f"{self.name} (CAN node {self.node_id}): {what} failed: {exc}")

    def sdo_read(self, index: int, subindex: int = 0) -> int:
        try:
            var = self.node.sdo[index] if subindex == 0 else self.node.sdo[index][subindex]
            return var.raw
        except (SdoCommunicationError, SdoAbortedError) as exc:
            raise self._sdo_fail(f"SDO read of 0x{index:04X}:{subindex:02X}", exc) from exc

    def sdo_write(self, index: int, value: int, subindex: int = 0) -> None:
        try:
            var = self.node.sdo[index] if subindex == 0 else self.node.sdo[index][subindex]
            var.raw = value
        except (SdoCommunicationError, SdoAbortedError) as exc:
            raise self._sdo_fail(f"SDO write of 0x{index:04X}:{subindex:02X} = {value}", exc) from exc

    def _open_node(self) -> None:
        """Add the RemoteNode, pre-operational, device type check, heartbeat; the PDOs are configured next."""
        if self.node is not None:
            return
        node = canopen.RemoteNode(self.node_id, self.eds)
        self.network.add_node(node)
        self.node = node
        node.nmt.state = "PRE-OPERATIONAL"
        device_type = self.sdo_read(0x1000)
        if device_type & 0xFFFF != self.profile:
            raise DeviceError(f"{self.name} (CAN node {self.node_id}) reports device type 0x{device_type:08X}, "
                              f"not a CiA {self.profile} device")
        node.emcy.add_callback(self._on_emcy)
        self.heartbeat = HeartbeatMonitor(node, self.heartbeat_period, self.clock, self.heartbeat_factor)
        self.sdo_write(0x1017, int(round(self.heartbeat_period * 1000)))

    def _map_tpdo(self, number: int, entries: list[tuple[int, int]], every: int = 1) -> None:
        """TPDO ``number`` (1-based) carries ``entries`` [(index, bits)], sent at every ``every``-th SYNC (CiA 301
        transmission type 1..240, checked by :func:`check_every`). Its frames are decoded here by COB-ID (see
        :meth:`_on_frame`)."""
        pdo = self.node.tpdo[number]
        pdo.clear()
        for index, bits in entries:
            pdo.add_variable(index, 0, bits)
        pdo.cob_id = 0x180 + 0x100 * (number - 1) + self.node_id
        pdo.trans_type = every
        # Every n-th SYNC: from the SYNC whose counter is 1 (CiA 301 SYNC start value, 0x18xx:06), so that the
        # master knows which SYNCs carry it (n divides the counter overflow, see check_every).
        if every > 1 and 6 not in pdo.com_record.od:
            raise DeviceError(f"{self.name} (CAN node {self.node_id}): its EDS has no SYNC start value 0x"
                              f"{pdo.com_record.od.index:04X}:06, needed to send TPDO{number} every {every} SYNCs")
        pdo.sync_start_value = 1 if every > 1 else None
        pdo.enabled = True
        try:
            pdo.save()
        except (SdoCommunicationError, SdoAbortedError) as exc:
            com = pdo.com_record.od.index
            hint = (f" at every {every} SYNCs from SYNC start value 1 (a node without 0x{com:04X}:06 needs "
                    f"'can: sync_overflow: 0' in the device file: feedback at every SYNC)") if every > 1 else ""
            raise self._sdo_fail(f"mapping TPDO{number}{hint}", exc) from exc
        # canopen's PdoMap subscribed itself to decode into its variables; this driver decodes the frame in one
        # struct call instead (a PDO arrives every few milliseconds for every node).
        self.network.unsubscribe(pdo.cob_id, pdo.on_message)
        fmt = "<" + "".join(_code(self.node.object_dictionary[i].data_type) for i, _ in entries)
        self._decoders[pdo.cob_id] = (struct.Struct(fmt), tuple(i for i, _ in entries), every)
        self._cyclic = sum(1 for _, _, n in self._decoders.values() if n == self.every)
        self.network.subscribe(pdo.cob_id, self._on_frame)

    def _disable_pdo(self, com_index: int, cob_base: int, number: int) -> None:
        if com_index in self.node.object_dictionary:
            self.sdo_write(com_index, 0x80000000 | (cob_base + 0x100 * (number - 1) + self.node_id), 1)

    def _start(self) -> None:
        nxt = self.sync.count + 1  # the node starts counting at the first SYNC with counter 1 from now on
        self._first_due = nxt if self.every == 1 else nxt + (1 - self.sync.wire_counter(nxt)) % self.sync.overflow
        self.node.nmt.state = "OPERATIONAL"
        self.heartbeat.state = None  # a heartbeat already in flight may still say pre-operational
        self.heartbeat.start()
        self.operational = True

    def close(self) -> None:
        """Stop the node (NMT pre-operational) and detach it from the network; safe to call twice."""
        node, self.node = self.node, None
        self.operational = False
        if node is None:
            return
        try:
            node.nmt.state = "PRE-OPERATIONAL"
        except Exception:  # the bus may already be gone
            pass
        for cob_id in self._decoders:
            try:
                self.network.unsubscribe(cob_id, self._on_frame)
            except (KeyError, ValueError):
                pass
        self._decoders.clear()
        if node.id in self.network:
            del self.network[node.id]

    # -- reception ------------------------------------------------------------------------------------
    def _on_emcy(self, entry) -> None:
        if entry.code & 0xFF00:
            self.emcy_faults.append(f"{self.name} (CAN node {self.node_id}) emergency 0x{entry.code:04X} "
                                    f"({entry.get_desc() or 'device specific'}), error register "
                                    f"0x{entry.register:02X}")
        else:
            self.emcy_faults.clear()

    def _on_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """One TPDO frame. The TPDOs sent at the node's feedback SYNCs (every ``every``-th) make one reading when
        all of them answered the same SYNC; a TPDO sent at another rate (the drive's velocity) only refreshes the
        values it carries, which every later reading includes."""
        st, indices, every = self._decoders[can_id]
        if len(data) < st.size:
            self.malformed += 1
            return
        values = st.unpack_from(data)
        count = self.sync.count
        with self._cond:
            self.frames += 1
            if every != self.every:
                self._slow.update(zip(indices, values, strict=True))
                latest = self._latest
                if latest is not None and latest.sync_count == count:  # it followed the TPDOs of its SYNC
                    self._latest = self._refresh(latest, self._slow)
                    if self._waiters:
                        self._cond.notify_all()
                return
            parts = self._parts
            if parts and self._parts_sync != count:
                self.incomplete += 1
                parts.clear()
            self._parts_sync = count
            parts[can_id] = values
            if len(parts) < self._cyclic:
                return
            merged = dict(self._slow)
            for cid, vals in parts.items():
                merged.update(zip(self._decoders[cid][1], vals, strict=True))
            parts.clear()
            self._seq += 1
            self._latest = self._make_reading(self.clock(), self._seq, count, merged)
            if self._waiters:
                self._cond.notify_all()

    def _make_reading(self, t: float, seq: int, sync_count: int, values: dict[int, int]):
        raise NotImplementedError

    def _refresh(self, reading, slow: dict[int, int]):
        """``reading`` with the values of the TPDOs sent every n-th SYNC that arrived after it for its SYNC."""
        return reading

    def latest(self):
        """The last complete reading (all TPDOs of one SYNC), or None."""
        return self._latest

    def due(self, count: int) -> bool:
        """Whether the node answers SYNC ``count`` with its readings (every ``every``-th SYNC once started)."""
        every = self.every
        if every == 1:
            return True
        first = self._first_due
        # the first due SYNC carries counter 1 and ``every`` divides the counter's overflow (check_every): the SYNCs
        # whose counter is 1 modulo ``every`` are those a multiple of ``every`` after it
        return first is not None and count >= first and (count - first) % every == 0

    def last_due(self, count: int) -> int | None:
        """The last SYNC count <= ``count`` that the node answers, None if none yet."""
        if self.every == 1:
            return count
        first = self._first_due
        if first is None or count < first:
            return None
        return count - (count - first) % self.every  # as due(): the multiples of every after the first

    def wait_for_sync(self, count: int, timeout: float = 1.0):
        """Block (wall time) until the reading answering SYNC ``count`` (or a later one) has arrived. A node that
        answers every n-th SYNC only: the reading of the last SYNC it answered up to ``count``.

        On a pumped network (``drivers.can_bus.Network``, the simulated prototype in lockstep) the answer has
        normally been decoded when the SYNC was sent; the wait pumps the channel every 2 ms in case."""
        wanted = self.last_due(count)
        if wanted is None:
            raise DeviceError(f"{self.name} (CAN node {self.node_id}) sends its readings every {self.every} SYNCs "
                              f"from SYNC {self._first_due}: none is due by SYNC {count}")
        count = wanted
        r = self._latest
        if r is not None and r.sync_count >= count:
            return r
        pump = self.network.pump if getattr(self.network, "pumped", False) else None
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._latest is None or self._latest.sync_count < count:
                if pump is not None:
                    pump()
                    if self._latest is not None and self._latest.sync_count >= count:
                        break
                left = deadline - time.monotonic()
                if left <= 0:
                    have = -1 if self._latest is None else self._latest.sync_count
                    raise DeviceError(f"{self.name} (CAN node {self.node_id}) sent no PDOs for SYNC {count} "
                                      f"within {timeout:.3f} s (last complete SYNC {have})")
                self._waiters += 1
                try:
                    self._cond.wait(left if pump is None else min(left, 0.002))
                finally:
                    self._waiters -= 1
            return self._latest

    # -- state -------------------------------------------------------------------------------------------
    def nmt_state(self) -> str:
        if self.heartbeat is None:
            return "CLOSED"
        if self.heartbeat.state is not None:
            return NMT_STATE_NAMES.get(self.heartbeat.state, f"state {self.heartbeat.state}")
        return self.node.nmt.state if self.node is not None else "CLOSED"

    def _link_fault(self) -> str | None:
        if self.emcy_faults:
            return self.emcy_faults[-1]
        if self.heartbeat is not None and self.node is not None:
            loss = self.heartbeat.describe_loss(self.name)
            if loss:
                return loss
            if self.heartbeat.state is not None and self.heartbeat.state not in (5,):
                return (f"{self.name} (CAN node {self.node_id}) left the operational state: its heartbeat "
                        f"reports {NMT_STATE_NAMES.get(self.heartbeat.state, self.heartbeat.state)}")
        return None


_STRUCT_CODES = {datatypes.UNSIGNED8: "B", datatypes.INTEGER8: "b", datatypes.UNSIGNED16: "H",
                 datatypes.INTEGER16: "h", datatypes.UNSIGNED32: "I", datatypes.INTEGER32: "i"}


def _code(data_type: int) -> str:
    """struct code of a CANopen integer data type."""
    return _STRUCT_CODES[data_type]


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
                if self.state() in ("operation enabled", "quick stop active"):
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
        return cia402_state(self.statusword())

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
        if s in ("fault", "fault reaction active"):
            self.fault_reset()
        elif s == "quick stop active":
            self._command(CW_DISABLE_VOLTAGE)
            self._expect("switch on disabled")
        if self.state() != "operation enabled":
            self._command(CW_SHUTDOWN)
            self._expect("ready to switch on")
            self._command(CW_SWITCH_ON)
            self._expect("switched on")
            self._command(CW_ENABLE)
            self._expect("operation enabled")

    def disable(self) -> None:
        """Disable voltage: switch on disabled, torque off."""
        self._command(CW_DISABLE_VOLTAGE)
        self._expect("switch on disabled", "fault")

    def quick_stop(self) -> None:
        """CiA 402 quick stop (the drive stops and holds, option code 0x605A)."""
        self._command(CW_QUICK_STOP)
        self._expect("quick stop active", "switch on disabled", "fault")

    def fault_reset(self) -> None:
        """Rising edge of controlword bit 7; the drive goes to switch on disabled."""
        if self.controlword & CW_FAULT_RESET:
            self._command(CW_DISABLE_VOLTAGE)
        self.emcy_faults.clear()
        self._command(CW_FAULT_RESET)
        self._expect("switch on disabled")
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
        return r is not None and cia402_state(r.statusword) == "operation enabled" and self.fault() is None

    def fault(self) -> str | None:
        """EMCY, statusword fault bit or lost heartbeat, as one sentence; None when healthy."""
        link = self._link_fault()
        if link:
            return link
        r = self._latest
        if r is not None and r.statusword & 0x08:
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
            drive = cia402_state(r.statusword)
            feedback = f"position {r.position_counts} counts, torque {r.torque:.3f} N m, SYNC {r.sync_count}"
        fault = self.fault()
        return (f"{self.name}: CAN node {self.node_id}, NMT {self.nmt_state()}, {drive}, "
                f"{MODE_NAMES.get(self.mode, self.mode)}, {feedback}" + (f"; FAULT: {fault}" if fault else ""))
