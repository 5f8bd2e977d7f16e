"""`cdpr devices check --config FILE | --backend sim`: connect every device of the set and list its state.

The CAN nodes are configured (SDO), started, and a few SYNCs are sent so that each one shows its PDO
feedback and heartbeat; the drives stay disabled (no torque). The SYNC round trip (SYNC sent -> the PDOs of
every node received) is measured on the way. Serial devices are opened and one sample is
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


@dataclass
class CheckResult:
    devices: list[DeviceCheck]
    sync_round_trip: list[float]  # s, per SYNC: sent -> every opened node's PDOs received

    def round_trip_summary(self) -> dict[str, float] | None:
        rt = self.sync_round_trip
        if not rt:
            return None
        return {"cycles": len(rt), "mean_us": 1e6 * sum(rt) / len(rt), "max_us": 1e6 * max(rt)}


def register(devsub) -> None:
    p = devsub.add_parser("check", help="connect every device of the set and list its state")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", help="device set YAML (see drivers/examples/irma4u_devices.yaml)")
    src.add_argument("--backend", choices=("sim",), help="check the devices of the simulated prototype")
    p.add_argument("--robot", default="irma4u", help="robot description (transmission ratios), default irma4u")
    p.add_argument("--syncs", type=int, default=40, help="SYNC cycles to run for the check (default 40)")
    p.add_argument("--period", type=float, default=0.005, help="SYNC period, s (default 0.005)")
    p.add_argument("--seed", type=int, default=0, help="simulator seed (--backend sim)")
    p.add_argument("--sim-config", help="simulation YAML: hidden effects and faults (--backend sim)")
    p.add_argument("--json", action="store_true", help="print a JSON list of devices on stdout")
    p.set_defaults(func=run)


def check_devices(config: DeviceConfig, robot, syncs: int = 40, period: float = 0.005, clock=None,
                  lockstep: bool = False) -> CheckResult:
    """Open every device of ``config``, run ``syncs`` SYNC cycles, and report each device's state.

    ``lockstep``: each SYNC advances a simulator, so wait for the PDOs of each SYNC instead of pacing on
    wall time (the CAN drivers' clock is then SYNC count x period, the simulated time)."""
    from drivers.open import open_devices

    try:
        devices = open_devices(config, robot.sensors.length_per_motor_rev or (1.0,) * len(config.drives),
                               robot.sensors.swivel_counts_per_rev, control_period=period, open_now=False)
    except DeviceConfigError as exc:
        raise UsageError(str(exc).rstrip(".") + ".") from exc
    except DeviceError as exc:
        raise OperationError(str(exc).rstrip(".") + ".") from exc
    with devices:
        nodes = devices.drives + devices.encoders
        serial = [(dev, kind, port) for dev, kind, port in
                  ((devices.loadcells, "load cells", config.loadcells and config.loadcells.port),
                   (devices.ahrs, "ahrs", config.ahrs and config.ahrs.port)) if dev is not None]
        if clock is None and lockstep:
            sync = devices.sync

            def clock():
                return sync.count * period
        for drv in nodes:
            if clock is not None:
                drv.clock = clock
        errors = devices.open_each()  # device -> why it did not open
        opened = [drv for drv in nodes if drv not in errors]
        round_trip = []
        for _ in range(syncs):
            t0 = time.perf_counter()
            count = devices.send_sync()
            complete = True
            for drv in opened:  # lockstep: the next SYNC only once this one is answered
                try:
                    drv.wait_for_sync(count, 0.5 if lockstep else period)
                except DeviceError:
                    complete = False
            elapsed = time.perf_counter() - t0
            if complete and opened:
                round_trip.append(elapsed)
            if not lockstep and elapsed < period:
                time.sleep(period - elapsed)

        def can_results() -> list[DeviceCheck]:
            out = []
            for kind, group in (("winch drive", devices.drives), ("swivel encoder", devices.encoders)):
                for drv in group:
                    where = f"CAN node {drv.node_id}"
                    if drv in errors:
                        out.append(DeviceCheck(drv.name, kind, where, False, errors[drv]))
                        continue
                    fault = drv.fault()
                    if fault is None and drv.latest() is None:
                        fault = f"{drv.name} ({where}) sent no PDO in {syncs} SYNC cycles"
                    if fault is None and drv.heartbeat is not None and drv.heartbeat.count == 0 \
                            and drv.heartbeat_period > 0 and syncs * period >= 2 * drv.heartbeat_period:
                        fault = f"{drv.name} ({where}) sent no heartbeat"
                    out.append(DeviceCheck(drv.name, kind, where, fault is None,
                                           drv.status() if fault is None else fault))
            return out

        def serial_results() -> list[DeviceCheck]:
            out = []
            for dev, kind, port in serial:
                if dev in errors:
                    out.append(DeviceCheck(dev.name, kind, port, False, errors[dev]))
                    continue
                if lockstep:  # one more tick, and judge the device right after its fresh sample
                    before = dev.latest()
                    count = devices.send_sync()
                    for drv in opened:
                        try:
                            drv.wait_for_sync(count, 0.5)
                        except DeviceError:
                            pass
                    deadline = time.monotonic() + 0.5
                    while dev.latest() is before and time.monotonic() < deadline:
                        time.sleep(0.0005)
                fault = dev.fault()
                if fault is None and dev.latest() is None:
                    fault = f"{kind} on {port}: no sample during the check"
                out.append(DeviceCheck(dev.name, kind, port, fault is None, dev.status() if fault is None else fault))
            return out

        if lockstep:
            results = can_results()
            return CheckResult(results + serial_results(), round_trip)
        # on wall time the serial devices stream on their own: judge them now, the CAN nodes a little later
        later = serial_results()
        time.sleep(2 * period)  # let the last PDOs and heartbeats in
        return CheckResult(can_results() + later, round_trip)


def _sim_check(args, robot) -> CheckResult:
    try:
        from sim_backend.backend import SimBackend
    except ModuleNotFoundError as exc:
        if exc.name == "sim_backend.backend":
            raise OperationError("the simulator backend (sim_backend/backend.py) is not available in this "
                                 "checkout.") from exc
        raise
    from sim_backend.config import SimConfigError

    try:
        sim = SimBackend(robot, args.sim_config, args.seed, args.period)
    except SimConfigError as exc:
        raise UsageError(str(exc)) from exc
    with sim:
        config = getattr(sim, "device_config", None) or sim.devices
        return check_devices(config, robot, args.syncs, args.period, lockstep=True)


def run(args) -> int:
    from calib.robot import RobotDescriptionError, load_robot

    if args.sim_config and args.backend != "sim":
        raise UsageError("--sim-config applies to --backend sim only.")
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
    rt = results.round_trip_summary()
    devices = results.devices
    if args.json:
        print(json.dumps({"devices": [asdict(r) for r in devices], "sync_round_trip": rt}))
    else:
        width = max((len(r.name) for r in devices), default=4)
        for r in devices:
            print(f"{r.name:<{width}}  {r.address:<14}  {'OK  ' if r.ok else 'FAIL'}  {r.state}")
        if rt:
            print(f"SYNC round trip (SYNC sent -> all PDOs in): mean {rt['mean_us']:.0f} us, "
                  f"max {rt['max_us']:.0f} us over {rt['cycles']} cycles")
    failed = [r.name for r in devices if not r.ok]
    if failed:
        sys.stderr.write(f"cdpr: {len(failed)} of {len(devices)} devices failed the check: {', '.join(failed)}.\n")
        return 1
    return 0
