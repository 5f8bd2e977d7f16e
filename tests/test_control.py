"""Tension controller, clocks and equilibrium detector on real numbers.

The controller drives a small but real winch plant defined here: a motor and drum (inertia, viscous and
Coulomb friction) reeling an elastic cable tied to a fixed point, integrated with substeps.
"""

import math

import numpy as np
import pytest

from acquisition.clock import RealClock, SimClock
from acquisition.control import ControllerConfig, TensionController, transmission_radius
from acquisition.equilibrium import DetectorConfig, EquilibriumDetector
from acquisition.trajectory import TensionTrajectory
from calib.robot import load_robot


class Winch:
    """n motors with drums reeling elastic cables: tension = k (s0 + radius theta), never negative."""

    def __init__(self, radius, k=20000.0, inertia=2e-4, viscous=2e-3, coulomb=0.02, pretension=20.0):
        self.r = np.asarray(radius, float)
        self.k, self.J, self.b, self.fc = k, inertia, viscous, coulomb
        self.theta = np.zeros_like(self.r)
        self.omega = np.zeros_like(self.r)
        self.s0 = pretension / k

    def tension(self):
        return np.maximum(0.0, self.k * (self.s0 + self.r * self.theta))

    def step(self, torque, dt, substeps=20):
        h = dt / substeps
        for _ in range(substeps):
            friction = self.b * self.omega + self.fc * np.tanh(self.omega / 1e-3)
            acc = (torque - self.r * self.tension() - friction) / self.J
            self.omega = self.omega + h * acc
            self.theta = self.theta + h * self.omega


