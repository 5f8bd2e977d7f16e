"""Quintic tension trajectories: rest at both ends, peak rate equal to the configured maximum."""

import numpy as np
import pytest

from acquisition.trajectory import PEAK_RATE, TensionTrajectory, quintic_profile, segment_duration


def test_profile_values_and_derivatives_match_finite_differences():
    s = np.linspace(0.0, 1.0, 2001)
    p, dp, ddp = quintic_profile(s)
    assert p[0] == 0.0 and p[-1] == 1.0
    assert p[1000] == pytest.approx(0.5)
    assert dp[0] == dp[-1] == 0.0 and ddp[0] == ddp[-1] == 0.0
    h = s[1] - s[0]
    assert np.max(np.abs(np.gradient(p, h)[1:-1] - dp[1:-1])) < 1e-5
    assert np.max(np.abs(np.gradient(dp, h)[1:-1] - ddp[1:-1])) < 1e-4
    assert dp.max() == pytest.approx(PEAK_RATE, rel=1e-6)


def test_duration_keeps_every_cable_under_the_rate_limit():
    a = np.array([100.0, 100.0, 100.0, 100.0])
    b = np.array([118.48, 170.83, 115.57, 82.98])
    T = segment_duration(a, b, max_rate=20.0)
    assert T == pytest.approx(1.875 * 70.83 / 20.0)
    traj = TensionTrajectory.through(np.stack([a, b]), max_rate=20.0)
    t = np.linspace(-1.0, T + 1.0, 4001)
    tau, rate, acc = traj.evaluate(t)
    assert np.abs(rate).max() == pytest.approx(20.0, rel=1e-4)  # the largest change hits the limit
    np.testing.assert_allclose(tau[0], a)
    np.testing.assert_allclose(tau[-1], b)
    dt = t[1] - t[0]
    np.testing.assert_allclose(np.gradient(tau, dt, axis=0)[5:-5], rate[5:-5], atol=0.05)
    np.testing.assert_allclose(np.gradient(rate, dt, axis=0)[5:-5], acc[5:-5], atol=0.5)


def test_chain_of_segments_passes_every_waypoint_at_rest():
    w = np.array([[100.0, 100.0], [150.0, 80.0], [150.0, 80.0], [60.0, 120.0]])
    traj = TensionTrajectory.through(w, max_rate=25.0, min_duration=0.5)
    np.testing.assert_allclose(traj.durations, [1.875 * 50 / 25, 0.5, 1.875 * 90 / 25])
    tau, rate, _ = traj.evaluate(traj.starts)
    np.testing.assert_allclose(tau, w, atol=1e-12)
    np.testing.assert_allclose(rate, 0.0, atol=1e-12)
    # the scalar path agrees with the vectorised one everywhere
    for t in np.linspace(-0.3, traj.duration + 0.3, 97):
        np.testing.assert_allclose(traj.at(t), traj.evaluate(t)[0][0], atol=1e-12)


def test_zero_length_move_and_bad_rate():
    a = np.array([50.0, 60.0])
    assert segment_duration(a, a, 10.0) == 0.0
    traj = TensionTrajectory.through(np.stack([a, a]), max_rate=10.0)
    np.testing.assert_allclose(traj.at(0.2), a)
    with pytest.raises(ValueError, match="max_rate"):
        segment_duration(a, a + 1, 0.0)
    with pytest.raises(ValueError, match="durations"):
        TensionTrajectory(np.zeros((3, 2)), np.array([1.0]))
