"""The numbers that the startup routine (acquisition/) and the planner's time model (calib/design.py) share,
each in one place (SI units). calib/ may not import acquisition/, so they live here."""

from __future__ import annotations

QUINTIC_PEAK_RATE = 15.0 / 8.0  # peak of the rest-to-rest quintic's rate over its mean rate (at s = 1/2)
CONTROL_RATE = 200.0  # Hz, the routine's control rate (the operator's default; the loop accepts 200..500)
MAX_TENSION_RATE = 40.0  # N/s, the tension trajectories' rate limit
MIN_TRANSITION = 1.0  # s, the shortest transition between setpoints
HOLD_TIME = 2.0  # s logged in each equilibrium window
EXPECTED_SETTLE = 8.0  # s for the platform to come to rest at a setpoint (time estimates only)
