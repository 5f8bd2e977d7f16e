"""Hidden effects of the simulated prototype: the model-vs-truth difference has the predicted sign and size.

The physics-level effects are checked here (the sensor-level ones, tension_offset, tension_gain and
ahrs_mounting, are checked through the emulated devices and the real drivers in test_sim_backend.py).
The predictions are first-order formulas written independently of the simulator's code.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from calib.equilibrium import direct_statics
from calib.kinematics import inverse_kinematics
from calib.robot import load_robot
from calib.statics import tension_model
from sim_backend.config import SimConfig, SimConfigError, sim_config_from_dict
from sim_backend.physics import CablePhysics, WinchParams

ROBOT = load_robot("irma4u")
TAU_A = np.array([100.0, 100.0, 100.0, 100.0])
TAU_B = np.array([118.48, 170.83, 115.57, 82.98])
DT = 0.005
POSE_A = direct_statics(ROBOT, TAU_A).poses[0]


def _config(effects: dict, physics: dict | None = None) -> SimConfig:
    return sim_config_from_dict({"effects": effects, "physics": physics or {}}, 4, "<test>")


def _physics(cfg: SimConfig, pose=POSE_A, tau=TAU_A, brakes=True) -> CablePhysics:
    return CablePhysics(cfg.true_robot(ROBOT), cfg.physics_params(), cfg.true_transmission(ROBOT), pose, tau, brakes)


def _settle(ph: CablePhysics, seconds: float) -> None:
    for _ in range(int(seconds / DT)):
        ph.step(DT)


def _locked_settle(cfg: SimConfig) -> CablePhysics:
    """Start at the MODEL's equilibrium with the winches braked; the true platform settles elsewhere."""
    ph = _physics(cfg)
    _settle(ph, 20.0)
    return ph


