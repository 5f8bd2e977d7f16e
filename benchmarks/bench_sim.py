"""Speed of the simulated prototype: physics step, backend tick, lockstep through the real drivers, startup.

    python benchmarks/bench_sim.py                 # physics, backend tick and driver lockstep at 200 and 500 Hz
    python benchmarks/bench_sim.py --startup 2     # plus the full 'cdpr startup --backend sim --grid 2'
    python benchmarks/bench_sim.py --startup 2 --repeat 5   # five startups: range and median
    python benchmarks/bench_sim.py --startup 2 --split      # plus where the routine's tick goes, method by method
    python benchmarks/bench_sim.py --startup 2 --no-html    # the startup without its HTML report

The target (issue 4): the whole 8-pose startup routine at >= 20x real time on 2 cores, device traffic
included. Reports wall microseconds per control tick, where they go, and the real-time factor
(simulated seconds per wall second); for the startup also the routine's own loop per 5 ms tick, apart from
connecting, solving and the report. The VM's timings drift by up to 1.6x between runs (the physics step,
printed first and after the startups, is the gauge): use --repeat.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from acquisition.connect import feedback_every
from calib.equilibrium import direct_statics
from calib.robot import load_robot
from sim_backend.backend import SimBackend
from sim_backend.physics import CablePhysics, PhysicsParams, transmission_of


def bench_physics(robot, steps: int = 20000) -> float:
    """Wall µs per physics step (5 ms) of the platform swinging under constant torques."""
    tau = np.full(robot.n, 100.0)
    pose = direct_statics(robot, tau).poses[0]
    k = transmission_of(robot)
    ph = CablePhysics(robot, PhysicsParams(), k, pose, tau, brakes=False)
    ph._v = [0.05, 0.02, 0.0]
    t0 = time.perf_counter()
    for _ in range(steps):
        ph.step(0.005)
    return (time.perf_counter() - t0) / steps * 1e6


def _wrap(obj, name: str, acc: dict, key: str) -> None:
    orig = getattr(obj, name)

    def timed(*a, **kw):
        t = time.perf_counter()
        try:
            return orig(*a, **kw)
        finally:
            acc[key] += time.perf_counter() - t

    setattr(obj, name, timed)


def _instrument(sim: SimBackend) -> dict:
    """Time the backend's SYNC handler and its parts: the plant (physics, load-cell line and AHRS sample, or,
    with the plant in its child process, handing the commands over and taking the state back), the drives'
    targets and the CAN nodes' TPDOs."""
    acc = {"tick": 0.0, "plant": 0.0, "apply_targets": 0.0, "can_tpdos": 0.0}
    link = sim._link
    _wrap(link, "collect", acc, "plant")
    _wrap(link, "emit", acc, "plant")
    _wrap(link, "advance", acc, "plant")
    for d in sim.drives:
        _wrap(d, "apply_targets", acc, "apply_targets")
    for node in sim.drives + sim.encoders:
        _wrap(node, "on_sync", acc, "can_tpdos")
    _wrap(sim, "tick", acc, "tick")
    return acc


def bench_backend_tick(robot, period: float, ticks: int = 2000, plant_process: bool = True) -> tuple[float, dict]:
    """Backend ticks called directly (no master, no drivers): wall µs per tick and its split."""
    with SimBackend(robot, None, seed=1, control_period=period, plant_process=plant_process) as sim:
        acc = _instrument(sim)
        t0 = time.perf_counter()
        for _ in range(ticks):
            sim.tick()
        wall = time.perf_counter() - t0
    return wall / ticks * 1e6, {k: v / ticks * 1e6 for k, v in acc.items()}


