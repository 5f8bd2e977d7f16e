"""The sway term of the estimate noise (issue 29 point 2, calib.selfcal.sway): its figures against direct
computations, and the opt-in (SolveOptions.sway, `cdpr solve --noise estimate+sway`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calib.robot import load_robot
from calib.selfcal import SelfCalInputError, SolveOptions
from calib.selfcal.noise import ar1_factor
from calib.selfcal.sway import SwayOffset, sway_offset, sway_tension_variance, tension_sigma
from calib.statics import tension_model


def test_the_tension_variance_is_d_sigma_d_t_averaged_over_the_windows():
    """diag(D Sigma D^T) averaged over two poses, D by central differences of the tension model, summed
    entry by entry: the term's figure (about 0.8 N on the real sc_8_final) is this, not another contraction."""
    robot = load_robot("irma4u")
    poses = np.array([[0.36, 0.37, 1.16, 0.08, -0.07, 0.01], [0.30, 0.42, 1.10, 0.05, -0.04, -0.02]])
    sd = np.array([0.1e-3, 0.08e-3, 0.13e-3, 1e-4, 1e-4, 0.9e-4])
    corr = np.eye(6)
    corr[0, 4] = corr[4, 0] = 0.6  # a swing along x tilts the platform about y
    corr[1, 3] = corr[3, 1] = -0.5
    cov = corr * np.outer(sd, sd)
    offset = SwayOffset(cov, sd, np.zeros(6), 20.0)
    want = np.zeros(robot.n)
    for z in poses:
        D = np.zeros((robot.n, 6))
        for i in range(6):
            h = np.zeros(6)
            h[i] = 1e-6
            D[:, i] = (tension_model(robot, (z + h)[None], derivatives=False).tau[0]
                       - tension_model(robot, (z - h)[None], derivatives=False).tau[0]) / 2e-6
        for c in range(robot.n):
            want[c] += sum(D[c, i] * cov[i, j] * D[c, j] for i in range(6) for j in range(6)) / len(poses)
    got = sway_tension_variance(robot, poses, offset)
    np.testing.assert_allclose(got, want, rtol=1e-4)
    assert np.all(got > 0.01)  # N^2: a tenth of a millimetre of sway is a few tenths of a newton here
    np.testing.assert_allclose(tension_sigma(robot, np.full(robot.n, 0.2), poses, offset), np.sqrt(0.04 + want),
                               rtol=1e-4)


def test_the_offset_is_the_spread_of_window_means_about_the_equilibrium():
    """Per-sample poses that wander as an AR(1) (rho 0.7 along x, white along z; y follows x) about a fixed
    equilibrium, 300 windows of 30 samples: the sway's sd of a window mean is what the window means actually
    scatter by about the equilibrium (within 10 % where the wander is an AR(1): x, z), its AR(1) and the
    correlation across coordinates as drawn. y, an AR(1) plus white noise, is no AR(1): the fitted one's lag-1
    ratio mixes both and the term comes out 11 % short of y's scatter (measured, this seed)."""
    rng = np.random.default_rng(3)
    k, n, rho = 300, 30, 0.7
    x = np.zeros((k, n))
    x[:, 0] = rng.normal(0.0, 1.0, k)
    for t in range(1, n):
        x[:, t] = rho * x[:, t - 1] + np.sqrt(1 - rho**2) * rng.normal(0.0, 1.0, k)
    poses = np.zeros((k, n, 6))
    poses[..., 0] = 1e-4 * x
    poses[..., 1] = 0.5e-4 * x + 0.2e-4 * rng.normal(size=(k, n))
    poses[..., 2] = 1e-4 * rng.normal(size=(k, n))
    poses[..., 3:] = 1e-5 * rng.normal(size=(k, n, 3))
    owner = np.repeat(np.arange(k), n)
    off = sway_offset(poses.reshape(-1, 6), owner)
    scatter = np.sqrt(np.mean(poses.mean(axis=1) ** 2, axis=0))  # the window means about the equilibrium (0)
    np.testing.assert_allclose(off.sd[[0, 2]], scatter[[0, 2]], rtol=0.1)
    assert 0.85 * scatter[1] < off.sd[1] < scatter[1]  # 0.89
    assert off.sd[0] == pytest.approx(1e-4 * np.sqrt(ar1_factor(0.7, n) / n), rel=0.1)  # 0.042 mm, 2.4x white
    assert off.rho[0] == pytest.approx(0.7, abs=0.05) and off.rho[2] < 0.1
    assert off.cov[0, 1] / (off.sd[0] * off.sd[1]) == pytest.approx(0.93, abs=0.05)  # 0.5 / sqrt(0.25 + 0.04)
    assert off.window_size == pytest.approx(n)


def test_sway_is_a_term_of_the_estimate_noise_only():
    with pytest.raises(SelfCalInputError, match="sway is a term of the estimate noise; noise 'paper' has none"):
        SolveOptions(noise="paper", sway=True)
    assert SolveOptions(noise="estimate", sway=True).sway and not SolveOptions().sway


def test_cdpr_solve_noise_estimate_plus_sway(irma_data, tmp_path, capsys):
    """The parsed sc_8_final: the sway adds ~0.8 N to the within-window tension sigma (0.2 N), but the settled
    rounds raise the tension rows to their model error (11-12 N) either way, so the pose moves 0.06 mm."""
    from acquisition.cli import main
    from acquisition.importers import import_irma

    run = tmp_path / "parsed"
    import_irma(irma_data / "sc_8_final_parsed.mat", run, targets=irma_data / "sc_control_target_8_final.mat")
    docs = {}
    for noise in ("estimate", "estimate+sway"):
        assert main(["solve", str(run), "--noise", noise, "--json"]) == 0
        docs[noise] = json.loads(capsys.readouterr().out)
    assert docs["estimate+sway"]["noise"]["source"] == "estimate+sway"
    assert docs["estimate"]["noise"]["source"] == "estimate"
    a, b = (np.array(docs[c]["initial_pose"][:3]) for c in docs)
    assert 0.0 < np.linalg.norm(a - b) < 0.3e-3  # 0.06 mm
    assert main(["solve", str(run), "--noise", "estimate+sway", "--effects", "tension_offset"]) == 2
    assert "--noise estimate+sway is a plain solve's weighting" in capsys.readouterr().err
