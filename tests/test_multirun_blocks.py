"""The joint fit's speed parts (issue 28, done-when 6) compute what the plain computation does: the block
(Schur) LM step against the dense normal equations, one model call for several problems' rows against each
problem's own, the point-load tensions against one tension model per point mass."""

from __future__ import annotations

import numpy as np
import pytest

from calib import multirun
from calib.effects import EffectModel, make_effects
from calib.effects.base import physical_rows
from calib.fitting import residuals
from calib.multirun import RIDGE, Arrow, Damping, RunFit, stack
from calib.planning import plan_poses
from calib.robot import load_robot
from calib.selfcal.model import CHANNELS, MeasurementModel
from calib.selfcal.problem import Measurements, Problem
from calib.statics import point_load_tensions, tension_model

ROBOT = load_robot("irma4u")
POSES = plan_poses(ROBOT, 2).poses[:5]
SIGMA = {"tension": np.full(4, 0.5), "length": np.full(4, 1e-4), "swivel": np.full(4, 1e-3),
         "orientation": np.full(3, 2e-3)}


def _problem(zeta0: np.ndarray, poses: np.ndarray, effects: list[str], rng) -> Problem:
    """Readings of the rigid model at the poses, with noise of SIGMA, for a model with these effects."""
    pred = MeasurementModel(ROBOT).predict(poses, zeta0, CHANNELS)
    ref = MeasurementModel(ROBOT).predict(zeta0[None], zeta0, ("tension", "orientation"))
    noisy = {c: pred[c].value + SIGMA[c] * rng.standard_normal(pred[c].value.shape) for c in CHANNELS}
    meas = Measurements(noisy["tension"], noisy["length"], noisy["swivel"], noisy["orientation"],
                        ref["tension"].value[0], ref["orientation"].value[0, :2])
    return Problem(EffectModel(ROBOT, make_effects(effects)), meas, SIGMA)


def _runs(rng) -> tuple[list[RunFit], int]:
    """Two runs sharing cable_sag (last in their models), one with a tension offset of its own."""
    out = []
    for j, own in enumerate((["tension_offset"], [])):
        zeta0 = np.r_[POSES[j, :3], 0.01, -0.02, 0.03]
        poses = POSES[j + 1:] + 0.002 * rng.standard_normal((POSES.shape[0] - j - 1, 6))
        prob = _problem(zeta0, poses, [*own, "cable_sag"], rng)
        theta = prob.model.initial_params(zeta0 + 1e-3)
        theta[-1] = 0.03
        out.append(RunFit(f"r{j}", None, prob, theta, poses.copy(), SIGMA))
    return out, 1


def test_the_block_step_is_the_dense_damped_gauss_newton_step():
    """Arrow.step eliminates each run's 6 x 6 pose blocks; its step and predicted decrease equal the dense
    solve of (N + damping diag N) ds = -g on unit-norm columns, shared columns free or fixed."""
    runs, q = _runs(np.random.default_rng(3))
    blocks = [residuals(rf.problem, rf.theta, rf.poses) for rf in runs]
    for fixed in (False, True):
        r, A, _ = stack(runs, q, fixed, blocks=blocks)
        scale = np.linalg.norm(A, axis=0)
        As = A / scale
        N, g = As.T @ As, As.T @ r
        arrow = Arrow.of(runs, blocks, q, fixed)
        np.testing.assert_allclose(arrow.scale, scale, rtol=1e-12)
        for lam in (1e-5, 1e-1):
            ds = -np.linalg.solve(N + (lam + RIDGE) * np.diag(np.diag(N)), g)
            step, gain = arrow.step(lam + RIDGE)
            np.testing.assert_allclose(step, ds, rtol=1e-8, atol=1e-10 * np.abs(ds).max())
            assert gain > 0
            np.testing.assert_allclose(gain, -(2.0 * g @ ds + ds @ N @ ds), rtol=1e-9)


