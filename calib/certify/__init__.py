"""Certified interval calibration of a cable robot's fixed anchor points (Sandretto et al., issue 8).

Each cable's fixed point A_i (the anchor of a straight cable, the pulley entry point d_i of a robot with
swivel pulleys) is enclosed by a box guaranteed to contain it under bounded errors: laser-tracker poses
(+-pose_tol m, +-angle_tol rad), the cable model error [dL] (distance - length, m), the platform geometry
(+-platform_tol m) and, for pulley robots, the pulley's effect on length bounded over the measured poses. The
programme is the paper's FixP(QInter(q, hc4r(F_1..F_N))) on codac, followed by a paving; measurements whose
thick sphere misses the final box are named as outliers. ``q`` is the fraction of measurements that must
hold (the paper's meaning); codac 2 is given the number allowed to fail.

Public entry point: :func:`certify_anchors`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib.certify._bounds import Shells, cable_shells
from calib.certify._nwls import LOSSES, anchor_least_squares
from calib.certify._pulley import pulley_length_bound
from calib.certify._solver import solve_cable
from calib.robot import Robot

__all__ = ["LOSSES", "AnchorEnclosure", "CertifyConfig", "CertifyResult", "certify_anchors", "n_allowed_failures"]

AXIS_NAMES = ("x", "y", "z")


@dataclass(frozen=True)
class CertifyConfig:
    """Bounded errors and solver settings (SI units).

    q: fraction of the measurements that must hold, in (0, 1]. pose_tol (m) and angle_tol (rad): tracker
    tolerances per axis / Euler angle. model_error: [dL] = distance - length (m). anchor_tol: half-width
    of the initial box about the nominal anchors (m). platform_tol: tolerance of the platform points b_i (m).
    rotation_bound: 'centred' (mean-value form of R b) or 'naive' (interval product of the three rotations).
    resolution: the paving stops bisecting boxes narrower than this (m). max_boxes: paving budget per cable.
    fixpoint_ratio: the fixpoint stops when no dimension shrinks by more than this fraction (root box);
    paving_ratio: the same criterion inside the paving.
    uncontracted_ratio: a dimension whose final width exceeds this fraction of the initial one is reported
    as not contracted.
    nwls_loss: scipy robust loss of the least-squares comparison ('linear' is plain NWLS).
    """

    q: float = 0.75
    pose_tol: float = 0.001
    angle_tol: float = 0.01
    model_error: tuple[float, float] = (-0.0006, 0.0037)
    anchor_tol: float = 0.01
    platform_tol: float = 0.0
    rotation_bound: str = "centred"
    resolution: float = 5e-4
    max_boxes: int = 20000
    fixpoint_ratio: float = 0.01
    paving_ratio: float = 0.1
    uncontracted_ratio: float = 0.9
    nwls_loss: str = "linear"

    def validate(self) -> None:
        """Raise ValueError naming the field and value of the first bad setting."""
        if not 0.0 < self.q <= 1.0:
            raise ValueError(f"q = {self.q} must be a fraction in (0, 1].")
        for name in ("pose_tol", "angle_tol", "platform_tol"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} = {v} must be a non-negative number.")
        for name in ("anchor_tol", "resolution", "fixpoint_ratio", "paving_ratio"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} = {v} must be a positive number.")
        lo, hi = self.model_error
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise ValueError(f"model_error = {self.model_error} must be (lo, hi) with lo <= hi.")
        if self.rotation_bound not in ("centred", "naive"):
            raise ValueError(f"rotation_bound = {self.rotation_bound!r} must be 'centred' or 'naive'.")
        if self.nwls_loss not in LOSSES:
            raise ValueError(f"nwls_loss = {self.nwls_loss!r} must be one of {', '.join(LOSSES)}.")


@dataclass(frozen=True)
class AnchorEnclosure:
    """One cable's result. Boxes are (3, 2) arrays [[lo, hi], ...] in m, None when empty.

    cable: 1-based. box: the certified enclosure (hull of the paving). contracted: the paper's
    FixP(QInter) without paving. outliers: 0-based pose indices inconsistent with ``box``. uncontracted:
    axes whose width stayed above ``uncontracted_ratio`` of the initial width (identifiability warning).
    nwls: least-squares estimate (3,), m; nwls_inside: whether it lies in ``box``. boxes: paving boxes
    visited; exhausted: the paving budget ran out (box still guaranteed); seconds: wall time.
    """

    cable: int
    initial: np.ndarray
    box: np.ndarray | None
    contracted: np.ndarray | None
    outliers: tuple[int, ...]
    uncontracted: tuple[str, ...]
    nwls: np.ndarray
    nwls_inside: bool
    boxes: int
    exhausted: bool
    seconds: float

    @property
    def widths(self) -> np.ndarray | None:
        """Box widths (3,), m."""
        return None if self.box is None else self.box[:, 1] - self.box[:, 0]

    def contains(self, point: np.ndarray) -> bool:
        """Whether ``point`` (3,) lies in the box."""
        return self.box is not None and bool(np.all((self.box[:, 0] <= point) & (point <= self.box[:, 1])))


@dataclass(frozen=True)
class CertifyResult:
    """Enclosures of all cables. model_error is the [dL] used (pulley effect included), m;
    pulley_error the bounded pulley effect added to it (None for straight cables)."""

    robot: str
    q: float
    n_measurements: int
    required: int
    anchors: tuple[AnchorEnclosure, ...]
    model_error: tuple[float, float]
    pulley_error: tuple[float, float] | None
    rotation_bound: str
    seconds: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The `cdpr certify anchors --json` document (../shared/spec/cli.md), with extra keys."""

        def box(b: np.ndarray | None) -> list | None:
            return None if b is None else [[float(lo), float(hi)] for lo, hi in b]

        return {
            "anchors": [
                {
                    "cable": a.cable,
                    "box": box(a.box),
                    "outliers": list(a.outliers),
                    "widths": None if a.box is None else [float(w) for w in a.widths],
                    "contracted_box": box(a.contracted),
                    "uncontracted": list(a.uncontracted),
                    "nwls": [float(v) for v in a.nwls],
                    "nwls_inside": a.nwls_inside,
                    "paving_boxes": a.boxes,
                    "paving_exhausted": a.exhausted,
                }
                for a in self.anchors
            ],
            "q": self.q,
            "measurements": self.n_measurements,
            "required": self.required,
            "model_error": list(self.model_error),
            "pulley_error": None if self.pulley_error is None else list(self.pulley_error),
            "rotation_bound": self.rotation_bound,
            "timing": {"certify_s": self.seconds},
        }


