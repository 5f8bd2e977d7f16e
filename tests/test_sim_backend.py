"""The simulated prototype behind the real drivers: lockstep streaming, determinism, sensor effects, faults."""

from __future__ import annotations

import math
import os
import signal
import threading

import can
import numpy as np
import pytest

from calib.robot import load_robot
from drivers.interfaces import DeviceError
from drivers.open import open_devices
from sim_backend import plant_link
from sim_backend.backend import SimBackend, power_on_state
from sim_backend.can_drive_emulator import SimulatedNode
from sim_backend.config import SimConfigError, sim_config_from_dict
from sim_backend.physics import CablePhysics, SimulationError
from sim_backend.plant_link import child_process_possible

ROBOT = load_robot("irma4u")
LPR = np.asarray(ROBOT.sensors.length_per_motor_rev)
PERIOD = 0.005


class Rig:
    """The real drivers connected to a running SimBackend on its simulated clock (what the acquisition does)."""

    def __init__(self, sim: SimBackend, listen: bool = False, every: tuple[int, int] = (1, 1)):
        cfg = sim.devices
        self.sim = sim
        self.listener = can.Bus(interface=cfg.can.interface, channel=cfg.can.channel) if listen else None
        self.devices = open_devices(cfg, LPR, clock=lambda: sim.time, every=every, control_period=PERIOD)
        self.sync = self.devices.sync
        self.drives, self.encoders = self.devices.drives, self.devices.encoders
        self.loadcells, self.ahrs = self.devices.loadcells, self.devices.ahrs

    def hold(self, tensions: np.ndarray) -> None:
        for d, tau, lpr in zip(self.drives, tensions, LPR, strict=True):
            d.set_torque(tau * abs(lpr) / (2 * math.pi))

    def tick(self, nodes: bool = True, timeout: float = 2.0):
        c = self.sync.send_sync()
        if not nodes:
            return c, None, None, None
        win = [d.wait_for_sync(c, timeout) if d.due(c) else d.latest() for d in self.drives]
        sw = [e.wait_for_sync(c, timeout) if e.due(c) else e.latest() for e in self.encoders]
        lc = self.loadcells.wait_for(c - 1, timeout)  # the amplifier's line of SYNC c has sequence c - 1
        return c, win, sw, lc

    def close(self) -> None:
        self.devices.close()
        if self.listener is not None:
            self.listener.shutdown()

    def frames(self) -> list[tuple[int, bytes]]:
        out = []
        while (msg := self.listener.recv(timeout=0.0)) is not None:
            out.append((msg.arbitration_id, bytes(msg.data)))
        return out


def test_power_on_pose_is_a_seeded_equilibrium_near_home():
    a = power_on_state(ROBOT, 1)
    b = power_on_state(ROBOT, 1)
    c = power_on_state(ROBOT, 2)
    np.testing.assert_array_equal(a[0], b[0])
    assert np.abs(a[0] - c[0]).max() > 1e-4
    home = power_on_state(ROBOT, 1, spread=0.0)[0]
    for pose, tau in (a, c):
        assert np.abs(pose[:3] - home[:3]).max() <= 0.03
        assert np.all((tau > 40) & (tau < 60))


