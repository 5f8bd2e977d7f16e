"""The CiA 402 winch-drive driver against the emulated drive over python-can's virtual bus.

A small real plant (motor inertia on a torsion spring with viscous damping and a constant load torque,
integrated semi-implicitly) stands in for the simulator's physics; :class:`CanRig` runs the lockstep the
simulator backend runs (for each SYNC: apply the RPDO targets, step the physics, transmit the TPDOs).
"""

from __future__ import annotations

import itertools
import math
import threading

import can
import canopen
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers import cia402
from drivers.can_bus import SyncProducer, open_network
from drivers.canopen_drive import CanopenWinchDrive
from drivers.canopen_node import wrap_delta
from drivers.cia402 import MODE_CSV, state_of
from drivers.interfaces import DeviceError
from sim_backend.can_drive_emulator import CanDriveEmulator
from sim_backend.can_encoder_emulator import CanEncoderEmulator

DT = 0.005  # s, control period
LPR = -0.028807  # m of cable per motor revolution (IRMA4U winch 1)
CPR = 1 << 20
_channels = itertools.count()


class WinchPlant:
    """n motors, each J th'' = tau - k th - c th' - load, with a holding brake (engaged: shaft locked);
    swivel angle = sigma0 + ratio * th (rad)."""

    def __init__(self, n: int, J: float = 2e-4, k: float = 2.0, c: float = 0.02, load: float = 0.0,
                 sigma0: float = 0.3, ratio: float = 0.5, substeps: int = 10):
        self.n = n
        self.J, self.k, self.c, self.load = J, k, c, load
        self.sigma0, self.ratio, self.substeps = sigma0, ratio, substeps
        self.th = np.zeros(n)
        self.om = np.zeros(n)
        self.tau = np.zeros(n)
        self.brake = np.ones(n, bool)  # engaged at power-on
        self._time = 0.0

    @property
    def time(self) -> float:
        return self._time

    def step(self, dt: float) -> None:
        h = dt / self.substeps
        for _ in range(self.substeps):
            acc = (self.tau - self.k * self.th - self.c * self.om - self.load) / self.J
            self.om = np.where(self.brake, 0.0, self.om + h * acc)
            self.th = self.th + h * self.om
        self._time += dt

    def motor_position(self) -> np.ndarray:
        return self.th.copy()

    def motor_velocity(self) -> np.ndarray:
        return self.om.copy()

    def motor_torque(self) -> np.ndarray:
        return self.tau.copy()

    def set_motor_torque(self, i: int, torque: float) -> None:
        self.tau[i] = torque

    def set_brake(self, i: int, engaged: bool) -> None:
        self.brake[i] = engaged
        if engaged:
            self.om[i] = 0.0

    def cable_tension(self) -> np.ndarray:
        return np.zeros(self.n)

    def swivel_angle(self) -> np.ndarray:
        return self.sigma0 + self.ratio * self.th

    def orientation(self) -> np.ndarray:
        return np.zeros(3)


class CanRig:
    """Master and emulated nodes on one virtual channel, stepped in lockstep by SYNC."""

    def __init__(self, n_drives: int = 1, n_encoders: int = 0, plant: WinchPlant | None = None, **plant_kw):
        self.channel = channel = f"cdpr-test-{next(_channels)}-{id(self)}"
        self.plant = plant or WinchPlant(max(n_drives, n_encoders, 1), **plant_kw)
        self.slave = open_network(can.Bus(interface="virtual", channel=channel))
        self.master = open_network(can.Bus(interface="virtual", channel=channel))
        self.drives = [CanDriveEmulator(self.slave, 1 + i, self.plant, i, control_period=DT)
                       for i in range(n_drives)]
        self.encoders = [CanEncoderEmulator(self.slave, 11 + i, self.plant, i) for i in range(n_encoders)]
        self.sync_counts: list[int] = []
        self._stepped = threading.Condition()
        self.slave.subscribe(0x80, self._on_sync)
        self.sync = SyncProducer(self.master)
        self.drivers: list = []

    def clock(self) -> float:
        return self.plant.time

    def _on_sync(self, can_id, data, timestamp) -> None:
        for d in self.drives:
            d.apply_targets()
        self.plant.step(DT)
        count = data[0] if data else -1
        for node in self.drives + self.encoders:
            node.on_sync(count, data[0] if data else 0)
        with self._stepped:
            self.sync_counts.append(count)
            self._stepped.notify_all()

    def tick(self, wait: bool = True) -> int:
        """One SYNC; wait for every driver's reading of it, or (wait=False) only for the emulated side."""
        count = self.sync.send_sync()
        if wait:
            for drv in self.drivers:
                drv.wait_for_sync(count, 2.0)
        else:
            with self._stepped:
                assert self._stepped.wait_for(lambda: len(self.sync_counts) >= count, 2.0)
        return count

    def ticks(self, n: int) -> None:
        for _ in range(n):
            self.tick()

    def winch(self, i: int = 0, **kw) -> CanopenWinchDrive:
        drv = CanopenWinchDrive(self.master, 1 + i, self.sync, LPR, clock=self.clock, **kw)
        drv.open()
        self.drivers.append(drv)
        return drv

    def close(self) -> None:
        for drv in self.drivers:
            drv.close()
        self.master.disconnect()
        self.slave.disconnect()


