"""Xsens Xbus codec: pure functions from bytes to messages and back (MT low-level communication protocol).

A message on the wire is ``FA BID MID LEN [EXT_HI EXT_LO] DATA... CS``: preamble 0xFA, bus identifier
(0xFF, the master), message identifier, payload length (0xFF announces a two-byte big-endian extended
length), the payload, and a checksum chosen so that the bytes from BID to CS sum to 0 modulo 256.
MTData2 payloads are a sequence of items ``XDI(2, big-endian) SIZE(1) DATA``. Floats are big-endian.

Nothing here touches a port or a clock; :class:`XbusDecoder` is the only stateful piece (a byte buffer),
and it never raises on bad input: garbage is counted and skipped.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

PREAMBLE = 0xFA
BUS_MASTER = 0xFF
EXTENDED_LENGTH = 0xFF
MAX_PAYLOAD = 2048  # the longest payload an MTi sends; longer announced lengths are false preambles


class MID:
    """Message identifiers of the subset we speak (acknowledgements are the request id + 1)."""

    REQ_DID = 0x00
    DEVICE_ID = 0x01
    GO_TO_MEASUREMENT = 0x10
    GO_TO_MEASUREMENT_ACK = 0x11
    REQ_PRODUCT_CODE = 0x1C
    PRODUCT_CODE = 0x1D
    GO_TO_CONFIG = 0x30
    GO_TO_CONFIG_ACK = 0x31
    MTDATA2 = 0x36
    WAKE_UP = 0x3E
    WAKE_UP_ACK = 0x3F
    RESET = 0x40
    RESET_ACK = 0x41
    ERROR = 0x42
    SET_OUTPUT_CONFIGURATION = 0xC0
    OUTPUT_CONFIGURATION = 0xC1


class XDI:
    """Xsens data identifiers (MTData2 items). The low nibble selects precision and coordinate frame."""

    PACKET_COUNTER = 0x1020  # uint16
    SAMPLE_TIME_FINE = 0x1060  # uint32, 1/10000 s
    QUATERNION = 0x2010  # 4 x float32 (q0, q1, q2, q3)
    EULER_ANGLES = 0x2030  # 3 x float32 (roll, pitch, yaw), degrees
    STATUS_WORD = 0xE020  # uint32
    FORMAT_MASK = 0x0003  # 0 float32, 1 fp12.20, 2 fp16.32, 3 float64
    FLOAT32 = 0x0000
    FLOAT64 = 0x0003
    MAX_RATE = 0xFFFF  # output frequency "with every packet"


ERROR_CODES = {
    0x03: "invalid period",
    0x04: "invalid message",
    0x1E: "timer overflow",
    0x20: "invalid baud rate",
    0x21: "invalid parameter",
    0x28: "device error",
}

MID_NAMES = {v: k for k, v in vars(MID).items() if not k.startswith("_")}


def mid_name(mid: int) -> str:
    """Readable name of a message id, e.g. ``GO_TO_CONFIG`` or ``0x7A``."""
    return MID_NAMES.get(mid, f"0x{mid:02X}")


def error_text(code: int) -> str:
    return ERROR_CODES.get(code, f"unknown error 0x{code:02X}")


@dataclass(frozen=True)
class Message:
    mid: int
    payload: bytes = b""
    bus_id: int = BUS_MASTER


def checksum(body: bytes) -> int:
    """The checksum byte for ``body`` = BID..last payload byte: makes the sum from BID to CS 0 mod 256."""
    return (-sum(body)) & 0xFF


def encode(mid: int, payload: bytes = b"", bus_id: int = BUS_MASTER) -> bytes:
    """One framed Xbus message; extended length for payloads of 255 bytes or more."""
    n = len(payload)
    if n > 0xFFFF:
        raise ValueError(f"Xbus payload of {n} bytes exceeds 65535")
    if n < EXTENDED_LENGTH:
        body = bytes((bus_id, mid, n)) + payload
    else:
        body = bytes((bus_id, mid, EXTENDED_LENGTH, n >> 8, n & 0xFF)) + payload
    return bytes((PREAMBLE,)) + body + bytes((checksum(body),))


@dataclass
class DecodeCounts:
    """What the decoder threw away: checksum failures, bytes skipped while hunting for a preamble."""

    frames: int = 0
    checksum_errors: int = 0
    bytes_discarded: int = 0
    resyncs: int = 0


def _frame_at(buf: bytes | bytearray, i: int) -> tuple[str, int]:
    """Inspect a candidate frame starting at buf[i] == PREAMBLE.

    Returns (state, end): state "ok" (complete, checksum good, end = index after CS), "length" (an
    impossible extended length: a false preamble), "checksum" (a failed checksum) or "short" (more bytes
    needed).
    """
    n = len(buf)
    if n - i < 4:
        return "short", 0
    length = buf[i + 3]
    head = 4
    if length == EXTENDED_LENGTH:
        if n - i < 6:
            return "short", 0
        length = (buf[i + 4] << 8) | buf[i + 5]
        head = 6
        if length > MAX_PAYLOAD:
            return "length", 0
    end = i + head + length + 1
    if end > n:
        return "short", 0
    if sum(buf[i + 1 : end]) & 0xFF:
        return "checksum", 0
    return "ok", end


def split_frames(buf: bytes | bytearray, counts: DecodeCounts | None = None) -> tuple[list[Message], int]:
    """Decode every complete message in ``buf``; returns (messages, bytes consumed). Never raises.

    Bytes before a preamble are discarded; a failed checksum skips that preamble byte only and hunts on,
    so the next valid frame is found even inside a damaged one. A candidate whose announced length runs
    past the end of the buffer is kept waiting, unless a complete valid frame starts later in the buffer,
    in which case the candidate was garbage and decoding resumes there.
    """
    c = counts if counts is not None else DecodeCounts()
    out: list[Message] = []
    i, n = 0, len(buf)
    while i < n:
        if buf[i] != PREAMBLE:
            j = buf.find(PREAMBLE, i)
            j = n if j < 0 else j
            c.bytes_discarded += j - i
            c.resyncs += 1
            i = j
            continue
        state, end = _frame_at(buf, i)
        if state == "ok":
            length = buf[i + 3]
            start = i + (6 if length == EXTENDED_LENGTH else 4)
            out.append(Message(mid=buf[i + 2], payload=bytes(buf[start : end - 1]), bus_id=buf[i + 1]))
            c.frames += 1
            i = end
        elif state in ("checksum", "length"):
            c.checksum_errors += state == "checksum"
            c.bytes_discarded += 1
            i += 1
        else:  # short: wait for more, unless a valid frame already follows
            j = _next_complete_frame(buf, i + 1)
            if j < 0:
                break
            c.bytes_discarded += j - i
            c.resyncs += 1
            i = j
    return out, i


def _next_complete_frame(buf: bytes | bytearray, start: int) -> int:
    j = buf.find(PREAMBLE, start)
    while j >= 0:
        if _frame_at(buf, j)[0] == "ok":
            return j
        j = buf.find(PREAMBLE, j + 1)
    return -1


@dataclass
class XbusDecoder:
    """Incremental decoder: feed it whatever the port returned, get the complete messages back."""

    counts: DecodeCounts = field(default_factory=DecodeCounts)
    max_buffer: int = 4 * (MAX_PAYLOAD + 7)
    _buf: bytearray = field(default_factory=bytearray, repr=False)

    def feed(self, data: bytes) -> list[Message]:
        self._buf += data
        messages, used = split_frames(self._buf, self.counts)
        del self._buf[:used]
        if len(self._buf) > self.max_buffer:  # cannot happen with bounded lengths; a guard all the same
            self.counts.bytes_discarded += len(self._buf)
            self._buf.clear()
        return messages

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)


# ---- MTData2 -----------------------------------------------------------------------------------------


def encode_mtdata2(items: list[tuple[int, bytes]]) -> bytes:
    """MTData2 payload from (XDI, data) items."""
    out = bytearray()
    for xdi, data in items:
        if len(data) > 255:
            raise ValueError(f"MTData2 item 0x{xdi:04X} of {len(data)} bytes exceeds 255")
        out += struct.pack(">HB", xdi, len(data)) + data
    return bytes(out)


def decode_mtdata2(payload: bytes) -> dict[int, bytes] | None:
    """Items of an MTData2 payload as {XDI: data}; None when an item runs past the payload's end."""
    items: dict[int, bytes] = {}
    i, n = 0, len(payload)
    while i < n:
        if n - i < 3:
            return None
        xdi = (payload[i] << 8) | payload[i + 1]
        size = payload[i + 2]
        if i + 3 + size > n:
            return None
        items[xdi] = bytes(payload[i + 3 : i + 3 + size])
        i += 3 + size
    return items


