"""Equilibrium windows against the run's own noise and the plan (calib.selfcal.windows), and the online
detector that shares their noise estimate; synthetic signals, no simulator (fast), and the real sc_8_final."""

from __future__ import annotations

import math

import numpy as np
import pytest

from acquisition.equilibrium import DetectorConfig, EquilibriumDetector
from calib.robot import load_robot
from calib.selfcal import Stillness, WindowOptions, search_windows
from calib.selfcal.windows import SettleTest, quiet_noise, settle_test, still_channels

DT = 0.1


@pytest.fixture(scope="module")
def robot():
    return load_robot("irma4u")


def _quintic(a, b, m):
    u = np.linspace(0.0, 1.0, m)[:, None]
    return a + (b - a) * u**3 * (10 - 15 * u + 6 * u**2)


def _swing(ref, decay=0.8, hz=0.7):
    """(N,) the platform's damped swing after each move of the reference: e-folding ``decay`` s, ``hz`` Hz
    (0: a creep towards rest without a swing)."""
    N = ref.shape[0]
    t = np.arange(N) * DT
    moving = np.r_[0.0, np.abs(np.diff(ref, axis=0)).max(axis=1)] > 1e-9
    swing = np.zeros(N)
    last = -1e9
    for i in range(N):
        if moving[i]:
            last = t[i]
        phase = math.sin(2 * math.pi * hz * (t[i] - last)) if hz else 1.0
        swing[i] = math.exp(-(t[i] - last) / decay) * phase if last > -1e9 else 0
    return swing


def _run(rng, setpoints, rest=12.0, move=4.0, noise=1.0, sway=0.0, blocks=None, tail=True, decay=0.8, hz=0.7):
    """A synthetic run: rest under tau0, then per block (setpoint j or the pretension tau0 for a pause) a
    quintic move of ``move`` s and a rest of ``rest`` s; poses follow the tensions (lengths, swivels, tilt
    proportional to the tension change). ``noise`` scales the noisy-sensor sigmas (0.3 N, 0.2 mm,
    1.5e-3 rad, 0.45 deg); ``sway`` m of a slow 8 s sway on every kinematic channel."""
    tau0 = np.full(4, 100.0)
    blocks = list(range(len(setpoints))) if blocks is None else blocks
    target = [tau0] + [tau0 if j < 0 else setpoints[j] for j in blocks] + ([tau0] if tail else [])
    m, r = int(move / DT), int(rest / DT)
    ref = [np.tile(tau0, (r, 1))]
    for a, b in zip(target[:-1], target[1:], strict=True):
        ref += [_quintic(a, b, m), np.tile(b, (r, 1))]
    ref = np.vstack(ref)
    N = ref.shape[0]
    # the platform lags the reference by a damped swing that dies out within a few seconds of each rest
    tau = ref.copy()
    dtau = ref - tau0
    t = np.arange(N) * DT
    swing = _swing(ref, decay, hz)
    sw = sway * (np.sin(2 * math.pi * t / 8.0) + 0.5 * np.sin(2 * math.pi * t / 6.4 + 1.0))
    dl = 2e-3 * dtau + 0.004 * swing[:, None] + sw[:, None]
    dsig = 1e-3 * dtau + 0.01 * swing[:, None] + 5 * sw[:, None]
    tilt = np.radians(0.02) * dtau[:, :2] + np.radians(1.0) * swing[:, None] + 2 * sw[:, None]
    tau = tau + 3.0 * swing[:, None]
    s = noise
    tau = tau + 0.3 * s * rng.standard_normal(tau.shape)
    dl = dl + 2e-4 * s * rng.standard_normal(dl.shape)
    dsig = dsig + 1.5e-3 * s * rng.standard_normal(dsig.shape)
    tilt = tilt + math.radians(0.45) * s * rng.standard_normal(tilt.shape)
    return t, tau, ref, dl, dsig, tilt[:, 0], tilt[:, 1]