@pytest.fixture
def rig():
    r = CanRig(n_drives=1)
    yield r
    r.close()


def test_the_state_machine_is_one_table_for_the_driver_and_the_emulated_drive():
    """Every state's statusword (with the remote and follows-command bits the drive sets) reads back as that state;
    the driver's enable and stop sequences walk the transitions the emulated drive applies."""
    for state, bits in cia402.STATUSWORD_BITS.items():
        assert state_of(bits | cia402.SW_REMOTE | cia402.SW_FOLLOWS_COMMAND) == state
    assert state_of(0x0001).startswith("unknown")
    s = cia402.SWITCH_ON_DISABLED
    path = []
    for cw in (cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON, cia402.CW_ENABLE):
        s = cia402.next_state(s, cw)
        path.append(s)
    assert path == [cia402.READY_TO_SWITCH_ON, cia402.SWITCHED_ON, cia402.OPERATION_ENABLED]
    enabled = cia402.OPERATION_ENABLED
    assert cia402.next_state(enabled, cia402.CW_QUICK_STOP) == cia402.QUICK_STOP_ACTIVE
    assert cia402.next_state(enabled, cia402.CW_QUICK_STOP, quick_stop_option=0) == cia402.SWITCH_ON_DISABLED
    qs = cia402.QUICK_STOP_ACTIVE
    assert cia402.next_state(qs, cia402.CW_ENABLE, quick_stop_option=2) == qs  # option 2 ends in a stop
    assert cia402.next_state(qs, cia402.CW_ENABLE, quick_stop_option=6) == enabled  # transition 16
    assert cia402.next_state(enabled, cia402.CW_DISABLE_VOLTAGE) == cia402.SWITCH_ON_DISABLED
    assert cia402.next_state(cia402.FAULT, cia402.CW_FAULT_RESET) == cia402.FAULT  # no rising edge
    assert cia402.next_state(cia402.FAULT, cia402.CW_FAULT_RESET, reset_edge=True) == cia402.SWITCH_ON_DISABLED
    assert cia402.next_state(cia402.SWITCH_ON_DISABLED, cia402.CW_ENABLE) == cia402.SWITCH_ON_DISABLED


def test_statusword_decoding_and_counter_wrap():
    assert state_of(0x0250) == "switch on disabled"
    assert state_of(0x0231) == "ready to switch on"
    assert state_of(0x0233) == "switched on"
    assert state_of(0x1237) == "operation enabled"
    assert state_of(0x0217) == "quick stop active"
    assert state_of(0x0208) == "fault"
    assert wrap_delta(5, 0xFFFFFFFB, 32) == 10
    assert wrap_delta(0x7FFFFFFF, -0x80000000 & 0xFFFFFFFF, 32) == -1
    assert wrap_delta(10, 65530, 16) == 16


@given(bits=st.sampled_from([16, 32]), start=st.integers(0, 2**32 - 1), steps=st.lists(st.integers(-30000, 30000),
       max_size=50))
def test_unwrapping_recovers_the_motion_from_wrapped_counters(bits, start, steps):
    """Any motion whose steps stay under half the counter range is recovered exactly from the wrapped counter."""
    mod = 1 << bits
    true, raw, unwrapped = start % mod, start % mod, start % mod
    for d in steps:
        true += d
        new_raw = true % mod
        unwrapped += wrap_delta(new_raw, raw, bits)
        raw = new_raw
    assert unwrapped == true


