"""Information-optimal plans, sequential acquisition and separating effects (issue 19)."""

from __future__ import annotations

import itertools
import json
import time

import numpy as np
import pytest

from acquisition.cli import main
from acquisition.estimates import EstimateWorker
from acquisition.runlog import read_run
from acquisition.session import simulated_startup
from calib.design import (
    LOOP_POSE_NOISE,
    PoseNoise,
    TimeModel,
    assess,
    candidates,
    information,
    lateral_stiffness,
    optimal_plan,
    planning_model,
    predict_loop,
    separating_poses,
    window_mean_noise,
)
from calib.diagnose import diagnose
from calib.effects import make_effects
from calib.equilibrium import inverse_geometrico_static
from calib.planning import PlanningError, PosePlan, plan_poses
from calib.robot import load_robot
from calib.selfcal import solve
from calib.sequential import OnlineSolve, SequentialDesign, WindowMean, drive, sequential_acquisition
from sim_backend.config import HiddenEffects, SimConfig, load_sim_config
from sim_backend.equilibrium_rows import WINDOW_NOISE, simulated_rows


@pytest.fixture(scope="module")
def robot():
    return load_robot("irma4u")


@pytest.fixture(scope="module")
def noise(robot):
    return window_mean_noise(robot)


@pytest.fixture(scope="module")
def cands(robot, noise):
    return candidates(robot, noise, step=0.2)


def test_information_is_the_inverse_of_the_solve_covariance(robot, noise):
    """The plan's information (rows' Schur complements added) is what the block-arrow solve inverts."""
    plan = plan_poses(robot, 2)
    rows = simulated_rows(robot, load_sim_config(None, robot.n), seed=3, noise=noise, plan=plan)
    model = planning_model(robot)
    sol = solve(robot, rows.meas, noise=noise, model=model, guess=(rows.guess_zeta0, rows.guess_poses))
    info0, info = information(robot, sol.poses, sol.theta[:6], noise)
    predicted = np.linalg.inv(info0 + info.sum(0))
    np.testing.assert_allclose(predicted[:6, :6], sol.covariance[:6, :6], rtol=1e-6, atol=1e-15)


def test_pose_noise_without_force_is_the_constant_noise(robot, noise):
    """A per-pose noise with no stiffness term weighs every window as the constant noise does."""
    plan = plan_poses(robot, 2)
    const = PoseNoise({c: np.asarray(v) for c, v in noise.items()}, {c: 0.0 for c in noise})
    a0, a = information(robot, plan.poses, plan.home_pose, noise)
    b0, b = information(robot, plan.poses, plan.home_pose, const)
    np.testing.assert_allclose(b0, a0, rtol=1e-12)
    np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-9 * np.abs(a).max())


def test_loop_prediction_of_the_grid_and_the_optimal_plan(robot):
    """The loop's prediction: the grid's 1-sigma is the RMS error of its 20 loop startups (0.156 mm, the
    calibration), the optimal plan chosen with the per-pose noise predicts 0.62 of it; compliant poses are
    noisier. (In the loop that plan measured 0.167 mm RMS: docs/planning.md.)"""
    grid = plan_poses(robot, 2)
    k = lateral_stiffness(robot, grid.poses, grid.setpoints)
    np.testing.assert_allclose(k, [131, 131, 131, 131, 345, 345, 345, 345], atol=1.0)
    sig = LOOP_POSE_NOISE.sigma(robot, k)
    assert sig["length"][0, 0] == pytest.approx(1.457 * np.hypot(3.611e-5, 4.29e-3 / k[0]))
    assert sig["length"][0, 0] > sig["length"][4, 0]  # the compliant poses (131 N/m) are the noisier
    assert sig["tension"][0, 0] == pytest.approx(1.457 * np.hypot(0.2062, 23.39 / k[0]))
    g = predict_loop(robot, grid, TimeModel()).position_sigma
    o = predict_loop(robot, optimal_plan(robot, 8, LOOP_POSE_NOISE), TimeModel()).position_sigma
    assert g == pytest.approx(0.156e-3, rel=0.01)
    assert o / g == pytest.approx(0.619, abs=0.01)


