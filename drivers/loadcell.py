"""Load-cell amplifier: the line protocol of docs/protocols/loadcell.md (codec) and the serial driver.

Device to host, one line per sample: ``$LC,<seq>,<f_1>,...,<f_n>*HH\\r\\n`` with ``seq`` a decimal
counter (+1 per sample, 32-bit), ``f_i`` the force of channel i in N with two decimals, or ``OPEN``
(bridge disconnected) or ``OVER`` (beyond the measuring range), and ``HH`` the XOR of every byte between
``$`` and ``*`` in two upper-case hex digits. Host to device: ``$INFO*HH`` is answered with
``$INFO,<model>,<channels>,<full scale N>,<rate Hz>*HH``.
"""

from __future__ import annotations

import math
import operator
import re
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from drivers.interfaces import DeviceError, TensionReading
from drivers.interfaces import LoadCellAmplifier as LoadCellBase
from drivers.serial_util import SerialDevice

MAX_LINE = 256
SEQ_MODULUS = 1 << 32
OPEN = "OPEN"
OVER = "OVER"
_NUMBER = re.compile(r"-?[0-9]{1,7}(\.[0-9]{1,6})?")
_SEQ = re.compile(r"[0-9]{1,10}")
_SAMPLE = re.compile(r"LC,([0-9]{1,10})((?:,(?:-?[0-9]{1,7}(?:\.[0-9]{1,6})?|OPEN|OVER))+)")  # LC,seq,values
# A whole sample line, '$' to the end (CR/LF included), in one match: body (_SAMPLE), seq, values, checksum. A
# line it matches passes every check of unframe and _SAMPLE but the checksum's value; any other goes through them.
_FRAMED_SAMPLE = re.compile(rb"\$(" + _SAMPLE.pattern.encode() + rb")\*([0-9A-F]{2})[\r\n]*")


def checksum(body: bytes) -> int:
    """XOR of the bytes between ``$`` and ``*``."""
    x = 0
    for b in body:
        x ^= b
    return x


def frame(body: str) -> bytes:
    """``$body*HH\\r\\n`` for an ASCII body."""
    raw = body.encode("ascii")
    return b"$" + raw + b"*" + f"{checksum(raw):02X}".encode() + b"\r\n"


def encode_sample(seq: int, values: Sequence[float | str]) -> bytes:
    """One sample line: forces in N (rounded to 0.01 N) or the flags OPEN / OVER."""
    fields = [v if isinstance(v, str) else f"{v:.2f}" for v in values]
    return frame(",".join(["LC", str(seq % SEQ_MODULUS), *fields]))


@dataclass(frozen=True)
class SampleLine:
    seq: int
    tau: np.ndarray  # (n,) N, NaN where a flag stands
    flags: tuple[str, ...]  # per channel: "" or OPEN / OVER


@dataclass(frozen=True)
class InfoLine:
    model: str
    channels: int
    full_scale: float  # N
    rate_hz: float


def unframe(line: bytes) -> str | None:
    """The body of ``$body*HH`` (trailing CR/LF allowed) when the checksum matches, else None."""
    line = line.rstrip(b"\r\n")
    if len(line) < 4 or line[:1] != b"$" or line[-3:-2] != b"*":
        return None
    body, hh = line[1:-3], line[-2:]
    try:
        if int(hh, 16) != checksum(body) or hh.upper() != hh:
            return None
        return body.decode("ascii")
    except (ValueError, UnicodeDecodeError):
        return None


# A sample as decoded, before it becomes a SampleLine: (sequence number, forces N with NaN where a flag stands,
# flags). The driver takes it as it is (no SampleLine and array per line).
_Sample = tuple[int, list[float], tuple[str, ...]]


def parse_line(line: bytes) -> SampleLine | InfoLine | None:
    """Decode one line (garbage before its ``$`` is ignored); None when it is not a valid line."""
    start = line.rfind(b"$")
    return None if start < 0 else _message(_decode(line, start))


def _message(decoded: _Sample | InfoLine | None) -> SampleLine | InfoLine | None:
    """The SampleLine of a decoded sample; an InfoLine or None as it is."""
    if type(decoded) is tuple:
        seq, tau, flags = decoded
        return SampleLine(seq=seq, tau=np.array(tau), flags=flags)
    return decoded