def n_allowed_failures(q: float, n: int) -> int:
    """Measurements allowed to fail (codac 2's q-intersection integer) when a fraction q of n must hold."""
    required = math.ceil(q * n - 1e-9)
    return n - max(required, 1)


def certify_anchors(
    robot: Robot,
    poses: np.ndarray,
    lengths: np.ndarray,
    config: CertifyConfig = CertifyConfig(),
    cables: list[int] | None = None,
) -> CertifyResult:
    """Certified boxes of the fixed anchors of ``robot`` from measured poses (k, 6) (m, rad) and cable
    lengths (k, n) (m); ``cables`` (0-based) restricts the cables. Raises ValueError on bad input."""
    config.validate()
    poses = np.atleast_2d(np.asarray(poses, float))
    lengths = np.atleast_2d(np.asarray(lengths, float))
    if poses.shape[1] != 6 or lengths.shape != (poses.shape[0], robot.n):
        raise ValueError(
            f"measurements have shapes {poses.shape} and {lengths.shape}; "
            f"expected (k, 6) poses and (k, {robot.n}) lengths."
        )
    t_start = time.perf_counter()
    n = len(poses)
    n_fail = n_allowed_failures(config.q, n)
    model_error = tuple(config.model_error)
    pulley = None
    if robot.has_pulleys:  # over the measured poses, widened by the pose and anchor tolerances
        widen = np.r_[[config.pose_tol + config.anchor_tol] * 3, [config.angle_tol] * 3]
        bound = pulley_length_bound(robot, poses.min(axis=0) - widen, poses.max(axis=0) + widen)
        pulley = bound.interval
        model_error = (model_error[0] + pulley[0], model_error[1] + pulley[1])
    results = []
    for i in range(robot.n) if cables is None else cables:
        t0 = time.perf_counter()
        nominal = np.asarray(robot.d[i], float)
        initial = np.stack([nominal - config.anchor_tol, nominal + config.anchor_tol], 1)
        shells: Shells = cable_shells(
            robot, i, poses, lengths[:, i], initial[:, 0], initial[:, 1],
            pose_tol=config.pose_tol, angle_tol=config.angle_tol, platform_tol=config.platform_tol,
            model_error=model_error, rotation_bound=config.rotation_bound,
        )
        sol = solve_cable(shells, initial, n_fail, resolution=config.resolution, max_boxes=config.max_boxes,
                          ratio=config.fixpoint_ratio, paving_ratio=config.paving_ratio)
        nwls = anchor_least_squares(shells, nominal, config.nwls_loss)
        inside = sol.box is not None and bool(np.all((sol.box[:, 0] <= nwls) & (nwls <= sol.box[:, 1])))
        if sol.box is None:
            flat: tuple[str, ...] = ()
        else:
            ratio = (sol.box[:, 1] - sol.box[:, 0]) / (initial[:, 1] - initial[:, 0])
            flat = tuple(AXIS_NAMES[j] for j in range(3) if ratio[j] > config.uncontracted_ratio)
        results.append(AnchorEnclosure(i + 1, initial, sol.box, sol.contracted, sol.outliers, flat, nwls, inside,
                                       sol.boxes, sol.exhausted, time.perf_counter() - t0))
    return CertifyResult(robot.name, config.q, n, n - n_fail, tuple(results), model_error, pulley,
                         config.rotation_bound, time.perf_counter() - t_start)