def _setpoints(rng, k):
    return 100.0 + rng.uniform(-40.0, 60.0, (k, 4))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noisy_sensors_and_sway_every_setpoint_gets_its_window(robot, seed):
    rng = np.random.default_rng(seed)
    sp = _setpoints(rng, 12)
    t, tau, ref, dl, dsig, roll, pitch = _run(rng, sp, sway=0.002)
    ws = search_windows(robot, t, tau, dl, dsig, roll, pitch, ref, sp)
    assert ws.planned == 12 and ws.missing == []
    assert [w.setpoint for w in ws.used] == list(range(12))
    assert [w.setpoint for w in ws.found] == [-1, *range(12), -1]  # the rests under tau0 are listed only
    # the fixed tolerances of the prototype (no noise term) find almost no still window in the same run
    fixed = WindowOptions(noise_factor=0.0, drift_factor=0.0)
    assert sum(not w.quasi for w in search_windows(robot, t, tau, dl, dsig, roll, pitch, ref, sp, fixed).used) <= 4


def test_prototype_noise_keeps_the_fixed_tolerances(robot):
    rng = np.random.default_rng(3)
    sp = _setpoints(rng, 6)
    t, tau, ref, dl, dsig, roll, pitch = _run(rng, sp, noise=0.05)
    ws = search_windows(robot, t, tau, dl, dsig, roll, pitch, ref, sp)
    assert [w.setpoint for w in ws.used] == list(range(6))
    opt = WindowOptions()
    np.testing.assert_allclose(ws.thresholds["length"], opt.length_tol)
    np.testing.assert_allclose(ws.thresholds["tilt"], opt.tilt_tol)


def test_pauses_are_listed_and_a_long_hold_is_one_window(robot):
    rng = np.random.default_rng(4)
    sp = _setpoints(rng, 5)
    # setpoint 1 held twice as long (a pause at it), then a pause back under tau0 between 2 and 3
    blocks = [0, 1, 1, 2, -1, 3, 4]
    t, tau, ref, dl, dsig, roll, pitch = _run(rng, sp, blocks=blocks, sway=0.002)
    ws = search_windows(robot, t, tau, dl, dsig, roll, pitch, ref, sp)
    assert [w.setpoint for w in ws.used] == list(range(5))
    assert [w.setpoint for w in ws.found] == [-1, 0, 1, 2, -1, 3, 4, -1]
    one = next(w for w in ws.used if w.setpoint == 1)
    assert one.size * DT > 20.0  # both rests at setpoint 1 (and the still move between them) in one window
    pause = ws.found[4]
    np.testing.assert_allclose(ref[pause.slice].mean(axis=0), 100.0, atol=0.01)  # the pause under tau0


def test_a_setpoint_without_a_window_is_named_with_its_reason(robot):
    rng = np.random.default_rng(5)
    sp = _setpoints(rng, 4)
    t, tau, ref, dl, dsig, roll, pitch = _run(rng, sp, tail=False)
    cut = len(t) - int(15.0 / DT)  # the log ends 1 s into the move to the last setpoint
    ws = search_windows(robot, t[:cut], tau[:cut], dl[:cut], dsig[:cut], roll[:cut], pitch[:cut], ref[:cut], sp)
    assert [w.setpoint for w in ws.used] == [0, 1, 2]
    assert [m.setpoint for m in ws.missing] == [3]
    assert ws.missing[0].reason == "setpoint 3: the log ends before its tensions were reached."
    # the platform kept swinging at setpoint 2: no still stretch, the reason says how far from still
    full = search_windows(robot, t, tau, dl, dsig, roll, pitch, ref, sp).used
    swinging = dl.copy()
    span = slice(full[1].last + 1, full[3].first)
    swinging[span] += 0.2 * np.sin(2 * np.pi * 0.7 * t[span])[:, None]
    ws = search_windows(robot, t, tau, swinging, dsig, roll, pitch, ref, sp)
    miss = {m.setpoint: m.reason for m in ws.missing}
    assert list(miss) == [2] and "never came to rest" in miss[2]


