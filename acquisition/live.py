"""The live view of a startup (``cdpr startup ... --live [HOST:]PORT``) and of a replayed run, in Foxglove.

The Foxglove SDK's WebSocket server (``foxglove-sdk``; protocol subprotocol ``foxglove.sdk.v1``, the renamed
``foxglove.websocket.v1``) on its own :class:`foxglove.Context` publishes the channels of
:mod:`acquisition.scene`. Read-only: it is started with no capability at all (no client publishing, no
services, no parameters, no playback control), so whatever a client sends is refused by the server with an
error status and never reaches this process; it binds 127.0.0.1 unless a host is named.

The control loop never waits for it: :class:`LiveTap` runs in the loop's thread at each tick and only, every
``every`` ticks and at each logged sample, puts the tick's snapshot (read-only arrays, no copy) into a
bounded queue, dropping it when the queue is full; :class:`LivePublisher`, a thread of its own, takes them
out, estimates the platform's pose (:class:`acquisition.scene.PoseTracker`), encodes and logs the messages.
The server's own threads send them; a client that is slow, connects or vanishes only changes what it
receives. The loop's thread, waking from its sleep, waits for the publisher's thread at most the switch
interval the routine runs at (:func:`acquisition.clock.loop_runtime`, with or without the view); a replay's
publisher sets the same :data:`SWITCH_INTERVAL`.
"""

from __future__ import annotations

import json
import math
import queue
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from acquisition.clock import LOOP_SWITCH_INTERVAL
from acquisition.scene import (
    ESTIMATE_SCHEMA,
    EVENT_SCHEMA,
    SUPERVISOR_SCHEMA,
    WINDOW_SCHEMA,
    PoseTracker,
    SceneModel,
    foxglove_schemas,
    log_message,
    number,
    sample_schema,
    startup_columns,
)
from calib.robot import Robot

SCENE_RATE = 20.0  # Hz, scene updates during a startup
QUEUE_SIZE = 256  # snapshots waiting for the publisher; more are dropped
SWITCH_INTERVAL = LOOP_SWITCH_INTERVAL  # s, sys.setswitchinterval while a publisher runs (also the loop's)


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


@dataclass(frozen=True)
class Frame:
    """One moment of a run for the view: log time (ns), run time t (s; NaN before the run log starts), the
    readings as logged (tau (n,) N, tau_ref (n,) N, dl (n,) m and dsigma (n,) rad since power-on, roll, pitch,
    dyaw rad), phase, setpoint, SYNC tick, and whether it is a row of samples.csv."""

    t_ns: int
    t: float
    tau: np.ndarray
    tau_ref: np.ndarray
    dl: np.ndarray
    dsigma: np.ndarray
    roll: float
    pitch: float
    dyaw: float
    phase: str
    setpoint: int
    tick: int
    logged: bool


