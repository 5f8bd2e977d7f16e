"""IRMA importers on the authors' real recording sc_8_final (parsed .mat and raw controller log)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from scipy.optimize import least_squares

from acquisition.damage import CUT, DamagedInputWarning
from acquisition.importers import (
    IRMA_HOMING_LENGTHS,
    IRMA_HOMING_SWIVELS,
    PARTIAL,
    IrmaImportError,
    import_irma,
    irma_run,
    read_irma_log,
    read_irma_parsed,
)
from acquisition.runlog import read_run
from acquisition.segmentation import segment_targets
from calib.kinematics import inverse_kinematics
from calib.robot import load_robot


@pytest.fixture(scope="module")
def parsed_run(irma_data, tmp_path_factory):
    return import_irma(irma_data / "sc_8_final_parsed.mat", tmp_path_factory.mktemp("imp") / "parsed")


@pytest.fixture(scope="module")
def log_run(irma_data, tmp_path_factory):
    return import_irma(irma_data / "sc_8_final.log", tmp_path_factory.mktemp("imp") / "log")


@pytest.fixture(scope="module")
def authors(irma_data):
    with warnings.catch_warnings():  # their workspace holds MATLAB objects saved under the name "None"
        warnings.simplefilter("ignore", scipy.io.matlab.MatReadWarning)
        return scipy.io.loadmat(irma_data / "ws_selfcalibration_8_final.mat", squeeze_me=True, struct_as_record=False)


@pytest.fixture(scope="module")
def plan(irma_data):
    out = scipy.io.loadmat(irma_data / "sc_control_target_8_final.mat", squeeze_me=True, struct_as_record=False)["out"]
    return out.static_tensions.T, out.opt_meas_config.T


def test_parsed_import_basics(parsed_run, irma_data):
    run = read_run(parsed_run.path)
    assert len(run) == 1280 and run.n == 4 and run.robot.name == "irma4u"
    assert run.source == "import:irma-parsed" and run.method == "equilibrium" and run.sample_period == 0.1
    assert run.t[0] == 0.0 and np.allclose(np.diff(run.t), 0.1, atol=1e-9)
    assert run.meta["time_origin"] == 257.854
    assert run.meta["homing"]["lengths"] == list(IRMA_HOMING_LENGTHS)
    assert run.meta["homing"]["swivels"] == list(IRMA_HOMING_SWIVELS)
    st = scipy.io.loadmat(irma_data / "sc_8_final_parsed.mat", squeeze_me=True, struct_as_record=False)["st"]
    np.testing.assert_array_equal(run.tau, st.tensions.T)
    np.testing.assert_array_equal(run.tau_ref, st.target_tensions.T)
    np.testing.assert_allclose(run.t + 257.854, st.t, atol=1e-9)


def test_parsed_deltas_match_the_authors_measurements(parsed_run, authors):
    """absolute = homing + delta at the authors' hand-picked samples meas_idx - 1."""
    idx = authors["meas_idx"] - 1
    run = parsed_run
    hl, hs = np.array(IRMA_HOMING_LENGTHS), np.array(IRMA_HOMING_SWIVELS)
    np.testing.assert_allclose(hl + run.dl[idx], authors["cable_length_meas"].T, atol=1e-12)
    np.testing.assert_allclose(hs + run.dsigma[idx], authors["swivel_meas"].T, atol=1e-12)
    np.testing.assert_allclose(run.roll[idx], authors["epsilon_meas"][0], atol=1e-15)
    np.testing.assert_allclose(run.pitch[idx], authors["epsilon_meas"][1], atol=1e-15)
    np.testing.assert_allclose(run.dyaw[idx], authors["epsilon_meas"][2], atol=1e-15)
    np.testing.assert_allclose(run.tau[idx[1:]], authors["loadcell_meas"].T, atol=1e-12)
    # their deltas are relative to the first picked sample
    np.testing.assert_allclose(run.dl[idx[1:]] - run.dl[idx[0]], authors["delta_length_meas"].T, atol=1e-12)
    np.testing.assert_allclose(run.dsigma[idx[1:]] - run.dsigma[idx[0]], authors["delta_swivel_meas"].T, atol=1e-12)
    np.testing.assert_allclose(run.dyaw[idx[1:]] - run.dyaw[idx[0]], authors["delta_yaw_meas"], atol=1e-12)


