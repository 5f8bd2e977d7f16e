"""Sway under force control: the window-mean pose is not the equilibrium pose of the window-mean tensions.

The force control holds the tensions at their setpoint while the platform swings slowly about the equilibrium
those tensions make (a draught, a cable's twist: a correlation time comparable to a window). A window's mean
readings of lengths, swivel angles and AHRS follow the platform's mean pose; its mean tensions are those of the
equilibrium. One pose per row carries both, so the statics rows (the tension channel) see the offset delta of
the mean pose from the equilibrium through the tension model's pose Jacobian D (N per pose unit): an extra
error D delta of a window's tension row, common to its cables.

Sized from the run itself (:func:`sway_offset`): the per-sample poses of the still windows (each fitted to its
sample's kinematic readings at the window's held tensions, :func:`calib.selfcal.noise.pose_free_noise`) wander
about their window mean; per pose coordinate an AR(1) model of that wander (its variance and lag-1 correlation
against their exact expectations once the window mean is removed, ``noise._pooled``) gives the variance of the
mean of a window of the windows' harmonic mean size, and the wander's correlation across the coordinates (a
sideways swing tilts the platform too) makes it a covariance Sigma (6, 6). :func:`tension_sigma` adds
diag(D Sigma D^T), averaged over the windows' poses, to the tension rows' variance. A platform that does not
sway gives a wander of the sensors' white noise only, whose mean over a window is a few hundredths of a
millimetre. :func:`with_sway` puts it into a pose-free noise estimate (calib.selfcal._solve, when asked:
``SolveOptions.sway``, ``cdpr solve --noise estimate+sway``; docs/windows.md, "Sway in the statics rows").
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from calib.robot import Robot
from calib.selfcal.noise import PoseFreeNoise, WindowNoise, _pooled, ar1_factor
from calib.statics import tension_model


@dataclass(frozen=True)
class SwayOffset:
    """The window-mean pose's offset from equilibrium: ``cov`` (6, 6) in pose units (m, rad; a window mean of
    ``window_size`` samples, the windows' harmonic mean), ``sd`` (6,) its standard deviations and ``rho`` (6,)
    the lag-1 correlation of the wander per coordinate."""

    cov: np.ndarray
    sd: np.ndarray
    rho: np.ndarray
    window_size: float


def sway_offset(poses: np.ndarray, owner: np.ndarray) -> SwayOffset:
    """The offset of a window-mean pose from equilibrium, from per-sample poses (N, 6) m, rad of still windows
    (``owner`` (N,) the window of each sample): see the module doc."""
    poses = np.asarray(poses, float)
    blocks = [poses[owner == j] for j in np.unique(owner)]
    var, rho = np.zeros(6), np.zeros(6)
    nh = 1.0
    for c in range(6):
        gamma0, rho[c], nh = _pooled([b[:, c : c + 1] for b in blocks], 0)
        var[c] = gamma0 * ar1_factor(rho[c], nh) / nh
    dev = [b - b.mean(axis=0) for b in blocks if b.shape[0] > 1]
    dev = np.concatenate(dev) if dev else np.zeros((0, 6))
    corr = np.eye(6)
    ok = dev.std(axis=0) > 0 if dev.shape[0] > 6 else np.zeros(6, bool)
    if ok.sum() > 1:
        corr[np.ix_(ok, ok)] = np.corrcoef(dev[:, ok], rowvar=False)
    sd = np.sqrt(var)
    return SwayOffset(corr * np.outer(sd, sd), sd, rho, nh)


def sway_tension_variance(robot: Robot, window_poses: np.ndarray, offset: SwayOffset) -> np.ndarray:
    """Per cable, the variance (n,) N^2 the sway adds to a window's tension row: diag(D Sigma D^T) averaged over
    the windows' poses (k, 6), D the rigid tension model's pose Jacobian (k, n, 6) there."""
    D = tension_model(robot, np.atleast_2d(np.asarray(window_poses, float))).jacobian
    return np.clip(np.einsum("kni,ij,knj->kn", D, offset.cov, D).mean(axis=0), 0.0, None)


def tension_sigma(robot: Robot, sigma: np.ndarray, window_poses: np.ndarray, offset: SwayOffset) -> np.ndarray:
    """The tension rows' sigma (n,) N with the sway added: sqrt(sigma^2 + :func:`sway_tension_variance`)."""
    return np.sqrt(np.asarray(sigma, float) ** 2 + sway_tension_variance(robot, window_poses, offset))


def with_sway(robot: Robot, pose_free: PoseFreeNoise, window_poses: np.ndarray) -> tuple[PoseFreeNoise, SwayOffset]:
    """``pose_free`` (calib.selfcal.noise.pose_free_noise) with its tension rows' sigma carrying the sway, sized
    from its per-sample poses; ``window_poses`` (k, 6): the poses of the windows it was estimated at."""
    offset = sway_offset(pose_free.poses, pose_free.owner)
    noise = pose_free.noise
    sigma = dict(noise.sigma) | {"tension": tension_sigma(robot, noise.sigma["tension"], window_poses, offset)}
    return dataclasses.replace(pose_free, noise=WindowNoise(sigma, noise.window_size, noise.groups)), offset
