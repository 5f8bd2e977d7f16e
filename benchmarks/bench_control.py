"""Control-loop timing at 500 Hz on the simulated prototype paced in real time (not collected by pytest).

    python benchmarks/bench_control.py [--rate 500] [--seconds 20]

The loop runs the real startup routine's tick (SYNC, the tick's readings through the real drivers, safety
checks, PI tension control, torque commands) on a wall clock (RealClock, lockstep with the simulator): the
platform goes from its power-on tensions to tau0 and is held there. Reported, in ms against the period:
the compute time per tick (safety + control + commands, from readings in hand to commands sent), the full
tick time (SYNC to commands sent, including the wait for the simulator and the drivers), their mean, 99th
percentile and maximum, and the ticks that missed their deadline.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from acquisition.clock import RealClock
from acquisition.connect import connect
from acquisition.plans import Plan
from acquisition.startup import StartupConfig, StartupRoutine
from calib.robot import load_robot
from sim_backend.backend import SimBackend


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=500.0)
    ap.add_argument("--seconds", type=float, default=20.0)
    args = ap.parse_args()
    robot = load_robot("irma4u")
    period = 1.0 / args.rate
    cfg = StartupConfig(rate=args.rate)
    plan = Plan.for_robot(robot, 2, "equilibrium")
    clock = RealClock(period, lockstep=True)
    with SimBackend(robot, None, 0, period) as sim, tempfile.TemporaryDirectory() as tmp:
        rig = connect(sim.devices, robot, clock, lockstep=True, period=period)
        try:
            routine = StartupRoutine(robot, rig, clock, plan, Path(tmp) / "run", cfg)
            ticks: list[float] = []
            inner = rig.tick

            def timed_tick(*a, **k):
                t0 = time.perf_counter()
                snap = inner(*a, **k)
                ticks.append(t0)
                return snap

            rig.tick = timed_tick
            routine.zero()
            routine.enable()
            routine._compute.clear()
            ticks.clear()
            clock.overruns.count = 0
            steps = int(args.seconds * args.rate)
            ends = []
            tau_init, tau0 = routine._tau_init, plan.tau0
            for k in range(steps):
                s = min(1.0, k * period / 5.0)
                routine._tick(tau_init + (tau0 - tau_init) * s, log=False)
                ends.append(time.perf_counter())
        finally:
            rig.close()
    comp = np.array(routine._compute) * 1e3
    full = (np.array(ends) - np.array(ticks[: len(ends)])) * 1e3
    p = period * 1e3
    print(f"rate {args.rate:g} Hz (period {p:.3f} ms), {len(comp)} ticks in real time, simulated prototype")
    for name, x in (("compute (safety+control+commands)", comp), ("full tick (SYNC..commands)", full)):
        print(f"{name:36s} mean {x.mean():.3f} ms  p99 {np.percentile(x, 99):.3f} ms  max {x.max():.3f} ms  "
              f"p99/period {np.percentile(x, 99) / p:.2f}")
    print(f"missed deadlines: {clock.overruns.count} of {len(comp)} ticks (worst {clock.overruns.worst * 1e3:.2f} ms "
          f"late)")


if __name__ == "__main__":
    main()
