"""Emulated CiA 402 winch servo drives on a canopen LocalNode (object dictionary drivers/od/cia402_winch.eds).

The nodes act on SYNC, never on wall time (see the simulator backend): for each SYNC the backend publishes
the plant's state of that instant, calls :meth:`CanDriveEmulator.apply_targets` (the RPDO received since
the last SYNC takes effect, CiA 301 synchronous RPDO: the plant steps with it towards the next SYNC) for
every drive, then :meth:`on_sync` for every node with something due (:meth:`SimulatedNode.idle_at`),
which reads the plant and transmits the TPDOs whose transmission type is due; heartbeats follow the
simulated time (every 0x1017 ms of ``plant.time``). SDO requests are answered at once by the canopen SDO
server, with live values for the process objects (statusword, position, velocity, torque).

Holding brake: when the plant has one (``set_brake(i, engaged)``, as ``sim_backend.physics`` does), the
drive releases it on entering operation enabled and engages it on leaving (disable, fault, quick stop), as
servo drives do; without one, quick stop holds the latched torque with velocity damping.

Units on the wire: 0x6064 position in motor encoder increments (20 bits per revolution, relative to
power-on), 0x606C velocity in increments/s, 0x6071/0x6077 torque in per mille of 0x6076 (mN m), 0x60FF
target velocity in increments/s.
"""

from __future__ import annotations

import math
import struct
import threading
from dataclasses import dataclass
from pathlib import Path

import canopen
import numpy as np
from canopen.objectdictionary import datatypes

from drivers.cia402 import (
    FAULT,
    MODE_CST,
    MODE_CSV,
    NOT_READY,
    OPERATION_ENABLED,
    QUICK_STOP_ACTIVE,
    STATUSWORD_BITS,
    SW_FOLLOWS_COMMAND,
    SW_REMOTE,
    SWITCH_ON_DISABLED,
    next_state,
)
from drivers.config import eds_path
from sim_backend.plant import Plant, scalar_reader

_STRUCT_CODES = {
    datatypes.BOOLEAN: "B", datatypes.UNSIGNED8: "B", datatypes.INTEGER8: "b",
    datatypes.UNSIGNED16: "H", datatypes.INTEGER16: "h", datatypes.UNSIGNED32: "I", datatypes.INTEGER32: "i",
}
_RANGES = {"B": (0, 0xFF), "b": (-0x80, 0x7F), "H": (0, 0xFFFF), "h": (-0x8000, 0x7FFF),
           "I": (0, 0xFFFFFFFF), "i": (-0x80000000, 0x7FFFFFFF)}


def pdo_struct(pdo_map) -> tuple[struct.Struct, list[tuple[int, int]]] | None:
    """A little-endian struct for a byte-aligned PDO map and its (index, subindex) list; None otherwise."""
    fmt, keys = "<", []
    for var in pdo_map.map:
        code = _STRUCT_CODES.get(var.od.data_type)
        if code is None or var.length != len(var.od) or var.offset % 8:
            return None
        fmt += code
        keys.append((var.index, var.subindex))
    return struct.Struct(fmt), keys


def clamp_int(code: str, value: float) -> int:
    """Round and saturate ``value`` to the range of the struct code (wrap 32-bit signed)."""
    if code == "i":
        return _wrap32(value)  # a 32-bit position counter wraps
    lo, hi = _RANGES[code]
    return min(max(int(round(value)), lo), hi)


def _wrap32(value: float) -> int:
    """Rounded and wrapped to a signed 32-bit counter (``clamp_int("i", value)``, called directly on the TPDO hot
    path)."""
    return (int(round(value)) + 0x80000000) % 0x100000000 - 0x80000000


# what an object mapped in an RPDO sets on the drive at SYNC (the controlword goes through the state machine);
# other objects mapped there are ignored
_RPDO_FIELDS = {0x6040: "controlword", 0x6071: "target_torque", 0x60FF: "target_velocity", 0x6060: "mode"}