def test_real_drivers_stream_in_lockstep_with_the_simulated_prototype():
    with SimBackend(ROBOT, None, seed=3, control_period=PERIOD) as sim:
        start = sim.truth()
        assert start.sync_count == 0 and start.time == 0.0
        rig = Rig(sim)
        try:
            rig.hold(start.tensions)
            for d in rig.drives:
                d.enable()
            l0_start = sim.physics.unstretched_lengths()
            sw_start = sim.physics.swivel_angle()
            ahrs = []
            for _ in range(300):
                c, win, sw, lc = rig.tick()
                assert all(r.sync_count == c for r in win + sw)
                assert lc.device_seq == c - 1
                truth = sim.truth()
                assert truth.sync_count == c and truth.time == pytest.approx(c * PERIOD)
                np.testing.assert_allclose(lc.tau, truth.tensions, atol=0.8)
                if (a := rig.ahrs.latest()) is not None:
                    ahrs.append(([a.roll, a.pitch], truth.pose[3:5]))
            assert sim.errors == []
            assert all(d.enabled and d.fault() is None for d in rig.drives)
            # holding torques keep the platform at rest
            assert np.abs(sim.truth().pose - start.pose).max() < 5e-4
            dl = np.array([r.delta_length for r in win])
            np.testing.assert_allclose(dl, sim.physics.unstretched_lengths() - l0_start, atol=2e-6)
            dsw = np.array([r.delta_angle for r in sw])
            np.testing.assert_allclose(dsw, sim.physics.swivel_angle() - sw_start, atol=2 * 2 * math.pi / 65536)
            assert len(ahrs) > 100
            meas, true = np.array([m for m, _ in ahrs]), np.array([t for _, t in ahrs])
            assert np.abs(meas - true).max() < math.radians(0.3)
            # the truth at an earlier time is the record of that tick
            mid = sim.truth(at_time=0.5004)
            assert mid.sync_count == 100 and mid.time == pytest.approx(0.5)
            assert sim.truth(sync_count=100).pose.tolist() == mid.pose.tolist()
        finally:
            rig.close()


def _record_run(seed: int, plant_process: bool | None = None, every: tuple[int, int] = (1, 1)) -> tuple[list, list,
                                                                                                         dict]:
    with SimBackend(ROBOT, None, seed=seed, control_period=PERIOD, plant_process=plant_process) as sim:
        rig = Rig(sim, listen=True, every=every)
        try:
            rig.hold(sim.truth().tensions * 1.05)  # a little more than holding: the platform moves
            for d in rig.drives:
                d.enable()
            cells, angles = [], {}
            for _ in range(120):
                _, _, _, lc = rig.tick()
                cells.append(lc.tau.tolist())
                a = rig.ahrs.latest()  # asynchronous: which packets are caught varies, their content must not
                if a is not None:
                    angles[a.packet_counter] = (a.sample_time_fine, a.roll, a.pitch, a.yaw)
            return rig.frames(), cells, angles
        finally:
            rig.close()


@pytest.mark.skipif(not child_process_possible(), reason="the plant's child process needs fork and two cores")
def test_same_seed_gives_the_same_frames_and_bytes():
    frames_a, cells_a, angles_a = _record_run(11, plant_process=True)
    frames_b, cells_b, angles_b = _record_run(11, plant_process=False)  # the plant in this process
    frames_c, cells_c, _ = _record_run(12)
    assert len(frames_a) > 120 * 8  # SDO set-up, then 1 TPDO per drive and per encoder every SYNC
    assert frames_a == frames_b
    assert cells_a == cells_b
    common = set(angles_a) & set(angles_b)
    assert len(common) > 20
    assert all(angles_a[k] == angles_b[k] for k in common)
    assert frames_a != frames_c and cells_a != cells_c


def test_nodes_skipping_their_quiet_syncs_send_the_same_frames(monkeypatch):
    # a drive answers every 4th SYNC and an encoder every 20th (feedback_every): the backend skips a node at
    # the SYNCs where it has nothing to send, and its counters catch up at the next one it answers
    frames_skipping, cells_skipping, _ = _record_run(5, every=(4, 20))
    monkeypatch.setattr(SimulatedNode, "idle_at", lambda self, count, t: False)  # every node at every SYNC
    frames_full, cells_full, _ = _record_run(5, every=(4, 20))
    tpdos = [f for f in frames_full if 0x180 <= f[0] < 0x500]
    assert 120 // 4 * 4 <= len(tpdos) < 120 * 8  # the drives' and encoders' TPDOs at their own rates
    assert frames_skipping == frames_full
    assert cells_skipping == cells_full


