"""Noise of a window mean (calib.selfcal.window_mean_noise, issue 17): against the empirical scatter of window
means of synthetic signals with known noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calib.robot import load_robot
from calib.selfcal import Window, resolution_floor, window_mean_noise

ROBOT = load_robot("irma4u")


def signals(noise: np.ndarray, n_windows: int, size: int, gap: int = 20) -> tuple[dict, list[Window]]:
    """A run whose every channel is ``noise`` (samples, ) plus a different constant per window."""
    N = noise.shape[0]
    t = np.arange(N) * 0.1
    x = np.repeat(noise[:, None], 4, axis=1)
    sig = {"t": t, "tau": 100.0 + x, "dl": x * 1e-3, "dsigma": x * 1e-3, "roll": x[:, 0] * 1e-3,
           "pitch": x[:, 0] * 1e-3, "dyaw": x[:, 0] * 1e-3}
    wins = [Window(j * (size + gap), j * (size + gap) + size - 1) for j in range(n_windows)]
    return sig, wins


def ar1(rng, N: int, rho: float, sd: float) -> np.ndarray:
    e = rng.standard_normal(N) * sd * math.sqrt(1 - rho**2)
    x = np.empty(N)
    x[0] = rng.standard_normal() * sd
    for i in range(1, N):
        x[i] = rho * x[i - 1] + e[i]
    return x


@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_sigma_of_a_window_mean_matches_the_scatter_of_window_means(rho):
    """White noise: sigma / sqrt(N); AR(1) of rho 0.6: four times the variance of that. The estimate from 30
    windows lands within 20 % of the true standard deviation of a 40-sample mean (measured: 1.02 and 1.16 of
    it). The kinematic channels, whose second differences reject a smooth motion, are checked on white noise."""
    rng = np.random.default_rng(3)
    size, n_windows = 40, 30
    x = ar1(rng, n_windows * (size + 20), rho, 1.0)
    sig, wins = signals(x, n_windows, size)
    wn = window_mean_noise(ROBOT, sig, wins)
    f = 1 + 2 * sum((1 - k / size) * rho**k for k in range(1, size))
    true = math.sqrt(f / size)  # sd of a 40-sample mean of unit-variance AR(1)
    assert wn.sigma["tension"][0] == pytest.approx(true, rel=0.2)
    assert wn.groups["tension"].rho == pytest.approx(rho, abs=0.1)
    if rho == 0.0:
        assert wn.sigma["length"][0] == pytest.approx(1e-3 * true, rel=0.2)
    # per-sample scatter (the old estimate) would have been sqrt(N / f) times larger
    assert wn.sigma["tension"][0] < 0.5 * float(np.std(x))


def test_a_slow_sway_is_not_taken_for_noise():
    """A smooth motion inside the windows (a 10 s sway of 5 x the noise, as in rigid_sway.yaml) is mostly
    taken by the quadratic removed per window: the estimate of the kinematic channels stays within 20 % of
    that of the white noise (measured 1.10 of it; 1.05 without the sway)."""
    rng = np.random.default_rng(5)
    size, n_windows = 40, 30
    N = n_windows * 60
    x = rng.standard_normal(N) + 5.0 * np.sin(2 * math.pi * np.arange(N) * 0.1 / 10.0)
    sig, wins = signals(x, n_windows, size)
    wn = window_mean_noise(ROBOT, sig, wins)
    assert wn.sigma["length"][0] == pytest.approx(1e-3 / math.sqrt(size), rel=0.2)
    assert wn.sigma["orientation"][0] == pytest.approx(1e-3 / math.sqrt(size), rel=0.2)


def test_a_reading_on_its_counts_is_floored_at_its_resolution():
    """Swivel encoders of a still platform sit on one count: the sigma of their mean is the resolution
    (step / sqrt 12), not zero."""
    rng = np.random.default_rng(7)
    size, n_windows = 40, 10
    x = rng.standard_normal(n_windows * 60)
    sig, wins = signals(x, n_windows, size)
    sig["dsigma"] = np.zeros_like(sig["dsigma"])
    wn = window_mean_noise(ROBOT, sig, wins)
    assert wn.sigma["swivel"][0] == pytest.approx(resolution_floor(ROBOT)["swivel"][0])
    assert wn.sigma["swivel"][0] == pytest.approx(2 * math.pi / 65536 / math.sqrt(12))


def test_variance_factors_measure_the_rows_scatter_and_only_shrink_the_sigmas():
    """Window means with known white noise (27 simulated equilibria): weighed with twice their sigma, each
    group's Helmert factor is near 1/4 and rescaled_sigma halves it; weighed with half, the factors are near 4
    and nothing is scaled up (a moderate misfit must stay in chi2)."""
    from calib.selfcal.lm import levenberg_marquardt
    from calib.selfcal.model import MeasurementModel
    from calib.selfcal.noise import rescaled_sigma, variance_factors
    from calib.selfcal.problem import Problem
    from sim_backend.config import sim_config_from_dict
    from sim_backend.equilibrium_rows import simulated_rows

    rows = simulated_rows(ROBOT, sim_config_from_dict({}), seed=4, grid=3, device_biases=False)
    model = MeasurementModel(ROBOT)
    for scale, expect in ((2.0, 0.25), (0.5, 4.0)):
        sigma = {c: scale * np.asarray(v, float) for c, v in rows.sigma.items()}
        problem = Problem(model, rows.meas, sigma)
        res = levenberg_marquardt(problem, rows.zeta0.copy(), rows.poses.copy())
        fac = variance_factors(problem, res.theta, res.poses)
        for group in ("tension", "length", "swivel", "tilt"):
            f, red = fac[group]
            assert red > 12 and expect / 1.6 < f < expect * 1.6, (scale, group, f, red)
        dof = problem.n_residuals - model.n_params - 6 * rows.meas.k
        assert sum(red for _, red in fac.values()) == pytest.approx(dof, abs=0.5)
        shrunk = rescaled_sigma(sigma, fac)
        if expect < 1:
            assert shrunk["tension"][0] == pytest.approx(sigma["tension"][0] * math.sqrt(fac["tension"][0]))
            assert shrunk["orientation"][0] < sigma["orientation"][0]
        else:
            assert shrunk is None


def test_each_cables_swivel_rows_get_their_own_component_where_they_carry_it():
    """Issue 29: 27 simulated equilibria whose cable-1 swivel readings carry twice the noise of the others
    (variance 4x), weighed with one sigma for all four: the per-cable Helmert factors find cable 1's near 4x
    the others' (their redundancies sum to the group's), and rescaled_sigma splits the group's sigma among
    the cables by sqrt(f_i / f), f_i shrunk toward the group's level (cable_factors), at the group's level; one
    cable with too few degrees of freedom (VCE_MIN_REDUNDANCY), or a group scattering beyond its noise's chi2
    band, leaves the group pooled."""
    from calib.selfcal.lm import levenberg_marquardt
    from calib.selfcal.model import MeasurementModel
    from calib.selfcal.noise import MISFIT_FACTOR, VCE_MIN_REDUNDANCY, rescaled_sigma, variance_factors
    from calib.selfcal.problem import Problem
    from calib.selfcal.shrinkage import cable_factors
    from sim_backend.config import sim_config_from_dict
    from sim_backend.equilibrium_rows import simulated_rows

    rows = simulated_rows(ROBOT, sim_config_from_dict({}), seed=4, grid=3, device_biases=False)
    sw = float(np.asarray(rows.sigma["swivel"], float)[0])
    rows.meas.dsigma[:, 0] += np.random.default_rng(7).normal(0.0, math.sqrt(3.0) * sw, rows.meas.k)
    sigma = {c: np.asarray(v, float) for c, v in rows.sigma.items()}
    problem = Problem(MeasurementModel(ROBOT), rows.meas, sigma)
    res = levenberg_marquardt(problem, rows.zeta0.copy(), rows.poses.copy())
    fac = variance_factors(problem, res.theta, res.poses, ("swivel",))
    per = np.array([fac[f"swivel.{i}"] for i in range(4)])
    assert sum(per[:, 1]) == pytest.approx(fac["swivel"][1], rel=1e-9)
    assert np.all(per[:, 1] > VCE_MIN_REDUNDANCY)
    assert 2.0 < per[0, 0] / np.mean(per[1:, 0]) < 8.0, per
    out = rescaled_sigma(sigma, fac)
    shrunk = cable_factors(per[:, 0], per[:, 1], sigma["swivel"])  # toward the pooled level, by empirical Bayes
    assert np.all(np.abs(np.log(shrunk / fac["swivel"][0])) < np.abs(np.log(per[:, 0] / fac["swivel"][0])))
    split = np.sqrt(shrunk / fac["swivel"][0]) * (math.sqrt(fac["swivel"][0]) if fac["swivel"][0] < 0.98 else 1)
    np.testing.assert_allclose(out["swivel"], sw * split, rtol=1e-9)
    assert out["swivel"][0] > 1.3 * np.max(out["swivel"][1:])  # the truth: 2x
    thin = dict(fac, **{"swivel.3": (per[3, 0], 0.5 * VCE_MIN_REDUNDANCY)})
    pooled = rescaled_sigma(sigma, thin)
    assert pooled is None or np.ptp(pooled["swivel"]) == 0.0
    # rows scattering 5x their variance on these degrees of freedom: model error, which a split would share out
    beyond = dict(fac, swivel=(5.0, fac["swivel"][1]))
    pooled = rescaled_sigma(sigma, beyond)
    assert pooled is None or np.ptp(pooled["swivel"]) == 0.0
    # a group whose sigma sits over sqrt(MISFIT_FACTOR) times its within-window noise was raised to a model
    # error: its cables' factors then say where the model misses, not how noisy they are (issue 28's guard)
    at_noise = {c: np.asarray(v, float) for c, v in sigma.items()}
    np.testing.assert_allclose(rescaled_sigma(sigma, fac, within=at_noise)["swivel"], out["swivel"], rtol=1e-12)
    raised = {c: v / (1.01 * math.sqrt(MISFIT_FACTOR)) for c, v in at_noise.items()}
    pooled = rescaled_sigma(sigma, fac, within=raised)
    assert pooled is None or np.ptp(pooled["swivel"]) == 0.0


def test_empirical_bayes_cable_factors_are_never_worse_than_the_better_of_pooled_and_own():
    """Four cables whose true variances differ as grid2's swivel rows do (1.82 / 0.77 / 0.79 / 1.82, issue 29),
    each estimated on r degrees of freedom (chi2_r / r), 2000 draws: the mean squared log error of
    cable_factors' shrunk variances is at most that of the better of the pooled variance (few r) and each
    cable's own (many r), and below both in between; identical estimates pool (prior_dof inf); the prior's
    dof solves var(log v) - mean trigamma(r / 2) = trigamma(d0 / 2) (scipy's trigamma)."""
    from scipy.special import digamma, polygamma

    from calib.selfcal.shrinkage import cable_factors, prior_dof

    true = np.array([1.82, 0.77, 0.79, 1.82])
    rng = np.random.default_rng(1)
    for r, gain in ((3.0, 1.02), (8.0, 0.85), (25.0, 1.02)):
        dof = np.full(4, r)
        v = true * rng.chisquare(r, (2000, 4)) / r
        own = np.mean(np.log(v / true) ** 2)
        pooled = np.mean(np.log(v.mean(axis=1, keepdims=True) / true) ** 2)
        shrunk = np.mean([np.log(cable_factors(x, dof, np.ones(4)) / true) ** 2 for x in v])
        assert shrunk <= gain * min(own, pooled), (r, own, pooled, shrunk)
    assert prior_dof(np.full(4, 2.0), np.full(4, 3.0)) == math.inf
    np.testing.assert_allclose(cable_factors(np.full(4, 2.0), np.full(4, 3.0), np.full(4, 0.5)), 2.0)
    v, dof = np.array([3.0, 0.4, 0.5, 2.5]), np.array([20.0, 22.0, 21.0, 25.0])
    d0 = prior_dof(v, dof)
    z = np.log(v) - digamma(dof / 2) + np.log(dof / 2)
    assert float(polygamma(1, d0 / 2)) == pytest.approx(np.var(z, ddof=1) - np.mean(polygamma(1, dof / 2)), rel=1e-8)


def test_a_group_dominated_by_model_error_weighs_what_its_rows_scatter_by():
    """Issue 28: a group whose rows scatter around the fit by far more than its window-mean sigma (Helmert
    factor above MISFIT_FACTOR) is model error: its sigma becomes its rows' scatter; a group the fit cannot
    judge (fewer than VCE_MIN_REDUNDANCY degrees of freedom, or a misfit on fewer than MISFIT_MIN_REDUNDANCY:
    yaw, 2.5) is then floored at the sensors' specifications;
    factors between 1 and MISFIT_FACTOR change nothing, and without a dominated group nothing is floored."""
    from calib.selfcal import sensor_noise
    from calib.selfcal.noise import MISFIT_FACTOR, rescaled_sigma

    sigma = {"tension": np.full(4, 0.2), "length": np.full(4, 1e-4), "swivel": np.full(4, 2e-4),
             "orientation": np.array([5e-5, 5e-5, 4e-5])}
    floor = sensor_noise(ROBOT)
    fac = {"tension": (900.0, 22.0), "length": (4.0, 9.0), "swivel": (0.25, 20.0), "tilt": (3000.0, 0.3),
           "yaw": (4000.0, 2.5)}
    out = rescaled_sigma(sigma, fac, floor)
    assert out["tension"][0] == pytest.approx(0.2 * 30.0)
    assert out["length"][0] == pytest.approx(1e-4)  # 4 < MISFIT_FACTOR: stays, the misfit shows in chi2
    assert out["swivel"][0] == pytest.approx(1e-4)
    np.testing.assert_allclose(out["orientation"], floor["orientation"])
    calm = dict(fac, tension=(MISFIT_FACTOR * 0.9, 22.0))
    out = rescaled_sigma(sigma, calm, floor)
    np.testing.assert_allclose(out["orientation"], sigma["orientation"])
    assert out["tension"][0] == pytest.approx(0.2)
    # noise, not misfit, on 3 degrees of freedom (more than 2): the group comes down to its rows' scatter
    out = rescaled_sigma(sigma, dict(calm, length=(0.25, 3.0)), floor)
    assert out["length"][0] == pytest.approx(0.5e-4)


def test_the_reference_window_follows_its_channels_down_never_up():
    """Issue 29: the reference window's mean is a window mean of the same readings as the rows, so where the
    rows' variance components bring a group below its within-window sigma (swivel: factor 1/4, sigma halved)
    its prior comes down with them; where they raise a group (tension: model error, factor 900) the
    reference reading carries no misfit and keeps its within-window sigma; an unjudged group (length) stays."""
    from calib.effects.priors import ReferenceNoise
    from calib.selfcal import sensor_noise
    from calib.selfcal.noise import reference_sigma, rescaled_sigma

    within = {"tension": np.full(4, 0.2), "length": np.full(4, 1e-6), "swivel": np.full(4, 4e-6),
              "orientation": np.array([5e-5, 5e-5, 4e-5])}
    fac = {"tension": (900.0, 22.0), "length": (0.01, 1.5), "swivel": (0.25, 20.0), "tilt": (1.0, 9.0),
           "yaw": (0.64, 6.0)}
    rows = rescaled_sigma(within, fac, sensor_noise(ROBOT))
    ref = reference_sigma(rows, within)
    assert rows["tension"][0] == pytest.approx(6.0) and ref["tension"][0] == pytest.approx(0.2)
    assert ref["swivel"][0] == pytest.approx(2e-6) == rows["swivel"][0]
    assert ref["length"][0] == pytest.approx(1e-6)
    np.testing.assert_allclose(ref["orientation"], [5e-5, 5e-5, 0.8 * 4e-5])
    # a 20-sample reference for rows of 20 and 80 samples (harmonic mean 32): variances go as 1 / size
    prior = ReferenceNoise.for_rows(ref, np.array([[0, 19], [100, 179]]), 20)
    assert prior.sd["swivel"] == pytest.approx(2e-6 * math.sqrt(32 / 20))
    assert prior.sd["yaw"] == pytest.approx(0.8 * 4e-5 * math.sqrt(32 / 20))


def test_estimate_noise_stays_near_the_paper_solve_on_the_misfitting_real_run(irma_data, tmp_path):
    """sc_8_final, whose rigid model misfits its window means some 25 times their sigma (issue 28): weighed
    by its window scatter alone the estimate-noise solve let the AHRS and swivel channels pull the pose (on
    the 27-pose run 247 mm from the paper-weight solve); now it lands no farther from the authors'
    zeta_0_real than the paper-weight solve + 2 mm (measured 3.9 mm, paper 8.7 mm; raw log 6.7 and 10.0)."""
    from acquisition.importers import import_irma
    from acquisition.runlog import read_run
    from calib.selfcal import solve

    zeta_0_real = np.array([0.36040811, 0.36748419, 1.15796772])
    out = tmp_path / "run"
    import_irma(irma_data / "sc_8_final_parsed.mat", out, targets=irma_data / "sc_control_target_8_final.mat")
    run = read_run(out)
    paper = solve(run.robot, run, noise="paper")
    est = solve(run.robot, run, noise="estimate")
    d_paper = np.linalg.norm(paper.initial_pose[:3] - zeta_0_real)
    d_est = np.linalg.norm(est.initial_pose[:3] - zeta_0_real)
    assert d_est <= d_paper + 0.002, (d_est, d_paper)
    assert np.linalg.norm(est.initial_pose[:3] - paper.initial_pose[:3]) < 0.02


def test_the_reference_prior_follows_each_cables_sigma():
    """Issue 29: rows weighed with one swivel sigma per cable give the reference window one prior per cable
    (scaled to its size, variances as 1 / size), kept as a list, and the same priors come back from it
    (calib.runrows rebuilds them from `cdpr solve --json`'s reference_noise); equal sigmas stay one number."""
    from calib.effects.priors import ReferenceNoise

    sigma = {"tension": np.full(4, 0.1), "length": np.full(4, 4e-7), "swivel": np.array([1e-6, 2e-6, 2e-6, 4e-6]),
             "orientation": np.array([1e-4, 1e-4, 2e-4])}
    prior = ReferenceNoise.for_rows(sigma, np.array([[0, 39], [50, 89]]), 10)  # 40-sample rows, a 10-sample ref
    np.testing.assert_allclose(prior.sd["swivel"], [2e-6, 4e-6, 4e-6, 8e-6])
    assert prior.sd["length"] == pytest.approx(8e-7)
    again = ReferenceNoise(**prior.sd)
    sd = [s.prior for s in again.params(ROBOT)]
    np.testing.assert_allclose(sd, [8e-7] * 4 + [2e-6, 4e-6, 4e-6, 8e-6] + [4e-4])


@pytest.mark.parametrize("motion", [0.0, 0.1, 0.25, 1.5])  # std of the motion in quantisation steps
def test_quantisation_error_of_a_window_mean_matches_monte_carlo(motion):
    """Widrow's quantisation of an average, sized from the windows' own readings: over 8 windows of 300 samples
    of a Gaussian motion about a mean placed anywhere within a step (a run's windows), the predicted variance
    matches the observed mean squared error of the window means over 400 such runs (still: step^2 / 12, not
    averaged away; a motion over several steps: averaged away; in between, one window's variance is a noisy
    figure of the motion and over-states the error, never under-states it)."""
    from calib.selfcal.noise import quantisation_variance

    rng = np.random.default_rng(29)
    step = 9.6e-5  # rad, a 16-bit swivel encoder
    x = (rng.uniform(0.0, 1.0, (1, 8, 400)) + motion * rng.standard_normal((300, 8, 400))) * step
    readings = np.round(x / step) * step  # (samples, windows, runs)
    observed = float(np.mean((readings.mean(0) - x.mean(0)) ** 2))
    predicted = float(np.mean(quantisation_variance(list(readings.transpose(1, 0, 2)), step)))
    if motion == 0.0:
        assert predicted == pytest.approx(step**2 / 12, rel=1e-6)
        assert observed == pytest.approx(step**2 / 12, rel=0.05)
    elif motion >= 1.0:  # dithered: only the sampling of a white motion is left (step^2 / 12 / 300)
        assert predicted < 1e-6 * step**2 and observed < step**2 / 12 / 100
    else:
        assert 1.3 < predicted / observed < 3.5, (predicted, observed)


def test_variance_components_never_shrink_a_channel_below_its_quantisation_error():
    """A group whose rows scatter a quarter of what its sigma says is halved, but a channel whose window means
    keep a quantisation error (``lower``) stops there, and one already below it is not raised."""
    from calib.selfcal.noise import rescaled_sigma

    sigma = {"tension": np.full(4, 0.02), "length": np.full(4, 1e-6), "swivel": np.full(4, 8e-6),
             "orientation": np.full(3, 1e-4)}
    factors = {c: (0.25, 20.0) for c in ("tension", "length", "swivel", "tilt", "yaw")}
    lower = {"swivel": np.array([6e-6, 2e-6, 6e-6, 9e-6]), "length": np.full(4, 1e-8)}
    out = rescaled_sigma(sigma, factors, lower=lower)
    assert out["tension"] == pytest.approx(np.full(4, 0.01))
    assert out["length"] == pytest.approx(np.full(4, 5e-7))
    assert out["swivel"] == pytest.approx([6e-6, 4e-6, 6e-6, 8e-6])


def test_a_sway_at_held_tension_is_not_taken_for_length_noise():
    """Force control holds the tensions while the platform sways (issue 29): the encoders count each sample's
    geometric length unstretched by its window's tension. The per-sample pose fit of pose_free_noise models
    that stretch at the window's tension, so a 1 mm sway of soft cables (EA 20 kN: the statics' tension at
    a swaying pose moves by newtons, its stretch by tens of um) leaves the lengths' pose-free noise near
    what the encoders add (0.1 um a sample; measured 0.81 um after the 4 rounds from the raw scatter of
    1.4 mm); stretching each sample by the statics' tension at its own pose instead (the model before) made
    it 23 um."""
    from calib.robot import robot_from_dict
    from calib.selfcal.model import MeasurementModel
    from calib.selfcal.noise import pose_free_noise

    data = ROBOT.to_dict()
    for c in data["cables"]:
        c["axial_stiffness"] = 2.0e4
    robot = robot_from_dict(data, "<soft>")
    model = MeasurementModel(robot)
    rng = np.random.default_rng(3)
    zeta0 = np.array([0.35, 0.35, 1.1, 0.0, 0.0, 0.0])
    theta = model.initial_params(zeta0)
    size, centres = 60, zeta0 + np.array([[dx, dy, dz, 0, 0, 0] for dx in (-0.1, 0.1) for dy in (-0.1, 0.1)
                                          for dz in (-0.05, 0.05)])
    t = np.arange(size) * 0.1
    sway = np.stack([1e-3 * np.sin(2 * math.pi * t / p + ph) for p, ph in ((4.0, 0.0), (5.0, 1.0), (7.0, 2.0))], 1)
    poses = np.concatenate([np.c_[c[:3] + sway, np.tile(c[3:], (size, 1)) + 1e-3 * sway] for c in centres])
    owner = np.repeat(np.arange(len(centres)), size)
    held = model.cable_tensions(theta, centres)[owner]
    pr = model.predict(poses, theta, ("length", "swivel", "orientation"), held_tension=held)
    n = robot.n
    noise = {"length": 1e-7, "swivel": 2e-5, "orientation": 5e-4}
    read = {c: pr[c].value + noise[c] * rng.standard_normal(pr[c].value.shape) for c in noise}
    sig = {"tau": held + 0.05 * rng.standard_normal(held.shape), "dl": read["length"], "dsigma": read["swivel"],
           "roll": read["orientation"][:, 0], "pitch": read["orientation"][:, 1], "dyaw": read["orientation"][:, 2]}
    wins = [Window(j * size, (j + 1) * size - 1) for j in range(len(centres))]
    spans = [(w.slice, c) for w, c in zip(wins, centres, strict=True)]
    ref = {"dl": np.zeros(n), "dsigma": np.zeros(n), "ori": np.zeros(3)}
    base = window_mean_noise(robot, sig, wins)

    class Unheld(MeasurementModel):  # no tension held: the statics' at each sample's own pose
        def cable_tensions(self, theta, poses):
            return np.full((len(poses), n), np.nan)

    held_fit = pose_free_noise(model, sig, spans, ref, theta, base)
    unheld_fit = pose_free_noise(Unheld(robot), sig, spans, ref, theta, base)
    assert base.groups["length"].sample > 1e-3  # the raw readings sway by a millimetre
    assert held_fit.sample["length"] < 1.5e-6
    assert unheld_fit.sample["length"] > 20 * held_fit.sample["length"]
