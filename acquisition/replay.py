"""Replay a run's raw record (acquisition/busrecord.py) through the real drivers and rebuild its samples.

The CAN frames of RUN/bus.blf (python-can's ``LogReader``) play on a :class:`PlaybackBus`: each frame the
master sends is matched with the next frame the run sent with the same COB-ID and data, and the frames the
run received after it, up to the run's next sent frame, are then received (a frame the run sent that the
replay does not, an RPDO, is skipped; what answered it is still received, in the recorded order). The
serial chunks of RUN/serial.rec play on pty pairs in the recorded order: what the run's driver wrote is
awaited from the driver, what it read is written at its place among the CAN frames, once the driver has read
the device's chunk before (:class:`SerialFeeder`). On these, :func:`acquisition.startup.
connect` opens the same drivers as ``cdpr startup`` (CiA 402 drives, CiA 406 encoders, load-cell amplifier,
Xsens MTi: their SDO set-up, PDO mapping, handshakes and decoders) and the same :class:`acquisition.control.Rig`
sends one SYNC per recorded SYNC and gathers each tick's readings.

The rebuilt samples are the run's sensor columns (tau, dl, dsigma, roll, pitch, dyaw, taken against the
readings of the third tick as the routine zeroes them); the routine's own columns (t, tau_ref, phase,
setpoint and the extra columns such as tick) are not on the wires and are the run's. A simulated run replays
to the same samples.csv byte for byte; a run whose record ends early (a cut) replays to the record's end.
Ticks are taken in lockstep (each device's reading answering the tick's SYNC), as the simulated prototype
runs; a hardware run is replayed that way too.
"""

from __future__ import annotations

import fcntl
import os
import queue
import select
import struct
import termios
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np

from acquisition.busrecord import (
    SERIAL_RECORD,
    SerialChunk,
    can_record_path,
    read_can_record,
    read_serial_record,
)
from acquisition.clock import SimClock
from acquisition.runlog import read_run
from acquisition.runwriter import RunWriter
from drivers.can_bus import SYNC_COB_ID

_STANDARD_META = ("format", "robot", "procedure", "events", "created", "source")


class PlaybackBus(can.BusABC):
    """A python-can bus that answers the master with a recorded run's frames (see the module docstring).

    :attr:`position`: frames of the record released so far (sent ones matched or skipped, received ones
    handed to :meth:`recv`); :meth:`wait_position` blocks until it reaches a count."""

    def __init__(self, frames: list[can.Message], channel: str = "replay", **kwargs) -> None:
        self._frames = frames
        self._rx: queue.Queue[can.Message] = queue.Queue()
        self._cond = threading.Condition()
        self._closed = False
        self.position = 0
        self.unmatched = 0  # frames the master sent that the record does not hold from where it stands
        super().__init__(channel=channel, **kwargs)
        self.channel_info = f"playback of {len(frames)} recorded frames"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        frames, data = self._frames, bytes(msg.data)
        with self._cond:
            start = self.position
            i = start
            while i < len(frames) and (frames[i].is_rx or frames[i].arbitration_id != msg.arbitration_id
                                       or bytes(frames[i].data) != data):
                i += 1
            if i == len(frames):
                self.unmatched += 1
                return
            j = i + 1
            while j < len(frames) and frames[j].is_rx:
                j += 1
            for k in range(start, j):
                if frames[k].is_rx:
                    self._rx.put(frames[k])
            self.position = j
            self._cond.notify_all()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            return self._rx.get(timeout=timeout), False
        except queue.Empty:
            return None, False

    def wait_position(self, count: int, timeout: float | None = None) -> bool:
        """Block until :attr:`position` >= ``count`` or the bus shuts down; whether it got there."""
        with self._cond:
            self._cond.wait_for(lambda: self.position >= count or self._closed, timeout)
            return self.position >= count

    def shutdown(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        super().shutdown()


class SerialFeeder:
    """Plays the recorded serial chunks on pty masters (``ports``: device -> (master fd, slave path)) in the
    recorded order: a chunk the driver wrote (``sent``) is awaited on the master, a chunk it read is written
    once the bus has released the CAN frames recorded before it and the driver has read the device's last
    chunk, so that every read of the driver sees what the run's read saw."""

    def __init__(self, bus: PlaybackBus, chunks: list[SerialChunk], ports: dict[str, tuple[int, str]]) -> None:
        self.bus = bus
        self.chunks = chunks
        self.ports = ports
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="replay-serial", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        watch = {dev: os.open(path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK) for dev, (_, path) in self.ports.items()}
        heard = dict.fromkeys(self.ports, 0)  # bytes the driver wrote so far, per device
        awaited = dict.fromkeys(self.ports, 0)  # bytes the run's driver had written, per device
        stop = self._stop
        try:
            for chunk in self.chunks:
                fd = self.ports[chunk.device][0]
                if chunk.sent:
                    awaited[chunk.device] += len(chunk.data)
                    while heard[chunk.device] < awaited[chunk.device]:
                        if stop.is_set():
                            return
                        if select.select([fd], [], [], 0.05)[0]:
                            heard[chunk.device] += _drain(fd)
                    continue
                if not self.bus.wait_position(chunk.can_frames) or stop.is_set():
                    return
                while _pending(watch[chunk.device]) and not stop.is_set():
                    time.sleep(2e-5)
                data = chunk.data
                while data and not stop.is_set():
                    heard[chunk.device] += _drain(fd)
                    try:
                        data = data[os.write(fd, data):]
                    except BlockingIOError:
                        select.select([], [fd], [], 0.05)
        except OSError:  # the replay closed the ports: nothing left to feed
            return
        finally:
            for fd in watch.values():
                os.close(fd)


def _drain(fd: int) -> int:
    """Read what the driver wrote to a pty (non-blocking master); the count of bytes."""
    count = 0
    try:
        while data := os.read(fd, 4096):
            count += len(data)
    except BlockingIOError:
        pass
    return count


def _pending(fd: int) -> int:
    """Bytes written to a pty that its reader has not read yet."""
    return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]