def test_configuration_by_sdo(rig):
    emu = rig.drives[0]
    assert emu.nmt_state == "PRE-OPERATIONAL"
    drv = rig.winch()
    rig.tick()  # the NMT start frame precedes this SYNC on the bus
    # the mapping the driver wrote by SDO is what the emulated node now transmits
    assert emu.nmt_state == "OPERATIONAL"
    # position, torque and statusword in one frame at every SYNC; the velocity every 20th SYNC
    assert emu.tpdo_layout == [(0x181, "<ihH"), (0x281, "<i")]
    assert [emu.node.tpdo[k].trans_type for k in (1, 2)] == [1, 20]
    assert emu.rpdo_layout == [(0x201, [0x6040, 0x6071, 0x60FF])]
    assert emu.heartbeat_period == pytest.approx(0.1)
    assert emu.mode == 10
    assert drv.rated_torque == pytest.approx(0.64)
    assert drv.max_torque == pytest.approx(1.92)
    assert drv.state() == "switch on disabled"
    assert "CAN node 1" in drv.status()


def test_streaming_torque_control_and_counts(rig):
    drv = rig.winch()
    drv.enable()
    assert drv.state() == "operation enabled"
    torque = 0.5  # N m against a 2 N m/rad spring: settles at 0.25 rad
    drv.set_torque(torque)
    readings = []
    for _ in range(400):
        c = rig.tick()
        r = drv.latest()
        assert r.sync_count == c
        readings.append(r)
    seqs = [r.seq for r in readings]
    assert seqs == list(range(seqs[0], seqs[0] + 400))
    last = readings[-1]
    th = rig.plant.th[0]
    assert abs(last.position_counts - th * CPR / (2 * math.pi)) <= 0.5 + 1e-9
    assert last.position_counts / CPR * 2 * math.pi == pytest.approx(torque / 2.0, abs=2e-3)
    assert last.delta_length == pytest.approx(last.position_counts / CPR * LPR)
    assert last.delta_length == pytest.approx(0.25 / (2 * math.pi) * LPR, rel=0.01)
    # torque per mille of 0.64 N m: 781 -> 0.49984 N m
    assert last.torque == pytest.approx(round(torque / 0.64 * 1000) / 1000 * 0.64)
    assert rig.plant.tau[0] == pytest.approx(last.torque)
    assert state_of(last.statusword) == "operation enabled"
    assert drv.enabled and drv.fault() is None
    # timestamps come from the simulated clock: one control period apart
    assert np.allclose(np.diff([r.t for r in readings]), DT)
    # saturation at the max torque 0x6072 (3000 per mille of 0.64 N m)
    drv.set_torque(10.0)
    rig.ticks(2)
    assert rig.plant.tau[0] == pytest.approx(1.92)


def test_drive_fault_detected_within_three_sync_periods_and_recovery(rig):
    drv = rig.winch()
    drv.set_torque(0.4)
    drv.enable()
    rig.ticks(50)
    assert drv.fault() is None
    rig.drives[0].schedule_fault(rig.plant.time + 0.5 * DT, code=0x2310)
    t_fault = rig.plant.time
    periods = 0
    while drv.fault() is None:
        rig.tick()
        periods += 1
        assert periods <= 3, "drive fault not detected within 3 SYNC periods"
    assert "0x2310" in drv.fault()
    assert rig.plant.time - t_fault <= 3 * DT
    assert not drv.enabled
    rig.ticks(3)
    assert rig.plant.tau[0] == 0.0  # torque off until fault reset
    assert drv.latest().statusword & 0x08
    assert drv.state() == "fault"
    # recovery: fault reset, then the state machine up to operation enabled again
    drv.enable()
    rig.ticks(3)
    assert drv.fault() is None and drv.enabled
    assert rig.plant.tau[0] == pytest.approx(round(0.4 / 0.64 * 1000) / 1000 * 0.64)


def test_fault_seen_in_the_statusword_when_the_emcy_is_lost(rig):
    drv = rig.winch()
    drv.set_torque(0.2)
    drv.enable()
    rig.ticks(5)
    rig.drives[0].lose_frames(1.0, kinds=("emcy",))
    rig.drives[0].trigger_fault(0x8611)
    rig.tick()
    assert drv.emcy_faults == []
    assert "fault in its statusword 0x0208" in drv.fault()
    assert not drv.enabled


