"""The effect library: Jacobian columns against finite differences, composition, absent = rigid model,
the physics each effect encodes, and user effects loaded from a file."""

from __future__ import annotations

import numpy as np
import pytest

from calib.effects import (
    BUILTIN,
    EffectLoadError,
    EffectModel,
    Projected,
    available_effects,
    load_effect_file,
    make_effects,
)
from calib.effects.builtin import pulley_gauge_basis
from calib.planning import plan_poses
from calib.robot import load_robot
from calib.selfcal.model import CHANNELS, MeasurementModel

ROBOT = load_robot("irma4u")
POSES = plan_poses(ROBOT, 2).poses[:4]


def _values(model: EffectModel, rng) -> np.ndarray:
    out = []
    for specs in model.specs:
        for s in specs:
            v = 0.6 * s.scale * rng.standard_normal()
            out.append(abs(v) if s.lower >= 0 else v)
    return np.array(out)


def _check_fd(model: EffectModel, theta: np.ndarray, poses: np.ndarray, approach: np.ndarray | None = None
              ) -> None:
    """Analytic d/dtheta and d/dpose against central differences, every channel (relative to the column's
    size, absolute floor for columns that are zero); ``approach`` (k, n, 2) the rows' directions."""
    def predict(z, th, chans):
        return model.predict(z, th, chans, None, approach)

    pred = predict(poses, theta, CHANNELS)
    for c in CHANNELS:
        for j in range(theta.size):
            h = 1e-6 if j < 6 else 1e-6 * max(abs(theta[j]), 1e-2)
            tp, tm = theta.copy(), theta.copy()
            tp[j] += h
            tm[j] -= h
            fd = (predict(poses, tp, (c,))[c].value - predict(poses, tm, (c,))[c].value) / (2 * h)
            an = pred[c].d_theta[..., j]
            floor = 1e-12 * np.abs(pred[c].value).max() / h  # round-off of the differences
            assert np.allclose(an, fd, rtol=2e-4, atol=max(2e-4 * np.abs(fd).max(), floor)), (c, j)
        for j in range(6):
            zp, zm = poses.copy(), poses.copy()
            zp[:, j] += 1e-6
            zm[:, j] -= 1e-6
            fd = (predict(zp, theta, (c,))[c].value - predict(zm, theta, (c,))[c].value) / 2e-6
            an = pred[c].d_pose[..., j]
            assert np.allclose(an, fd, rtol=2e-4, atol=2e-4 * max(np.abs(fd).max(), 1e-3)), (c, "pose", j)


@pytest.mark.parametrize("name", list(BUILTIN))
def test_each_effect_jacobian_matches_finite_differences(name):
    rng = np.random.default_rng(7)
    model = EffectModel(ROBOT, make_effects([name]))
    theta = model.initial_params(POSES[0] + 0.01 * rng.standard_normal(6), _values(model, rng))
    _check_fd(model, theta, POSES)


def test_all_effects_composed_jacobian_matches_finite_differences():
    rng = np.random.default_rng(11)
    model = EffectModel(ROBOT, make_effects(list(BUILTIN)))
    # pulley_position: 12 - 4 gauge modes; then pulley_friction (2), loadcell_hysteresis, cable_sag; then
    # swivel_tilt (2 per pulley), swivel_entry (2 per pulley), swivel_gain, swivel_friction
    assert model.n_params == 6 + 1 + 4 + 4 + 4 + 1 + 2 + 1 + 3 + 1 + 8 + 2 + 1 + 1 + 8 + 8 + 4 + 1
    vals = _values(model, rng)
    # cable_sag's columns leave out rho times the change of the cable weights' tensions with the pulley
    # geometry, swivel_friction's the change of the cable's lever with it (second order, documented): both 0
    # here, their own columns are checked alone
    names = model.param_names[6:]
    for j, name in enumerate(names):
        if name.startswith(("cable_sag.", "swivel_friction.")):
            vals[j] = 0.0
    theta = model.initial_params(POSES[1] + 0.01 * rng.standard_normal(6), vals)
    _check_fd(model, theta, POSES[:3], rng.choice([-1.0, 0.0, 1.0], size=(3, ROBOT.n, 4)))


