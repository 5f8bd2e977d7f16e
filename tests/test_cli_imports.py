"""A command line that answers at once: each command imports only what it uses (issue 31)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from acquisition.cli import COMMAND_MODULES, COMMAND_OWNERS, build_parser, modules_for
from acquisition.importers import import_irma
from calib.selfcal.result import chi2_sf

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("matplotlib", "scipy.stats", "codac", "dask", "distributed", "scipy.optimize")


def modules_after(argv: list[str]) -> tuple[int, set[str]]:
    """Exit status and the names in sys.modules after ``cdpr ARGV`` in a fresh interpreter."""
    code = ("import json, sys, contextlib, io\n"
            "from acquisition.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    try:\n"
            f"        status = main({argv!r})\n"
            "    except SystemExit as exc:\n"
            "        status = exc.code\n"
            "print(json.dumps([status, sorted(sys.modules)]))\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT,
                          timeout=120)
    status, names = json.loads(proc.stdout.splitlines()[-1])
    return status, set(names)


def test_solve_imports_no_plotting_statistics_or_interval_library(irma_data, tmp_path):
    run = tmp_path / "sc8f"
    import_irma(irma_data / "sc_8_final_parsed.mat", run)
    status, names = modules_after(["solve", str(run)])
    assert status == 0 and "calib.selfcal._solve" in names  # the solve ran
    assert [m for m in HEAVY if m in names] == []
    assert not any(m.startswith(("can.", "canopen", "serial")) or m == "can" for m in names)


def test_version_imports_no_scipy_and_no_command():
    status, names = modules_after(["--version"])
    assert status == 0
    assert not any(m == "scipy" or m.startswith("scipy.") for m in names)
    assert not any(m.startswith("acquisition.cli.") and m != "acquisition.cli.errors" for m in names)


def test_each_command_is_registered_by_its_owner_alone_with_the_same_parser():
    full = build_parser()
    commands = next(a for a in full._actions if a.dest == "command").choices
    assert set(commands) == set(COMMAND_OWNERS) and set(COMMAND_OWNERS.values()) == set(COMMAND_MODULES)
    for name, owner in COMMAND_OWNERS.items():
        alone = next(a for a in build_parser((owner,))._actions if a.dest == "command").choices
        assert alone[name].format_help() == commands[name].format_help(), name


@pytest.mark.parametrize("argv, modules", [
    (["solve", "RUN"], ("acquisition.cli.solve",)),
    (["--debug", "workspace"], ("acquisition.cli.poses",)),
    (["--version"], ()),
    (["--version", "solve"], ()),
    (["solve", "--help"], ("acquisition.cli.solve",)),
    (["-h", "solve"], COMMAND_MODULES),
    (["solv"], COMMAND_MODULES),
    ([], COMMAND_MODULES),
])
def test_modules_a_command_line_needs(argv, modules):
    assert modules_for(argv) == modules


def test_chi2_sf_is_scipy_stats_float_for_float():
    rng = np.random.default_rng(7)
    for dof in (1, 2, 5, 7.5, 40, 1000):
        xs = [*rng.uniform(0.0, 3.0 * dof, 50), 0.0, -1.0, 1e-300, 5e3, math.inf]
        assert [chi2_sf(x, dof) for x in xs] == [float(chi2.sf(x, dof)) for x in xs]
    assert math.isnan(chi2_sf(math.nan, 3)) and math.isnan(chi2_sf(1.0, 0))
