"""The live view of a startup (``cdpr startup ... --live [HOST:]PORT``) and of a replayed run, in Foxglove.

The Foxglove SDK's WebSocket server (``foxglove-sdk``; protocol subprotocol ``foxglove.sdk.v1``, the renamed
``foxglove.websocket.v1``) on its own :class:`foxglove.Context` publishes the channels of
:mod:`acquisition.scene`. Read-only: it is started with no capability at all (no client publishing, no
services, no parameters, no playback control), so whatever a client sends is refused by the server with an
error status and never reaches this process; it binds 127.0.0.1 unless a host is named.

The control loop never waits for it, nor shares its interpreter with it: :class:`LiveTap` runs in the loop's
thread at each tick and only, every ``every`` ticks and at each logged sample, copies the tick's record (a few
hundred bytes of plain numbers) into a lock-free ring in shared memory (:mod:`acquisition.live_ring`: no
system call, no wait), dropping it when the ring is full; the publisher, a process of its own (spawned, at
a lower priority: :func:`_serve`), polls the ring, runs the server, estimates the platform's pose
(:class:`acquisition.scene.PoseTracker`), builds, encodes and logs the messages. The server's own
threads send them; a client that is slow, connects or vanishes only changes what it receives.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import pickle
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from acquisition.live_messages import Frame, RunView
from acquisition.live_ring import SLOTS, ShmRing
from acquisition.scene import (
    ESTIMATE_SCHEMA,
    EVENT_SCHEMA,
    SUPERVISOR_SCHEMA,
    WINDOW_SCHEMA,
    PoseTracker,
    foxglove_schemas,
    sample_schema,
    startup_columns,
)
from calib.robot import Robot

SCENE_RATE = 20.0  # Hz, scene updates during a startup
# the publisher's wait when the ring is empty, as a share of the interval between two scene updates (1 / SCENE_RATE
# s): matched to what it shows, so it wakes about as often as it has something to publish (it drained the ring
# at every 2 ms until 2026-11-27: 500 wake-ups/s, each one more chance that the loop's vCPU is busy or stolen)
WAIT_SHARE = 1.0
PUBLISHER_NICE = 19  # the publisher process's niceness (every thread it starts inherits it): the lowest
START_TIMEOUT = 60.0  # s to wait for the publisher process to listen
NEWS = 4  # windows, events and estimates per record at most (a record fits one slot of the ring, 4080 bytes)
GHOST_ROWS = 16  # planned poses per record at most
# s the publisher keeps serving after the run's last word while a viewer is subscribed: the SDK sends from its
# own runtime and its server's stop drops what is still queued (a loaded machine lost the final "stopped")
CLOSE_LINGER = 0.5


@dataclass(frozen=True)
class LiveAddress:
    """Where the live server listens."""

    host: str
    port: int

    @classmethod
    def parse(cls, text: str, option: str = "--live") -> LiveAddress:
        """``PORT`` or ``HOST:PORT`` (PORT 0: any free port); raises ValueError with one sentence."""
        host, sep, port = str(text).rpartition(":")
        host = host.strip("[]") if sep else "127.0.0.1"
        try:
            p = int(port)
        except ValueError:
            p = -1
        if not 0 <= p <= 65535 or (sep and not host):
            raise ValueError(f"{option} {text!r} is not [HOST:]PORT (a port 0..65535, e.g. 8765 or 0.0.0.0:8765).")
        return cls(host, p)


def json_channels(kinds: dict[str, str]) -> dict[str, tuple[str, str, bytes]]:
    """topic -> (schema name, schema encoding, schema data) of the JSON channels, ``kinds`` the sample columns."""
    return {"/samples": ("cdpr.Sample", "jsonschema", sample_schema(kinds)),
            "/windows": ("cdpr.Window", "jsonschema", WINDOW_SCHEMA),
            "/events": ("cdpr.Event", "jsonschema", EVENT_SCHEMA),
            "/estimate": ("cdpr.Estimate", "jsonschema", ESTIMATE_SCHEMA),
            "/supervisor": ("cdpr.Supervisor", "jsonschema", SUPERVISOR_SCHEMA)}


def channel_specs(kinds: dict[str, str]) -> dict[str, tuple[str, str, bytes, str]]:
    """topic -> (schema name, schema encoding, schema data, message encoding) of every view channel."""
    specs = {k: (*v, "json") for k, v in json_channels(kinds).items()}
    for topic, s in foxglove_schemas().items():
        specs[topic] = (s.name, s.encoding, bytes(s.data), "protobuf")
    return specs


def encode(msg: Any) -> bytes:
    """A message's bytes: JSON for a dict, protobuf for a Foxglove message."""
    return json.dumps(msg).encode() if isinstance(msg, dict) else msg.encode()


