"""The CAN side of the master: open the bus, the network its nodes share, SYNC, heartbeat supervision.

One :class:`CanNetwork` (a :class:`canopen.Network`, received by its :class:`can.Notifier`) per bus carries every
CANopen node (winch drives and swivel encoders); the drivers share it, and python-can listeners can be attached
to it to see its whole traffic (:meth:`CanNetwork.add_listener`). :class:`SyncProducer` sends the SYNC frames of
the control loop and remembers the counter of the last one, so that each driver can stamp the TPDOs that answer
it with that counter. Only python-can's and canopen's public API is used: any python-can interface works,
the simulated prototype's (``cdpr_sim``, a plugin of ``sim_backend``) included. ``drivers.open`` opens a whole
device file.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import can
import canopen

from drivers.interfaces import DeviceError

SYNC_COB_ID = 0x80
HEARTBEAT_BASE = 0x700


def open_bus(interface: str, channel: str, bitrate: int | None = None, **kwargs) -> can.BusABC:
    """Open a python-can bus (``can.Bus(interface=..., channel=..., bitrate=...)``); DeviceError on failure."""
    if bitrate is not None:
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


class _Tap(can.Listener):
    """The listeners attached to a :class:`CanNetwork`, called one frame at a time (a received frame comes from the
    notifier's thread, a sent one from the sender's) and stopped with the network's notifier."""

    def __init__(self) -> None:
        self.listeners: list[can.Listener] = []
        self._lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            for listener in self.listeners:
                listener.on_message_received(msg)

    def stop(self) -> None:
        with self._lock:
            for listener in self.listeners:
                listener.stop()

    def add(self, listener: can.Listener) -> None:
        with self._lock:
            self.listeners.append(listener)

    def remove(self, listener: can.Listener) -> None:
        with self._lock:
            self.listeners.remove(listener)


class CanNetwork(canopen.Network):
    """:class:`canopen.Network` whose traffic, received and sent, can go to python-can listeners as well.

    :meth:`add_listener` attaches a :class:`can.Listener` (a :class:`can.Logger`, say): it gets every frame the
    network's :class:`can.Notifier` receives (before the CANopen nodes see it) and every frame the network sends
    (``is_rx`` False, time-stamped when handed to the bus, before anything that answers it), one frame at a time,
    and is stopped when the network disconnects.
    """

    NOTIFIER_CYCLE = 0.1  # s, how long closing waits for the receive thread at most

    def __init__(self, bus: can.BusABC | None = None):
        super().__init__(bus)
        self._tap = _Tap()

    def add_listener(self, listener: can.Listener) -> None:
        """Give ``listener`` every frame received and sent from now on."""
        tap = self._tap
        if tap not in self.listeners:  # the first: the tap joins the receivers, ahead of canopen's listener, so
            self.listeners.insert(0, tap)  # that a frame is recorded before anything it causes
            if self.notifier is not None:
                self.notifier.listeners.insert(0, tap)
        tap.add(listener)

    def remove_listener(self, listener: can.Listener) -> None:
        """Stop giving frames to ``listener`` (it is not stopped; ValueError if it was not attached)."""
        self._tap.remove(listener)

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        """As :meth:`canopen.Network.send_message`, the frame also given to the attached listeners."""
        if not self.bus:
            raise RuntimeError("Not connected to CAN bus")
        msg = can.Message(is_extended_id=can_id > 0x7FF, arbitration_id=can_id, data=data, is_remote_frame=remote,
                          is_rx=False)
        with self.send_lock:
            if self._tap.listeners:
                msg.timestamp = time.time()
                self._tap.on_message_received(msg)
            self.bus.send(msg)
        self.check()


def open_network(bus: can.BusABC) -> CanNetwork:
    """A connected :class:`CanNetwork` on ``bus``: its :class:`can.Notifier` receives for every node."""
    return CanNetwork(bus).connect()


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