class RunView:
    """The messages of a run's view (topic, message), frame by frame; remembers the phase and the supervisor's
    state to log their changes. Shared by the live startup, the live replay and the MCAP export."""

    def __init__(self, robot: Robot, ghosts: np.ndarray | None, slack: float, overload: float):
        self.robot = robot
        self.scene = SceneModel.for_robot(robot, ghosts)
        self.slack, self.overload = float(slack), float(overload)
        self._phase: tuple[str, int] | None = None
        self._state: tuple[str, str | None] | None = None
        self._state_ns = 0

    @property
    def stop(self) -> str | None:
        """The stop the supervisor reported last (None: no stop)."""
        return None if self._state is None else self._state[1]

    def set_ghosts(self, ghosts: np.ndarray) -> None:
        """The planned poses (k, 6) shown as ghosts (a sequential plan grows)."""
        self.scene = SceneModel.for_robot(self.robot, ghosts)

    def sample(self, f: Frame) -> dict[str, Any]:
        """The /samples message: the columns of samples.csv by name."""
        n = self.robot.n
        msg: dict[str, Any] = {"t": number(f.t)}
        for g, a in (("tau", f.tau), ("tau_ref", f.tau_ref), ("dl", f.dl), ("dsigma", f.dsigma)):
            vals = np.asarray(a, dtype=float).tolist()
            for i in range(n):
                msg[f"{g}_{i + 1}"] = number(vals[i])
        msg.update(roll=number(f.roll), pitch=number(f.pitch), dyaw=number(f.dyaw), phase=str(f.phase),
                   setpoint=int(f.setpoint), tick=int(f.tick))
        return msg

    def frame(self, f: Frame, pose: np.ndarray | None, scene: bool = True, solved: np.ndarray | None = None
              ) -> list[tuple[str, Any]]:
        """The messages of one frame: its sample (if logged), the scene and transform at ``pose`` (6,) (None:
        unknown; ``solved``: the solve's initial pose, see SceneModel.update), and a log line when the phase or
        setpoint changes."""
        out: list[tuple[str, Any]] = []
        if f.logged:
            out.append(("/samples", self.sample(f)))
        if (f.phase, f.setpoint) != self._phase:
            self._phase = (f.phase, f.setpoint)
            where = f" setpoint {f.setpoint}" if f.setpoint >= 0 else ""
            out.append(("/log", log_message(f.t_ns, f"phase {f.phase}{where}")))
        if scene:
            label = f"{f.phase}" + (f" {f.setpoint}" if f.setpoint >= 0 else "")
            out.append(("/scene", self.scene.update(f.t_ns, pose, f.tau, label, solved)))
            if pose is not None:
                out.append(("/tf", self.scene.transform(f.t_ns, pose)))
        return out

    def supervisor(self, t_ns: int, t: float, state: str, stop: str | None, every_ns: int = 1_000_000_000
                   ) -> list[tuple[str, Any]]:
        """/supervisor when its state changes, else once per ``every_ns``; a stop is also a /log error."""
        key = (state, stop)
        if key == self._state and t_ns - self._state_ns < every_ns:
            return []
        out: list[tuple[str, Any]] = [("/supervisor", {"t": number(t) if number(t) is not None else 0.0,
                                                      "state": state, "slack_N": self.slack,
                                                      "overload_N": self.overload, "stop": stop})]
        if key != self._state and state != "watching":
            out.append(("/log", log_message(t_ns, f"supervisor: {state}" + (f": {stop}" if stop else ""),
                                            "Error" if stop else "Warning")))
        self._state, self._state_ns = key, t_ns
        return out

    @staticmethod
    def window(t_ns: int, first: int, last: int, t_first: float, t_last: float, setpoint: int,
               source: str) -> list[tuple[str, Any]]:
        msg = {"first": int(first), "last": int(last), "t_first": float(t_first), "t_last": float(t_last),
               "setpoint": int(setpoint), "source": source}
        return [("/windows", msg), ("/log", log_message(t_ns, f"equilibrium window of setpoint {setpoint}: samples "
                                                          f"{first}..{last} ({t_first:.1f}..{t_last:.1f} s)"))]

    @staticmethod
    def event(t_ns: int, ev: dict[str, Any]) -> list[tuple[str, Any]]:
        msg = {"t": float(ev["t"]), "kind": str(ev["kind"]), "message": str(ev["message"])}
        return [("/events", msg), ("/log", log_message(t_ns, f"{msg['kind']}: {msg['message']}", "Error"))]

    @staticmethod
    def estimate(t_ns: int, pose: int, t: float, initial_pose, sigma, position_sigma: float | None
                 ) -> list[tuple[str, Any]]:
        p = [float(v) for v in initial_pose][:6]
        ps = None if position_sigma is None else number(position_sigma)
        msg = {"pose": int(pose), "t": float(t), "initial_pose": p,
               "initial_pose_sigma": None if sigma is None else [number(v) for v in sigma][:6],
               "position_sigma_m": ps}
        text = (f"online estimate after pose {pose}: x0 {p[0]:+.4f} {p[1]:+.4f} {p[2]:+.4f} m"
                + (f", 1-sigma {1000 * ps:.2f} mm" if ps is not None else " (reference window)"))
        return [("/estimate", msg), ("/log", log_message(t_ns, text))]


