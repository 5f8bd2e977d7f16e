"""The joint fits converge (issue 28, done-when 1 and 6): on the two real medium runs the cables' compliance
and the runs' heights form a curved valley; Levenberg-Marquardt with geodesic acceleration reaches its bottom
and says so, the straight steps stop at the cap and the fit says that too."""

from __future__ import annotations

import numpy as np
import pytest

from calib import multirun
from calib.effects import available_effects
from calib.runselect import Judge


@pytest.fixture(scope="module")
def medium_runs(irma_data, tmp_path_factory):
    from acquisition.importers import import_irma
    from acquisition.runlog import read_run
    from calib.runrows import run_rows

    out = tmp_path_factory.mktemp("medium")
    items = []
    for name, targets in (("sc_8_medium_a", "sc_control_target_8.mat"),
                          ("sc_27_medium_a", "sc_control_target_27.mat")):
        import_irma(irma_data / f"{name}_parsed.mat", out / name, targets=irma_data / targets)
        items.append((name, run_rows(read_run(out / name))))
    return items


def _pair_fit(items) -> multirun.JointFit:
    """The judged fit of cable_elasticity, tension_offset as the selection makes it: started from both
    members' own judged fits, one weights round and a last one of at most 60 iterations."""
    classes = available_effects()
    judge = Judge(items, lambda names: [classes[n]() for n in names])
    base = judge.fit([])
    a, b = judge.fit(["cable_elasticity"], base.fit), judge.fit(["tension_offset"], base.fit)
    return judge.fit(["cable_elasticity", "tension_offset"], a.fit, b.fit).fit


def _to_the_bottom(fit: multirun.JointFit, monkeypatch) -> tuple[float, float]:
    """The same fit continued (same weights) with a criterion 1e5 times tighter: its chi2 and compliance."""
    monkeypatch.setattr(multirun, "FTOL", 1e-10)
    runs, cost, stop, _, _ = multirun.lm_runs(fit.runs, fit.shared, max_iter=400, covariance=False)
    monkeypatch.undo()
    assert stop.converged
    return cost, float(runs[0].theta[runs[0].theta.shape[0] - fit.values.shape[0]])


def test_the_curved_valley_is_followed_to_its_bottom_and_a_cap_is_said(medium_runs, monkeypatch):
    """With geodesic acceleration the fit converges well within its cap and is where a 1e5 times tighter
    criterion leaves it (chi2 within 0.01, compliance within 0.1 sigma); with straight steps (acceleration
    refused) the same fit stops at the cap 0.3-0.6 sigma short of it, and says so."""
    fit = _pair_fit(medium_runs)
    conv = fit.convergence()
    assert conv["converged"] and conv["criterion"] == "decrease" and conv["iterations"] < 40
    assert conv["remaining_chi2"] <= multirun.FTOL * fit.chi2
    assert fit.convergence_words().startswith("converged")
    sd = float(np.sqrt(fit.cov[0, 0]))
    chi2, c = _to_the_bottom(fit, monkeypatch)
    assert fit.chi2 - chi2 < 0.01 and abs(c - fit.values[0]) < 0.1 * sd
    assert 5.0e3 < 1.0 / c < 6.5e3  # EA (N) at the bottom of the valley

    monkeypatch.setattr(multirun, "GEO_ALPHA", 0.0)  # every acceleration refused: Marquardt's straight steps
    capped = _pair_fit(medium_runs)
    monkeypatch.undo()
    assert not capped.converged and capped.stop.reason == "cap" and capped.stop.remaining > 0.05
    assert capped.convergence_words().startswith("WARNING: not converged (stopped by the iteration cap")
    assert 0.3 * sd < abs(capped.values[0] - c) < 0.6 * sd
    assert capped.chi2 - chi2 > 0.1