def _feed(det, rng, n, t0=0.0, sigma=0.3):
    """n samples of a platform at rest with load cells of ``sigma`` N; the last state."""
    st = None
    for k in range(1, n):
        st = det.push(t0 + k * DT, 100.0 + sigma * rng.standard_normal(4), 2e-5 * rng.standard_normal(4),
                      1e-4 * rng.standard_normal(4), 1e-4 * rng.standard_normal(), 1e-4 * rng.standard_normal())
        if st.settled or st.timed_out:
            break
    return st


def test_online_detector_learns_the_noise_it_sees(robot):
    """With 0.3 N load cells a tension ripple tolerance of 0.196 N never settles; the offline ripple tolerance
    (3 x the tensions' noise floor) the detector learns from the samples it sees lets it settle."""
    rng = np.random.default_rng(6)
    cfg = DetectorConfig.for_robot(robot, timeout=20.0)
    det = EquilibriumDetector(DT, cfg)
    det.start(0.0)
    st = _feed(det, rng, 300)
    assert st.settled and st.elapsed < 5.0
    for j in range(300):  # 30 s more: the noise floor estimate converges to 0.3 N
        det.push(30.0 + j * DT, 100.0 + 0.3 * rng.standard_normal(4), np.zeros(4), np.zeros(4), 0.0, 0.0)
    det.update_thresholds()
    assert det.stillness.ripple_tol == pytest.approx(3 * 0.3, rel=0.15)
    fixed = EquilibriumDetector(DT, DetectorConfig.for_robot(robot, timeout=20.0,
                                                             options=WindowOptions(ripple_factor=0.0)))
    fixed.start(0.0)
    st = _feed(fixed, rng, 300)
    assert st.timed_out and fixed.stillness.ripple_tol == pytest.approx(robot.sensors.load_cell_uncertainty)


def _online_windows(det, t, tau, dl, dsig, roll, pitch):
    """Feed a record to the detector one sample at a time; its windows as offline sample spans: the runs of
    spans judged still that last a window's length (the span ending at sample i judges its middle sample)."""
    det.start(0.0)
    still = np.array([det.push(t[i], tau[i], dl[i], dsig[i], roll[i], pitch[i]).still for i in range(len(t))])
    shift = det.span - 1 - det.span // 2
    edges = np.diff(np.r_[0, still.astype(int), 0])
    return [(int(a) - shift, int(b) - 1 - shift) for a, b in
            zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True) if b - a >= det.needed]


@pytest.mark.parametrize("seed", [0, 1])
def test_online_and_offline_judge_a_record_identically(robot, seed):
    """A noisy run with sway fed one sample at a time to the online detector: with the offline search's
    Stillness its windows are the offline ones within two samples (the offline span is centred and repeats
    its first and last full span at the run's ends); learning the thresholds from what it has seen so far, it
    ends with exactly the offline thresholds and its windows differ only while its history is short (the
    first two rests, judged on under 30 s of samples)."""
    rng = np.random.default_rng(seed)
    sp = _setpoints(rng, 8)
    t, tau, ref, dl, dsig, roll, pitch = _run(rng, sp, sway=0.002)
    # the spans' judgement alone (the ends test, which both also apply, is test_the_detector_waits_for_...;
    # the offline cut where the reference moves is the detector's start after each move, tau_ref left out)
    ws = search_windows(robot, t, tau, dl, dsig, roll, pitch, None, sp,
                        options=WindowOptions(ends_p=0.0, settle_test_p=0.0))
    offline = [(w.first, w.last) for w in ws.found]
    assert len(offline) == 10 and not any(w.quasi for w in ws.found)
    given = Stillness(5, ws.thresholds, ws.ripple_tol)
    same = _online_windows(EquilibriumDetector(DT, DetectorConfig.for_robot(robot, stillness=given)),
                           t, tau, dl, dsig, roll, pitch)
    assert len(same) == 10
    assert max(max(abs(a - c), abs(b - d)) for (a, b), (c, d) in zip(same, offline, strict=True)) <= 2
    det = EquilibriumDetector(DT, DetectorConfig.for_robot(robot, timeout=1e9, history=1e4))
    learned = _online_windows(det, t, tau, dl, dsig, roll, pitch)
    det.update_thresholds()
    for c, thr in ws.thresholds.items():
        np.testing.assert_allclose(det.stillness.thresholds[c], thr, rtol=1e-12)
    assert det.stillness.ripple_tol == pytest.approx(ws.ripple_tol, rel=1e-12)
    assert len(learned) == 10
    gaps = [max(abs(a - c), abs(b - d)) for (a, b), (c, d) in zip(learned, offline, strict=True)]
    assert max(gaps[2:]) <= 2
    # the first two rests (under 30 s of history: the first seconds' noise, no drift estimate yet) within 2 s
    assert max(gaps[:2]) <= 20


