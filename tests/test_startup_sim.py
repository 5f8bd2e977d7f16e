"""`cdpr startup --backend sim` end to end: the real drivers against the simulated prototype, the run log,
the solve and the report; each simulated fault and an operator's SIGINT end in a safe stop.
"""

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml

import sim_backend.backend
from acquisition.cli import main
from acquisition.runlog import read_run
from acquisition.startup import StartupConfig
from drivers.loadcell import LoadCellDriver
from sim_backend.config import example_path
from sim_backend.plant_link import ChildPlantLink, child_process_possible


def _angle_errors_deg(a, b):
    return np.degrees(np.abs((np.asarray(a[3:]) - np.asarray(b[3:]) + math.pi) % (2 * math.pi) - math.pi))


def _check_pose(tmp_path, out, truth_file):
    sol = json.loads((out / "solution.json").read_text())
    truth = json.loads(truth_file.read_text())["window_mean_pose"]  # the pose a window-mean solve estimates
    est = np.array(sol["initial_pose"])
    pos_mm = 1000 * np.linalg.norm(est[:3] - np.array(truth[:3]))
    ang = _angle_errors_deg(est, truth)
    assert pos_mm <= 3.0, f"position error {pos_mm:.2f} mm"
    assert ang.max() <= 0.3, f"orientation errors {ang} deg"
    return sol


