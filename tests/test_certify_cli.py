"""`cdpr certify simulate` and `cdpr certify anchors`: the contract of ../shared/spec/cli.md, end to end
through the console entry point."""

from __future__ import annotations

import json

import numpy as np
import pytest

from acquisition.cli import main


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("certify")
    csv, truth = folder / "m.csv", folder / "truth.json"
    rc = main(["certify", "simulate", "--robot", "reelax8", "-n", "42", "--outliers", "0.2", "--seed", "21",
               "-o", str(csv), "--truth", str(truth)])
    assert rc == 0
    return csv, json.loads(truth.read_text())


def test_simulate_writes_the_spec_csv(dataset):
    csv, truth = dataset
    lines = csv.read_text().splitlines()
    assert lines[0] == "x,y,z,roll,pitch,yaw,l_1,l_2,l_3,l_4,l_5,l_6,l_7,l_8"
    assert len(lines) == 43
    assert all(len(line.split(",")) == 14 for line in lines[1:])
    assert len(truth["outliers"]) == 8 and len(truth["true_anchors"]) == 8


def test_anchors_json_follows_the_spec(dataset, capsys):
    csv, truth = dataset
    assert main(["certify", "anchors", str(csv), "--robot", "reelax8", "--q", "0.75", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["q"] == 0.75
    assert [a["cable"] for a in out["anchors"]] == list(range(1, 9))
    for a, true in zip(out["anchors"], truth["true_anchors"], strict=True):
        box = np.array(a["box"])
        assert box.shape == (3, 2)
        assert np.all(box[:, 0] <= true) and np.all(np.array(true) <= box[:, 1])
        assert a["outliers"] == truth["outliers"]


def test_plain_intersection_is_null_in_json(dataset, capsys):
    csv, _ = dataset
    assert main(["certify", "anchors", str(csv), "--robot", "reelax8", "--q", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert all(a["box"] is None for a in out["anchors"])


def test_text_table_names_widths_nwls_and_identifiability(tmp_path, capsys):
    csv = tmp_path / "clustered.csv"
    assert main(["certify", "simulate", "--robot", "reelax8", "-n", "30", "--clustered", "--seed", "5",
                 "-o", str(csv)]) == 0
    assert main(["certify", "anchors", str(csv), "--robot", "reelax8", "--q", "1", "--anchor-tol", "0.03"]) == 0
    text = capsys.readouterr().out
    assert "width (mm)" in text and "NWLS (m)" in text
    assert "not contracted (identifiability" in text
    assert text.count("inside") + text.count("OUTSIDE") == 8


def test_tolerance_options_change_the_result(dataset, capsys):
    csv, _ = dataset
    main(["certify", "anchors", str(csv), "--robot", "reelax8", "--json"])
    default = json.loads(capsys.readouterr().out)
    main(["certify", "anchors", str(csv), "--robot", "reelax8", "--json", "--angle-tol", "0.02",
          "--model-error", "-0.002,0.005", "--pose-tol", "0.002", "--anchor-tol", "0.02"])
    wide = json.loads(capsys.readouterr().out)
    assert wide["model_error"] == [-0.002, 0.005]
    w0 = np.mean([a["widths"] for a in default["anchors"]])
    w1 = np.mean([a["widths"] for a in wide["anchors"]])
    assert w1 > w0 + 0.005


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--q", "1.5"], "option --q = 1.5 must be a fraction in (0, 1]"),
        (["--model-error", "0.1"], "option --model-error = '0.1' must be two numbers LO,HI in m"),
        (["--model-error", "0.004,-0.001"], "must be finite with LO <= HI"),
        (["--anchor-tol", "0"], "option --anchor-tol = 0.0 must be a positive number"),
        (["--pose-tol", "-1"], "option --pose-tol = -1.0 must be a non-negative number"),
    ],
)
def test_bad_options_exit_2_with_one_sentence(dataset, capsys, args, message):
    csv, _ = dataset
    assert main(["certify", "anchors", str(csv), "--robot", "reelax8", *args]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_bad_files_and_robots_exit_2(dataset, tmp_path, capsys):
    csv, _ = dataset
    assert main(["certify", "anchors", str(csv), "--robot", "irma4u"]) == 2
    assert "line 2 has 14 fields, expected 10" in capsys.readouterr().err
    assert main(["certify", "anchors", str(tmp_path / "none.csv"), "--robot", "reelax8"]) == 2
    assert "none.csv: cannot be read" in capsys.readouterr().err
    assert main(["certify", "anchors", str(csv), "--robot", "nosuchrobot"]) == 2
    assert "nosuchrobot" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text(csv.read_text().replace(csv.read_text().splitlines()[5].split(",")[2], "nan", 1))
    assert main(["certify", "anchors", str(bad), "--robot", "reelax8"]) == 2
    assert "line 6, field 'z' = 'nan' is not a finite number" in capsys.readouterr().err
