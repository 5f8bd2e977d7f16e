"""`cdpr devices read`: against the simulated devices, and against an MTi-630 played byte by byte from the
Xbus protocol definition by a responder that shares no code with ours (no PyPI package implements Xbus
correctly: the one candidate, mti8-navigation 1.0.0, checks an XOR instead of the Xbus sum and needs Qt)."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from sim_backend.loadcell_emulator import LoadCellEmulator
from sim_backend.pty import open_pty_pair
from sim_backend.xsens_emulator import XsensEmulator


def cdpr(*args: str) -> subprocess.CompletedProcess:
    """Run the console script in its own process, as an operator does."""
    exe = shutil.which("cdpr")
    head = [exe] if exe else [sys.executable, "-c", "import sys; from acquisition.cli import main; "
                                                    "sys.exit(main(sys.argv[1:]))"]
    return subprocess.run([*head, *args], capture_output=True, text=True, timeout=60)


@pytest.fixture()
def pty_pair():
    master, path = open_pty_pair()
    yield master, path
    os.close(master)


def _tick_in_background(step, stop: threading.Event, dt: float = 0.01) -> threading.Thread:
    def run():
        k = 0
        while not stop.is_set():
            step(k * dt)
            k += 1
            time.sleep(dt / 2)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def test_read_loadcells_json(pty_pair):
    master, path = pty_pair
    emu = LoadCellEmulator(master, np.random.default_rng(4), offsets=[1.0, 0.0, 0.0, -1.0]).start()
    stop = threading.Event()
    th = _tick_in_background(lambda t: emu.emit(t, np.array([40.0, 35.0, 60.0, 75.0])), stop)
    try:
        proc = cdpr("devices", "read", "loadcells", "--port", path, "--count", "5", "--json")
    finally:
        stop.set()
        th.join()
        emu.close()
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    out = proc.stdout.splitlines()
    assert len(out) == 5
    rows = [json.loads(line) for line in out]
    assert all(set(r) >= {"t", "tau"} for r in rows)
    assert np.allclose([r["tau"] for r in rows], [41.0, 35.0, 60.0, 74.0], atol=0.7)
    assert all(b["t"] > a["t"] for a, b in zip(rows, rows[1:], strict=False))
    assert [r["seq"] for r in rows] == sorted({r["seq"] for r in rows})


def test_read_ahrs_text(pty_pair):
    master, path = pty_pair
    emu = XsensEmulator(master, np.random.default_rng(4)).start()
    stop = threading.Event()
    th = _tick_in_background(lambda t: emu.emit(t, 0.1, -0.05, 1.0), stop)
    try:
        proc = cdpr("devices", "read", "ahrs", "--port", path, "--count", "3", "--rate", "50")
    finally:
        stop.set()
        th.join()
        emu.close()
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) == 3
    for line in lines:  # 0.1 rad = 5.730 deg, -0.05 rad = -2.865 deg, within the 0.2 deg accuracy
        fields = dict(f.split("=") for f in line.split("  ") if "=" in f)
        assert abs(float(fields["roll"].split()[0]) - 5.730) < 0.2
        assert abs(float(fields["pitch"].split()[0]) + 2.865) < 0.2
    assert "0 bad, 0 missing" in proc.stderr


# ---- an MTi-630 written out by hand ----

GO_TO_CONFIG = bytes.fromhex("FA FF 30 00 D1")
GO_TO_CONFIG_ACK = bytes.fromhex("FA FF 31 00 D0")
REQ_DID = bytes.fromhex("FA FF 00 00 01")
DEVICE_ID = bytes.fromhex("FA FF 01 04 06 30 12 34 80")  # FF+01+04+06+30+12+34 = 0x180 -> 0x80
# SetOutputConfiguration [(PacketCounter, FFFF), (SampleTimeFine, FFFF), (EulerAngles, 100 Hz)] and its ack
SET_OUTPUT = bytes.fromhex("FA FF C0 0C 10 20 FF FF 10 60 FF FF 20 30 00 64 E5")
OUTPUT_CONFIGURATION = bytes.fromhex("FA FF C1 0C 10 20 FF FF 10 60 FF FF 20 30 00 64 E4")
GO_TO_MEASUREMENT = bytes.fromhex("FA FF 10 00 F1")
GO_TO_MEASUREMENT_ACK = bytes.fromhex("FA FF 11 00 F0")


def mtdata2(counter: int) -> bytes:
    """PacketCounter ``counter`` (258..), SampleTimeFine 0x00012345, EulerAngles (1.0, -2.5, 90.0) deg.

    For counter 258 (01 02) the bytes sum to 0x553 from BID on, so CS = 0xAD; each further count adds
    one to the low byte of the counter (kept below 0x100 here) and takes one from CS.
    """
    assert 258 <= counter < 512
    return (bytes.fromhex("FA FF 36 1B 10 20 02 01") + bytes([counter - 256])
            + bytes.fromhex("10 60 04 00 01 23 45 20 30 0C 3F 80 00 00 C0 20 00 00 42 B4 00 00")
            + bytes([(0xAD - (counter - 258)) & 0xFF]))


class HandWrittenMti:
    """Answers the four configuration requests with fixed bytes, then streams MTData2 every 10 ms."""

    def __init__(self, master: int) -> None:
        self.fd = master
        self.stop = threading.Event()
        self.heard = bytearray()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        answers = {GO_TO_CONFIG: GO_TO_CONFIG_ACK, REQ_DID: DEVICE_ID, SET_OUTPUT: OUTPUT_CONFIGURATION,
                   GO_TO_MEASUREMENT: GO_TO_MEASUREMENT_ACK}
        streaming, counter = False, 258
        while not self.stop.is_set():
            try:
                self.heard += os.read(self.fd, 1024)
            except (BlockingIOError, OSError):
                pass
            for request, answer in answers.items():
                at = self.heard.find(request)
                if at >= 0:
                    del self.heard[: at + len(request)]
                    os.write(self.fd, answer)
                    streaming = request == GO_TO_MEASUREMENT
            if streaming and counter < 500:
                os.write(self.fd, mtdata2(counter))
                counter += 1
            time.sleep(0.01)


def test_hand_written_frames_check_out():
    for frame in (GO_TO_CONFIG_ACK, DEVICE_ID, OUTPUT_CONFIGURATION, GO_TO_MEASUREMENT_ACK, mtdata2(258),
                  mtdata2(300)):
        assert sum(frame[1:]) % 256 == 0


def test_cdpr_devices_read_ahrs_from_an_independent_xbus_device(pty_pair):
    master, path = pty_pair
    dev = HandWrittenMti(master)
    try:
        proc = cdpr("devices", "read", "ahrs", "--port", path, "--count", "4", "--json")
    finally:
        dev.stop.set()
        dev.thread.join()
    assert proc.returncode == 0, proc.stderr
    rows = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(rows) == 4
    for r in rows:
        assert (r["roll"], r["pitch"], r["yaw"]) == pytest.approx(
            (math.radians(1.0), math.radians(-2.5), math.radians(90.0)), rel=1e-6)
    # each line is the newest frame after the previous line's (Ahrs.wait_for): consecutive on an idle machine,
    # but a loaded one may deliver two frames between the CLI's waits, and the seq then shows the one skipped
    seqs = [r["seq"] for r in rows]
    assert seqs[0] >= 258 and all(0 < b - a <= 3 for a, b in zip(seqs, seqs[1:], strict=False)), seqs


def test_usage_and_operation_errors(pty_pair):
    _, path = pty_pair
    proc = cdpr("devices", "read", "ahrs", "--port", "/nonexistent/ttyUSB9")
    assert (proc.returncode, proc.stderr) == (2, "cdpr: --port /nonexistent/ttyUSB9: no such serial port.\n")
    proc = cdpr("devices", "read", "ahrs", "--port", path, "--rate", "30")
    assert proc.returncode == 2
    assert proc.stderr == "cdpr: --rate 30 Hz is not an MTi output rate (a divisor of 400 Hz).\n"
    # nobody on the line: a failed operation, exit 1, one sentence
    proc = cdpr("devices", "read", "loadcells", "--port", path)
    assert (proc.returncode, proc.stdout) == (1, "")
    assert proc.stderr == f"cdpr: load-cell amplifier on {path} did not answer INFO within 1 s.\n"
