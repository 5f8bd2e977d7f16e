"""Exporters (mat, npz, csv) and the `cdpr import irma` / `cdpr export` commands: round trips by value."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from acquisition.cli import main
from acquisition.export import ExportError, export_run
from acquisition.importers import IRMA_HOMING_LENGTHS, IRMA_HOMING_SWIVELS, import_irma
from acquisition.runlog import read_run
from acquisition.runwriter import new_run, write_run, write_solution

SOLUTION = {
    "method": "tlse",
    "initial_pose": [0.3604, 0.3675, 1.158, 0.0847, -0.0717, 0.007],
    "reference_sample": 3,
    "sensor_offsets": {"length": [1.65, 1.10, 1.64, 2.04], "swivel": [1.28, -1.08, 1.05, -1.28], "yaw": 0.01},
    "windows": [[2, 5], [7, 9]],
    "chi2": 29.9,
    "dof": 57,
    "residuals": {"tension": {"rms": 9.1, "rms_normalized": 0.91}},
    "effects": {},
    "timing": {"solve_s": 0.012},
}


@pytest.fixture()
def small_run(tmp_path: Path):
    rng = np.random.default_rng(7)
    N = 12
    run = new_run(
        "irma4u", "equilibrium", 0.1, "sim",
        t=np.arange(N) * 0.1, tau=100 + rng.normal(0, 5, (N, 4)), tau_ref=np.full((N, 4), 100.0),
        dl=rng.normal(0, 0.2, (N, 4)), dsigma=rng.normal(0, 0.1, (N, 4)),
        roll=rng.normal(0, 0.05, N), pitch=rng.normal(0, 0.05, N), dyaw=rng.normal(0, 0.01, N),
        phase=["pretension"] * 4 + ["hold"] * 8, setpoint=[-1] * 4 + [0] * 8,
        setpoints=[[118.48, 170.83, 115.57, 82.98]], ideal_poses=[[0.4, 0.4, 1.2, 0.084, -0.0905, 0.0047]],
        extra={"motor_position_1": np.arange(N, dtype=np.int64) * 17},
    )
    return write_run(tmp_path / "run", run)


def loadmat_st(path: Path):
    return scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)["st"]


def test_mat_export_of_an_unsolved_run_holds_the_deltas(small_run, tmp_path):
    run = read_run(small_run.path)
    export_run(run, "mat", tmp_path / "x.mat")
    st = loadmat_st(tmp_path / "x.mat")
    assert not bool(st.absolute)
    np.testing.assert_array_equal(st.t, run.t)
    np.testing.assert_array_equal(st.epsilon, np.vstack([run.roll, run.pitch, run.dyaw]))
    np.testing.assert_array_equal(st.cable_length, run.dl.T)
    np.testing.assert_array_equal(st.swivel, run.dsigma.T)
    np.testing.assert_array_equal(st.tensions, run.tau.T)
    np.testing.assert_array_equal(st.target_tensions, run.tau_ref.T)
    raw = scipy.io.loadmat(tmp_path / "x.mat", squeeze_me=False)["st"][0, 0]  # one column per pose, unsqueezed
    np.testing.assert_array_equal(raw["setpoints"], run.setpoints.T)
    np.testing.assert_array_equal(raw["ideal_poses"], run.ideal_poses.T)
    assert raw["cable_length"].shape == (4, 12) and raw["t"].shape == (1, 12)
    assert list(st.phase) == list(run.phase) and st.setpoint.tolist() == run.setpoint.tolist()
    assert st.extra.motor_position_1.tolist() == list(range(0, 12 * 17, 17))
    assert json.loads(st.meta)["procedure"]["method"] == "equilibrium"
    assert "solution" not in st._fieldnames


def test_mat_export_of_a_solved_run_is_absolute(small_run, tmp_path):
    write_solution(small_run.path, SOLUTION)
    run = read_run(small_run.path)
    export_run(run, "mat", tmp_path / "s.mat")
    st = loadmat_st(tmp_path / "s.mat")
    off = SOLUTION["sensor_offsets"]
    assert bool(st.absolute)
    np.testing.assert_allclose(st.cable_length, (np.array(off["length"]) + run.dl).T, rtol=0, atol=1e-15)
    np.testing.assert_allclose(st.swivel, (np.array(off["swivel"]) + run.dsigma).T, rtol=0, atol=1e-15)
    np.testing.assert_allclose(st.epsilon[2], off["yaw"] + run.dyaw, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(st.delta_length, run.dl.T)
    np.testing.assert_allclose(st.solution.initial_pose, SOLUTION["initial_pose"])
    np.testing.assert_array_equal(st.solution.windows, [[2, 5], [7, 9]])
    assert st.solution.method == "tlse" and st.solution.residuals.tension.rms == 9.1


def test_solved_irma_run_exports_back_to_the_authors_parsed_struct(irma_data, tmp_path):
    """Offsets = homing values: the exported absolute channels are the authors' st, by value."""
    run = import_irma(irma_data / "sc_8_final_parsed.mat", tmp_path / "irma")
    write_solution(run.path, {"sensor_offsets": {"length": list(IRMA_HOMING_LENGTHS),
                                                 "swivel": list(IRMA_HOMING_SWIVELS), "yaw": 0.0}})
    export_run(read_run(run.path), "mat", tmp_path / "irma.mat")
    ours = loadmat_st(tmp_path / "irma.mat")
    theirs = loadmat_st(irma_data / "sc_8_final_parsed.mat")
    np.testing.assert_allclose(ours.t + run.meta["time_origin"], theirs.t, rtol=0, atol=1e-9)
    for name in ("epsilon", "cable_length", "swivel", "tensions", "target_tensions"):
        np.testing.assert_allclose(getattr(ours, name), getattr(theirs, name), rtol=0, atol=1e-12, err_msg=name)


