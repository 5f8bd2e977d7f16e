"""Issue 30: the sixteen rough edges a new user met. One test (or a few) per point, each failing without
its fix; the points about the IRMA importers read the real recordings (tests/conftest.py: irma_data)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from acquisition.cli import main
from acquisition.runlog import read_run

REPO = Path(__file__).resolve().parent.parent


def _one_sentence(err: str) -> str:
    assert err.count("\n") == 1 and err.startswith("cdpr: ") and err.endswith(".\n"), err
    assert "Traceback" not in err and "usage:" not in err
    return err


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def run8(irma_data, tmp_path_factory) -> Path:
    """sc_8_final (parsed) imported, solved with the default options once: a run with its solution."""
    out = tmp_path_factory.mktemp("r30") / "R"
    assert main(["import", "irma", str(irma_data / "sc_8_final_parsed.mat"), "-o", str(out)]) == 0
    assert main(["solve", str(out), "--json"]) == 0
    return out


@pytest.fixture
def run(run8, tmp_path) -> Path:
    r = tmp_path / "R"
    shutil.copytree(run8, r)
    return r


# ---- 1: an output that is, holds or is inside an input is refused, with or without --force ------------------


def test_an_output_that_is_holds_or_is_inside_the_input_run_is_refused_even_with_force(run, capsys):
    (run / "bus.blf").write_bytes(b"")  # replay checks for its record first
    (run / "serial.rec").write_bytes(b"")
    before = _tree(run)
    capsys.readouterr()
    cases = [
        (["diagnose", str(run), "--plots", str(run)], f"--plots {run} is the input {run}"),
        (["diagnose", str(run), "--html", str(run)], f"--html {run} is the input {run}"),
        (["diagnose", str(run), "--html", str(run / "d.html")], f"--html {run / 'd.html'} is inside the input {run}"),
        (["export", str(run), "--format", "mcap", "-o", str(run)], f"-o {run} is the input {run}"),
        (["export", str(run), "--format", "csv", "-o", str(run.parent)], f"-o {run.parent} holds the input {run}"),
        (["replay", str(run), "--out", str(run)], f"--out {run} is the input {run}"),
    ]
    for args, said in cases:
        for extra in ([], ["--force"]):
            assert main([*args, *extra]) == 2, args
            err = _one_sentence(capsys.readouterr().err)
            assert said in err and "even --force cannot" in err, err
    assert _tree(run) == before and not list(run.parent.glob("R.replaced-*"))


def test_an_import_never_writes_onto_its_own_input(irma_data, tmp_path, capsys):
    src = tmp_path / "sc.mat"
    shutil.copy(irma_data / "sc_8_final_parsed.mat", src)
    assert main(["import", "irma", str(src), "-o", str(src), "--force"]) == 2
    assert f"-o {src} is the input {src}" in _one_sentence(capsys.readouterr().err)
    assert src.read_bytes() == (irma_data / "sc_8_final_parsed.mat").read_bytes()


# ---- 2, 3, 4, 15: the IRMA importers -----------------------------------------------------------------------


def test_the_power_on_rest_is_not_a_setpoint_and_one_warning_says_so(irma_data, tmp_path, capsys):
    planned = read_run_targets(irma_data / "sc_control_target_8.mat")
    for name in ("sc_8_medium_a_parsed.mat", "sc_8_medium_a.log"):
        out = tmp_path / name
        assert main(["import", "irma", str(irma_data / name), "-o", str(out)]) == 0
        cap = capsys.readouterr()
        assert "8 setpoints" in cap.out
        doubt = [line for line in cap.err.splitlines() if "setpoints found without --targets" in line]
        assert len(doubt) == 1 and "rest before the sequence, not a setpoint" in doubt[0], cap.err
        r = read_run(out)
        np.testing.assert_allclose(r.setpoints, planned, atol=2e-3)  # the plan, found without it
        rest = r.phase == "rest"
        assert 30 <= rest.sum() <= 60 and np.all(r.setpoint[rest] == -1) and rest[:70].sum() == rest.sum()
    # a run without a rest nor a doubtful move imports without a word
    assert main(["import", "irma", str(irma_data / "sc_8_final_parsed.mat"), "-o", str(tmp_path / "f")]) == 0
    assert capsys.readouterr().err == ""


def read_run_targets(path: Path) -> np.ndarray:
    from acquisition.importers import read_irma_targets

    return read_irma_targets(path)[0]


def test_targets_of_another_experiment_are_one_sentence_and_nothing_is_written(irma_data, tmp_path, capsys):
    out = tmp_path / "R27"
    args = ["import", "irma", str(irma_data / "sc_27_medium_a_parsed.mat"), "--targets",
            str(irma_data / "sc_control_target_8.mat"), "-o", str(out)]
    assert main(args) == 2
    err = _one_sentence(capsys.readouterr().err)
    assert "sc_control_target_8.mat: its 8 setpoints do not match sc_27_medium_a_parsed.mat" in err
    assert not out.exists()
    args[4] = str(irma_data / "sc_control_target_27.mat")
    assert main(args) == 0 and "27 setpoints" in capsys.readouterr().out


def test_the_controllers_tension_target_csv_is_accepted_as_targets(irma_data, tmp_path, capsys):
    out = tmp_path / "csv"
    assert main(["import", "irma", str(irma_data / "sc_8_medium_a_parsed.mat"), "--targets",
                 str(irma_data / "tension_target_8.csv"), "-o", str(out)]) == 0
    assert capsys.readouterr().err == ""  # with targets, no setpoint is in doubt
    r = read_run(out)
    np.testing.assert_allclose(r.setpoints, read_run_targets(irma_data / "sc_control_target_8.mat"), atol=0.05)
    assert sorted(set(r.setpoint) - {-1}) == list(range(8)) and r.ideal_poses is None
    bad = tmp_path / "t.csv"
    bad.write_text("1,2\n3,4\n")
    assert main(["import", "irma", str(irma_data / "sc_8_medium_a_parsed.mat"), "--targets", str(bad),
                 "-o", str(tmp_path / "x")]) == 2
    assert f"{bad}: 2 lines, expected 4" in _one_sentence(capsys.readouterr().err)


def test_a_log_without_any_ahrs_line_says_so(irma_data, tmp_path, capsys):
    log = irma_data / "sc_8_medium_b.log"
    assert main(["import", "irma", str(log), "-o", str(tmp_path / "b")]) == 2
    assert _one_sentence(capsys.readouterr().err) == (
        f"cdpr: {log}: the log has no AHRS line (type 5) at all, only cable lines, so it holds no roll, pitch or "
        "yaw and cannot be imported.\n")


# ---- 5: missing output folders: one rule, checked before any work ------------------------------------------


def test_missing_output_folders_are_made_by_every_command(run, tmp_path, capsys):
    deep = tmp_path / "a" / "b"
    assert main(["export", str(run), "--format", "npz", "-o", str(deep / "x.npz")]) == 0
    assert (deep / "x.npz").is_file()
    assert main(["import", "irma", str(run.parent / "nosuch.mat"), "-o", str(tmp_path / "c" / "d")]) == 2
    assert not (tmp_path / "c").exists()  # a refused command makes no folder
    capsys.readouterr()


def test_an_output_under_a_file_is_refused_before_any_work(run, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for args in (["diagnose", str(run), "--html", str(blocker / "d" / "d.html")],
                 ["export", str(run), "--format", "csv", "-o", str(blocker / "x.csv")],
                 ["startup", "--backend", "sim", "--no-html", "--out", str(blocker / "R")]):
        assert main(args) == 2
        assert f"cannot be written: {blocker} is not a folder." in _one_sentence(capsys.readouterr().err)


# ---- 6: an error quotes at most a line ------------------------------------------------------------------------


def test_a_bad_configuration_file_is_quoted_by_one_short_line(run, capsys):
    assert main(["startup", "--backend", "sim", "--no-html", "--sim-config", str(run / "samples.csv"),
                 "--out", str(run.parent / "S")]) == 2
    err = _one_sentence(capsys.readouterr().err)
    assert len(err) < 200 and "..." in err


# ---- 7: a closed pipe ends quietly ----------------------------------------------------------------------------


def test_a_closed_stdout_pipe_ends_quietly():
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-c", "import sys; from acquisition.cli import main; "
                             "sys.exit(main(['poses', '--grid', '2', '--json']))"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=REPO)
    proc.stdout.close()  # the reader left before the command wrote (`| head -c 10` once it has its bytes)
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141 and err == ""


# ---- 9: --tolerance ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("value, said", [
    ("3", "--tolerance '3' needs its unit: 3mm, 3cm or 3m."),
    ("-3mm", "--tolerance '-3mm' must be a positive length."),
    ("3parsecs", "--tolerance '3parsecs' is not a length: give a number and its unit, e.g. 3mm, 0.5cm or 0.003m."),
])
def test_a_tolerance_needs_its_unit_and_a_bad_one_is_one_sentence(value, said, tmp_path, capsys):
    for command in (["startup", "--backend", "sim", "--no-html", "--out", str(tmp_path / "R")],
                    ["study", "--plan", "sequential", "--runs", "1", "--out", str(tmp_path / "S")]):
        assert main([*command, "--tolerance", value]) == 2
        assert _one_sentence(capsys.readouterr().err) == f"cdpr: {said}\n"
    assert not (tmp_path / "R").exists() and not (tmp_path / "S").exists()


# ---- 10: exploring does not change the run's solution ------------------------------------------------------


def test_exploratory_solves_leave_the_runs_solution_and_export_names_it(run, tmp_path, capsys):
    saved = (run / "solution.json").read_bytes()
    for extra in (["--effects", "tension_offset"], ["--noise", "estimate"], ["--method", "lse", "--stride", "20"]):
        assert main(["solve", str(run), *extra]) == 0
        out = capsys.readouterr().out
        assert f"not saved: {run / 'solution.json'} stays the run's solution (--save to replace it)" in out
        assert (run / "solution.json").read_bytes() == saved
    assert main(["export", str(run), "--format", "npz", "-o", str(tmp_path / "a.npz")]) == 0
    assert (f"with its solution {run / 'solution.json'} (method tlse, noise paper, effects none"
            in capsys.readouterr().out)
    assert main(["solve", str(run), "--noise", "estimate", "--save", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert json.loads((run / "solution.json").read_text()) == doc and doc["noise"]["source"] == "estimate"
    assert main(["export", str(run), "--format", "npz", "-o", str(tmp_path / "b.npz")]) == 0
    assert "(method tlse, noise estimate, effects " in capsys.readouterr().out


# ---- 14: run.yaml records --pause, and previous_offsets names the run the offsets came from -----------------


def test_run_yaml_records_the_pauses_and_the_run_the_previous_offsets_came_from(tmp_path, capsys):
    run, offsets = tmp_path / "R", tmp_path / "offsets.yaml"
    base = ["startup", "--backend", "sim", "--grid", "2", "--no-html", "--json", "--out", str(run),
            "--offsets", str(offsets)]
    assert main([*base, "--pause", "0:0.5:home"]) == 0
    meta = yaml.safe_load((run / "run.yaml").read_text())
    assert meta["pauses"] == [{"after": 0, "seconds": 0.5, "home": True}]
    assert yaml.safe_load(offsets.read_text())["run"] == str(run)
    assert main([*base, "--force"]) == 0
    kept = next(tmp_path.glob("R.replaced-*"))
    meta = yaml.safe_load((run / "run.yaml").read_text())
    assert meta["previous_offsets"]["run"] == str(kept) and "pauses" not in meta
    assert yaml.safe_load((kept / "run.yaml").read_text())["pauses"][0]["after"] == 0
    capsys.readouterr()