def test_one_model_call_for_two_problems_rows_gives_each_problems_own_residuals():
    """The physical quantities of both runs' rows and zeta_0s from one EffectModel.physical call, laid out
    per run, give Problem.evaluate the residuals and Jacobians of each run's own call, to rounding."""
    runs, _ = _runs(np.random.default_rng(4))
    rows = [np.vstack([rf.theta[None, :6], rf.poses[rf.problem.groups[0].idx], rf.theta[None, :6]]) for rf in runs]
    robot, ph = runs[0].problem.model.physical(runs[0].theta, np.vstack(rows))
    assert set(ph.terms) == {"cable_sag"}  # the sag's per-pose terms come with the physical quantities
    start = 0
    for rf, z in zip(runs, rows, strict=True):
        part = physical_rows(ph, slice(start, start + z.shape[0]))
        start += z.shape[0]
        p, p0 = rf.theta.shape[0], runs[0].theta.shape[0]
        for name in ("tL", "tsigma", "ttau"):  # the shared (last) columns at this run's place
            t = np.zeros(getattr(part, name).shape[:2] + (p,))
            t[..., -1] = getattr(part, name)[..., p0 - 1]
            setattr(part, name, t)
        a = residuals(rf.problem, rf.theta, rf.poses)
        b = residuals(rf.problem, rf.theta, rf.poses, physical=(robot, part))
        np.testing.assert_allclose(b.r, a.r, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b.A, a.A, rtol=1e-12, atol=1e-9)
        assert a.r.shape[0] == rf.problem.n_residuals


def test_point_load_tensions_are_the_sum_of_one_tension_model_per_point_mass():
    """Tensions holding masses at the four anchors: one statics evaluation, value and pose Jacobian equal to
    the sum over the anchors of the tension model of a robot whose whole mass sits there."""
    from calib.kinematics import inverse_kinematics, kinematic_jacobians

    kin = inverse_kinematics(ROBOT, POSES)
    jac = kinematic_jacobians(ROBOT, kin)
    masses = np.random.default_rng(5).uniform(0.05, 0.3, (POSES.shape[0], ROBOT.n))
    each, tau, dtau = point_load_tensions(ROBOT, kin, jac, ROBOT.a_local, masses)
    ref_tau, ref_dtau = np.zeros_like(tau), np.zeros_like(dtau)
    for i in range(ROBOT.n):
        tm = tension_model(ROBOT.replace(mass=1.0, com=ROBOT.a_local[i].copy()), kin=kin, jac=jac)
        np.testing.assert_allclose(each[..., i], tm.tau, rtol=1e-10)
        ref_tau += masses[:, i, None] * tm.tau
        ref_dtau += masses[:, i, None, None] * tm.jacobian
    np.testing.assert_allclose(tau, ref_tau, rtol=1e-10)
    np.testing.assert_allclose(dtau, ref_dtau, rtol=1e-9, atol=1e-9 * np.abs(ref_dtau).max())
    assert np.abs(tau).max() > 1.0  # newtons: the loads are felt (0.05-0.3 kg per anchor)


def _damped(n: int, lightest) -> tuple[list[float], int]:
    """LM's damping over n iterations when a trial is accepted only at a damping of at least lightest(k) at
    iteration k: the accepted dampings and the refused trials."""
    d, accepted, refused = Damping(), [], 0
    for k in range(n):
        tries = 0
        while d.lam < lightest(k):
            d.refused()
            tries += 1
        refused += tries
        accepted.append(d.lam)
        d.accepted(after_refusal=tries > 0)
    return accepted, refused


def test_the_damping_memory_takes_marquardts_steps_with_fewer_refused_trials(monkeypatch):
    """While the lighter step keeps failing (the real runs' weak directions) the damping memory accepts the
    very dampings of Marquardt's rule (x10 / 10) with a refused trial every 1, 2, 4, 8 iterations instead of
    every iteration; when the lighter steps start to hold, it reaches them at most HOLD_MAX iterations later."""
    def lightest(k):
        return 3e-6 if k < 40 else 3e-10  # the quadratic model holds with light damping from iteration 40

    memory, refused = _damped(60, lightest)
    hold_max = multirun.HOLD_MAX
    monkeypatch.setattr(multirun, "HOLD_MAX", 0)
    plain, refused_plain = _damped(60, lightest)
    np.testing.assert_allclose(memory[:40], plain[:40], rtol=1e-12)
    np.testing.assert_allclose(plain[:40], 1e-5, rtol=1e-12)
    assert refused_plain == 59 - 4  # one per iteration but the first and the four that reach 1e-9
    assert refused <= 10
    first = lambda acc: next(k for k, v in enumerate(acc) if v < 3e-9)  # noqa: E731
    assert first(plain) == 43 and first(memory) <= first(plain) + hold_max == 51


