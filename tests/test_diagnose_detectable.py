"""The size from which a run's diagnosis would see a candidate it rejects (calib.diagnose.with_detectable_size,
issue 28): Baarda's minimal detectable effect along the score test's expected change, checked by Monte Carlo on
simulated runs whose noise did not shape it, and on the real sc_8_final, whose length scale one run cannot see."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from calib.diagnose import DETECT_POWER, detectable_factor, diagnose
from calib.effects import make_effects
from calib.robot import load_robot
from sim_backend.config import sim_config_from_dict
from sim_backend.equilibrium_rows import simulated_rows

ROBOT = load_robot("irma4u")
CANDIDATES = ("length_scale", "tension_offset", "cable_elasticity")
ALPHA_EACH = 0.01 / len(CANDIDATES)


def _length_scale(k, seed: int):
    """The length_scale candidate of a diagnosis of simulated rows with a hidden per-winch scale k."""
    d = simulated_rows(ROBOT, sim_config_from_dict({"effects": {"length_scale": {"k": [float(v) for v in k]}}}),
                       seed=seed)
    diag = diagnose(ROBOT, d.meas, d.sigma, d.guess_zeta0, d.guess_poses, candidates=make_effects(CANDIDATES),
                    refits=0, max_effects=0)
    return next(c for c in diag.ranking if c.effect == "length_scale")


def test_detectable_factor_is_the_noncentrality_of_the_power_over_the_score():
    crit = stats.chi2.isf(ALPHA_EACH, 4)
    f = detectable_factor(10.0, 4, ALPHA_EACH)
    assert stats.ncx2.sf(crit, 4, f * f * 10.0) == pytest.approx(DETECT_POWER, abs=1e-9)
    assert detectable_factor(40.0, 4, ALPHA_EACH) == pytest.approx(f / 2)  # the score grows as the size squared
    assert detectable_factor(10.0, 4, ALPHA_EACH, power=0.5) < f
    assert detectable_factor(0.0, 4, ALPHA_EACH) == np.inf


def test_an_effect_of_the_detectable_size_is_found_as_often_as_said():
    """A scale too small for seed 5's diagnosis (score p 0.28) gives its detectable size; hidden at that size
    in 80 other runs (independent noise), the score test finds it in about 80 % of them (measured 0.86); at
    half that size in about 11 % (the noncentral chi2 at a quarter of the noncentrality; measured 0.18)."""
    small = _length_scale(0.003 * np.array([0.015, -0.01, 0.02, 0.0]), seed=5)
    assert small.reason.code == "score_not_significant"
    n = small.reason.numbers
    size = np.array([v for v, _ in n["detectable"].values()])
    epc = np.array([small.epc[f"k_{i + 1}"] for i in range(4)])
    np.testing.assert_allclose(size, n["detect_factor"] * epc)
    assert n["detect_factor"] > 1 and "finds it with 80 % probability only from" in small.decision
    seeds = range(100, 180)
    found = np.mean([_length_scale(size, s).score_p < ALPHA_EACH for s in seeds])
    half = np.mean([_length_scale(size / 2, s).score_p < ALPHA_EACH for s in seeds])
    crit = stats.chi2.isf(ALPHA_EACH, 4)
    lam = detectable_factor(small.score, 4, ALPHA_EACH) ** 2 * small.score
    expected_half = stats.ncx2.sf(crit, 4, lam / 4)
    sd = np.sqrt(DETECT_POWER * (1 - DETECT_POWER) / len(seeds))
    assert abs(found - DETECT_POWER) < 3.5 * sd, found
    assert half < expected_half + 3.5 * np.sqrt(expected_half * (1 - expected_half) / len(seeds)), half
    assert half < found - 0.3


def test_one_real_run_sees_its_length_scale_only_from_about_one_percent(irma_data, tmp_path):
    """sc_8_final (parsed .mat, its targets): the parsed file's own scale (0.35-0.95 % with tension_offset,
    docs/effects.md) is below what one 8-pose run finds: the diagnosis says from which size it would."""
    from acquisition.cli import main as cdpr
    from acquisition.runlog import read_run
    from calib.diagnose import diagnose_run

    out = tmp_path / "sc8f"
    assert cdpr(["import", "irma", str(irma_data / "sc_8_final_parsed.mat"), "--targets",
                 str(irma_data / "sc_control_target_8_final.mat"), "-o", str(out)]) == 0
    diag = diagnose_run(read_run(out), max_effects=0)
    ls = next(c for c in diag.ranking if c.effect == "length_scale")
    assert ls.reason.code == "score_not_significant"
    k = np.array([v for v, _ in ls.reason.numbers["detectable"].values()])
    assert 1.2 < ls.reason.numbers["detect_factor"] < 2.0  # measured 1.50
    # measured 0.94, 1.10, 0.77, 1.51 % (0.95, 1.13, 0.77, 1.53 % before issue 29's windows at rest)
    assert np.all((np.abs(k) > 0.005) & (np.abs(k) < 0.02)), k
    assert "only from 1.5 times its expected change (k_1 = 0.00935" in ls.decision