def test_windows_cut_the_creep_towards_rest_the_ranges_let_in(robot):
    """A platform that creeps towards its rest after each move (e-folding 1 s, 4 mm of cable, 3 N of ripple,
    no swing: nothing the 0.5 s ranges and their floors of 2 mm, 0.1 deg, 0.3 deg see) over 5 s rests: the
    windows of the ranges alone start where the creep is still 0.8 mm on average over the window; the ends
    test cuts it to under 0.2 mm (measured on the known creep, mm of cable length; every setpoint keeps its
    window). What is left is below the test's power: 0.1 mm per sample of noise at the start of the rest."""
    worst = {}
    for p in (1e-3, 0.0):  # ends_p 0: the ranges alone
        shifts = []
        for seed in range(3):
            rng = np.random.default_rng(seed)
            sp = _setpoints(rng, 8)
            t, tau, ref, dl, dsig, roll, pitch = _run(rng, sp, rest=5.0, noise=0.5, decay=1.0, hz=0.0)
            opt = WindowOptions(ends_p=p, settle_test_p=p)  # both off: the ranges alone
            ws = search_windows(robot, t, tau, dl, dsig, roll, pitch, ref, sp, options=opt)
            assert [w.setpoint for w in ws.used] == list(range(8)) and not any(w.quasi for w in ws.used)
            creep = 4.0 * _swing(ref, 1.0, 0.0)
            shifts += [abs(float(creep[w.slice].mean())) for w in ws.used]
        worst[p] = max(shifts)
    assert worst[0.0] > 0.7 and worst[1e-3] < 0.2


def test_the_detector_waits_for_the_ends_test_the_search_applies(robot):
    """Online and offline one criterion: on a record whose platform still wobbles, the detector settles only
    where a window of its length would keep both ends under Stillness.trim."""
    rng = np.random.default_rng(4)
    sp = _setpoints(rng, 3)
    t, tau, ref, dl, dsig, roll, pitch = _run(rng, sp, noise=0.5, decay=2.5)
    ws = search_windows(robot, t, tau, dl, dsig, roll, pitch, ref, sp, options=WindowOptions(ends_p=1e-3))
    still = Stillness(5, ws.thresholds, ws.ripple_tol, ws.ends)
    det = EquilibriumDetector(DT, DetectorConfig.for_robot(robot, stillness=still))
    det.start(0.0)
    settled = [det.push(t[i], tau[i], dl[i], dsig[i], roll[i], pitch[i]).settled for i in range(t.size)]
    ch = {"length": dl, "swivel": dsig, "tilt": np.stack([roll, pitch], -1)}
    n = det.span - 1 + det.needed  # a window's worth of samples: the span, then a window's length of spans
    hits = [i for i in range(n, t.size) if settled[i]]
    assert hits
    for i in hits:
        block = slice(i - n + 1, i + 1)
        assert still.trim(tau[block], {c: x[block] for c, x in ch.items()}, n) == (0, 0)
    # and a detector without the ends test settles earlier after each move, on samples the test cuts
    bare = EquilibriumDetector(DT, DetectorConfig.for_robot(robot, stillness=Stillness(5, ws.thresholds,
                                                                                        ws.ripple_tol)))
    bare.start(0.0)
    early = [bare.push(t[i], tau[i], dl[i], dsig[i], roll[i], pitch[i]).settled for i in range(t.size)]
    assert sum(early) > sum(settled)