@dataclass(frozen=True)
class ReplayResult:
    out: Path
    samples: int  # samples rebuilt
    original: int  # samples of the original run
    frames: int  # CAN frames in the record
    syncs: int  # SYNCs replayed
    unmatched: int  # frames the replay sent that the record did not hold


def replay_run(run: str | Path, out: str | Path, overwrite: bool = False, timeout: float = 0.2) -> ReplayResult:
    """Replay ``run``'s record through the drivers into a new run folder ``out`` (see the module docstring).
    ``timeout``: wall seconds a tick waits for a device's reading before it counts as missing."""
    from acquisition.connect import connect
    from drivers.config import AhrsConfig, CanConfig, DeviceConfig, NodeConfig, SerialConfig
    from sim_backend.pty import open_pty_pair

    run, out = Path(run), Path(out)
    original = read_run(run)
    if "tick" not in original.extra:
        raise ValueError(f"{run / 'samples.csv'}: no 'tick' column; only runs of `cdpr startup` can be replayed.")
    settings, chunks = read_serial_record(run / SERIAL_RECORD)
    can_path = can_record_path(run)
    frames = read_can_record(can_path)
    period = 1.0 / float(settings["rate"])
    dev = settings["devices"]
    fds: list[int] = []
    ports: dict[str, tuple[int, str]] = {}
    for name in ("loadcells", "ahrs"):
        fd, path = open_pty_pair()
        fds.append(fd)
        ports[name] = (fd, path)
    devices = DeviceConfig(
        can=CanConfig(**dev["can"]),
        drives=tuple(NodeConfig(**d) for d in dev["drives"]),
        encoders=tuple(NodeConfig(**e) for e in dev["encoders"]),
        loadcells=SerialConfig(ports["loadcells"][1], int(dev["loadcells"]["baud"])),
        ahrs=AhrsConfig(ports["ahrs"][1], int(dev["ahrs"]["baud"]), float(dev["ahrs"]["rate"])),
        source=f"{can_path} (replay)",
    )
    bus = PlaybackBus(frames)
    feeder = SerialFeeder(bus, chunks, ports)
    # a record cut short: the ticks whose serial bytes the record still holds (read after their SYNC)
    end = max((c.can_frames for c in chunks if not c.sent), default=0)
    syncs = sum(1 for f in frames[:end] if not f.is_rx and f.arbitration_id == SYNC_COB_ID)
    snaps = {}
    feeder.start()
    try:
        clock = SimClock(period)
        rig = connect(devices, original.robot, clock, lockstep=True, period=period,
                      every=tuple(settings["feedback_every"]), bus=bus)
        try:
            for _ in range(syncs):
                tk = clock.advance()
                snap = rig.tick(tk.index, tk.t, timeout)
                snaps[snap.sync] = snap
        finally:
            rig.close()
    finally:
        feeder.stop()
        bus.shutdown()
        for fd in fds:
            os.close(fd)
    written = _write(original, snaps, out, overwrite, run, len(frames))
    return ReplayResult(out, written, len(original), len(frames), syncs, bus.unmatched)


