"""One honest 1-sigma everywhere (issue 29): the sequential stop, the startup's summary, `cdpr study`'s table
and `cdpr solve` print the same 1-sigma, that of the estimate-noise solve, and the paper's weights stay
available by name. One simulated sequential startup (a few seconds of CPU on an idle machine)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from acquisition.cli import main
from acquisition.report import pose_lines
from acquisition.session import simulated_startup
from acquisition.study import RunTask, StudyConfig, plan_statistics, run_result


@pytest.fixture(scope="module")
def sequential(tmp_path_factory):
    """A sequential startup that stops below 0.5 mm (seed 2, candidates every 0.25 m)."""
    out = tmp_path_factory.mktemp("one_sigma") / "seq"
    return out, simulated_startup(out, plan="sequential", tolerance=5e-4, step=0.25, seed=2)


def test_the_sequential_stop_prints_the_one_sigma_it_stopped_below(sequential):
    """The stop rule's sentence names the 1-sigma the summary then prints (the final estimate-noise solve's
    position 1-sigma, sqrt of the covariance's trace), and it is below the tolerance."""
    _, out = sequential
    sol = out["solution"]
    sigma = np.asarray(sol["initial_pose_sigma"][:3])
    printed = float(np.linalg.norm(sigma))
    assert sol["noise"]["source"] == "estimate"
    assert printed < 5e-4
    assert out["message"] == (f"sequential: 1-sigma of the initial position {1000 * printed:.2f} mm < tolerance "
                              f"0.5 mm after {out['setpoints']} poses.")
    # the pose lines of the summary carry the same per-axis sigmas
    assert pose_lines(sol["initial_pose"], sol["initial_pose_sigma"])[0].endswith(f"+- {1000 * sigma[0]:.3f} mm")


def test_study_table_and_cdpr_solve_print_the_startups_sigma(sequential, capsys):
    """`cdpr study` reads the startup's own sigma (no solve of its own), and `cdpr solve RUN` prints it
    again by default; `--noise paper` gives the paper's weights, a 1-sigma tens of times wider."""
    folder, out = sequential
    task = RunTask("sequential", 2, StudyConfig(tolerance="0.5mm"))
    res = run_result(task, out, {"initial_pose": out["truth"]})
    assert res["position_sigma_m"] == out["solution"]["initial_pose_sigma"][:3]
    stats = plan_statistics([res])
    assert stats["sigma_mm"]["rms"] == pytest.approx(1000 * np.linalg.norm(res["position_sigma_m"]), rel=1e-9)
    assert main(["solve", str(folder), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["noise"]["source"] == "estimate"
    np.testing.assert_allclose(doc["initial_pose_sigma"], out["solution"]["initial_pose_sigma"], rtol=1e-6)
    assert main(["solve", str(folder), "--json", "--noise", "paper"]) == 0
    paper = json.loads(capsys.readouterr().out)
    assert paper["noise"]["source"] == "paper"
    assert np.linalg.norm(paper["initial_pose_sigma"][:3]) > 10 * np.linalg.norm(doc["initial_pose_sigma"][:3])