def test_the_shared_covariance_from_the_blocks_is_that_block_of_the_dense_inverse():
    """Arrow.covariance (the inverse of the runs' Schur complement) is the shared block of the inverse of the
    dense normal matrix on unit-norm columns, and its rank the column count."""
    runs, q = _runs(np.random.default_rng(4))
    blocks = [residuals(rf.problem, rf.theta, rf.poses) for rf in runs]
    _, A, _ = stack(runs, q, blocks=blocks)
    As = A / np.linalg.norm(A, axis=0)
    dense = np.linalg.inv(As.T @ As)[:q, :q]
    cov, rank = Arrow.of(runs, blocks, q, False).covariance()
    np.testing.assert_allclose(cov, dense, rtol=1e-8)
    assert rank == A.shape[1]


def test_the_geodesic_acceleration_solves_the_same_damped_system_for_the_second_derivative():
    """Arrow.gradient(r') is the dense J^T r' on unit-norm columns, and Arrow.step with it the dense damped
    solve (N + damping diag N) a = -J^T r'; a shared column held at a bound (Arrow.pinned) gets no step and the
    others are the dense solve without it."""
    runs, q = _runs(np.random.default_rng(5))
    blocks = [residuals(rf.problem, rf.theta, rf.poses) for rf in runs]
    _, A, _ = stack(runs, q, blocks=blocks)
    scale = np.linalg.norm(A, axis=0)
    As = A / scale
    N = As.T @ As
    other = [np.random.default_rng(6).standard_normal(b.r.shape[0]) for b in blocks]
    arrow = Arrow.of(runs, blocks, q, False)
    lam = 1e-3 + RIDGE
    acc, _ = arrow.step(lam, arrow.gradient(other))
    dense = -np.linalg.solve(N + lam * np.diag(np.diag(N)), As.T @ np.concatenate(other))
    np.testing.assert_allclose(acc, dense, rtol=1e-8, atol=1e-10 * np.abs(dense).max())
    arrow.pinned = np.ones(q, bool)  # the shared sag density held
    held, _ = arrow.step(lam)
    g = As.T @ np.concatenate([b.r for b in blocks])
    free = np.arange(q, A.shape[1])
    Nf = N[np.ix_(free, free)]
    dense = -np.linalg.solve(Nf + lam * np.diag(np.diag(Nf)), g[free])
    assert np.all(held[:q] == 0.0)
    np.testing.assert_allclose(held[free], dense, rtol=1e-8, atol=1e-10 * np.abs(dense).max())


def test_a_singular_pose_block_leaves_the_covariance_to_the_dense_svd():
    """A pose whose block of the normal matrix is singular (on the real runs a fit can reach poses whose six
    unit columns are parallel: rank 1, eigenvalues 6 and 0) makes Arrow.covariance return None, for the
    caller's SVD, instead of inverting the block undamped and raising."""
    runs, q = _runs(np.random.default_rng(4))
    blocks = [residuals(rf.problem, rf.theta, rf.poses) for rf in runs]
    arrow = Arrow.of(runs, blocks, q, False)
    arrow.U[0] = arrow.U[0].copy()
    arrow.U[0][1] = np.ones((6, 6))
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.inv(arrow.U[0][1])  # what the reduction would do with it undamped
    assert arrow.covariance() is None


def _shared_runs(names: list[str], rng, values: np.ndarray | None = None) -> tuple[list[RunFit], list, int]:
    """Three runs of one robot: the effects ``names`` shared (the same instances, last in every model) at
    ``values`` (None: absent + 0.5 typical size, within bounds), noisy rigid-model readings."""
    shared = make_effects(names)
    specs = [sp for e in shared for sp in e.params(ROBOT)]
    if values is None:
        values = np.clip([sp.absent + 0.5 * sp.scale for sp in specs], [sp.lower for sp in specs],
                         [sp.upper for sp in specs])
    runs = []
    for j in range(3):
        zeta0 = np.r_[POSES[j, :3], 0.01, -0.02, 0.03]
        poses = POSES[j + 1:] + 0.002 * rng.standard_normal((POSES.shape[0] - j - 1, 6))
        prob = Problem(EffectModel(ROBOT, shared), _problem(zeta0, poses, [], rng).meas, SIGMA)
        runs.append(RunFit(f"r{j}", None, prob, np.r_[zeta0 + 1e-3, values], poses.copy(), SIGMA))
    return runs, shared, len(specs)


