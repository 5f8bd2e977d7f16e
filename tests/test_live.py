"""The live view (`cdpr startup --live`, `cdpr replay --live`): a real WebSocket client speaking the Foxglove
WebSocket protocol (subprotocol foxglove.sdk.v1, the SDK's name for foxglove.websocket.v1) subscribes, decodes
the tensions (JSON) and the 3D scene (protobuf, from the schema the server advertises), tries what a
read-only server must refuse, and vanishes mid-run; the run's samples.csv is the one of a run without --live."""

from __future__ import annotations

import base64
import json
import os
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from test_export_mcap import protobuf_class
from websockets.sync.client import connect

from acquisition.cli import main
from acquisition.live import LiveAddress
from acquisition.runlog import read_run
from acquisition.safety import SafetyLimits
from calib.robot import load_robot
from calib.scene import frame_bounds

ROOT = Path(__file__).resolve().parents[1]
CDPR = [sys.executable, "-c", "import sys; from acquisition.cli import main; sys.exit(main(sys.argv[1:]))"]
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
# a short startup: 8 poses, 1 s windows
STARTUP = ["startup", "--backend", "sim", "--grid", "2", "--hold", "1", "--no-html", "--seed", "5"]


class Client:
    """A Foxglove WebSocket protocol client: serverInfo, advertise, subscribe, binary message data."""

    def __init__(self, port: int):
        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=60).__enter__()
        self.channels: dict[str, dict] = {}
        self.info: dict = {}
        self.status: list[dict] = []
        self.subs: dict[int, str] = {}
        self.classes: dict[str, type] = {}

    def handshake(self, topics: list[str]) -> None:
        while set(topics) - set(self.channels) or not self.info:
            self._text(json.loads(self.ws.recv(timeout=60)))
        self.subs = {i: t for i, t in enumerate(topics)}
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": i, "channelId": self.channels[t]["id"]} for i, t in self.subs.items()]}))

    def _text(self, msg: dict) -> None:
        if msg["op"] == "serverInfo":
            self.info = msg
        elif msg["op"] == "advertise":
            self.channels.update({c["topic"]: c for c in msg["channels"]})
        elif msg["op"] in ("status", "serviceCallFailure"):
            self.status.append(msg)

    def decode(self, topic: str, payload: bytes):
        ch = self.channels[topic]
        if ch["encoding"] == "json":
            return json.loads(payload)
        if topic not in self.classes:
            self.classes[topic] = protobuf_class(ch["schemaName"], base64.b64decode(ch["schema"]))
        return self.classes[topic].FromString(payload)

    def receive(self, until, timeout: float = 120.0) -> dict[str, list]:
        """{topic: [message]} in arrival order until ``until(got)`` holds."""
        got: dict[str, list] = {}
        end = time.monotonic() + timeout
        while not until(got) and time.monotonic() < end:
            data = self.ws.recv(timeout=max(end - time.monotonic(), 0.1))
            if isinstance(data, str):
                self._text(json.loads(data))
                continue
            assert data[0] == 0x01  # MessageData: opcode, subscription id, receive time, payload
            sub, _ = struct.unpack_from("<IQ", data, 1)
            topic = self.subs[sub]
            got.setdefault(topic, []).append(self.decode(topic, data[13:]))
        return got

    def close(self) -> None:
        self.ws.close()


