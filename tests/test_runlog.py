"""The cdpr-run/1 reader and writers: exact round trips, streaming, truncation, one-sentence errors."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from acquisition.damage import DamagedInputWarning
from acquisition.runlog import RunFormatError, read_run, read_solution, sample_columns
from acquisition.runwriter import RunWriter, new_run, write_run, write_solution
from calib.robot import load_robot


def make_run(N: int = 30, seed: int = 1, robot="irma4u"):
    rng = np.random.default_rng(seed)
    n = load_robot(robot).n if isinstance(robot, str) else len(robot["cables"])
    return new_run(
        robot,
        "equilibrium",
        0.1,
        "test",
        t=np.arange(N) * 0.1,
        tau=50 + 100 * rng.random((N, n)),
        tau_ref=np.full((N, n), 100.0),
        dl=rng.normal(0, 0.3, (N, n)),
        dsigma=rng.normal(0, 0.2, (N, n)),
        roll=rng.normal(0, 0.05, N),
        pitch=rng.normal(0, 0.05, N),
        dyaw=rng.normal(0, 0.01, N),
        phase=np.where(np.arange(N) < N // 2, "transition", "hold"),
        setpoint=np.where(np.arange(N) < N // 2, -1, 0),
        setpoints=[[118.48, 170.83, 115.57, 82.98]] if n == 4 else None,
        ideal_poses=[[0.4, 0.4, 1.2, 0.084, -0.0905, 0.0047]] if n == 4 else None,
        extra={"motor_position_1": np.arange(N, dtype=np.int64) * 1000 - 9339263, "note": np.full(N, "ok")},
        meta_extra={"homing": {"lengths": [2.27, 2.27, 2.27, 2.27], "yaw": 0.0}},
    )


def assert_same_samples(a, b, count=None):
    count = len(a) if count is None else count
    ca, cb = a.columns(), b.columns()
    assert list(ca) == list(cb)
    for k in ca:
        assert np.array_equal(ca[k][:count], cb[k][:count]), k


def test_write_read_round_trip_is_exact_and_deterministic(tmp_path: Path):
    run = make_run()
    write_run(tmp_path / "a", run)
    write_run(tmp_path / "b", run)
    for f in ("run.yaml", "samples.csv"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()
    back = read_run(tmp_path / "a")
    assert len(back) == 30 and back.n == 4 and back.method == "equilibrium" and back.sample_period == 0.1
    assert_same_samples(run, back)
    assert back.extra["motor_position_1"][0] == -9339263
    assert back.extra["note"][3] == "ok"
    np.testing.assert_array_equal(back.setpoints, [[118.48, 170.83, 115.57, 82.98]])
    assert back.ideal_poses.shape == (1, 6)
    assert back.meta["homing"]["lengths"] == [2.27] * 4
    header = (tmp_path / "a" / "samples.csv").read_text().splitlines()[0].split(",")
    assert header[: len(sample_columns(4))] == sample_columns(4)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=4, max_size=4))
def test_any_finite_float_survives_the_text_format(tmp_path_factory, values):
    folder = tmp_path_factory.mktemp("run")
    N = 1
    run = new_run(
        "irma4u", "kinematic", 0.01, "hypothesis",
        t=[values[0]], tau=[values], tau_ref=[values], dl=[values], dsigma=[values],
        roll=[values[1]], pitch=[values[2]], dyaw=[values[3]],
    )
    write_run(folder, run, overwrite=True)
    back = read_run(folder)
    assert len(back) == N
    assert back.tau.tolist() == [values] and back.dyaw.tolist() == [values[3]]


def test_subset_keeps_columns_aligned(tmp_path: Path):
    run = make_run(N=30)
    part = run.subset(slice(10, 20))
    assert len(part) == 10 and part.path is None and part.setpoints is run.setpoints
    np.testing.assert_array_equal(part.dl, run.dl[10:20])
    np.testing.assert_array_equal(part.extra["motor_position_1"], run.extra["motor_position_1"][10:20])
    holds = run.subset(run.phase == "hold")
    assert len(holds) == 15 and set(holds.setpoint) == {0}
    write_run(tmp_path / "part", part)
    assert_same_samples(part, read_run(tmp_path / "part"))


def test_reelax8_run_with_full_robot_mapping(tmp_path: Path):
    spec = load_robot("reelax8").to_dict()
    spec["name"] = "my_reelax"  # not a built-in name: stored as a mapping
    run = make_run(N=5, robot=spec)
    write_run(tmp_path / "r", run)
    meta = yaml.safe_load((tmp_path / "r" / "run.yaml").read_text())
    assert isinstance(meta["robot"], dict) and len(meta["robot"]["cables"]) == 8
    back = read_run(tmp_path / "r")
    assert back.n == 8 and back.tau.shape == (5, 8) and back.robot.name == "my_reelax"
    np.testing.assert_array_equal(back.robot.d, load_robot("reelax8").d)


def test_a_modified_builtin_robot_is_stored_in_full(tmp_path: Path):
    heavier = load_robot("irma4u").replace(mass=13.5)
    with RunWriter(tmp_path / "m", heavier, "kinematic", 0.01, "sim") as w:
        w.append(0.0, [100.0] * 4, [100.0] * 4, [0.0] * 4, [0.0] * 4, 0.01, -0.02, 0.0)
    back = read_run(tmp_path / "m")
    assert isinstance(back.meta["robot"], dict) and back.robot.mass == 13.5
    with RunWriter(tmp_path / "p", load_robot("irma4u"), "kinematic", 0.01, "sim") as w:
        pass
    assert read_run(tmp_path / "p").meta["robot"] == "irma4u" and len(read_run(tmp_path / "p")) == 0


def test_streaming_writer_events_and_reading_while_open(tmp_path: Path):
    src = make_run(N=12)
    w = RunWriter(
        tmp_path / "live", "irma4u", "equilibrium", 0.1, "sim",
        setpoints=src.setpoints, extra_columns=("motor_position_1", "note"),
    )
    for j in range(len(src)):
        w.append(
            src.t[j], src.tau[j], src.tau_ref[j], src.dl[j], src.dsigma[j], src.roll[j], src.pitch[j], src.dyaw[j],
            src.phase[j], src.setpoint[j], motor_position_1=src.extra["motor_position_1"][j], note="ok",
        )
        if j == 5:
            w.sync()
            w.add_event(src.t[j], "window", "first equilibrium window")
            partial = read_run(tmp_path / "live")  # readable while the acquisition goes on
            assert len(partial) == 6
            assert partial.events == [{"t": 0.5, "kind": "window", "message": "first equilibrium window"}]
    w.update_meta(zeroed_at={"t": 0.0, "how": "power-on"})
    w.add_event(1.1, "abort", "operator stop")
    w.close()
    back = read_run(tmp_path / "live")
    assert_same_samples(src, back)
    assert [e["kind"] for e in back.events] == ["window", "abort"]
    assert back.meta["zeroed_at"] == {"t": 0.0, "how": "power-on"}
    assert not list((tmp_path / "live").glob(".*.tmp"))
    with pytest.raises(ValueError, match="closed"):
        w.append(0, src.tau[0], src.tau[0], src.dl[0], src.dsigma[0], 0, 0, 0)


def test_writer_rejects_wrong_sizes_and_refuses_to_overwrite(tmp_path: Path):
    with RunWriter(tmp_path / "w", "irma4u", "equilibrium", 0.1, "sim") as w:
        with pytest.raises(ValueError, match="'dl' has 3 values, expected 4"):
            w.append(0.0, [1, 2, 3, 4], [1, 2, 3, 4], [1, 2, 3], [1, 2, 3, 4], 0, 0, 0)
        with pytest.raises(ValueError, match="unknown extra column"):
            w.append(0.0, [1] * 4, [1] * 4, [1] * 4, [1] * 4, 0, 0, 0, speed=3)
    with pytest.raises(FileExistsError):
        RunWriter(tmp_path / "w", "irma4u", "equilibrium", 0.1, "sim")


def test_a_run_cut_mid_line_reads_back_up_to_its_last_complete_line(tmp_path: Path):
    run = make_run(N=20)
    write_run(tmp_path / "c", run)
    f = tmp_path / "c" / "samples.csv"
    data = f.read_bytes()
    f.write_bytes(data[: len(data) - 40])  # crash in the middle of the 20th sample's line
    cut = r"1 cut short \(the log was cut while writing it\) \(line 21\); 19 samples kept"
    with pytest.warns(DamagedInputWarning, match=cut):
        back = read_run(tmp_path / "c")
    assert len(back) == 19
    assert_same_samples(run, back, count=19)


def _edit(tmp_path: Path, yaml_edit=None, csv_edit=None) -> Path:
    folder = tmp_path / "bad"
    write_run(folder, make_run(N=60), overwrite=True)
    if yaml_edit:
        meta = yaml.safe_load((folder / "run.yaml").read_text())
        yaml_edit(meta)
        (folder / "run.yaml").write_text(yaml.safe_dump(meta))
    if csv_edit:
        lines = (folder / "samples.csv").read_text().splitlines()
        csv_edit(lines)
        (folder / "samples.csv").write_text("\n".join(lines) + "\n")
    return folder


def _set_cell(lines, line_no, column, value):
    header = lines[0].split(",")
    cells = lines[line_no - 1].split(",")
    cells[header.index(column)] = value
    lines[line_no - 1] = ",".join(cells)


def _drop_column(lines, column):
    j = lines[0].split(",").index(column)
    for k, line in enumerate(lines):
        cells = line.split(",")
        del cells[j]
        lines[k] = ",".join(cells)


@pytest.mark.parametrize(
    "yaml_edit, csv_edit, message",
    [
        (lambda m: m.pop("format"), None, r"run\.yaml: required field 'format' is missing"),
        (lambda m: m.update(format="cdpr-run/2"), None, r"field 'format' = 'cdpr-run/2' is not a known format"),
        (lambda m: m.pop("robot"), None, r"required field 'robot' is missing"),
        (lambda m: m.update(robot="irma5u"), None, r"field 'robot' = 'irma5u' is not a built-in robot"),
        (lambda m: m["procedure"].pop("method"), None, r"required field 'procedure\.method' is missing"),
        (lambda m: m["procedure"].update(method="dance"), None, r"'procedure\.method' = 'dance' must be one of"),
        (lambda m: m["procedure"].update(sample_period=-0.1), None, r"'procedure\.sample_period' = -0\.1 must be"),
        (lambda m: m["procedure"].update(setpoints=[[1.0, 2.0, 3.0]]), None,
         r"field 'procedure\.setpoints\[0\]' = \[1\.0, 2\.0, 3\.0\] must be a list of 4 numbers"),
        (lambda m: m["procedure"].update(ideal_poses=[[0.0] * 6, [0.0] * 6]), None,
         r"'procedure\.ideal_poses' has 2 poses but 'procedure\.setpoints' has 1"),
        (None, lambda ls: _drop_column(ls, "tau_3"), r"samples\.csv: required column 'tau_3' is missing"),
    ],
)
def test_bad_runs_give_one_sentence_naming_file_field_and_value(tmp_path, yaml_edit, csv_edit, message):
    folder = _edit(tmp_path, yaml_edit, csv_edit)
    with pytest.raises(RunFormatError, match=message) as info:
        read_run(folder)
    text = str(info.value)
    assert str(folder) in text and text.endswith(".") and "\n" not in text


@pytest.mark.parametrize(
    "csv_edit, message",
    [
        (lambda ls: _set_cell(ls, 57, "dl_2", "0.1x"),
         r"samples\.csv: damaged input: 1 a non-numeric or non-finite value \(first: line 57 column 'dl_2' = "
         r"'0\.1x'\); 59 samples kept\."),
        (lambda ls: _set_cell(ls, 12, "pitch", "nan"), r"\(first: line 12 column 'pitch' = 'nan'\); 59 samples"),
        (lambda ls: ls.__setitem__(30, ls[30] + ",7"),
         r"1 wrong number of fields \(first: line 31 has 25 values, the header 24\); 59 samples kept"),
        (lambda ls: _set_cell(ls, 9, "setpoint", "two"), r"\(first: line 9 column 'setpoint' = 'two'\); 59 samples"),
    ],
)
def test_a_damaged_line_is_skipped_and_counted_in_one_warning(tmp_path, csv_edit, message):
    folder = _edit(tmp_path, None, csv_edit)
    with pytest.warns(DamagedInputWarning, match=message) as rec:
        back = read_run(folder)
    assert len(rec) == 1 and len(back) == 59


def test_missing_files_and_extra_keys(tmp_path: Path):
    with pytest.raises(RunFormatError, match="not a run folder"):
        read_run(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RunFormatError, match=r"run\.yaml: missing"):
        read_run(tmp_path / "empty")
    folder = _edit(tmp_path, yaml_edit=lambda m: m.update(operator="anna", sensors_zeroed={"t": -3.2}))
    assert read_run(folder).meta["operator"] == "anna"  # unknown keys are kept, not refused


def test_windows_line_endings_and_trailing_blank_lines(tmp_path: Path):
    run = make_run(N=8)
    write_run(tmp_path / "w", run)
    f = tmp_path / "w" / "samples.csv"
    f.write_bytes(f.read_bytes().replace(b"\n", b"\r\n") + b"\r\n\n")
    assert_same_samples(run, read_run(tmp_path / "w"))


def test_phase_and_setpoint_columns_are_optional(tmp_path: Path):
    def drop(lines):
        _drop_column(lines, "phase")
        _drop_column(lines, "setpoint")

    back = read_run(_edit(tmp_path, csv_edit=drop))
    assert len(back) == 60 and set(back.phase) == {""} and set(back.setpoint) == {-1}


def test_solution_file(tmp_path: Path):
    folder = tmp_path / "s"
    write_run(folder, make_run(N=3))
    assert read_solution(folder) is None
    sol = {"method": "tlse", "initial_pose": [0.36, 0.37, 1.16, 0.085, -0.072, 0.007], "reference_sample": 1}
    write_solution(folder, sol)
    assert read_solution(folder) == sol
    assert read_run(folder).n == 4  # readers of the run ignore solution.json
    (folder / "solution.json").write_text("{not json")
    with pytest.raises(RunFormatError, match=r"solution\.json: is not valid JSON"):
        read_solution(folder)
    assert math.isclose(read_run(folder).t[2], 0.2)


def test_warning_free_on_a_complete_file(tmp_path: Path):
    write_run(tmp_path / "ok", make_run(N=4))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(read_run(tmp_path / "ok")) == 4