@dataclass(slots=True)
class _Tpdo:
    """One synchronous TPDO of an emulated node and its SYNC countdown."""

    cob_id: int
    every: int  # transmission type n: every n-th SYNC
    start: int  # SYNC start value (0x18xx:06), 0 for none
    st: struct.Struct
    getters: list  # zero-argument functions giving the mapped values
    left: int  # SYNCs until the next transmission; -1 while waiting for the SYNC whose counter is ``start``


@dataclass
class FrameLoss:
    """Outgoing frames of a node are lost with probability ``fraction`` while start <= plant.time < stop."""

    fraction: float
    start: float = 0.0
    stop: float = math.inf
    kinds: tuple[str, ...] = ("tpdo", "heartbeat", "emcy")


class SimulatedNode:
    """What every emulated CANopen node shares: the LocalNode, NMT, SYNC-driven TPDOs, sim-time heartbeat,
    frame loss. Subclasses provide :meth:`process_value` (live values of the mapped objects)."""

    eds_name = ""

    def __init__(self, network: canopen.Network, node_id: int, plant: Plant, index: int,
                 rng: np.random.Generator | None = None, eds: str | Path | None = None):
        self.network = network
        self.plant = plant
        self.index = index
        self.rng = rng if rng is not None else np.random.default_rng(node_id)
        self.node = canopen.LocalNode(node_id, str(eds or eds_path(self.eds_name)))
        self.node.nmt.start_heartbeat = self._set_heartbeat_ms  # sim-time heartbeat instead of a wall timer
        network.add_node(self.node)
        network.subscribe(0, self._on_nmt)
        self.lock = threading.RLock()
        self.heartbeat_period = 0.0
        self._next_heartbeat = math.inf
        self._tpdos: list[_Tpdo] = []  # the TPDOs sent at SYNC, from the mapping the master wrote
        self.losses: list[FrameLoss] = []
        self.frames_sent = 0
        self.frames_lost = 0
        self.last_sync_count = -1  # the last SYNC seen, skipped ones included (see idle_at)
        self.quiet_until = -1  # the last SYNC count of the quiet run ahead (see idle_at), -1 for none
        self._counted = -1  # the SYNC count the TPDO counters stand at
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        self.boot()

    # -- NMT -----------------------------------------------------------------------------------------
    @property
    def node_id(self) -> int:
        return self.node.id

    @property
    def nmt_state(self) -> str:
        return self.node.nmt.state

    def boot(self) -> None:
        """Power-on: boot-up frame, then pre-operational (heartbeat from 0x1017)."""
        self._end_quiet()
        self.node.nmt.state = "INITIALISING"  # sends the boot-up frame
        self.node.nmt.state = "PRE-OPERATIONAL"

    def _set_heartbeat_ms(self, ms: int) -> None:
        with self.lock:
            self.heartbeat_period = ms / 1000.0
            self._next_heartbeat = self.plant.time + self.heartbeat_period if ms > 0 else math.inf

    def _on_nmt(self, can_id, data, timestamp) -> None:
        if len(data) >= 2 and data[1] in (0, self.node.id):
            self._end_quiet()  # the state may change: the next SYNC takes the full path
            if data[0] == 1:  # start remote node: the PDO configuration written by SDO takes effect
                self.load_pdo_config()
            elif data[0] in (129, 130):  # reset node (every object) / communication (0x1000-0x1FFF)
                for index in list(self.node.data_store):
                    if data[0] == 129 or 0x1000 <= index <= 0x1FFF:
                        del self.node.data_store[index]
                self.reset()

    def reset(self) -> None:
        with self.lock:
            self._tpdos = []
        self.boot()

    def load_pdo_config(self) -> None:
        """Read the PDO communication and mapping objects of the local OD (as written by the master)."""
        with self.lock:
            self._end_quiet()
            self._tpdos = []
            self.node.tpdo.read()
            for pdo_map in self.node.tpdo.map.values():
                if not pdo_map.enabled or not pdo_map.map or not 1 <= (pdo_map.trans_type or 0) <= 240:
                    continue
                packed = pdo_struct(pdo_map)
                if packed is None:
                    continue
                st, keys = packed
                getters = [self._getter(index, sub, code) for (index, sub), code in zip(keys, st.format[1:],
                                                                                       strict=True)]
                every, start = pdo_map.trans_type, self._sync_start_value(pdo_map)
                self._tpdos.append(_Tpdo(pdo_map.cob_id, every, start, st, getters,
                                         -1 if start and every > 1 else every))
            self.on_rpdo_config()

    @staticmethod
    def _sync_start_value(pdo_map) -> int:
        """0x18xx:06 as stored in the local OD (canopen's PdoMap.read only reads it for event-driven types)."""
        try:
            return int(pdo_map.com_record[6].raw or 0)
        except (KeyError, canopen.SdoAbortedError):
            return 0

    def _getter(self, index: int, subindex: int, code: str):
        """A zero-argument function giving the wire value of a mapped object (an int in the range of ``code``):
        the node's :meth:`live_getter` if it has one, else its :meth:`process_value` rounded and saturated."""
        fast = self.live_getter(index, subindex)
        if fast is not None:
            return fast
        value = self.process_value
        return lambda: clamp_int(code, value(index, subindex))

    def live_getter(self, index: int, subindex: int):
        """A zero-argument function giving the wire value of a process object mapped in a TPDO, or None to use
        :meth:`process_value` (nodes override it for the objects they send at every SYNC)."""
        return None

    def on_rpdo_config(self) -> None:
        """Drives read their RPDO maps here."""

    @property
    def tpdo_layout(self) -> list[tuple[int, str]]:
        """(COB-ID, struct format) of each TPDO the node sends at SYNC, as the master mapped them."""
        return [(tp.cob_id, tp.st.format) for tp in self._tpdos]

    # -- SDO live values ---------------------------------------------------------------------------
    def _on_read(self, index, subindex, od):
        return self.process_value(index, subindex)

    def _on_write(self, index, subindex, od, data):
        self.on_object_written(index, subindex, od.decode_raw(bytes(data)))

    def process_value(self, index: int, subindex: int):
        """Live value of a process object, or None to use the stored one."""
        return None

    def on_object_written(self, index: int, subindex: int, value) -> None:
        """Called for every SDO write (before the value is stored)."""

    # -- SYNC ---------------------------------------------------------------------------------------
    def on_sync(self, sync_count: int, counter: int = 0) -> None:
        """After the physics step: the heartbeat if due, then the TPDOs due at this SYNC (in this order, so
        that a master that has the TPDOs of a SYNC has also seen that tick's heartbeat and EMCY).

        ``counter``: the counter byte of the SYNC (0 when it carries none). A TPDO of transmission type n goes
        out at every n-th SYNC since the node was started; with a SYNC start value s (0x18xx:06, used only
        with a counting SYNC) the SYNC with counter s is the first one counted and carries the first
        transmission."""
        with self.lock:
            self._catch_up(sync_count - 1)
            self._counted = self.last_sync_count = sync_count
            self.before_tpdo()
            now = self.plant.time
            if now >= self._next_heartbeat - 1e-9:
                state = {"OPERATIONAL": 5, "STOPPED": 4, "PRE-OPERATIONAL": 127}.get(self.node.nmt.state, 0)
                self.send(0x700 + self.node.id, bytes([state]), "heartbeat")
                while self._next_heartbeat <= now + 1e-9:
                    self._next_heartbeat += self.heartbeat_period
            if self.node.nmt.state == "OPERATIONAL":
                for tp in self._tpdos:
                    left = tp.left
                    if left < 0:  # waiting for the SYNC start value
                        if counter and counter != tp.start:
                            continue
                        left = 1
                    if left == 1:
                        tp.left = tp.every
                        self.send(tp.cob_id, tp.st.pack(*[g() for g in tp.getters]), "tpdo")
                    else:
                        tp.left = left - 1
            quiet = self._quiet_syncs()
            self.quiet_until = sync_count + quiet if quiet else -1

    def idle_at(self, sync_count: int, sim_time: float) -> bool:
        """Whether SYNC ``sync_count`` at ``sim_time`` (s) needs nothing of this node but advancing its
        transmission counters (no TPDO, heartbeat or scheduled fault due): the caller may then skip
        :meth:`on_sync` and only set :attr:`last_sync_count`; the next full SYNC counts the skipped ones."""
        return sync_count <= self.quiet_until and sim_time < self._next_heartbeat - 1e-9

    def _quiet_syncs(self) -> int:
        """How many of the next SYNCs need nothing of this node but its transmission counters (its heartbeat
        is checked at each): operational, every TPDO counted from the start and none due before then. Ended
        by anything that changes that (NMT, PDO configuration, a scheduled fault: :meth:`_end_quiet`)."""
        if not self._tpdos or self.node.nmt.state != "OPERATIONAL":
            return 0
        least = min(tp.left for tp in self._tpdos)
        return least - 1 if least > 1 else 0

    def _catch_up(self, upto: int) -> None:
        """Advance the TPDO counters over the quiet SYNCs skipped since the last full one, up to ``upto``."""
        lag = min(upto, self.quiet_until) - self._counted
        if lag > 0:
            for tp in self._tpdos:
                tp.left -= lag
            self._counted += lag

    def _end_quiet(self) -> None:
        """Count the SYNCs skipped so far and take the full path from the next one on."""
        self._catch_up(self.last_sync_count)
        self.quiet_until = -1

    def before_tpdo(self) -> None:
        """Hook run at each SYNC before the TPDOs are built."""

    # -- transmission with loss --------------------------------------------------------------------
    def lose_frames(self, fraction: float = 1.0, start: float | None = None, duration: float = math.inf,
                    kinds: tuple[str, ...] = ("tpdo", "heartbeat", "emcy")) -> FrameLoss:
        """Lose a fraction of this node's outgoing frames from ``start`` (sim time, s; default now) for
        ``duration`` s; ``kinds`` restricts it to TPDOs, heartbeats and/or EMCYs."""
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"frame loss fraction must be in [0, 1], got {fraction}")
        t0 = self.plant.time if start is None else float(start)
        loss = FrameLoss(float(fraction), t0, t0 + duration, tuple(kinds))
        with self.lock:
            self.losses.append(loss)
        return loss

    def clear_frame_loss(self) -> None:
        with self.lock:
            self.losses = []

    def send(self, cob_id: int, data: bytes, kind: str) -> bool:
        """Send a frame unless an active loss window drops it; returns whether it was sent."""
        if self.losses:
            now = self.plant.time
            for loss in self.losses:
                if kind in loss.kinds and loss.start <= now < loss.stop:
                    if loss.fraction >= 1.0 or self.rng.random() < loss.fraction:
                        self.frames_lost += 1
                        return False
        self.network.send_message(cob_id, data)
        self.frames_sent += 1
        return True

    def close(self) -> None:
        """Detach the node from the network."""
        self.network.unsubscribe(0, self._on_nmt)
        if self.node.id in self.network:
            del self.network[self.node.id]


