"""The plans of a startup, in one vocabulary for ``cdpr startup``, ``cdpr study`` and ``cdpr poses``: what to
plan (:class:`PlanRequest`, checked once), and what the routine visits (:class:`Plan`: setpoints, a kinematic
path, pauses, or a sequential design that chooses its setpoints as it goes).

Plan kinds (:data:`PLANS`): ``grid`` (``grid`` points per axis, :data:`GRID_POINTS`), ``optimal`` (the A-optimal
``poses`` poses of the static workspace, default 8) and ``sequential`` (stop at ``tolerance`` m, at most
``poses`` poses, default 27). A study names a plan in one word (:data:`STUDY_PLANS`: grid2, grid3, optimal,
sequential; :meth:`PlanRequest.named`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from calib.errors import CdprError
from calib.fields import quote

if TYPE_CHECKING:
    from calib.design import PoseNoise, TimeModel
    from calib.robot import Robot
    from calib.sequential import SequentialDesign

PLANS = ("grid", "optimal", "sequential")
STUDY_PLANS = ("grid2", "grid3", "optimal", "sequential")
GRID_POINTS = (2, 6)  # calibration grid points per axis that `cdpr startup` can acquire and solve
DEFAULT_POSES = {"optimal": 8, "sequential": 27}


class PlanRequestError(CdprError, ValueError):
    """A plan that cannot be asked for (an option out of range or without its companion); one sentence that
    names the option."""


LENGTH_UNITS = (("mm", 1e-3), ("cm", 1e-2), ("m", 1.0))


def parse_length(text: str, option: str) -> float:
    """A positive length with its unit (mm, cm or m), in metres; anything else is one sentence (PlanRequestError)."""
    t = text.strip().lower()
    unit = next(((u, f) for u, f in LENGTH_UNITS if t.endswith(u)), None)
    try:
        value = float(t[: -len(unit[0])]) * unit[1] if unit else float(t)
    except ValueError:
        raise PlanRequestError(f"{option} {quote(text)} is not a length: give a number and its unit, e.g. 3mm, "
                               "0.5cm or 0.003m.") from None
    if unit is None:
        raise PlanRequestError(f"{option} {quote(text)} needs its unit: {t}mm, {t}cm or {t}m.")
    if not (value > 0 and math.isfinite(value)):
        raise PlanRequestError(f"{option} {quote(text)} must be a positive length.")
    return value


def check_grid(grid: int) -> None:
    """Refuse a --grid outside GRID_POINTS: the same range for planning (poses) and acquiring (startup)."""
    lo, hi = GRID_POINTS
    if not lo <= grid <= hi:
        raise PlanRequestError(f"--grid {grid} is out of range: give {lo} to {hi} grid points per axis.")


def check_step(step: float) -> None:
    """Refuse a non-positive spacing of the candidate positions (m)."""
    if not step > 0:
        raise PlanRequestError(f"--step must be positive, got {step}.")


@dataclass(frozen=True)
class PlanRequest:
    """What to plan: ``kind`` one of :data:`PLANS`, ``grid`` points per axis, ``poses`` (optimal: how many;
    sequential: at most; None: :data:`DEFAULT_POSES`), ``tolerance`` m (sequential), ``step`` m (candidate
    spacing). Build it with :meth:`of`, which checks it."""

    kind: str = "grid"
    grid: int = 2
    poses: int | None = None
    tolerance: float | None = None
    step: float = 0.1

    @classmethod
    def of(cls, plan: str | None = None, grid: int = 2, poses: int | None = None, tolerance: float | None = None,
           step: float = 0.1) -> PlanRequest:
        """The request of ``cdpr startup --plan --grid --poses --tolerance --step``: ``plan`` None is grid, or
        sequential when a tolerance is given. Raises PlanRequestError."""
        check_grid(grid)
        kind = plan or ("sequential" if tolerance is not None else "grid")
        if kind not in PLANS:
            raise PlanRequestError(f"--plan {kind!r} is not one of {', '.join(PLANS)}.")
        if tolerance is not None and kind != "sequential":
            raise PlanRequestError(f"--tolerance applies to the sequential plan, not to --plan {kind}.")
        if kind == "sequential" and tolerance is None:
            raise PlanRequestError("--plan sequential needs --tolerance (e.g. --tolerance 3mm).")
        check_step(step)
        if poses is not None and not 1 <= poses <= 100:
            raise PlanRequestError(f"--poses {poses} is out of range: give 1 to 100 poses.")
        return cls(kind, grid, poses, tolerance, step)

    @classmethod
    def named(cls, name: str, tolerance: float | None = None, step: float = 0.1) -> PlanRequest:
        """A study's plan by its name (:data:`STUDY_PLANS`; 'gridN': N points per axis). Raises
        PlanRequestError."""
        if name not in STUDY_PLANS:
            raise PlanRequestError(f"--plan {name!r} is not one of {', '.join(STUDY_PLANS)}.")
        if name == "sequential" and tolerance is None:
            raise PlanRequestError("--plan sequential needs --tolerance (the 1-sigma to stop at, e.g. 3mm).")
        if name.startswith("grid"):
            return cls.of("grid", int(name[4:]), step=step)
        return cls.of(name, tolerance=tolerance, step=step)

    @property
    def pose_count(self) -> int:
        """The optimal plan's poses, or the most a sequential plan visits."""
        return self.poses or DEFAULT_POSES.get(self.kind, 8)