def test_on_the_real_sc_8_final_the_ends_test_cuts_only_motion_and_keeps_the_paper_pose(irma_data, tmp_path):
    """Issue 29 point 1 judged on the real robot (parsed sc_8_final): every end the test cuts off a still
    stretch is a motion, not noise (a cable length there stands more than 10 times the run's own per-sample
    length noise, ~0.01 mm, from the kept window's mean), the 8 setpoints keep a window each and the
    paper-weights solve moves by under 0.2 mm (0.13 mm measured)."""
    from acquisition.importers import import_irma
    from calib.selfcal import solve

    run = import_irma(irma_data / "sc_8_final_parsed.mat", tmp_path / "r",
                      targets=irma_data / "sc_control_target_8_final.mat")
    args = (run.robot, run.t, run.tau, run.dl, run.dsigma, run.roll, run.pitch, run.tau_ref, run.setpoints)
    off = search_windows(*args, options=WindowOptions(ends_p=0.0, settle_test_p=0.0))
    on = search_windows(*args, options=WindowOptions(ends_p=1e-3, settle_test_p=0.0))
    assert sorted(w.setpoint for w in on.used) == list(range(8)) == sorted(w.setpoint for w in off.used)
    noise = quiet_noise(run.dl)
    assert np.all(noise < 0.02e-3)
    cut = 0
    for w0 in off.found:
        w1 = next((w for w in on.found if w0.first <= w.first and w.last <= w0.last), None)
        if w1 is None or (w1.first == w0.first and w1.last == w0.last):
            continue
        kept = run.dl[w1.slice].mean(axis=0)
        for end in [i for i, moved in ((w0.first, w1.first > w0.first), (w0.last, w1.last < w0.last)) if moved]:
            cut += 1
            assert np.max(np.abs(run.dl[end] - kept) / noise) > 10.0, (w0, w1, end)
    assert cut >= 8
    pose = [solve(run.robot, run, noise="paper", window_options=o).initial_pose[:3]
            for o in (WindowOptions(ends_p=0.0, settle_test_p=0.0), WindowOptions(ends_p=1e-3, settle_test_p=0.0))]
    assert np.linalg.norm(pose[1] - pose[0]) < 0.2e-3


def test_of_the_still_stretches_at_one_setpoint_the_longest_is_its_window(robot):
    """After a move the platform swings and passes the ranges at a turning point for 1.5 s before it rests
    for 5 s at the same tensions, 6 mm of cable away: the rest is the setpoint's window, although the
    turning point's mean tension is the nearer to the setpoint (0.02 N against 0.4 N): of the still
    stretches at one setpoint the longest, not the nearest (issue 29: a startup's earliest flat spot was
    taken, seconds before its hold)."""
    rng = np.random.default_rng(3)
    tau0, sp = np.full(4, 100.0), np.array([130.0, 80.0, 120.0, 95.0])
    parts = [np.tile(tau0, (120, 1)), _quintic(tau0, sp, 40), np.tile(sp, (15, 1)), np.tile(sp, (15, 1)),
             np.tile(sp + 0.4, (50, 1)), _quintic(sp, tau0, 40), np.tile(tau0, (60, 1))]
    ref = np.vstack(parts)
    N = ref.shape[0]
    a = 120 + 40  # the turning point's first sample; its swing to the rest from a + 15 to a + 30
    offset = np.zeros(N)
    u = np.linspace(0.0, 1.0, 15)
    offset[a + 15 : a + 30] = 6e-3 * 0.5 * (1.0 - np.cos(math.pi * u))
    offset[a + 30 :] = 6e-3
    offset[a + 80 :] = 0.0  # back under tau0 (the move back starts at a + 80)
    t = np.arange(N) * DT
    tau = ref + 0.1 * rng.standard_normal(ref.shape)
    tau[a : a + 15] += sp - tau[a : a + 15].mean(axis=0)  # its mean exactly the setpoint
    dl = 2e-3 * (ref - tau0) + offset[:, None] + 2e-5 * rng.standard_normal((N, 4))
    dsig = 1e-3 * (ref - tau0) + 1e-4 * rng.standard_normal((N, 4))
    roll, pitch = 1e-4 * rng.standard_normal(N), 1e-4 * rng.standard_normal(N)
    ws = search_windows(robot, t, tau, dl, dsig, roll, pitch, ref, sp[None], options=WindowOptions(ends_p=0.0))
    starts = sorted(w.first for w in ws.found if w.first >= a - 5 and w.last <= a + 85)
    assert len(starts) == 2  # the turning point and the rest, both still by the ranges
    (used,) = ws.used
    assert used.setpoint == 0 and used.first > a + 15 and used.size >= 40