class _Subscriptions:
    """The server's listener: it only notes that a viewer subscribed (the server has no capability, so a
    client's messages, service calls and parameters are refused before any listener would hear of them)."""

    def __init__(self) -> None:
        self.first = threading.Event()
        self.active = 0  # subscriptions held now (client, channel pairs)

    def on_subscribe(self, client, channel) -> None:
        self.active += 1
        self.first.set()

    def on_unsubscribe(self, client, channel) -> None:
        self.active = max(self.active - 1, 0)


class LiveServer:
    """The SDK's WebSocket server with the view's channels, read-only (no capability); a context manager."""

    def __init__(self, address: LiveAddress, n: int, name: str = "cdpr", stream=None):
        import foxglove

        self._subscriptions = _Subscriptions()
        self.context = foxglove.Context()
        self._channels = {}
        for topic, (sname, senc, sdata, menc) in channel_specs(startup_columns(n)).items():
            self._channels[topic] = foxglove.Channel(
                topic, schema=foxglove.Schema(name=sname, encoding=senc, data=sdata), message_encoding=menc,
                context=self.context)
        try:
            self.server = foxglove.start_server(name=name, host=address.host, port=address.port,
                                                capabilities=[], context=self.context,
                                                server_listener=self._subscriptions)
        except Exception as exc:  # the SDK raises its own error type: say where it could not listen
            raise OSError(f"the live view cannot listen on {address.host}:{address.port} ({exc}).") from exc
        self.host, self.port = address.host, int(self.server.port)
        (stream or sys.stderr).write(listening(self.host, self.port))

    def publish(self, topic: str, msg: Any, t_ns: int) -> None:
        self._channels[topic].log(encode(msg), log_time=int(t_ns))

    def wait_for_viewer(self, timeout: float | None = None) -> bool:
        """Wait until a client has subscribed to a channel (at most ``timeout`` s); True if one has."""
        return self._subscriptions.first.wait(timeout)

    def close(self, linger: float = 0.0) -> None:
        """Stop serving; with a viewer still subscribed, first let ``linger`` s pass so that what was published
        last reaches it (the server's stop drops the messages still queued)."""
        if linger > 0 and self._subscriptions.active > 0:
            time.sleep(linger)
        for ch in self._channels.values():
            ch.close()
        self.server.stop()

    def __enter__(self) -> LiveServer:
        return self

    def __exit__(self, *exc) -> None:
        self.close(linger=CLOSE_LINGER)


