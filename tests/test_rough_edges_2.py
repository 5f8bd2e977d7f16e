"""A second new user's pass (issue30u): the rough edges it met, one test (or a few) each, each failing without
its fix. The real-data tests read ../shared/data/irma4u (tests/conftest.py: irma_data)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from acquisition.cli import main


def _one_sentence(err: str) -> str:
    assert err.count("\n") == 1 and err.startswith("cdpr: ") and err.endswith(".\n"), err
    assert "Traceback" not in err and "usage:" not in err
    return err


@pytest.fixture(scope="module")
def run8(irma_data, tmp_path_factory) -> Path:
    """sc_8_final (parsed) imported and solved with the default options: a run with its solution."""
    out = tmp_path_factory.mktemp("r30u") / "R"
    assert main(["import", "irma", str(irma_data / "sc_8_final_parsed.mat"), "-o", str(out)]) == 0
    assert main(["solve", str(out), "--json"]) == 0
    return out


@pytest.fixture
def run(run8, tmp_path) -> Path:
    r = tmp_path / "R"
    shutil.copytree(run8, r)
    return r


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
