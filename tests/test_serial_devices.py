"""Drivers against the simulated devices over pty pairs: configuration, streaming, a fault, recovery, and
detection of a silent device within 3 periods."""

from __future__ import annotations

import math
import os
import struct
import threading
import time

import numpy as np
import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from calib.kinematics import rotation, rotation_to_euler
from drivers import xbus
from drivers.interfaces import DeviceError
from drivers.loadcell import LoadCellConfig, LoadCellDriver
from drivers.xbus import MID, XDI
from drivers.xsens import XsensConfig, XsensMti
from sim_backend.loadcell_emulator import LoadCellEmulator
from sim_backend.pty import open_pty_pair
from sim_backend.xsens_emulator import XsensEmulator

DT = 0.01  # simulated control tick, s


class Ticker:
    """Steps an emulator on the simulated clock from a thread, a little faster than real time."""

    def __init__(self, step) -> None:
        self.step = step
        self.k = 0
        self.running = threading.Event()
        self.running.set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.running.is_set():
                self.step(self.k * DT)
                self.k += 1
            time.sleep(DT / 2)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


def quiesce(drv, settle: float = 0.15, limit: float = 5.0):
    """The driver's latest reading once nothing new has arrived for ``settle`` s (the line has gone quiet)."""
    end = time.monotonic() + limit
    last = drv.latest()
    while time.monotonic() < end:
        time.sleep(settle)
        now = drv.latest()
        if now is last:
            return last
        last = now
    raise AssertionError("the line did not go quiet")


@pytest.fixture()
def pty_pair():
    master, path = open_pty_pair()
    yield master, path
    os.close(master)


# ---- Xsens MTi-630 ----

ANGLES = {"roll": 0.05, "pitch": -0.03, "yaw": 0.2}  # rad, the platform's true attitude


@pytest.fixture()
def ahrs(pty_pair):
    master, path = pty_pair
    emu = XsensEmulator(master, np.random.default_rng(5)).start()
    tick = Ticker(lambda t: emu.emit(t, ANGLES["roll"], ANGLES["pitch"], ANGLES["yaw"]))
    drv = XsensMti(XsensConfig(path, rate_hz=50))
    drv.open()
    yield emu, drv, tick
    drv.close()
    tick.stop()
    emu.close()


def test_xsens_configuration_and_streaming(ahrs):
    emu, drv, _ = ahrs
    assert drv.device_id == 0x06302A17
    assert emu.measuring
    assert emu.config == [(XDI.PACKET_COUNTER, 0xFFFF), (XDI.SAMPLE_TIME_FINE, 0xFFFF), (XDI.EULER_ANGLES, 50)]
    first = drv.wait_for(0, 2.0)
    r = drv.wait_for(first.seq + 10, 2.0)
    assert r.seq >= first.seq + 10
    assert abs(r.roll - 0.05) < math.radians(0.2) and abs(r.pitch + 0.03) < math.radians(0.2)
    assert abs(r.yaw) < math.radians(1.0)  # yaw is 0 at start-up
    assert r.packet_counter == r.seq & 0xFFFF
    # 50 Hz output on a 100 Hz tick: SampleTimeFine advances 200 ticks of 0.1 ms per packet
    samples = []
    for _ in range(5):
        samples.append(drv.wait_for(drv.latest().seq + 1, 2.0))
    stf = np.diff([s.sample_time_fine for s in samples]) / np.diff([s.seq for s in samples])
    assert np.all(stf == 200)
    assert drv.stats.sequence_gaps == 0 and drv.stats.checksum_errors == 0
    ANGLES["yaw"] = 0.3
    try:
        later = drv.wait_for(drv.latest().seq + 3, 2.0)
        assert abs(later.yaw - 0.1) < math.radians(1.0)
    finally:
        ANGLES["yaw"] = 0.2
    assert drv.fault() is None
    assert "Xsens MTi 06302A17" in drv.status()