def test_optimal_plan_beats_the_grid_and_is_reachable(robot, noise, cands):
    grid = plan_poses(robot, 2)
    opt = optimal_plan(robot, 8, noise, cands=cands)
    a_grid, a_opt = assess(robot, grid, noise, TimeModel()), assess(robot, opt, noise, TimeModel())
    assert a_opt.position_sigma <= 0.75 * a_grid.position_sigma
    assert len({tuple(p) for p in np.round(opt.poses[:, :3], 6)}) == 8  # distinct poses
    sp = inverse_geometrico_static(robot, opt.poses[:, :3])
    assert sp.feasible.all()
    assert np.all(opt.setpoints >= robot.tau_min - 1e-9) and np.all(opt.setpoints <= robot.tau_max + 1e-9)
    np.testing.assert_allclose(sp.tensions, opt.setpoints, atol=1e-6)


def test_ordering_minimises_the_robot_time(robot, noise, cands):
    opt = optimal_plan(robot, 6, noise, cands=cands)
    tm = TimeModel(min_transition=0.0)
    ordered = tm.tour(opt.tau0, opt.setpoints)
    others = [tm.tour(opt.tau0, opt.setpoints[list(p)]) for p in itertools.permutations(range(6))]
    assert ordered <= min(others) + 1e-9
    assert ordered < np.median(others) - 5.0  # seconds saved against a typical order


def test_empty_workspace_is_one_sentence(robot, noise):
    with pytest.raises(PlanningError, match=r"static workspace inside .* is empty"):
        candidates(robot, noise, step=0.1, lower=[-0.05, -0.05, 1.75], upper=[0.05, 0.05, 1.8])


def test_sequential_choice_and_stop_rule_on_simulated_windows(robot, noise, cands):
    """After each window the warm-started solve's 1-sigma shrinks; the stop rule fires at the tolerance, sooner
    than the grid's robot time, and the 1-sigma it stops on covers the error."""
    tol = 0.8 * assess(robot, plan_poses(robot, 2), noise, TimeModel()).position_sigma
    # the simulator's window means at every candidate, one draw (the reference window is the home pose)
    rows = simulated_rows(robot, load_sim_config(None, robot.n), seed=1, noise=noise, plan=_plan_of(cands))
    m = rows.meas
    ref = WindowMean(m.ref_tau, np.zeros(robot.n), np.zeros(robot.n), np.r_[m.ref_orientation, 0.0])
    online, history = OnlineSolve(robot, noise, ref, cands.home_pose), []
    steps = sequential_acquisition(SequentialDesign(cands, TimeModel()), online, tol, 20, history)
    why = drive(steps, lambda j: WindowMean(m.tau[j], m.dl[j], m.dsigma[j], m.orientation[j]))
    sigmas = [e.position_sigma for _, e in history]
    assert why == "tolerance" and sigmas[-1] < tol <= sigmas[-2]
    assert all(b <= a * (1 + 1e-6) for a, b in itertools.pairwise(sigmas))
    assert len(sigmas) < 8
    visited = cands.setpoints[[c for c, _ in history]]
    assert TimeModel().tour(cands.tau0, visited) < TimeModel().tour(cands.tau0, plan_poses(robot, 2).setpoints)
    assert np.linalg.norm(online.theta[:3] - rows.zeta0[:3]) < 4 * sigmas[-1]
    assert max(e.iterations for _, e in history[1:]) < 20  # warm starts


def _plan_of(cands):
    """A PosePlan visiting every candidate (for simulated window means at each)."""
    k = cands.size
    return PosePlan(cands.poses, cands.setpoints, cands.tau0, cands.home_pose, np.full((k, 3), -1), 0.0, np.ones(k))


