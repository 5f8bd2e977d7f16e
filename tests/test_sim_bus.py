"""The simulated prototype's CAN bus (``cdpr_sim``, sim_backend/sim_bus.py) and the master network's listeners."""

from __future__ import annotations

import itertools
import threading

import can
import canopen
import pytest

from drivers.can_bus import open_network
from drivers.config import eds_path

_channels = itertools.count()


def _channel() -> str:
    return f"cdpr-sim-test-{next(_channels)}"


def test_a_plain_receiver_gets_what_a_virtual_bus_would_give_it():
    """A bus no notifier reads gets each frame through recv, with the fields python-can's virtual bus gives."""
    sim, virt = _channel(), _channel()
    buses = [can.Bus(interface="cdpr_sim", channel=sim), can.Bus(interface="cdpr_sim", channel=sim),
             can.Bus(interface="virtual", channel=virt), can.Bus(interface="virtual", channel=virt)]
    try:
        frames = [(0x080, b"\x05", False), (0x201, bytes(range(8)), False), (0x1ABCDE, b"", False),
                  (0x202, b"", True)]
        got, want = [], []
        for sender, receiver, out in ((buses[0], buses[1], got), (buses[2], buses[3], want)):
            for can_id, data, remote in frames:
                sender.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=can_id > 0x7FF,
                                        is_remote_frame=remote))
            out.extend(receiver.recv(1.0) for _ in frames)
            assert receiver.recv(0.0) is None and sender.recv(0.0) is None  # nothing comes back to the sender
        for g, w in zip(got, want, strict=True):
            assert g.equals(w, timestamp_delta=1.0, check_channel=False, check_direction=True), (g, w)
            assert g.timestamp > 0
    finally:
        for b in buses:
            b.shutdown()


def test_the_nodes_answer_within_the_masters_send_in_its_thread():
    """An SDO read of a canopen LocalNode on the channel and the TPDO answering a SYNC are decoded by the master
    before its send returns, in the sending thread, although the master's notifier thread is running."""
    channel = _channel()
    slave = canopen.Network(can.Bus(interface="cdpr_sim", channel=channel)).connect()
    master = open_network(can.Bus(interface="cdpr_sim", channel=channel))
    try:
        node = canopen.LocalNode(3, str(eds_path("cia406_encoder.eds")))
        slave.add_node(node)
        slave.subscribe(0x80, lambda can_id, data, ts: slave.send_message(0x183, bytes([data[0], 0x12])))
        remote = canopen.RemoteNode(3, str(eds_path("cia406_encoder.eds")))
        master.add_node(remote)
        assert remote.sdo[0x1000].raw & 0xFFFF == 406
        got = []
        master.subscribe(0x183, lambda can_id, data, ts: got.append((bytes(data), threading.get_ident())))
        master.send_message(0x80, b"\x07")
        assert got == [(b"\x07\x12", threading.get_ident())]
        assert master.notifier is not None and not master.notifier.stopped
    finally:
        master.disconnect()
        slave.disconnect()


@pytest.mark.parametrize("interface", ["cdpr_sim", "virtual"])
def test_a_listener_on_the_master_network_sees_every_frame_sent_and_received(interface):
    """CanNetwork.add_listener: each request the master sends (is_rx False) comes before the answer it received
    (is_rx True), with a time stamp; the listener is stopped when the network disconnects."""
    channel = _channel()
    slave = canopen.Network(can.Bus(interface=interface, channel=channel)).connect()
    master = open_network(can.Bus(interface=interface, channel=channel))
    stopped = threading.Event()

    class Record(can.BufferedReader):
        def stop(self):
            stopped.set()
            super().stop()

    record = Record()
    try:
        node = canopen.LocalNode(5, str(eds_path("cia406_encoder.eds")))
        slave.add_node(node)
        remote = canopen.RemoteNode(5, str(eds_path("cia406_encoder.eds")))
        master.add_node(remote)
        master.add_listener(record)
        assert remote.sdo[0x6001].raw == 65536  # one SDO upload: request 0x605, answer 0x585
        master.send_message(0x80, b"\x01")
        frames = []
        while (msg := record.get_message(1.0 if len(frames) < 3 else 0.05)) is not None:
            frames.append(msg)
        assert [(m.arbitration_id, m.is_rx) for m in frames] == [(0x605, False), (0x585, True), (0x80, False)]
        assert all(m.timestamp > 1e9 for m in frames)  # wall time, as python-can's loggers expect
        assert frames[1].data[0] >> 5 == 2  # an upload response
        master.remove_listener(record)
        master.send_message(0x80, b"\x02")
        assert record.get_message(0.05) is None
        master.add_listener(record)
    finally:
        master.disconnect()
        slave.disconnect()
    assert stopped.is_set()