def test_projected_effect_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    basis = np.array([[1.0, 0.0], [0.0, 1.0], [0.5, -0.5]]) * 0.01
    model = EffectModel(ROBOT, [Projected(BUILTIN["com_offset"](), basis), BUILTIN["ahrs_mounting"]()])
    theta = model.initial_params(POSES[0], np.array([0.3, -0.7, 0.01, -0.02]))
    _check_fd(model, theta, POSES[:3])
    rep = model.report(theta)["com_offset"]
    assert rep["dx"] == pytest.approx(0.003) and rep["dz"] == pytest.approx(0.005)
    del rng


def test_absent_effects_reproduce_the_rigid_model():
    rigid = MeasurementModel(ROBOT)
    model = EffectModel(ROBOT, make_effects(list(BUILTIN)))
    zeta0 = POSES[2] + np.array([0.01, -0.02, 0.01, 0.01, 0.0, 0.02])
    theta = model.initial_params(zeta0)
    a = rigid.predict(POSES, zeta0, CHANNELS)
    b = model.predict(POSES, theta, CHANNELS)
    for c in CHANNELS:
        assert np.allclose(a[c].value, b[c].value, atol=1e-12)
        assert np.allclose(a[c].d_pose, b[c].d_pose, atol=1e-10)
        assert np.allclose(a[c].d_theta, b[c].d_theta[..., :6], atol=1e-10)


def test_effects_change_readings_as_their_physics_says():
    zeta0 = POSES[0]
    rigid = EffectModel(ROBOT, [])
    base = rigid.predict(POSES, zeta0, CHANNELS)
    # cable elasticity: the encoders count L / (1 + tau / EA)
    m = EffectModel(ROBOT, make_effects(["cable_elasticity"]))
    p = m.predict(POSES, m.initial_params(zeta0, [1 / 15000.0]), ("length", "tension"))
    ph = m._physical(m.initial_params(zeta0, [1 / 15000.0]), np.vstack([POSES, zeta0]))[1]
    l0 = ph.L / (1 + ph.tau / 15000.0)
    assert np.allclose(p["length"].value, l0[:-1] - l0[-1])
    assert np.abs(p["length"].value - base["length"].value).max() > 5e-4  # sub-mm to mm at 30-170 N
    # length scale: reading = (1 + k) true change
    m = EffectModel(ROBOT, make_effects(["length_scale"]))
    p = m.predict(POSES, m.initial_params(zeta0, [0.02, 0, -0.01, 0]), ("length",))
    assert np.allclose(p["length"].value, base["length"].value * [1.02, 1, 0.99, 1])
    # load cells: (1 + g) tau + o
    m = EffectModel(ROBOT, make_effects(["tension_gain", "tension_offset"]))
    p = m.predict(POSES, m.initial_params(zeta0, [0.02, 0, 0, 0, 3.0, 0, 0, -1.0]), ("tension",))
    assert np.allclose(p["tension"].value, base["tension"].value * [1.02, 1, 1, 1] + [3.0, 0, 0, -1.0])
    # mass scale: tensions scale with the mass
    m = EffectModel(ROBOT, make_effects(["mass_scale"]))
    p = m.predict(POSES, m.initial_params(zeta0, [0.03]), ("tension",))
    assert np.allclose(p["tension"].value, 1.03 * base["tension"].value)
    # AHRS mounting: a pure roll tilt at a level pose reads as roll
    m = EffectModel(ROBOT, make_effects(["ahrs_mounting"]))
    level = np.array([[0.0, 0.0, 0.9, 0.0, 0.0, 0.0]])
    p = m.predict(level, m.initial_params(zeta0, [0.0175, 0.0]), ("orientation",))
    assert p["orientation"].value[0, 0] == pytest.approx(0.0175, abs=1e-9)


def test_pulley_modes_exclude_the_gauge_motions():
    B = pulley_gauge_basis(ROBOT)
    assert B.shape == (12, 8)
    assert np.allclose(B.T @ B, np.eye(8), atol=1e-12)
    for ax in range(3):
        t = np.zeros((4, 3))
        t[:, ax] = 1.0
        assert np.allclose(B.T @ t.ravel(), 0.0, atol=1e-12)


def test_duplicate_and_unknown_effects_are_refused():
    with pytest.raises(ValueError, match="twice"):
        EffectModel(ROBOT, make_effects(["mass_scale", "mass_scale"]))
    with pytest.raises(EffectLoadError, match="unknown effect 'warp_drive'"):
        make_effects(["warp_drive"])