def test_a_torque_target_acts_from_the_sync_after_it_arrives():
    # CiA 402 synchronous RPDO: the target received before SYNC n is applied at SYNC n; the tensions the
    # load cells read at SYNC n are those of that instant, before the new torque has acted
    with SimBackend(ROBOT, None, seed=2, control_period=PERIOD) as sim:
        rig = Rig(sim)
        try:
            hold = sim.truth().tensions
            rig.hold(hold)
            for d in rig.drives:
                d.enable()
            for _ in range(40):
                rig.tick()
            _, _, _, before = rig.tick()
            rig.hold(hold * 1.3)  # the step, sent before the next SYNC
            _, _, _, at = rig.tick()
            _, _, _, after = rig.tick()
            # at the SYNC that applies the step the platform has not felt it yet; one period later it has
            assert np.abs(at.tau - before.tau).max() < 0.3
            assert (after.tau - at.tau).min() > 1.0
        finally:
            rig.close()


@pytest.mark.parametrize("plant_process", [True, False], ids=["child", "in-process"])
def test_a_failing_plant_silences_the_nodes_with_its_reason(monkeypatch, plant_process):
    if plant_process and not child_process_possible():
        pytest.skip("the plant's child process needs fork and two cores")
    real_step = CablePhysics.step

    def step(self, dt, t_end=None):
        if t_end is not None and t_end > 10 * PERIOD + 1e-9:
            raise SimulationError(f"the simulated platform diverged at t = {self.time:.3f} s (test)")
        real_step(self, dt, t_end)

    monkeypatch.setattr(CablePhysics, "step", step)  # before the backend starts: the child inherits it
    with SimBackend(ROBOT, None, seed=1, control_period=PERIOD, plant_process=plant_process) as sim:
        for _ in range(10):
            sim.tick()
        with pytest.raises(SimulationError, match=r"diverged at t = 0\.050 s \(test\)"):
            sim.tick()  # SYNC 11 would publish the state the failed step was to give
        with pytest.raises(SimulationError, match="diverged at t = 0.050 s"):
            sim.tick()  # and it stays failed
        assert sim.sync_count == 10 and sim.truth().sync_count == 10


@pytest.mark.skipif(not child_process_possible(), reason="the plant's child process needs fork and two cores")
def test_the_plant_process_dies_loudly_and_holds_no_pipe_of_its_parent():
    r, w = os.pipe()  # a pipe the parent holds to someone else (cdpr's report renderer has one)
    try:
        with SimBackend(ROBOT, None, seed=1, control_period=PERIOD, plant_process=True) as sim:
            os.close(w)
            w = -1
            os.set_blocking(r, False)
            assert os.read(r, 1) == b""  # end of file: the child did not keep a copy of the write end
            pid = sim._link.pid
            sim.tick()
            sim._link.collect()  # its answer to that SYNC is in
            os.kill(pid, signal.SIGKILL)
            sim.tick()  # publishes that answer, hands over commands nobody will take
            with pytest.raises(SimulationError, match=rf"process \(pid {pid}\) ended \(killed by signal 9\)"):
                sim.tick()
        with pytest.raises(ChildProcessError):
            os.waitpid(pid, os.WNOHANG)  # reaped
    finally:
        os.close(r)
        if w >= 0:
            os.close(w)


@pytest.mark.skipif(not child_process_possible(), reason="the plant's child process needs fork and two cores")
def test_a_sync_returns_with_its_serial_samples_on_the_lines_however_late_the_plant_runs(monkeypatch):
    # the plant's process stopped right after answering a SYNC (a loaded machine's worst case, made sure):
    # the next SYNC's send returns only once the process has run again and written that SYNC's samples, so the
    # master's look at its ports right after the send (no waiting) finds them; before, the send returned at
    # once and the line came whenever the process ran again. A stopped plant is late, not silent: the link's
    # guard against a hung child does not count the time it is stopped
    monkeypatch.setattr(plant_link, "ANSWER_TIMEOUT", 0.2)
    with SimBackend(ROBOT, None, seed=1, control_period=PERIOD, plant_process=True, ahrs_rate=200.0) as sim:
        devices = open_devices(sim.devices, LPR, clock=lambda: sim.time, control_period=PERIOD, polled=True)
        try:
            for _ in range(3):
                devices.sync.send_sync()
            pid = sim.plant_pid
            seen = []
            for stop in (0.0, 0.5, 0.0, 0.5):
                sim._link.collect()  # the plant has answered the last SYNC: it now waits for the next one
                if stop:
                    os.kill(pid, signal.SIGSTOP)
                    threading.Timer(stop, os.kill, (pid, signal.SIGCONT)).start()
                c = devices.sync.send_sync()
                lc, ahrs = devices.loadcells.latest(), devices.ahrs.latest()  # one non-blocking read each
                seen.append((c, lc.device_seq, round(ahrs.sample_time_fine * 1e-4 / PERIOD)))
            assert seen == [(c, c - 1, c) for c, _, _ in seen]  # the line of SYNC c has sequence c - 1
        finally:
            devices.close()