def make_plan(robot: Robot, request: PlanRequest, method: str = "equilibrium", speed: float = 0.05,
              spacing: float = 0.05, time_model: TimeModel | None = None) -> Plan:
    """The plan `cdpr startup` runs for ``request``. The window-mean noise the optimal and sequential plans are
    chosen with is the startup loop's at each pose (:data:`calib.design.LOOP_POSE_NOISE`); a sequential startup
    then weighs its choices and its stop rule with its own (its own solve of the samples so far). Raises
    PlanRequestError (a plan the robot cannot make, e.g. a tolerance out of reach, included)."""
    from calib.design import LOOP_POSE_NOISE
    from calib.planning import PlanningError

    try:
        return Plan.for_robot(robot, request.grid, method, speed, spacing, plan=request.kind,
                              poses=request.pose_count, tolerance=request.tolerance, noise=LOOP_POSE_NOISE,
                              step=request.step, time_model=time_model)
    except PlanningError as exc:
        raise PlanRequestError(str(exc)) from exc


def parse_pause(text: str, k: int) -> Pause:
    """``J:S`` or ``J:S:home`` -> a Pause after setpoint J (0..k-1) of S > 0 seconds (at most 600).
    Raises PlanRequestError."""
    parts = text.split(":")
    try:
        if len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] != "home"):
            raise ValueError
        pause = Pause(int(parts[0]), float(parts[1]), len(parts) == 3)
    except ValueError:
        raise PlanRequestError(f"--pause {text!r} is not J:S or J:S:home (setpoint index, seconds).") from None
    if not 0 <= pause.after < k or not 0 < pause.seconds <= 600:
        raise PlanRequestError(f"--pause {text!r}: the setpoint must be 0..{k - 1} and the seconds within "
                               f"(0, 600].")
    return pause


@dataclass(frozen=True)
class Pause:
    """A pause of the sequence after setpoint ``after``'s window: ``seconds`` at rest, at that setpoint or
    (``home``) back under tau0; logged as phase ``pause`` with setpoint -1 (not a planned equilibrium)."""

    after: int
    seconds: float
    home: bool = False


@dataclass
class Sequential:
    """Sequential acquisition (issue 19): the next pose is the candidate of ``design`` with the most expected
    information per second from where the platform is; after each window the solve is updated and the
    routine returns as soon as the position 1-sigma (sqrt trace, m) is below ``tolerance``, or after
    ``max_poses`` poses (the plan is exhausted). ``noise``: sigma of a window mean per channel."""

    design: SequentialDesign
    tolerance: float
    noise: dict[str, np.ndarray]
    max_poses: int = 27