def bench_lockstep(robot, period: float, ticks: int = 2000, plant_process: bool = True) -> tuple[float, dict]:
    """A simple force loop through the real drivers in lockstep, set up as the startup's connect() does (one
    drivers.open.open_devices, polled serial ports, the drives and encoders answering every n-th SYNC as
    feedback_every says): torque targets -> SYNC -> wait for the TPDOs due and the load-cell line of that tick.
    Wall µs per tick and the backend's share (the SYNC handler runs inside the SYNC send)."""
    from drivers.open import open_devices

    lpr = np.asarray(robot.sensors.length_per_motor_rev)
    radius = np.abs(lpr) / (2 * math.pi)
    with SimBackend(robot, None, seed=1, control_period=period, plant_process=plant_process) as sim:
        every = feedback_every(1.0 / period, int(round(0.1 / period)))  # the routine's feedback rates
        devices = open_devices(sim.devices, lpr, clock=lambda: sim.time, every=every, control_period=period,
                               polled=True, stale_periods=1e9)
        drives, encs, cells, sync = devices.drives, devices.encoders, devices.loadcells, devices.sync
        try:
            ref = sim.truth().tensions
            for d, r, tau in zip(drives, radius, ref, strict=True):
                d.set_torque(tau * r)
            for d in drives:
                d.enable()
            acc = _instrument(sim)
            nodes = sim.drives + sim.encoders
            sent0 = sum(n.frames_sent for n in nodes)
            integ = np.zeros(robot.n)
            target = np.full(robot.n, 100.0)
            t0 = time.perf_counter()
            lc = None
            for s in range(ticks):
                a = min(1.0, s * period / 3.0)
                tref = ref + (target - ref) * a
                meas = tref if lc is None else lc.tau
                err = tref - meas
                integ += err * period
                u = radius * (tref + 0.5 * err + 10.0 * integ)
                for d, ui in zip(drives, u, strict=True):
                    d.set_torque(float(ui))
                c = sync.send_sync()
                for d in drives + encs:
                    if d.due(c):
                        d.wait_for_sync(c, 2.0)
                lc = cells.wait_for(c - 1, 2.0)
            wall = time.perf_counter() - t0
            # the nodes' TPDOs and heartbeats, and the master's SYNC and one RPDO per drive
            acc["frames"] = (sum(n.frames_sent for n in nodes) - sent0 + ticks * (1 + len(drives))) * 1e-6
        finally:
            devices.close()
        if sim.errors:
            raise RuntimeError(sim.errors[0])
    return wall / ticks * 1e6, {k: v / ticks * 1e6 for k, v in acc.items()}


def bench_startup(grid: int, extra: tuple[str, ...] = ()) -> tuple[float, float, dict]:
    """The operator's routine: 'cdpr startup --backend sim --grid N'; (wall s, simulated s, the timing it reports:
    acquisition_s simulated, wall_s of the routine's loop, solve_s)."""
    import contextlib
    import io
    import json

    from acquisition.cli import main

    with tempfile.TemporaryDirectory() as tmp:
        out = io.StringIO()
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(out):
            status = main(["startup", "--backend", "sim", "--grid", str(grid), "--out", str(Path(tmp) / "run"), *extra,
                           "--json"])
        wall = time.perf_counter() - t0
    if status:
        raise RuntimeError(f"cdpr startup exited with status {status}")
    timing = json.loads(out.getvalue())["timing"]
    return wall, float(timing["acquisition_s"]), timing


# (module, class, method) timed by --split: the routine's tick and where it goes, on both sides of the wire
_SPLIT = [
    ("acquisition.startup", "StartupRoutine", "_tick"), ("acquisition.control", "Rig", "tick"),
    ("drivers.can_bus", "SyncProducer", "send_sync"), ("sim_backend.backend", "SimBackend", "tick"),
    ("sim_backend.plant_link", "ChildPlantLink", "collect"), ("sim_backend.plant_link", "ChildPlantLink", "emit"),
    ("sim_backend.plant_link", "ChildPlantLink", "advance"),
    ("sim_backend.can_drive_emulator", "SimulatedNode", "on_sync"),
    ("sim_backend.can_drive_emulator", "CanDriveEmulator", "apply_targets"),
    ("drivers.loadcell", "LoadCellDriver", "latest"), ("drivers.xsens", "XsensMti", "latest"),
    ("acquisition.startup", "StartupRoutine", "_supervise"), ("acquisition.control", "Rig", "faults"),
    ("acquisition.control", "Rig", "command"), ("acquisition.control", "TensionController", "update"),
    ("acquisition.startup", "StartupRoutine", "_log"),
]


