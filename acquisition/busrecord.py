"""The raw record beside a run: every CAN frame in RUN/bus.blf (or bus.asc), every serial byte in RUN/serial.rec.

``cdpr startup`` records what crossed the wires, so that a run can be replayed through the drivers
(``acquisition/replay.py``, ``cdpr replay``) after a decoder change, or read with the lab's CAN tools.

- CAN: python-can's own loggers (``can.Logger``: :class:`can.BLFWriter` by default, :class:`can.ASCWriter`
  for ``asc``) get every frame the master's CANopen network sends and receives, in bus order
  (``drivers.can_bus.CanNetwork.add_listener``). Sent frames have ``is_rx`` False. A BLF file is written in
  compressed containers of 16 KiB (about 0.2 s of traffic at 200 Hz); an ASC file line by line; both files are
  fsynced once per second of wall time. A run cut by SIGINT or SIGTERM ends in a safe stop that closes the
  record complete; a run killed keeps what reached the file, which python-can's ``LogReader`` reads up to
  there.
- Serial: ``serial.rec`` (format ``cdpr-serial-record/1``, docs/run-format.md): a first line naming the
  format, a second line of JSON with what a replay needs to open the devices again, then one line per chunk
  read from a port (``rx``) or written to it (``tx``: the drivers' requests), flushed as it is written:
  ``<wall time s> <CAN frames recorded before it> <device> <rx|tx> <hex bytes>``. The CAN frame count places
  each chunk exactly among the frames of bus.blf.
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from calib.errors import CdprError

SERIAL_RECORD = "serial.rec"
SERIAL_FORMAT = "cdpr-serial-record/1"
CAN_FORMATS = ("blf", "asc")
SERIAL_DEVICES = ("loadcells", "ahrs")
BLF_CONTAINER = 16 * 1024  # bytes of frames per compressed BLF container


class RecordError(CdprError, ValueError):
    """A record that cannot be read; the message names the file, line and value."""


class RecordTruncatedWarning(UserWarning):
    """A record ends in a piece that cannot be read (a run killed while writing); what comes before is used."""


def can_record_path(run: str | Path, fmt: str | None = None) -> Path:
    """RUN/bus.blf or RUN/bus.asc; with ``fmt`` None, the one the run holds (bus.blf when neither)."""
    run = Path(run)
    if fmt is not None:
        if fmt not in CAN_FORMATS:
            raise ValueError(f"bus log format {fmt!r} is not one of {', '.join(CAN_FORMATS)}.")
        return run / f"bus.{fmt}"
    for f in CAN_FORMATS:
        if (run / f"bus.{f}").is_file():
            return run / f"bus.{f}"
    return run / "bus.blf"


def record_settings(devices, every: tuple[int, int], rate: float, lockstep: bool) -> dict[str, Any]:
    """What a replay needs to open the devices as the run did: the ``drivers.config.DeviceConfig``, the
    feedback periods in SYNCs (drives, encoders), the control rate (Hz), and whether the loop waited for each
    tick's readings (the simulated prototype)."""
    return {"devices": dataclasses.asdict(devices), "feedback_every": [int(every[0]), int(every[1])],
            "rate": float(rate), "lockstep": bool(lockstep)}


