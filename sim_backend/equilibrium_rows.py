"""Equilibrium measurements of the simulated prototype, with its hidden effects, without running the loop.

The startup routine drives the platform by force control to each planned setpoint and averages the sensors
in the equilibrium windows. At such an equilibrium the load cells read the setpoint, so the true tensions
are ``(setpoint - offset) / (1 + gain)``; the platform of the TRUE robot (``SimConfig.true_robot``: pulley
radii and positions, centre of mass, mass) rests where those tensions balance it (direct statics); the
motor encoders count the unstretched length ``l0 = L / (1 + tau / EA)`` through the nominal transmission
(the true one is ``(1 + k_i)`` times larger, so the reading is ``delta l0 / (1 + k_i)``); the swivel
encoders see the true geometry; the AHRS reads the angles of ``R(zeta) Rx(roll_m) Ry(pitch_m)``. This is
the physics of ``sim_backend`` (same SimConfig, same formulas) at its static equilibria plus white noise of
the size of a window average, plus (``device_biases``, on by default) the constant per-device errors the
emulators draw at power-on: each load-cell channel off by up to its accuracy class (0.02 % of 100 kg),
the AHRS roll and pitch off by up to 0.1 deg. Those are part of every run of the simulated prototype, as of
the real one, with or without a hidden effect; they are what limits the rigid model on an effect-free run.
The reference (zeta_0) is the home pose under the home tensions, the rows are the planned poses. With a
``sway`` in the configuration each equilibrium is displaced by an independent horizontal push at the centre
of mass (the window mean of the simulator's sway force): the tensions stay at their setpoints (force
control), every kinematic reading follows the displaced pose, and the statics no longer hold exactly.

Issue-17 effects: with ``pulley_friction`` the cell (in the transmission, winch side) reads the platform
tension tau as tau (1 - a mu) - a f, a = +1 when the cable was last paid out into the window, -1 when
reeled in (from the plan's sequence of poses: home, then the planned poses in order; 0 at home, which
the pretension reaches from slack); with ``loadcell_hysteresis`` the cells read tau - s h, s the sign of the
setpoint change into the window (+1 at home: loaded from zero); with ``cable_sag`` the chord tensions
hold the platform and half of every cable's weight at its anchor, the cells read the chord tension plus
rho g dz / 2 and the encoders count the sagging path (the model of ``sim_backend.physics`` and of the
``cable_sag`` effect). The rows carry the directions (``Measurements.approach``/``load_approach``), as
``calib.selfcal.measurement_rows`` computes them from a run's signals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.equilibrium import direct_statics
from calib.kinematics import inverse_kinematics, rotation, rotation_to_euler
from calib.planning import PosePlan, plan_poses
from calib.robot import Robot
from calib.selfcal.problem import Measurements
from calib.statics import equilibrium_residual
from sim_backend.xsens_emulator import XsensNoise

# standard deviation of one equilibrium-window average: N, m, rad, rad (roll, pitch, yaw)
WINDOW_NOISE = {
    "tension": 0.1,
    "length": 5e-5,
    "swivel": 1e-4,
    "orientation": np.array([5e-4, 5e-4, 2e-3]),
}


def sag_cell(robot: Robot, kin) -> np.ndarray:
    """(k, n) what a cell at the pulley reads above the chord tension per kg/m of cable: g dz / 2, N."""
    return -0.5 * float(robot.gravity) * kin.rho[..., 2]


def sag_length(robot: Robot, kin, tau: np.ndarray, density: float) -> np.ndarray:
    """(k, n) the sagging path's extra length over the chord, (rho g)^2 lc h^2 / (24 tau^2), m."""
    if density == 0.0:
        return np.zeros_like(kin.rho_norm)
    h2 = kin.rho[..., 0] ** 2 + kin.rho[..., 1] ** 2
    return (density * float(robot.gravity)) ** 2 * kin.rho_norm * h2 / (24.0 * np.maximum(tau, 1.0) ** 2)