def bench_split(grid: int) -> tuple[int, dict[str, tuple[float, float]]]:
    """The startup with the methods of _SPLIT timed (class-level wrappers, ~0.3 us each): (SYNC ticks,
    {Class.method: (wall us per tick, calls per tick)})."""
    import collections
    import importlib

    acc: dict[str, float] = collections.Counter()
    calls: dict[str, int] = collections.Counter()
    saved = []
    for module, cls_name, name in _SPLIT:
        cls = getattr(importlib.import_module(module), cls_name)
        orig = cls.__dict__[name]
        key = f"{cls_name}.{name}"

        def timed(*a, _orig=orig, _key=key, **kw):
            t = time.perf_counter()
            try:
                return _orig(*a, **kw)
            finally:
                acc[_key] += time.perf_counter() - t
                calls[_key] += 1

        setattr(cls, name, timed)
        saved.append((cls, name, orig))
    try:
        bench_startup(grid)
    finally:
        for cls, name, orig in saved:
            setattr(cls, name, orig)
    ticks = max(calls["SimBackend.tick"], 1)
    return ticks, {k: (v / ticks * 1e6, calls[k] / ticks) for k, v in sorted(acc.items(), key=lambda kv: -kv[1])}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=2000)
    ap.add_argument("--startup", type=int, default=0, metavar="GRID", help="also time the full startup")
    ap.add_argument("--repeat", type=int, default=1, help="startup runs (the VM's speed drifts between runs)")
    ap.add_argument("--split", action="store_true", help="with --startup: one more run, timed method by method")
    ap.add_argument("--no-html", action="store_true", help="time the startup without its report (its --no-html)")
    args = ap.parse_args(argv)
    robot = load_robot("irma4u")
    print(f"physics step (5 ms, substeps 1): {bench_physics(robot):.1f} us")
    for rate, child in ((200, True), (200, False), (500, True)):
        period = 1.0 / rate
        where = "plant in its child process" if child else "plant in this process"
        us, split = bench_backend_tick(robot, period, args.ticks, child)
        parts = ", ".join(f"{k} {v:.0f}" for k, v in split.items() if k != "tick")
        print(f"{rate} Hz backend tick alone, {where}: {us:.0f} us/tick ({parts}) -> {period * 1e6 / us:.1f}x "
              f"real time")
        us, split = bench_lockstep(robot, period, args.ticks, child)
        frames = split.pop("frames")
        parts = ", ".join(f"{k} {v:.0f}" for k, v in split.items())
        print(f"{rate} Hz lockstep through the real drivers, {where}: {us:.0f} us/tick -> "
              f"{period * 1e6 / us:.1f}x real time, {frames:.1f} CAN frames/tick; in the backend's SYNC handler: "
              f"{parts}; master side and bus: {us - split['tick']:.0f}")
    factors = []
    for _ in range(args.startup and args.repeat):
        wall, sim_s, timing = bench_startup(args.startup, ("--no-html",) if args.no_html else ())
        loop = float(timing["wall_s"])
        factors.append(sim_s / wall)
        print(f"cdpr startup --backend sim --grid {args.startup}: {sim_s:.1f} s simulated in {wall:.1f} s wall "
              f"-> {sim_s / wall:.1f}x real time (the routine's loop {loop:.1f} s, "
              f"{loop / sim_s * 1e6 * 0.005:.0f} us per 5 ms tick; solve {float(timing['solve_s']):.1f} s; "
              f"connecting, report and the rest {wall - loop - float(timing['solve_s']):.1f} s)")
    if len(factors) > 1:
        print(f"startup over {len(factors)} runs: {min(factors):.1f}x to {max(factors):.1f}x real time, "
              f"median {statistics.median(factors):.1f}x")
    if factors:  # the VM's speed drifts: the same pure-Python step again tells how fast it ran meanwhile
        print(f"physics step after the startups: {bench_physics(robot, 5000):.1f} us (this machine at its usual "
              f"speed: 37-41 us)")
    if args.startup and args.split:
        ticks, split = bench_split(args.startup)
        print(f"where a tick of the startup goes ({ticks} SYNCs; nested: a row includes the rows it calls):")
        for key, (us, per) in split.items():
            print(f"  {key:34s} {us:7.1f} us/tick  ({per:.2f} calls/tick)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