class _Subscriptions:
    """The server's listener: it only notes that a viewer subscribed (the server has no capability, so a
    client's messages, service calls and parameters are refused before any listener would hear of them)."""

    def __init__(self) -> None:
        self.first = threading.Event()

    def on_subscribe(self, client, channel) -> None:
        self.first.set()

    def on_unsubscribe(self, client, channel) -> None:
        pass


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
        (stream or sys.stderr).write(f"cdpr: live view on ws://{self.host}:{self.port} (read-only; Foxglove: "
                                     f"Open connection, Foxglove WebSocket, this URL; layout docs/foxglove-layout"
                                     f".json)\n")

    def publish(self, topic: str, msg: Any, t_ns: int) -> None:
        self._channels[topic].log(encode(msg), log_time=int(t_ns))

    def wait_for_viewer(self, timeout: float | None = None) -> bool:
        """Wait until a client has subscribed to a channel (at most ``timeout`` s); True if one has."""
        return self._subscriptions.first.wait(timeout)

    def close(self) -> None:
        for ch in self._channels.values():
            ch.close()
        self.server.stop()

    def __enter__(self) -> LiveServer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class LiveTap:
    """The control loop's side of the live view: ``on_tick`` (StartupRoutine's hook) hands every ``every``-th
    tick and every logged sample to a bounded queue, dropping what does not fit; never blocks, never writes
    to the routine. :meth:`attach` the routine before it runs."""

    def __init__(self, every: int, maxsize: int = QUEUE_SIZE):
        self.every = max(int(every), 1)
        self.queue: queue.Queue = queue.Queue(maxsize)
        self.dropped = 0
        self.handed = 0
        self._routine = None
        self._windows = self._events = self._estimates = 0  # seen so far

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
        if news:
            extra = (r._windows[self._windows:], r.writer.meta["events"][self._events:] if events else [],
                     [est for _, est in r._history[self._estimates:]], self._estimates)
        item = (time.time_ns(), snap, r._ref, r._phase, r._setpoint, logged, r._t_run0, r._zero,
                r.supervisor.requested, extra, r.plan.ideal_poses)
        try:
            self.queue.put_nowait(item)
        except queue.Full:  # dropped; a window, event or estimate in it goes with the next tick handed over
            self.dropped += 1
            return
        self.handed += 1
        if news:
            self._windows, self._events, self._estimates = wins, events, estimates

    def close(self, timeout: float = 5.0) -> None:
        """Hand over what the routine recorded since its last tick (a stop's event), then tell the publisher the
        run is over (waits at most ``timeout`` s for room in the queue)."""
        r = self._routine
        if r is not None and r._last is not None:
            self._hand(r._last, final=True)
        try:
            self.queue.put(None, timeout=timeout)
        except queue.Full:
            pass