@dataclass(frozen=True)
class Mtdata2Sample:
    """The fields we use from one MTData2 message; None where the item is absent or malformed."""

    packet_counter: int | None
    sample_time_fine: int | None
    euler_deg: tuple[float, float, float] | None  # roll, pitch, yaw, degrees
    quaternion: tuple[float, float, float, float] | None = None


def _floats(data: bytes, count: int, xdi: int) -> tuple[float, ...] | None:
    fmt = xdi & XDI.FORMAT_MASK
    if fmt == XDI.FLOAT32 and len(data) == 4 * count:
        return struct.unpack(f">{count}f", data)
    if fmt == XDI.FLOAT64 and len(data) == 8 * count:
        return struct.unpack(f">{count}d", data)
    return None


def find_item(items: dict[int, bytes], base: int) -> tuple[int, bytes] | None:
    """The item whose XDI equals ``base`` up to the format/coordinate nibble."""
    for xdi, data in items.items():
        if xdi & 0xFFF0 == base:
            return xdi, data
    return None


# The MTData2 payload the driver configures (PacketCounter, SampleTimeFine, float32 EulerAngles, in this order),
# unpacked in one call: XDI, size and data of each item.
_STREAMED = struct.Struct(">HBHHBIHB3f")
_STREAMED_ITEMS = (XDI.PACKET_COUNTER, 2, XDI.SAMPLE_TIME_FINE, 4, XDI.EULER_ANGLES, 12)


