"""The CAN side of the master: open the bus from the device configuration, produce SYNC, watch heartbeats.

One :class:`canopen.Network` per bus carries every CANopen node (winch drives and swivel encoders); the
drivers share it. :class:`SyncProducer` sends the SYNC frames of the control loop and remembers the
counter of the last one, so that each driver can stamp the TPDOs that answer it with that counter.
:func:`open_can_devices` builds the whole CAN side of a :class:`drivers.config.DeviceConfig` (bus, network,
SYNC producer, one driver per drive and encoder) for the acquisition and ``cdpr devices check``.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import can
import canopen
from can.interfaces.virtual import VirtualBus

from drivers.interfaces import DeviceError

_log = logging.getLogger(__name__)

SYNC_COB_ID = 0x80
HEARTBEAT_BASE = 0x700


def open_bus(interface: str, channel: str, bitrate: int | None = None, **kwargs) -> can.BusABC:
    """Open a python-can bus (``can.Bus(interface=..., channel=..., bitrate=...)``); DeviceError on failure."""
    if bitrate is not None and interface != "virtual":
        kwargs["bitrate"] = int(bitrate)
    try:
        return can.Bus(interface=interface, channel=channel, **kwargs)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        raise DeviceError(
            f"cannot open CAN interface {interface!r} channel {channel!r} at {bitrate} bit/s: {exc}"
        ) from exc


def open_bus_from_config(can_config) -> can.BusABC:
    """Open the bus a :class:`drivers.config.CanConfig` describes."""
    return open_bus(can_config.interface, can_config.channel, can_config.bitrate)


class _Frame(can.Message):
    """A frame this master sends. python-can's ``virtual`` interface hands every receiver its own ``deepcopy``
    of it, and the generic deep copy of a :class:`can.Message` and its bytearray costs ~5 us a frame (most of
    a simulated bus's cost); this one copies the fields straight into a plain :class:`can.Message`."""

    __slots__ = ()

    def __deepcopy__(self, memo) -> can.Message:
        m = _new_message(can.Message)
        m.timestamp = self.timestamp
        m.arbitration_id = self.arbitration_id
        m.is_extended_id = self.is_extended_id
        m.is_remote_frame = self.is_remote_frame
        m.is_error_frame = self.is_error_frame
        m.channel = self.channel
        m.dlc = self.dlc
        m.data = bytearray(self.data)
        m.is_fd = self.is_fd
        m.is_rx = self.is_rx
        m.bitrate_switch = self.bitrate_switch
        m.error_state_indicator = self.error_state_indicator
        return m


_new_message = can.Message.__new__


def _virtual_send(bus: VirtualBus, can_id: int, data: bytes, remote: bool, inboxes: dict[queue.Queue, deque]) -> None:
    """``bus.send`` of the frame (``can_id``, ``data``, ``remote``) on a python-can ``virtual`` bus, as
    :meth:`VirtualBus.send` does it (time stamp, channel, ``is_rx``, one copy per receiving queue), but with
    each receiver's :class:`can.Message` built directly: no frame to build and then deep-copy per receiver
    (~3 us a frame; a pumped network sends ~7 frames per control tick). A queue in ``inboxes`` (a pumped
    network's, see :attr:`_Lane.inboxes`) gets the frame appended to its deque."""
    bus._check_if_open()
    timestamp = 0.0 if bus.preserve_timestamps else time.time()  # a new frame's own time stamp is 0.0
    own = bus.queue
    extended = can_id > 0x7FF
    channel = bus.channel_id
    for bus_queue in bus.channel:
        if bus_queue is own and not bus.receive_own_messages:
            continue
        m = _new_message(can.Message)
        m.timestamp = timestamp
        m.arbitration_id = can_id
        m.is_extended_id = extended
        m.is_remote_frame = remote
        m.is_error_frame = False
        m.channel = channel
        m.data = bytearray() if remote or data is None else bytearray(data)
        m.dlc = len(m.data)
        m.is_fd = False
        m.is_rx = bus_queue is not own
        m.bitrate_switch = False
        m.error_state_indicator = False
        inbox = inboxes.get(bus_queue)
        if inbox is not None:
            inbox.append(m)
        else:
            bus_queue.put(m)  # as VirtualBus.send without a timeout: waits while a bounded queue is full


class _Lane:
    """The pumped networks on one python-can ``virtual`` channel and the lock under which one thread at a time
    delivers their queued frames (see :class:`Network`)."""

    def __init__(self, channel) -> None:
        self.channel = channel
        self.networks: list[Network] = []
        self.sent = 0  # frames sent by the pumped networks, to know when a pass delivered something new
        # The receive queues of the pumped networks, unbounded ones, with their deques: only the pump takes from
        # them and nobody blocks on them, so the pumped senders append and the pump pops there directly, without
        # Queue's lock and its conditions to notify (~2 us a frame); deque appends and pops are thread-safe.
        self.inboxes: dict[queue.Queue, deque] = {}
        self._lock = threading.RLock()
        self._owner: int | None = None

    def pump(self) -> None:
        """Deliver every queued frame, network by network in the order they joined, until a whole pass sends
        nothing new. A send from inside a delivery (an answer) only queues: the pass under way delivers it."""
        me = threading.get_ident()
        if self._owner == me:
            return
        with self._lock:
            self._owner = me
            try:
                while True:
                    before = self.sent
                    for net in list(self.networks):
                        net._drain()
                    if self.sent == before:
                        return
            finally:
                self._owner = None


_lanes: dict[object, _Lane] = {}
_lanes_lock = threading.Lock()


class Network(canopen.Network):
    """:class:`canopen.Network` with cheap frame copies (:class:`_Frame`) and an optional pumped mode.

    Pumped (``connect(pumped=True)``, python-can ``virtual`` bus only): no notifier thread; each frame sent by a
    pumped network on the channel is followed, in the sender's thread, by the delivery of every frame queued
    for the pumped networks of that channel, answers included, until the channel is quiet. In-process devices
    that answer at once (the simulated prototype in lockstep) then have answered when ``send_message``
    returns: an SDO response waits for the SDO client, the TPDOs that answer a SYNC are decoded, and no
    thread hand-off happens on the way (each costs tens of microseconds). The frames are python-can's as
    ever (a pumped send puts them in the channel's queues as ``VirtualBus.send`` does, see
    :func:`_virtual_send`); only who reads the queues changes (and how: see :attr:`_Lane.inboxes`). A frame
    from a non-pumped sender waits for the next pump (:meth:`pump`, which the drivers' waits call). A PDO
    (COB-IDs 0x180-0x57F) does not pump by itself: nobody answers one, and the next frame that pumps (the SYNC
    the synchronous RPDOs are meant for, an SDO request) delivers it first, in the order sent; the waits pump
    too.
    """

    def __init__(self, bus: can.BusABC | None = None):
        super().__init__(bus)
        self._lane: _Lane | None = None
        self._inbox: deque | None = None  # pumped: the deque of the bus's receive queue (see _Lane.inboxes)
        self._send_listeners: list[can.Listener] = []  # see add_listener

    @property
    def pumped(self) -> bool:
        return self._lane is not None

    def connect(self, *args, pumped: bool = False, **kwargs) -> Network:
        if not pumped:
            return super().connect(*args, **kwargs)
        if self.bus is None:
            self.bus = can.Bus(*args, **kwargs)
        if not isinstance(self.bus, VirtualBus):
            raise ValueError(f"a pumped CANopen network needs a python-can virtual bus, not {type(self.bus).__name__}")
        channel = self.bus.channel_id
        with _lanes_lock:
            lane = _lanes.get(channel)
            if lane is None:
                lane = _lanes[channel] = _Lane(channel)
            lane.networks.append(self)
            rx = self.bus.queue
            if type(rx) is queue.Queue and rx.maxsize <= 0:
                lane.inboxes[rx] = self._inbox = rx.queue
        self._lane = lane
        return self

    def disconnect(self) -> None:
        lane, self._lane = self._lane, None
        if lane is not None:
            with _lanes_lock:
                if self in lane.networks:
                    lane.networks.remove(self)
                if self._inbox is not None:
                    lane.inboxes.pop(self.bus.queue, None)
                    self._inbox = None
                if not lane.networks and _lanes.get(lane.channel) is lane:
                    del _lanes[lane.channel]
        super().disconnect()

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        bus = self.bus
        if not bus:
            raise RuntimeError("Not connected to CAN bus")
        if self._send_listeners:
            sent = can.Message(timestamp=time.time(), arbitration_id=can_id, is_extended_id=can_id > 0x7FF,
                               is_remote_frame=remote, data=data, is_rx=False)
            for listener in self._send_listeners:
                listener.on_message_received(sent)
        lane = self._lane
        if lane is None:
            msg = _Frame(is_extended_id=can_id > 0x7FF, arbitration_id=can_id, data=data, is_remote_frame=remote)
            with self.send_lock:
                bus.send(msg)
            self.check()
            return
        with self.send_lock:
            _virtual_send(bus, can_id, data, remote, lane.inboxes)
        lane.sent += 1
        if not 0x180 <= can_id < 0x580:  # a PDO waits for the next frame that pumps (see the class)
            lane.pump()

    def add_listener(self, listener: can.Listener) -> None:
        """Hand every frame this network sends and receives to ``listener`` (a :class:`can.Logger`: the raw bus
        record), in bus order. Received frames come through canopen's notifier (or, pumped, the delivery); a
        frame sent is stamped (wall time) and handed over before it leaves, so that the answers it causes
        follow it. python-can's own bus does not receive what it sends (``receive_own_messages``)."""
        if self.notifier is not None:
            self.notifier.add_listener(listener)
        else:
            self.listeners.append(listener)
        self._send_listeners.append(listener)

    def pump(self) -> None:
        """Pumped mode: deliver what is queued on the channel now (no-op otherwise)."""
        if self._lane is not None:
            self._lane.pump()

    def _drain(self) -> None:
        """Deliver the frames queued for this network (see :class:`Network`)."""
        inbox = self._inbox
        if inbox is not None and not inbox:  # nothing queued (most drains of a pass)
            return
        bus = self.bus
        if bus is None:
            return
        listeners = self.listeners
        if (inbox is None or bus.filters or len(listeners) != 1
                or not isinstance(listeners[0], canopen.network.MessageListener)):
            while bus.queue.qsize() and (msg := bus.recv(0.0)) is not None:
                for listener in listeners:
                    listener(msg)
            return
        # The usual case, canopen's own listener alone on an unfiltered bus: what bus.recv and the listener do,
        # without their per-frame layers (a simulated tick moves ~7 frames), the frames taken from the inbox.
        notify = self.notify
        while inbox:
            msg = inbox.popleft()
            if msg.is_error_frame or msg.is_remote_frame:
                continue
            try:
                notify(msg.arbitration_id, msg.data, msg.timestamp)
            except Exception as exc:  # as canopen's listener: a callback's error must not stop the bus
                _log.error("CAN frame 0x%X: %s", msg.arbitration_id, exc)


def pumped_channel(channel) -> bool:
    """Whether pumped networks (:class:`Network`) are on python-can ``virtual`` channel ``channel``."""
    with _lanes_lock:
        return channel in _lanes


def open_network(bus: can.BusABC, pumped: bool | None = None) -> Network:
    """A connected :class:`Network` on ``bus``: a notifier thread receives for every node, or, ``pumped``, the
    senders deliver (see :class:`Network`). ``pumped=None`` follows the channel: a network joining a virtual
    channel where pumped networks already are (the simulated prototype's) is pumped too, as it must be to
    exchange frames with them."""
    if pumped is None:
        pumped = isinstance(bus, VirtualBus) and pumped_channel(bus.channel_id)
    network = Network(bus)
    network.NOTIFIER_CYCLE = 0.1  # s, how long closing waits for the receive thread at most
    network.connect(pumped=pumped)
    return network


class SyncProducer:
    """Sends SYNC frames with the CiA 301 counter and keeps the count of SYNCs sent.

    ``count`` is unwrapped (1, 2, 3, ... since this producer was created); the frame carries
    ``(count - 1) % overflow + 1`` (1..overflow, object 0x1019 of the nodes). With ``overflow=0`` the
    frame carries no counter byte.
    """

    def __init__(self, network: canopen.Network, overflow: int = 240):
        if overflow != 0 and not 2 <= overflow <= 240:
            raise ValueError(f"SYNC counter overflow must be 0 or 2..240, got {overflow}")
        self.network = network
        self.overflow = overflow
        self._count = 0
        self._lock = threading.Lock()

    @property
    def count(self) -> int:
        """Unwrapped counter of the last SYNC sent, 0 before the first."""
        return self._count

    def wire_counter(self, count: int) -> int:
        """The counter byte a SYNC with unwrapped ``count`` carries on the wire."""
        return (count - 1) % self.overflow + 1 if self.overflow else 0

    def send_sync(self) -> int:
        """Send one SYNC; returns its unwrapped counter (recorded before the frame leaves)."""
        with self._lock:
            self._count += 1
            count = self._count
            data = bytes([self.wire_counter(count)]) if self.overflow else b""
            try:
                self.network.send_message(SYNC_COB_ID, data)
            except (can.CanError, OSError, RuntimeError) as exc:
                raise DeviceError(f"sending SYNC {count} failed: {exc}") from exc
        return count


class HeartbeatMonitor:
    """Heartbeat consumer for one node: the node is lost when no heartbeat came for ``factor`` periods.

    Times are taken from ``clock`` (s) when a heartbeat arrives and when the monitor is asked, so that the
    simulated prototype can run it on its own clock. Monitoring starts at :meth:`start` (a node that never
    sends is lost ``factor`` periods later).
    """

    def __init__(self, node: canopen.RemoteNode, period: float, clock: Callable[[], float] = time.monotonic,
                 factor: float = 2.5):
        self.node = node
        self.period = float(period)
        self.clock = clock
        self.factor = float(factor)
        self.last: float | None = None
        self.state: int | None = None  # last NMT state reported (0 boot-up, 4, 5, 127)
        self.count = 0
        self._started: float | None = None
        self._safe_until = math.inf  # clock time before which the node cannot be lost (see describe_loss)
        node.nmt.add_heartbeat_callback(self._on_heartbeat)

    def _on_heartbeat(self, state: int) -> None:
        self.last = self.clock()
        self.state = state
        self.count += 1
        self._watch()

    def start(self) -> None:
        self._started = self.clock()
        self._watch()

    def _watch(self) -> None:
        if self._started is None or self.period <= 0:
            self._safe_until = math.inf
            return
        ref = self.last if self.last is not None and self.last >= self._started else self._started
        self._safe_until = ref + 0.999 * self.factor * self.period  # the exact test runs from there on

    def silence(self) -> float | None:
        """Time since the last heartbeat (or since start), s; None when not monitoring."""
        if self._started is None or self.period <= 0:
            return None
        ref = self.last if self.last is not None and self.last >= self._started else self._started
        return self.clock() - ref

    def lost(self) -> bool:
        silence = self.silence()
        return silence is not None and silence > self.factor * self.period

    def describe_loss(self, name: str) -> str | None:
        """One sentence when the node is lost, else None (asked at every control tick: one clock reading and
        one comparison while heartbeats come in time)."""
        if self.clock() < self._safe_until:
            return None
        silence = self.silence()
        if silence is None or silence <= self.factor * self.period:
            return None
        return (f"{name} (node {self.node.id}) lost its heartbeat: none for {silence:.3f} s "
                f"(period {self.period:.3f} s)")


NMT_STATE_NAMES = {0: "BOOT-UP", 4: "STOPPED", 5: "OPERATIONAL", 127: "PRE-OPERATIONAL"}


@dataclass
class CanDevices:
    """The CANopen side of a device set: one network, the SYNC producer, the drive and encoder drivers
    (cable order). Close it to stop the nodes and release the bus."""

    network: canopen.Network
    sync: SyncProducer
    drives: list = field(default_factory=list)  # CanopenWinchDrive
    encoders: list = field(default_factory=list)  # CanopenSwivelEncoder

    def open(self) -> None:
        """Configure and start every node (DeviceError names the first that fails)."""
        for drv in self.drives + self.encoders:
            drv.open()

    def send_sync(self) -> int:
        return self.sync.send_sync()

    def wait_for_sync(self, count: int, timeout: float = 1.0) -> tuple[list, list]:
        """Readings of every drive and encoder answering SYNC ``count`` (DeviceError on timeout)."""
        return ([d.wait_for_sync(count, timeout) for d in self.drives],
                [e.wait_for_sync(count, timeout) for e in self.encoders])

    def faults(self) -> dict[str, str | None]:
        return {d.name: d.fault() for d in self.drives + self.encoders}

    def close(self) -> None:
        for drv in self.drives + self.encoders:
            drv.close()
        if self.network.bus is not None:
            self.network.disconnect()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_can_devices(config, length_per_motor_rev, swivel_counts_per_rev: int = 65536,
                     clock: Callable[[], float] = time.monotonic, open_nodes: bool = True,
                     bus: can.BusABC | None = None) -> CanDevices:
    """Open the bus of a :class:`drivers.config.DeviceConfig` and create its drivers.

    ``length_per_motor_rev``: m of cable per motor revolution per drive (robot.sensors); ``clock``: time
    source of timestamps and heartbeat checks (the simulated clock in simulation). With ``open_nodes`` the
    nodes are configured and started at once.
    """
    from drivers.canopen_drive import CanopenWinchDrive
    from drivers.swivel_encoder import CanopenSwivelEncoder

    if len(length_per_motor_rev) < len(config.drives):
        raise DeviceError(f"{config.source}: {len(config.drives)} drives but only {len(length_per_motor_rev)} "
                          f"transmission ratios in the robot description")
    network = open_network(bus if bus is not None else open_bus_from_config(config.can))
    sync = SyncProducer(network, config.can.sync_overflow)
    hb = config.can.heartbeat_period
    devices = CanDevices(network, sync)
    devices.drives = [CanopenWinchDrive(network, n.node_id, sync, float(length_per_motor_rev[i]), name=n.name,
                                        clock=clock, heartbeat_period=hb) for i, n in enumerate(config.drives)]
    devices.encoders = [CanopenSwivelEncoder(network, n.node_id, sync, name=n.name, clock=clock,
                                             heartbeat_period=hb, counts_per_rev=swivel_counts_per_rev)
                        for n in config.encoders]
    if open_nodes:
        try:
            devices.open()
        except Exception:
            devices.close()
            raise
    return devices
