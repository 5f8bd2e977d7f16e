"""The shared-memory ring between the control loop and the live view's publisher (acquisition/live_ring.py):
order, wrap-around, full -> drop, the end record, torn frames detected and read again, two processes."""

from __future__ import annotations

import multiprocessing
import struct
from collections import deque

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acquisition.live_ring import _DATA, MAX_TRIES, ShmRing


@pytest.fixture
def ring():
    producer = ShmRing.create(slots=4, slot_size=128)
    consumer = ShmRing.attach(producer.name)
    yield producer, consumer
    consumer.close()
    producer.close()


def test_frames_come_out_in_order_across_the_wrap_and_a_full_ring_drops(ring):
    producer, consumer = ring
    assert (consumer.slots, consumer.slot_size, consumer.payload_max) == (4, 128, 112)
    sent = [bytes([k]) * (1 + 37 * k % 112) for k in range(11)]  # lengths 1..112, 11 frames: the ring wraps twice
    got = []
    for k in range(0, 11, 4):
        assert all(producer.put(f) for f in sent[k:k + 4])
        got += [consumer.get() for _ in sent[k:k + 4]]
        assert consumer.get() is None  # nothing more
    assert got == sent and producer.pending() == 0
    assert all(producer.put(b"x%d" % k) for k in range(4))
    assert not producer.put(b"fifth") and producer.dropped == 1  # full: dropped, counted
    assert not producer.put(b"y" * 113) and not producer.put(b"") and producer.dropped == 3  # too long, empty
    assert not producer.put_end() and producer.dropped == 3  # the end record waits for room, not counted
    assert consumer.get() == b"x0" and producer.put(b"x4") and producer.pending() == 4
    assert [consumer.get() for _ in range(4)] == [b"x1", b"x2", b"x3", b"x4"]
    assert producer.put_end() and consumer.get() == b"" and consumer.get() is None  # the end record
    assert (consumer.torn, consumer.lost) == (0, 0)


def test_a_torn_frame_is_detected_left_in_place_and_read_again(ring):
    """What a weakly ordered CPU may show the consumer: the write index before the frame's bytes (its header
    still of the frame a lap before, or its payload not all there)."""
    producer, consumer = ring
    for k in range(4):
        assert producer.put(b"lap0-%d" % k)
        assert consumer.get() == b"lap0-%d" % k
    assert producer.put(b"lap1-0 payload")  # slot 0 again, sequence 5
    buf, head = consumer.shm.buf, _DATA
    header = bytes(buf[head:head + 16])
    buf[head:head + 8] = struct.pack("<Q", 1)  # the header not visible yet: lap 0's sequence
    assert consumer.get() is None and consumer.torn == 1
    buf[head:head + 16] = header
    buf[head + 16 + 3] ^= 0x20  # the header visible, one payload byte not yet
    assert consumer.get() is None and consumer.torn == 2 and producer.pending() == 1  # left in place
    buf[head + 16 + 3] ^= 0x20  # now all of it
    assert consumer.get() == b"lap1-0 payload" and producer.pending() == 0
    assert producer.put(b"never whole") and producer.put(b"next")
    buf[_DATA + 128 + 16] ^= 0xFF  # slot 1's payload stays wrong: skipped after MAX_TRIES reads, counted lost
    assert [consumer.get() for _ in range(MAX_TRIES)] == [None] * MAX_TRIES
    assert consumer.lost == 1 and consumer.get() == b"next"


@settings(max_examples=60, deadline=None)
@given(st.lists(st.one_of(st.binary(min_size=1, max_size=120), st.none()), max_size=80))
def test_any_interleaving_of_puts_and_gets_keeps_order_and_counts_every_drop(ops):
    """None: the consumer takes a frame; bytes: the producer puts them (a model: a deque of at most 3 slots)."""
    producer = ShmRing.create(slots=3, slot_size=128)
    consumer = ShmRing.attach(producer.name)
    try:
        model: deque[bytes] = deque()
        dropped = 0
        for op in ops:
            if op is None:
                assert consumer.get() == (model.popleft() if model else None)
            else:
                fits = len(op) <= 112 and len(model) < 3
                assert producer.put(op) is fits
                if fits:
                    model.append(op)
                dropped += not fits
        assert [consumer.get() for _ in range(len(model) + 1)] == [*model, None]
        assert producer.dropped == dropped
    finally:
        consumer.close()
        producer.close()


def _consume(name: str, out) -> None:
    """In another process: every frame until the end record, as the integers they carry."""
    import time

    ring = ShmRing.attach(name)
    got = []
    while (data := ring.get()) != b"":
        if data is None:
            time.sleep(0.0005)
        else:
            got.append(struct.unpack("<Q", data[:8])[0])
    out.send((got, ring.torn))
    ring.close()


def test_two_processes_the_consumer_gets_every_frame_not_dropped_in_order_and_the_ring_is_unlinked():
    producer = ShmRing.create(slots=8, slot_size=256)
    ctx = multiprocessing.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_consume, args=(producer.name, send))
    proc.start()
    sent = [k for k in range(20000) if producer.put(struct.pack("<Q", k) + bytes(k % 200))]
    while not producer.put_end():
        pass
    got, torn = recv.recv()
    proc.join(60)
    name = producer.name
    producer.close()
    assert proc.exitcode == 0 and got == sent  # order kept, nothing twice, nothing put lost
    assert len(sent) + producer.dropped == 20000 and len(sent) >= 8  # what did not fit was counted
    with pytest.raises(FileNotFoundError):
        ShmRing.attach(name)  # unlinked by its creator


def test_every_ring_has_its_own_name():
    a, b = ShmRing.create(slots=1, slot_size=64), ShmRing.create(slots=1, slot_size=64)
    try:
        assert a.name != b.name and a.name.startswith("cdpr-live-")
        other = ShmRing.attach(b.name)
        assert a.put(b"a") and other.get() is None  # the other's frames are not seen
        other.close()
    finally:
        a.close()
        b.close()
    with pytest.raises(ValueError, match="slot_size 60"):
        ShmRing.create(slots=1, slot_size=60)
