"""What the diagnosis and ``cdpr solve --effects`` fit on a run: its rows, their noise and the rigid solve
that starts every fit (:func:`run_rows`), the base model with the devices' priors and the reference window's
noise (:func:`base_fit`), and the effects added one at a time (:func:`effect_chain`): the same computation,
so the same numbers, in both."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.effects import Effect
from calib.effects.priors import DeviceAccuracy, ReferenceNoise
from calib.fitting import Fit, fit, refit
from calib.robot import Robot
from calib.selfcal.problem import Measurements


@dataclass
class RunRows:
    """What both the diagnosis and ``cdpr solve --effects`` fit on a run: the rows of a method's windows,
    their noise (``source`` names it), the rigid solve whose solution is the start of every fit."""

    robot: Robot
    meas: Measurements
    sigma: dict[str, np.ndarray]
    source: str
    solution: Any
    reference: Effect | None = None  # the reference window's noise (ReferenceNoise), in every fit


def run_rows(run: Any, noise: str = "estimate", method: str = "tlse", stride: int = 1,
             reference_sample: int | None = None) -> RunRows:
    """The rows, noise and start of a run: the windows, rows and initial guess are those of
    ``calib.selfcal.solve(method)``; noise ``estimate`` is that solve's (the noise of window means,
    calib.selfcal.noise, with its refinements and the reference window's noise), ``accuracy`` that noise
    floored at the sensors' accuracy class, ``paper`` (eq. 18) and ``sensors`` as in solve."""
    from calib.selfcal import measurement_rows, noise_levels, run_signals, sensor_noise, solve

    robot = run.robot
    # the rounds' 'first' sizing of a model-error level: the diagnosis reads its leftover chi2 as the model's
    # misfit (calib.selfcal.SolveOptions.estimate_rounds; at settled rounds chi2 is inside its band by design)
    sol = solve(robot, run, method=method, noise="estimate" if noise == "accuracy" else noise, stride=stride,
                reference_sample=reference_sample, estimate_rounds="first")
    sig = run_signals(robot, run)
    meas = measurement_rows(sig, sol.windows, method, stride, sol.reference_sample)[0]
    # the estimate-noise solve's own sigmas: the kinematic ones without the motion the rows' poses absorb
    solved = {c: np.asarray(v, float) for c, v in sol.noise.items()}
    if noise == "estimate":
        sigma, source = solved, "estimate"
    elif noise == "accuracy":  # the noise of a window mean floored at the sensors' accuracy
        acc = sensor_noise(robot)
        sigma = {c: np.maximum(v, acc[c]) for c, v in solved.items()}
        source = "accuracy"
    else:
        sigma, source = noise_levels(robot, noise, sig, sol.windows)
    reference = None
    if noise in ("estimate", "accuracy") and sol.reference_noise:  # the solve's: the same priors in every fit
        reference = ReferenceNoise(**sol.reference_noise)
    return RunRows(robot, meas, sigma, source, sol, reference)


def base_fit(rows: RunRows, included: Sequence[Effect] = ()) -> Fit:
    """The diagnosis's base model on a run's rows: the devices' constant errors within their datasheet
    accuracy, the reference window's noise (with the estimate-noise solve's priors) and the included
    effects, started from the rigid solve."""
    sol = rows.solution
    base = [DeviceAccuracy()] + ([rows.reference] if rows.reference is not None else [])
    return fit(rows.robot, rows.meas, rows.sigma, [*base, *included], sol.theta[:6], sol.poses)


def effect_chain(rows: RunRows, effects: Sequence[Effect]) -> list[Fit]:
    """The base fit, then the effects added one at a time, each fit started from the previous one: the
    fits the diagnosis's forward selection makes, and those of ``cdpr solve --effects`` (same noise, same
    priors, same start, so the same numbers)."""
    fits = [base_fit(rows)]
    for e in effects:
        fits.append(refit(fits[-1], e))
    return fits