def test_nmt_reset_node_is_reported_and_recovered(rig):
    drv = rig.winch()
    drv.enable()
    rig.ticks(30)
    drv.node.nmt.state = "RESET"
    for _ in range(int(0.2 / DT)):
        rig.tick(wait=False)  # no PDOs while pre-operational
    assert "left the operational state" in drv.fault()
    assert rig.drives[0].state == "switch on disabled"
    drv.close()
    rig.drivers.remove(drv)
    drv = rig.winch()  # configure again after the reset
    drv.enable()
    rig.ticks(int(0.2 / DT))
    assert drv.fault() is None and drv.enabled


def test_lost_heartbeat_detected_within_three_periods(rig):
    drv = rig.winch()
    period = drv.heartbeat_period
    rig.ticks(int(1.0 / DT))  # 1 s of healthy traffic: no false alarm
    assert drv.heartbeat.count >= 9
    assert drv.fault() is None
    last_hb = drv.heartbeat.last
    rig.drives[0].lose_frames(1.0, kinds=("heartbeat",))
    while drv.fault() is None:
        rig.tick()
        assert rig.plant.time - last_hb <= 3 * period + 1e-9, "lost heartbeat not detected within 3 periods"
    assert "heartbeat" in drv.fault()
    # the node's heartbeat comes back: the fault clears
    rig.drives[0].clear_frame_loss()
    rig.ticks(int(2 * period / DT))
    assert drv.fault() is None


def test_frame_loss_leaves_incomplete_syncs(rig):
    drv = rig.winch()
    rig.ticks(5)
    rig.drives[0].lose_frames(1.0, duration=3.5 * DT, kinds=("tpdo",))  # the next 3 SYNCs
    with pytest.raises(DeviceError, match=r"node 1\) sent no PDOs for SYNC"):
        c = rig.sync.send_sync()
        drv.wait_for_sync(c, 0.2)
    rig.tick(wait=False)
    rig.tick(wait=False)
    rig.ticks(3)  # frames flow again
    assert drv.latest().sync_count == rig.sync.count
    assert rig.drives[0].frames_lost == 3  # one TPDO1 per SYNC (no velocity TPDO2 due in SYNCs 7-9)
    assert drv.incomplete == 0 and drv.malformed == 0


def test_velocity_comes_every_nth_sync_and_readings_keep_the_last_one(rig):
    drv = rig.winch(velocity_every=4)
    drv.set_mode(MODE_CSV)
    drv.enable()
    drv.set_velocity(1.0)  # rad/s: the motor speeds up, each velocity frame differs from the one before
    seen = []
    for _ in range(12):
        c = rig.tick()
        seen.append((c, drv.latest().velocity))
    # the velocity TPDO starts at the SYNC with counter 1 (start value) and comes every 4th: SYNCs 1, 5, 9
    assert rig.drives[0].node.tpdo[2].trans_type == 4
    assert not math.isnan(seen[0][1])
    assert [c for (c, v), (_, before) in zip(seen[1:], seen[:-1], strict=True) if v != before] == [5, 9]
    with pytest.raises(ValueError, match="transmission type must be 1..240 SYNCs, got 300"):
        CanopenWinchDrive(rig.master, 2, rig.sync, LPR, velocity_every=300)
    with pytest.raises(ValueError, match="every 7 SYNCs needs a SYNC counter overflow that 7 divides, not 240"):
        CanopenWinchDrive(rig.master, 2, rig.sync, LPR, every=7)
    # without a SYNC counter nobody can tell which SYNC carries a 1-in-n TPDO: the velocity then comes at each
    assert CanopenWinchDrive(rig.master, 2, SyncProducer(rig.master, overflow=0), LPR).velocity_every == 1
    assert CanopenWinchDrive(rig.master, 2, rig.sync, LPR).velocity_every == 20


def test_feedback_every_nth_sync_from_counter_one(rig):
    rig.ticks(2)  # SYNCs 1, 2 before the drive starts: it waits for the counter to come back to 1
    drv = rig.winch(every=4)
    assert [drv.due(c) for c in (3, 241, 242, 245)] == [False, True, False, True]
    got = []
    for _ in range(250):
        c = rig.tick(wait=False)
        r = drv.latest()
        got.append(None if r is None else r.sync_count)
        if c >= 241:
            assert drv.wait_for_sync(c, 1.0).sync_count == drv.last_due(c) == c - (c - 241) % 4
    assert set(got[:238]) == {None}  # SYNCs 3..240 carry no feedback from it
    assert rig.drives[0].tpdo_layout == [(0x181, "<ihH"), (0x281, "<i")]
    assert drv.incomplete == 0
    with pytest.raises(DeviceError, match=r"every 4 SYNCs from SYNC 241: none is due by SYNC 100"):
        drv.wait_for_sync(100, 0.1)


