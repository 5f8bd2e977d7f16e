"""The options of a solve, in one frozen dataclass (:class:`SolveOptions`), and what each defaults to."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.robot import NoiseLevels
from calib.selfcal.model import MeasurementModel
from calib.selfcal.result import SelfCalInputError
from calib.selfcal.windows import Window, WindowOptions

METHODS = ("tlse", "lse", "hybrid")
NOISE = ("paper", "estimate", "sensors")
# where an estimate solve (noise "estimate", method tlse) starts: see SolveOptions
ESTIMATE_STARTS = ("within", "likelier")
ESTIMATE_ROUNDS = ("settle", "first")


def default_noise(method: str) -> str:
    """The weights a solve takes unless told: the run's own noise of a window mean ('estimate', whose 1-sigma
    covers the truth as often as it says) for the window methods, the paper's (eq. 18) for lse's samples."""
    return "paper" if method == "lse" else "estimate"


@dataclass(frozen=True)
class SolveOptions:
    """How :func:`calib.selfcal.solve` solves a run.

    method: 'tlse' | 'lse' | 'hybrid'. noise: 'paper' | 'sensors' | 'estimate' | NoiseLevels | per-channel
        dict of sigmas. stride: for lse/hybrid, every stride-th sample. reference_sample: the sample whose
        pose is zeta_0 (default: the middle of the first equilibrium window, else sample 0).
    windows: use these equilibrium windows instead of finding them (``window_options``: how to find them).
    model: a measurement model (effects). guess: (theta0, poses0) instead of the initial guess of Section 3.3
        (poses0 None: estimated from the readings given theta0). reference_pose: a known zeta_0 (6,) to
        compare with (Solution.reference: eps_p, eps_r of eq. 20, geodesic angle). max_iter: LM iterations
        (0: the guess is taken as the solution).
    estimate_start: an estimate solve's start. 'within' (default): the within-window first pass, again from
        the paper's weights when it ends unusable; 'likelier': both, the end whose weights make the rows more
        likely (restricted likelihood), at twice the cost (docs/windows.md: what each does on the real runs).
    estimate_rounds: how an estimate solve's variance-component rounds treat a group raised to model error.
        'settle' (default): it follows its rows' scatter around each new fit, up and down, to Helmert's fixed
        point (chi2 ends inside its band); 'first': it keeps the size its first round gave it, at a poorly
        fitted pose (the rounds before issue 29 r, whose leftover chi2 the diagnosis's tests read as the
        model's misfit: calib.runrows keeps it until that test is made against the window-scatter noise).
    sway: an estimate solve's statics rows also carry the platform's sway under force control (the offset of a
        window-mean pose from the equilibrium of its held tensions, sized from the run's per-sample poses:
        calib.selfcal.sway; ``cdpr solve --noise estimate+sway``). Off by default (docs/windows.md, "Sway in
        the statics rows": what it does to the prediction of held-out real windows). Needs noise 'estimate'.
    """

    method: str = "tlse"
    noise: str | NoiseLevels | dict = "paper"
    stride: int = 1
    reference_sample: int | None = None
    windows: list[Window] | None = None
    window_options: WindowOptions | None = None
    model: MeasurementModel | None = None
    guess: tuple[np.ndarray, np.ndarray] | None = None
    reference_pose: np.ndarray | None = None
    max_iter: int = 200
    estimate_start: str = "within"
    estimate_rounds: str = "settle"
    sway: bool = False

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise SelfCalInputError(f"method '{self.method}' is not one of {', '.join(METHODS)}.")
        if int(self.stride) < 1:
            raise SelfCalInputError(f"stride {self.stride} must be a positive integer.")
        if self.estimate_rounds not in ESTIMATE_ROUNDS:
            raise SelfCalInputError(
                f"estimate_rounds '{self.estimate_rounds}' is not one of {', '.join(ESTIMATE_ROUNDS)}.")
        if self.estimate_start not in ESTIMATE_STARTS:
            raise SelfCalInputError(
                f"estimate_start '{self.estimate_start}' is not one of {', '.join(ESTIMATE_STARTS)}.")
        if self.sway and not (isinstance(self.noise, str) and self.noise == "estimate"):
            raise SelfCalInputError(f"sway is a term of the estimate noise; noise {self.noise!r} has none "
                                    "(use noise 'estimate').")

    @classmethod
    def of(cls, options: SolveOptions | None = None, **changes: Any) -> SolveOptions:
        """``options`` (default: the defaults) with the named fields changed."""
        if options is None:
            return cls(**changes)
        return dataclasses.replace(options, **changes) if changes else options