def test_the_detector_holds_until_the_platform_rests_for_settle_s(robot):
    """The hold-time rule of new startups: a platform that sits still for 2 s at a swing's turning point and
    then moves 5 mm is not at rest; the detector calls a rest only after settle_s (3 s) of still samples that
    the ends test finds resting end to end, and the same detector with a window's length (1 s) would have
    called the turning point a rest."""
    rng = np.random.default_rng(8)

    def feed(det):
        det.start(0.0)
        for k in range(300):
            x = 5e-3 * min(max((k - 20) / 10.0, 0.0), 1.0)  # still 2 s, a 5 mm move over 1 s, then still
            st = det.push(k * DT, 100.0 + 0.1 * rng.standard_normal(4), x + 2e-5 * rng.standard_normal(4),
                          1e-4 * rng.standard_normal(4), 1e-4 * rng.standard_normal(), 1e-4 * rng.standard_normal())
            if st.settled or st.timed_out:
                return k
        return None

    assert WindowOptions().settle_s == 3.0
    k = feed(EquilibriumDetector(DT, DetectorConfig.for_robot(robot, history=5.0)))
    assert k is not None and k >= 30 + 30  # 3 s after the move ended at sample 30
    early = feed(EquilibriumDetector(DT, DetectorConfig.for_robot(robot, history=5.0,
                                                                  options=WindowOptions(settle_s=1.0))))
    assert early is not None and early < 20


def _settle_block(rng, n=60, wobble=0.0, creep=0.0):
    """A still stretch of n samples at 10 Hz (tensions 1 N, lengths 0.2 mm, swivels 0.1 mrad, AHRS 0.35 mrad
    of white noise): the AHRS swings after the move by ``wobble`` rad (2.2 Hz, e-folding 1 s) and the
    lengths converge by 0.6 mm x wobble / 2 mrad (e-folding 0.3 s); ``creep`` m per sample of steady drift."""
    t = np.arange(n) * DT
    swing = wobble * np.exp(-t / 1.0) * np.sin(2 * math.pi * 2.2 * t + 0.5)
    tau = 100.0 + rng.standard_normal((n, 4))
    dl = 2e-4 * rng.standard_normal((n, 4)) + 0.3 * wobble * np.exp(-t / 0.3)[:, None] + creep * t[:, None] / DT
    dsig = 1e-4 * rng.standard_normal((n, 4))
    tilt = 3.5e-4 * rng.standard_normal((n, 2)) + swing[:, None]
    return tau, {"length": dl, "swivel": dsig, "tilt": tilt}


def test_the_settle_test_cuts_a_swinging_head_and_keeps_a_resting_or_creeping_window():
    """Issue 29 point 1: the AHRS swing and the approach the ranges let in at a window's head (2 mrad at 0.35
    mrad of noise, dying over 1-2 s) are cut until what is left matches the window's middle; a window at rest
    is kept whole in at least 97 % (at a false-alarm budget of 1e-3 per group and block), and so is
    one whose lengths creep steadily by 5 um per sample (the real winches in a hold: the line the middle half
    follows is the window's, not a move)."""
    floor = {"tension": np.full(4, 0.003), "length": np.full(4, 2e-3 / 12),
             "swivel": np.full(4, math.radians(0.1) / 12), "tilt": np.zeros(2)}
    strict, default = SettleTest(5, 1e-3, floor), SettleTest(5, WindowOptions().settle_test_p, floor)
    rng = np.random.default_rng(11)
    swinging = [_settle_block(rng, wobble=2e-3) for _ in range(20)]
    for test, least in ((strict, 3), (default, 6)):
        cuts = [test.trim(tau, ch, 10) for tau, ch in swinging]
        assert all(b == 0 for _, b in cuts)  # the tail is not tested by default
        heads = [a for a, _ in cuts]
        # the swing is 5 noise sigmas in its first 0.3 s and 1 sigma after 1.7 s: cut in 19 of 20 and the
        # median cut grows with the test's false-alarm budget (measured 4 and 9 samples)
        assert sum(a > 0 for a in heads) >= 19 and np.median(heads) >= least
    kept = [strict.trim(*_settle_block(rng), 10) == (0, 0) for _ in range(200)]
    assert sum(kept) >= 194  # measured 297 of 300: the budget is p per group and block (Bonferroni)
    creeping = [strict.trim(*_settle_block(rng, creep=5e-6), 10) == (0, 0) for _ in range(30)]
    assert sum(creeping) >= 28


