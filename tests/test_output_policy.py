"""Issue 21: nothing a user types loses data, every bad input gets one sentence. One test per repro of the
issue (signals: tests/test_signals.py), and the output policy's own rules (acquisition/outputs.py)."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from acquisition.cli import main
from acquisition.outputs import OutputExistsError, check_output, claim_output, kept_name
from acquisition.runlog import read_run

REPO = Path(__file__).resolve().parent.parent


def _one_sentence(err: str) -> str:
    assert err.count("\n") == 1 and err.startswith("cdpr: ") and err.endswith(".\n"), err
    assert "Traceback" not in err
    return err


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory) -> Path:
    """A simulated startup run (grid 2, 8 setpoints), made once."""
    out = tmp_path_factory.mktemp("sim") / "R"
    assert main(["startup", "--backend", "sim", "--grid", "2", "--out", str(out), "--no-html", "--json"]) == 0
    return out


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_startup_onto_an_existing_run_is_refused_and_force_keeps_the_old_run(sim_run, tmp_path, capsys):
    run = tmp_path / "R"
    shutil.copytree(sim_run, run)
    before = _files(run)
    capsys.readouterr()
    args = ["startup", "--backend", "sim", "--grid", "2", "--seed", "1", "--out", str(run), "--no-html", "--json"]
    assert main(args) == 2
    err = _one_sentence(capsys.readouterr().err)
    assert f"--out {run} already holds a run" in err and "--force" in err
    assert _files(run) == before  # nothing touched
    assert main([*args, "--force"]) == 0
    err = capsys.readouterr().err
    kept = [p for p in tmp_path.iterdir() if p.name.startswith("R.replaced-")]
    assert len(kept) == 1 and re.fullmatch(r"R\.replaced-\d{8}-\d{6}", kept[0].name)
    assert f"cdpr: note: {run} existed; it is kept as {kept[0]}." in err
    assert _files(kept[0]) == before  # the replaced run, byte for byte
    new, old = read_run(run), read_run(kept[0])
    assert len(new) > 100 and not np.array_equal(new.tau[:100], old.tau[:100])  # seed 1: another run


def test_startup_into_a_folder_holding_other_files_is_refused(tmp_path, capsys):
    folder = tmp_path / "notes"
    folder.mkdir()
    (folder / "todo.txt").write_text("calibrate\n")
    assert main(["startup", "--backend", "sim", "--grid", "2", "--out", str(folder), "--no-html"]) == 2
    assert f"--out {folder} already holds files" in _one_sentence(capsys.readouterr().err)
    assert [p.name for p in folder.iterdir()] == ["todo.txt"]


def test_export_never_replaces_the_runs_own_log_and_a_file_only_with_force(sim_run, tmp_path, capsys):
    run = tmp_path / "R"
    shutil.copytree(sim_run, run)
    log = (run / "samples.csv").read_bytes()
    for extra in ([], ["--force"]):
        assert main(["export", str(run), "--format", "csv", "-o", str(run / "samples.csv"), *extra]) == 2
        assert "is the log of the run in" in _one_sentence(capsys.readouterr().err)
    assert (run / "samples.csv").read_bytes() == log
    out = tmp_path / "x.csv"
    out.write_text("mine\n")
    assert main(["export", str(run), "--format", "csv", "-o", str(out)]) == 2
    assert f"-o {out} already exists" in _one_sentence(capsys.readouterr().err)
    assert out.read_text() == "mine\n"
    assert main(["export", str(run), "--format", "csv", "-o", str(out), "--force"]) == 0
    kept = next(tmp_path.glob("x.csv.replaced-*"))
    assert kept.read_text() == "mine\n" and out.read_text().startswith("t,")


def test_solve_of_a_run_with_a_header_and_no_rows_is_one_sentence(sim_run, tmp_path, capsys):
    run = tmp_path / "E"
    run.mkdir()
    shutil.copy(sim_run / "run.yaml", run)
    (run / "samples.csv").write_text((sim_run / "samples.csv").read_text().splitlines()[0] + "\n")
    assert len(read_run(run)) == 0  # readable: a startup stopped as its log began leaves such a run
    for command in ("solve", "diagnose"):
        assert main([command, str(run)]) == 2
        assert _one_sentence(capsys.readouterr().err) == (
            f"cdpr: {run}: the run holds 0 samples; a solve needs at least 3.\n")


def test_import_irma_treats_every_damaged_line_the_same_way(irma_data, tmp_path, capsys):
    lines = (irma_data / "sc_8_final.log").read_text().splitlines()
    damaged = list(lines)
    cable = next(k for k in range(6000, 7000) if damaged[k].startswith("3,"))
    ahrs = next(k for k in range(5000, 6000) if damaged[k].startswith("5,"))
    damaged[cable] = ",".join(damaged[cable].split(",")[:-2])  # one short cable line
    cells = damaged[ahrs].split(",")
    damaged[ahrs] = ",".join([*cells[:3], "abc", *cells[4:]])  # one non-numeric field
    damaged.insert(3000, "hello from another program")  # foreign lines
    damaged.insert(1000, "7,1,2,3")
    f = tmp_path / "damaged.log"
    f.write_text("\n".join(damaged) + "\n")
    assert main(["import", "irma", str(irma_data / "sc_8_final.log"), "-o", str(tmp_path / "good")]) == 0
    capsys.readouterr()
    assert main(["import", "irma", str(f), "-o", str(tmp_path / "bad")]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"cdpr: warning: {f}: damaged input: "), err
    for said in ("2 not a record of the format", "1 wrong number of fields", "1 a non-numeric or non-finite value",
                 "2 logging cycles lacking a cable or AHRS line", "; 1278 samples kept."):
        assert said in err, said
    good, bad = read_run(tmp_path / "good"), read_run(tmp_path / "bad")
    assert len(good) == 1280 and len(bad) == 1278
    kept = np.isin(good.t, bad.t)  # the others are the samples of the good run, unchanged
    assert kept.sum() == 1278
    np.testing.assert_array_equal(bad.tau, good.tau[kept])
    np.testing.assert_array_equal(bad.dl, good.dl[kept])


def test_effects_from_a_missing_or_broken_file_is_refused_without_effects(sim_run, tmp_path, capsys):
    broken = tmp_path / "broken.py"
    broken.write_text("raise RuntimeError('boom')\n")
    for source, said in ((tmp_path / "nosuch.py", "effect file not found"),
                         (broken, "importing the effect file failed (RuntimeError: boom)")):
        assert main(["solve", str(sim_run), "--effects-from", str(source)]) == 2
        assert said in _one_sentence(capsys.readouterr().err)
    mine = tmp_path / "mine.py"
    mine.write_text("from calib.effects import Effect\n\n\nclass Nothing(Effect):\n    name = 'nothing'\n")
    assert main(["solve", str(sim_run), "--effects-from", str(mine), "--json"]) == 0
    err = capsys.readouterr().err
    assert err.startswith("cdpr: warning: --effects-from defines ") and "without --effects none" in err


def test_a_truncated_run_log_is_one_cdpr_warning_line(sim_run, tmp_path, capsys):
    run = tmp_path / "cut"
    shutil.copytree(sim_run, run)
    data = (run / "samples.csv").read_bytes()
    (run / "samples.csv").write_bytes(data[:-30])
    n = data.count(b"\n") - 2  # samples before the cut line
    for args in (["solve", str(run), "--json"], ["export", str(run), "--format", "npz", "-o", str(tmp_path / "x.npz")]):
        assert main(args) == 0
        err = capsys.readouterr().err
        assert err == (f"cdpr: warning: {run / 'samples.csv'}: damaged input: 1 cut short (the log was cut while "
                       f"writing it) (line {n + 2}); {n} samples kept.\n")


def test_the_hint_for_a_run_with_one_window_is_honest(sim_run, tmp_path, capsys):
    run = tmp_path / "one"
    run.mkdir()
    shutil.copy(sim_run / "run.yaml", run)
    from acquisition.runlog import read_run
    from calib.selfcal import solve

    first = solve(read_run(sim_run).robot, read_run(sim_run)).windows[0]
    lines = (sim_run / "samples.csv").read_text().splitlines()
    (run / "samples.csv").write_text("\n".join(lines[:first.last + 6]) + "\n")  # the first hold only
    assert main(["solve", str(run)]) == 1
    err = _one_sentence(capsys.readouterr().err)
    assert "1 equilibrium window(s) found" in err and "nothing can be solved" in err and "try" not in err
    meta = yaml.safe_load((run / "run.yaml").read_text())
    meta["procedure"]["method"] = "kinematic"
    (run / "run.yaml").write_text(yaml.safe_dump(meta))
    assert main(["solve", str(run)]) == 1
    assert "a kinematic run is solved with --method lse" in _one_sentence(capsys.readouterr().err)


@pytest.mark.parametrize("grid", [1, 8])
def test_poses_refuses_the_grids_startup_refuses(grid, capsys):
    for command in ("poses", "startup"):
        args = [command, "--grid", str(grid)] + (["--backend", "sim", "--no-html"] if command == "startup" else [])
        assert main(args) == 2
        assert _one_sentence(capsys.readouterr().err) == (
            f"cdpr: --grid {grid} is out of range: give 2 to 6 grid points per axis.\n")


def test_the_readme_certify_example_makes_its_own_input():
    text = (REPO / "README.md").read_text()
    commands = [line.split("#")[0].split() for line in text.splitlines() if line.startswith("cdpr certify")]
    simulate = next(c for c in commands if c[2] == "simulate")
    anchors = next(c for c in commands if c[2] == "anchors")
    assert commands.index(simulate) < commands.index(anchors)
    assert simulate[simulate.index("-o") + 1] == anchors[3]


# ---- the policy's own rules ---------------------------------------------------------------------------


def test_an_empty_folder_is_used_and_a_kept_name_never_collides(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert claim_output(empty, False, "--out") is None and empty.is_dir()
    f = tmp_path / "a.png"
    f.write_text("1")
    kept = kept_name(f)
    kept.write_text("older")
    assert claim_output(f, True, "--plot").kept == kept.with_name(kept.name + "-2")
    assert kept.read_text() == "older" and not f.exists()


def test_force_never_moves_the_current_folder(tmp_path):
    (tmp_path / "x").write_text("1")
    cwd = Path.cwd()
    os.chdir(tmp_path)
    try:
        with pytest.raises(OutputExistsError, match="holds the current folder"):
            check_output(tmp_path, True, "--plots")
    finally:
        os.chdir(cwd)
    assert (tmp_path / "x").is_file()