class LivePublisher(threading.Thread):
    """Publishes what a :class:`LiveTap` hands over, on a :class:`LiveServer`; stops at the tap's close."""

    def __init__(self, tap: LiveTap, server: LiveServer, robot: Robot, slack: float, overload: float):
        super().__init__(name="cdpr-live", daemon=True)
        self.tap, self.server, self.robot = tap, server, robot
        self.view = RunView(robot, None, slack, overload)
        self.tracker = PoseTracker(robot)
        self.published = 0
        self.scenes = 0
        self.errors: list[str] = []
        self._ghosts = 0
        self._nwin = 0  # windows published (held in setpoint order)
        self._stopped_by: str | None = None  # the stop recorded in run.yaml, once there is one
        self._times: list[float] = []  # run time of every logged sample seen (window times)
        self._switch = sys.getswitchinterval()

    def start(self) -> None:
        sys.setswitchinterval(SWITCH_INTERVAL)
        super().start()

    def stop(self, timeout: float = 10.0) -> None:
        """Close the tap and wait for the queue to be published (at most ``timeout`` s)."""
        self.tap.close()
        self.join(timeout)
        sys.setswitchinterval(self._switch)

    def run(self) -> None:
        while True:
            item = self.tap.queue.get()
            if item is None:
                break
            try:
                self._publish(*item)
            except Exception as exc:  # the view is not the run: a failure here is reported, never raised
                if len(self.errors) < 10:
                    self.errors.append(f"{type(exc).__name__}: {exc}")
        t_ns = time.time_ns()  # the run is over: the supervisor's last word
        for topic, msg in self.view.supervisor(t_ns, math.nan, "stopped", self.view.stop, every_ns=0):
            self.server.publish(topic, msg, t_ns)

    def _publish(self, t_ns, snap, ref, phase, setpoint, logged, t_run0, zero, requested, extra, ghosts) -> None:
        out: list[tuple[str, Any]] = []
        if len(ghosts) != self._ghosts:
            self.view.set_ghosts(ghosts)
            self._ghosts = len(ghosts)
        t = round(snap.t - t_run0, 9) if t_run0 is not None else math.nan  # the run log's time
        if logged:
            self._times.append(t)
        if zero:
            dl, ds, dyaw = snap.dl - zero["dl"], snap.dsigma - zero["dsigma"], snap.yaw - zero["yaw"]
        else:
            dl, ds, dyaw = snap.dl * math.nan, snap.dsigma * math.nan, math.nan
        f = Frame(t_ns, t, snap.tau, ref, dl, ds, snap.roll, snap.pitch, dyaw, phase, setpoint, snap.sync, logged)
        pose = self.tracker.update(snap.tau)
        out += self.view.frame(f, pose)
        state = "stopping" if phase == "safe_stop" else "watching"
        if extra is not None:
            wins, events, estimates, first_pose = extra
            for first, last in wins:
                j, self._nwin = self._nwin, self._nwin + 1
                tf, tl = (self._times[first], self._times[last]) if last < len(self._times) else (math.nan, math.nan)
                out += self.view.window(t_ns, first, last, tf, tl, j, "startup")
            for ev in events:
                out += self.view.event(t_ns, ev)
                self._stopped_by = str(ev["message"])
            for k, est in enumerate(estimates):
                if est is None:
                    continue
                sigma = None if est.covariance is None else np.sqrt(np.maximum(np.diag(est.covariance)[:6], 0))
                ps = est.position_sigma if math.isfinite(est.position_sigma) else None
                out += self.view.estimate(t_ns, first_pose + k, t, est.theta[:6], sigma, ps)
        out += self.view.supervisor(t_ns, t, state, self._stopped_by or requested)
        for topic, msg in out:
            self.server.publish(topic, msg, t_ns)
            self.published += 1
            self.scenes += topic == "/scene"


class LiveView:
    """What ``cdpr startup --live`` runs beside the loop: the server, the loop's tap and the publisher thread;
    :meth:`off` is the view of a startup without ``--live`` (no hook, nothing started)."""

    def __init__(self, server: LiveServer | None = None, tap: LiveTap | None = None,
                 publisher: LivePublisher | None = None, stream=None):
        self.server, self.tap, self.publisher = server, tap, publisher
        self._stream = stream or sys.stderr

    @classmethod
    def off(cls) -> LiveView:
        return cls()

    @classmethod
    def start(cls, address: str | LiveAddress, robot: Robot, rate: float, limits, scene_rate: float = SCENE_RATE,
              stream=None) -> LiveView:
        """Listen on ``address`` ([HOST:]PORT) for a startup at ``rate`` Hz whose supervisor has ``limits``
        (acquisition.safety.SafetyLimits); scene updates at ``scene_rate`` Hz. Raises ValueError (address)
        or OSError (cannot listen)."""
        addr = address if isinstance(address, LiveAddress) else LiveAddress.parse(address)
        server = LiveServer(addr, robot.n, stream=stream)
        tap = LiveTap(int(round(rate / scene_rate)))
        return cls(server, tap, LivePublisher(tap, server, robot, limits.slack, limits.overload), stream)

    @property
    def hook(self):
        """The routine's ``on_tick`` (None when off)."""
        return None if self.tap is None else self.tap.on_tick

    def started(self, routine):
        """Attach the routine to the tap and start publishing; returns the routine."""
        if self.tap is not None:
            self.tap.attach(routine)
            self.publisher.start()
        return routine

    def close(self) -> None:
        """Publish what is queued, stop the server (safe to call twice)."""
        if self.server is None:
            return
        if self.publisher.is_alive():
            self.publisher.stop()
        self.server.close()
        self.server = None
        tap, pub = self.tap, self.publisher
        if tap.dropped or pub.errors:
            self._stream.write(f"cdpr: live view: {tap.dropped} of {tap.dropped + tap.handed} ticks dropped (the "
                               f"publisher fell behind the loop; the run is not affected)"
                               + (f"; {len(pub.errors)} publishing error(s), the first: {pub.errors[0]}" if pub.errors
                                  else "") + "\n")