def direct_statics_with_cables(robot: Robot, tau: np.ndarray, guess: np.ndarray, density: float, kin):
    """Direct statics under chord tensions tau (k, n) with half of every cable's weight (density kg/m,
    chord lengths of ``kin``) hanging at its anchor: weights at body points add up to one weight at their
    common centre of mass, so each pose is solved with the robot's mass and centre of mass so augmented."""
    if density == 0.0:
        return direct_statics(robot, tau, guess)
    m_i = 0.5 * density * kin.rho_norm  # (k, n) kg at each anchor
    poses, ok = np.empty_like(guess), np.empty(guess.shape[0], bool)
    for j in range(guess.shape[0]):
        mass = robot.mass + m_i[j].sum()
        com = (robot.mass * robot.com + m_i[j] @ robot.a_local) / mass
        ds = direct_statics(robot.replace(mass=mass, com=com), tau[j : j + 1], guess[j : j + 1])
        poses[j], ok[j] = ds.poses[0], ds.converged[0]
    return _Statics(poses, ok)


@dataclass
class _Statics:
    poses: np.ndarray
    converged: np.ndarray


@dataclass
class SimulatedRows:
    """Readings at the planned equilibria (``meas``), the noise used (``sigma``, per channel), the true
    initial pose and row poses, and the Section 3.3 guess (ideal poses)."""

    meas: Measurements
    sigma: dict[str, np.ndarray]
    zeta0: np.ndarray
    poses: np.ndarray
    guess_zeta0: np.ndarray
    guess_poses: np.ndarray


def force_displacement(robot: Robot, poses: np.ndarray, tau: np.ndarray, force: np.ndarray) -> np.ndarray:
    """Pose change (k, 6) of platforms in equilibrium at ``poses`` under fixed tensions ``tau`` (k, n) when a
    force (k, 3) N acts at the centre of mass, to first order: the statics' pose Jacobian at fixed tensions
    times the change equals the force's generalised wrench."""
    kin = inverse_kinematics(robot, poses)
    s = np.einsum("kab,b->ka", kin.R, robot.com)
    wrench = np.concatenate([force, np.einsum("kaj,ka->kj", kin.H, np.cross(s, force))], axis=1)
    _, jac = equilibrium_residual(robot, poses, tau)
    return np.linalg.solve(jac, wrench[..., None])[..., 0]


def sway_displacement(robot: Robot, poses: np.ndarray, tau: np.ndarray, amplitude: float,
                      rng: np.random.Generator) -> np.ndarray:
    """Pose change (k, 6) from the window-mean push of the simulator's sway (sim_backend.physics.Sway: per
    horizontal axis three sines of amplitude F/3, F the cables' lateral stiffness at the first pose,
    sum tau_i / l_i, times ``amplitude`` m), drawn independently per pose (standard deviation F / sqrt 6 per
    axis)."""
    stiffness = float(np.sum(tau[0] / inverse_kinematics(robot, poses[:1]).lengths[0]))
    force = np.zeros((poses.shape[0], 3))
    force[:, :2] = rng.standard_normal((poses.shape[0], 2)) * stiffness * amplitude / math.sqrt(6.0)
    return force_displacement(robot, poses, tau, force)