def start_cdpr(args: list[str]) -> tuple[subprocess.Popen, int]:
    """`cdpr ARGS` in a child process; the port its live view says it listens on."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    proc = subprocess.Popen([*CDPR, *args], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    line = proc.stderr.readline()
    assert line.startswith("cdpr: live view on ws://127.0.0.1:"), line + proc.stderr.read()
    return proc, int(line.split("ws://127.0.0.1:")[1].split()[0])


@pytest.fixture(scope="module")
def plain_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("live") / "plain"
    assert main([*STARTUP, "--out", str(out), "--json"]) == 0
    return out


def test_a_live_startup_reaches_its_viewers_in_order_refuses_what_they_send_and_changes_nothing(plain_run, tmp_path):
    """Two viewers of one live startup: one subscribes to the tensions and the scene and vanishes mid-run, the
    other advertises a channel, publishes on it, calls a service, sets and gets a parameter; the run's
    samples.csv is, byte for byte, the one of the same startup without --live."""
    robot = load_robot("irma4u")
    limits = SafetyLimits.for_robot(robot)
    out = tmp_path / "live"
    proc, port = start_cdpr([*STARTUP, "--out", str(out), "--live", "0"])
    try:
        client, pushy = Client(port), Client(port)
        client.handshake(["/samples", "/scene"])
        assert client.ws.subprotocol in SUBPROTOCOLS and client.info["capabilities"] == []  # read-only
        assert client.channels["/scene"]["schemaName"] == "foxglove.SceneUpdate"
        pushy.handshake(["/supervisor"])
        pushy.ws.send(json.dumps({"op": "advertise", "channels": [
            {"id": 1, "topic": "/tension_setpoint", "encoding": "json", "schemaName": "cmd"}]}))
        pushy.ws.send(b"\x01" + struct.pack("<I", 1) + json.dumps({"tau_1": 250.0}).encode())
        pushy.ws.send(b"\x02" + struct.pack("<III", 1, 1, 4) + b"json" + b"{}")
        pushy.ws.send(json.dumps({"op": "setParameters", "parameters": [{"name": "kp", "value": 5.0}]}))
        pushy.ws.send(json.dumps({"op": "getParameters", "parameterNames": ["kp"]}))
        got = client.receive(lambda g: len(g.get("/samples", [])) >= 60 and len(g.get("/scene", [])) >= 60)
        client.close()  # gone mid-run: the startup goes on
        pushy.receive(lambda g: len(pushy.status) >= 5, timeout=60)
        pushy.close()
        stdout, stderr = proc.communicate(timeout=900)
    finally:
        proc.kill()
    assert proc.returncode == 0, stderr
    assert stderr.count("safe stop") == 0
    errors = [s for s in pushy.status if s.get("level") == 2 or s["op"] == "serviceCallFailure"]
    text = " ".join(s["message"] for s in errors)
    assert len(errors) >= 5 and "clientPublish" in text and "parameters" in text and "services" in text
    samples, scenes = got["/samples"], got["/scene"]
    t = np.array([s["t"] for s in samples])
    assert len(t) >= 60 and np.all(np.diff(t) > 0)  # in order, none twice
    tau = np.array([[s[f"tau_{i}"] for i in range(1, 5)] for s in samples])
    assert np.all((tau > limits.slack) & (tau < limits.overload))  # within the supervisor's bounds
    assert {s["phase"] for s in samples} <= {"pretension", "transition", "settle", "hold", "return"}
    lo, hi = frame_bounds(robot)
    stamps = []
    for update in scenes:
        ents = {e.id: e for e in update.entities}
        assert {"frame", "pulleys", "ghosts"} <= set(ents)
        assert len(ents["ghosts"].cubes) == 8
        stamps.append(ents["frame"].timestamp.seconds * 10**9 + ents["frame"].timestamp.nanos)
        if "platform" in ents:  # the platform inside the frame, its cables from the pulleys to it
            p = ents["platform"].cubes[0].pose.position
            assert np.all(lo < [p.x, p.y, p.z]) and np.all([p.x, p.y, p.z] < hi)
            pts = np.array([[q.x, q.y, q.z] for q in ents["cables"].lines[0].points]).reshape(4, 2, 3)
            assert np.all(np.linalg.norm(pts[:, 0] - robot.d, axis=1) < 3 * robot.r)  # exits on the pulleys
    assert sum("platform" in {e.id for e in u.entities} for u in scenes) >= 0.9 * len(scenes)
    assert np.all(np.diff(stamps) > 0)
    # the run is the one without --live, byte for byte
    assert (out / "samples.csv").read_bytes() == (plain_run / "samples.csv").read_bytes()


def test_a_safe_stop_is_shown_live(tmp_path):
    """Winch drive 2 faults at 20 s: the viewer sees the supervisor stop, the event and its sentence."""
    out = tmp_path / "stopped"
    proc, port = start_cdpr([*STARTUP, "--out", str(out), "--live", "0",
                             "--sim-config", str(ROOT / "sim_backend/examples/fault_drive_fault.yaml")])
    try:
        client = Client(port)
        client.handshake(["/supervisor", "/events", "/log", "/samples"])
        got = client.receive(lambda g: any(s["state"] == "stopped" for s in g.get("/supervisor", [])))
        client.close()
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 1 and "safe stop: winch drive 2" in stderr, stderr
    states = [s["state"] for s in got["/supervisor"]]
    assert states.index("watching") < states.index("stopping") < states.index("stopped")
    stop = next(s for s in got["/supervisor"] if s["state"] == "stopping")
    assert stop["stop"].startswith("winch drive 2") and stop["slack_N"] < stop["overload_N"]
    assert [e["kind"] for e in got["/events"]] == ["drive_fault"] == [e["kind"] for e in read_run(out).events]
    assert any(s["phase"] == "safe_stop" for s in got["/samples"])  # the ramp down is watched too
    assert any(m.level == 4 and "drive_fault" in m.message for m in got["/log"])  # an error line (Log.ERROR)


def test_a_replay_plays_the_run_to_a_viewer_at_its_pace(plain_run):
    run = read_run(plain_run)
    speed = 25.0
    proc, port = start_cdpr(["replay", str(plain_run), "--live", "0", "--speed", str(speed)])
    try:
        client = Client(port)
        client.handshake(["/samples", "/windows", "/scene"])
        t0 = time.monotonic()
        got = client.receive(lambda g: len(g.get("/samples", [])) >= len(run))
        wall = time.monotonic() - t0
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 0, stderr
    assert [s["t"] for s in got["/samples"]] == run.t.tolist()
    assert [s["tau_2"] for s in got["/samples"]] == run.tau[:, 1].tolist()
    assert [w["setpoint"] for w in got["/windows"]] == list(range(8))
    assert len(got["/scene"]) >= len(run) - 1
    assert wall > 0.8 * (run.t[-1] - run.t[0]) / speed  # paced, not dumped


@pytest.mark.parametrize("text", ["abc", "70000", "host:", ":-1"])
def test_a_wrong_live_address_is_one_sentence(text, tmp_path, capsys):
    with pytest.raises(ValueError, match=r"is not \[HOST:\]PORT"):
        LiveAddress.parse(text)
    assert main([*STARTUP, "--out", str(tmp_path / "x"), "--live", text]) == 2
    assert "[HOST:]PORT" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_the_live_address_binds_localhost_unless_a_host_is_named():
    assert LiveAddress.parse("8765") == LiveAddress("127.0.0.1", 8765)
    assert LiveAddress.parse("0.0.0.0:9000") == LiveAddress("0.0.0.0", 9000)


def test_the_shipped_layout_shows_only_channels_and_fields_the_view_publishes():
    from acquisition.live import channel_specs
    from acquisition.scene import startup_columns

    layout = json.loads((ROOT / "docs" / "foxglove-layout.json").read_text())
    specs = channel_specs(startup_columns(4))
    panels = layout["configById"]
    paths = [p["value"] for c in panels.values() for p in c.get("paths", [])]
    topics = {c["topicPath"] for c in panels.values() if "topicPath" in c} | {panels["Log!log"]["topicToRender"]}
    topics |= set(panels["3D!cdpr"]["topics"])
    assert topics <= set(specs) and {"/scene", "/tf", "/log", "/supervisor", "/estimate"} <= topics
    assert len(paths) == 19 and all(p.split(".")[0] == "/samples" for p in paths)
    assert {p.split(".")[1] for p in paths} <= set(startup_columns(4))

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(panels)  # every panel placed, none twice


def test_the_loop_runs_on_a_frozen_heap_and_its_run_log_is_written_off_its_thread(tmp_path):
    """Issue 32, the loop's bounded ticks: while the routine runs, the heap that existed before it is frozen
    (no collection walks it inside a tick), the oldest generation is never collected (the young ones are, the
    objects the loop keeps accumulate) and the switch interval is 0.5 ms; the run log is created, fsynced and
    closed by the log worker's thread, all of it on disk when run() returns; the interpreter is restored."""
    import gc
    import math
    import threading

    from acquisition.clock import LOOP_SWITCH_INTERVAL, SimClock
    from acquisition.connect import ahrs_rate_for, connect
    from acquisition.plans import Plan
    from acquisition.runwriter import RunWriter
    from acquisition.startup import StartupConfig, StartupRoutine
    from sim_backend.backend import SimBackend

    robot = load_robot("irma4u")
    grid = Plan.for_robot(robot, 2, "equilibrium")
    plan = Plan(grid.setpoints[:1], grid.ideal_poses[:1], grid.tau0)  # one pose: a few seconds
    cfg = StartupConfig(hold_time=0.5)
    seen: list[tuple[int, float]] = []
    writers: list[str] = []
    loop = threading.current_thread().name

    class Recorded(RunWriter):  # the real writer, noting the thread each file system call runs in
        def __init__(self, *a, **k):
            writers.append(threading.current_thread().name)
            super().__init__(*a, **k)

        def sync(self):
            writers.append(threading.current_thread().name)
            super().sync()

    collections: list[int] = []  # generations collected between the loop's first and last tick

    def note(phase, info):
        if phase == "start" and seen:
            collections.append(info["generation"])

    gc.collect()
    switch, alive, thresholds = sys.getswitchinterval(), len(gc.get_objects()), gc.get_threshold()
    clock = SimClock(1.0 / cfg.rate)
    with SimBackend(robot, None, 3, clock.period, ahrs_rate=ahrs_rate_for(cfg.log_period)) as sim:
        rig = connect(sim.devices, robot, clock, lockstep=True, period=clock.period)
        try:
            import acquisition.startup as startup

            original, startup.RunWriter = startup.RunWriter, Recorded
            try:
                routine = StartupRoutine(robot, rig, clock, plan, tmp_path / "run", cfg, on_tick=lambda s: seen.append(
                    (gc.get_freeze_count() if s.tick % 200 == 0 else math.inf, sys.getswitchinterval())))
                gc.callbacks.append(note)
                routine.run()
            finally:
                gc.callbacks.remove(note)
                startup.RunWriter = original
        finally:
            rig.close()
    assert len(seen) > 1000 and min(f for f, _ in seen) >= 0.9 * alive  # what lived before the run stays frozen
    assert {s for _, s in seen} == {LOOP_SWITCH_INTERVAL}
    # some 2600 ticks: the young generations are collected (tens of times), the oldest never
    assert collections.count(0) > 10 and 2 not in collections, collections
    assert gc.get_freeze_count() == 0 and sys.getswitchinterval() == switch and gc.get_threshold() == thresholds
    assert len(writers) >= 3 and loop not in writers  # created, synced at each window and at the end
    run = read_run(tmp_path / "run")
    assert len(run.t) == routine.writer.count > 0
    assert list(run.phase).count("hold") == 5  # the pose's 0.5 s window at 10 Hz