class LiveTap:
    """The control loop's side of the live view: ``on_tick`` (StartupRoutine's hook) hands every ``every``-th
    tick and every logged sample, as one small pickled record, to the publisher process through the producer's
    side of a :class:`ShmRing` (a record that does not fit is dropped and counted); makes no system call, never
    waits, never writes to the routine. :meth:`attach` the routine before it runs."""

    def __init__(self, every: int, ring: ShmRing):
        self.every = max(int(every), 1)
        self.ring = ring
        self.dropped = 0
        self.handed = 0
        self._routine = None
        self._windows = self._events = self._estimates = 0  # seen so far
        self._ghosts = 0  # planned poses sent so far

    def attach(self, routine) -> None:
        self._routine = routine

    def on_tick(self, snap) -> None:
        self._hand(snap)

    def _hand(self, snap, final: bool = False) -> None:
        r = self._routine
        logged = r._log_open and snap.tick % r.log_every == 0 and not final
        wins, estimates = len(r._windows), len(r._history)
        events = len(r.writer.meta["events"]) if r.writer is not None else 0
        news = (wins, events, estimates) != (self._windows, self._events, self._estimates)
        if not (news or (not final and (logged or snap.tick % self.every == 0))):
            return
        extra = None
        if news:  # at most NEWS of each per record (the record stays within one atomic write); the rest follows
            evs = r.writer.meta["events"] if events else []
            extra = (r._windows[self._windows:self._windows + NEWS], evs[self._events:self._events + NEWS],
                     [_plain_estimate(est) for _, est in r._history[self._estimates:self._estimates + NEWS]],
                     self._estimates)
        ghosts = r.plan.ideal_poses  # GHOST_ROWS of the planned poses not sent yet, with the first one's index
        new_ghosts = ((self._ghosts, ghosts[self._ghosts:self._ghosts + GHOST_ROWS].tolist())
                      if len(ghosts) > self._ghosts else None)
        z, t0 = r._zero, r._t_run0
        if z:
            dl, ds, dyaw = (snap.dl - z["dl"]).tolist(), (snap.dsigma - z["dsigma"]).tolist(), snap.yaw - z["yaw"]
        else:
            dl = ds = [math.nan] * len(snap.tau)
            dyaw = math.nan
        t = round(snap.t - t0, 9) if t0 is not None else math.nan  # the run log's time
        index = r.logged - 1 if logged and r.writer is not None else -1  # the sample's row in samples.csv
        record = (time.time_ns(), t, snap.tau.tolist(), r._ref.tolist(), dl, ds, snap.roll, snap.pitch, dyaw,
                  r._phase, r._setpoint, snap.sync, logged, index, r.supervisor.requested, extra, new_ghosts)
        if not self._send(record):
            return
        self.handed += 1
        if extra is not None:
            self._windows += len(extra[0])
            self._events += len(extra[1])
            self._estimates += len(extra[2])
        if new_ghosts is not None:
            self._ghosts += len(new_ghosts[1])

    def _send(self, record) -> bool:
        """Put one record in the ring, or drop it (full, or longer than a slot)."""
        if self.ring.put(pickle.dumps(record, protocol=pickle.HIGHEST_PROTOCOL)):
            return True
        self.dropped += 1
        return False

    def close(self, timeout: float = 5.0, alive=lambda: True) -> bool:
        """Hand over what the routine recorded since its last tick (a stop's event), then tell the publisher the
        run is over (tries for at most ``timeout`` s while the ring is full and ``alive()``, the publisher's
        process runs); False if it could not."""
        r = self._routine
        for _ in range(100 if r is not None and r._last is not None else 0):  # NEWS at a time
            seen = (self._windows, self._events, self._estimates)
            self._hand(r._last, final=True)
            if (self._windows, self._events, self._estimates) == seen:
                break
        end = time.monotonic() + timeout
        while not self.ring.put_end():
            if not alive() or time.monotonic() > end:
                return False
            time.sleep(0.01)
        return True


def _plain_estimate(est) -> tuple | None:
    """An online estimate as plain numbers: initial pose (6), its 1-sigma (6, None without a covariance) and
    the position 1-sigma (m, None for the reference window)."""
    if est is None:
        return None
    sigma = None if est.covariance is None else np.sqrt(np.maximum(np.diag(est.covariance)[:6], 0)).tolist()
    ps = float(est.position_sigma) if math.isfinite(est.position_sigma) else None
    return [float(v) for v in est.theta[:6]], sigma, ps


