"""Is a robot effect one value across runs (calib.spread): the consistency chi2 and the between-run sigma."""

from __future__ import annotations

import numpy as np
from scipy import stats

from calib.spread import between_run_sd, consistency


def test_between_run_sd_is_dersimonian_laird():
    # two runs 3 apart with unit variances: Q = 4.5, S1 = 2, S2 = 2, tau^2 = (4.5 - 1) / (2 - 1) = 3.5
    tau = between_run_sd(np.array([[0.0, 0.0], [3.0, 0.5]]), np.ones((2, 2)))
    assert np.allclose(tau, [np.sqrt(3.5), 0.0])  # the second column agrees within its sigma: no spread
    assert np.allclose(between_run_sd(np.array([[1.0, 2.0]]), np.ones((1, 2))), 0.0)  # one run: none


def test_consistency_counts_only_what_each_run_sees():
    """Run 2 does not see parameter 2 (a zero variance is no information): its value there adds neither
    chi2 nor a degree of freedom."""
    x = np.array([[1.0, 5.0], [-1.0, 7.0]])
    cov = np.array([np.eye(2), np.diag([1.0, 0.0])])
    chi2, dof = consistency(x, cov)
    assert np.isclose(chi2, 2.0) and dof == 1
    chi2, dof = consistency(x, np.array([np.eye(2), np.eye(2)]))
    assert np.isclose(chi2, 2.0 + 2.0) and dof == 2


def test_consistency_rejects_at_its_level_and_sees_a_real_spread():
    """Three runs, four correlated parameters with unequal covariances: without a spread the 1 % test
    rejects about 1 % of the time; with a between-run spread of 2 sigma it rejects nearly always, and the
    between-run sigma is of the size drawn."""
    rng = np.random.default_rng(7)
    trials, reject, reject_spread, taus = 2000, 0, 0, []
    for _ in range(trials):
        covs = []
        for _ in range(3):
            a = rng.normal(size=(4, 4))
            covs.append(a @ a.T / 4 + 0.05 * np.eye(4))
        covs = np.array(covs)
        truth = rng.normal(size=4)
        x = np.array([rng.multivariate_normal(truth, c) for c in covs])
        chi2, dof = consistency(x, covs)
        reject += stats.chi2.sf(chi2, dof) < 0.01
        sd = np.sqrt(np.diagonal(covs, axis1=1, axis2=2)).mean()
        xs = x + rng.normal(scale=2.0 * sd, size=(3, 4))
        chi2, dof = consistency(xs, covs)
        reject_spread += stats.chi2.sf(chi2, dof) < 0.01
        taus.append(between_run_sd(xs, np.diagonal(covs, axis1=1, axis2=2)).mean() / (2.0 * sd))
    assert dof == 8
    assert 0.004 <= reject / trials <= 0.02
    assert reject_spread / trials > 0.9
    assert 0.6 < np.median(taus) < 1.2
