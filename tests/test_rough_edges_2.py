"""A second new user's pass (issue30u): the rough edges it met, one test (or a few) each, each failing without
its fix. The real-data tests read ../shared/data/irma4u (tests/conftest.py: irma_data)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from acquisition.cli import main


def _one_sentence(err: str) -> str:
    assert err.count("\n") == 1 and err.startswith("cdpr: ") and err.endswith(".\n"), err
    assert "Traceback" not in err and "usage:" not in err
    return err


# ---- the verdict of a diagnosis whose finding comes after a kept effect ---------------------------------------


def test_a_finding_after_a_kept_effect_does_not_say_nothing_is_recommended(run8, capsys):
    capsys.readouterr()
    assert main(["diagnose", str(run8), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["selected"] == ["tension_offset"] and doc["finding"], doc["verdict"]  # sc_8_final, parsed
    verdict = doc["verdict"]
    assert verdict.startswith("FINDING: once tension_offset is in the model, swivel_entry explains the most of "
                              "what is left (delta chi2 "), verdict
    assert "recommended in its place" not in verdict and "nothing that explains less is added after " \
        "tension_offset. Before it: tension_offset explains" in verdict, verdict


# ---- export: a name that says another format; what a CSV carries ------------------------------------------------


def test_export_refuses_a_name_that_says_another_format(run, tmp_path, capsys):
    capsys.readouterr()
    for fmt, name in (("mat", "x.npz"), ("npz", "x.MAT"), ("csv", "x.mcap"), ("mcap", "x.csv")):
        assert main(["export", str(run), "--format", fmt, "-o", str(tmp_path / name)]) == 2
        err = _one_sentence(capsys.readouterr().err)
        assert f"the name says {Path(name).suffix[1:].lower()} but --format is {fmt}" in err, err
        assert not (tmp_path / name).exists()
    assert main(["export", str(run), "--format", "mat", "-o", str(tmp_path / "x.dat")]) == 0  # any other name


def test_export_csv_says_the_solution_is_not_in_the_csv(run, tmp_path, capsys):
    capsys.readouterr()
    assert main(["export", str(run), "--format", "csv", "-o", str(tmp_path / "r.csv")]) == 0
    said = capsys.readouterr().out
    assert "with the absolute channels of its solution" in said and "is not in a CSV" in said, said
    header = (tmp_path / "r.csv").read_text().splitlines()[0].split(",")
    assert "length_1" in header and not any(h.startswith(("initial", "sigma", "chi2")) for h in header)  # as said
    assert main(["export", str(run), "--format", "mat", "-o", str(tmp_path / "r.mat")]) == 0
    assert "with its solution " in capsys.readouterr().out


# ---- one solution, printed the same way by cdpr startup and cdpr solve -------------------------------------------


def test_startup_summary_and_solve_print_one_solution_with_the_same_numbers_and_units(run, capsys):
    from acquisition.report import StartupSummary, render_text

    sol = json.loads((run / "solution.json").read_text())
    held = [(a + 5, b) for a, b in sol["windows"]]  # the controller's holds start after the solve's windows
    text = render_text(StartupSummary("ok", str(run), "equilibrium", 8, solution=sol, windows=held))
    capsys.readouterr()
    assert main(["solve", str(run)]) == 0
    out = capsys.readouterr().out
    for name in ("x", "y", "z", "roll", "pitch", "yaw"):
        start = next(line.split() for line in text.splitlines() if line.strip().startswith(name + " "))
        solve = next(line.split() for line in out.splitlines() if line.strip().startswith(name + " "))
        assert start[1] == solve[1] and start[3] == solve[3] and start[4] == solve[2], (start, solve)
    swivel = next(line for line in text.splitlines() if line.strip().startswith("swivel"))
    solved = next(line for line in out.splitlines() if line.strip().startswith("swivel [deg]")).split()[2:]
    assert swivel.endswith(" deg") and swivel.split("[")[1].split("]")[0].split(", ") == solved, (swivel, solved)
    yaw = next(line for line in text.splitlines() if line.strip().startswith("yaw ") and "+-" not in line)
    assert yaw.split()[1:] == [next(line for line in out.splitlines() if "yaw [deg]" in line).split()[2], "deg"]
    used = next(line for line in text.splitlines() if line.startswith("windows the solve used"))
    assert used.endswith(", ".join(f"[{a}, {b}]" for a, b in sol["windows"])), used
    same = render_text(StartupSummary("ok", str(run), "equilibrium", 8, solution=sol, windows=sol["windows"]))
    assert "windows the solve used" not in same  # said only when they differ


# ---- argparse's own errors: one sentence, no usage block ----------------------------------------------------------


@pytest.mark.parametrize("argv, said", [
    (["solve", "R", "--method", "foo"], "argument --method: invalid choice: 'foo'"),
    (["solve", "R", "--stride", "x"], "argument --stride: invalid int value: 'x'"),
    (["export", "R", "--format", "xls", "-o", "a.xls"], "argument --format: invalid choice: 'xls'"),
    (["startup"], "the following arguments are required: --backend"),
    (["poses", "--grid", "2", "--bogus"], "unrecognized arguments: --bogus"),
])
def test_a_usage_error_is_one_sentence_pointing_at_the_help(argv, said, capsys):
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = _one_sentence(capsys.readouterr().err)
    assert said in err and err.endswith(f"see `cdpr {argv[0]} --help`.\n"), err


def test_a_command_without_its_action_prints_its_own_help(capsys):
    for command, action in (("import", "irma"), ("robot", "show"), ("devices", "read"), ("certify", "anchors")):
        assert main([command]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"usage: cdpr {command} ") and action in err and "Self-calibration" not in err, err
    assert main([]) == 2 and "Self-calibration" in capsys.readouterr().err  # no command: the whole help


# ---- certify simulate: --out as every other writer, and it says what it wrote -----------------------------------


def test_certify_simulate_takes_out_as_the_other_writers_and_says_what_it_wrote(tmp_path, capsys):
    common = ["certify", "simulate", "--robot", "reelax8", "-n", "5", "--seed", "1"]
    capsys.readouterr()
    for option, name in (("--out", "a.csv"), ("--output", "b.csv"), ("-o", "c.csv")):  # the old name still works
        assert main([*common, option, str(tmp_path / name)]) == 0
        said = capsys.readouterr().out
        assert said == (f"{tmp_path / name}: 5 simulated poses of reelax8 (0 outliers), one a line under the "
                        "header x,y,z,roll,pitch,yaw,l_1..l_8 (m, rad)\n"), said
        assert len((tmp_path / name).read_text().splitlines()) == 1 + 5


# ---- startup: a bad value names its option, alone ------------------------------------------------------------------


@pytest.mark.parametrize("option, value, said", [
    ("--hold", "-1", "--hold -1 must be positive (s)."),
    ("--max-rate", "0", "--max-rate 0 must be positive (N/s)."),
    ("--settle-timeout", "-2", "--settle-timeout -2 must be positive (s)."),
    ("--rate", "50", "--rate 50 is outside the control rates 200..500 Hz."),
    ("--rt-priority", "0", "--rt-priority 0 is outside the SCHED_FIFO priorities 1..99."),
])
def test_a_bad_startup_value_names_its_option_alone(option, value, said, tmp_path, capsys):
    out = tmp_path / "R"
    assert main(["startup", "--backend", "sim", "--no-html", "--out", str(out), option, value]) == 2
    err = _one_sentence(capsys.readouterr().err)
    assert err == f"cdpr: {said}\n" and not out.exists(), err


# ---- a whole MATLAB workspace that holds `st`: scipy's nameless-variable warnings stay out ------------------------


def test_importing_the_authors_workspace_leaks_no_scipy_warning(irma_data, tmp_path, capsys):
    out = tmp_path / "W"
    assert main(["import", "irma", str(irma_data / "ws_selfcalibration_8_final.mat"), "-o", str(out)]) == 0
    cap = capsys.readouterr()
    assert cap.err == "" and cap.out.startswith(f"{out}: 1280 samples"), cap


# ---- a log handed to a command that reads runs -------------------------------------------------------------------


def test_a_log_given_for_a_run_says_it_is_a_file_and_how_to_import_it(irma_data, tmp_path, capsys):
    log = irma_data / "sc_8_final.log"
    for argv in (["solve", str(log)], ["diagnose", str(log)], ["export", str(log), "--format", "mat", "-o",
                                                                 str(tmp_path / "x.mat")]):
        assert main(argv) == 2
        err = _one_sentence(capsys.readouterr().err)
        assert err == (f"cdpr: {log}: a file, not a run folder (a cdpr-run/1 folder holds run.yaml and samples.csv); "
                       f"convert it first: cdpr import irma {log} -o RUN.\n"), err
    note = tmp_path / "notes.txt"
    note.write_text("x")
    assert main(["solve", str(note)]) == 2
    assert "notes.txt: a file, not a run folder" in _one_sentence(capsys.readouterr().err)


# ---- several runs: the shared values with their units, and which 1-sigma is printed --------------------------------


def test_the_several_run_report_gives_the_shared_values_their_units():
    from types import SimpleNamespace

    from acquisition.selection_report import shared_values_text
    from calib.effects import make_effects
    from calib.robot import load_robot

    robot = load_robot("irma4u")
    fit = SimpleNamespace(
        shared=make_effects(["cable_elasticity", "tension_offset"]),
        runs=[SimpleNamespace(rows=SimpleNamespace(robot=robot))],
        shared_params=lambda: {"cable_elasticity": {"EA": 7413.8, "compliance": 1.3488e-4},
                               "tension_offset": {"o_1": 11.36, "o_2": 13.08}},
        shared_sigmas=lambda: {"cable_elasticity": {"compliance": 3.12e-5},
                               "tension_offset": {"o_1": 2.985, "o_2": 2.886}})
    assert shared_values_text(fit, "cable_elasticity") == "EA = 7414 N, compliance = 0.0001349 ± 3.1e-05 1/N"
    assert shared_values_text(fit, "tension_offset") == "o_1 = 11.36 ± 3 N, o_2 = 13.08 ± 2.9 N"


# ---- the workspace summary: units and millimetres, not float noise --------------------------------------------------


def test_the_workspace_summary_gives_its_extent_in_metres_to_the_millimetre(capsys):
    assert main(["workspace", "--step", "0.3"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("grid positions: ") and "(step 0.3 m)" in out, out
    extent = next(line for line in out.splitlines() if line.strip().startswith("extent (m): "))
    for part in extent.split(": ", 1)[1].split(", "):
        axis, lo, dots, hi = part.split()
        assert axis in "xyz" and dots == ".." and len(lo.split(".")[1]) == 3 and len(hi.split(".")[1]) == 3, part
    assert main(["workspace", "--step", "0.3", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) >= {"points", "in_workspace", "boundary", "extent_lower", "extent_upper"}  # JSON as before


# ---- solve --model explores, as --effects does: the run's solution changes only with --save ------------------------


def test_a_solve_with_a_model_does_not_become_the_runs_solution_unless_saved(irma_data, tmp_path, capsys):
    run = tmp_path / "R"
    assert main(["import", "irma", str(irma_data / "sc_8_final_parsed.mat"), "-o", str(run)]) == 0
    model = tmp_path / "m.yaml"
    model.write_text("format: cdpr-robot-model\nversion: 1\nrobot: irma4u\neffects:\n- name: tension_offset\n"
                     "  values: {o_1: 10.0, o_2: 10.0, o_3: 5.0, o_4: 12.0}\n"
                     "  sigma: {o_1: 3.0, o_2: 3.0, o_3: 3.0, o_4: 3.0}\n")
    capsys.readouterr()
    assert main(["solve", str(run), "--model", str(model)]) == 0
    assert "not saved: the run has no solution yet" in capsys.readouterr().out
    assert not (run / "solution.json").exists()
    assert main(["solve", str(run), "--model", str(model), "--save", "--json"]) == 0
    assert json.loads((run / "solution.json").read_text()) == json.loads(capsys.readouterr().out)


# ---- study --force moves another study aside, as every command does, instead of deleting its results ---------------


def test_study_force_moves_another_studys_results_aside_never_deletes_them(tmp_path, capsys):
    import socket

    out = tmp_path / "S"
    out.mkdir()
    (out / "config.json").write_text('{"format": "another study"}\n')
    (out / "run-grid2-s00000.json").write_text('{"plan": "grid2", "seed": 0}\n')
    with socket.socket() as s:  # nobody listens: the study stops after preparing its folder, nothing run
        s.bind(("127.0.0.1", 0))
        addr = f"tcp://127.0.0.1:{s.getsockname()[1]}"
    argv = ["study", "--plan", "grid2", "--runs", "1", "--out", str(out), "--scheduler", addr,
            "--connect-timeout", "1", "--no-html"]
    assert main(argv) == 2  # refused without --force, nothing touched
    assert "--force to move them aside" in _one_sentence(capsys.readouterr().err)
    assert main([*argv, "--force"]) == 1
    err = capsys.readouterr().err
    kept = list(tmp_path.glob("S.replaced-*"))
    assert len(kept) == 1 and f"it is kept as {kept[0]}" in err, err
    assert (kept[0] / "run-grid2-s00000.json").read_text() == '{"plan": "grid2", "seed": 0}\n'
    assert (out / "config.json").is_file() and not list(out.glob("run-*.json"))


# ---- a damaged solution.json, a replay of no run -----------------------------------------------------------------


def test_solve_does_not_call_a_damaged_solution_the_runs_solution(run, tmp_path, capsys):
    (run / "solution.json").write_text("{not json")
    capsys.readouterr()
    assert main(["solve", str(run)]) == 0
    said = capsys.readouterr().out.splitlines()[-1]
    assert said == (f"not saved: {run / 'solution.json'} is damaged, so the run has no solution that export can "
                    "carry (--save to replace it)"), said
    assert main(["export", str(run), "--format", "mat", "-o", str(tmp_path / "x.mat")]) == 2  # as said


def test_replay_of_no_run_says_it_is_not_a_run_folder(tmp_path, capsys):
    assert main(["replay", str(tmp_path / "nosuch"), "--out", str(tmp_path / "X")]) == 2
    assert _one_sentence(capsys.readouterr().err) == f"cdpr: {tmp_path / 'nosuch'}: not a run folder (no such " \
        "directory).\n"


# ---- the pose tables name the unit of the positions, as of the angles and setpoints ----------------------------------


def test_the_pose_table_gives_the_positions_their_unit(capsys):
    assert main(["poses", "--grid", "2"]) == 0
    head = capsys.readouterr().out.splitlines()[1].split()
    assert head[:7] == ["#", "x", "(m)", "y", "(m)", "z", "(m)"] and "roll°" in head, head


# ---- 'noise estimate' in diagnose and in solve: one name, two weightings, and the report says which -----------------


def test_diagnose_says_its_estimate_noise_is_not_the_solves(run8, capsys):
    capsys.readouterr()
    assert main(["solve", str(run8), "--json"]) == 0
    solved = json.loads(capsys.readouterr().out)
    assert main(["diagnose", str(run8)]) == 0
    lines = capsys.readouterr().out.splitlines()
    chi2 = float(lines[0].split()[1])
    assert lines[0].endswith("noise estimate") and chi2 > 2 * solved["chi2"], (lines[0], solved["chi2"])  # 178, 64
    assert lines[1] == ("  (noise estimate here is the windows' own scatter; cdpr solve's estimate also weighs a "
                        "channel the model misses by that misfit, so its chi2 of this run can be smaller and its "
                        "1-sigma wider)"), lines[1]


# ---- the several-run diagnosis reports its progress like the one-run diagnosis ------------------------------------


def test_a_redirected_several_run_diagnosis_reports_progress(irma_data, tmp_path, monkeypatch, capsys):
    from acquisition.cli import progress

    monkeypatch.setattr(progress.Activity.__init__, "__defaults__", (None, None, 0.01))  # a line every 10 ms
    runs = []
    for name in ("sc_8_final", "sc_8_medium_a"):
        runs.append(str(tmp_path / name))
        assert main(["import", "irma", str(irma_data / f"{name}_parsed.mat"), "-o", runs[-1]]) == 0
    capsys.readouterr()
    assert main(["diagnose", *runs, "--max-effects", "0"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err and err[-1].startswith("cdpr: diagnose: 2 runs, choosing among ") and " done in " in err[-1], err


# ---- an empty log; a log given as --targets --------------------------------------------------------------------------


def test_an_empty_file_and_a_log_given_as_targets_say_what_they_are(irma_data, tmp_path, capsys):
    empty = tmp_path / "x.log"
    empty.write_bytes(b"")
    assert main(["import", "irma", str(empty), "-o", str(tmp_path / "R")]) == 2
    assert _one_sentence(capsys.readouterr().err) == (f"cdpr: {empty}: the file is empty (neither a MATLAB v5 "
                                                       "*_parsed.mat nor a controller log).\n")
    log = irma_data / "sc_8_final.log"
    assert main(["import", "irma", str(log), "--targets", str(log), "-o", str(tmp_path / "R")]) == 2
    err = _one_sentence(capsys.readouterr().err)
    assert err.startswith(f"cdpr: {log}: 7956 lines, expected 4 (--targets takes a sc_control_target_*.mat, or a "
                          "tension_target_*.csv"), err
    assert not (tmp_path / "R").exists()