def test_quick_stop_holds_and_reenable(rig):
    drv = rig.winch(velocity_every=2)
    drv.set_torque(0.6)
    drv.enable()
    rig.ticks(10)  # the motor is accelerating towards 0.3 rad; its velocity came with SYNC 10
    assert abs(drv.latest().velocity) > 0.5
    drv.quick_stop()
    assert drv.state() == "quick stop active"
    held = drv.latest().position_counts
    rig.ticks(100)
    r = drv.latest()
    assert r.velocity == 0.0 and r.torque == 0.0  # the brake holds the shaft
    assert r.position_counts == held  # locked where the quick stop found it
    assert state_of(r.statusword) == "quick stop active"
    drv.enable()
    rig.ticks(400)
    assert drv.latest().position_counts / CPR * 2 * math.pi == pytest.approx(0.3, abs=5e-3)


def test_close_disables_the_drive_and_the_brake_holds(rig):
    drv = rig.winch()
    drv.set_torque(0.3)
    drv.enable()
    rig.ticks(20)
    assert not rig.plant.brake[0]
    drv.close()
    rig.drivers.remove(drv)
    rig.tick(wait=False)
    assert rig.drives[0].state == "switch on disabled"
    assert rig.plant.brake[0] and rig.plant.tau[0] == 0.0
    assert rig.drives[0].nmt_state == "PRE-OPERATIONAL"


def test_cyclic_synchronous_velocity_mode():
    rig = CanRig(n_drives=1, k=0.0)  # no spring: the motor can turn at constant speed
    drv = rig.winch()
    drv.set_mode(MODE_CSV)
    drv.enable()
    drv.set_velocity(2.0)  # rad/s
    rig.ticks(400)
    assert drv.latest().velocity == pytest.approx(2.0, abs=0.02)
    drv.disable()
    assert drv.state() == "switch on disabled"
    rig.close()


def test_missing_node_is_one_clear_error(rig):
    drv = CanopenWinchDrive(rig.master, 7, rig.sync, LPR, name="winch7", clock=rig.clock)
    with pytest.raises(DeviceError, match=r"winch7 \(CAN node 7\): SDO read of 0x1000:00 failed"):
        drv.open()
    assert 7 not in rig.master


def test_wrong_device_type_is_rejected():
    rig = CanRig(n_drives=0, n_encoders=1)
    try:
        drv = CanopenWinchDrive(rig.master, 11, rig.sync, LPR, clock=rig.clock)
        with pytest.raises(DeviceError, match="not a CiA 402 device"):
            drv.open()
    finally:
        rig.close()


def test_lost_bus_is_a_device_error(rig):
    drv = rig.winch()
    drv.enable()
    rig.master.disconnect()
    with pytest.raises(DeviceError, match=r"winch drive 1 \(CAN node 1\): sending RPDO1 failed"):
        drv.set_torque(0.1)
    with pytest.raises(DeviceError, match="sending SYNC 1 failed"):
        rig.sync.send_sync()
    drv.close()  # safe on a lost bus
    assert drv.node is None and not drv.operational


def test_a_node_without_sync_start_value_is_one_sentence_naming_the_fallback(rig):
    emu = rig.drives[0]
    written = emu.on_object_written

    def no_start_value(index, subindex, value):  # a drive whose 0x1800:06 does not exist
        if 0x1800 <= index <= 0x1803 and subindex == 6:
            raise canopen.SdoAbortedError(0x06090011)
        written(index, subindex, value)

    emu.on_object_written = no_start_value
    with pytest.raises(DeviceError, match=r"mapping TPDO1 at every 4 SYNCs from SYNC start value 1 \(a node "
                                          r"without 0x1800:06 needs 'can: sync_overflow: 0' in the device file"):
        rig.winch(every=4)
    drv = rig.winch(velocity_every=1)  # every SYNC needs no start value
    rig.ticks(3)
    assert drv.latest().sync_count == 3