USER_EFFECT = '''
import numpy as np
from calib.effects import Effect, ParamSpec


class SwivelOffset(Effect):
    """A constant error of each swivel encoder's zero does not show in relative readings; a swivel gain does."""

    name = "swivel_gain"
    order = 25

    def params(self, robot):
        return [ParamSpec("gain", "1", 0.0, -0.5, 0.5, 0.01)]

    def transform(self, ctx, values, preds):
        if "swivel" in preds:
            pr = preds["swivel"]
            base = pr.value.copy()
            pr.value = (1 + values[0]) * pr.value
            pr.d_pose = (1 + values[0]) * pr.d_pose
            pr.d_theta = (1 + values[0]) * pr.d_theta
            pr.d_theta[..., ctx.cols] = base[..., None]
'''


def test_user_effect_from_a_file(tmp_path):
    f = tmp_path / "my_effects.py"
    f.write_text(USER_EFFECT)
    found = load_effect_file(f)
    assert list(found) == ["swivel_gain"]
    avail = available_effects([f])
    assert "swivel_gain" in avail and "cable_elasticity" in avail
    model = EffectModel(ROBOT, make_effects(["swivel_gain", "length_scale"], avail))
    theta = model.initial_params(POSES[0], [0.05, 0.01, 0.0, 0.0, -0.01])
    _check_fd(model, theta, POSES[:2])
    bad = tmp_path / "bad.py"
    bad.write_text("x = 1\n")
    with pytest.raises(EffectLoadError, match="defines no subclass"):
        load_effect_file(bad)
    with pytest.raises(EffectLoadError, match="not found"):
        load_effect_file(tmp_path / "missing.py")


def test_absolute_lengths_are_what_the_encoders_count():
    m = EffectModel(ROBOT, make_effects(["cable_elasticity", "mass_scale"]))
    theta = m.initial_params(POSES[0], [1 / 20000.0, 0.02])
    ph = m._physical(theta, POSES[[0]])[1]
    absolute = m.absolute_readings(theta)
    assert np.allclose(absolute["length"], ph.L[0] / (1 + ph.tau[0] / 20000.0))
    # L tau / EA: 4-10 mm of stretch at 42-92 N on 1.4-2.3 m of cable of 20 kN
    assert np.all(ph.L[0] - absolute["length"] > 0.0035)


def test_device_accuracy_columns_and_its_prior_pseudo_readings():
    """The devices' constant errors compose with the other effects (exact columns), and each of their
    parameters adds one pseudo-reading (theta_j - 0) / sd_j, sd = accuracy / sqrt(3): the degrees of
    freedom of a fit do not change. The AHRS yaw drifts at a rate within the gyro's in-run bias stability
    (8 deg/h): its column is the rows' time."""
    from calib.effects.priors import DeviceAccuracy
    from calib.selfcal.problem import Measurements, Problem

    rng = np.random.default_rng(3)
    model = EffectModel(ROBOT, [*make_effects(["ahrs_mounting", "tension_gain"]), DeviceAccuracy()])
    theta = model.initial_params(POSES[2] + 0.01 * rng.standard_normal(6), _values(model, rng))
    _check_fd(model, theta, POSES)
    idx, mean, sd = model.priors()
    assert idx.tolist() == list(range(12, 19)) and not mean.any()
    np.testing.assert_allclose(sd[:4], 0.0002 * 100 * 9.81 / np.sqrt(3))  # 0.113 N
    np.testing.assert_allclose(sd[4:6], np.radians(0.2) / np.sqrt(3))
    np.testing.assert_allclose(sd[6], np.radians(8.0) / 3600 / np.sqrt(3))  # 2.24e-5 rad/s
    times = np.array([12.0, 30.0, 47.5, 61.0])
    with_t = model.predict(POSES, theta, ("orientation",), times)["orientation"]
    without = model.predict(POSES, theta, ("orientation",))["orientation"]
    np.testing.assert_allclose(with_t.value[:, 2] - without.value[:, 2], theta[18] * times)
    np.testing.assert_allclose(with_t.d_theta[:, 2, 18], times)
    assert not without.d_theta[:, :, 18].any()
    k, n = POSES.shape[0], ROBOT.n
    meas = Measurements(np.full((k, n), 60.0), np.zeros((k, n)), np.zeros((k, n)), np.zeros((k, 3)),
                        np.full(n, 60.0), np.zeros(2))
    sigma = {"tension": 0.1, "length": 1e-4, "swivel": 1e-3, "orientation": np.array([1e-3, 1e-3, 1e-2])}
    with_p, without = Problem(model, meas, sigma), Problem(EffectModel(ROBOT, model.effects[:2]), meas, sigma)
    assert with_p.n_residuals == without.n_residuals + 7
    ev = with_p.evaluate(theta, POSES)
    np.testing.assert_allclose(ev.r0[-7:], theta[12:] / sd)
    np.testing.assert_allclose(ev.g0[-7:, 12:], np.diag(1.0 / sd))
    assert not ev.g0[-7:, :12].any()