@dataclass(frozen=True)
class DriveEmulatorConfig:
    """Servo behaviour outside plain torque following (CSV velocity loop, quick-stop hold) and sensor noise."""

    velocity_kp: float = 0.05  # N m per rad/s, CSV velocity loop
    velocity_ki: float = 0.5  # N m per rad
    hold_kd: float = 0.02  # N m s/rad, quick-stop velocity damping on a plant without brake
    stop_velocity: float = 0.05  # rad/s, below this a quick stop with option code 1/2 ends
    torque_noise: float = 0.0  # N m, standard deviation of the reported torque
    position_noise: float = 0.0  # rad of motor, standard deviation of the reported position
    encoder_bits: int = 20


class CanDriveEmulator(SimulatedNode):
    """One winch drive: CiA 402 state machine, CST/CSV modes, fault and quick stop, driving ``plant``'s
    motor ``index``."""

    eds_name = "cia402_winch.eds"

    def __init__(self, network: canopen.Network, node_id: int, plant: Plant, index: int,
                 config: DriveEmulatorConfig | None = None, rng: np.random.Generator | None = None,
                 eds: str | Path | None = None, control_period: float = 0.005):
        self.config = config or DriveEmulatorConfig()
        self.counts_per_rev = 1 << self.config.encoder_bits
        self.control_period = control_period
        self._state = NOT_READY
        self.controlword = 0
        self.target_torque = 0  # per mille
        self.target_velocity = 0  # increments/s
        self.mode = MODE_CST
        self.error_code = 0
        self.error_register = 0
        self.torque_command = 0.0  # N m sent to the plant
        # (cob_id, struct, mapped (index, sub), what each mapped object sets: _RPDO_FIELDS, or None)
        self._rpdos: list[tuple[int, struct.Struct, list, tuple[str | None, ...]]] = []
        self._rx: dict[int, bytes | None] = {}  # cob_id -> RPDO data received since the last SYNC
        self._v_integral = 0.0
        self._hold: float | None = None  # torque at quick stop (plant without brake)
        self._scheduled: list[tuple[float, int]] = []
        self.faults: list[tuple[float, int]] = []
        self._torque_now = scalar_reader(plant, "motor_torque", index)  # N m; before booting, which maps TPDOs
        self._position_now = scalar_reader(plant, "motor_position", index)  # rad
        super().__init__(network, node_id, plant, index, rng, eds)
        self.rated_torque = self.node.object_dictionary[0x6076].default / 1000.0  # N m
        self.max_torque = self.node.object_dictionary[0x6072].default  # per mille
        self.quick_stop_option = self.node.object_dictionary[0x605A].default
        self.state = SWITCH_ON_DISABLED  # after initialisation

    # -- object values ------------------------------------------------------------------------------
    @property
    def statusword(self) -> int:
        sw = STATUSWORD_BITS[self._state] | SW_REMOTE
        if self._state == OPERATION_ENABLED and self.mode in (MODE_CST, MODE_CSV):
            sw |= SW_FOLLOWS_COMMAND
        return sw

    def live_getter(self, index: int, subindex: int):
        """Wire values of the objects a drive sends at SYNC, read straight from the plant (the TPDO hot path)."""
        scale = self.counts_per_rev / (2 * math.pi)
        if index == 0x6041:
            return lambda: self.statusword
        if index == 0x6064:
            return lambda: _wrap32(self.position_actual() * scale)
        if index == 0x606C:
            read = scalar_reader(self.plant, "motor_velocity", self.index)
            return lambda: _wrap32(read() * scale)
        if index == 0x6077:
            return self.torque_actual
        return None  # the rest: process_value, rounded and saturated

    def position_actual(self) -> float:
        """The motor angle (rad) the encoder reports: the plant's, with the configured noise."""
        pos = self._position_now()
        if self.config.position_noise:
            pos += self.config.position_noise * self.rng.standard_normal()
        return pos

    def torque_actual(self) -> int:
        """0x6077: the torque commanded to the plant, per mille of the rated torque, with the configured noise."""
        tq = self._torque_now()
        if self.config.torque_noise:
            tq += self.config.torque_noise * self.rng.standard_normal()
        return clamp_int("h", tq / self.rated_torque * 1000.0)

    def process_value(self, index: int, subindex: int):
        if index == 0x6041:
            return self.statusword
        if index == 0x6064:
            return clamp_int("i", self.position_actual() * self.counts_per_rev / (2 * math.pi))
        if index == 0x606C:
            return clamp_int("i", float(self.plant.motor_velocity()[self.index]) * self.counts_per_rev / (2 * math.pi))
        if index == 0x6077:
            return self.torque_actual()
        if index == 0x6040:
            return self.controlword
        if index == 0x6071:
            return self.target_torque
        if index == 0x60FF:
            return self.target_velocity
        if index == 0x6060:
            return self.mode
        if index == 0x6061:
            return self.mode
        if index == 0x603F:
            return self.error_code
        if index == 0x1001:
            return self.error_register
        if index == 0x6076:
            return int(round(self.rated_torque * 1000))
        if index == 0x6072:
            return self.max_torque
        if index == 0x605A:
            return self.quick_stop_option
        return None

    def on_object_written(self, index: int, subindex: int, value) -> None:
        with self.lock:
            if index == 0x6040:
                self.command(int(value))
            elif index == 0x6071:
                self.target_torque = int(value)
            elif index == 0x60FF:
                self.target_velocity = int(value)
            elif index == 0x6060:
                self.mode = int(value)
            elif index == 0x6076:
                self.rated_torque = int(value) / 1000.0
            elif index == 0x6072:
                self.max_torque = int(value)
            elif index == 0x605A:
                self.quick_stop_option = int(value)

    def on_rpdo_config(self) -> None:
        """Take the RPDO maps the master wrote. Each RPDO frame is kept raw by COB-ID (:meth:`_on_rpdo`) and
        decoded once at the next SYNC, instead of through canopen's PdoMap at every frame."""
        self._drop_rpdo_subscriptions()
        self._rpdos = []
        self.node.rpdo.read()  # subscribes the enabled RPDO maps on the network; replaced by _on_rpdo below
        for pdo_map in self.node.rpdo.map.values():
            if not pdo_map.enabled or not pdo_map.map:
                continue
            packed = pdo_struct(pdo_map)
            if packed is not None:
                self.network.unsubscribe(pdo_map.cob_id, pdo_map.on_message)
                self._rx[pdo_map.cob_id] = None
                self.network.subscribe(pdo_map.cob_id, self._on_rpdo)
                fields = tuple(_RPDO_FIELDS.get(index) for index, _ in packed[1])
                self._rpdos.append((pdo_map.cob_id, packed[0], packed[1], fields))

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._rx[can_id] = bytes(data)  # the last one before the SYNC wins (CiA 301 synchronous RPDO)

    def _drop_rpdo_subscriptions(self) -> None:
        for cob_id in self._rx:
            try:
                self.network.unsubscribe(cob_id, self._on_rpdo)
            except (KeyError, ValueError):
                pass
        self._rx = {}

    def close(self) -> None:
        self._drop_rpdo_subscriptions()
        super().close()

    @property
    def rpdo_layout(self) -> list[tuple[int, list[int]]]:
        """(COB-ID, mapped object indices) of each RPDO the drive applies at SYNC."""
        return [(cob_id, [i for i, _ in keys]) for cob_id, _, keys, _ in self._rpdos]

    # -- state machine -------------------------------------------------------------------------------
    @property
    def state(self) -> str:
        return self._state

    @state.setter
    def state(self, new: str) -> None:
        """Enter a CiA 402 state; the holding brake is released only in operation enabled."""
        self._state = new
        set_brake = getattr(self.plant, "set_brake", None)
        if set_brake is not None and new != NOT_READY:
            set_brake(self.index, new != OPERATION_ENABLED)

    def command(self, cw: int) -> None:
        """Apply a controlword (from SDO or the RPDO) to the CiA 402 state machine (``drivers.cia402``)."""
        if self._state == OPERATION_ENABLED and cw & 0x8F == 0x0F and cw == self.controlword:
            return  # a running drive's RPDO at every SYNC: enable operation again changes nothing
        rising_reset = bool(cw & 0x80) and not (self.controlword & 0x80)
        self.controlword = cw
        old = self._state
        new = next_state(old, cw, rising_reset, self.quick_stop_option)
        if new == old:
            return
        self.state = new
        if new == OPERATION_ENABLED:
            self._v_integral = 0.0
        elif new == QUICK_STOP_ACTIVE:
            self._hold = None
        elif old == FAULT:  # fault reset
            self.error_code = 0
            self.error_register = 0
            self.send(0x80 + self.node.id, struct.pack("<HB5s", 0, 0, b""), "emcy")

    def reset(self) -> None:
        """NMT reset node: the application restarts in switch on disabled, errors and targets cleared."""
        with self.lock:
            self.error_code = 0
            self.error_register = 0
            self.target_torque = 0
            self.target_velocity = 0
            self.controlword = 0
            self._rpdos = []
            self.state = SWITCH_ON_DISABLED
        super().reset()

    def trigger_fault(self, code: int = 0x2310, register: int = 0x03) -> None:
        """A drive fault now: torque off, statusword fault bit, EMCY ``code`` (default 0x2310 over-current)."""
        with self.lock:
            self.state = FAULT
            self.error_code = code
            self.error_register = register | 0x01
            self.torque_command = 0.0
            self.plant.set_motor_torque(self.index, 0.0)
            self.faults.append((self.plant.time, code))
            self.send(0x80 + self.node.id, struct.pack("<HB5s", code, self.error_register, b""), "emcy")

    def schedule_fault(self, at_time: float, code: int = 0x2310) -> None:
        """A drive fault when the simulated time reaches ``at_time`` (s)."""
        with self.lock:
            self._scheduled.append((float(at_time), int(code)))
            self._scheduled.sort()
            self._end_quiet()

    def _check_scheduled(self) -> None:
        while self._scheduled and self.plant.time >= self._scheduled[0][0] - 1e-12:
            _, code = self._scheduled.pop(0)
            self.trigger_fault(code)

    # -- SYNC ---------------------------------------------------------------------------------------
    def apply_targets(self) -> None:
        """At SYNC, before the physics step: the last RPDO takes effect, the torque command goes to the plant."""
        with self.lock:
            if self._scheduled:
                self._check_scheduled()
            if self.node.nmt.state == "OPERATIONAL":
                rx = self._rx
                for cob_id, st, _, fields in self._rpdos:
                    data = rx.get(cob_id)
                    if data is None:
                        continue
                    rx[cob_id] = None
                    if len(data) < st.size:
                        continue
                    for field, value in zip(fields, st.unpack_from(data), strict=True):  # in the order mapped
                        if field == "controlword":
                            self.command(value)
                        elif field is not None:
                            setattr(self, field, value)
            self.torque_command = self._torque_law()
            self.plant.set_motor_torque(self.index, self.torque_command)

    def _torque_law(self) -> float:
        limit = self.max_torque / 1000.0 * self.rated_torque
        if self._state == OPERATION_ENABLED:
            self._hold = None
            if self.mode == MODE_CST:
                tq = self.target_torque / 1000.0 * self.rated_torque
            elif self.mode == MODE_CSV:
                v_ref = self.target_velocity * 2 * math.pi / self.counts_per_rev
                err = v_ref - float(self.plant.motor_velocity()[self.index])
                tq = self.config.velocity_kp * err + self.config.velocity_ki * (
                    self._v_integral + err * self.control_period)
                if abs(tq) < limit:  # integrate only while unsaturated (anti-windup)
                    self._v_integral += err * self.control_period
            else:
                tq = 0.0
            return -limit if tq < -limit else limit if tq > limit else tq  # min(max()) without the two calls
        if self.state == QUICK_STOP_ACTIVE:
            vel = float(self.plant.motor_velocity()[self.index])
            if self.quick_stop_option in (1, 2) and abs(vel) < self.config.stop_velocity:
                self.state = SWITCH_ON_DISABLED
                return 0.0
            if getattr(self.plant, "set_brake", None) is not None:
                return 0.0  # the brake holds
            if self._hold is None:
                self._hold = self.torque_command
            return min(max(self._hold - self.config.hold_kd * vel, -limit), limit)
        return 0.0

    def before_tpdo(self) -> None:
        if self._scheduled:
            self._check_scheduled()

    def _quiet_syncs(self) -> int:
        return 0 if self._scheduled else super()._quiet_syncs()
