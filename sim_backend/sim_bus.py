"""The simulated prototype's CAN bus: a python-can interface plugin, ``can.Bus(interface="cdpr_sim", channel=...)``.

Every bus opened on one channel name sees the frames the others send, as on python-can's ``virtual`` interface,
but a frame is delivered in the sender's thread before ``send`` returns: straight to the listeners of the
:class:`can.Notifier` that reads the receiving bus (``can.Notifier.find_instances``) or to the listeners given
to the bus, else into the receive queue of the bus (for its ``recv``). The emulated nodes (canopen LocalNodes
on their own network on the channel) thus handle the master's SYNC, RPDOs and SDO requests within the master's send, and
the master's network has decoded their answers when that send returns: the lockstep needs no thread hand-off
(each costs tens of microseconds) and runs in one fixed order, so that the same seed gives the same frames. A
frame sent during a delivery (an answer) is queued behind the frames before it and delivered by the delivery
under way. Frames are handed over as sent, not copied as ``virtual`` does: a receiver must not change one.
A bus with ``can_filters`` gets its frames through ``recv`` (python-can applies the filters there).

Registered under the entry point group ``can.interface`` (pyproject.toml), so that the drivers open the
simulated prototype's bus from its device file like any other interface.
"""

from __future__ import annotations

import threading
import time
from collections import deque

import can


class _Channel:
    """The buses on one channel name and the frames waiting to be delivered to them."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.buses: tuple[SimBus, ...] = ()
        self.pending: deque[tuple[SimBus, can.Message]] = deque()
        self._lock = threading.Lock()
        self._owner: int | None = None  # the thread delivering now

    def deliver(self) -> None:
        """Deliver every pending frame, in the order sent, answers included; a call from inside a delivery
        returns at once (the delivery under way takes what it queued)."""
        lock = self._lock
        if not lock.acquire(blocking=False):
            if self._owner == threading.get_ident():
                return
            lock.acquire()  # another thread delivers: wait for it, then deliver what is left
        self._owner = threading.get_ident()
        try:
            pending = self.pending
            while pending:
                bus, msg = pending.popleft()
                for receive in bus.receivers():
                    receive(msg)
        finally:
            self._owner = None
            lock.release()


_channels: dict[str, _Channel] = {}
_channels_lock = threading.Lock()


class SimBus(can.BusABC):
    """One bus on a simulated channel (see the module). ``receive_own_messages``: the bus also gets what it sends.
    ``listeners``: the listeners that receive this bus's frames, for a receiver in the simulator's own process
    that needs no :class:`can.Notifier` (the emulated nodes' canopen network: its ``listeners``)."""

    def __init__(self, channel: str, receive_own_messages: bool = False, listeners: list | None = None,
                 **kwargs) -> None:
        if not isinstance(channel, str) or not channel:
            raise can.CanInitializationError(f"a cdpr_sim channel is a non-empty name, not {channel!r}")
        self.channel_info = f"cdpr simulated CAN channel {channel!r}"
        self.receive_own_messages = bool(receive_own_messages)
        self._listeners = listeners
        self._notifier: can.Notifier | None = None
        self._seen: list = []  # the listeners that _calls was made from
        self._calls: tuple = ()
        self._filtered = False
        self._rx: deque[can.Message] = deque()
        self._rx_ready = threading.Condition()
        self._closed = False
        super().__init__(channel=channel, **kwargs)
        with _channels_lock:
            self._channel = _channels.setdefault(channel, _Channel(channel))
            self._channel.buses += (self,)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Put ``msg`` on the channel (time-stamped now) and deliver it, with everything it causes."""
        if self._closed:
            raise can.CanOperationError(f"{self.channel_info} is shut down")
        msg.timestamp = time.time()
        channel = self._channel
        for bus in channel.buses:
            if bus is not self or self.receive_own_messages:
                channel.pending.append((bus, msg))
        channel.deliver()

    def set_filters(self, filters=None) -> None:
        self._filtered = bool(filters)
        super().set_filters(filters)

    def receivers(self) -> tuple:
        """What a frame for this bus is given to: its listeners' ``on_message_received`` (the notifier's that reads
        the bus, or those given at creation), else (no notifier, or filters set) its receive queue."""
        listeners = self._listeners
        if listeners is None:
            notifier = self._notifier
            if notifier is None or notifier.stopped:
                found = can.Notifier.find_instances(self)
                notifier = self._notifier = found[0] if found else None
            if notifier is None or self._filtered:
                return (self._enqueue,)
            listeners = notifier.listeners
        if listeners != self._seen:
            self._seen = list(listeners)
            self._calls = tuple(getattr(x, "on_message_received", x) for x in listeners)
        return self._calls

    def _enqueue(self, msg: can.Message) -> None:
        with self._rx_ready:
            self._rx.append(msg)
            self._rx_ready.notify()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        with self._rx_ready:
            if not self._rx and timeout != 0:
                self._rx_ready.wait_for(lambda: self._rx or self._closed, timeout)
            return (self._rx.popleft() if self._rx else None), False

    def shutdown(self) -> None:
        if not self._closed:
            self._closed = True
            with _channels_lock:
                channel = self._channel
                channel.buses = tuple(b for b in channel.buses if b is not self)
                if not channel.buses and _channels.get(channel.name) is channel:
                    del _channels[channel.name]
            with self._rx_ready:
                self._rx_ready.notify_all()
        super().shutdown()