def test_on_a_real_clock_the_samples_lines_are_written_by_the_log_worker_in_order(tmp_path):
    """Issue 32: a file write can wait for the file system's journal (a tick 361 ms late at load 12), so on a
    real clock each samples.csv line is written and flushed by the log worker, not the loop (on the simulated
    clock the loop writes them): every line is there, in the loop's order, and the windows' row indices name
    the rows of their hold. The clock here is real but does not sleep (lockstep, as fast as it goes)."""
    import threading

    from acquisition.clock import RealClock
    from acquisition.connect import ahrs_rate_for, connect
    from acquisition.plans import Plan
    from acquisition.runwriter import RunWriter
    from acquisition.startup import StartupConfig, StartupRoutine
    from sim_backend.backend import SimBackend

    robot = load_robot("irma4u")
    grid = Plan.for_robot(robot, 2, "equilibrium")
    plan = Plan(grid.setpoints[:2], grid.ideal_poses[:2], grid.tau0)
    cfg = StartupConfig(hold_time=0.5)
    threads: set[str] = set()

    class Recorded(RunWriter):  # the real writer, noting the thread each line is written in
        def append(self, *a, **k):
            threads.add(threading.current_thread().name)
            super().append(*a, **k)

    clock = RealClock(1.0 / cfg.rate, lockstep=True, sleep=lambda s: None)
    with SimBackend(robot, None, 3, clock.period, ahrs_rate=ahrs_rate_for(cfg.log_period)) as sim:
        rig = connect(sim.devices, robot, clock, lockstep=True, period=clock.period)
        try:
            import acquisition.startup as startup

            original, startup.RunWriter = startup.RunWriter, Recorded
            try:
                result = StartupRoutine(robot, rig, clock, plan, tmp_path / "run", cfg).run()
            finally:
                startup.RunWriter = original
        finally:
            rig.close()
    assert len(threads) == 1 and threads != {threading.current_thread().name}, threads
    run = read_run(tmp_path / "run")
    assert len(run.t) == len(result.ticks) > 100
    assert run.extra["tick"].astype(int).tolist() == result.ticks.tolist()
    for j, (first, last) in enumerate(result.windows):
        assert set(run.phase[first:last + 1]) == {"hold"} and set(run.setpoint[first:last + 1]) == {j}
        assert run.phase[first - 1] != "hold" and (last + 1 == len(run.t) or run.phase[last + 1] != "hold")