def _write(original, snaps: dict, out: Path, overwrite: bool, run: Path, frames: int) -> int:
    """The rebuilt samples in ``out``: the sensor columns from ``snaps`` (SYNC count -> Snapshot), the rest
    from ``original``; stops at the first sample whose SYNC the record does not hold."""
    meta = original.meta
    extra_meta = {k: v for k, v in meta.items() if k not in _STANDARD_META}
    extra_meta["replay"] = {"of": str(run), "can_frames": frames}
    proc = meta["procedure"]
    ticks = original.extra["tick"]
    zero = snaps.get(3)  # the routine zeroes the relative sensors at the third tick
    writer = RunWriter(out, meta["robot"], original.method, original.sample_period, original.source,
                       setpoints=proc.get("setpoints"), ideal_poses=proc.get("ideal_poses"),
                       extra_columns=tuple(original.extra), meta_extra=extra_meta, overwrite=overwrite)
    count = 0
    try:
        for ev in original.events:
            writer.add_event(ev["t"], ev["kind"], ev["message"])
        for j in range(len(original)):
            snap = snaps.get(int(ticks[j]))
            if snap is None or zero is None:
                break
            extra = {name: _cell(col[j]) for name, col in original.extra.items()}
            writer.append(float(original.t[j]), snap.tau, original.tau_ref[j], snap.dl - zero.dl,
                          snap.dsigma - zero.dsigma, snap.roll, snap.pitch, snap.yaw - zero.yaw,
                          str(original.phase[j]), int(original.setpoint[j]), **extra)
            count += 1
    finally:
        writer.close()
    return count


def _cell(v):
    """A value of an extra column as it was written: whole numbers as ints."""
    if isinstance(v, np.floating) and float(v).is_integer():
        return int(v)
    return v.item() if isinstance(v, np.generic) else v


@dataclass
class LiveReplay:
    """What ``cdpr replay RUN --live`` played: messages published, samples, run time (s) and the wall time (s)
    from the first message to the last."""

    messages: int
    samples: int
    run_time: float
    wall_time: float


def replay_live(path: Path, server, speed: float = 1.0, sleep=time.sleep, wait=None) -> LiveReplay:
    """Play the run folder ``path`` to a live view (``server``: an ``acquisition.live.LiveServer``) at its real
    pace times ``speed``: its samples, windows, events, estimates and the supervisor's state, with the scene
    and transforms of the MCAP export (acquisition/export_mcap.py), each published when its time comes;
    ``wait()`` is called before the play starts (e.g. until a viewer subscribes)."""
    import json as _json

    from acquisition.export_mcap import view_messages
    from acquisition.scene import static_poses

    run = read_run(path)
    sol_path = Path(path) / "solution.json"
    solution = _json.loads(sol_path.read_text()) if sol_path.is_file() else None
    poses = static_poses(run.robot, run.tau)
    c0 = time.perf_counter()  # building the messages takes a while: timed once, to stamp them ahead of it
    view_messages(run, solution, 0, speed, samples=True, poses=poses)
    build = time.perf_counter() - c0
    if wait is not None:
        wait()
    # stamped with the wall time each is sent at (a late one goes at once)
    msgs = view_messages(run, solution, time.time_ns() + int((0.3 + 1.3 * build) * 1e9), speed, samples=True,
                         poses=poses)
    for t_ns, topic, msg in msgs:
        wait = (t_ns - time.time_ns()) / 1e9
        if wait > 0:
            sleep(wait)
        server.publish(topic, msg, t_ns)
    span = float(run.t[-1] - run.t[0]) if len(run) else 0.0
    return LiveReplay(len(msgs), len(run), span, (time.time_ns() - msgs[0][0]) / 1e9 if msgs else 0.0)