def test_raw_log_gives_the_same_signals_as_the_parsed_file(parsed_run, log_run):
    p, r = parsed_run, log_run
    assert r.source == "import:irma-log" and len(r) == len(p) == 1280
    np.testing.assert_array_equal(r.t, p.t)
    np.testing.assert_array_equal(r.tau, p.tau)
    np.testing.assert_array_equal(r.tau_ref, p.tau_ref)
    for name in ("dsigma", "roll", "pitch", "dyaw"):  # same to float rounding (unit conversions)
        np.testing.assert_allclose(getattr(r, name), getattr(p, name), rtol=0, atol=1e-12, err_msg=name)
    assert r.meta["homing"]["recording"]["samples"] == 65
    assert r.meta["homing"]["recording"]["t"] == [184.922, 191.322]


def test_raw_and_parsed_lengths_differ_by_the_transmission_ratio(parsed_run, log_run):
    """The parser uses one m/rev for all winches, the controller each winch's own: dl ratio is constant."""
    moving = np.abs(parsed_run.dl) > 0.05
    ratios = []
    for i in range(4):
        q = log_run.dl[moving[:, i], i] / parsed_run.dl[moving[:, i], i]
        assert np.ptp(q) < 1e-9
        ratios.append(q.mean())
    ratios = np.array(ratios)
    np.testing.assert_allclose(ratios, [1.02645, 1.02092, 1.01367, 1.02055], atol=1e-5)
    lpr = np.array(load_robot("irma4u").sensors.length_per_motor_rev)
    common = lpr / ratios  # the parser's single ratio, the same for the four winches
    np.testing.assert_allclose(common, -0.0280645, atol=1e-6)  # lpr has 5 digits
    assert np.max(np.abs(log_run.dl - parsed_run.dl)) > 0.03  # the difference is real: tens of mm


def test_the_two_imports_solved_with_the_same_effects_land_together(parsed_run, log_run, capsys):
    """Issue 28, done-when 2: the two files differ only by the per-winch transmission ratio, which length_scale
    takes whole. `cdpr solve --noise estimate --effects tension_offset,length_scale` weighs each channel by what
    that model leaves of it: the two initial positions agree to 0.03 mm (8.2 mm apart with the rigid model's
    weights, where the raw lengths' unmodelled scale had set their sigma to 8 mm, the parsed 1.2 mm), and the
    fitted scales carry the ratio of the two files: (1 + k_raw) / (1 + k_parsed) = 1.0265, 1.0209, 1.0137,
    1.0206."""
    import json

    from acquisition.cli import main as cdpr

    sols = {}
    for name, run in (("parsed", parsed_run), ("log", log_run)):
        capsys.readouterr()
        assert cdpr(["solve", str(run.path), "--noise", "estimate", "--effects", "tension_offset,length_scale",
                     "--json"]) == 0
        sols[name] = json.loads(capsys.readouterr().out)
    p, r = sols["parsed"], sols["log"]
    assert np.linalg.norm(np.subtract(r["initial_pose"][:3], p["initial_pose"][:3])) < 0.2e-3
    assert r["noise"]["length"] == pytest.approx(p["noise"]["length"], rel=0.05)  # 1.05 mm both
    k = {n: np.array([s["effects"]["length_scale"][f"k_{i}"] for i in range(1, 5)]) for n, s in sols.items()}
    np.testing.assert_allclose((1 + k["log"]) / (1 + k["parsed"]), [1.02645, 1.02092, 1.01367, 1.02055], atol=2e-4)


def test_the_parsers_lengths_fit_the_geometry_better(parsed_run, log_run, authors):
    """Pose (x, y, z, yaw) fitted to 4 swivels + 4 lengths at the 8 picked samples, roll/pitch from the AHRS."""
    robot = load_robot("irma4u")
    hl, hs = np.array(IRMA_HOMING_LENGTHS), np.array(IRMA_HOMING_SWIVELS)
    chi2 = {}
    for name, run in (("parsed", parsed_run), ("log", log_run)):
        total = 0.0
        for j in authors["meas_idx"] - 1:
            sw, lengths = hs + run.dsigma[j], hl + run.dl[j]

            def res(x, j=j, sw=sw, lengths=lengths, run=run):
                kin = inverse_kinematics(robot, np.r_[x[:3], run.roll[j], run.pitch[j], x[3]][None])
                return np.r_[(kin.swivel[0] - sw) / np.radians(1.0), (kin.lengths[0] - lengths) / 0.01]

            total += 2 * least_squares(res, [0.0, 0.0, 1.0, 0.0]).cost
        chi2[name] = total
    assert chi2["parsed"] < 8.0  # 5.4 measured
    assert chi2["log"] > 5 * chi2["parsed"]  # 52 measured: the controller's ratios carry a scale error