class LivePublisher:
    """Publishes the records a :class:`LiveTap` hands over on a :class:`LiveServer` (in the publisher process):
    the platform's pose (:class:`acquisition.scene.PoseTracker`), the scene, the samples, windows, events,
    estimates and the supervisor's state."""

    def __init__(self, server: LiveServer, robot: Robot, slack: float, overload: float):
        self.server, self.robot = server, robot
        self.view = RunView(robot, None, slack, overload)
        self.tracker = PoseTracker(robot)
        self.published = 0
        self.scenes = 0
        self.errors: list[str] = []
        self._nwin = 0  # windows published (held in setpoint order)
        self._stopped_by: str | None = None  # the stop recorded in run.yaml, once there is one
        self._times: dict[int, float] = {}  # run time of the logged samples seen, by row (window times)
        self._ghosts: list[list[float]] = []  # the planned poses received

    def publish(self, record: tuple) -> None:
        """One record; a failure is kept in ``errors`` (the view is not the run), never raised."""
        try:
            self._publish(*record)
        except Exception as exc:
            if len(self.errors) < 10:
                self.errors.append(f"{type(exc).__name__}: {exc}")

    def warm_up(self) -> None:
        """Import and run once, on a throwaway view, what publishing a record runs (the statics' first solve and
        a Newton step, the scene's messages and their encoding: 12 ms of CPU the first time, 4 ms the next), so
        that none of it falls in the loop's first seconds."""
        n, tau = self.robot.n, np.full(self.robot.n, 0.5 * (self.robot.tau_min + self.robot.tau_max))
        view, tracker = RunView(self.robot, None, self.view.slack, self.view.overload), PoseTracker(self.robot)
        f = Frame(time.time_ns(), 0.0, tau, tau, np.zeros(n), np.zeros(n), 0.0, 0.0, 0.0, "warm_up", 0, 0, True)
        for _ in range(2):
            msgs = view.frame(f, tracker.update(tau)) + view.supervisor(f.t_ns, 0.0, "stopped", "warm-up")
            msgs += view.window(f.t_ns, 0, 1, 0.0, 0.1, 0, "startup") + view.estimate(f.t_ns, 0, 0.0, [0.0] * 6,
                                                                                      None, None)
            for _, msg in msgs:
                encode(msg)

    def finish(self) -> None:
        """The run is over: the supervisor's last word."""
        t_ns = time.time_ns()
        for topic, msg in self.view.supervisor(t_ns, math.nan, "stopped", self.view.stop, every_ns=0):
            self.server.publish(topic, msg, t_ns)

    def _publish(self, t_ns, t, tau, ref, dl, ds, roll, pitch, dyaw, phase, setpoint, sync, logged, index,
                 requested, extra, ghosts) -> None:
        out: list[tuple[str, Any]] = []
        if ghosts is not None:  # (index of the first, rows): the planned poses as they come
            first, rows = ghosts
            self._ghosts = self._ghosts[:first] + rows
            self.view.set_ghosts(np.array(self._ghosts, dtype=float).reshape(-1, 6))
        if logged:
            self._times[index] = t
        tau = np.array(tau, dtype=float)
        f = Frame(t_ns, t, tau, np.array(ref), np.array(dl), np.array(ds), roll, pitch, dyaw, phase, setpoint,
                  sync, logged)
        out += self.view.frame(f, self.tracker.update(tau))
        state = "stopping" if phase == "safe_stop" else "watching"
        if extra is not None:
            wins, events, estimates, first_pose = extra
            for first, last in wins:
                j, self._nwin = self._nwin, self._nwin + 1
                tf, tl = self._times.get(first, math.nan), self._times.get(last, math.nan)
                out += self.view.window(t_ns, first, last, tf, tl, j, "startup")
            for ev in events:
                out += self.view.event(t_ns, ev)
                self._stopped_by = str(ev["message"])
            for k, est in enumerate(estimates):
                if est is not None:
                    out += self.view.estimate(t_ns, first_pose + k, t, *est)
        out += self.view.supervisor(t_ns, t, state, self._stopped_by or requested)
        for topic, msg in out:
            self.server.publish(topic, msg, t_ns)
            self.published += 1
            self.scenes += topic == "/scene"


def _lowest_priority() -> None:
    """Every thread of this process at nice PUBLISHER_NICE: Linux's niceness is per thread, and numpy's BLAS
    pool starts at import, before ``os.nice``; the threads started later inherit it. Not allowed: unchanged."""
    with contextlib.suppress(OSError):  # e.g. a sandbox that forbids it, or a thread gone meanwhile
        os.nice(PUBLISHER_NICE)
        for tid in map(int, os.listdir("/proc/self/task") if os.path.isdir("/proc/self/task") else []):
            os.setpriority(os.PRIO_PROCESS, tid, max(PUBLISHER_NICE, os.getpriority(os.PRIO_PROCESS, tid)))