def _tension_step(cfg: SimConfig) -> tuple[CablePhysics, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Constant motor torques tau |k_true| from tau_a to tau_b (no Coulomb friction): exact static tensions.

    Returns the physics, the motor angle change, the true geometric length change, lengths at a and b."""
    ph = _physics(cfg, brakes=False)
    k = cfg.true_transmission(ROBOT)
    _settle(ph, 2.0)
    th_a, len_a = ph.motor_position(), ph.cable_lengths()
    for i in range(4):
        ph.set_motor_torque(i, TAU_B[i] * abs(k[i]))
    _settle(ph, 40.0)
    np.testing.assert_allclose(ph.cable_tension(), TAU_B, atol=0.05)
    len_b = ph.cable_lengths()
    return ph, ph.motor_position() - th_a, len_b - len_a, len_a, len_b


NO_COULOMB = {"winch": {"coulomb": 0.0, "viscous": WinchParams().viscous}}


def test_cable_elasticity_motor_length_lags_geometry_by_tau_l_over_ea():
    ea = 20000.0
    cfg = _config({"cable_elasticity": {"EA": ea}}, NO_COULOMB)
    _, dth, dlen, len_a, len_b = _tension_step(cfg)
    k_nominal = np.asarray(ROBOT.sensors.length_per_motor_rev) / (2 * math.pi)
    motor_dl = k_nominal * dth  # what the drives report as cable-length change
    predicted = (TAU_B * len_b / (1 + TAU_B / ea) - TAU_A * len_a / (1 + TAU_A / ea)) / ea  # stretch change
    diff = dlen - motor_dl
    assert np.all(np.sign(diff) == np.sign(predicted))
    np.testing.assert_allclose(diff, predicted, rtol=0.02, atol=2e-5)
    assert np.abs(predicted).max() > 1e-3  # millimetres: a visible effect
    # the nominal cable (EA 2e6 N) stays below a tenth of a millimetre
    _, dth0, dlen0, _, _ = _tension_step(_config({}, NO_COULOMB))
    assert np.abs(dlen0 - k_nominal * dth0).max() < 1e-4


def test_length_scale_motor_length_is_one_plus_k_times_the_true_change():
    scale = np.array([0.02, -0.01, 0.0, 0.015])
    cfg = _config({"length_scale": {"k": scale.tolist()}}, NO_COULOMB)
    _, dth, dlen, _, _ = _tension_step(cfg)
    k_nominal = np.asarray(ROBOT.sensors.length_per_motor_rev) / (2 * math.pi)
    motor_dl = k_nominal * dth
    elastic = (TAU_B - TAU_A) * 2.3 / cfg.physics_params().ea  # < 0.1 mm, allowed for in the tolerance
    np.testing.assert_allclose(motor_dl, dlen * (1 + scale), atol=np.abs(elastic).max() + 2e-5)
    assert np.abs(dlen).max() > 0.05  # the step moved the cables by centimetres
    assert np.abs(motor_dl - dlen)[0] > 1e-3 and np.abs(motor_dl - dlen)[2] < 1e-4


def test_mass_scale_scales_the_equilibrium_tensions():
    cfg = _config({"mass_scale": {"scale": 0.05}})
    ph = _locked_settle(cfg)
    model = tension_model(ROBOT, ph.pose(), derivatives=False).tau[0]
    np.testing.assert_allclose(ph.cable_tension(), 1.05 * model, rtol=1e-3)


def test_com_offset_shifts_the_tensions_by_the_moment_of_the_weight():
    offset = np.array([0.01, -0.005, 0.03])
    cfg = _config({"com_offset": {"offset": offset.tolist()}})
    ph = _locked_settle(cfg)
    pose = ph.pose()
    nominal = tension_model(ROBOT, pose, derivatives=False).tau[0]
    # first-order prediction: the tension model's sensitivity to the centre of mass, by finite differences
    pred = np.zeros(4)
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1e-4
        shifted = ROBOT.replace(com=ROBOT.com + e)
        pred += (tension_model(shifted, pose, derivatives=False).tau[0] - nominal) / 1e-4 * offset[j]
    diff = ph.cable_tension() - nominal
    assert np.abs(pred).max() > 0.5
    np.testing.assert_allclose(diff, pred, atol=0.05 * np.abs(pred).max())


def test_pulley_position_changes_lengths_by_minus_t_dot_offset_and_swivels_by_w_dot_offset():
    offs = np.array([[0.01, 0.0, 0.0], [0.0, -0.01, 0.005], [0.0, 0.0, 0.0], [-0.005, 0.005, 0.0]])
    cfg = _config({"pulley_position": {"offset": offs.tolist()}})
    ph = _locked_settle(cfg)
    kin = inverse_kinematics(ROBOT, ph.pose())  # the model at the true pose
    pred_len = -np.einsum("na,na->n", kin.t[0], offs)
    pred_sw = -np.einsum("na,na->n", kin.w[0], offs) / kin.rho_u[0]
    np.testing.assert_allclose(ph.cable_lengths() - kin.lengths[0], pred_len, atol=2e-4)
    np.testing.assert_allclose(ph.swivel_angle() - kin.swivel[0], pred_sw, atol=2e-4)
    assert np.abs(pred_len).max() > 5e-3 and np.abs(pred_sw).max() > 2e-3


def test_pulley_radius_lengthens_cables_by_pi_minus_psi_minus_t_dot_u():
    delta = 0.005
    cfg = _config({"pulley_radius": {"delta": delta}})
    ph = _locked_settle(cfg)
    kin = inverse_kinematics(ROBOT, ph.pose())
    pred = delta * (np.pi - kin.psi[0] - np.einsum("na,na->n", kin.t[0], kin.u[0]))
    np.testing.assert_allclose(ph.cable_lengths() - kin.lengths[0], pred, rtol=0.05)
    np.testing.assert_allclose(ph.swivel_angle(), kin.swivel[0], atol=1e-12)  # swivels do not see the radius
    assert np.all(pred > 1e-3)


def test_cable_sag_loads_the_cells_with_the_cable_weight():
    density = 0.08
    cfg = _config({"cable_sag": {"density": density}})
    ph = _locked_settle(cfg)
    pose = ph.pose()
    kin = inverse_kinematics(ROBOT, pose)
    model = tension_model(ROBOT, pose, derivatives=False).tau[0]
    w = density * ROBOT.gravity
    lc = kin.rho_norm[0]
    dz = -kin.rho[0, :, 2]  # height of the pulley exit above the anchor
    cells = ph.cable_tension()
    assert np.all(cells > model + 0.5 * w * dz)  # heavier than the rigid model says, at every cell
    # vertical balance: the chord tensions hold the platform and half of every cable's weight
    chord = cells - 0.5 * w * dz
    lifted = np.sum((chord - model) * -kin.t[0, :, 2])
    assert lifted == pytest.approx(0.5 * w * lc.sum(), rel=0.03)
    assert np.all(ph.cable_lengths() > kin.lengths[0])  # the sagging path is longer than the chord


def test_validation_errors_name_file_field_and_value():
    with pytest.raises(SimConfigError, match=r"<test>: field 'effects.mass_scale.scale' = 2 must be <= 0.5"):
        sim_config_from_dict({"effects": {"mass_scale": {"scale": 2}}}, 4, "<test>")
    with pytest.raises(SimConfigError, match=r"field 'effects.cable_stretch' = .* is not one of cable_elasticity"):
        sim_config_from_dict({"effects": {"cable_stretch": {"EA": 1}}}, 4, "<test>")
    with pytest.raises(SimConfigError, match=r"field 'effects.length_scale.k' = \[0.1\] must be a list of 4"):
        sim_config_from_dict({"effects": {"length_scale": {"k": [0.1]}}}, 4, "<test>")
    with pytest.raises(SimConfigError, match=r"field 'faults\[0\].drive' = 5 must be an integer from 1 to 4"):
        sim_config_from_dict({"faults": [{"kind": "drive_fault", "t": 1.0, "drive": 5}]}, 4, "<test>")
    with pytest.raises(SimConfigError, match=r"field 'faults\[0\].kind' = 'meltdown' is not one of"):
        sim_config_from_dict({"faults": [{"kind": "meltdown", "t": 1.0}]}, 4, "<test>")
    with pytest.raises(SimConfigError, match=r"required field 'faults\[0\].t' is missing"):
        sim_config_from_dict({"faults": [{"kind": "loadcell_disconnected"}]}, 4, "<test>")
    with pytest.raises(SimConfigError, match=r"<test>: field 'effects.pulley_friction.mu' = -0.1 must be >= 0"):
        sim_config_from_dict({"effects": {"pulley_friction": {"mu": -0.1}}}, 4, "<test>")
    with pytest.raises(SimConfigError, match=r"field 'effects.loadcell_hysteresis.h' = 'big' must be a finite"):
        sim_config_from_dict({"effects": {"loadcell_hysteresis": {"h": "big"}}}, 4, "<test>")
    with pytest.raises(SimConfigError, match=r"required field 'effects.loadcell_hysteresis.h' is missing"):
        sim_config_from_dict({"effects": {"loadcell_hysteresis": {}}}, 4, "<test>")
    with pytest.raises(SimConfigError, match=r"field 'physics.ea' = -1 must be > 0"):
        sim_config_from_dict({"physics": {"ea": -1}}, 4, "<test>")
    with pytest.raises(SimConfigError, match=r"field 'physics.winch.drum_radius' = 0.0 must be > 0"):
        sim_config_from_dict({"physics": {"winch": {"drum_radius": 0}}}, 4, "<test>")


def test_every_shipped_example_loads_and_nominal_changes_nothing(tmp_path):
    from sim_backend.config import SensorNoise, example_names, example_path, load_sim_config

    names = example_names()
    assert {"nominal", "cable_sag", "fault_drive_fault"} <= set(names)
    for name in names:
        cfg = load_sim_config(example_path(name))
        if name.startswith("fault_"):
            assert len(cfg.faults) == 1 and cfg.faults[0].kind == name[6:]
        elif name in ("noisy_sensors", "realistic_noise"):  # the sensors' noise and a sway, no hidden effect
            assert cfg.effects.active() == [] and cfg.sensors != SensorNoise() and cfg.sway.amplitude > 0
        elif name.startswith("rigid"):  # no effect at all: cables as stiff as the rigid model's (issue 17)
            assert cfg.effects.active() == [] and cfg.physics_params().ea >= 1e12
            assert (cfg.sway is not None) == (name == "rigid_sway")
        elif name == "settling_sway":  # rigid, a wobble and a sway, no effect (issue 29)
            assert cfg.effects.active() == [] and cfg.physics_params().ea >= 1e12
            assert cfg.wobble > 0 and cfg.sway.amplitude > 0
            assert cfg.physics_params(ROBOT).linear_damping < cfg.physics_params().linear_damping
        elif name != "nominal":
            assert cfg.effects.active() == [name]
    nominal = load_sim_config(example_path("nominal"))
    assert nominal.true_robot(ROBOT) is ROBOT and nominal.effects.active() == []
    bad = tmp_path / "bad.yaml"
    bad.write_text("effects: [1, 2\n")
    with pytest.raises(SimConfigError, match="bad.yaml: not valid YAML"):
        load_sim_config(bad)


def test_a_push_at_the_centre_of_mass_displaces_the_equilibrium_as_the_statics_say():
    """sim_backend.equilibrium_rows.force_displacement (the sway of the row-level simulator) against the exact
    statics: a downward push of 0.1 N is a platform 10 g heavier (direct statics), to 1e-6 m."""
    import dataclasses

    from calib.planning import plan_poses
    from sim_backend.equilibrium_rows import force_displacement

    robot = load_robot("irma4u")
    plan = plan_poses(robot, 2)
    Z = direct_statics(robot, plan.setpoints, plan.poses).poses
    heavier = direct_statics(dataclasses.replace(robot, mass=robot.mass + 0.01), plan.setpoints, Z).poses
    force = np.zeros((Z.shape[0], 3))
    force[:, 2] = -0.01 * robot.gravity
    d = force_displacement(robot, Z, plan.setpoints, force)
    assert np.abs(heavier - Z).max() > 1e-3
    assert np.abs(d - (heavier - Z)).max() < 1e-6


def test_row_level_sway_moves_the_kinematic_readings_not_the_tensions():
    from sim_backend.equilibrium_rows import simulated_rows

    robot = load_robot("irma4u")
    still = simulated_rows(robot, sim_config_from_dict({}), seed=4)
    sway = simulated_rows(robot, sim_config_from_dict({"sway": {"amplitude": 0.002, "period": 10.0}}), seed=4)
    assert np.array_equal(still.meas.tau, sway.meas.tau)
    moved = 1e3 * np.abs(sway.poses[:, :2] - still.poses[:, :2])
    assert 0.1 < moved.max() < 6.0  # mm, a 2 mm sway
    assert np.abs(sway.meas.dl - still.meas.dl).max() > 1e-4


def test_pulley_friction_cells_read_the_winch_side_by_the_direction_the_cable_moved():
    """Torque step from TAU_A to TAU_B: the platform side settles at TAU_B; the cells (in the transmission,
    winch side) read 3 % + 1.5 N less on the cables last paid out, as much more on those last reeled in,
    the direction being the rows' (calib.selfcal.approach_directions on the paid-out length, 0.5 mm): the
    platform's swing after the step can make it differ from the net change."""
    from calib.selfcal import approach_directions

    cfg = _config({"pulley_friction": {"mu": 0.03, "f": 1.5}}, NO_COULOMB)
    ph = _physics(cfg, brakes=False)
    k = cfg.true_transmission(ROBOT)
    _settle(ph, 2.0)
    for i in range(4):
        ph.set_motor_torque(i, TAU_B[i] * abs(k[i]))
    paid = []
    for _ in range(int(40.0 / DT)):
        ph.step(DT)
        paid.append(k * ph.motor_position())
    tau = ph.chord_tension()
    np.testing.assert_allclose(tau, TAU_B, atol=0.05)
    a = approach_directions(np.array(paid), np.array([len(paid) - 1]), 5e-4)[0]
    assert set(a) == {-1.0, 1.0}  # both directions occur in this step
    np.testing.assert_allclose(ph.cable_tension(), tau * (1 - 0.03 * a) - 1.5 * a, atol=0.05)


def test_loadcell_hysteresis_reads_low_on_a_rising_load_and_high_on_a_falling_one():
    from sim_backend.loadcell_emulator import LoadCellEmulator

    emu = LoadCellEmulator(-1, np.random.default_rng(0), channels=2, noise_std=0.0, accuracy=0.0, hysteresis=0.2)
    for t in np.linspace(50.0, 100.0, 20):  # channel 1 rises to 100 N, channel 2 falls to 100 N
        emu.measure(np.array([t, 200.0 - t]))
    np.testing.assert_allclose(emu.measure(np.array([100.0, 100.0])), [99.8, 100.2], atol=0.011)


def test_cable_effects_in_the_rows_simulator_match_the_effects_model():
    """simulated_rows with friction, hysteresis and sag: the readings the calib effects predict at the true
    poses and directions, noise and device errors off (so the two implementations check each other)."""
    from calib.effects import EffectModel, make_effects
    from sim_backend.equilibrium_rows import simulated_rows

    cfg = _config({"pulley_friction": {"mu": 0.03, "f": 1.5}, "loadcell_hysteresis": {"h": 0.2},
                   "cable_sag": {"density": 0.06}})
    zero = {"tension": 0.0, "length": 0.0, "swivel": 0.0, "orientation": np.zeros(3)}
    d = simulated_rows(ROBOT, cfg, noise=zero, device_biases=False)
    m = EffectModel(ROBOT, make_effects(["cable_sag", "pulley_friction", "loadcell_hysteresis",
                                         "cable_elasticity"]))
    ea = cfg.physics_params(ROBOT).ea  # the simulator's nominal 2e6 N (irma4u's description gives no EA)
    theta = m.initial_params(d.zeta0, [0.06, 0.03, 1.5, 0.2, 1.0 / ea])
    appr = np.stack([d.meas.approach, d.meas.load_approach], axis=-1)
    p = m.predict(d.poses, theta, ("tension", "length"), None, appr)
    np.testing.assert_allclose(p["tension"].value, d.meas.tau, atol=1e-6)
    # the elasticity effect stretches by the rigid model's tension, the simulator by the chord tension,
    # which also holds the cables' weight (~0.3 N more): 0.4 um
    np.testing.assert_allclose(p["length"].value, d.meas.dl, atol=1e-6)
    ref = m.predict(d.zeta0[None], theta, ("tension",), None,
                    np.stack([d.meas.ref_approach, d.meas.ref_load_approach], axis=-1)[None])
    np.testing.assert_allclose(ref["tension"].value[0], d.meas.ref_tau, atol=1e-6)
    # the friction moved the equilibria: without it the same setpoints give other poses (mm)
    plain = simulated_rows(ROBOT, _config({}), noise=zero, device_biases=False)
    assert np.abs(plain.poses[:, :3] - d.poses[:, :3]).max() > 2e-3
