"""`cdpr devices check --config FILE | --backend sim`: connect every device of the set and list its state.

The CAN nodes are configured (SDO), started, and a few SYNCs are sent so that each one shows its PDO
feedback and heartbeat; the drives stay disabled (no torque). Serial devices are opened and one sample is
awaited. One line per device: ``OK`` or ``FAIL`` and its state; exit status 1 when any device fails.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass

from acquisition.cli.errors import OperationError, UsageError
from drivers.config import DeviceConfig, DeviceConfigError, load_device_config
from drivers.interfaces import DeviceError


@dataclass
class DeviceCheck:
    name: str
    kind: str  # winch drive, swivel encoder, load cells, ahrs
    address: str  # CAN node id or serial port
    ok: bool
    state: str


def register(devsub) -> None:
    p = devsub.add_parser("check", help="connect every device of the set and list its state")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", help="device set YAML (see drivers/examples/irma4u_devices.yaml)")
    src.add_argument("--backend", choices=("sim",), help="check the devices of the simulated prototype")
    p.add_argument("--robot", default="irma4u", help="robot description (transmission ratios), default irma4u")
    p.add_argument("--syncs", type=int, default=40, help="SYNC cycles to run for the check (default 40)")
    p.add_argument("--period", type=float, default=0.005, help="SYNC period, s (default 0.005)")
    p.add_argument("--seed", type=int, default=0, help="simulator seed (--backend sim)")
    p.add_argument("--json", action="store_true", help="print a JSON list of devices on stdout")
    p.set_defaults(func=run)


def check_devices(config: DeviceConfig, robot, syncs: int = 40, period: float = 0.005, clock=None,
                  lockstep: bool = False, bus=None) -> list[DeviceCheck]:
    """Open and check every device of ``config``; ``lockstep``: the SYNC advances a simulator, so wait
    for each SYNC's PDOs instead of pacing on wall time (the clock is then SYNC count x period)."""
    from drivers.can_bus import open_can_devices

    results: list[DeviceCheck] = []
    devices = None
    try:
        devices = open_can_devices(config, robot.sensors.length_per_motor_rev or (1.0,) * len(config.drives),
                                   robot.sensors.swivel_counts_per_rev, clock=time.monotonic,
                                   open_nodes=False, bus=bus)
    except DeviceError as exc:
        raise OperationError(str(exc).rstrip(".") + ".") from exc
    try:
        if clock is None and lockstep:
            sync = devices.sync

            def clock():
                return sync.count * period
        for drv in devices.drives + devices.encoders:
            if clock is not None:
                drv.clock = clock
        opened = []
        errors: dict[str, str] = {}
        for drv in devices.drives + devices.encoders:
            try:
                drv.open()
                opened.append(drv)
            except DeviceError as exc:
                errors[drv.name] = str(exc)
        for _ in range(max(syncs, 0)):
            count = devices.send_sync()
            if lockstep:
                for drv in opened:
                    try:
                        drv.wait_for_sync(count, 0.5)
                    except DeviceError:
                        pass
            else:
                time.sleep(period)
        time.sleep(0.01 if lockstep else 2 * period)
        for kind, group in (("winch drive", devices.drives), ("swivel encoder", devices.encoders)):
            for drv in group:
                if drv.name in errors:
                    results.append(DeviceCheck(drv.name, kind, f"CAN node {drv.node_id}", False, errors[drv.name]))
                    continue
                fault = drv.fault()
                if fault is None and drv.latest() is None:
                    fault = f"{drv.name} (CAN node {drv.node_id}) sent no PDO in {syncs} SYNC cycles"
                if fault is None and drv.heartbeat is not None and drv.heartbeat.count == 0 \
                        and drv.heartbeat_period > 0 and syncs * period >= 2 * drv.heartbeat_period:
                    fault = f"{drv.name} (CAN node {drv.node_id}) sent no heartbeat"
                results.append(DeviceCheck(drv.name, kind, f"CAN node {drv.node_id}", fault is None,
                                           drv.status() if fault is None else fault))
    finally:
        devices.close()
    results += _check_serial(config)
    return results


def _check_serial(config: DeviceConfig) -> list[DeviceCheck]:
    out = []
    if config.loadcells is not None:
        from drivers.loadcell import LoadCellConfig, LoadCellDriver

        dev = LoadCellDriver(LoadCellConfig(port=config.loadcells.port, baud=config.loadcells.baud))
        out.append(_serial_one(dev, "loadcells", "load cells", config.loadcells.port))
    if config.ahrs is not None:
        from drivers.xsens import XsensConfig, XsensMti

        try:
            dev = XsensMti(XsensConfig(port=config.ahrs.port, baud=config.ahrs.baud, rate_hz=int(config.ahrs.rate)))
        except ValueError as exc:
            return out + [DeviceCheck("ahrs", "ahrs", config.ahrs.port, False, str(exc))]
        out.append(_serial_one(dev, "ahrs", "ahrs", config.ahrs.port))
    return out


def _serial_one(dev, name: str, kind: str, port: str) -> DeviceCheck:
    try:
        dev.open()
    except DeviceError as exc:
        return DeviceCheck(name, kind, port, False, str(exc))
    try:
        deadline = time.monotonic() + 1.0
        while dev.latest() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        fault = dev.fault()
        if fault is None and dev.latest() is None:
            fault = f"{kind} on {port}: no sample within 1 s"
        return DeviceCheck(name, kind, port, fault is None, dev.status() if fault is None else fault)
    finally:
        dev.close()


def _sim_check(args, robot) -> list[DeviceCheck]:
    try:
        from sim_backend.backend import SimBackend
    except ModuleNotFoundError as exc:
        if exc.name == "sim_backend.backend":
            raise OperationError("the simulator backend (sim_backend/backend.py) is not available in this "
                                 "checkout.") from exc
        raise
    with SimBackend(robot, None, args.seed, args.period) as sim:
        config = getattr(sim, "device_config", None) or sim.devices
        return check_devices(config, robot, args.syncs, args.period, lockstep=True)


def run(args) -> int:
    from calib.robot import RobotDescriptionError, load_robot

    if args.syncs < 1:
        raise UsageError(f"--syncs must be at least 1, got {args.syncs}.")
    if not args.period > 0:
        raise UsageError(f"--period must be a positive number of seconds, got {args.period}.")
    try:
        robot = load_robot(args.robot)
    except (RobotDescriptionError, FileNotFoundError) as exc:
        raise UsageError(str(exc)) from exc
    if args.backend == "sim":
        results = _sim_check(args, robot)
    else:
        try:
            config = load_device_config(args.config)
            config.check_robot(robot.n)
        except DeviceConfigError as exc:
            raise UsageError(str(exc).rstrip(".") + ".") from exc
        results = check_devices(config, robot, args.syncs, args.period)
    if args.json:
        print(json.dumps([asdict(r) for r in results]))
    else:
        width = max((len(r.name) for r in results), default=4)
        for r in results:
            print(f"{r.name:<{width}}  {r.address:<14}  {'OK  ' if r.ok else 'FAIL'}  {r.state}")
    failed = [r.name for r in results if not r.ok]
    if failed:
        sys.stderr.write(f"cdpr: {len(failed)} of {len(results)} devices failed the check: {', '.join(failed)}.\n")
        return 1
    return 0
