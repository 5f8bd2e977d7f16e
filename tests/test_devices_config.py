"""The device-set YAML (drivers/config.py) and `cdpr devices check` against emulated CAN nodes."""

from __future__ import annotations

import json

import pytest
import yaml
from test_canopen_drive import CanRig

import acquisition.cli
from acquisition.cli import main
from calib.robot import load_robot
from drivers.config import (
    DeviceConfigError,
    device_config_from_dict,
    dump_device_config,
    eds_path,
    example_config_path,
    load_device_config,
)
from drivers.open import open_devices


def test_example_file_describes_the_irma4u_prototype():
    cfg = load_device_config(example_config_path())
    assert (cfg.can.interface, cfg.can.channel, cfg.can.bitrate) == ("socketcan", "can0", 1_000_000)
    assert [n.node_id for n in cfg.drives] == [1, 2, 3, 4]
    assert [n.node_id for n in cfg.encoders] == [11, 12, 13, 14]
    assert (cfg.loadcells.port, cfg.loadcells.baud) == ("/dev/ttyUSB0", 115200)
    assert (cfg.ahrs.port, cfg.ahrs.baud, cfg.ahrs.rate) == ("/dev/ttyUSB1", 115200, 100.0)
    assert cfg.can.heartbeat_ms == 100
    cfg.check_robot(load_robot("irma4u").n)
    assert eds_path("cia402_winch.eds").is_file() and eds_path("cia406_encoder.eds").is_file()


def test_round_trip(tmp_path):
    cfg = load_device_config(example_config_path())
    path = tmp_path / "devices.yaml"
    dump_device_config(cfg, path)
    again = load_device_config(path)
    assert again.to_dict() == cfg.to_dict()
    assert again.source == str(path)


def _base() -> dict:
    return yaml.safe_load(example_config_path().read_text())


@pytest.mark.parametrize(
    ("edit", "field", "value"),
    [
        (lambda d: d["can"].update(interface="canbus9"), "can.interface", "'canbus9'"),
        (lambda d: d["can"].update(bitrate=300000), "can.bitrate", "300000"),
        (lambda d: d["drives"][2].update(node_id=128), "drives[2].node_id", "128"),
        (lambda d: d["encoders"][0].update(node_id=3), "encoders[0].node_id", "3"),
        (lambda d: d["loadcells"].update(baud="fast"), "loadcells.baud", "'fast'"),
        (lambda d: d["ahrs"].update(rate=-5), "ahrs.rate", "-5"),
        (lambda d: d["ahrs"].pop("port"), "ahrs.port", "None"),
        (lambda d: d["can"].update(heartbeat=0.1), "can.heartbeat", "0.1"),
        (lambda d: d.update(drives={"winch1": 1}), "drives", "{'winch1': 1}"),
        (lambda d: d["can"].update(sync_overflow=1), "can.sync_overflow", "1"),
    ],
)
def test_errors_name_file_field_and_value(edit, field, value):
    data = _base()
    edit(data)
    with pytest.raises(DeviceConfigError) as err:
        device_config_from_dict(data, "robot.yaml")
    msg = str(err.value)
    assert msg.startswith(f"robot.yaml: field '{field}' = {value} ")
    assert "\n" not in msg


def test_file_level_errors(tmp_path):
    with pytest.raises(DeviceConfigError, match="nope.yaml: cannot read"):
        load_device_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("can: [1, 2\n")
    with pytest.raises(DeviceConfigError, match="bad.yaml: not valid YAML"):
        load_device_config(bad)
    cfg = device_config_from_dict({"drives": [{"node_id": 1}], "encoders": []}, "two.yaml")
    with pytest.raises(DeviceConfigError, match="two.yaml: field 'drives' lists 1 nodes but the robot has 4"):
        cfg.check_robot(4)


# ---- `cdpr devices check` against emulated nodes on a virtual bus ------------------------------------------------

@pytest.fixture(autouse=True)
def _only_device_commands(monkeypatch):
    """Build the CLI with the device commands alone: importing codac (cdpr certify) under pytest turns on
    flush-to-zero, which breaks hypothesis when this file runs on its own."""
    monkeypatch.setattr(acquisition.cli, "COMMAND_MODULES", ("acquisition.cli.devices",))


def _virtual_config(tmp_path, channel: str) -> str:
    data = _base()
    # heartbeats off: the emulated nodes beat on simulated time, which this wall-paced check does not follow
    data["can"].update(interface="virtual", channel=channel, heartbeat_period=0)
    del data["loadcells"], data["ahrs"]
    path = tmp_path / "sim_devices.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_devices_check_lists_every_node(tmp_path, capsys):
    rig = CanRig(n_drives=4, n_encoders=4)
    try:
        cfg = _virtual_config(tmp_path, rig.channel)
        status = main(["devices", "check", "--config", cfg, "--json", "--syncs", "60"])
        report = json.loads(capsys.readouterr().out)
    finally:
        rig.close()
    out = report["devices"]
    assert status == 0, out
    assert 0 < report["sync_round_trip"]["cycles"] <= 60  # wall-paced: a late SYNC under load is not counted
    assert [d["name"] for d in out] == [f"winch{i}" for i in range(1, 5)] + [f"swivel{i}" for i in range(1, 5)]
    assert all(d["ok"] for d in out)
    assert all("NMT OPERATIONAL" in d["state"] for d in out)
    assert "switch on disabled" in out[0]["state"]


