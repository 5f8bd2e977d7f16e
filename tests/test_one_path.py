"""One job per module, and one path for a startup (issue 31): no module of the packages grows past
MAX_LINES unless it is named in ONE_JOB with the one job it does, and the startup's path (session, plans,
study) never reaches back up into the command line (acquisition.cli)."""

from __future__ import annotations

import ast
import subprocess
import sys

from test_import_graph import PACKAGES, ROOT, import_graph

MAX_LINES = 500
# modules allowed past MAX_LINES: one job each, said here, and a ceiling so that a second job shows
ONE_JOB = {
    "acquisition/startup.py": ("the startup routine: its settings, control loop, windows and safe stop", 560),
    "calib/selfcal/windows.py": ("the search of the equilibrium windows of a run", 620),
    "sim_backend/physics.py": ("the simulated prototype's physics (dynamics, cables, sensors' truth)", 720),
    "sim_backend/can_drive_emulator.py": ("one emulated CiA 402 winch drive on the simulated CAN bus", 660),
    "calib/multirun.py": ("the joint fit of several runs sharing robot effects (issue 28, being extended)", 640),
    "sim_backend/plant_link.py": ("the lockstep link between the loop and the simulated plant, in process or in "
                                  "a child process", 560),
}
# modules of the startup's path below the command line: they must not import acquisition.cli
BELOW_CLI = ("acquisition.session", "acquisition.plans", "acquisition.study", "acquisition.study_report",
             "acquisition.startup")


def _lines() -> dict[str, int]:
    return {str(f.relative_to(ROOT)): len(f.read_text().splitlines())
            for pkg in PACKAGES for f in sorted((ROOT / pkg).rglob("*.py"))}


def test_no_module_past_the_line_limit_does_more_than_its_one_named_job():
    lines = _lines()
    over = {f: n for f, n in lines.items() if n > MAX_LINES and f not in ONE_JOB}
    assert over == {}, f"modules over {MAX_LINES} lines that do more than one job: {over}"
    for f, (job, ceiling) in ONE_JOB.items():
        assert f in lines, f"{f} is named in ONE_JOB but does not exist"
        assert lines[f] <= ceiling, f"{f} ({lines[f]} lines) has outgrown its one job ({job}): split it"


def test_the_startup_path_imports_nothing_from_the_command_line():
    graph = import_graph(ROOT)
    for mod in BELOW_CLI:
        up = sorted(t for t in graph[mod] if t == "acquisition.cli" or t.startswith("acquisition.cli."))
        assert up == [], f"{mod} imports {up}"
    tree = ast.parse((ROOT / "acquisition" / "study.py").read_text())
    names = [getattr(n, "module", None) or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    names += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    assert not any(n.startswith("acquisition.cli") for n in names), names


def test_importing_the_session_and_the_study_loads_no_command_module():
    code = ("import sys, acquisition.session, acquisition.study, acquisition.plans; "
            "print(sorted(m for m in sys.modules if m.startswith('acquisition.cli')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}).stdout
    assert out.strip() == "[]"
