"""Results of a self-calibration solve and the comparison with a reference initial pose (eq. 20)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib.chi2 import chi2_sf
from calib.errors import CdprError
from calib.kinematics import rotation
from calib.selfcal.windows import Window, WindowSearch

MISFIT_P = 1e-3  # a chi2 whose upper-tail probability is below this rejects the model for the noise used


def sigma_scale(chi2: float, dof: int) -> float:
    """sqrt(chi2 / dof) when the chi2 test rejects the fit (upper tail below MISFIT_P), else 1: the factor
    (Birge ratio) that makes the misfit count as noise in the 1-sigma bounds."""
    if dof <= 0 or not math.isfinite(chi2) or chi2_sf(chi2, dof) >= MISFIT_P:
        return 1.0
    return math.sqrt(chi2 / dof)


class SelfCalInputError(CdprError, ValueError):
    """A run or argument that cannot be solved as given (the message names the field and value)."""


class SelfCalFailure(CdprError, RuntimeError):
    """A valid problem whose solve failed (no equilibrium found, no convergence)."""


class TooFewWindows(SelfCalFailure):
    """Fewer equilibrium windows than the method needs; ``found`` is how many the run holds."""

    def __init__(self, message: str, found: int):
        super().__init__(message)
        self.found = found


@dataclass(frozen=True)
class ReferenceComparison:
    """Errors against a reference initial pose: eps_p (m), eps_r (rad, eq. 20: difference of the axis-angle
    rotation angles), geodesic (rad, the angle of the relative rotation)."""

    eps_p: float
    eps_r: float
    geodesic: float


def rotation_angle(angles: np.ndarray, convention: str) -> float:
    """Axis-angle rotation angle (rad) of the orientation given by Euler angles (3,) (eq. 20)."""
    R = rotation(np.asarray(angles, float)[None], convention)[0]
    return math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def compare_pose(solution: np.ndarray, reference: np.ndarray, convention: str) -> ReferenceComparison:
    """eps_p, eps_r and the geodesic angle between two poses [x, y, z, roll, pitch, yaw]."""
    s, r = np.asarray(solution, float), np.asarray(reference, float)
    Rs = rotation(s[None, 3:], convention)[0]
    Rr = rotation(r[None, 3:], convention)[0]
    geo = math.acos(float(np.clip((np.trace(Rr.T @ Rs) - 1.0) / 2.0, -1.0, 1.0)))
    return ReferenceComparison(
        float(np.linalg.norm(s[:3] - r[:3])),
        abs(rotation_angle(r[3:], convention) - rotation_angle(s[3:], convention)),
        geo,
    )


@dataclass
class Solution:
    """Outcome of :func:`calib.selfcal.solve`. SI units (m, rad, N) throughout.

    initial_pose: zeta_0 (6,) at ``reference_sample``; initial_pose_sigma its 1-sigma bounds (6,).
    sensor_offsets: absolute value of each relative sensor when it read zero (absolute = offset + reading):
        ``length`` (n,), ``swivel`` (n,), ``yaw``.
    poses (k, 6) the measurement poses with ``poses_sigma`` (k, 6); ``samples`` (k,) the sample each row
    stands for (a window's middle); ``windows`` the equilibrium windows found (all of them, reference
    included); ``theta``/``param_names``/``covariance``: the global parameters and their covariance
    ((J^T W J)^-1, not rescaled by chi2/dof). ``residuals``: per channel ``rms`` (SI) and ``rms_normalized``.
    ``window_search``: the windows planned, found and used and the planned setpoints without one (None when
    the windows were given).
    ``initial_pose_sigma_scaled``: initial_pose_sigma times :func:`sigma_scale` (sqrt(chi2/dof) when the chi2
    test rejects the model): the misfit counted as noise. A model error is not noise, so on simulated runs
    with hidden effects even these bounds are still too narrow (docs/effects.md); they give its order.
    """

    method: str
    initial_pose: np.ndarray
    initial_pose_sigma: np.ndarray
    reference_sample: int
    sensor_offsets: dict[str, Any]
    poses: np.ndarray
    poses_sigma: np.ndarray
    samples: np.ndarray
    windows: list[Window]
    theta: np.ndarray
    param_names: tuple[str, ...]
    covariance: np.ndarray
    chi2: float
    dof: int
    residuals: dict[str, dict[str, float]]
    noise: dict[str, list[float]]
    noise_source: str
    iterations: int
    converged: bool
    message: str
    timing: dict[str, float]
    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    reference: ReferenceComparison | None = None
    window_search: WindowSearch | None = None
    # priors of the reference window's noise (m, rad, rad): one value, or one per cable where they differ
    reference_noise: dict[str, float | list[float]] | None = None

    @property
    def sigma_scale(self) -> float:
        """sqrt(chi2/dof) when the chi2 test rejects the model for its noise, else 1 (:func:`sigma_scale`)."""
        return sigma_scale(self.chi2, self.dof)

    @property
    def initial_pose_sigma_scaled(self) -> np.ndarray:
        """The initial pose's 1-sigma bounds (6,) times :attr:`sigma_scale`."""
        return self.initial_pose_sigma * self.sigma_scale

    def to_json(self) -> dict[str, Any]:
        """The `cdpr solve --json` object of spec/cli.md (plus a few extra keys)."""
        out: dict[str, Any] = {
            "method": self.method,
            "initial_pose": [float(v) for v in self.initial_pose],
            "reference_sample": int(self.reference_sample),
            "sensor_offsets": {
                "length": [float(v) for v in self.sensor_offsets["length"]],
                "swivel": [float(v) for v in self.sensor_offsets["swivel"]],
                "yaw": float(self.sensor_offsets["yaw"]),
            },
            "poses": int(self.poses.shape[0] + 1),
            "windows": [[w.first, w.last] for w in self.windows],
            "chi2": float(self.chi2),
            "dof": int(self.dof),
            "residuals": {c: {k: float(v) for k, v in d.items()} for c, d in self.residuals.items()},
            "effects": {e: {k: float(v) for k, v in p.items()} for e, p in self.effects.items()},
            "timing": {k: float(v) for k, v in self.timing.items()},
            "initial_pose_sigma": [float(v) for v in self.initial_pose_sigma],
            "sigma_scale": self.sigma_scale,
            "initial_pose_sigma_scaled": [float(v) for v in self.initial_pose_sigma_scaled],
            "noise": {"source": self.noise_source, **{c: [float(v) for v in s] for c, s in self.noise.items()}},
            "converged": bool(self.converged),
            "iterations": int(self.iterations),
        }
        ws = self.window_search
        if ws is not None:
            out["window_search"] = {
                "planned": ws.planned,
                "found": [{"first": w.first, "last": w.last, "setpoint": w.setpoint, "quasi": w.quasi,
                           "used": w in ws.used} for w in ws.found],
                "used": len(ws.used),
                "missing": [{"setpoint": m.setpoint, "reason": m.reason} for m in ws.missing],
                "thresholds": {c: [float(v) for v in x] for c, x in ws.thresholds.items()},
                "ripple_tol": float(ws.ripple_tol),
            }
        if self.reference_noise is not None:
            out["reference_noise"] = {k: v if isinstance(v, list) else float(v)  # a list: one per cable
                                      for k, v in self.reference_noise.items()}
        if self.reference is not None:
            out["reference"] = {
                "eps_p": self.reference.eps_p,
                "eps_r_deg": math.degrees(self.reference.eps_r),
                "geodesic_deg": math.degrees(self.reference.geodesic),
            }
        return out
