"""The CiA 406 swivel-encoder driver against the emulated encoder over python-can's virtual bus."""

from __future__ import annotations

import math

import pytest
from test_canopen_drive import DT, LPR, CanRig

from drivers.canopen_drive import CanopenWinchDrive
from drivers.interfaces import DeviceError
from drivers.swivel_encoder import CanopenSwivelEncoder

CPR = 65536


def open_encoder(rig: CanRig, i: int = 0, **kw) -> CanopenSwivelEncoder:
    enc = CanopenSwivelEncoder(rig.master, 11 + i, rig.sync, clock=rig.clock, **kw)
    enc.open()
    rig.drivers.append(enc)
    return enc


@pytest.fixture
def rig():
    # one winch driving the plant, one encoder whose swivel angle follows the motor angle (ratio 0.5)
    r = CanRig(n_drives=1, n_encoders=1, k=0.0, c=0.02)
    yield r
    r.close()


def test_configuration_and_streaming(rig):
    enc = open_encoder(rig)
    rig.tick()
    emu = rig.encoders[0]
    assert emu.nmt_state == "OPERATIONAL"
    assert emu.tpdo_layout == [(0x18B, "<I")]
    assert emu.heartbeat_period == pytest.approx(0.1)
    r = enc.latest()
    assert r.counts == 0 and r.delta_angle == 0.0  # reads 0 at power-on
    assert r.sync_count == rig.sync.count
    assert enc.fault() is None
    assert "CAN node 11" in enc.status()


def test_counts_to_radians_and_wrap_around(rig):
    """The swivel turns backwards through 0 (counts wrap to 65535...) and then forwards over more than a
    full turn: the unwrapped angle follows the plant within one count all the way."""
    winch = CanopenWinchDrive(rig.master, 1, rig.sync, LPR, clock=rig.clock)
    winch.open()
    rig.drivers.append(winch)
    enc = open_encoder(rig)
    winch.set_mode(9)
    winch.enable()
    sigma0 = rig.plant.swivel_angle()[0]
    seen_wrap = False
    errors = []
    for v in (-6.0, 20.0):  # motor rad/s; swivel = half of it
        winch.set_velocity(v)
        for _ in range(300):
            rig.tick()
            r = enc.latest()
            true = rig.plant.swivel_angle()[0] - sigma0
            errors.append(abs(r.delta_angle - true))
            assert 0 <= r.counts < CPR
            if r.counts > CPR // 2 and r.delta_angle < 0:
                seen_wrap = True
    assert seen_wrap
    assert max(errors) <= 0.5 * 2 * math.pi / CPR + 1e-12
    final = enc.latest().delta_angle
    assert final > 2 * math.pi  # more than one turn, unwrapped
    assert enc.latest().counts == round(final * CPR / (2 * math.pi)) % CPR


def test_preset_by_sdo(rig):
    enc = open_encoder(rig)
    enc.sdo_write(0x6003, 1000)
    rig.tick()
    assert enc.latest().counts == 1000
    assert enc.sdo_read(0x6004) == 1000


def test_dropped_frames_and_heartbeat_then_recovery(rig):
    enc = open_encoder(rig)
    rig.ticks(100)
    assert enc.fault() is None
    last_hb = enc.heartbeat.last
    rig.encoders[0].lose_frames(1.0)  # the node goes silent
    with pytest.raises(DeviceError, match=r"swivel encoder 11 \(CAN node 11\) sent no PDOs"):
        enc.wait_for_sync(rig.sync.send_sync(), 0.1)
    while enc.fault() is None:
        rig.tick(wait=False)
        assert rig.plant.time - last_hb <= 3 * 0.1 + 1e-9
    assert "lost its heartbeat" in enc.fault()
    rig.encoders[0].clear_frame_loss()
    rig.ticks(int(0.25 / DT))
    assert enc.fault() is None
    assert enc.latest().sync_count == rig.sync.count


def test_wrong_resolution_is_rejected(rig):
    rig.encoders[0].node.sdo[0x6001].raw = 4096  # an encoder configured for 12 bits
    enc = CanopenSwivelEncoder(rig.master, 11, rig.sync, name="swivel1", clock=rig.clock)
    with pytest.raises(DeviceError, match=r"swivel1 \(CAN node 11\) reports 4096 counts per revolution"):
        enc.open()