def _serve(ring_name: str, alive, control, address: LiveAddress, robot: Robot, slack: float,
           overload: float, wait: float) -> None:
    """The publisher process: the server on ``address``, then every record of the ring ``ring_name`` published
    until its end record or until the loop's process is gone (``alive``, the read end of a pipe the loop never
    writes, reads end of file; or this process's parent changed); waits ``wait`` s (the interval between two
    scene updates) whenever the ring is empty. Runs once what it publishes with (:meth:`LivePublisher.warm_up`)
    before it says it listens. ``control`` says where it listens (or why it cannot) and, at the end, what it
    published. Runs at the lowest priority (nice 19, which the SDK's threads inherit) and leaves SIGINT/SIGTERM
    to the routine (its safe stop is shown to the end). Unlinks the ring if the loop's process is gone (else
    the loop does)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _lowest_priority()
    parent = os.getppid()
    try:
        ring = ShmRing.attach(ring_name)
        server = LiveServer(address, robot.n, stream=io.StringIO())
    except OSError as exc:
        control.send(("error", str(exc)))
        return
    pub = LivePublisher(server, robot, slack, overload)
    pub.warm_up()
    control.send(("listening", server.host, server.port))
    gone = False
    try:
        while True:
            data = ring.get()
            if data is None:  # nothing yet: wait, unless the loop's process ends meanwhile
                gone = alive.poll(wait) or os.getppid() != parent
                if gone:
                    break
                continue
            if not data:  # the end record
                break
            pub.publish(pickle.loads(data))
        pub.finish()
    finally:
        ring.close(unlink=gone)
        server.close(linger=CLOSE_LINGER)
        try:
            control.send(("done", pub.published, pub.scenes, pub.errors))
        except OSError:  # the loop's process is gone
            pass


class LiveView:
    """What ``cdpr startup --live`` runs beside the loop: the loop's tap and the publisher process (the server,
    the scene, the encoding: off the loop's interpreter, so it never holds the loop's GIL); :meth:`off` is the
    view of a startup without ``--live`` (no hook, nothing started)."""

    def __init__(self, tap: LiveTap | None = None, process=None, control=None, host: str = "", port: int = 0,
                 stream=None, alive=None):
        self.tap, self.process, self.control = tap, process, control
        self._alive = alive  # the write end of the pipe whose end of file tells the publisher the loop is gone
        self.host, self.port = host, port
        self.published = self.scenes = 0
        self.errors: list[str] = []
        self._stream = stream or sys.stderr

    @classmethod
    def off(cls) -> LiveView:
        return cls()

    @classmethod
    def start(cls, address: str | LiveAddress, robot: Robot, rate: float, limits, scene_rate: float = SCENE_RATE,
              stream=None, timeout: float = START_TIMEOUT, slots: int = SLOTS) -> LiveView:
        """Start the publisher process listening on ``address`` ([HOST:]PORT) for a startup at ``rate`` Hz whose
        supervisor has ``limits`` (acquisition.safety.SafetyLimits); scene updates at ``scene_rate`` Hz; says
        where it listens on ``stream``; the ring to it holds ``slots`` records. Raises ValueError (address)
        or OSError (cannot listen); the ring is unlinked then."""
        import multiprocessing

        addr = address if isinstance(address, LiveAddress) else LiveAddress.parse(address)
        ctx = multiprocessing.get_context("spawn")  # not forked: the loop's process may have the bus's threads
        ring = ShmRing.create(slots)
        alive_r = alive_w = control_r = control_w = proc = None
        try:
            alive_r, alive_w = ctx.Pipe(duplex=False)
            control_r, control_w = ctx.Pipe(duplex=False)
            proc = ctx.Process(target=_serve, name="cdpr-live", daemon=True,
                               args=(ring.name, alive_r, control_w, addr, robot, limits.slack, limits.overload,
                                     WAIT_SHARE / scene_rate))
            proc.start()
            alive_r.close()
            control_w.close()
            try:
                if not control_r.poll(timeout):
                    raise OSError(f"the live view did not start listening on {addr.host}:{addr.port} within "
                                  f"{timeout:g} s.")
                got = control_r.recv()
            except (EOFError, OSError) as exc:
                raise OSError(str(exc) if str(exc) else "the live view's process ended before it listened.") from exc
            if got[0] == "error":
                proc.join(timeout)
                raise OSError(got[1])
        except BaseException:
            for end in (alive_r, alive_w, control_r, control_w):
                if end is not None:
                    end.close()
            if proc is not None and proc.is_alive():
                proc.kill()
                proc.join(timeout)
            ring.close()
            raise
        view = cls(LiveTap(int(round(rate / scene_rate)), ring), proc, control_r, got[1], got[2], stream, alive_w)
        view._stream.write(listening(view.host, view.port))
        return view

    @property
    def hook(self):
        """The routine's ``on_tick`` (None when off)."""
        return None if self.tap is None else self.tap.on_tick

    def started(self, routine):
        """Attach the routine to the tap; returns the routine."""
        if self.tap is not None:
            self.tap.attach(routine)
        return routine

    def close(self, timeout: float = 10.0) -> None:
        """Publish what is in the ring, stop the server and its process, unlink the ring (safe to call twice)."""
        if self.process is None:
            return
        proc, self.process = self.process, None
        try:
            ended = self.tap.close(alive=proc.is_alive)
            if ended and self.control.poll(timeout):
                try:
                    _, self.published, self.scenes, self.errors = self.control.recv()
                except EOFError:
                    pass
        finally:
            self._alive.close()
            proc.join(timeout)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout)
            self.control.close()
            self.tap.ring.close()
        tap = self.tap
        if tap.dropped or self.errors:
            self._stream.write(f"cdpr: live view: {tap.dropped} of {tap.dropped + tap.handed} ticks dropped (the "
                               f"publisher fell behind the loop; the run is not affected)"
                               + (f"; {len(self.errors)} publishing error(s), the first: {self.errors[0]}"
                                  if self.errors else "") + "\n")


def listening(host: str, port: int) -> str:
    """The line a live view says on start: where it listens."""
    return (f"cdpr: live view on ws://{host}:{port} (read-only; Foxglove: Open connection, Foxglove WebSocket, "
            f"this URL; layout docs/foxglove-layout.json)\n")

