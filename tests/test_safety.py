"""Safety supervisor: each condition ends in a SafeStop with one sentence; the stop plan holds then ramps."""

import os
import signal

import numpy as np
import pytest

from acquisition.safety import SafeStop, SafetyLimits, SafetySupervisor
from calib.robot import load_robot

OK_AGES = {"load cells": (0.002, 0.002), "AHRS": (0.005, 0.01)}
NO_FAULTS = {"winch drive 1": None, "winch drive 2": None}


def sup(**kw):
    return SafetySupervisor(SafetyLimits.for_robot(load_robot("irma4u"), **kw), 4)


def test_limits_from_the_robot():
    lim = SafetyLimits.for_robot(load_robot("irma4u"))
    assert lim.slack == pytest.approx(9.0) and lim.overload == pytest.approx(300.0)
    assert lim.safe_pretension == pytest.approx(30.0)


def test_quiet_tick_passes_and_each_condition_stops_with_a_sentence():
    s = sup()
    tau = np.array([100.0, 101.0, 99.0, 100.5])
    s.check(tau, tau, OK_AGES, NO_FAULTS)
    with pytest.raises(SafeStop, match=r"^cable 3 slack: 2.0 N measured for 99.0 N commanded") as e:
        s.check(np.array([100.0, 101.0, 2.0, 100.5]), tau, OK_AGES, NO_FAULTS)
    assert e.value.kind == "slack"
    # not armed (tensions being established) or commanded low: no slack stop
    s.check(np.array([100.0, 101.0, 2.0, 100.5]), tau, OK_AGES, NO_FAULTS, armed=False)
    s.check(np.array([100.0, 101.0, 2.0, 100.5]), np.array([100.0, 101.0, 10.0, 100.5]), OK_AGES, NO_FAULTS)
    with pytest.raises(SafeStop, match="cable 2 overloaded: 350.0 N measured, above the 300 N limit") as e:
        s.check(np.array([100.0, 350.0, 99.0, 100.5]), tau, OK_AGES, NO_FAULTS)
    assert e.value.kind == "overload"
    with pytest.raises(SafeStop, match="load cells silent for 0.007 s, more than 3 periods of 0.002 s") as e:
        s.check(tau, tau, {"load cells": (0.007, 0.002)}, NO_FAULTS)
    assert e.value.kind == "stale_sensor" and e.value.channels == (0, 1, 2, 3)
    with pytest.raises(SafeStop, match=r"^winch drive 2: heartbeat lost\.$") as e:
        s.check(tau, tau, OK_AGES, {"winch drive 1": None, "winch drive 2": "heartbeat lost."})
    assert e.value.kind == "drive_fault"


def test_stuck_load_cell_is_found_by_repeated_values():
    s = sup(stuck_samples=50)
    rng = np.random.default_rng(3)
    stuck = 97.25
    with pytest.raises(SafeStop, match=r"load cell 4 stuck at 97.25 N for 50 samples") as e:
        for _ in range(200):
            tau = 100.0 + 0.1 * rng.standard_normal(4)
            tau[3] = stuck
            s.check(tau, np.full(4, 100.0), OK_AGES, NO_FAULTS)
    assert e.value.channels == (3,)


def test_signals_become_a_stop_request_and_handlers_are_restored():
    s = sup()
    before = signal.getsignal(signal.SIGTERM)
    s.install_signals()
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        with pytest.raises(SafeStop, match=r"^stopped by the operator \(SIGTERM\)\.$") as e:
            s.check(np.full(4, 100.0), np.full(4, 100.0), OK_AGES, NO_FAULTS)
        assert e.value.kind == "operator"
    finally:
        s.restore_signals()
    assert signal.getsignal(signal.SIGTERM) == before


def test_stop_plan_holds_then_ramps_to_the_safe_pretension():
    s = sup(hold_time=0.5, ramp_rate=40.0)
    plan = s.plan(np.array([150.0, 120.0, 25.0, 5.0]), power_on=np.array([35.0, 35.0, 35.0, 35.0]))
    # target: max(30 N, power-on 35 N), never raised above the tension now, never below 2 x slack (18 N)
    np.testing.assert_allclose(plan.target, [35.0, 35.0, 25.0, 18.0])
    np.testing.assert_allclose(plan.reference(0.4), [150.0, 120.0, 25.0, 5.0])
    np.testing.assert_allclose(plan.reference(1.5), [110.0, 80.0, 25.0, 18.0])
    assert plan.duration == pytest.approx(0.5 + 115.0 / 40.0)
    np.testing.assert_allclose(plan.reference(plan.duration + 1), plan.target)
