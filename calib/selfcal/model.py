"""The measurement model: what each sensor channel should read at a pose, given the global parameters.

Channels (widths for n cables): ``tension`` (n, N, absolute), ``length`` (n, m) and ``swivel`` (n, rad),
both relative to the reference sample, ``orientation`` (3: roll and pitch absolute, yaw relative to the
reference sample, rad). The global parameter vector ``theta`` starts with the initial pose zeta_0
(x, y, z, roll, pitch, yaw) at the reference sample; models that add physical effects append their own
parameters after it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calib.kinematics import convert_euler, inverse_kinematics, kinematic_jacobians
from calib.robot import Robot
from calib.statics import tension_model

CHANNELS = ("tension", "length", "swivel", "orientation")


def encoder_lengths(robot: Robot, L: np.ndarray, tau: np.ndarray, dL: np.ndarray | None = None,
                    dtau: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """The cable lengths (k, n) m the winch encoders count: the unstretched length L / (1 + tau / EA) of a
    cable of the robot's axial stiffness EA (``robot.axial_stiffness``, N; none: inextensible, L itself)
    under the modelled tension tau (k, n) N; with dL, dtau (k, n, q) also its derivative (k, n, q)."""
    c = robot.compliance
    if not np.any(c):
        return L, dL
    den = 1.0 + c * tau
    if dL is None or dtau is None:
        return L / den, None
    return L / den, dL / den[..., None] - (L * c / den**2)[..., None] * dtau


def held_tensions(tau: np.ndarray, dtau: np.ndarray | None, held: np.ndarray | None
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """The cables' tensions (k, n) N and their pose derivatives (k, n, 6) where a row's tensions are held:
    ``held`` (k, n) N where finite, the modelled tau and dtau elsewhere (None: tau everywhere). A force-
    controlled hold keeps each cable at its tension while the platform sways about its equilibrium: the
    sway moves the pose at that tension, so a held tension does not follow the row's pose (derivative 0)."""
    if held is None:
        return tau, dtau
    h = np.isfinite(held)
    return np.where(h, held, tau), None if dtau is None else np.where(h[..., None], 0.0, dtau)


def statics_tensions(robot: Robot, poses: np.ndarray) -> np.ndarray:
    """The tensions (k, n) N the rigid statics give the cables of ``robot`` at poses (k, 6)."""
    return tension_model(robot, kin=inverse_kinematics(robot, np.asarray(poses, float)), derivatives=False).tau


def channel_width(name: str, n: int) -> int:
    """Number of scalar readings of a channel for n cables."""
    if name not in CHANNELS:
        raise ValueError(f"unknown channel {name!r} (known: {', '.join(CHANNELS)})")
    return 3 if name == "orientation" else n


@dataclass
class ChannelPrediction:
    """Predicted readings of one channel at k poses and their derivatives.

    value: (k, c); d_pose: (k, c, 6) with respect to each pose; d_theta: (k, c, p) with respect to the
    global parameters (zeta_0 first).
    """

    value: np.ndarray
    d_pose: np.ndarray
    d_theta: np.ndarray


def orientation_prediction(robot: Robot, poses: np.ndarray, theta: np.ndarray,
                           converted: tuple[np.ndarray, ...] | None = None) -> ChannelPrediction:
    """What the AHRS reads at poses (k, 6): its roll and pitch (absolute) and its yaw relative to the one at
    zeta_0 = theta[:6], all in the AHRS's own Euler convention (``robot.ahrs_convention``: a heading
    reference offset is then a pure yaw offset), with derivatives (k, 3, 6) and (k, 3, len(theta)).
    ``converted``: the poses' and zeta_0's angles in that convention with their Jacobians (``convert_euler``:
    (k, 3), (k, 3, 3), (1, 3), (1, 3, 3)) if already computed."""
    conv = robot.ahrs_convention
    z = np.asarray(poses, dtype=float)
    k, p = z.shape[0], theta.shape[0]
    if converted is None:
        both, dboth = convert_euler(np.vstack([z[:, 3:], theta[None, 3:6]]), robot.orientation, conv)  # one call
        converted = both[:k], dboth[:k], both[k:], dboth[k:]
    val, dang, ref, dref = converted
    val = val.copy()
    val[:, 2] = np.angle(np.exp(1j * (val[:, 2] - ref[0, 2])))
    dp = np.zeros((k, 3, 6))
    dp[:, :, 3:] = dang
    dth = np.zeros((k, 3, p))
    dth[:, 2, 3:6] = -dref[0, 2]
    return ChannelPrediction(val, dp, dth)