def test_the_detector_waits_for_the_settle_test_the_search_applies(robot):
    """Online and offline one criterion, the settle test included: on a record whose platform still swings
    after each move, the detector settles only on blocks the settle test leaves whole, later than without it."""
    rng = np.random.default_rng(4)
    sp = _setpoints(rng, 3)
    t, tau, ref, dl, dsig, roll, pitch = _run(rng, sp, noise=0.5, decay=2.5)
    opt = WindowOptions()  # the default: the settle test on, as offline
    ws = search_windows(robot, t, tau, dl, dsig, roll, pitch, ref, sp, options=opt)
    ch = still_channels(dl, dsig, roll, pitch)
    still = Stillness(5, ws.thresholds, ws.ripple_tol, None, settle_test(tau, ch, 5, opt))

    def settles(stillness):
        det = EquilibriumDetector(DT, DetectorConfig.for_robot(robot, stillness=stillness))
        det.start(0.0)
        return det, [det.push(t[i], tau[i], dl[i], dsig[i], roll[i], pitch[i]).settled for i in range(t.size)]

    det, settled = settles(still)
    n = det.span - 1 + det.needed
    hits = [i for i in range(n, t.size) if settled[i]]
    assert hits
    for i in hits:
        block = slice(i - n + 1, i + 1)
        assert still.trim(tau[block], {c: x[block] for c, x in ch.items()}, n) == (0, 0)
    _, early = settles(Stillness(5, ws.thresholds, ws.ripple_tol))
    assert sum(early) > sum(settled)


def test_a_window_the_settle_test_judged_loses_its_margins_and_a_rest_from_the_start_keeps_its_head(robot):
    """Issue 29: the hold's first samples carry the controller's tension transient under the load cells' noise,
    and a window's last sample the next move's start, so every window the settle test judged starts
    settle_margin_s (0.5 s, 5 samples at 10 Hz) later and ends settle_tail_margin_s (0.1 s) earlier than the
    test alone would make it; a window that starts with the run (no move before it) keeps its first sample, and
    without the settle test no margin is cut."""
    rng = np.random.default_rng(5)
    sp = _setpoints(rng, 3)
    t, tau, ref, dl, dsig, roll, pitch = _run(rng, sp, noise=0.5)
    args = (robot, t, tau, dl, dsig, roll, pitch, ref, sp)

    def spans(**kw):
        return [(w.first, w.last) for w in search_windows(*args, options=WindowOptions(**kw)).used]

    bare, kept = spans(settle_margin_s=0.0, settle_tail_margin_s=0.0), spans()
    off, off_margin = spans(settle_test_p=0.0), spans(settle_test_p=0.0, settle_margin_s=1.0)
    assert len(bare) == len(kept) == 3 and off == off_margin
    assert [(c - a, b - d) for (a, b), (c, d) in zip(bare, kept, strict=True)] == [(5, 1)] * 3
    # a run that rests from its first sample: its window keeps that sample
    still = search_windows(robot, t[:100], tau[:100], dl[:100], dsig[:100], roll[:100], pitch[:100], ref[:100], None)
    assert still.found and still.found[0].first == 0