@dataclass
class Plan:
    """What the routine will visit: setpoints (k, n) N (tau0 first), ideal poses (k, 6), kinematic path,
    pauses; a sequential plan starts empty and its setpoints are appended as they are chosen."""

    setpoints: np.ndarray
    ideal_poses: np.ndarray
    tau0: np.ndarray
    path_tensions: np.ndarray | None = None  # (m, n) N, kinematic method
    path_times: np.ndarray | None = None  # (m,) s
    pauses: tuple[Pause, ...] = ()
    sequential: Sequential | None = None

    @classmethod
    def for_robot(cls, robot: Robot, grid: int, method: str, speed: float = 0.05, spacing: float = 0.05,
                  plan: str = "grid", poses: int = 8, tolerance: float | None = None,
                  noise: dict[str, np.ndarray] | PoseNoise | None = None, step: float = 0.1,
                  time_model: TimeModel | None = None) -> Plan:
        """The grid plan, the A-optimal plan of ``poses`` poses (``plan='optimal'``) or a sequential plan
        that stops at ``tolerance`` m (``plan='sequential'``, at most ``poses`` poses); candidates every
        ``step`` m of the static workspace, ``noise`` the window-mean sigma, per channel or per pose (default
        the loop's per pose, :data:`calib.design.LOOP_POSE_NOISE`), ``time_model`` the robot time the
        sequential choice weighs
        (default :class:`calib.design.TimeModel`). Raises ``calib.planning.PlanningError``."""
        from calib.design import (
            LOOP_POSE_NOISE,
            PoseNoise,
            TimeModel,
            candidates,
            loop_noise,
            optimal_plan,
            select_a_optimal,
        )
        from calib.planning import PlanningError, kinematic_path, plan_poses
        from calib.sequential import SequentialDesign

        if plan not in PLANS:
            raise PlanningError(f"plan must be one of {', '.join(PLANS)}, got {plan!r}.")
        if method == "kinematic":
            if plan != "grid":
                raise PlanningError(f"plan '{plan}' applies to the equilibrium method only.")
            path = kinematic_path(robot, grid, speed=speed, spacing=spacing)
            return cls(np.empty((0, robot.n)), np.empty((0, 6)), plan_poses(robot, grid).tau0, path.tensions,
                       path.times)
        if plan == "grid":
            g = plan_poses(robot, grid)
            return cls(g.setpoints, g.poses, g.tau0)
        noise = noise or LOOP_POSE_NOISE
        cands = candidates(robot, noise, step)
        if plan == "optimal":
            o = optimal_plan(robot, poses, noise, cands=cands)
            return cls(o.setpoints, o.poses, o.tau0)
        if tolerance is None or not tolerance > 0:
            raise PlanningError(f"a sequential plan needs a positive tolerance, got {tolerance!r} m.")
        k = min(poses, cands.size)
        reach = select_a_optimal(cands, k, max_rounds=0)[1]  # greedy: what the sequential choice can attain
        if reach > tolerance:
            raise PlanningError(f"the tolerance {1000 * tolerance:g} mm cannot be reached: {k} poses of the static "
                                f"workspace predict at best a 1-sigma of the initial position of "
                                f"{1000 * reach:.3f} mm.")
        pose_noise = noise if isinstance(noise, PoseNoise) else None
        flat = loop_noise(robot) if pose_noise is not None else noise  # the online solve weighs its rows per channel
        seq = Sequential(SequentialDesign(cands, time_model or TimeModel(), pose_noise=pose_noise), float(tolerance),
                         flat, poses)
        return cls(np.empty((0, robot.n)), np.empty((0, 6)), cands.tau0, sequential=seq)