def test_npz_export_round_trip(small_run, tmp_path):
    write_solution(small_run.path, SOLUTION)
    run = read_run(small_run.path)
    export_run(run, "npz", tmp_path / "x.data")  # any file name is kept as given
    with np.load(tmp_path / "x.data", allow_pickle=False) as z:
        for name, values in run.columns().items():
            np.testing.assert_array_equal(z[name], values, err_msg=name)
        np.testing.assert_allclose(z["length_2"], SOLUTION["sensor_offsets"]["length"][1] + run.dl[:, 1], atol=1e-15)
        np.testing.assert_allclose(z["yaw"], 0.01 + run.dyaw, atol=1e-15)
        assert json.loads(str(z["meta"]))["robot"] == "irma4u"
        assert json.loads(str(z["solution"]))["chi2"] == 29.9


def test_csv_export_round_trip(small_run, tmp_path):
    run = read_run(small_run.path)
    export_run(run, "csv", tmp_path / "plain.csv")
    with open(tmp_path / "plain.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 12 and "length_1" not in rows[0]
    assert [float(r["dl_3"]) for r in rows] == run.dl[:, 2].tolist()
    write_solution(small_run.path, SOLUTION)
    export_run(read_run(small_run.path), "csv", tmp_path / "solved.csv")
    with open(tmp_path / "solved.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    np.testing.assert_allclose([float(r["swivel_4"]) for r in rows], -1.28 + run.dsigma[:, 3], atol=1e-15)
    assert rows[5]["phase"] == "hold" and rows[0]["setpoint"] == "-1"


def test_bad_solution_and_format(small_run, tmp_path):
    run = read_run(small_run.path)
    with pytest.raises(ExportError, match="format 'xls' is not one of mat, npz, csv"):
        export_run(run, "xls", tmp_path / "x.xls")
    bad = {"sensor_offsets": {"length": [1.0, 2.0, 3.0], "swivel": [0, 0, 0, 0], "yaw": 0}}
    write_solution(small_run.path, bad)
    with pytest.raises(ExportError, match=r"solution\.json: field 'sensor_offsets\.length' = \[1\.0, 2\.0, 3\.0\]"):
        export_run(run, "mat", tmp_path / "x.mat")


def test_cli_import_and_export(irma_data, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["import", "irma", str(irma_data / "sc_8_final.log"), "-o", str(out)]) == 0
    assert "1280 samples" in capsys.readouterr().out
    assert read_run(out).source == "import:irma-log"
    assert main(["import", "irma", str(irma_data / "sc_8_final.log"), "-o", str(out)]) == 2
    assert "already holds a run" in capsys.readouterr().err
    assert main(["export", str(out), "--format", "mat", "-o", str(tmp_path / "r.mat")]) == 0
    assert loadmat_st(tmp_path / "r.mat").tensions.shape == (4, 1280)
    assert main(["export", str(tmp_path / "missing"), "--format", "csv", "-o", str(tmp_path / "r.csv")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cdpr: ") and "missing: not a run folder" in err and err.count("\n") == 1
    assert main(["import", "irma", str(irma_data / "README.md"), "-o", str(tmp_path / "x")]) == 2