def test_xsens_error_messages_are_surfaced_and_recovered(ahrs):
    emu, drv, _ = ahrs
    seq = drv.wait_for(0, 2.0).seq
    cfg = xbus.encode_output_configuration([(XDI.EULER_ANGLES, 100)])
    with pytest.raises(DeviceError, match=r"answered SET_OUTPUT_CONFIGURATION with Error 0x04 \(invalid message\)"):
        drv.request(MID.SET_OUTPUT_CONFIGURATION, cfg, MID.OUTPUT_CONFIGURATION)  # not in measurement mode
    drv.request(MID.GO_TO_CONFIG, b"", MID.GO_TO_CONFIG_ACK)
    bad = xbus.encode_output_configuration([(XDI.EULER_ANGLES, 7)])  # 7 Hz does not divide 400 Hz
    with pytest.raises(DeviceError, match=r"Error 0x21 \(invalid parameter\)"):
        drv.request(MID.SET_OUTPUT_CONFIGURATION, bad, MID.OUTPUT_CONFIGURATION)
    assert "Error 0x21 (invalid parameter)" in drv.fault()
    assert emu.config[-1] == (XDI.EULER_ANGLES, 50)  # the device kept its configuration
    # recovery: back to measurement, the stream resumes
    drv.request(MID.GO_TO_MEASUREMENT, b"", MID.GO_TO_MEASUREMENT_ACK)
    assert drv.wait_for(seq + 3, 2.0).seq >= seq + 3
    drv.clear_errors()
    assert drv.fault() is None


def test_xsens_corrupted_bytes_fault_and_recovery(ahrs):
    emu, drv, _ = ahrs
    before = drv.wait_for(0, 2.0).seq
    emu.corrupt(60)
    after = drv.wait_for(before + 30, 3.0)
    s = drv.stats
    assert s.checksum_errors + s.bytes_discarded > 0
    assert s.sequence_gaps >= 1  # the damaged packets are missing from the counter sequence
    assert abs(after.roll - 0.05) < math.radians(0.2)  # what comes through is right


def test_xsens_silent_device_detected_within_three_periods(ahrs):
    emu, drv, tick = ahrs
    drv.wait_for(3, 2.0)
    emu.disconnect()
    last = quiesce(drv)
    period = 1 / 50
    assert drv.staleness(now=last.t + 2.9 * period) is None
    msg = drv.staleness(now=last.t + 3.05 * period)
    assert msg.startswith(f"Xsens MTi on {drv.config.port} silent for 0.061 s")
    with pytest.raises(DeviceError, match="no sample with packet counter"):
        drv.wait_for(last.seq + 1, 0.2)
    assert "silent" in drv.fault()
    emu.reconnect()
    r = drv.wait_for(last.seq + 1, 2.0)
    assert drv.staleness(now=r.t) is None
    assert drv.stats.sequence_gaps == 0  # the MTi does not count packets it did not send


def test_xsens_extended_length_frame_and_unknown_items(pty_pair):
    master, path = pty_pair
    emu = XsensEmulator(master, np.random.default_rng(1)).start()  # answers the configuration only
    drv = XsensMti(XsensConfig(path, rate_hz=100))
    try:
        drv.open()
        payload = (bytes([0x10, 0x20, 0x02, 0x00, 0x2A])  # PacketCounter 42
                   + bytes([0x10, 0x60, 0x04, 0x00, 0x00, 0x27, 0x10])  # SampleTimeFine 10000
                   + bytes([0x99, 0x90, 0xFA]) + bytes(range(250))  # an item we do not know, 250 bytes
                   + bytes([0x20, 0x30, 0x0C]) + struct.pack(">3f", 10.0, -5.0, 45.0))
        assert len(payload) == 280
        head = bytes([0xFA, 0xFF, 0x36, 0xFF, 0x01, 0x18])
        frame = head + payload + bytes([(-sum(head[1:] + payload)) & 0xFF])
        os.write(master, b"\x00\xfa\x12" + frame)
        r = drv.wait_for(42, 2.0)
        assert r.packet_counter == 42 and r.sample_time_fine == 10000
        assert (math.degrees(r.roll), math.degrees(r.pitch), math.degrees(r.yaw)) == pytest.approx((10, -5, 45))
    finally:
        drv.close()
        emu.close()


def test_xsens_open_fails_clearly_without_a_device(pty_pair):
    _, path = pty_pair
    drv = XsensMti(XsensConfig(path, ack_timeout=0.1, retries=2))
    with pytest.raises(DeviceError, match=f"Xsens MTi on {path} did not acknowledge GO_TO_CONFIG within 0.1 s"):
        drv.open()
    with pytest.raises(DeviceError, match="cannot open serial port /nonexistent/tty"):
        XsensMti(XsensConfig("/nonexistent/tty")).open()
    # 32-byte frames at 400 Hz are 128000 bit/s: more than 115200 baud carry, fine at 230400
    with pytest.raises(ValueError, match="400 Hz needs 128000 bit/s, more than 115200 baud"):
        XsensMti(XsensConfig(path, rate_hz=400))
    with pytest.raises(ValueError, match="not a divisor of 400 Hz"):
        XsensMti(XsensConfig(path, rate_hz=30))
    XsensMti(XsensConfig(path, baud=230400, rate_hz=400))