def test_load_cell_offset_gain_and_ahrs_tilt_reach_the_drivers():
    offset = np.array([3.0, -2.0, 0.0, 4.0])
    gain = np.array([0.03, -0.02, 0.0, 0.01])
    tilt = (math.radians(1.0), math.radians(-0.5))
    cfg = sim_config_from_dict(
        {
            "effects": {
                "tension_offset": {"offset": offset.tolist()},
                "tension_gain": {"gain": gain.tolist()},
                "ahrs_mounting": {"roll": tilt[0], "pitch": tilt[1]},
            }
        }
    )
    with SimBackend(ROBOT, cfg, seed=4, control_period=PERIOD) as sim:
        rig = Rig(sim)
        try:
            err, angle_err = [], []
            for _ in range(150):
                _, _, _, lc = rig.tick()
                truth = sim.truth()
                err.append(lc.tau - ((1 + gain) * truth.tensions + offset))
                if (a := rig.ahrs.latest()) is not None:
                    angle_err.append(np.array([a.roll, a.pitch]) - truth.pose[3:5])
            # what remains is the amplifier's accuracy class (0.02 % of 981 N) and its noise
            assert np.abs(np.mean(err, axis=0)).max() < 0.25
            np.testing.assert_allclose(np.mean(angle_err, axis=0), tilt, atol=math.radians(0.12))
        finally:
            rig.close()


def test_serial_and_cable_faults_happen_at_their_times():
    cfg = sim_config_from_dict(
        {
            "faults": [
                {"kind": "loadcell_stuck", "t": 0.2, "channel": 3},
                {"kind": "ahrs_corrupt", "t": 0.3, "bytes": 12},
                {"kind": "cable_slack", "t": 0.4, "cable": 1, "length": 0.05},
                {"kind": "loadcell_disconnected", "t": 0.6},
            ]
        }
    )
    with SimBackend(ROBOT, cfg, seed=5, control_period=PERIOD) as sim:
        rig = Rig(sim)
        try:
            readings = []
            for _ in range(119):  # up to t = 0.595 s
                c, _, _, lc = rig.tick()
                readings.append((sim.time, lc.tau.copy(), sim.truth().tensions))
            ch3 = np.array([r[1][2] for r in readings])
            times = np.array([r[0] for r in readings])
            assert np.ptp(ch3[times < 0.2 - 1e-9]) > 0  # noisy before
            assert np.ptp(ch3[times >= 0.2 - 1e-9]) == 0  # frozen after
            slack = [r for r in readings if r[0] > 0.45]
            assert all(r[2][0] == 0.0 for r in slack)
            assert all(abs(r[1][0]) < 1.0 for r in slack)
            for _ in range(40):  # the corrupted bytes reach the AHRS driver
                rig.tick(nodes=False)
            assert rig.ahrs.stats.checksum_errors + rig.ahrs.stats.resyncs > 0
            with pytest.raises(DeviceError):
                rig.loadcells.wait_for(c + 60, 0.3)
        finally:
            rig.close()