class BusRecorder(can.Listener):
    """Writes the raw record of one run. A :class:`can.Listener` for the CAN frames (any thread); serial
    chunks come through :meth:`serial_tap`. ``settings``: JSON-able, the second line of serial.rec."""

    def __init__(self, run: str | Path, settings: dict[str, Any], can_format: str = "blf") -> None:
        folder = Path(run)
        self._made_folder = not folder.exists()
        folder.mkdir(parents=True, exist_ok=True)
        self.can_path = can_record_path(folder, can_format)
        self.serial_path = folder / SERIAL_RECORD
        extra = {"max_container_size": BLF_CONTAINER} if can_format == "blf" else {}
        self._writer = can.Logger(self.can_path, **extra)
        self._serial = open(self.serial_path, "w", encoding="ascii", newline="\n")  # noqa: SIM115
        self._serial.write(f"{SERIAL_FORMAT}\n{json.dumps(settings, sort_keys=True)}\n")
        self._serial.flush()
        self._lock = threading.Lock()
        self.frames = 0
        self.closed = False
        self._next_sync = time.time() + 1.0

    def on_message_received(self, msg: can.Message) -> None:
        if msg.channel is not None and not isinstance(msg.channel, int):  # a virtual bus's channel name
            msg = can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id,
                              is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                              is_error_frame=msg.is_error_frame, data=msg.data, is_rx=msg.is_rx)
        with self._lock:
            if not self.closed:
                self._writer.on_message_received(msg)
                self.frames += 1
                if msg.timestamp >= self._next_sync:
                    self._sync(msg.timestamp)

    def _sync(self, now: float) -> None:
        """Both files to the disk (fsync), at most once per second of wall time."""
        for fh in (self._serial, self._writer.file):
            fh.flush()
            os.fsync(fh.fileno())
        self._next_sync = now + 1.0

    def serial_tap(self, device: str) -> Callable[[bytes, bool], None]:
        """The tap of one serial device's port (``drivers.serial_util.PortReader``): records each chunk read
        (``sent`` False) or written (``sent`` True)."""
        if device not in SERIAL_DEVICES:
            raise ValueError(f"serial device {device!r} is not one of {', '.join(SERIAL_DEVICES)}.")

        def tap(data: bytes, sent: bool) -> None:
            with self._lock:
                if self.closed:
                    return
                way = "tx" if sent else "rx"
                self._serial.write(f"{time.time():.6f} {self.frames} {device} {way} {data.hex()}\n")
                self._serial.flush()
                self._writer.file.flush()  # what the CAN writer has handed to its file so far

        return tap

    def discard(self) -> None:
        """Stop and delete the record, and the run folder when this recorder made it and it is empty (the
        devices never answered: nothing was run)."""
        self.stop()
        self.can_path.unlink(missing_ok=True)
        self.serial_path.unlink(missing_ok=True)
        if self._made_folder and not any(self.can_path.parent.iterdir()):
            self.can_path.parent.rmdir()

    def stop(self) -> None:
        """Close both files (the BLF header gets its final counts); safe to call twice."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            self._writer.stop()
            self._serial.close()


@dataclass(frozen=True)
class SerialChunk:
    """Bytes read from (``sent`` False) or written to one serial port at once: wall time s, CAN frames recorded
    before them, device."""

    t: float
    can_frames: int
    device: str
    sent: bool
    data: bytes


def read_serial_record(path: str | Path) -> tuple[dict[str, Any], list[SerialChunk]]:
    """The settings and the chunks of a serial.rec; a last line cut off (a run killed while writing) is
    dropped, any other bad line raises :class:`RecordError`."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="ascii").split("\n")
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordError(f"{path}: cannot read the serial record ({exc}).") from exc
    if not lines or lines[0] != SERIAL_FORMAT:
        raise RecordError(f"{path}: line 1 is {lines[0][:40]!r}, expected {SERIAL_FORMAT!r}.")
    try:
        settings = json.loads(lines[1]) if len(lines) > 1 else None
    except json.JSONDecodeError:
        settings = None
    if not isinstance(settings, dict):
        raise RecordError(f"{path}: line 2 is not the JSON settings of the record.")
    body = lines[2:]
    complete = body[:-1]  # the text after the last newline is a line cut off, or empty
    return settings, list(_chunks(path, complete))


def _chunks(path: Path, lines: list[str]) -> Iterator[SerialChunk]:
    for no, line in enumerate(lines, start=3):
        parts = line.split(" ")
        try:
            if len(parts) != 5 or parts[2] not in SERIAL_DEVICES or parts[3] not in ("rx", "tx"):
                raise ValueError(line[:60])
            yield SerialChunk(float(parts[0]), int(parts[1]), parts[2], parts[3] == "tx", bytes.fromhex(parts[4]))
        except ValueError as exc:
            raise RecordError(f"{path}: line {no} is not '<t> <frames> <device> <rx|tx> <hex>': {exc}.") from exc


def read_can_record(path: str | Path) -> list[can.Message]:
    """Every frame of a bus.blf / bus.asc (python-can's ``LogReader``), in the order recorded. A file that
    ends in a piece python-can cannot read (a run killed while the logger wrote) gives the frames before it,
    with a :class:`RecordTruncatedWarning`."""
    path = Path(path)
    frames: list[can.Message] = []
    try:
        with can.LogReader(path) as reader:
            for msg in reader:
                frames.append(msg)
    except Exception as exc:  # the readers raise their own parse errors, zlib.error, struct.error, OSError
        if not frames:
            raise RecordError(f"{path}: python-can cannot read the CAN record ({exc}).") from exc
        warnings.warn(f"{path}: the CAN record ends in a piece python-can cannot read ({exc}); the "
                      f"{len(frames)} frames before it are used.", RecordTruncatedWarning, stacklevel=2)
    return frames