def test_yaw_drift_column_is_the_row_time_and_needs_times():
    model = EffectModel(ROBOT, make_effects(["ahrs_mounting", "ahrs_yaw_drift"]))
    theta = model.initial_params(POSES[0], [0.01, -0.005, 2e-4])
    times = np.array([12.0, 30.0, 47.5, 61.0])
    with_t = model.predict(POSES, theta, ("orientation",), times)["orientation"]
    without = model.predict(POSES, theta, ("orientation",))["orientation"]
    np.testing.assert_allclose(with_t.value[:, 2] - without.value[:, 2], 2e-4 * times, atol=1e-15)
    tp, tm = theta.copy(), theta.copy()
    tp[-1] += 1e-7
    tm[-1] -= 1e-7
    fd = (model.predict(POSES, tp, ("orientation",), times)["orientation"].value
          - model.predict(POSES, tm, ("orientation",), times)["orientation"].value) / 2e-7
    np.testing.assert_allclose(with_t.d_theta[..., -1], fd, atol=1e-7)
    np.testing.assert_allclose(with_t.d_theta[:, 2, -1], times)
    assert not without.d_theta[..., -1].any()  # rows without times cannot see a drift
    assert model.report(theta)["ahrs_yaw_drift"]["deg_per_hour"] == pytest.approx(np.degrees(2e-4) * 3600)


@pytest.mark.parametrize("name", ["pulley_friction", "loadcell_hysteresis", "cable_sag", "swivel_friction"])
def test_cable_effects_jacobian_matches_finite_differences_with_directions(name):
    """The issue-17 effects and the swivel friction alone and behind robot and reading effects, the rows'
    directions given (cable motion, load change, swivel turn, the reference's swivel turn)."""
    rng = np.random.default_rng(5)
    approach = rng.choice([-1.0, 1.0], size=(POSES.shape[0], ROBOT.n, 4))
    approach[..., 3] = approach[0, :, 3]  # the reference's direction: one per cable
    for names in ([name], ["mass_scale", "com_offset", name, "cable_elasticity", "tension_gain"]):
        model = EffectModel(ROBOT, make_effects(names))
        vals = _values(model, rng)
        sl = model.slices[names.index(name)]
        vals[sl.start - 6 : sl.stop - 6] = {"pulley_friction": [0.03, 2.0], "loadcell_hysteresis": [0.2],
                                            "cable_sag": [0.05], "swivel_friction": [0.01]}[name]
        theta = model.initial_params(POSES[0] + 0.01 * rng.standard_normal(6), vals)
        _check_fd(model, theta, POSES, approach)