def decode_sample(payload: bytes) -> Mtdata2Sample | None:
    """Packet counter, SampleTimeFine, Euler angles and quaternion of an MTData2 payload (None if malformed)."""
    fields = sample_fields(payload)
    return None if fields is None else Mtdata2Sample(*fields)


SampleFields = tuple[int | None, int | None, tuple[float, ...] | None, tuple[float, ...] | None]


def sample_fields(payload: bytes) -> SampleFields | None:
    """:func:`decode_sample` as a plain tuple (packet counter, SampleTimeFine, Euler angles in degrees, quaternion;
    None where absent or malformed), for the driver's per-sample path."""
    if len(payload) == _STREAMED.size:  # the configured stream (at every sample): one unpack, the same result
        xdi_pc, n_pc, pc, xdi_stf, n_stf, stf, xdi_euler, n_euler, roll, pitch, yaw = _STREAMED.unpack(payload)
        if (xdi_pc, n_pc, xdi_stf, n_stf, xdi_euler, n_euler) == _STREAMED_ITEMS:
            return pc, stf, (roll, pitch, yaw), None
    items = decode_mtdata2(payload)
    if items is None:
        return None
    pc = items.get(XDI.PACKET_COUNTER)
    stf = items.get(XDI.SAMPLE_TIME_FINE)
    euler = find_item(items, XDI.EULER_ANGLES)
    quat = find_item(items, XDI.QUATERNION)
    return (struct.unpack(">H", pc)[0] if pc is not None and len(pc) == 2 else None,
            struct.unpack(">I", stf)[0] if stf is not None and len(stf) == 4 else None,
            _floats(euler[1], 3, euler[0]) if euler else None,
            _floats(quat[1], 4, quat[0]) if quat else None)


def encode_sample(
    packet_counter: int, sample_time_fine: int, euler_deg: tuple[float, float, float] | None = None,
    quaternion: tuple[float, float, float, float] | None = None,
) -> bytes:
    """MTData2 payload with PacketCounter, SampleTimeFine and (float32) EulerAngles and/or Quaternion."""
    items = [
        (XDI.PACKET_COUNTER, struct.pack(">H", packet_counter & 0xFFFF)),
        (XDI.SAMPLE_TIME_FINE, struct.pack(">I", sample_time_fine & 0xFFFFFFFF)),
    ]
    if quaternion is not None:
        items.append((XDI.QUATERNION, struct.pack(">4f", *quaternion)))
    if euler_deg is not None:
        items.append((XDI.EULER_ANGLES, struct.pack(">3f", *euler_deg)))
    return encode_mtdata2(items)


# ---- configuration messages ---------------------------------------------------------------------------


def encode_output_configuration(items: list[tuple[int, int]]) -> bytes:
    """SetOutputConfiguration payload from (XDI, output frequency Hz; 0xFFFF = with every packet)."""
    return b"".join(struct.pack(">HH", xdi, rate) for xdi, rate in items)


def decode_output_configuration(payload: bytes) -> list[tuple[int, int]] | None:
    """(XDI, frequency) pairs of a SetOutputConfiguration / OutputConfiguration payload; None if malformed."""
    if len(payload) % 4:
        return None
    return [struct.unpack(">HH", payload[i : i + 4]) for i in range(0, len(payload), 4)]


def decode_error(payload: bytes) -> int | None:
    """The error code of an Error message (first payload byte), None if empty."""
    return payload[0] if payload else None


def decode_device_id(payload: bytes) -> int | None:
    """A DeviceID payload: 4 bytes (8 bytes on newer firmware) big-endian."""
    if len(payload) in (4, 8):
        return int.from_bytes(payload, "big")
    return None