def test_inside_the_loop_runtime_the_objects_kept_never_cost_a_full_collection():
    """The loop's collector policy (acquisition/clock.py): objects kept by the hundred thousand (a long run's
    rows) trigger automatic collections of the oldest generation outside loop_runtime, none inside it, where
    the young generations are still collected; the thresholds are restored on exit."""
    import gc

    from acquisition.clock import loop_runtime

    def generations_collected(inside: bool) -> list[int]:
        seen: list[int] = []

        def note(phase, info):
            if phase == "start":
                seen.append(info["generation"])

        kept = []
        gc.collect()
        gc.callbacks.append(note)
        try:
            if inside:
                with loop_runtime():
                    seen.clear()  # not loop_runtime's own collection before it freezes
                    kept.extend([k] for k in range(400_000))
            else:
                kept.extend([k] for k in range(400_000))
        finally:
            gc.callbacks.remove(note)
        return seen

    thresholds = gc.get_threshold()
    outside = generations_collected(False)
    inside = generations_collected(True)
    assert outside.count(2) >= 1 and inside.count(2) == 0
    assert inside.count(0) > 100  # 400000 allocations at 700 per young collection
    assert gc.get_threshold() == thresholds and gc.get_freeze_count() == 0


REFUSED_RT = """
import logging, os, resource
import numpy.ma
from acquisition.clock import loop_runtime
resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))  # no real-time priority for an unprivileged process
if os.getuid() == 0:
    os.setgid(65534); os.setuid(65534)  # root may always: be nobody (everything imported before)
with loop_runtime(rt_priority=40) as rt:
    print(rt, os.sched_getscheduler(0) == os.SCHED_OTHER)
"""


@pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="SCHED_FIFO is Linux's")
def test_real_time_priority_is_opt_in_and_falls_back_with_one_sentence():
    """The loop's SCHED_FIFO (acquisition/clock.py, StartupConfig.rt_priority): granted, the loop's thread runs
    under it inside loop_runtime only, and the process's other threads (the interpreter lock's other holders)
    one priority below it, restored after; refused (an unprivileged process without an rtprio limit), the loop runs
    at normal priority and one warning sentence says why and how to grant it."""
    from acquisition.clock import loop_runtime
    from acquisition.startup import StartupConfig

    with pytest.raises(ValueError, match="within 1..99"):
        StartupConfig(rt_priority=0)
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", REFUSED_RT], cwd="/", env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.stdout.split() == ["False", "True"], done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "real-time priority 40 (SCHED_FIFO) was refused" in lines[0]
    assert "ulimit -r 40" in lines[0]
    before = os.sched_getscheduler(0)
    stop, started = threading.Event(), threading.Event()

    def sharer() -> None:  # a thread of the process that shares the interpreter lock (the log worker, say)
        sharer.tid = threading.get_native_id()
        started.set()
        stop.wait(30)

    helper = threading.Thread(target=sharer, daemon=True)
    helper.start()
    started.wait(10)
    try:
        with loop_runtime(rt_priority=40) as rt:
            inside = os.sched_getscheduler(0)
            sharer_inside = os.sched_getscheduler(sharer.tid), os.sched_getparam(sharer.tid).sched_priority
        sharer_after = os.sched_getscheduler(sharer.tid)
    finally:
        stop.set()
        helper.join()
    if not rt:
        pytest.skip("this process may not use SCHED_FIFO (no rtprio limit): the refusal is checked above")
    assert inside & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO and os.sched_getscheduler(0) == before
    assert (sharer_inside[0] & ~os.SCHED_RESET_ON_FORK, sharer_inside[1]) == (os.SCHED_FIFO, 39)
    assert sharer_after == os.SCHED_OTHER


REFUSED_LOCK = """
import os, resource
import numpy.ma
from acquisition.clock import loop_runtime
resource.setrlimit(resource.RLIMIT_MEMLOCK, (8 << 20, 8 << 20))  # a desktop's default: 8 MiB, not unlimited
if os.getuid() == 0:
    os.setgid(65534); os.setuid(65534)  # root may always (CAP_IPC_LOCK): be nobody
with loop_runtime(lock=True):
    print([line.split()[1] for line in open("/proc/self/status") if line.startswith("VmLck")][0])
"""


def _locked_kib() -> int:
    with open("/proc/self/status") as f:
        return int(next(line.split()[1] for line in f if line.startswith("VmLck")))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mlockall and /proc are Linux's")
def test_memory_locking_keeps_the_loop_from_faulting_and_falls_back_with_one_sentence():
    """Issue 32 (acquisition/clock.py lock_memory, StartupConfig.lock_memory): inside loop_runtime(lock=True) the
    process's pages are locked and a heap reserve is resident, so a 48 MiB buffer made and written in the
    loop faults in (almost) no page, where outside it faults each of its pages (48 MiB: above glibc's largest
    mmap threshold, so always fresh pages outside); after it nothing is locked.
    Refused (a finite RLIMIT_MEMLOCK without CAP_IPC_LOCK), nothing is locked and one sentence says how."""
    import resource

    from acquisition.clock import loop_runtime

    def faults_of_a_fresh_array() -> int:
        before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
        a = bytearray(48 << 20)  # 12288 pages (not numpy's: it asks for transparent huge pages)
        a[::4096] = b"\1" * (12 << 10)  # a byte in each page
        del a
        return resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before

    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", REFUSED_LOCK], cwd="/", env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.stdout.split() == ["0"], done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "memory locking (mlockall) was not done" in lines[0], done.stderr
    assert "ulimit -l unlimited" in lines[0]
    outside = faults_of_a_fresh_array()
    with loop_runtime(lock=True):
        locked = _locked_kib()
        inside = faults_of_a_fresh_array()
    if locked == 0:
        pytest.skip("this process may not lock its memory (ulimit -l): the refusal is checked above")
    assert outside >= 12000 and inside <= 20, (outside, inside)
    assert locked > 64 * 1024 and _locked_kib() == 0