def test_cable_effects_change_readings_as_their_physics_says():
    from calib.effects.cable import sag_terms
    from calib.statics import tension_model

    zeta0 = POSES[0]
    tau = tension_model(ROBOT, POSES).tau
    a = np.tile(np.array([1.0, -1.0, 1.0, -1.0]), (POSES.shape[0], 1))
    s = -a
    approach = np.stack([a, s], axis=-1)
    m = EffectModel(ROBOT, make_effects(["pulley_friction"]))
    p = m.predict(POSES, m.initial_params(zeta0, [0.02, 1.5]), ("tension",), None, approach)["tension"]
    # paid out (+1): the winch side holds 2 % + 1.5 N less than the platform side; reeled in: more
    np.testing.assert_allclose(p.value, tau * (1 - 0.02 * a) - 1.5 * a, atol=1e-9)
    assert p.value[0, 0] < tau[0, 0] and p.value[0, 1] > tau[0, 1]
    # without directions (old rows) the friction is invisible
    p0 = m.predict(POSES, m.initial_params(zeta0, [0.02, 1.5]), ("tension",))["tension"]
    np.testing.assert_allclose(p0.value, tau, atol=1e-9)
    m = EffectModel(ROBOT, make_effects(["loadcell_hysteresis"]))
    p = m.predict(POSES, m.initial_params(zeta0, [0.2]), ("tension",), None, approach)["tension"]
    np.testing.assert_allclose(p.value, tau - 0.2 * s, atol=1e-9)  # rising load reads low
    m = EffectModel(ROBOT, make_effects(["cable_sag"]))
    p = m.predict(POSES, m.initial_params(zeta0, [0.05]), ("tension", "length"))
    terms = sag_terms(ROBOT, POSES)
    # the cells read more: half the cables' weight (0.05 kg/m x ~2 m per cable) and rho g dz / 2 on top
    extra = p["tension"].value - tau
    np.testing.assert_allclose(extra, 0.05 * (terms.tw + terms.cell), atol=1e-9)
    assert 0.1 < extra.mean() < 1.0, extra.mean()
    assert np.all(terms.cell > 0)  # the pulleys are above the anchors
    # the sag lengthens the path by (rho g)^2 lc h^2 / (24 tau^2): tenths of a mm at 0.05 kg/m, 30-170 N
    sag = (0.05 * ROBOT.gravity) ** 2 * terms.m / (24 * (tau + 0.05 * terms.tw) ** 2)
    assert 1e-6 < sag.max() < 1e-3, sag.max()


def test_reference_noise_shifts_every_row_of_a_relative_channel_by_one_value_per_cable():
    """The reference window's noise is one offset per cable in lengths and swivel angles and one in yaw,
    the same in every row (exact columns), with priors of the reference mean's sigma: the rows' sigma
    scaled by sqrt(harmonic-mean window size / reference window size)."""
    from calib.effects.priors import DeviceAccuracy, ReferenceNoise

    sigma = {"tension": np.full(4, 0.1), "length": np.full(4, 4e-5), "swivel": np.full(4, 1e-5),
             "orientation": np.array([1e-4, 1e-4, 2e-4])}
    windows = np.array([[0, 19], [30, 59], [70, 89]])  # 20, 30 and 20 samples: harmonic mean 22.5
    rn = ReferenceNoise.for_rows(sigma, windows, ref_size=90)
    assert rn.sd["length"] == pytest.approx(4e-5 * np.sqrt(22.5 / 90))
    assert rn.sd["swivel"] == pytest.approx(1e-5 * 0.5) and rn.sd["yaw"] == pytest.approx(2e-4 * 0.5)
    model = EffectModel(ROBOT, [DeviceAccuracy(), rn])
    rng = np.random.default_rng(5)
    values = np.r_[np.zeros(7), 3e-5 * rng.standard_normal(4), 1e-5 * rng.standard_normal(4), 4e-4]
    theta = model.initial_params(POSES[1], values)
    _check_fd(model, theta, POSES)
    base = EffectModel(ROBOT, [DeviceAccuracy()]).predict(POSES, theta[:13], CHANNELS)
    pred = model.predict(POSES, theta, CHANNELS)
    np.testing.assert_allclose(pred["length"].value - base["length"].value, np.tile(values[7:11], (4, 1)))
    np.testing.assert_allclose(pred["swivel"].value - base["swivel"].value, np.tile(values[11:15], (4, 1)))
    np.testing.assert_allclose(pred["orientation"].value[:, 2] - base["orientation"].value[:, 2], 4e-4)
    np.testing.assert_allclose(pred["tension"].value, base["tension"].value)
    idx, _, sd = model.priors()
    assert idx.tolist() == list(range(6, 6 + 7 + 9))
    np.testing.assert_allclose(sd[7:], [rn.sd["length"]] * 4 + [rn.sd["swivel"]] * 4 + [rn.sd["yaw"]])