def test_an_evaluation_without_jacobian_has_the_same_residuals_for_every_effect():
    """multirun's geodesic trial point needs residuals only: EffectModel.physical(derivatives=False) computes no
    derivative (kinematic Jacobians, the statics' pose derivatives, the robot effects' finite-difference theta
    columns: a model call per parameter), and with every effect of the library the residuals are bitwise
    those of the evaluation with its Jacobian (the swivel entry with robot effects too)."""
    from calib.effects import available_effects

    sets = [["tension_offset", name] if name != "tension_offset" else [name] for name in available_effects()]
    for names in [*sets, ["swivel_entry", "swivel_tilt"], ["swivel_entry", "pulley_position"]]:
        # (the swivel entry's columns follow the robot effects' geometry: Context.robot_at, None without them)
        runs, shared, q = _shared_runs(names, np.random.default_rng(6))
        name = ",".join(names)
        assert multirun.one_robot(runs, shared)
        full, c_full = multirun._evaluate(runs, q, batch=True, jacobian=True)
        bare, c_bare = multirun._evaluate(runs, q, batch=True, jacobian=False)
        assert c_full == c_bare, name
        for a, b in zip(full, bare, strict=True):
            np.testing.assert_array_equal(a.r, b.r, err_msg=name)
            assert np.abs(a.A).max() > 1.0  # the Jacobian the other evaluation has
    runs, _, _ = _shared_runs(["pulley_position"], np.random.default_rng(6))
    z = np.vstack([runs[0].theta[None, :6], runs[0].poses])
    _, ph = runs[0].problem.model.physical(runs[0].theta, z, derivatives=False)
    assert not ph.tL.any() and not ph.ttau.any() and not ph.dL.any() and not ph.dtau.any()
    _, ph = runs[0].problem.model.physical(runs[0].theta, z)
    assert ph.tL.any() and ph.ttau.any() and ph.dL.any() and ph.dtau.any()


def _dense_leave_one_run_out(runs: list[RunFit], q: int, floor) -> list[float]:
    """The fold scores from the dense joint normal equations (the plain computation the blocks replace)."""
    from calib.multirun import score_of

    blocks = [rf.residuals() for rf in runs]
    r, A, cols = stack(runs, q, blocks=blocks)
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    As = A / scale
    N, g = As.T @ As, As.T @ r
    bounds = np.cumsum([0] + [b.r.shape[0] for b in blocks])
    out = []
    for j, res in enumerate(blocks):
        rows = slice(bounds[j], bounds[j + 1])
        own = np.r_[np.arange(cols[j][0].start, cols[j][0].stop), np.arange(cols[j][1].start, cols[j][1].stop)]
        keep = np.setdiff1d(np.arange(A.shape[1]), own)
        Aj, rj = As[rows], r[rows]
        Nt = (N - Aj.T @ Aj)[np.ix_(keep, keep)]
        delta = -np.linalg.solve(Nt + 1e-9 * np.diag(np.maximum(np.diag(Nt), 1e-12)), (g - Aj.T @ rj)[keep])
        e = rj + Aj[:, :q] @ delta[:q]
        step, *_ = np.linalg.lstsq(Aj[:, own], e, rcond=1e-10)
        e = e - Aj[:, own] @ step
        unit = np.where(res.r != 0, res.si / np.where(res.r != 0, res.r, 1.0), 0.0)
        out.append(score_of(e * unit, res.channel, floor))
    return out


def test_leave_one_run_out_by_blocks_is_the_dense_computation():
    """runselect.leave_one_run_out reduces each run's normal matrix to the shared columns once; its fold scores
    equal those of the dense joint normal equations less the left-out run's rows (three runs sharing
    cable_sag and tension offsets, theta away from the readings' so that the folds differ)."""
    from calib.multirun import JointFit
    from calib.runselect import leave_one_run_out
    from calib.selfcal import sensor_noise

    rng = np.random.default_rng(8)
    values = np.r_[rng.normal(0.0, 2.0, 4), 0.03]
    runs, shared, _ = _shared_runs(["tension_offset", "cable_sag"], rng, values)
    q, floor = values.size, sensor_noise(ROBOT)
    fit = JointFit(shared, values, np.eye(q), runs, 0.0, True, 0)
    total, folds = leave_one_run_out(fit, floor)
    ref = _dense_leave_one_run_out(runs, q, floor)
    np.testing.assert_allclose([f["score"] for f in folds], ref, rtol=1e-9)
    assert total == pytest.approx(sum(ref), rel=1e-9)
    assert np.ptp(ref) > 1.0  # the folds see different runs
    assert [f["run"] for f in folds] == ["r0", "r1", "r2"] and all(f["J"] > 0 for f in folds)