def test_devices_check_reports_a_missing_node(tmp_path, capsys):
    rig = CanRig(n_drives=3, n_encoders=4)  # winch4 is not on the bus
    try:
        cfg = _virtual_config(tmp_path, rig.channel)
        status = main(["devices", "check", "--config", cfg, "--syncs", "20"])
        captured = capsys.readouterr()
    finally:
        rig.close()
    assert status == 1
    lines = captured.out.splitlines()
    assert len(lines) == 9 and lines[8].startswith("SYNC round trip")
    assert lines[3].startswith("winch4") and "FAIL" in lines[3] and "SDO read of 0x1000:00 failed" in lines[3]
    assert all("OK" in line for line in lines[:3] + lines[4:8])
    assert "1 of 8 devices failed the check: winch4." in captured.err


def test_devices_check_bad_config_is_a_usage_error(tmp_path, capsys):
    path = tmp_path / "devices.yaml"
    data = _base()
    data["drives"][0]["node_id"] = 0
    path.write_text(yaml.safe_dump(data))
    assert main(["devices", "check", "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"{path}: field 'drives[0].node_id' = 0 must be in [1, 127]." in err


def test_open_devices_streams_in_lockstep():
    rig = CanRig(n_drives=4, n_encoders=4)
    robot = load_robot("irma4u")
    cfg = device_config_from_dict({
        "can": {"interface": "virtual", "channel": rig.channel, "heartbeat_period": 0.05},
        "drives": [{"name": f"w{i}", "node_id": i} for i in range(1, 5)],
        "encoders": [{"name": f"s{i}", "node_id": 10 + i} for i in range(1, 5)],
    })
    try:
        devices = open_devices(cfg, robot.sensors.length_per_motor_rev, clock=rig.clock)
        with devices:
            for _ in range(30):
                count = devices.send_sync()
                winches, swivels = devices.wait_for_sync(count, 2.0)
            assert [r.sync_count for r in winches + swivels] == [count] * 8
            assert devices.faults() == dict.fromkeys([f"w{i}" for i in range(1, 5)] + [f"s{i}" for i in range(1, 5)])
            assert [d.length_per_motor_rev for d in devices.drives] == list(robot.sensors.length_per_motor_rev)
    finally:
        rig.close()


def test_devices_check_on_the_simulated_prototype(capsys):
    pytest.importorskip("sim_backend.backend", reason="the simulator backend is not in this checkout")
    status = main(["devices", "check", "--backend", "sim", "--json", "--syncs", "30"])
    out = json.loads(capsys.readouterr().out)["devices"]
    assert status == 0, [d for d in out if not d["ok"]]
    kinds = [d["kind"] for d in out]
    assert kinds == ["winch drive"] * 4 + ["swivel encoder"] * 4 + ["load cells", "ahrs"]
    assert all(d["ok"] for d in out)
    assert all("SYNC 30" in d["state"] for d in out[:8])


def test_open_bus_failure_is_one_sentence():
    from drivers.can_bus import open_bus
    from drivers.interfaces import DeviceError

    with pytest.raises(DeviceError, match=r"cannot open CAN interface 'socketcan' channel 'cdpr-no-such0'"):
        open_bus("socketcan", "cdpr-no-such0", 1_000_000)


def test_sync_producer_counter_wraps_at_the_overflow_value():
    import can

    from drivers.can_bus import SyncProducer, open_network

    net = open_network(can.Bus(interface="virtual", channel="cdpr-sync-test"))
    listener = can.Bus(interface="virtual", channel="cdpr-sync-test")
    try:
        sync = SyncProducer(net, overflow=240)
        counts = [sync.send_sync() for _ in range(242)]
        wire = [listener.recv(1.0) for _ in range(242)]
    finally:
        listener.shutdown()
        net.disconnect()
    assert counts == list(range(1, 243))
    assert all(m.arbitration_id == 0x80 and m.dlc == 1 for m in wire)
    assert [m.data[0] for m in wire[-3:]] == [240, 1, 2]
    with pytest.raises(ValueError, match="overflow"):
        SyncProducer(net, overflow=1)


def test_devices_check_shows_a_simulated_drive_fault(tmp_path, capsys):
    pytest.importorskip("sim_backend.backend", reason="the simulator backend is not in this checkout")
    faults = tmp_path / "fault.yaml"
    faults.write_text("faults:\n  - {kind: drive_fault, t: 0.1, drive: 3}\n")
    status = main(["devices", "check", "--backend", "sim", "--sim-config", str(faults), "--syncs", "40"])
    captured = capsys.readouterr()
    assert status == 1
    line = next(ln for ln in captured.out.splitlines() if ln.startswith("winch 3"))
    assert "FAIL" in line and "emergency 0x2310" in line
    assert "1 of 10 devices failed the check: winch 3." in captured.err
