"""Initial-pose self-calibration (Zoffoli, Ida, Carricato, Robotica 2025): methods tlse, lse and hybrid.

One entry point, :func:`solve`, in the style of scipy.optimize::

    from calib.selfcal import solve
    sol = solve(robot, run, method="tlse", noise="paper")   # run: an acquisition.runlog.Run (or any object
    sol.initial_pose, sol.sensor_offsets, sol.chi2           # with t, tau, dl, dsigma, roll, pitch, dyaw)

Methods: ``tlse`` (tau-l-sigma-epsilon: the equilibrium windows, tensions included), ``lse`` (l-sigma-epsilon:
samples anywhere in the run at a stride, no tensions), ``hybrid`` (statics at the equilibria plus every
other sample kinematically). Noise (weights of eq. 17): ``paper`` (eq. 18, robot.noise), ``sensors`` (the
sensors' specifications), ``estimate`` (the scatter inside the equilibrium windows).

Structure. The unknowns are global parameters ``theta`` (zeta_0, the pose at the reference sample, first;
then any effect parameters) and one pose per measurement row; the Jacobian is block-arrow and
:mod:`calib.selfcal.lm` solves it by Levenberg-Marquardt with a Schur complement on the normal equations,
O(k) per iteration. The windows come from :func:`calib.selfcal.windows.search_windows` (matched to the
planned setpoints; ``Solution.window_search`` says which were planned, found and used).

Extension hook (physical effects, issue 7). Every channel's prediction is computed in one place,
:meth:`calib.selfcal.model.MeasurementModel.predict(poses, theta, channels)`, returning per channel the
predicted readings (k, c) with derivatives with respect to each pose (k, c, 6) and to theta (k, c, p).
An effect wraps a model: it subclasses or delegates to it, appends its parameter names to
``param_names`` (``n_params`` follows), appends their neutral values in ``initial_params(zeta0)``, and in
``predict`` calls the inner model with ``theta[:inner.n_params]``, then changes values and derivatives
(extra columns of d_theta for its own parameters). Pass it as ``solve(..., model=wrapped)``; covariance,
chi2 and residuals then include the effect's parameters (``Solution.theta``, ``param_names``,
``covariance``), and the caller fills ``Solution.effects``.
"""

from __future__ import annotations

from typing import Any

from calib.robot import Robot
from calib.selfcal.guess import Prepared, prepare
from calib.selfcal.model import CHANNELS, ChannelPrediction, MeasurementModel, channel_width
from calib.selfcal.noise import ChannelNoise, WindowNoise, resolution_floor, window_mean_noise
from calib.selfcal.options import METHODS, NOISE, SolveOptions, default_noise
from calib.selfcal.problem import Measurements, Problem
from calib.selfcal.result import (
    MISFIT_P,
    ReferenceComparison,
    SelfCalFailure,
    SelfCalInputError,
    Solution,
    TooFewWindows,
    compare_pose,
    sigma_scale,
)
from calib.selfcal.rows import (
    APPROACH_LENGTH,
    APPROACH_SWIVEL,
    APPROACH_TENSION,
    approach_directions,
    measurement_rows,
    noise_levels,
    paper_noise,
    run_signals,
    sensor_noise,
)
from calib.selfcal.windows import (
    MissingSetpoint,
    Stillness,
    Window,
    WindowOptions,
    WindowSearch,
    find_windows,
    search_windows,
)

__all__ = [
    "MISFIT_P",
    "sigma_scale",
    "ChannelNoise",
    "WindowNoise",
    "resolution_floor",
    "window_mean_noise",
    "solve",
    "SolveOptions",
    "default_noise",
    "Solution",
    "ReferenceComparison",
    "Measurements",
    "MeasurementModel",
    "ChannelPrediction",
    "Problem",
    "Window",
    "WindowOptions",
    "SelfCalInputError",
    "SelfCalFailure",
    "TooFewWindows",
    "METHODS",
    "NOISE",
    "CHANNELS",
    "channel_width",
    "find_windows",
    "search_windows",
    "prepare",
    "Prepared",
    "WindowSearch",
    "MissingSetpoint",
    "Stillness",
    "compare_pose",
    "noise_levels",
    "APPROACH_LENGTH",
    "APPROACH_SWIVEL",
    "APPROACH_TENSION",
    "approach_directions",
    "measurement_rows",
    "run_signals",
    "paper_noise",
    "sensor_noise",
]


def solve(robot: Robot, run: Any, options: SolveOptions | None = None, **changes: Any) -> Solution:
    """Estimate the initial pose and the relative sensors' offsets of a run.

    run: a Run (arrays t (N,), tau, dl, dsigma (N, n), roll, pitch, dyaw (N,); optional tau_ref,
        setpoints, ideal_poses) or a :class:`Measurements` of readings already relative to the reference
        (then ``options.guess`` = (theta0, poses0) is used if given, else the robot's home pose and pose
        estimation).
    options: a :class:`SolveOptions` (method, noise, stride, reference sample, windows, model, guess,
        reference pose, iterations); ``changes``: its fields by name, over ``options`` or the defaults
        (``solve(robot, run, method="tlse", noise="estimate")``).

    Raises SelfCalInputError (bad run or arguments) or SelfCalFailure (no equilibrium, no convergence).
    """
    from calib.selfcal import _solve

    return _solve.solve_run(robot, run, SolveOptions.of(options, **changes))
