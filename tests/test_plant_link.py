"""The simulated plant's child process: it waits for a paced SYNC instead of spinning; the link reports its timing."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from calib.robot import load_robot
from sim_backend.backend import SimBackend
from sim_backend.plant_link import CHILD_POLL, Durations, child_process_possible

ROBOT = load_robot("irma4u")
PERIOD = 0.005
needs_child = pytest.mark.skipif(not child_process_possible(), reason="the plant's child process needs two cores")


def _cpu_and_wakeups(pid: int) -> tuple[float, int]:
    """CPU s and voluntary context switches of process ``pid``'s threads so far (/proc)."""
    cpu, vcs = 0.0, 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
            cpu += int(f.read().split()[0]) * 1e-9
        with open(f"/proc/{pid}/task/{tid}/status") as f:
            vcs += next(int(line.split()[1]) for line in f if line.startswith("voluntary_ctxt_switches"))
    return cpu, vcs


def _paced_ticks(sim: SimBackend, ticks: int) -> float:
    """``ticks`` SYNCs of the backend at its control period in wall time; returns the wall time, s."""
    t0 = time.perf_counter()
    for k in range(ticks):
        delay = t0 + k * PERIOD - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        sim.tick()
    return time.perf_counter() - t0


@needs_child
def test_a_paced_plant_blocks_between_syncs_instead_of_spinning():
    with SimBackend(ROBOT, None, seed=3, control_period=PERIOD, plant_process=True) as sim:
        _paced_ticks(sim, 40)  # the child learns the pace (one poll that runs out)
        cpu0, vcs0 = _cpu_and_wakeups(sim.plant_pid)
        wall = _paced_ticks(sim, 200)
        cpu1, vcs1 = _cpu_and_wakeups(sim.plant_pid)
        timing = sim.plant_timing()
    share = (cpu1 - cpu0) / wall
    # polling CHILD_POLL = 2 ms of every 5 ms period was 40-45 % of a core; its step and samples are a few %
    assert share < 0.2, f"the paced plant used {100 * share:.1f} % of a core"
    assert vcs1 - vcs0 >= 150  # it slept until (nearly) every SYNC: one wake-up per period
    assert timing["wake"]["count"] == timing["confirm"]["count"] == 240
    assert timing["step"]["count"] == 240  # power-on and 239 steps: the last is collected at the next SYNC
    assert 0.0 < timing["step"]["p50_ms"] < PERIOD * 1e3  # the state is ready within the period
    assert 0.0 <= timing["wake"]["p50_ms"] < PERIOD * 1e3


@needs_child
def test_the_plant_answers_the_same_states_paced_or_unpaced():
    """The wait's policy is timing only: the same seed gives the same states whatever the pace."""
    states = []
    for paced in (True, False):
        with SimBackend(ROBOT, None, seed=5, control_period=PERIOD, plant_process=True) as sim:
            for k in range(80):
                if paced and (k // 20) % 2:  # 20 SYNCs at once (the child starts polling), 20 beyond its poll
                    time.sleep(1.5 * CHILD_POLL)
                sim.tick()
            states.append(sim.physics.state)
    assert states[0] == states[1]


def test_durations_keep_the_last_values_and_summarise_them_in_ms():
    d = Durations(size=4)
    assert d.summary() == {"count": 0}
    for v in (9.0, 1e-3, 2e-3, 3e-3, 4e-3):  # the first is pushed out
        d.add(v)
    s = d.summary()
    assert s["count"] == 5
    assert s["worst_ms"] == pytest.approx(4.0)
    assert s["p50_ms"] == pytest.approx(2.5)
    assert np.isclose(s["p99_ms"], 3.97)


def test_the_in_process_plant_has_no_timing():
    with SimBackend(ROBOT, None, seed=3, control_period=PERIOD, plant_process=False) as sim:
        sim.tick()
        assert sim.plant_timing() == {}