def _decode(line: bytes, start: int) -> _Sample | InfoLine | None:
    """:func:`parse_line` of ``line`` (its newline may be cut off) whose last ``$`` is at ``start`` (>= 0), its
    sample left as a :data:`_Sample`."""
    framed = _FRAMED_SAMPLE.fullmatch(line, start)
    if framed is not None:  # a well-formed sample line (one at every control tick): only its checksum is left
        body, seq_text, values, hh = framed.groups()
        return _sample(seq_text, values.decode("ascii")) if int(hh, 16) == checksum(body) else None
    body = unframe(line[start:])
    if body is None:
        return None
    sample = _SAMPLE.fullmatch(body)
    if sample is not None:
        return _sample(*sample.groups())
    parts = body.split(",")
    try:
        if parts[0] == "INFO" and len(parts) == 5 and _SEQ.fullmatch(parts[2]) and all(
                _NUMBER.fullmatch(p) for p in parts[3:]):
            return InfoLine(model=parts[1], channels=int(parts[2]), full_scale=float(parts[3]),
                            rate_hz=float(parts[4]))
    except ValueError:
        return None
    return None


def _sample(seq_text: str | bytes, values: str) -> _Sample | None:
    """The sample of a body that matched ``_SAMPLE`` (sequence number, ``,f_1,...,f_n``); None past 32 bits."""
    seq = int(seq_text)
    if seq >= SEQ_MODULUS:
        return None
    fields = values[1:].split(",")
    if "O" in values:  # an OPEN or OVER flag stands somewhere
        flags = tuple(p if p in (OPEN, OVER) else "" for p in fields)
        tau = [math.nan if f else float(p) for p, f in zip(fields, flags, strict=True)]
    else:
        flags = ("",) * len(fields)
        tau = list(map(float, fields))
    return seq, tau, flags


@dataclass
class LineDecoder:
    """Incremental splitter: bytes in, decoded lines out; bad lines and overlong junk are counted."""

    bad_lines: int = 0
    bytes_discarded: int = 0
    resyncs: int = 0  # good lines found after garbage
    _buf: bytearray = field(default_factory=bytearray, repr=False)

    def feed(self, data: bytes) -> list[SampleLine | InfoLine]:
        return [_message(m) for m in self.decode(data)]

    def decode(self, data: bytes) -> list[_Sample | InfoLine]:
        """:meth:`feed`, each sample left as ``(seq, forces, flags)`` (a :data:`_Sample`)."""
        buf = self._buf
        if buf:  # the start of a line came with an earlier chunk
            buf += data
            data = bytes(buf)
            buf.clear()
        out: list[_Sample | InfoLine] = []
        end = data.rfind(b"\n") + 1
        if end:  # the complete lines, split at once
            lines = data[:end].split(b"\n")
            lines.pop()  # the empty rest after the last newline
            for line in lines:
                start = line.rfind(b"$")
                msg = None if start < 0 else _decode(line, start)
                if msg is None:
                    self.bad_lines += 1
                    self.bytes_discarded += len(line) + 1  # with its newline
                else:
                    self.bytes_discarded += start
                    self.resyncs += start > 0
                    out.append(msg)
        if end < len(data):
            buf += data[end:]
            if len(buf) > MAX_LINE:  # no newline for too long: keep only from the last '$'
                start = buf.rfind(b"$")
                cut = len(buf) if start < 0 or len(buf) - start > MAX_LINE else start
                self.bytes_discarded += cut
                del buf[:cut]
        return out


# ---- the driver ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LoadCellConfig:
    port: str
    baud: int = 115200
    channels: int = 4
    rate_hz: float = 100.0  # expected sample rate, for the staleness rule
    stale_periods: float = 3.0
    stuck_samples: int = 50  # identical consecutive values that mark a stuck channel
    info_timeout: float = 1.0  # s
    polled: bool = False  # read the port in the waiting thread, not a reader thread (lockstep simulation)
    tap: Callable[[bytes, bool], None] | None = field(default=None, compare=False)  # raw record (PortReader)


