"""A single-producer single-consumer ring of byte frames in shared memory, between two processes.

The control loop (the producer) hands records to the live view's publisher process (the consumer) through it.
The producer makes no system call and never waits: it reads the consumer's read index, copies the frame into
its slot and publishes its write index; a full ring drops the frame (``put`` returns False). The consumer
polls. Nothing is locked, so the slowest reader cannot hold anything the loop needs (a pipe's write takes the
pipe's kernel mutex, which its reader holds while it copies).

Layout (``multiprocessing.shared_memory``, little-endian): the write index (frames published, u64) at byte 0,
the read index (frames consumed, u64) at byte 64, ``slots`` and ``slot_size`` (u32) at 128, then from byte
4096 ``slots`` fixed slots of ``slot_size`` bytes. Frame k goes in slot k % slots: a header (sequence k + 1,
u64; payload length, u32, ``END`` for the end record; crc32 of the sequence, length and payload, u32) and
the payload. The producer writes the payload before the header and the header before the write index; the
consumer checks the sequence and crc after its copy, so a frame read before all its bytes are visible (a weakly
ordered CPU, or no fence from Python) is detected as torn, left in place and read again at the next poll.
"""

from __future__ import annotations

import os
import secrets
import struct
import zlib
from multiprocessing import shared_memory

SLOT_SIZE = 4096  # bytes per slot (header included): PIPE_BUF, the pipe's atomic write it replaces
SLOTS = 1024  # slots in a ring: 4 MiB, about the ~1000 records the pipe held
END = 0xFFFF_FFFF  # the payload length of the end record
MAX_TRIES = 50  # polls a torn frame is read again before it is skipped and counted lost
_W, _R, _SHAPE, _DATA = 0, 64, 128, 4096  # byte offsets: write index, read index, geometry, slots
_HEAD = struct.Struct("<QII")  # sequence, length, crc32
_INDEX = struct.Struct("<Q")
_GEOMETRY = struct.Struct("<II")


def ring_name() -> str:
    """A shared-memory name no other ring on this machine has (this process's id and 32 random bits)."""
    return f"cdpr-live-{os.getpid()}-{secrets.token_hex(4)}"


def _check(seq: int, length: int, payload) -> int:
    return zlib.crc32(payload, zlib.crc32(_INDEX.pack(seq) + length.to_bytes(4, "little")))


class ShmRing:
    """One end of a ring: :meth:`create` (the producer's side, which unlinks it) or :meth:`attach` (the
    consumer's). Counters: ``dropped`` (frames refused, full or too long), ``torn`` (reads that failed the
    check), ``lost`` (frames skipped after ``MAX_TRIES`` torn reads)."""

    def __init__(self, shm: shared_memory.SharedMemory, slots: int, slot_size: int, owner: bool):
        self.shm, self.slots, self.slot_size, self.owner = shm, slots, slot_size, owner
        self.name = shm.name
        self.payload_max = slot_size - _HEAD.size
        self.dropped = self.torn = self.lost = 0
        self._w = _INDEX.unpack_from(shm.buf, _W)[0]  # the producer's own copy of what it published
        self._r = _INDEX.unpack_from(shm.buf, _R)[0]  # the consumer's own copy of what it consumed
        self._tries = 0  # torn reads of the frame at the read index

    @classmethod
    def create(cls, slots: int = SLOTS, slot_size: int = SLOT_SIZE, name: str | None = None) -> ShmRing:
        """A new ring of ``slots`` slots of ``slot_size`` bytes (a multiple of 8, at least 64), every page of
        it written once here (so the loop's first frames do not fault)."""
        if slots < 1 or slot_size < 64 or slot_size % 8:
            raise ValueError(f"a ring needs at least one slot of at least 64 bytes, a multiple of 8 (slots "
                             f"{slots}, slot_size {slot_size}).")
        size = _DATA + slots * slot_size
        shm = shared_memory.SharedMemory(name or ring_name(), create=True, size=size)
        shm.buf[:size] = bytes(size)
        _GEOMETRY.pack_into(shm.buf, _SHAPE, slots, slot_size)
        return cls(shm, slots, slot_size, owner=True)

    @classmethod
    def attach(cls, name: str) -> ShmRing:
        """The consumer's side of the ring ``name``."""
        shm = shared_memory.SharedMemory(name)
        slots, slot_size = _GEOMETRY.unpack_from(shm.buf, _SHAPE)
        return cls(shm, slots, slot_size, owner=False)

    # the producer's side: no system call, no wait

    def put(self, data: bytes) -> bool:
        """Publish one frame of 1..``payload_max`` bytes; False (dropped, counted) if the ring is full or the
        frame too long."""
        return self._put(data, len(data)) if 0 < len(data) <= self.payload_max else self._drop()

    def put_end(self) -> bool:
        """Publish the end record; False if the ring is full (not counted as dropped)."""
        return self._put(b"", END, count=False)

    def _put(self, data: bytes, length: int, count: bool = True) -> bool:
        w, buf = self._w, self.shm.buf
        if w - _INDEX.unpack_from(buf, _R)[0] >= self.slots:
            return self._drop() if count else False
        at = _DATA + (w % self.slots) * self.slot_size
        buf[at + _HEAD.size:at + _HEAD.size + len(data)] = data
        _HEAD.pack_into(buf, at, w + 1, length, _check(w + 1, length, data))
        self._w = w + 1
        _INDEX.pack_into(buf, _W, w + 1)
        return True

    def _drop(self) -> bool:
        self.dropped += 1
        return False

    # the consumer's side

    def get(self) -> bytes | None:
        """The next frame's payload (``b""`` for the end record), or None if there is none yet (nothing
        published, or the next frame is torn: read again at the next call)."""
        r, buf = self._r, self.shm.buf
        if r >= _INDEX.unpack_from(buf, _W)[0]:
            return None
        at = _DATA + (r % self.slots) * self.slot_size
        seq, length, crc = _HEAD.unpack_from(buf, at)
        n = 0 if length == END else length
        data = bytes(buf[at + _HEAD.size:at + _HEAD.size + n]) if n <= self.payload_max else None
        if seq != r + 1 or data is None or _check(seq, length, data) != crc or _INDEX.unpack_from(buf, at)[0] != seq:
            self.torn += 1
            self._tries += 1
            if self._tries >= MAX_TRIES:  # never became whole: skip it
                self.lost += 1
                self._consumed(r + 1)
            return None
        self._consumed(r + 1)
        return data

    def _consumed(self, r: int) -> None:
        self._r, self._tries = r, 0
        _INDEX.pack_into(self.shm.buf, _R, r)

    def pending(self) -> int:
        """Frames published and not consumed yet."""
        return _INDEX.unpack_from(self.shm.buf, _W)[0] - _INDEX.unpack_from(self.shm.buf, _R)[0]

    def close(self, unlink: bool | None = None) -> None:
        """Unmap this side and, if ``unlink`` (default: on the producer's side), remove the segment's name (the
        consumer does when the producer's process is gone); safe to call twice."""
        if self.shm is None:
            return
        shm, self.shm = self.shm, None
        shm.close()
        if self.owner if unlink is None else unlink:
            try:
                shm.unlink()
            except FileNotFoundError:  # already removed
                pass