def test_xsens_emulator_same_seed_same_bytes(pty_pair):
    master, path = pty_pair
    port = serial.Serial(path, timeout=0.2)
    try:
        streams = []
        for _ in range(2):
            emu = XsensEmulator(master, np.random.default_rng(9), mounting_roll=0.01)
            for k in range(10):
                emu.emit(k * DT, 0.1, 0.05, -0.4)
            streams.append(port.read(10 * 36))  # FA FF 36 1F, PacketCounter 5 + SampleTimeFine 7 + Quaternion 19, CS
        assert len(streams[0]) == 360 and streams[0] == streams[1]
        msgs = xbus.XbusDecoder().feed(streams[0])
        assert [xbus.decode_sample(m.payload).packet_counter for m in msgs] == list(range(10))
    finally:
        port.close()


def test_xsens_emulator_accuracy_and_mounting_tilt(pty_pair):
    master, _ = pty_pair
    true = np.array([0.08, -0.07, 0.4])
    emu = XsensEmulator(master, np.random.default_rng(2), mounting_roll=0.02, mounting_pitch=-0.01)
    m = np.array([emu.measured_angles(k * DT, *true) for k in range(3000)])
    sensor = rotation_to_euler(rotation(true)[0] @ rotation(np.array([0.02, -0.01, 0.0]))[0])[0]
    err = m[:, :2] - sensor[:2]
    assert np.all(np.abs(err) < math.radians(0.2))  # roll/pitch accuracy
    assert np.all(np.abs(err.mean(0)) <= math.radians(0.1) + 1e-4)  # the per-device bias bound
    assert abs(m[0, 2]) < math.radians(0.5)  # yaw 0 at start-up (noise only)
    assert np.all(np.abs(m[:, 2]) < math.radians(1.0))  # within 1 deg over 30 s of drift and noise
    assert np.std(m[:, 2]) > math.radians(0.05)  # and it is noisy, not constant


def test_xsens_emulator_answers_any_host_message_with_one_valid_frame(pty_pair):
    master, _ = pty_pair
    emu = XsensEmulator(master, np.random.default_rng(0))
    answers = {MID.GO_TO_CONFIG_ACK, MID.GO_TO_MEASUREMENT_ACK, MID.DEVICE_ID, MID.PRODUCT_CODE, MID.ERROR,
               MID.OUTPUT_CONFIGURATION, MID.RESET_ACK}

    @settings(max_examples=300, deadline=None)
    @given(st.integers(0, 255), st.binary(max_size=64))
    def check(mid, payload):
        reply = emu.handle(xbus.Message(mid, payload))
        if reply:
            msgs, used = xbus.split_frames(reply)
            assert used == len(reply) and len(msgs) == 1 and msgs[0].mid in answers
        if mid == MID.SET_OUTPUT_CONFIGURATION and reply and msgs[0].mid == MID.OUTPUT_CONFIGURATION and payload:
            assert xbus.decode_output_configuration(msgs[0].payload) == emu.config

    check()
    assert emu.handle(xbus.Message(MID.GO_TO_CONFIG)) == bytes.fromhex("FA FF 31 00 D0")
    assert emu.handle(xbus.Message(0x7A)) == bytes.fromhex("FA FF 42 01 04 BA")  # FF+42+01+04 = 0x146


# ---- load-cell amplifier ----

TRUE_TAU = np.array([50.0, 30.0, 55.0, 80.0])
OFFSETS = np.array([4.0, -2.0, 0.5, 0.0])
GAINS = np.array([1.0, 1.03, 1.0, 0.98])


@pytest.fixture()
def cells(pty_pair):
    master, path = pty_pair
    emu = LoadCellEmulator(master, np.random.default_rng(8), offsets=OFFSETS, gains=GAINS).start()
    tick = Ticker(lambda t: emu.emit(t, TRUE_TAU))
    drv = LoadCellDriver(LoadCellConfig(path, rate_hz=100.0, stuck_samples=20))
    drv.open()
    yield emu, drv, tick
    drv.close()
    tick.stop()
    emu.close()


