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

import numpy as np

from calib.robot import NoiseLevels, Robot
from calib.selfcal._solve import (
    APPROACH_LENGTH,
    APPROACH_SWIVEL,
    APPROACH_TENSION,
    METHODS,
    NOISE,
    Prepared,
    approach_directions,
    measurement_rows,
    noise_levels,
    paper_noise,
    prepare,
    run_signals,
    sensor_noise,
    solve_run,
)
from calib.selfcal.model import CHANNELS, ChannelPrediction, MeasurementModel, channel_width
from calib.selfcal.noise import ChannelNoise, WindowNoise, resolution_floor, window_mean_noise
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


def solve(
    robot: Robot,
    run: Any,
    method: str = "tlse",
    noise: str | NoiseLevels | dict = "paper",
    stride: int = 1,
    reference_sample: int | None = None,
    windows: list[Window] | None = None,
    window_options: WindowOptions | None = None,
    model: MeasurementModel | None = None,
    guess: tuple[np.ndarray, np.ndarray] | None = None,
    reference_pose: np.ndarray | None = None,
    max_iter: int = 200,
) -> Solution:
    """Estimate the initial pose and the relative sensors' offsets of a run.

    run: a Run (arrays t (N,), tau, dl, dsigma (N, n), roll, pitch, dyaw (N,); optional tau_ref,
        setpoints, ideal_poses) or a :class:`Measurements` of readings already relative to the reference
        (then ``guess`` = (theta0, poses0) is used if given, else the robot's home pose and pose estimation).
    method: 'tlse' | 'lse' | 'hybrid'. noise: 'paper' | 'sensors' | 'estimate' | NoiseLevels | per-channel
        dict of sigmas. stride: for lse/hybrid, every stride-th sample. reference_sample: the sample whose
        pose is zeta_0 (default: the middle of the first equilibrium window, else sample 0).
    windows: use these equilibrium windows instead of finding them. model: a measurement model (effects).
    guess: (theta0, poses0) instead of the initial guess of Section 3.3 (poses0 None: estimated from the
        readings given theta0). reference_pose: a known
        zeta_0 to compare with (Solution.reference: eps_p, eps_r of eq. 20, geodesic angle).

    Raises SelfCalInputError (bad run or arguments) or SelfCalFailure (no equilibrium, no convergence).
    """
    return solve_run(
        robot, run, method, noise, stride, reference_sample, windows, window_options, model, guess,
        reference_pose, max_iter,
    )