def simulated_rows(robot: Robot, config, seed: int = 0, grid: int = 2, noise: dict | None = None,
                   plan: PosePlan | None = None, device_biases: bool = True) -> SimulatedRows:
    """Window-averaged readings at the planned poses of ``robot`` with the hidden effects of ``config``
    (a ``sim_backend.config.SimConfig``), noise of ``noise`` (default WINDOW_NOISE) drawn with ``seed``,
    and, with ``device_biases``, the emulators' per-device constant errors drawn with ``seed``."""
    e = config.effects
    n = robot.n
    plan = plan or plan_poses(robot, grid)
    sp = np.vstack([plan.tau0, plan.setpoints])
    cell_error, ahrs_bias = np.zeros(n), np.zeros(3)
    if device_biases:  # a stream of its own, so that the noise draws do not depend on this switch
        brng = np.random.default_rng([seed, 406])
        fs = robot.sensors.load_cell_uncertainty
        cell_error = brng.uniform(-fs, fs, n)
        ahrs_bias[:2] = np.radians(brng.uniform(-XsensNoise.roll_pitch_bias, XsensNoise.roll_pitch_bias, 2))
    gain, offset = config.tension_gain(n), config.tension_offset(n) + cell_error
    # the load direction into each window: the setpoints' change (home: loaded from zero)
    dsp = np.diff(sp, axis=0)
    load_dir = np.vstack([np.ones((1, n)), np.where(np.abs(dsp) > 1e-9, np.sign(dsp), 0.0)])
    tau_cell = (sp + config.loadcell_hysteresis() * load_dir - offset) / gain  # the cells are regulated to sp
    truth = config.true_robot(robot)
    guess = np.vstack([plan.home_pose, plan.poses])
    mu, fr = config.pulley_friction()
    density = 0.0 if e.cable_sag is None else float(e.cable_sag)
    Z = guess
    # the direction each cable moves into each equilibrium: from the plan's sequence of poses (at home: 0)
    approach = np.zeros((Z.shape[0], n))
    kin_plan = inverse_kinematics(truth, guess)
    approach[1:] = np.sign(np.diff(kin_plan.lengths, axis=0))
    turn = np.zeros((Z.shape[0], n))  # the way each swivel turns into each equilibrium (no swivel friction here)
    turn[1:] = np.sign(np.angle(np.exp(1j * np.diff(kin_plan.swivel, axis=0))))
    tau = (tau_cell + approach * fr) / (1.0 - approach * mu)  # platform side of the pulleys
    chord = tau
    for _ in range(5 if density else 1):  # the cables' weights depend on the poses: a fixed point
        kin = inverse_kinematics(truth, Z)
        tau = chord - density * sag_cell(truth, kin)  # the chord tension: the cell reads rho g dz / 2 more
        ds = direct_statics_with_cables(truth, tau, Z, density, kin)
        if not ds.converged.all():
            raise ValueError("simulated_rows: no equilibrium of the true robot under some setpoint.")
        Z = ds.poses
    if config.sway is not None and config.sway.amplitude > 0:
        Z = Z + sway_displacement(truth, Z, tau, config.sway.amplitude, np.random.default_rng([seed, 517]))
    kin = inverse_kinematics(truth, Z)
    ea = config.physics_params(truth).ea
    path = kin.lengths + sag_length(truth, kin, tau, density)
    l0 = path / (1.0 + tau / ea)
    # the drives report (1 + k) times the true change (the simulator's and the effect's convention)
    scale = 1.0 if e.length_scale is None else 1.0 + np.asarray(e.length_scale)
    dl = (l0[1:] - l0[0]) * scale
    dsig = np.angle(np.exp(1j * (kin.swivel[1:] - kin.swivel[0])))
    mr, mp = config.ahrs_mounting()
    M = rotation(np.array([[mr, mp, 0.0]]), "xyz")[0]
    ang = rotation_to_euler(rotation(Z[:, 3:], robot.orientation) @ M, robot.ahrs_convention) + ahrs_bias
    ori = ang[1:].copy()
    ori[:, 2] = np.angle(np.exp(1j * (ori[:, 2] - ang[0, 2])))
    read_tau = gain * tau_cell + offset - config.loadcell_hysteresis() * load_dir
    sig = {k: np.broadcast_to(np.asarray(v, float), (3 if k == "orientation" else n,)).copy()
           for k, v in (noise or WINDOW_NOISE).items()}
    rng = np.random.default_rng(seed)
    k = Z.shape[0] - 1
    meas = Measurements(
        tau=read_tau[1:] + sig["tension"] * rng.standard_normal((k, n)),
        dl=dl + sig["length"] * rng.standard_normal((k, n)),
        dsigma=dsig + sig["swivel"] * rng.standard_normal((k, n)),
        orientation=ori + sig["orientation"] * rng.standard_normal((k, 3)),
        ref_tau=read_tau[0] + sig["tension"] * rng.standard_normal(n),
        ref_orientation=ang[0, :2] + sig["orientation"][:2] * rng.standard_normal(2),
        samples=np.arange(1, k + 1),
        windows=np.stack([np.arange(1, k + 1)] * 2, axis=1),
        approach=approach[1:].copy(),
        load_approach=load_dir[1:].copy(),
        ref_approach=approach[0].copy(),
        ref_load_approach=load_dir[0].copy(),
        swivel_approach=turn[1:].copy(),
        ref_swivel_approach=turn[0].copy(),
    )
    return SimulatedRows(meas, sig, Z[0].copy(), Z[1:].copy(), plan.home_pose.copy(), plan.poses.copy())
