"""The robot model: descriptions, inverse kinematics, statics, Jacobians, equilibria, planning."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.io as sio
import yaml

from acquisition.cli import main as cli_main
from calib.equilibrium import direct_statics, inverse_geometrico_static, stability
from calib.kinematics import (
    cable_direction_jacobian,
    inverse_kinematics,
    kinematic_jacobians,
    rotation,
    rotation_to_euler,
)
from calib.planning import kinematic_path, order_setpoints, plan_poses, transition_costs
from calib.robot import RobotDescriptionError, builtin_robot_yaml, load_robot, robot_from_dict
from calib.statics import equilibrium_residual, structure_matrix, tension_model, wrench_residual
from calib.workspace import static_workspace


@pytest.fixture(scope="module")
def robot():
    return load_robot("irma4u")


@pytest.fixture(scope="module")
def authors_targets(irma_data):
    out = sio.loadmat(irma_data / "sc_control_target_8_final.mat", squeeze_me=True, struct_as_record=False)["out"]
    return out.opt_meas_config.T, out.static_tensions.T


def random_poses(robot, k, seed=0, spread=0.05):
    """Random poses of the static workspace: equilibrium orientations at random positions in the bounds,
    perturbed by up to ``spread`` rad (the solver's poses lie near equilibria)."""
    rng = np.random.default_rng(seed)
    lo, hi = robot.workspace_lower, robot.workspace_upper
    eq = inverse_geometrico_static(robot, rng.uniform(lo, hi, (k, 3)))
    return eq.poses + np.c_[np.zeros((k, 3)), rng.uniform(-spread, spread, (k, 3))]


# ---- descriptions -------------------------------------------------------------------------------------------


def test_builtin_irma4u_matches_table_1(robot):
    assert robot.n == 4
    np.testing.assert_allclose(robot.d[0], [1.065, -1.155, 1.839])
    np.testing.assert_allclose(robot.d[2], [-1.066, 1.155, 1.839])
    np.testing.assert_allclose(robot.a_local[3], [-0.075, -0.075, 0.266])
    np.testing.assert_allclose(robot.frames[2], [[0, 0, -1], [0, -1, 0], [-1, 0, 0]])
    assert robot.mass == 12.992 and robot.com[2] == 0.173 and robot.r[1] == 0.03
    assert robot.orientation == "xyz" and robot.controlled == (0, 1, 2, 5)
    np.testing.assert_allclose([robot.noise.tension, robot.noise.length], [10.0, 0.01])
    np.testing.assert_allclose(np.degrees([robot.noise.swivel, robot.noise.orientation]), [1.0, 2.0])
    np.testing.assert_allclose(robot.workspace_lower, [-0.4, -0.4, 0.6])
    assert robot.sensors.load_cell_uncertainty == pytest.approx(0.1962)


def test_irma4u_pulley_conventions_reproduce_the_authors_homing_readings(robot):
    """Table I's pulley frames, radius and swivel sign, checked against the lab's own numbers: the homing
    cable lengths and swivel angles of the data README are the authors' rigid inverse kinematics of the
    design homing pose [0, 0, -0.119, 0, 0, 0]; the description reproduces them to the last digit, so every
    swivel angle has the authors' sign and zero (pulleys 1 and 3 positive, 2 and 4 negative)."""
    from acquisition.importers import IRMA_HOMING_LENGTHS, IRMA_HOMING_SWIVELS

    kin = inverse_kinematics(robot, np.array([[0.0, 0.0, -0.119, 0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(kin.lengths[0], IRMA_HOMING_LENGTHS, atol=1e-12)
    np.testing.assert_allclose(kin.swivel[0], IRMA_HOMING_SWIVELS, atol=1e-12)
    r2 = robot.replace(r=robot.r * 2)  # eq. 2: the swivel angle does not depend on the pulley radius
    np.testing.assert_allclose(inverse_kinematics(r2, kin.poses).swivel, kin.swivel, atol=1e-15)


def test_reelax8_has_eight_straight_cables():
    r8 = load_robot("reelax8")
    assert r8.n == 8 and not r8.has_pulleys
    np.testing.assert_allclose(r8.a_local[0], [-0.111, 0.346, -0.016])
    # straight cables: the length is the anchor distance
    z = np.array([[0.0, 0.0, -1.5, 0.05, -0.02, 0.1]])
    kin = inverse_kinematics(r8, z)
    direct = np.linalg.norm(z[0, :3, None] + rotation(z[:, 3:])[0] @ r8.a_local.T - r8.d.T, axis=0)
    np.testing.assert_allclose(kin.lengths[0], direct, rtol=1e-12)


def test_description_round_trips_through_yaml(robot):
    again = robot_from_dict(yaml.safe_load(yaml.safe_dump(robot.to_dict())), "round-trip")
    for field in ("d", "frames", "r", "a_local", "com", "inertia", "tau0", "workspace_lower"):
        np.testing.assert_allclose(getattr(again, field), getattr(robot, field), rtol=1e-12)
    assert again.noise == robot.noise and again.controlled == robot.controlled


@pytest.mark.parametrize(
    "mutate, words",
    [
        (lambda d: d["platform"].__setitem__("mass", -3), ["platform.mass", "-3", "positive"]),
        (lambda d: d["cables"][1].__setitem__("pulley_point", [1, 2]), ["cables[1].pulley_point", "3 numbers"]),
        (lambda d: d.__setitem__("orientation", "xzy"), ["orientation", "xzy"]),
        (lambda d: d["cables"][0]["frame"].__setitem__("x", [1, 1, 0]), ["cables[0].frame", "orthonormal"]),
        (lambda d: d["tensions"].__setitem__("max", 5), ["tensions.max", "5"]),
        (lambda d: d.pop("platform"), ["platform", "missing"]),
    ],
)
def test_bad_description_names_file_field_and_value(tmp_path, mutate, words):
    data = yaml.safe_load(builtin_robot_yaml("irma4u"))
    mutate(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(RobotDescriptionError) as err:
        load_robot(str(path))
    msg = str(err.value)
    assert str(path) in msg and msg.count("\n") == 0
    for w in words:
        assert w in msg


# ---- statics at the authors' poses (issue 2, done-when 1) ---------------------------------------------------


def test_authors_ideal_poses_are_equilibria(robot, authors_targets):
    poses, tensions = authors_targets
    res = wrench_residual(robot, poses, tensions)
    assert np.abs(res).max() <= 1e-3  # N and N m
    # and the equilibrium is not trivially satisfied: a 1 N change on one cable breaks it
    bumped = tensions.copy()
    bumped[:, 0] += 1.0
    assert np.abs(wrench_residual(robot, poses, bumped)).max() > 0.5


def test_tension_model_returns_the_setpoints(robot, authors_targets):
    poses, tensions = authors_targets
    tm = tension_model(robot, poses)
    assert np.abs(tm.tau - tensions).max() <= 0.01


def test_zyx_convention_is_a_different_model(robot, authors_targets):
    poses, tensions = authors_targets
    r_zyx = robot.replace(orientation="zyx")
    # the authors' poses are equilibria only in their own (xyz) convention
    assert np.abs(wrench_residual(r_zyx, poses, tensions)).max() > 0.05


def test_rotation_conventions_invert():
    rng = np.random.default_rng(3)
    e = rng.uniform(-1.2, 1.2, (200, 3))
    for conv in ("xyz", "zyx"):
        R = rotation(e, conv)
        np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
        np.testing.assert_allclose(rotation_to_euler(R, conv), e, atol=1e-10)
    # xyz: R = Rx Ry Rz, checked on a single axis rotation each
    np.testing.assert_allclose(rotation([[0, 0, np.pi / 2]])[0] @ [1, 0, 0], [0, 1, 0], atol=1e-12)


# ---- Jacobians against central finite differences (issue 2, done-when 2) ------------------------------------


def _central(f, z, h):
    cols = []
    for j in range(6):
        dz = np.zeros(6)
        dz[j] = h
        cols.append((f(z + dz) - f(z - dz)) / (2 * h))
    return np.stack(cols, -1)


def _rel_err(analytic, numeric):
    # relative to the largest entry of each (pose, cable) row of the Jacobian
    scale = np.abs(analytic).max(axis=-1, keepdims=True)
    return (np.abs(analytic - numeric) / np.maximum(scale, 1e-12)).max()


@pytest.mark.parametrize("orientation", ["xyz", "zyx"])
def test_jacobians_match_finite_differences(robot, orientation):
    r = robot.replace(orientation=orientation)
    z = random_poses(r, 1000, seed=11)
    kin = inverse_kinematics(r, z)
    jac = kinematic_jacobians(r, kin)
    h = 1e-6
    checks = {
        "lengths": (lambda x: inverse_kinematics(r, x).lengths, jac.lengths),
        "swivel": (lambda x: inverse_kinematics(r, x).swivel, jac.swivel),
        "psi": (lambda x: inverse_kinematics(r, x).psi, jac.psi),
        "tension": (lambda x: tension_model(r, x, derivatives=False).tau, tension_model(r, z).jacobian),
    }
    for name, (f, a) in checks.items():
        err = _rel_err(a, _central(f, z, h))
        assert err <= 1e-6, f"{name}: relative error {err:.2e}"
    dt = cable_direction_jacobian(r, kin, jac)
    num = _central(lambda x: inverse_kinematics(r, x).t, z, h)
    assert _rel_err(dt, num) <= 1e-6
    tau = tension_model(r, z, derivatives=False).tau
    _, je = equilibrium_residual(r, z, tau)
    num = _central(lambda x: equilibrium_residual(r, x, tau, derivatives=False)[0], z, h)
    assert _rel_err(je, num) <= 1e-6


def test_length_gradient_is_the_cable_direction(robot):
    # dl/dp = t: moving the platform along a cable's direction lengthens it one for one
    z = random_poses(robot, 50, seed=2)
    kin = inverse_kinematics(robot, z)
    jac = kinematic_jacobians(robot, kin)
    np.testing.assert_allclose(jac.lengths[..., :3], kin.t, atol=1e-12)
    xi = structure_matrix(kin)
    np.testing.assert_allclose(xi[:, :3, :], np.swapaxes(kin.t, 1, 2))


# ---- direct statics, inverse geometrico-static, stability --------------------------------------------------


def test_direct_statics_recovers_the_ideal_poses(robot, authors_targets):
    poses, tensions = authors_targets
    res = direct_statics(robot, tensions)
    assert res.converged.all()
    assert np.abs(res.poses[:, :3] - poses[:, :3]).max() < 1e-4
    assert np.abs(res.poses[:, 3:] - poses[:, 3:]).max() < 1e-4


def test_direct_statics_inverts_the_tension_model(robot):
    z = random_poses(robot, 200, seed=5)
    tau = tension_model(robot, z, derivatives=False).tau
    # generic poses are not equilibria of tau(z) (only 4 of 6 equations are used); their equilibria are
    eq = direct_statics(robot, tau)
    ok = eq.converged
    assert ok.mean() > 0.9
    assert np.abs(wrench_residual(robot, eq.poses[ok], tau[ok])).max() < 1e-5


def test_inverse_geometrico_static_and_stability(robot):
    sp = inverse_geometrico_static(robot, [[0.2, -0.1, 0.9], [0.0, 0.0, 1.0]])
    assert sp.feasible.all()
    assert np.abs(wrench_residual(robot, sp.poses, sp.tensions)).max() < 1e-5
    # a suspended platform hanging from its 4 cables is stable; flipped upside down it is not
    assert (stability(robot, sp.poses, sp.tensions) > 0).all()
    flipped = sp.poses.copy()
    flipped[:, 3] += np.pi
    assert (stability(robot, flipped, sp.tensions) < 0).any()


def test_planned_grid_2_is_eight_stable_corner_equilibria(robot):
    plan = plan_poses(robot, 2)
    assert plan.poses.shape == (8, 6) and plan.setpoints.shape == (8, 4)
    corners = {tuple(np.round(p, 6)) for p in plan.poses[:, :3]}
    lo, hi = robot.workspace_lower, robot.workspace_upper
    expected = {(x, y, z) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])}
    assert corners == {tuple(np.round(c, 6)) for c in expected}
    assert np.abs(wrench_residual(robot, plan.poses, plan.setpoints)).max() < 1e-5
    assert (stability(robot, plan.poses, plan.setpoints) > 0).all()
    assert plan.setpoints.min() >= robot.tau_min and plan.setpoints.max() <= robot.tau_max


def test_visiting_order_is_optimal_for_grid_2(robot):
    plan = plan_poses(robot, 2)
    cost = transition_costs(np.vstack([plan.tau0, plan.setpoints]))
    tour = [0, *range(1, 9), 0]
    total = sum(cost[a, b] for a, b in zip(tour[:-1], tour[1:], strict=True))
    assert total == pytest.approx(plan.transition_cost)
    # no other order is cheaper (brute force over the 8! tours is 40320: check a random sample of them)
    rng = np.random.default_rng(0)
    for _ in range(2000):
        perm = [0, *(rng.permutation(8) + 1), 0]
        assert sum(cost[a, b] for a, b in zip(perm[:-1], perm[1:], strict=True)) >= total - 1e-9
    order, heur_cost = order_setpoints(plan.tau0, plan.setpoints)
    assert heur_cost == pytest.approx(total)


def test_grid_3_gives_27_poses(robot):
    plan = plan_poses(robot, 3)
    assert plan.poses.shape == (27, 6)
    assert len({tuple(np.round(p, 6)) for p in plan.poses[:, :3]}) == 27


def test_kinematic_path_is_a_chain_of_equilibria(robot):
    path = kinematic_path(robot, 2, speed=0.05)
    assert np.abs(wrench_residual(robot, path.poses, path.tensions)).max() < 1e-5
    steps = np.linalg.norm(np.diff(path.poses[:, :3], axis=0), axis=1)
    assert steps.max() <= 0.05 + 1e-9
    np.testing.assert_allclose(np.diff(path.times), steps / 0.05)


def test_static_workspace_contains_the_calibration_box(robot):
    ws = static_workspace(robot, lower=[-0.6, -0.6, 0.4], upper=[0.6, 0.6, 1.4], step=0.2)
    inside = np.all((ws.positions >= robot.workspace_lower - 1e-9) & (ws.positions <= robot.workspace_upper + 1e-9), 1)
    assert ws.member[inside].all()
    assert not ws.member.all()  # the top corners need more than tensions.max
    assert ws.boundary.sum() > 0 and not (ws.boundary & ~ws.member).any()


def test_cli_poses_json(capsys):
    assert cli_main(["poses", "--grid", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["poses"]) == 8 and len(out["setpoints"]) == 8 and len(out["setpoints"][0]) == 4


def test_cli_robot_show(capsys):
    assert cli_main(["robot", "show"]) == 0
    data = yaml.safe_load(capsys.readouterr().out)
    assert data["name"] == "irma4u" and len(data["cables"]) == 4
    assert cli_main(["robot", "show", "nope"]) == 2
    assert "no built-in robot named 'nope'" in capsys.readouterr().err
