"""What the CANopen drivers share (CiA 402 winch drives, CiA 406 swivel encoders): :class:`CanopenNodeDriver`.

A canopen.RemoteNode on the shared network, SDO helpers, the heartbeat monitor, the EMCY log, NMT start, TPDO
mapping by SDO (transmission type n: every n-th SYNC, from the SYNC whose counter is 1) and the assembly of the
TPDOs answering one SYNC into one reading stamped with that SYNC's counter (from the shared
:class:`drivers.can_bus.SyncProducer`); the frames are decoded by COB-ID with one struct call each.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

import canopen
from canopen.objectdictionary import datatypes
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.can_bus import NMT_STATE_NAMES, HeartbeatMonitor, SyncProducer
from drivers.config import eds_path
from drivers.interfaces import DeviceError


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
        answers every n-th SYNC only: the reading of the last SYNC it answered up to ``count``."""
        wanted = self.last_due(count)
        if wanted is None:
            raise DeviceError(f"{self.name} (CAN node {self.node_id}) sends its readings every {self.every} SYNCs "
                              f"from SYNC {self._first_due}: none is due by SYNC {count}")
        count = wanted
        r = self._latest
        if r is not None and r.sync_count >= count:
            return r
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._latest is None or self._latest.sync_count < count:
                left = deadline - time.monotonic()
                if left <= 0:
                    have = -1 if self._latest is None else self._latest.sync_count
                    raise DeviceError(f"{self.name} (CAN node {self.node_id}) sent no PDOs for SYNC {count} "
                                      f"within {timeout:.3f} s (last complete SYNC {have})")
                self._waiters += 1
                try:
                    self._cond.wait(left)
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