def test_grid2_equilibrium_lands_within_3mm_and_0_3deg(tmp_path, capsys):
    out, truth = tmp_path / "run", tmp_path / "truth.json"
    code = main(["startup", "--backend", "sim", "--grid", "2", "--out", str(out), "--truth", str(truth),
                 "--json"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    summary = json.loads(cap.out)
    assert summary["status"] == "ok" and summary["setpoints"] == 8
    sol = _check_pose(tmp_path, out, truth)
    run = read_run(out)
    assert run.setpoints.shape == (8, 4) and run.method == "equilibrium"
    assert len(summary["windows"]) == 8 and len(sol["windows"]) >= 8
    # the windows the loop held are logged as phase 'hold' with their setpoint index
    for j, (a, b) in enumerate(summary["windows"]):
        assert set(run.phase[a : b + 1]) == {"hold"} and set(run.setpoint[a : b + 1]) == {j}
        # at rest the tensions are at their setpoint within the integral deadband (averaged)
        np.testing.assert_allclose(run.tau[a : b + 1].mean(axis=0), run.setpoints[j], atol=1.6)
    off = yaml.safe_load((out / "offsets.yaml").read_text())
    assert off["pose"] == sol["initial_pose"] and len(off["lengths"]) == 4
    assert (out / "report.html").read_text().count("data:image/svg+xml;base64,") == 2
    assert not run.events


def test_kinematic_method_lands_within_3mm_and_0_3deg(tmp_path, capsys):
    out, truth = tmp_path / "run", tmp_path / "truth.json"
    code = main(["startup", "--backend", "sim", "--grid", "2", "--method", "kinematic", "--speed", "0.15",
                 "--out", str(out), "--truth", str(truth), "--json", "--no-html"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    sol = _check_pose(tmp_path, out, truth)
    assert sol["method"] == "lse"
    run = read_run(out)
    assert run.method == "kinematic" and run.setpoints is None
    moving = run.phase == "motion"
    assert moving.sum() * run.sample_period > 30.0  # the path is logged throughout
    assert np.ptp(run.dl[moving], axis=0).min() > 0.3  # m: every cable length changed along the path


def test_grid3_equilibrium_at_the_fastest_acceptable_settings(tmp_path, capsys):
    out, truth = tmp_path / "run", tmp_path / "truth.json"
    code = main(["startup", "--backend", "sim", "--grid", "3", "--max-rate", "80", "--hold", "1",
                 "--out", str(out), "--truth", str(truth), "--json", "--no-html"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    summary = json.loads(cap.out)
    assert summary["setpoints"] == 27 and len(summary["windows"]) == 27
    _check_pose(tmp_path, out, truth)


def _sample_noise(run, w):
    """Per-sample noise the run log shows inside the windows w: robust scale of second differences."""
    from calib.selfcal.windows import sample_noise

    rows = np.concatenate([np.arange(a, b + 1) for a, b in w])
    return {name: sample_noise(np.atleast_2d(getattr(run, name)[rows].T).T)
            for name in ("tau", "dl", "dsigma", "roll", "pitch")}


def test_grid3_noisy_sensors_sway_and_pauses_every_window_found_once(tmp_path, capsys):
    """AHRS and swivel encoders 15x noisier, load cells 3x, a 2 mm sway, a 15 s pause at setpoint 5 and a
    10 s pause back under tau0 after setpoint 12: one window per planned setpoint (none split, no pause
    used as a pose), the initial pose within 2 mm of the truth, and the noise logged is the one asked for."""
    out, truth = tmp_path / "run", tmp_path / "truth.json"
    code = main(["startup", "--backend", "sim", "--grid", "3", "--seed", "1", "--sim-config",
                 str(example_path("noisy_sensors")), "--pause", "5:15", "--pause", "12:10:home",
                 "--out", str(out), "--truth", str(truth), "--json", "--no-html"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    sol = json.loads((out / "solution.json").read_text())
    z = json.loads(truth.read_text())["window_mean_pose"]
    assert 1000 * np.linalg.norm(np.subtract(sol["initial_pose"][:3], z[:3])) <= 2.0
    ws = sol["window_search"]
    assert ws["planned"] == 27 and ws["used"] == 27 and ws["missing"] == []
    used = [w for w in ws["found"] if w["used"]]
    assert [w["setpoint"] for w in used] == list(range(27)) and not any(w["quasi"] for w in used)
    run = read_run(out)
    # the pause at setpoint 5 is inside its one window; the pause under tau0 is a still stretch not used
    w5 = used[5]
    assert set(run.phase[w5["first"] : w5["last"] + 1]) >= {"hold", "pause"}
    home = [w for w in ws["found"] if not w["used"] and "pause" in set(run.phase[w["first"] : w["last"] + 1])]
    # one stretch, or two when the platform's swing after the move home passes the ranges at a turning point
    # before it rests (seed 1 since the hold-time rule of issue 29: 1.5 s, 4.6 mm of cable from the rest)
    assert 1 <= len(home) <= 2
    noise = _sample_noise(run, [(w["first"], w["last"]) for w in used])
    np.testing.assert_allclose(noise["tau"], 0.3, rtol=0.3)
    np.testing.assert_allclose(noise["dl"], 2e-4, rtol=0.3)
    np.testing.assert_allclose(noise["dsigma"], 1.5e-3, rtol=0.3)
    np.testing.assert_allclose(np.degrees([noise["roll"], noise["pitch"]]).ravel(), 0.45, rtol=0.3)


def test_realistic_noise_configuration_acts(tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["startup", "--backend", "sim", "--grid", "2", "--sim-config", str(example_path("realistic_noise")),
                 "--out", str(out), "--json", "--no-html"])
    assert code == 0, capsys.readouterr().err
    run = read_run(out)
    sol = json.loads((out / "solution.json").read_text())
    assert [w["setpoint"] for w in sol["window_search"]["found"] if w["used"]] == list(range(8))
    noise = _sample_noise(run, [w for w in sol["windows"]])
    # the load cells close the tension loop: their 1 N noise also moves the true tensions a little (measured
    # 0.98 to 1.36 N per channel, 1.16 N on average)
    assert np.mean(noise["tau"]) == pytest.approx(1.0, rel=0.3)
    assert np.mean(noise["dl"]) == pytest.approx(2e-4, rel=0.3)  # measured 0.18 to 0.26 mm
    assert np.degrees(np.mean([noise["roll"], noise["pitch"]])) == pytest.approx(0.02, rel=0.4)  # 0.022, 0.025


def _fault(tmp_path, capsys, name):
    out = tmp_path / name
    code = main(["startup", "--backend", "sim", "--grid", "2", "--out", str(out), "--sim-config",
                 str(example_path(name))])
    err = capsys.readouterr().err.strip()
    run = read_run(out)  # complete and readable
    return code, err, run


@pytest.mark.parametrize(
    "name, kind, words",
    [
        ("fault_can_frames_lost", "stale_sensor", "silent"),
        ("fault_drive_fault", "drive_fault", "winch 2"),
        ("fault_loadcell_stuck", "sensor_fault", "load cell 3"),
        ("fault_loadcell_disconnected", None, "load"),
        ("fault_ahrs_corrupt", "corrupted_stream", "AHRS"),
        ("fault_cable_slack", "slack", "cable 1"),
    ],
)
def test_each_simulated_fault_ends_in_a_safe_stop(tmp_path, capsys, name, kind, words):
    code, err, run = _fault(tmp_path, capsys, name)
    assert code == 1
    assert err.startswith("cdpr: safe stop: ") and err.count("\n") == 0 and words in err, err
    assert len(run.events) == 1
    ev = run.events[0]
    if kind is not None:
        assert ev["kind"] == kind, ev
    # the fault is injected at 20 s of simulated time; the log goes on through the safe stop
    assert "safe_stop" in set(run.phase)
    stop = run.phase == "safe_stop"
    assert np.all(np.diff(run.t) > 0)
    # the stop ramps the references down towards the safe pretension
    assert run.tau_ref[stop][-1].max() < run.tau_ref[stop][0].max() + 1e-9


def test_same_seed_same_run_log_byte_for_byte_however_late_the_plant_runs(tmp_path, capsys, monkeypatch):
    # a cable slips early, while the platform settles under tau0: the stop comes before the run log would
    # start, so the samples seen so far are written with the event. In the first run the simulated plant's
    # child process is stopped for longer than the loop waits for a device (a loaded machine's worst case,
    # made sure: right after it answered SYNC 499); the second has the plant in the routine's own process,
    # undisturbed: the same bytes either way (before the fix the loop went on with the last tick's load cells).
    # The child is also stopped as the load cells are asked for INFO, for longer than a real serial device's
    # handshake answer is awaited (1 s): the simulated devices answer from that process, and once a loaded machine
    # ran it that late the load cells "did not answer INFO within 1 s" and the startup stopped before its first SYNC
    cfg = tmp_path / "early_slack.yaml"
    cfg.write_text("faults:\n  - {kind: cable_slack, t: 6.0, cable: 2, length: 0.05}\n")
    stalled, links, emit, init, greet = [], [], ChildPlantLink.emit, ChildPlantLink.__init__, LoadCellDriver._greet
    stall = StartupConfig.device_timeout + 0.3

    def stop(link, at):
        os.kill(link.pid, signal.SIGSTOP)
        threading.Timer(stall, os.kill, (link.pid, signal.SIGCONT)).start()
        stalled.append(at)

    def stalling_init(link, core):
        init(link, core)
        links.append(link)

    def stalling_greet(driver):
        if links:
            stop(links.pop(), "INFO")
        greet(driver)

    def stalling_emit(link, count):
        if count == 500:
            stop(link, count)
        emit(link, count)

    monkeypatch.setattr(ChildPlantLink, "__init__", stalling_init)
    monkeypatch.setattr(LoadCellDriver, "_greet", stalling_greet)
    monkeypatch.setattr(ChildPlantLink, "emit", stalling_emit)
    logs = []
    for k in range(2):
        if k == 1:
            assert stalled == (["INFO", 500] if child_process_possible() else [])
            monkeypatch.setattr(sim_backend.backend, "child_process_possible", lambda: False)
        out = tmp_path / f"run{k}"
        code = main(["startup", "--backend", "sim", "--seed", "3", "--out", str(out), "--sim-config", str(cfg)])
        assert code == 1
        assert "cable 2 slack" in capsys.readouterr().err
        logs.append((out / "samples.csv").read_bytes())
        run = read_run(out)
        assert run.phase[0] == "pretension" and run.phase[-1] == "safe_stop" and run.events[0]["kind"] == "slack"
    assert logs[0] == logs[1] and logs[0].count(b"\n") > 40


def test_sigint_during_the_run_ends_in_a_safe_stop(tmp_path):
    out = tmp_path / "run"
    env = dict(os.environ)
    cmd = [sys.executable, "-c", "import sys; from acquisition.cli import main; sys.exit(main())",
           "startup", "--backend", "sim", "--grid", "2", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    deadline = time.monotonic() + 120
    samples = out / "samples.csv"
    while time.monotonic() < deadline:
        if samples.exists() and samples.read_text().count("\n") > 40:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 1
    assert stderr.strip() == f"cdpr: safe stop: stopped by the operator (SIGINT) (run log: {out})."
    run = read_run(out)
    assert [e["kind"] for e in run.events] == ["operator"]
    assert run.phase[-1] == "safe_stop" and len(run) > 40


def test_bad_options_and_absent_devices_end_with_one_sentence(tmp_path, capsys):
    assert main(["startup", "--backend", "sim", "--grid", "9"]) == 2
    assert capsys.readouterr().err == "cdpr: --grid 9 is out of range: give 2 to 6 grid points per axis.\n"
    assert main(["startup", "--backend", "sim", "--rate", "1000"]) == 2
    assert capsys.readouterr().err == "cdpr: --rate 1000 is outside the control rates 200..500 Hz.\n"  # named
    assert main(["startup", "--backend", "hw"]) == 2
    assert capsys.readouterr().err == "cdpr: --backend hw needs --config FILE (the device configuration YAML).\n"
    cfg = tmp_path / "devices.yaml"
    nodes = lambda base: [{"name": f"n{i}", "node_id": base + i} for i in range(1, 5)]  # noqa: E731
    cfg.write_text(yaml.safe_dump({
        "can": {"interface": "virtual", "channel": f"nobody-{os.getpid()}", "bitrate": 1000000},
        "drives": nodes(0), "encoders": nodes(10),
        "loadcells": {"port": str(tmp_path / "no-port"), "baud": 115200},
        "ahrs": {"port": str(tmp_path / "no-port-2"), "baud": 115200, "rate": 100},
    }))
    assert main(["startup", "--backend", "hw", "--config", str(cfg), "--out", str(tmp_path / "run")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("cdpr: device check failed: n1 (CAN node 1): ") and err.count("\n") == 1, err
    assert not (tmp_path / "run").exists()


def test_feedback_rates_halve_the_frames_and_every_log_tick_is_fresh():
    from acquisition.clock import SimClock
    from acquisition.connect import ahrs_rate_for, connect, feedback_every
    from calib.robot import load_robot
    from sim_backend.backend import SimBackend

    assert feedback_every(200.0, 20) == (4, 20)  # drives at 50 Hz, encoders at the 10 Hz log rate
    assert feedback_every(500.0, 50) == (10, 10)  # gcd(50, 240) = 10
    assert feedback_every(250.0, 25) == (5, 5)
    assert feedback_every(200.0, 20, overflow=0) == (1, 1)  # no SYNC counter: every SYNC
    assert [ahrs_rate_for(p) for p in (0.1, 0.05, 0.2, 0.03, 0.0071)] == [10, 20, 5, 100, 100]
    robot = load_robot("irma4u")
    period = 0.005
    with SimBackend(robot, None, seed=3, control_period=period) as sim:
        clock = SimClock(period)
        rig = connect(sim.devices, robot, clock, lockstep=True, period=period, every=(4, 20))
        try:
            assert rig.periods()["swivel encoder 1"] == pytest.approx(0.1)
            assert rig.periods()["winch drive 1"] == pytest.approx(0.02)
            sent0 = [n.frames_sent for n in sim.encoders]
            snaps = []
            for _ in range(45):
                tk = clock.advance()
                snap = rig.tick(tk.index, tk.t)
                snaps.append(snap)
                if tk.index % 20 == 0:  # a log tick: every drive and encoder answered this very SYNC
                    assert [d.latest().sync_count for d in rig.drives] == [snap.sync] * 4
                    assert [e.latest().sync_count for e in rig.encoders] == [snap.sync] * 4
                    assert np.array_equal(snap.dsigma, [e.latest().delta_angle for e in rig.encoders])
                if tk.index % 4 == 0:
                    assert [d.latest().sync_count for d in rig.drives] == [snap.sync] * 4
            assert all(s.missing == () for s in snaps)
            assert all(np.isfinite(s.dl).all() and np.isfinite(s.dsigma).all() for s in snaps)
            # 45 SYNCs: encoders answered SYNCs 1, 21, 41 (beside their heartbeats)
            tpdos = [n.frames_sent - s0 for n, s0 in zip(sim.encoders, sent0, strict=True)]
            beats = int(45 * period / sim.devices.can.heartbeat_period + 1e-9)
            assert all(t in (3 + beats, 3 + beats + 1) for t in tpdos)
        finally:
            rig.close()