def test_a_run_log_write_that_fails_on_the_log_worker_is_raised(tmp_path):
    from acquisition.estimates import LogWorker

    worker = LogWorker()
    worker.submit(open, tmp_path / "no such folder" / "run.yaml", "w")
    with pytest.raises(FileNotFoundError):
        worker.close()


def test_on_a_real_clock_the_detector_refreshes_its_thresholds_on_a_worker_without_waiting():
    """Issue 32: the detector's refresh (the offline statistics of up to 600 s of samples, 15 ms at 6000) is
    handed to a worker; the sample that asks never waits for it and keeps the thresholds it had, the first
    sample after it is ready takes exactly the thresholds the in-line detector took at the asking sample."""
    import pickle
    from concurrent.futures import Future, ThreadPoolExecutor

    from acquisition.equilibrium import DetectorConfig, EquilibriumDetector

    cfg = DetectorConfig.for_robot(load_robot("irma4u"))
    held: list[tuple] = []

    def later(fn, *args) -> Future:  # a worker that has not run the call yet
        held.append((fn, args))
        return Future()

    inline, slow = EquilibriumDetector(0.1, cfg), EquilibriumDetector(0.1, cfg, background=later)
    pool = ThreadPoolExecutor(1)
    worker = EquilibriumDetector(0.1, cfg, background=pool.submit)
    rng = np.random.default_rng(3)
    for det in (inline, slow, worker):
        det.start(0.0)
    for k in range(1, 61):
        row = (100.0 + 0.3 * rng.standard_normal(4), 2e-5 * rng.standard_normal(4), 1e-4 * rng.standard_normal(4),
               1e-4 * rng.standard_normal(), 1e-4 * rng.standard_normal())
        before = slow.stillness
        states = [det.push(0.1 * k, *row) for det in (inline, slow, worker)]
        assert slow.stillness is before  # asked, not waited for
        if k % 10 == 0:  # a refresh: the in-line detector took new thresholds at once, the worker's comes later
            assert inline.stillness.ripple_tol != before.ripple_tol or k == 10
            worker._refreshing.result(timeout=60)
        elif k % 10 == 1 and k > 1:
            assert pickle.dumps(worker.stillness) == pickle.dumps(inline.stillness)  # every threshold, bit for bit
            assert states[2] == states[0]  # judged with the same thresholds
    pool.shutdown()
    assert len(held) == 1 and slow.stillness.ripple_tol == cfg.ripple_floor  # one refresh asked, none taken


def _one_pose_startup(view, out: Path):
    """A one-pose simulated startup (lockstep) with ``view``'s hook; its StartupResult."""
    from acquisition.clock import SimClock
    from acquisition.connect import ahrs_rate_for, connect
    from acquisition.plans import Plan
    from acquisition.startup import StartupConfig, StartupRoutine
    from sim_backend.backend import SimBackend

    robot = load_robot("irma4u")
    grid = Plan.for_robot(robot, 2, "equilibrium")
    plan = Plan(grid.setpoints[:1], grid.ideal_poses[:1], grid.tau0)
    cfg = StartupConfig(hold_time=0.5)
    clock = SimClock(1.0 / cfg.rate)
    with SimBackend(robot, None, 3, clock.period, ahrs_rate=ahrs_rate_for(cfg.log_period)) as sim:
        rig = connect(sim.devices, robot, clock, lockstep=True, period=clock.period)
        try:
            return view.started(StartupRoutine(robot, rig, clock, plan, out, cfg, on_tick=view.hook)).run()
        finally:
            rig.close()


def _start_view(slots: int, said):
    from acquisition.live import LiveView

    robot = load_robot("irma4u")
    return LiveView.start("127.0.0.1:0", robot, 200.0, SafetyLimits.for_robot(robot), stream=said, slots=slots)