def run(controller, plant, reference, duration, dt, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    steps = int(round(duration / dt))
    log_ref, log_tau, log_torque = [], [], []
    for k in range(steps):
        meas = plant.tension() + noise * rng.standard_normal(plant.r.size)
        ref = reference(k * dt)
        torque = controller.update(ref, meas, dt)
        plant.step(torque, dt)
        log_ref.append(ref)
        log_tau.append(plant.tension())
        log_torque.append(torque)
    return np.array(log_ref), np.array(log_tau), np.array(log_torque)


def test_transmission_radius_sign_and_size_for_irma4u():
    r = transmission_radius(load_robot("irma4u"))
    np.testing.assert_allclose(r, np.array([0.028807, 0.028652, 0.028448, 0.028641]) / (2 * math.pi))


def test_pi_tracks_a_quintic_and_removes_the_friction_offset():
    radius = transmission_radius(load_robot("irma4u"))
    cfg = ControllerConfig(rate=500.0, integral_deadband=0.0)
    ctl = TensionController(radius, cfg)
    plant = Winch(radius)
    ctl.reset(plant.tension())
    traj = TensionTrajectory.through(np.array([[20.0] * 4, [118.48, 170.83, 115.57, 82.98]]), max_rate=60.0)
    ref, tau, torque = run(ctl, plant, traj.at, traj.duration + 3.0, cfg.period, noise=0.05)
    err = np.abs(ref - tau)
    assert err.max() < 2.0  # N, during the move
    # N, at rest over the last second: within the load cells' accuracy (0.2 N) on average. Without the
    # deadband the integral hunts the Coulomb friction (stick-slip of about 0.3 N), a tenth of its offset
    assert err[-500:].mean() < 0.25 and err[-500:].max() < 0.4
    # feed-forward alone leaves the Coulomb friction's offset (0.02 N m / 4.6 mm = 4.4 N)
    ff = TensionController(radius, ControllerConfig(kp=0.0, ki=0.0))
    plant2 = Winch(radius)
    ff.reset(plant2.tension())
    ref2, tau2, _ = run(ff, plant2, traj.at, traj.duration + 2.0, cfg.period)
    assert np.abs(ref2 - tau2)[-1].max() > 2.0


def test_integral_deadband_ignores_small_errors():
    """Errors inside the deadband (load-cell noise, friction's stick band) are not integrated, so the
    winch is not made to creep in stick-slip at rest; larger errors are."""
    ctl = TensionController(np.array([0.005, 0.005]), ControllerConfig(ki=30.0, integral_deadband=1.5))
    ctl.reset(np.array([100.0, 100.0]))
    for _ in range(100):
        ctl.update(np.array([100.0, 100.0]), np.array([98.8, 97.0]), 0.002)
    np.testing.assert_allclose(ctl.integral, [0.0, 30.0 * 3.0 * 0.2])


def test_torque_rate_limit_and_anti_windup():
    radius = np.array([0.0046])
    cfg = ControllerConfig(rate=500.0, max_command=120.0, max_command_rate=300.0, integral_deadband=0.0)
    ctl = TensionController(radius, cfg)
    plant = Winch(radius, pretension=50.0)
    ctl.reset(plant.tension())
    # a step to 200 N: the command ramps at 300 N/s and stops at 120 N; the integral stays frozen
    ref, tau, torque = run(ctl, plant, lambda t: np.array([200.0]), 1.0, cfg.period)
    steps = np.diff(torque[:, 0]) / radius[0]
    assert steps.max() <= 300.0 * cfg.period + 1e-9
    assert torque[:, 0].max() == pytest.approx(120.0 * radius[0])
    assert abs(ctl.integral[0]) < 5.0  # frozen while saturated
    # back to a reachable 100 N: settles without a windup overshoot
    ref, tau, _ = run(ctl, plant, lambda t: np.array([100.0]), 1.5, cfg.period)
    assert tau[:, 0].min() > 90.0 and tau[-1, 0] == pytest.approx(100.0, abs=0.2)


def test_open_loop_channel_ignores_its_load_cell():
    ctl = TensionController(np.array([0.005, 0.005]), ControllerConfig())
    ctl.reset(np.array([100.0, 100.0]))
    t = ctl.update(np.array([100.0, 100.0]), np.array([0.0, 0.0]), 0.002)
    ctl.open_loop(np.array([1]))
    t2 = ctl.update(np.array([100.0, 100.0]), np.array([0.0, 0.0]), 0.002)
    assert t[0] > 0.5 and t2[1] == pytest.approx(0.5)  # feed-forward only on channel 2


def test_sim_clock_is_lockstep_and_real_clock_sleeps_to_deadlines():
    c = SimClock(0.002)
    ticks = [c.advance() for _ in range(3)]
    assert c.lockstep and [k.index for k in ticks] == [0, 1, 2] and ticks[2].t == pytest.approx(0.004)
    now = [10.0]
    slept = []

    def sleep(d):
        slept.append(d)
        now[0] += d

    rc = RealClock(0.004, monotonic=lambda: now[0], sleep=sleep)
    rc.advance()
    now[0] += 0.001  # the loop computes for 1 ms
    rc.advance()
    assert slept == [pytest.approx(0.003)]
    now[0] += 0.010  # a 10 ms hiccup: the next deadline has passed
    rc.advance()
    assert rc.overruns.count == 1 and rc.overruns.worst == pytest.approx(0.006)
    assert not rc.lockstep and RealClock(0.002, lockstep=True).lockstep


def test_detector_settles_on_a_decaying_swing_and_times_out_on_a_sustained_one():
    dt = 0.1
    det = EquilibriumDetector(dt, DetectorConfig.for_robot(load_robot("irma4u"), timeout=20.0))
    det.start(0.0)
    rng = np.random.default_rng(1)
    settled_at = None
    for k in range(1, 400):
        t = k * dt
        swing = math.exp(-t / 1.5) * math.sin(2 * math.pi * 0.7 * t)
        tau = 100.0 + 5.0 * swing + 0.05 * rng.standard_normal(4)
        dl = 0.01 * swing + 2e-5 * rng.standard_normal(4)
        st = det.push(t, tau, dl, np.zeros(4), math.radians(1.0) * swing, 0.0)
        if st.settled:
            settled_at = t
            break
    # the thresholds learnt from the swing itself (3.2 mm length range over 0.5 s when the 1 s rule settled at
    # about 4 s): the span is still from about 2.7 s (a 1.6 mm swing), then settle_s (3 s) more plus the span, whose
    # samples the ends test finds at rest (issue 29's hold-time rule; a window's length of 1 s settled at
    # 3.5-5 s); by then half the history rests and the length range is back at its 2 mm floor
    assert settled_at is not None and 5.5 < settled_at < 7.0
    assert det.stillness.thresholds["length"] == pytest.approx(2e-3)
    det.start(100.0)
    for k in range(1, 300):
        t = 100.0 + k * dt
        st = det.push(t, np.full(4, 100.0), np.full(4, 3e-3 * math.sin(2 * math.pi * 0.5 * t)), np.zeros(4), 0.0, 0.0)
        if st.timed_out:
            break
    assert st.timed_out and not st.settled and st.elapsed == pytest.approx(20.1)
    assert st.scores[0] > 1.0 and st.scores[1] == 0.0  # a 6 mm range over the span, no tension ripple


def hold_on_the_simulator(config: ControllerConfig, ea: float, noise: float, hold: float = 20.0, seed: int = 0):
    """The simulated prototype's physics (sim_backend/examples/settling_sway.yaml: winches with a stick phase,
    wobble, sway; cable stiffness ``ea`` N) under the tension controller with the drives' two-tick delay and
    ``noise`` N of load-cell noise per tick: a 40 N/s move of the platform by (5, 3, 6) cm, then ``hold`` s at
    fixed references. Returns per tick: time after the move (s), true tension error (n,) N, all winches stuck,
    platform position (3,) m."""
    import dataclasses

    from calib.statics import tension_model
    from sim_backend.backend import power_on_state
    from sim_backend.config import example_path, load_sim_config
    from sim_backend.physics import CablePhysics, Sway

    robot = load_robot("irma4u")
    sim = load_sim_config(example_path("settling_sway"), robot.n)
    physics = CablePhysics(robot, dataclasses.replace(sim.physics_params(robot), ea=ea), sim.true_transmission(robot),
                           *power_on_state(robot, seed), brakes=False,
                           sway=Sway(sim.sway.amplitude, sim.sway.period, seed))
    pose0, tau0 = power_on_state(robot, seed)
    tau1 = tension_model(robot, pose0 + np.r_[0.05, 0.03, 0.06, 0, 0, 0], derivatives=False).tau[0]
    ctl = TensionController(transmission_radius(robot), config)
    ctl.reset(tau0)
    rng = np.random.default_rng(seed)
    dt, move = config.period, float(np.abs(tau1 - tau0).max() / 40.0)
    reading, pending = physics.cable_tension(), ctl.torque_for(tau0)
    t, err, stuck, pos = [], [], [], []
    for k in range(int(round((move + hold) / dt))):
        ref = tau0 + (tau1 - tau0) * min(k * dt / move, 1.0)
        meas = reading + noise * rng.standard_normal(robot.n)  # read at this SYNC, answered at the next
        reading = physics.cable_tension()
        for i, torque in enumerate(pending):
            physics.set_motor_torque(i, float(torque))
        pending = ctl.update(ref, meas, dt)
        physics.step(dt, t_end=(k + 1) * dt)
        t.append((k + 1) * dt - move)
        err.append(ref - physics.cable_tension())
        stuck.append(not physics.motor_velocity().any())  # a stuck winch stands exactly still
        pos.append(physics.pose()[:3])
    return np.array(t), np.array(err), np.array(stuck), np.array(pos)


def test_a_held_platform_rests_with_winch_friction_and_noisy_load_cells():
    """Issue 29: 1 N of load-cell noise per tick against winches whose friction holds them still. With the
    dead band on the raw reading (and the integral holding what it learnt against the sliding friction) the
    winches kept breaking free and sticking elsewhere: the platform wandered millimetres through the hold.
    The dead band on a 0.1 s low-passed reading and the leak inside it let the winches stick for good."""
    cfg = ControllerConfig(rate=200.0)
    t, _, stuck, pos = hold_on_the_simulator(cfg, ea=1e12, noise=1.0)
    late = t > 8.0
    assert stuck[late].all()
    assert np.ptp(pos[late], axis=0).max() < 2e-5  # m: at rest (the sway's push on stuck winches)
    t, _, stuck, pos = hold_on_the_simulator(
        ControllerConfig(rate=200.0, integral_filter=0.0, integral_leak=0.0), ea=1e12, noise=1.0)
    assert stuck[t > 8.0].mean() < 0.8 and np.ptp(pos[t > 8.0], axis=0).max() > 5e-4


@pytest.mark.parametrize("ea", [1e4, 2e6])
def test_the_loop_with_its_hold_filter_tracks_and_settles_from_soft_to_nominal_cables(ea):
    """The control.py gains' range: a soft cable (EA 10 kN) to the nominal one (2 MN), at 200 and 500 Hz, with
    the two-tick delay. The low-pass only switches the integral (the loop's feedback is the raw reading) and
    the leak is a stable first-order lag: the move is tracked within 2.5 N (as before the filter: 2.2-2.4 N),
    and the hold ends with every winch stuck, the tension error inside the dead band and steady."""
    for rate in (200.0, 500.0):
        t, err, stuck, _ = hold_on_the_simulator(ControllerConfig(rate=rate), ea=ea, noise=0.0, hold=8.0)
        assert np.abs(err[t < 0]).max() < 2.5
        assert np.abs(err[t > 3.0]).max() < 1.5  # N
        assert stuck[t > 7.0].all() and err[t > 7.0].std(axis=0).max() < 0.02