def test_raw_log_extra_columns_agree_with_the_lengths(log_run):
    lpr = np.array(load_robot("irma4u").sensors.length_per_motor_rev)
    counts = np.stack([log_run.extra[f"motor_position_{i}"] for i in range(1, 5)], axis=1)
    assert counts.dtype.kind == "f" and np.all(counts == np.round(counts))
    from_counts = (counts - counts[0]) * lpr / 2**20
    np.testing.assert_allclose(log_run.dl - log_run.dl[0], from_counts, atol=2e-5)
    assert {"motor_speed_1", "motor_torque_4", "aux_position_2", "state_3"} <= set(log_run.extra)


def test_setpoints_found_in_the_target_tensions(parsed_run, plan):
    planned, _ = plan
    found = parsed_run.setpoints
    # all eight: the two poses the controller left before every target had settled (the next move began)
    # are recovered from the quintic their still-moving targets followed (the authors' static_tensions)
    assert found.shape == (8, 4)
    np.testing.assert_allclose(found, planned, atol=2e-3)
    hold = parsed_run.setpoint >= 0
    np.testing.assert_array_equal(parsed_run.tau_ref[hold], found[parsed_run.setpoint[hold]])
    assert sorted(set(parsed_run.setpoint[hold])) == [1, 2, 3, 5, 6, 7]  # 0 and 4 were never held
    assert set(parsed_run.phase[:79]) == {"pretension"} and set(parsed_run.phase[hold]) == {"hold"}


def test_raw_log_import_lists_the_eight_setpoints(log_run, plan):
    np.testing.assert_allclose(log_run.setpoints, plan[0], atol=2e-3)


def test_a_move_cut_by_the_next_one_is_extended_to_its_destination():
    k = np.arange(60.0)
    u = np.clip(k / 80.0, 0, 1)  # an 80-sample quintic from 50 to 130 N, cut at 60 samples
    T = np.full((200, 2), 50.0)
    T[10:70, 0] = 50.0 + 80.0 * u**3 * (10 - 15 * u + 6 * u**2)
    T[10:70, 1] = 50.0 + np.minimum(k, 30) * 1.0  # the other target reached 80 N and stays there
    T[70:] = [110.0, 79.0]  # the reference restarts from the measured tensions and holds them
    seg = segment_targets(T, 0.1)
    np.testing.assert_allclose(seg.setpoints, [[130.0, 80.0], [110.0, 79.0]], atol=1e-3)
    assert seg.cut == [(0, 69)] and seg.plateaus == [(70, 199)] and set(seg.index[10:70]) == {-1}


def test_import_with_the_planned_targets(irma_data, plan, tmp_path):
    run = import_irma(irma_data / "sc_8_final.log", tmp_path / "r", targets=irma_data / "sc_control_target_8_final.mat")
    planned, poses = plan
    np.testing.assert_allclose(run.setpoints, planned, atol=1e-12)
    np.testing.assert_allclose(run.ideal_poses, poses, atol=1e-12)
    assert sorted(set(run.setpoint) - {-1}) == [1, 2, 3, 5, 6, 7]
    hold = run.setpoint >= 0
    np.testing.assert_allclose(run.tau_ref[hold], planned[run.setpoint[hold]], atol=1e-3)


def test_segment_targets_on_a_synthetic_sequence():
    T = np.full((100, 2), 100.0)
    T[20:30] = np.linspace([100, 100], [150, 60], 11)[1:]
    T[30:50] = [150, 60]
    T[50:60] = np.linspace([150, 60], [80, 90], 11)[1:]
    T[60:75] = [80, 90]
    T[75:] = np.linspace([80, 90], [100, 100], 26)[1:]
    seg = segment_targets(T, 0.1)
    np.testing.assert_array_equal(seg.setpoints, [[150, 60], [80, 90]])
    assert seg.plateaus == [(29, 49), (59, 74)]
    assert seg.phase[0] == "pretension" and seg.phase[40] == "hold" and seg.phase[55] == "transition"
    assert seg.index[40] == 0 and seg.index[70] == 1 and seg.index[90] == -1