def test_a_stalled_publisher_process_costs_the_loop_nothing_but_dropped_ticks(tmp_path):
    """Issue 32: the publisher is a process of its own and the loop only puts records in a shared-memory ring
    without waiting. With that process frozen (SIGSTOP) and a ring of 16 slots, a one-pose startup runs to its
    end, the ticks that do not fit are dropped and counted; thawed, the publisher publishes what the ring held
    and ends, and the ring is unlinked."""
    import io
    import signal

    said = io.StringIO()
    view = _start_view(16, said)
    assert said.getvalue().startswith(f"cdpr: live view on ws://127.0.0.1:{view.port} (read-only")
    assert view.process.pid != os.getpid() and view.process.is_alive()
    name = view.tap.ring.name
    assert Path("/dev/shm", name).exists()
    os.kill(view.process.pid, signal.SIGSTOP)
    try:
        result = _one_pose_startup(view, tmp_path / "run")
    finally:
        os.kill(view.process.pid, signal.SIGCONT)
    tap = view.tap
    assert result.windows and tap.handed == 16 and tap.dropped > 5 * tap.handed  # the ring's 16 slots
    proc = view.process
    view.close()
    assert 0 < view.published and view.scenes <= tap.handed and not view.errors
    assert f"{tap.dropped} of {tap.dropped + tap.handed} ticks dropped" in said.getvalue()
    assert proc.exitcode == 0  # it ended on the end record, not killed
    assert not Path("/dev/shm", name).exists()