class LoadCellDriver(SerialDevice, LoadCellBase):
    """A multi-channel amplifier on a serial port; implements :class:`drivers.interfaces.LoadCellAmplifier`."""

    name = "loadcells"
    kind = "load-cell amplifier"
    tag = "loadcell"

    def __init__(self, config: LoadCellConfig) -> None:
        super().__init__(config)
        self.info: InfoLine | None = None
        self._decoder = LineDecoder()
        self._info_event = threading.Event()
        self._last_seq: int | None = None
        self._same = [0] * config.channels  # repeats of each channel's value in a row (plain list: every tick)
        self._prev: list[float] | None = None
        self._flags: tuple[str, ...] = ("",) * config.channels

    def _greet(self) -> None:  # INFO: the amplifier's channels; the silence is counted from its answer
        self._info_event.clear()
        try:
            self._reader.write(frame("INFO"))
        except Exception as exc:  # serial.SerialException, OSError, write timeout
            raise DeviceError(f"load-cell amplifier: writing INFO to {self.config.port} failed ({exc}).") from exc
        if self.config.polled:
            answered = self._reader.until(self._info_event.is_set, self.config.info_timeout)
        else:
            answered = self._info_event.wait(self.config.info_timeout)
        if not answered:
            raise DeviceError(f"load-cell amplifier on {self.config.port} did not answer INFO within "
                              f"{self.config.info_timeout:g} s.")
        if self.info.channels != self.config.channels:
            raise DeviceError(f"load-cell amplifier on {self.config.port} has {self.info.channels} channels, "
                              f"the configuration expects {self.config.channels}.")
        self._box.opened_at = time.monotonic()

    def _on_bytes(self, data: bytes, t: float) -> None:
        decoder = self._decoder
        for msg in decoder.decode(data):
            if isinstance(msg, InfoLine):
                self.info = msg
                self._info_event.set()
            else:
                self._on_sample(*msg, t)
        stats = self._stats
        stats.checksum_errors = decoder.bad_lines
        stats.bytes_discarded = decoder.bytes_discarded
        stats.resyncs = decoder.resyncs

    def _on_sample(self, seq: int, tau: list[float], flags: tuple[str, ...], t: float) -> None:
        """One decoded sample line: sequence number, forces N (NaN where a flag stands), flags; ``t`` s."""
        stats = self._stats
        if len(tau) != self.config.channels:
            stats.extra["wrong_width"] = stats.extra.get("wrong_width", 0) + 1
            return
        if self._last_seq is not None:
            step = (seq - self._last_seq) % SEQ_MODULUS
            if step == 0:
                return  # a repeated line
            if step > SEQ_MODULUS // 2:  # the counter went back: the amplifier restarted
                stats.extra["restarts"] = stats.extra.get("restarts", 0) + 1
            elif step > 1:
                stats.sequence_gaps += step - 1
        self._last_seq = seq
        prev = self._prev
        if prev is not None:
            same = self._same
            if any(map(operator.eq, tau, prev)):  # some channel repeats its value: count the finite repeats
                isfinite = math.isfinite
                self._same = [n + 1 if v == p and isfinite(v) else 0
                              for v, p, n in zip(tau, prev, same, strict=True)]
            elif any(same):  # no channel repeats: every count starts again
                self._same = [0] * len(same)
        self._prev = tau
        self._flags = flags
        stats.frames += 1
        self._box.put(TensionReading(t=t, seq=seq, tau=np.array(tau), device_seq=seq))

    def _count(self, reading: TensionReading) -> int:
        return reading.device_seq

    def channel_faults(self) -> list[str]:
        """One sentence per faulty channel (1-based): open bridge, over range, stuck value."""
        out = []
        for i, f in enumerate(self._flags):
            if f == OPEN:
                out.append(f"load cell {i + 1} on {self.config.port} is disconnected (the amplifier reports "
                           f"an open bridge).")
            elif f == OVER:
                out.append(f"load cell {i + 1} on {self.config.port} is over its measuring range.")
            elif self._same[i] + 1 >= self.config.stuck_samples and self._prev is not None:
                out.append(f"load cell {i + 1} on {self.config.port} is stuck at {self._prev[i]:.2f} N for "
                           f"{self._same[i] + 1} consecutive samples.")
        return out

    def fault(self) -> str | None:
        if self._reader is not None and self._reader.error:
            return f"load-cell amplifier: {self._reader.error}."
        stale = self.staleness()
        if stale:
            return stale
        faults = self.channel_faults()
        return faults[0] if faults else None

    def status(self) -> str:
        r = self.latest()
        model = self.info.model if self.info else "?"
        if r is None:
            return f"load-cell amplifier {model} on {self.config.port}: no sample yet"
        tau = ", ".join("nan" if math.isnan(v) else f"{v:.1f}" for v in r.tau)
        return (f"load-cell amplifier {model} on {self.config.port}: [{tau}] N, sequence {r.seq}, "
                f"{self._stats.frames} lines, {self._stats.checksum_errors} bad, "
                f"{self._stats.sequence_gaps} missing")