def test_truncated_raw_log_drops_its_last_incomplete_cycle(irma_data, tmp_path):
    data = (irma_data / "sc_8_final.log").read_bytes()
    cut = tmp_path / "cut.log"
    cut.write_bytes(data[:-20])  # the log stops inside the last AHRS line
    sig = read_irma_log(cut)
    assert sig.damage.counts == {CUT: 1, PARTIAL: 1}  # the cut line, and the cycle it belonged to
    assert sig.t.shape == (1279,) and sig.t[-1] == pytest.approx(385.654)
    with pytest.warns(DamagedInputWarning, match=r"cut\.log: damaged input: 1 cut short .*; 1279 samples kept"):
        irma_run(cut)


def test_the_medium_raw_log_keeps_every_cycle_the_parsed_file_has(irma_data):
    """sc_8_medium_a's cycles are stamped up to 1 ms apart (its cable lines before its AHRS line): the import kept
    1362 of its 2076 experiment cycles before issue 28i, and now every one, at the parsed file's times."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", DamagedInputWarning)
        run = irma_run(irma_data / "sc_8_medium_a.log", targets=irma_data / "sc_control_target_8.mat")
    parsed = read_irma_parsed(irma_data / "sc_8_medium_a_parsed.mat")
    assert len(run) == len(parsed.t) == 2076 and run.meta["homing"]["recording"]["samples"] == 58
    np.testing.assert_allclose(run.t + run.meta["time_origin"], parsed.t, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(run.tau, parsed.tension)
    assert run.setpoints.shape == (8, 4)


@pytest.mark.parametrize(
    "content, message",
    [
        ("3,1.0,0,9,1,2,3,0.5,0,40,55,1,0,0.3\n5,1.0,0.1,0.2\n",
         r"no complete logging cycle .*; damaged input: 1 wrong number of fields \(first: line 2 \(type 5\) has 4 "),
        ("3,1.0,0,9,1,2,3,0.5,0,40,55,1,0,0.3\n5,1.0,0.1,abc,0.3\n", r"\(first: line 2 has the value 'abc'\)"),
        ("3,1.0,7,9,1,2,3,0.5,0,40,55,1,0,0.3\n", r"\(first: line 1 has actuator id '7', expected 0\.\.3\)"),
    ],
)
def test_bad_raw_logs(tmp_path, content, message):
    f = tmp_path / "bad.log"
    f.write_text(content)
    with pytest.raises(IrmaImportError, match=message) as info:
        import_irma(f, tmp_path / "run")
    assert str(f) in str(info.value)


def test_raw_log_without_homing_pause_is_refused(tmp_path):
    lines = []
    for k in range(5):
        t = 10 + 0.1 * k
        lines += [f"3,{t:.3f},{i},9,{i},0,0,0.5,0,40,55,0,0,0.3" for i in range(4)] + [f"5,{t:.3f},0.1,0.2,0.3"]
    f = tmp_path / "nopause.log"
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(IrmaImportError, match="no pause longer than 1.0 s"):
        import_irma(f, tmp_path / "run")


def test_bad_parsed_files(tmp_path: Path):
    f = tmp_path / "other.mat"
    scipy.io.savemat(f, {"x": np.ones(3)})
    with pytest.raises(IrmaImportError, match=r"variable 'st' is missing \(variables found: x\)"):
        import_irma(f, tmp_path / "r1")
    g = tmp_path / "short_parsed.mat"
    st = {"t": np.arange(5.0), "epsilon": np.zeros((3, 5)), "cable_length": np.zeros((4, 5)),
          "swivel": np.zeros((4, 5)), "tensions": np.zeros((4, 4))}
    scipy.io.savemat(g, {"st": st})
    with pytest.raises(IrmaImportError, match=r"field 'st\.target_tensions' is missing"):
        import_irma(g, tmp_path / "r2")
    st["target_tensions"] = np.zeros((4, 5))
    scipy.io.savemat(g, {"st": st})
    with pytest.raises(IrmaImportError, match=r"0 steady setpoint hold\(s\) in the experiment \(4 samples\), a solve "
                       r"needs at least 2; damaged input: 1 samples missing from a field \(first: field 'st\.tensions' "
                       r"has 4 samples, 'st\.t' 5\)\."):
        import_irma(g, tmp_path / "r3")
    h = tmp_path / "notes.txt"
    h.write_text("hello\n")
    with pytest.raises(IrmaImportError, match="neither a MATLAB v5"):
        import_irma(h, tmp_path / "r4")
