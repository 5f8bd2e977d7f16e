"""A cable's axial stiffness in the robot description (issue 29, DW2): the measurement model and the
simulator read the same figure, so that a simulated robot stretches its cables only as much as the model
knows (fast: no simulated startup)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.effects import EffectModel
from calib.effects.priors import DeviceAccuracy
from calib.robot import RobotDescriptionError, load_robot, robot_from_dict
from calib.selfcal.model import MeasurementModel
from calib.statics import tension_model
from sim_backend.config import SimConfigError, sim_config_from_dict
from sim_backend.physics import PhysicsParams

RIGID = load_robot("irma4u")
EA = np.array([2.0e4, 3.0e4, 2.5e4, 4.0e4])  # N: soft ropes, so that the stretch is millimetres
POSES = np.array([[0.1, -0.05, 0.9, 0.02, -0.01, 0.03], [-0.1, 0.1, 1.0, -0.02, 0.01, 0.0]])
ZETA0 = np.array([0.0, 0.02, 0.8, 0.01, 0.0, 0.01])


def _elastic(ea=EA):
    data = RIGID.to_dict()
    for c, v in zip(data["cables"], np.broadcast_to(ea, (4,)), strict=True):
        c["axial_stiffness"] = float(v)
    return robot_from_dict(data, "<elastic>")


def test_the_description_reads_writes_and_checks_the_axial_stiffness():
    robot = _elastic()
    np.testing.assert_array_equal(robot.axial_stiffness, EA)
    np.testing.assert_allclose(robot.compliance, 1.0 / EA)
    np.testing.assert_array_equal(robot_from_dict(robot.to_dict()).axial_stiffness, EA)
    assert RIGID.axial_stiffness is None and not np.any(RIGID.compliance)
    data = robot.to_dict()
    data["cables"][2]["axial_stiffness"] = -5.0
    with pytest.raises(RobotDescriptionError, match=r"cables\[2\]\.axial_stiffness' = -5\.0"):
        robot_from_dict(data)


@pytest.mark.parametrize("make", [MeasurementModel, lambda r: EffectModel(r, [DeviceAccuracy()])])
def test_the_model_predicts_the_unstretched_lengths_with_exact_derivatives(make):
    robot = _elastic()
    model, rigid = make(robot), make(RIGID)
    theta = model.initial_params(ZETA0)
    p = model.predict(POSES, theta, ["length"])["length"]
    # the encoders count L / (1 + tau / EA), tau the modelled tension, relative to zeta_0's
    tau, tau0 = (tension_model(robot, z, derivatives=False).tau for z in (POSES, ZETA0[None]))
    L, L0 = (rigid.predict(z, rigid.initial_params(ZETA0), ["length"])["length"].value + rigid.absolute_readings(
        rigid.initial_params(ZETA0))["length"] for z in (POSES, ZETA0[None]))
    np.testing.assert_allclose(p.value, L / (1 + tau / EA) - L0 / (1 + tau0 / EA), atol=1e-12)
    stretch = np.abs(p.value - rigid.predict(POSES, theta, ["length"])["length"].value).max()
    assert 1e-3 < stretch < 2e-2  # millimetres of difference in relative length at tens of kN
    np.testing.assert_allclose(model.absolute_readings(theta)["length"], L0[0] / (1 + tau0[0] / EA), atol=1e-12)
    h = 1e-6
    fd_pose = np.stack([(model.predict(POSES + h * np.eye(6)[j], theta, ["length"])["length"].value - p.value) / h
                        for j in range(6)], -1)
    fd_zeta = np.stack([(model.predict(POSES, theta + h * np.eye(theta.size)[j], ["length"])["length"].value
                         - p.value) / h for j in range(6)], -1)
    np.testing.assert_allclose(p.d_pose, fd_pose, atol=2e-6)
    np.testing.assert_allclose(p.d_theta[..., :6], fd_zeta, atol=2e-6)


def test_the_simulator_takes_the_described_stiffness_unless_told_otherwise():
    plain = sim_config_from_dict({}, 4, "<test>")
    assert plain.physics_params(_elastic(3.0e4)).ea == 3.0e4
    assert plain.physics_params(RIGID).ea == PhysicsParams().ea  # no figure: the simulator's nominal 2e6 N
    assert sim_config_from_dict({"physics": {"ea": 5.0e5}}, 4).physics_params(_elastic(3.0e4)).ea == 5.0e5
    hidden = sim_config_from_dict({"effects": {"cable_elasticity": {"EA": 2.0e4}}}, 4)
    assert hidden.physics_params(_elastic(3.0e4)).ea == 2.0e4  # a hidden effect: what the model does not know
    with pytest.raises(SimConfigError, match="one axial stiffness for every cable"):
        plain.physics_params(_elastic())


def test_simulated_rows_of_an_elastic_robot_are_what_the_model_predicts():
    """The rows simulator at the true equilibria, without noise or device errors: the lengths of a robot
    whose description gives EA = 30 kN are the model's within 1e-9 m, while the rigid model misses them by
    millimetres."""
    from sim_backend.equilibrium_rows import simulated_rows

    robot = _elastic(3.0e4)
    zero = {"tension": 0.0, "length": 0.0, "swivel": 0.0, "orientation": np.zeros(3)}
    d = simulated_rows(robot, sim_config_from_dict({}, 4), noise=zero, device_biases=False)
    theta = MeasurementModel(robot).initial_params(d.zeta0)
    p = MeasurementModel(robot).predict(d.poses, theta, ("length",))["length"]
    np.testing.assert_allclose(p.value, d.meas.dl, atol=1e-9)
    rigid = MeasurementModel(RIGID).predict(d.poses, theta, ("length",))["length"]
    assert np.abs(rigid.value - d.meas.dl).max() > 1e-3


@pytest.mark.parametrize("make", [MeasurementModel, lambda r: EffectModel(r, [DeviceAccuracy()])])
def test_a_held_tension_stretches_the_cable_whatever_the_pose(make):
    """A force-controlled hold keeps the tensions while the platform sways (issue 29): with a held tension the
    encoders count L(pose) / (1 + tau_held / EA), its pose derivative the geometry's alone (finite
    differences), NaN rows keep the statics' tension; Problem hands Measurements.held_tau to the model in
    both its evaluation and its per-row normal equations."""
    from calib.selfcal.problem import Measurements, Problem

    robot = _elastic()
    model, rigid = make(robot), make(RIGID)
    theta = model.initial_params(ZETA0)
    tau = tension_model(robot, POSES, derivatives=False).tau
    held = tau + np.array([[50.0, -80.0, 30.0, 0.0], [np.nan] * 4])  # row 2: the statics' own
    free = model.predict(POSES, theta, ["length", "tension"])
    p = model.predict(POSES, theta, ["length", "tension"], held_tension=held)
    L = rigid.predict(POSES, theta, ["length"])["length"].value + rigid.absolute_readings(theta)["length"]
    L0 = model.absolute_readings(theta)["length"]
    np.testing.assert_allclose(p["length"].value[0], L[0] / (1 + held[0] / EA) - L0, atol=1e-12)
    np.testing.assert_allclose(p["length"].value[1], free["length"].value[1], atol=1e-15)
    assert abs(p["length"].value[0, 1] - free["length"].value[0, 1]) > 1e-4  # 80 N on 30 kN: 0.1 mm and more
    np.testing.assert_allclose(p["tension"].value[0], held[0])
    np.testing.assert_array_equal(p["tension"].d_pose[0], 0.0)
    h = 1e-6
    fd = np.stack([(model.predict(POSES + h * np.eye(6)[j], theta, ["length"], held_tension=held)["length"].value
                    - p["length"].value) / h for j in range(6)], -1)
    np.testing.assert_allclose(p["length"].d_pose, fd, atol=2e-6)
    np.testing.assert_allclose(p["length"].d_pose[0], rigid.predict(POSES, theta, ["length"])["length"].d_pose[0]
                               / (1 + held[0] / EA)[:, None], atol=1e-12)
    n = robot.n
    meas = Measurements(np.full((2, n), np.nan), np.zeros((2, n)), np.zeros((2, n)), np.zeros((2, 3)),
                        np.full(n, np.nan), np.full(2, np.nan), held_tau=held)
    prob = Problem(model, meas, {"tension": np.ones(n), "length": np.full(n, 1e-3), "swivel": np.full(n, 1e-3),
                                 "orientation": np.full(3, 1e-3)})
    (g, r, J, _), = prob.evaluate(theta, POSES).groups
    np.testing.assert_allclose(r[:, g.slices["length"]], 1e3 * p["length"].value, atol=1e-9)
    cost, U, b = prob.pose_normal_equations(theta, POSES[1:], np.array([1]))
    np.testing.assert_allclose(U[0], J[1].T @ J[1], rtol=1e-10)
