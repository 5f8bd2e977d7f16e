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
    for extra in (["--effects", "tension_offset"], ["--noise", "paper"], ["--method", "lse", "--stride", "20"]):
        assert main(["solve", str(run), *extra]) == 0
        out = capsys.readouterr().out
        assert f"not saved: {run / 'solution.json'} stays the run's solution (--save to replace it)" in out
        assert (run / "solution.json").read_bytes() == saved
    assert main(["export", str(run), "--format", "npz", "-o", str(tmp_path / "a.npz")]) == 0
    assert (f"with its solution {run / 'solution.json'} (method tlse, noise estimate, effects device_accuracy"
            in capsys.readouterr().out)
    assert main(["solve", str(run), "--noise", "paper", "--save", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert json.loads((run / "solution.json").read_text()) == doc and doc["noise"]["source"] == "paper"
    assert main(["export", str(run), "--format", "npz", "-o", str(tmp_path / "b.npz")]) == 0
    assert "(method tlse, noise paper, effects " in capsys.readouterr().out


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


# ---- 8: no numpy warning from the workspace ----------------------------------------------------------------


def test_the_workspace_near_the_pulleys_leaks_no_numpy_warning(recwarn):
    from calib.robot import load_robot
    from calib.workspace import static_workspace

    robot = load_robot("irma4u")
    # around [-0.966, -1.155, 1.6], a position of the default grid (step 0.1) whose orientation search meets
    # an anchor within a pulley's radius (no tangent: NaN): the warning `cdpr workspace` printed every time
    centre = np.array([-0.966, -1.155, 1.55])
    ws = static_workspace(robot, centre - [0.1, 0.1, 0.05], centre + [0.1, 0.1, 0.05], step=0.1)
    assert len(ws.member) == 18 and ws.member.sum() < 18
    assert [str(w.message) for w in recwarn if issubclass(w.category, RuntimeWarning)] == []


# ---- 11: the README's certify example contracts the boxes ---------------------------------------------------


def test_the_readme_certify_example_is_meaningful(tmp_path, capsys):
    text = (REPO / "README.md").read_text()
    commands = [line.split("#")[0].split() for line in text.splitlines() if line.startswith("cdpr certify")]
    cwd = Path.cwd()
    os.chdir(tmp_path)
    try:
        for c in commands:
            assert main([*c[1:], "--json"] if c[2] == "anchors" else c[1:]) == 0, c
    finally:
        os.chdir(cwd)
    doc = json.loads(capsys.readouterr().out.splitlines()[-1])
    widths = np.array([[hi - lo for lo, hi in a["box"]] for a in doc["anchors"]])
    assert widths.shape == (8, 3) and widths.max() < 0.011  # every 20 mm box contracts to 4-10 mm
    assert (REPO / "docs" / "certify.md").is_file() and "OUTSIDE" in (REPO / "docs" / "certify.md").read_text()


# ---- 12: display -------------------------------------------------------------------------------------------


def test_the_solve_table_prints_the_position_sigma_in_mm_and_the_effects_with_units(run, capsys):
    assert main(["solve", str(run), "--noise", "estimate"]) == 0
    out = capsys.readouterr().out
    x = next(line for line in out.splitlines() if line.strip().startswith("x "))
    value, sigma = x.split()[1], x.split()[3:5]
    assert float(value) != 0 and sigma[1] == "mm" and 0.01 < float(sigma[0]) < 10, x  # not "0.0000"
    assert main(["solve", str(run), "--effects", "tension_offset"]) == 0
    out = capsys.readouterr().out
    head = next(line for line in out.splitlines() if line.startswith("model "))
    assert " tension " in head and "orientation" in head
    params = next(line for line in out.splitlines() if line.strip().startswith("tension_offset:"))
    assert params.count(" N") == 4, params


def test_the_startup_summary_puts_units_beside_their_numbers():
    from acquisition.report import StartupSummary, render_html, render_text

    sol = {"reference_sample": 3, "initial_pose": [0.4, 0.4, 1.2, 0.0, 0.0, 0.0], "initial_pose_sigma": [1e-4] * 6,
           "sensor_offsets": {"length": [2.0] * 4, "swivel": [0.5] * 4, "yaw": 0.0}, "chi2": 0.0123, "dof": 63,
           "residuals": {"tension": {"rms": 1.5, "rms_normalized": 0.15}, "length": {"rms": 2e-4,
                                                                                  "rms_normalized": 0.02}}}
    summary = StartupSummary("ok", "R", "equilibrium", 8, solution=sol,
                             timing={"wall_s": 9.31234, "control_p99_ms": 0.4409810499805631})
    text = render_text(summary)
    assert "residuals (chi2 0.0123, dof 63):" in text
    assert "  tension              1.5 N        0.150" in text and "  length            0.0002 m        0.020" in text
    html = render_html(summary, np.zeros(0), np.zeros((0, 4)), np.zeros((0, 4)))
    assert "<td>control_p99_ms</td><td>0.441 ms</td>" in html and "0.4409810499805631" not in html


def test_plots_label_what_they_show(monkeypatch, tmp_path):
    import matplotlib.figure

    from acquisition.diagnose_report import plot_steps
    from calib.robot import load_robot
    from calib.workspace import plot_workspace, static_workspace

    figs = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: figs.append(fig))
    plot_steps([{"effects": [], "chi2": 812.0, "dof": 57}], tmp_path / "c.png")  # no effect added
    dof = next(line for line in figs[-1].axes[0].get_lines() if line.get_label() == "dof")
    assert dof.get_marker() not in ("None", "", None) and figs[-1].axes[0].get_xlim() == (-0.5, 0.5)
    robot = load_robot("irma4u")
    plot_workspace(static_workspace(robot, step=0.4), robot, tmp_path / "w.png")
    ax = figs[-1].axes[0]
    assert ax.get_zlabel() == "z (m)" and ax.get_box_aspect() is not None
    assert "calibration poses' bounds (eq. 19)" in [t.get_text() for t in ax.get_legend().get_texts()]


# ---- 13: progress ------------------------------------------------------------------------------------------


def test_long_commands_report_progress_in_plain_lines_when_redirected(capsys):
    assert main(["workspace", "--step", "0.3"]) == 0
    err = capsys.readouterr().err
    assert err.endswith("cdpr: workspace: 432/432 positions (100%, " + err.rsplit("(100%, ", 1)[1]) and "\r" not in err


def test_progress_is_a_tqdm_bar_on_a_terminal_and_lines_otherwise():
    import io
    import time

    from acquisition.cli.progress import Activity, Progress

    tty = io.StringIO()
    with Progress(1, "workspace", "positions", stream=tty, tty=True) as bar:
        bar._bar.mininterval = 0  # draw every update
        for done in range(0, 1001, 250):
            bar.update(done, 1000)
    assert "workspace:" in tty.getvalue() and "1000/1000" in tty.getvalue() and "\r" in tty.getvalue()
    plain = io.StringIO()
    with Progress(20, "study", "runs", stream=plain, tty=False) as bar:
        for done in range(1, 21):
            bar.update(done)
    lines = plain.getvalue().splitlines()
    assert len(lines) == 10 and lines[0].startswith("cdpr: study: 2/20 runs (10%, ")
    quiet, slow = io.StringIO(), io.StringIO()
    with Activity("diagnose", stream=quiet, tty=False, every=5.0):
        pass  # a step that ends sooner than its first line writes nothing
    with Activity("diagnose", stream=slow, tty=False, every=0.05):
        time.sleep(0.3)
    assert quiet.getvalue() == "" and slow.getvalue().splitlines()[-1].startswith("cdpr: diagnose: done in ")


# ---- 16: the README's times ---------------------------------------------------------------------------------


def test_the_readme_gives_the_startup_time_idle_and_loaded():
    quick = " ".join((REPO / "README.md").read_text().split("## What is in the box")[0].split())
    assert "idle two-core machine" in quick and "load average" in quick
    assert "about 10 s of wall time on two cores" not in quick


def test_a_redirected_study_reports_its_runs_in_plain_lines(capsys):
    from acquisition.cli.study import _StudyLines

    progress = _StudyLines(4)
    for done in range(1, 5):
        progress.advance(done, failed=done // 4)
    progress.close()
    lines = capsys.readouterr().err.splitlines()
    assert [line.split(" (")[0] for line in lines] == [f"cdpr: study: {k}/4 runs" for k in range(1, 5)]