def test_drive_fault_and_lost_frames_reach_the_drivers():
    cfg = sim_config_from_dict(
        {
            "faults": [
                {"kind": "drive_fault", "t": 0.1, "drive": 2},
                {"kind": "can_frames_lost", "t": 0.3, "duration": 0.02, "fraction": 1.0},
            ]
        }
    )
    with SimBackend(ROBOT, cfg, seed=6, control_period=PERIOD) as sim:
        rig = Rig(sim)
        try:
            rig.hold(sim.truth().tensions)
            for d in rig.drives:
                d.enable()
            seen_fault = None
            for _ in range(50):  # to t = 0.25 s
                c, win, _, _ = rig.tick()
                if seen_fault is None and rig.drives[1].fault() is not None:
                    seen_fault = sim.time
            assert seen_fault is not None and seen_fault <= 0.1 + 3 * PERIOD + 1e-9
            assert "emergency 0x2310" in rig.drives[1].fault()
            assert sim.physics.brake(1) and not sim.physics.brake(0)  # the faulted winch holds on its brake
            assert rig.drives[0].fault() is None
            for _ in range(9):  # to t = 0.295 s
                rig.tick()
            c = rig.sync.send_sync()  # SYNC 60, stepped to t = 0.300 s: every node's frames are lost
            with pytest.raises(DeviceError, match="sent no PDOs for SYNC 60"):
                rig.drives[0].wait_for_sync(c, 0.2)
            for _ in range(6):
                rig.tick(nodes=False)
            c, win, sw, _ = rig.tick()  # t = 0.335 s: back
            assert win[0].sync_count == c and sw[3].sync_count == c
            assert sim.errors == []
        finally:
            rig.close()


def test_backend_errors_name_the_bad_value():
    with pytest.raises(SimConfigError, match="control_period = 0.5 s must be in"):
        SimBackend(ROBOT, None, control_period=0.5)
    with pytest.raises(SimConfigError, match="initial_pose = .* needs a slack cable"):
        SimBackend(ROBOT, None, initial_pose=np.array([1.5, 0.0, 0.5, 0.0, 0.0, 0.0])).start()


def test_initial_pose_is_honoured_and_the_platform_rests_there():
    pose = np.array([0.1, -0.05, 0.8, 0.0, 0.0, 0.0])
    with SimBackend(ROBOT, None, seed=0, initial_pose=pose) as sim:
        t = sim.truth()
        assert t.time == 0.0
        assert np.abs(t.pose[:3] - pose[:3]).max() < 0.01  # roll and pitch settle to balance the moments
        for _ in range(100):
            sim.tick()  # no driver: ticks straight from the backend, drives disabled, winches braked
        assert np.abs(sim.truth().pose - t.pose).max() < 1e-4
        # the clock sits exactly on the SYNC grid (summing 0.005 s a hundred times would give 0.5000000000000002)
        assert sim.time == 100 * 0.005


def test_scalar_readers_follow_the_published_state_and_name_a_bad_quantity():
    from sim_backend.plant import scalar_reader

    robot = load_robot("irma4u")
    with SimBackend(robot, seed=2, plant_process=False) as sim:
        view = sim.physics
        physics = sim._link.core.physics  # a plant without readers of its own: the generic path
        readers = {q: [scalar_reader(view, q, i) for i in range(4)]
                   for q in ("motor_position", "motor_velocity", "cable_tension", "swivel_angle", "motor_torque")}
        generic = [scalar_reader(physics, "cable_tension", i) for i in range(4)]
        for _ in range(30):
            sim.tick()
            for q, rs in readers.items():
                assert [r() for r in rs] == [float(v) for v in getattr(view, q)()]
        view.set_motor_torque(2, 0.125)  # a command given now is read at once
        assert readers["motor_torque"][2]() == 0.125
        assert [g() for g in generic] == physics.cable_tension().tolist()
        with pytest.raises(ValueError, match="no per-cable quantity 'q' with cable 0"):
            view.reader("q", 0)
        with pytest.raises(ValueError, match="'swivel_angle' with cable 4"):
            view.reader("swivel_angle", 4)
        with pytest.raises(ValueError, match="'motor_torque' with cable -1"):
            view.reader("motor_torque", -1)