def _threads_now(pid: int) -> dict[int, tuple[int, int]]:
    """tid -> (nice, voluntary context switches) of every thread of process ``pid`` (/proc)."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
        status = Path(f"/proc/{pid}/task/{tid}/status").read_text()
        vcs = int(next(ln for ln in status.splitlines() if ln.startswith("voluntary_ctxt_switches")).split()[1])
        out[int(tid)] = (int(stat[stat.rindex(")") + 2:].split()[16]), vcs)
    return out


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux's /proc")
def test_the_idle_publisher_wakes_about_once_per_scene_interval_at_the_lowest_priority():
    """What the view costs beside the loop (issue 32, done-when 2): waiting for records, the publisher process
    wakes about once per scene interval (1/20 s), not every 2 ms (500 wake-ups/s, each a chance that the loop's
    vCPU is busy or stolen); it and every thread it started (the SDK's) run at nice 19."""
    import io

    view = _start_view(16, io.StringIO())
    try:
        pid = view.process.pid
        before = _threads_now(pid)
        time.sleep(2.0)
        after = _threads_now(pid)
        assert len(after) >= 2 and {nice for nice, _ in after.values()} == {19}  # the SDK's threads too
        woke = after[pid][1] - before[pid][1]  # the publisher's own thread: its waits on an empty ring
        assert 10 <= woke <= 60, woke  # 40 at 50 ms; the 2 ms poll it replaces made ~1000
    finally:
        proc = view.process
        view.close()
    assert proc.exitcode == 0 and not view.errors  # it ended on the end record


def test_a_publisher_gone_leaves_the_run_going_and_a_loop_gone_ends_the_publisher(tmp_path):
    """The publisher killed before the run: the startup runs to its end, the ring fills and the rest is dropped,
    the close does not wait for it and unlinks the ring. The loop's process killed mid-run: its publisher sees
    the pipe the loop never writes reach its end of file, ends and unlinks the ring itself."""
    import io
    import signal

    view = _start_view(16, io.StringIO())
    name = view.tap.ring.name
    view.process.kill()
    view.process.join(30)
    result = _one_pose_startup(view, tmp_path / "run")
    t0 = time.monotonic()
    view.close()
    assert result.windows and view.tap.handed == 16 and view.tap.dropped > 100 and view.published == 0
    assert time.monotonic() - t0 < 2.0 and not Path("/dev/shm", name).exists()

    script = ("import io, time; from acquisition.live import LiveView; from acquisition.safety import SafetyLimits; "
              "from calib.robot import load_robot; r = load_robot('irma4u'); v = LiveView.start('127.0.0.1:0', r, "
              "200.0, SafetyLimits.for_robot(r), stream=io.StringIO(), slots=16); "
              "print(v.process.pid, v.tap.ring.name, flush=True); time.sleep(600)")
    loop = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1"))
    try:
        pid, name = loop.stdout.readline().split()
        assert Path("/dev/shm", name).exists()
        os.kill(loop.pid, signal.SIGKILL)
        loop.wait(30)
        end = time.monotonic() + 30
        while Path("/dev/shm", name).exists() and time.monotonic() < end:
            time.sleep(0.05)
        assert not Path("/dev/shm", name).exists()  # the publisher unlinked it
        while time.monotonic() < end:
            try:
                os.kill(int(pid), 0)
            except ProcessLookupError:  # the publisher ended
                break
            time.sleep(0.05)
        else:
            raise AssertionError(f"the publisher {pid} outlived the loop's process by 30 s")
    finally:
        loop.kill()


def _readings(serial_lines: str, ticks: int = 240) -> tuple[str, np.ndarray]:
    """The drivers' port name and (ticks, n + 3) load cells, roll, pitch, yaw the loop reads in lockstep from a
    simulated prototype whose serial lines are ``serial_lines`` (its winches held at a torque ramp)."""
    from acquisition.clock import SimClock
    from acquisition.connect import connect
    from sim_backend.backend import SimBackend

    robot = load_robot("irma4u")
    clock = SimClock(0.005)
    rows = []
    with SimBackend(robot, None, 3, 0.005, serial_lines=serial_lines) as sim:
        rig = connect(sim.devices, robot, clock, lockstep=True, period=0.005)
        try:
            for _ in range(ticks):
                tk = clock.advance()
                snap = rig.tick(tk.index, tk.t, 2.0)
                rows.append([*snap.tau, snap.roll, snap.pitch, snap.yaw])
                rig.command(np.full(robot.n, 0.2 + 1e-3 * tk.index))
        finally:
            rig.close()
        port = sim.devices.loadcells.port
    return port, np.array(rows)


def test_the_simulated_serial_lines_are_socket_pairs_that_carry_the_ptys_bytes():
    """The simulated prototype's load-cell and AHRS lines are Unix socket pairs (their write wakes the reader:
    no kernel worker thread between the plant's process and the loop, docs/live.md) that the drivers open as
    pyserial ``cdprsim://`` ports; the loop reads from them what it reads from ptys, reading for reading."""
    from sim_backend.pty import socket_line_fd

    port, by_socket = _readings("socket")
    pty_port, by_pty = _readings("pty")
    assert port.startswith("cdprsim://loadcells-") and pty_port.startswith("/dev/pts/")
    assert by_socket.shape == (240, 7) and np.isfinite(by_socket).all() and np.ptp(by_socket[:, 0]) > 0
    np.testing.assert_array_equal(by_socket, by_pty)
    with pytest.raises(KeyError):
        socket_line_fd(port)  # the backend closed its end of the line


def test_the_hybrid_wait_sleeps_to_its_margin_then_polls_and_the_loop_runs_with_no_timer_slack():
    """RealClock(spin=...): the sleep ends ``spin`` s before the deadline and the clock is polled to it; without
    spin the sleep is the whole wait (acquisition/clock.py). Inside loop_runtime the thread's timer slack is
    1 ns (Linux's default for a normal thread: 50 us), restored after."""
    import ctypes

    from acquisition.clock import RealClock, loop_runtime

    now, slept, polls = [10.0], [], []

    def sleep(d):
        slept.append(d)
        now[0] += d

    def monotonic():
        polls.append(now[0])
        now[0] += 1e-4  # each look at the clock costs 0.1 ms of the fake wall time
        return now[0]

    rc = RealClock(0.005, monotonic=monotonic, sleep=sleep, spin=0.001)
    rc.advance()
    now[0] += 0.001  # the loop computes for 1 ms
    first = len(polls)
    rc.advance()
    # time zero 10.0001 (the first look); the second tick's deadline 10.0051 is asked for at 10.0013
    assert slept == [pytest.approx(10.0051 - 10.0013 - 0.001)]
    # one look, then about ten polls (0.1 ms each, rounding) from the sleep's end to the deadline and no further
    assert 11 <= len(polls) - first <= 12 and 10.0051 - 1e-9 <= now[0] <= 10.0052 + 1e-9
    assert rc.overruns.count == 0
    with pytest.raises(ValueError, match="spin"):
        RealClock(0.005, spin=0.005)
    if not sys.platform.startswith("linux"):
        return
    prctl = ctypes.CDLL(None, use_errno=True).prctl
    before = prctl(30, 0, 0, 0, 0)  # PR_GET_TIMERSLACK
    with loop_runtime():
        inside = prctl(30, 0, 0, 0, 0)
    assert (inside, prctl(30, 0, 0, 0, 0)) == (1, before) and before > 1


@pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="SCHED_FIFO is Linux's")
def test_real_time_priority_given_to_a_process_reaches_every_thread_of_it():
    """set_realtime(priority, pid) puts every thread of process pid under SCHED_FIFO (the simulated plant's
    process: its main thread and its serial devices' threads share its interpreter lock), not only its first."""
    from acquisition.clock import set_realtime

    code = ("import threading, time; threading.Thread(target=time.sleep, args=(30,), daemon=True).start(); "
            "print('ready', flush=True); time.sleep(30)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        tids = [int(t) for t in os.listdir(f"/proc/{proc.pid}/task")]
        assert len(tids) == 2
        if set_realtime(7, proc.pid) is not None:
            pytest.skip("this process may not use SCHED_FIFO (no rtprio limit)")
        assert [os.sched_getscheduler(t) & ~os.SCHED_RESET_ON_FORK for t in tids] == [os.SCHED_FIFO] * 2
        assert [os.sched_getparam(t).sched_priority for t in tids] == [7, 7]
    finally:
        proc.kill()
        proc.wait()