def test_loadcell_configuration_and_streaming(cells):
    emu, drv, _ = cells
    assert (drv.info.model, drv.info.channels, drv.info.full_scale) == ("LC4-SIM", 4, 981.0)
    first = drv.wait_for(0, 2.0)
    rs = [drv.wait_for(first.device_seq + k, 2.0) for k in range(1, 30)]
    seqs = [r.device_seq for r in rs]
    assert seqs == sorted(seqs) and seqs[-1] >= first.device_seq + 29
    tau = np.array([r.tau for r in rs])
    expected = GAINS * TRUE_TAU + OFFSETS
    assert np.all(np.abs(tau.mean(0) - expected) < 0.2 + 0.1)  # accuracy class + noise of a 29-sample mean
    assert drv.stats.sequence_gaps == 0 and drv.stats.checksum_errors == 0
    assert drv.fault() is None
    assert "LC4-SIM" in drv.status()


def test_loadcell_stuck_and_disconnected_cells_then_recovery(cells):
    emu, drv, _ = cells
    drv.wait_for(0, 2.0)
    emu.stick(1)
    emu.disconnect(2)
    r = drv.wait_for(emu.seq + 25, 3.0)  # counted on the amplifier: the driver may lag behind it
    assert math.isnan(r.tau[2]) and not math.isnan(r.tau[1])
    faults = drv.channel_faults()
    assert any(f.startswith("load cell 2 ") and "stuck at" in f for f in faults)
    assert any(f.startswith("load cell 3 ") and "disconnected" in f for f in faults)
    assert not any(f.startswith("load cell 1 ") or f.startswith("load cell 4 ") for f in faults)
    emu.unstick(1)
    emu.reconnect(2)
    r = drv.wait_for(emu.seq + 3, 3.0)
    assert not np.any(np.isnan(r.tau))
    assert drv.channel_faults() == [] and drv.fault() is None


def test_loadcell_silent_amplifier_gap_and_corruption(cells):
    emu, drv, tick = cells
    drv.wait_for(2, 2.0)
    emu.disconnect()
    last = quiesce(drv)
    frames = drv.stats.frames
    assert drv.staleness(now=last.t + 2.9 / 100) is None
    assert drv.staleness(now=last.t + 3.05 / 100).startswith(f"load-cell amplifier on {drv.config.port} silent")
    with pytest.raises(DeviceError, match="no sample with sequence"):
        drv.wait_for(last.device_seq + 1, 0.2)
    emu.reconnect()
    drv.wait_for(last.device_seq + 1, 2.0)
    tick.running.clear()
    quiesce(drv)
    # every sequence number after the last line before the silence was either received or counted missing
    received = drv.stats.frames - frames
    gaps = drv.stats.sequence_gaps
    assert gaps > 0 and drv.latest().device_seq - last.device_seq == gaps + received
    tick.running.set()
    drv.wait_for(0, 2.0)
    emu.corrupt(5)  # five bytes of the next line
    r2 = drv.wait_for(emu.seq + 5, 3.0)
    assert drv.stats.sequence_gaps == gaps + 1  # the damaged line is dropped, not misread
    assert drv.stats.checksum_errors + drv.stats.bytes_discarded > 0
    assert not np.any(np.isnan(r2.tau)) and drv.staleness(now=r2.t) is None


def test_loadcell_wrong_channel_count_and_no_answer(pty_pair):
    master, path = pty_pair
    with pytest.raises(DeviceError, match=f"load-cell amplifier on {path} did not answer INFO within 0.2 s"):
        LoadCellDriver(LoadCellConfig(path, info_timeout=0.2)).open()
    emu = LoadCellEmulator(master, np.random.default_rng(0)).start()
    try:
        with pytest.raises(DeviceError, match="has 4 channels, the configuration expects 3"):
            LoadCellDriver(LoadCellConfig(path, channels=3)).open()
    finally:
        emu.close()


def test_emulator_rotations_in_plain_floats_match_the_models():
    """The emulated MTi composes its rotations in plain floats (speed); they are the model's, both ways."""
    from sim_backend.xsens_emulator import _euler, _matmul, _rotation

    rng = np.random.default_rng(4)
    for conv in ("xyz", "zyx"):
        for ang in rng.uniform(-0.6, 0.6, (20, 3)):
            R = rotation(ang[None], conv)[0]
            np.testing.assert_allclose(_rotation(*ang, conv), R, atol=1e-15)
            M = rotation(rng.uniform(-0.1, 0.1, (1, 3)), "xyz")[0]
            for out in ("xyz", "zyx"):
                np.testing.assert_allclose(_euler(_matmul(R.tolist(), M.tolist()), out),
                                           rotation_to_euler(R @ M, out)[0], atol=1e-12)