def test_offsets_written_with_an_absent_effect_equal_the_plain_solves():
    """Issue 28, point 7: the absolute readings behind the written offsets take the yaw in the AHRS's own
    convention under effects too (the rigid model converts it; ``EffectModel`` once returned theta[5], the
    yaw of the robot's convention: 1 deg off at this tilt). Every effect at its absent value writes the
    plain solve's offsets, through the solve itself (the plain solution handed over, not iterated)."""
    from calib.selfcal import solve
    from calib.selfcal.problem import Measurements

    zeta0 = np.r_[POSES[1, :3], 0.12, -0.1, 0.05]
    rigid = MeasurementModel(ROBOT).absolute_readings(zeta0)
    assert abs(rigid["yaw"] - zeta0[5]) > np.radians(0.5)  # the conversion matters at this tilt
    poses = np.vstack([zeta0, POSES + [0, 0, 0, 0.05, -0.04, 0.03]])
    pred = MeasurementModel(ROBOT).predict(poses[1:], zeta0, CHANNELS)
    ref = MeasurementModel(ROBOT).predict(zeta0[None], zeta0, ("tension", "orientation"))
    meas = Measurements(pred["tension"].value, pred["length"].value, pred["swivel"].value,
                        pred["orientation"].value, ref["tension"].value[0], ref["orientation"].value[0, :2])
    plain = solve(ROBOT, meas, guess=(zeta0, poses[1:]))
    assert np.allclose(plain.initial_pose, zeta0, atol=1e-8)
    for name in available_effects():
        model = EffectModel(ROBOT, make_effects([name], available_effects()))
        absolute = model.absolute_readings(model.initial_params(zeta0))
        for c in ("length", "swivel", "yaw"):
            np.testing.assert_allclose(absolute[c], rigid[c], atol=1e-12, err_msg=f"{name}: {c}")
        sol = solve(ROBOT, meas, model=model, guess=(model.initial_params(plain.initial_pose), plain.poses),
                    max_iter=0)
        for c in ("length", "swivel", "yaw"):
            np.testing.assert_allclose(sol.sensor_offsets[c], plain.sensor_offsets[c], atol=1e-12,
                                       err_msg=f"{name}: {c}")


def test_swivel_geometry_changes_readings_as_its_physics_says():
    """The swivel family (issue 28), against geometry computed independently: a pulley plane 4 mm off the
    swivel axis turns the swivel angle by -asin(f / rho_u), rho_u the anchor's distance from the axis; a
    radial entry offset e shortens the in-plane distance, as a robot whose anchors sit e closer to the axis
    along u would; a tilted axis reads what the rigid model of the tilted frames reads; the gain scales."""
    from calib.effects.swivel import SwivelTilt
    from calib.kinematics import inverse_kinematics

    zeta0 = POSES[0]
    rigid = MeasurementModel(ROBOT).predict(POSES, zeta0, CHANNELS)
    kin, kin0 = inverse_kinematics(ROBOT, POSES), inverse_kinematics(ROBOT, zeta0[None])
    entry = EffectModel(ROBOT, make_effects(["swivel_entry"]))
    f = np.zeros(8)
    f[1] = 0.004  # f_1
    got = entry.predict(POSES, entry.initial_params(zeta0, f), CHANNELS)
    turn = -np.arcsin(0.004 / kin.rho_u[:, 0]) + np.arcsin(0.004 / kin0.rho_u[0, 0])
    np.testing.assert_allclose(got["swivel"].value[:, 0] - rigid["swivel"].value[:, 0], turn, atol=1e-12)
    np.testing.assert_allclose(got["swivel"].value[:, 1:], rigid["swivel"].value[:, 1:], atol=1e-12)
    assert np.abs(turn).max() > np.radians(0.01)  # visible to a 0.03 deg encoder's window mean
    absolute = entry.absolute_readings(entry.initial_params(zeta0, f))
    assert absolute["swivel"][0] == pytest.approx(kin0.swivel[0, 0] - np.arcsin(0.004 / kin0.rho_u[0, 0]))
    # a radial offset: the lengths of a pulley whose centre sits e farther out, i.e. anchors e nearer along u
    e = np.zeros(8)
    e[0] = 0.003
    got = entry.predict(POSES, entry.initial_params(zeta0, e), ("length",))["length"].value
    r = ROBOT.r[0]

    def plane_length(ru, rk):  # the wrap of eq. 4-5 by direct search of the tangent point
        phi = np.linspace(0.0, np.pi, 200001)
        bx, bz = r - r * np.cos(phi), r * np.sin(phi)  # groove points from the entry, centre at (r, 0)
        tx, tz = np.sin(phi), np.cos(phi)  # the groove's tangent there, continuing the wrap
        cross_ = (ru - bx) * tz - (rk - bz) * tx
        j = int(np.argmin(np.abs(cross_) + 1e9 * ((ru - bx) * tx + (rk - bz) * tz < 0)))
        return r * phi[j] + np.hypot(ru - bx[j], rk - bz[j])

    want = [plane_length(kin.rho_u[k, 0] - 0.003, kin.rho_k[k, 0]) for k in range(len(POSES))]
    want0 = plane_length(kin0.rho_u[0, 0] - 0.003, kin0.rho_k[0, 0])
    np.testing.assert_allclose(got[:, 0], np.array(want) - want0, atol=2e-6)
    # a tilted axis: exactly the rigid model of the tilted frames
    tilt = np.radians([1.5, -1.0, 0, 0, 0, 0, 0.5, 0.5])
    model = EffectModel(ROBOT, make_effects(["swivel_tilt"]))
    tilted = MeasurementModel(SwivelTilt().modify(ROBOT, tilt)).predict(POSES, zeta0, CHANNELS)
    got = model.predict(POSES, model.initial_params(zeta0, tilt), CHANNELS)
    for c in CHANNELS:
        np.testing.assert_allclose(got[c].value, tilted[c].value, atol=1e-12)
    assert np.abs(tilted["swivel"].value - rigid["swivel"].value).max() > np.radians(0.05)
    gain = EffectModel(ROBOT, make_effects(["swivel_gain"]))
    got = gain.predict(POSES, gain.initial_params(zeta0, [0.01, 0, 0, -0.02]), ("swivel",))["swivel"].value
    np.testing.assert_allclose(got, rigid["swivel"].value * [1.01, 1, 1, 0.98], atol=1e-15)