class MeasurementModel:
    """Rigid-body model of Zoffoli eq. 8-13: inverse kinematics, the tension model and the AHRS.

    ``predict(poses, theta, channels)`` is the one place where a channel's prediction is computed; physical
    effects (issue 7) wrap a model, append parameters to ``param_names`` and change values and derivatives.
    """

    def __init__(self, robot: Robot):
        self.robot = robot

    @property
    def param_names(self) -> tuple[str, ...]:
        """Names of the global parameters, zeta_0's six coordinates first."""
        return ("x0", "y0", "z0", "roll0", "pitch0", "yaw0")

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def initial_params(self, zeta0: np.ndarray) -> np.ndarray:
        """The starting global vector for a guess of zeta_0 (effects append their neutral values)."""
        return np.asarray(zeta0, dtype=float).copy()

    def priors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Theta indices, means and standard deviations of the parameters with a Gaussian prior: none here
        (effects with a prior, e.g. a device's accuracy class, add them)."""
        return np.zeros(0, dtype=int), np.zeros(0), np.zeros(0)

    def cable_tensions(self, theta: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """The tensions (k, n) N the statics give the cables at poses (k, 6) (theta: no robot effects here)."""
        return statics_tensions(self.robot, poses)

    def predict(
        self, poses: np.ndarray, theta: np.ndarray, channels: Sequence[str], times: np.ndarray | None = None,
        approach: np.ndarray | None = None, held_tension: np.ndarray | None = None,
    ) -> dict[str, ChannelPrediction]:
        """Predicted readings of ``channels`` at poses (k, 6) for global parameters theta (p,) (the rigid model
        depends neither on the rows' ``times`` nor on the directions of ``approach``, (k, n, 2)).
        ``held_tension`` (k, n) N: where finite, the tension a row's cable is held at in place of the statics'
        at its pose (:func:`held_tensions`), in its tension and in the stretch its encoder counts."""
        robot = self.robot
        z = np.asarray(poses, dtype=float)
        k, n, p = z.shape[0], robot.n, theta.shape[0]
        kin = inverse_kinematics(robot, z)
        jac = kinematic_jacobians(robot, kin)
        out: dict[str, ChannelPrediction] = {}
        kin0 = jac0 = None
        if "length" in channels or "swivel" in channels:
            kin0 = inverse_kinematics(robot, theta[None, :6])
            jac0 = kinematic_jacobians(robot, kin0)
        elastic = "length" in channels and bool(np.any(robot.compliance))
        tm = tension_model(robot, kin=kin, jac=jac) if "tension" in channels or elastic else None
        tau, dtau = held_tensions(tm.tau, tm.jacobian, held_tension) if tm is not None else (None, None)
        for name in channels:
            if name == "tension":
                out[name] = ChannelPrediction(tau, dtau, np.zeros((k, n, p)))
            elif name in ("length", "swivel"):
                cur = kin.lengths if name == "length" else kin.swivel
                ref = kin0.lengths if name == "length" else kin0.swivel
                dcur = jac.lengths if name == "length" else jac.swivel
                dref = jac0.lengths if name == "length" else jac0.swivel
                if name == "length" and elastic:  # the encoders count the unstretched lengths
                    tm0 = tension_model(robot, kin=kin0, jac=jac0)
                    cur, dcur = encoder_lengths(robot, cur, tau, dcur, dtau)
                    ref, dref = encoder_lengths(robot, ref, tm0.tau, dref, tm0.jacobian)
                val = cur - ref
                if name == "swivel":
                    val = np.angle(np.exp(1j * val))
                dth = np.zeros((k, n, p))
                dth[:, :, :6] = -dref
                out[name] = ChannelPrediction(val, dcur, dth)
            elif name == "orientation":
                out[name] = orientation_prediction(robot, z, theta)
            else:
                raise ValueError(f"unknown channel {name!r} (known: {', '.join(CHANNELS)})")
        return out

    def absolute_readings(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        """Absolute values of the relative sensors at the reference pose: lengths (n,), swivels (n,), yaw."""
        kin0 = inverse_kinematics(self.robot, theta[None, :6])
        yaw0 = convert_euler(theta[None, 3:6], self.robot.orientation, self.robot.ahrs_convention)[0][0, 2]
        lengths = kin0.lengths
        if np.any(self.robot.compliance):
            tau0 = tension_model(self.robot, kin=kin0, derivatives=False).tau
            lengths = encoder_lengths(self.robot, lengths, tau0)[0]
        return {"length": lengths[0], "swivel": kin0.swivel[0], "yaw": float(yaw0)}
