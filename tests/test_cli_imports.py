"""A command line that answers at once: each command imports only what it uses (issue 31)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from acquisition.cli import COMMAND_MODULES, COMMAND_OWNERS, build_parser, modules_for
from acquisition.importers import import_irma
from calib.chi2 import chi2_isf, chi2_sf
from calib.robust import median

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
    # no scipy at all: its chi2 tail (calib.chi2 computes it) cost the command ~0.15 s of scipy.special; no
    # numpy.ma (np.median's and np.unique's first call import it, ~25 ms: calib.robust.median), no effect library
    assert sorted(m for m in names if m == "scipy" or m.startswith("scipy.")) == []
    assert [m for m in ("numpy.ma", "calib.effects.cable", "calib.effects.swivel", "acquisition.outputs")
            if m in names] == []


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


def test_chi2_tail_and_quantile_agree_with_scipy_stats_to_1e_12():
    rng = np.random.default_rng(7)
    for dof in (0.5, 1, 2, 3, 5, 7.5, 15, 19.9, 20, 21, 40, 99, 100, 101, 333.3, 1000):
        xs = np.r_[rng.uniform(0.0, 3.0 * dof, 40), np.geomspace(1e-6 * dof, 20 * dof + 200, 60)]
        want = chi2.sf(xs, dof)
        got = np.array([chi2_sf(x, dof) for x in xs])
        ok = want > 1e-300  # below, both underflow (to 0 or a subnormal)
        np.testing.assert_allclose(got[ok], want[ok], rtol=1e-12, atol=0, err_msg=f"dof {dof}")
        ps = np.geomspace(1e-300, 0.5, 60)
        np.testing.assert_allclose([chi2_isf(p, dof) for p in ps], chi2.isf(ps, dof), rtol=1e-12, atol=0,
                                   err_msg=f"dof {dof}")
    assert [chi2_sf(x, 3) for x in (0.0, -1.0, math.inf)] == [1.0, 1.0, 0.0]
    assert [chi2_isf(p, 3) for p in (1.0, 0.0)] == [0.0, math.inf]
    assert math.isnan(chi2_sf(math.nan, 3)) and math.isnan(chi2_sf(1.0, 0)) and math.isnan(chi2_isf(1.5, 3))
    assert chi2_sf(5e3, 1) == 0.0  # e^-2500: no overflow on the way


def test_chi2_quantile_is_the_tail_inverse_where_the_window_ends_test_uses_it():
    for columns in range(8, 30):  # the ends test's columns (tension, lengths, swivels, tilt) at p = 1e-3
        x = chi2_isf(1e-3, columns)
        assert chi2_sf(x, columns) == pytest.approx(1e-3, rel=1e-13)


@pytest.mark.parametrize("shape, axis", [((7,), None), ((8,), None), ((9, 4), 0), ((10, 4), 0), ((1, 3), 0),
                                         ((6, 3), None), ((0,), None)])
def test_median_is_numpys_number_for_number(shape, axis):
    rng = np.random.default_rng(3)
    for a in (rng.normal(0.0, 10.0, shape), rng.integers(-50, 50, shape)):
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # the median of nothing is NaN, with numpy's warning
            want, got = np.median(a, axis=axis), median(a, axis=axis)
        assert type(got) is type(want) and np.array_equal(got, want, equal_nan=True)
        if a.dtype.kind == "f" and a.size:
            a[(0,) * a.ndim] = np.nan  # a column with a NaN has a NaN median
            want, got = np.median(a, axis=axis), median(a, axis=axis)
            assert type(got) is type(want) and np.array_equal(got, want, equal_nan=True)