def test_swivel_friction_lags_the_pulley_by_the_torque_over_the_cables_moment():
    """swivel_friction: a pulley held delta short of the cable's plane feels the cable's moment about its axis,
    computed here from the points of the geometry (the exit point B on the pulley turned by -delta, the
    anchor A); the torque M balances it at delta = M / (tau lever). The reading lags against the way the
    swivel last turned, the reference's lag enters every relative reading, and without directions (rows of
    older code) nothing changes."""
    from calib.effects.swivel import _lever
    from calib.kinematics import inverse_kinematics
    from calib.statics import tension_model

    zeta0 = POSES[0]
    kin = inverse_kinematics(ROBOT, POSES)
    lev, _ = _lever(ROBOT, POSES)
    delta = 1e-6
    for i in range(ROBOT.n):
        fi, fj, fk = ROBOT.frames[i]
        sig = kin.swivel[:, i] - delta
        u = np.cos(sig)[:, None] * fi + np.sin(sig)[:, None] * fj
        nv = np.cos(kin.psi[:, i])[:, None] * u + np.sin(kin.psi[:, i])[:, None] * fk
        b = ROBOT.d[i] + ROBOT.r[i] * (u + nv)
        a = ROBOT.d[i] + kin.q[:, i]
        t = (a - b) / np.linalg.norm(a - b, axis=1)[:, None]
        moment = np.cross(b - ROBOT.d[i], t) @ fk  # per newton of tension, about k_i through D_i
        np.testing.assert_allclose(np.abs(moment) / delta, lev[:, i], rtol=1e-4)
        assert np.all(moment > 0)  # it turns the pulley back towards the cable: a restoring moment
    tau = tension_model(ROBOT, POSES).tau
    tau0, lev0 = tension_model(ROBOT, zeta0[None]).tau[0], _lever(ROBOT, zeta0[None])[0][0]
    s = np.tile([1.0, -1.0, 1.0, 0.0], (POSES.shape[0], 1))
    s0 = np.array([-1.0, -1.0, 1.0, 1.0])
    approach = np.stack([np.zeros_like(s), np.zeros_like(s), s, np.broadcast_to(s0, s.shape)], axis=-1)
    m = EffectModel(ROBOT, make_effects(["swivel_friction"]))
    theta = m.initial_params(zeta0, [0.02])
    rigid = MeasurementModel(ROBOT).predict(POSES, zeta0, ("swivel",))["swivel"].value
    got = m.predict(POSES, theta, ("swivel",), None, approach)["swivel"].value
    np.testing.assert_allclose(got, rigid - 0.02 * (s / (tau * lev) - s0 / (tau0 * lev0)), atol=1e-12)
    assert 0.05 < np.degrees(np.abs(0.02 / (tau * lev))).min()  # 0.02 N m: a visible lag at these tensions
    np.testing.assert_allclose(m.predict(POSES, theta, ("swivel",))["swivel"].value, rigid, atol=1e-15)