def test_poses_optimal_cli_json(capsys):
    assert main(["poses", "--optimal", "4", "--step", "0.25", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["poses"]) == 4 and out["candidates"] > 4
    assert out["predicted"]["position_sigma_m"] > 0 and out["grid"]["poses"] == 8
    assert out["predicted"]["robot_time_s"] > 0 and out["grid"]["robot_time_s"] > 0


def test_unreachable_tolerance_is_a_usage_error(tmp_path, capsys):
    code = main(["startup", "--backend", "sim", "--no-html", "--out", str(tmp_path / "r"), "--tolerance", "0.001mm",
                 "--step", "0.25", "--poses", "4"])
    err = capsys.readouterr().err
    assert code == 2
    assert "cannot be reached" in err and err.count("\n") == 1
    assert not (tmp_path / "r").exists()


def test_sequential_startup_stops_at_the_tolerance(tmp_path):
    """A small simulated startup: the sequential plan stops once the 1-sigma is below 0.5 mm, well before the
    grid's 8 poses, and the run records why. The 1-sigma the stop rule compares is that of the run's own solve
    (``cdpr solve --noise estimate`` on the samples so far): the finished run's solve prints it again."""
    out = simulated_startup(tmp_path / "seq", plan="sequential", tolerance=5e-4, step=0.25, seed=2)
    assert out["status"] == "ok"
    assert "< tolerance 0.5 mm" in out["message"]
    assert 3 <= out["setpoints"] < 8
    run = read_run(tmp_path / "seq")
    assert len(run.setpoints) == out["setpoints"] == len(run.ideal_poses)
    online = run.meta["sequential"]["windows"][-1]["position_sigma_m"]
    sol = solve(run.robot, run, noise="estimate")
    final = float(np.sqrt(np.trace(sol.covariance[:3, :3])))
    assert online < 5e-4 and online == pytest.approx(final, rel=0.1)
    truth = np.asarray(out["truth_window_mean"], float)
    assert np.linalg.norm(sol.initial_pose[:3] - truth[:3]) < 3 * final
    # on a real clock that solve runs in a worker process while the loop keeps ticking (holding the platform)
    rows = list(zip(run.t, run.tau, run.tau_ref, run.dl, run.dsigma, run.roll, run.pitch, run.dyaw, strict=True))
    args = (run.robot, rows, run.setpoints, run.ideal_poses)
    ticks: list[float] = []
    worker = EstimateWorker(lockstep=False)
    try:
        est, _ = worker.compute(args, lambda: (ticks.append(time.perf_counter()), time.sleep(0.002)), time.perf_counter)
    finally:
        worker.close()
    assert len(ticks) > 10 and est.position_sigma == pytest.approx(final, rel=1e-9)
    # the loop was never held up by the solve: no gap between ticks is a sizeable part of the solve's time (a solve
    # in line would be one gap as long as the whole solve); relative, so a loaded machine does not fail it
    assert max(np.diff(ticks)) < 0.25 * (ticks[-1] - ticks[0])


def _diagnosis_gap(robot, rows, names):
    """chi2 improvement of the first effect's refit minus the second's, as the diagnosis ranks the two."""
    d = diagnose(robot, rows.meas, rows.sigma, rows.guess_zeta0, rows.guess_poses, candidates=make_effects(names),
                 max_effects=1, refits=2)
    by = {c.effect: c.delta_chi2 for c in d.ranking}
    return by[names[0]] - by[names[1]], d.selected


def test_separating_poses_tell_pulley_radius_from_pulley_position(robot):
    """Grid rows of a prototype whose pulleys are 2 mm larger, with noisy windows: both effects fit about
    as well (the diagnosis cannot tell them apart). After the three proposed poses are added, the true
    effect fits better by more than 10 chi2 units (a likelihood ratio above e^5)."""
    names = ["pulley_radius", "pulley_position"]
    noise = {k: 5 * np.asarray(v) for k, v in WINDOW_NOISE.items()}
    config = SimConfig(effects=HiddenEffects(pulley_radius=(0.002,) * robot.n))
    grid = plan_poses(robot, 2)
    rows = simulated_rows(robot, config, seed=0, noise=noise, plan=grid)
    before, _ = _diagnosis_gap(robot, rows, names)
    assert abs(before) < 5.0
    cands = candidates(robot, rows.sigma, step=0.3)
    sep = separating_poses(robot, rows.meas, rows.sigma, rows.guess_zeta0, rows.guess_poses,
                           tuple(make_effects(names)), cands, count=3)
    assert len(sep.poses) == 3 and np.all(sep.score > 0)
    assert inverse_geometrico_static(robot, sep.poses[:, :3]).feasible.all()
    more = PosePlan(np.vstack([grid.poses, sep.poses]), np.vstack([grid.setpoints, sep.setpoints]), grid.tau0,
                    grid.home_pose, np.full((11, 3), -1), 0.0, np.ones(11))
    after, selected = _diagnosis_gap(robot, simulated_rows(robot, config, seed=0, noise=noise, plan=more), names)
    assert after > 10.0
    assert selected == ["pulley_radius"]


def test_poses_separate_cli_errors(tmp_path, capsys):
    assert main(["poses", "--separate", "pulley_radius", str(tmp_path)]) == 2
    assert "two different effect names" in capsys.readouterr().err
    assert main(["poses", "--separate", "pulley_radius,no_such_effect", str(tmp_path)]) == 2
    assert "unknown effect 'no_such_effect'" in capsys.readouterr().err
