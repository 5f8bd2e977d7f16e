"""Effects of a real cable transmission the rigid model leaves out (issue 17), analytic Jacobian columns.

* ``pulley_friction``: on IRMA4U the load cell sits in the transmission, between the winch and the pulleys
  that lead the cable to the platform (Zoffoli et al. 2025, Section 4: "load cells inside the
  transmission"). Friction in those pulleys makes the winch-side tension the cell reads differ from the
  platform-side tension: reading = tau (1 - a mu) - a f, a = +1 when the cable last moved out (paid out:
  the platform pulls it over the pulleys, the winch side holds less), -1 when it was reeled in (the winch
  pulls it, the winch side carries more). ``mu`` is the friction proportional to the tension (sheave
  efficiency, rope bending), ``f`` the constant part (bearing and seal breakaway torque over the radius).
* ``loadcell_hysteresis``: a strain-gauge cell reads low on a rising load and high on a falling one:
  reading = tau - s h, s = +1 when the load last rose, -1 when it last fell.
* ``cable_sag``: cables of linear density rho (kg/m) with a parabolic sag (Irvine): the platform carries
  half of each cable's weight at its anchor, the cell at the pulley reads the chord tension plus
  rho g dz / 2 (dz: height of the pulley exit above the anchor), and the encoders count the sagging path,
  longer than the chord by (rho g)^2 lc h^2 / (24 tau^2) (lc: chord length, h: its horizontal span).
  The same model as the full simulator ``sim_backend.physics``.

The directions come with the rows (``Measurements.approach``/``load_approach``, ``Context.approach``);
rows without them (0) see neither direction-dependent effect.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.effects.base import Context, Effect, ParamSpec, _dataclass_rows
from calib.kinematics import (
    KinematicJacobians,
    Kinematics,
    inverse_kinematics,
    kinematic_jacobians,
    pose_jacobian_of_points,
)
from calib.robot import Robot
from calib.selfcal.model import ChannelPrediction
from calib.statics import point_load_tensions


def _direction(ctx: Context, which: int, shape: tuple[int, int]) -> np.ndarray:
    """(k, n) directions of the rows: 0 cable motion, 1 load change; zeros when unknown."""
    a = ctx.approach
    if a is None:
        return np.zeros(shape)
    return np.broadcast_to(np.asarray(a, float)[..., which], shape)


class PulleyFriction(Effect):
    """Friction in the pulleys between load cell and platform: reading = tau (1 - a mu) - a f, a = +1 when
    the cable was last paid out, -1 when reeled in (``Context.approach[..., 0]``)."""

    name = "pulley_friction"
    order = 28  # on the physical tension, before the cell's own gain (30) and offset (31)
    description = "friction in the pulleys between load cell and platform (relative mu, constant f N)"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: 0 <= mu <= 8 %, 0 <= f <= 4 N (friction opposes the motion: never negative). A sheave's
        # efficiency is 0.98 on rolling bearings and 0.96 on plain ones (FEM 1.001 / ISO 4301 rope drives);
        # between the cell and the platform the cable passes at most two sheaves (the cell's deflection
        # sheave and the swivel pulley): 1 - 0.96^2 = 8 %. The constant part is the bearings' and seals'
        # breakaway torque (0.02-0.05 N m for small sealed ball bearings) over a ~25 mm groove radius:
        # 1-2 N per sheave.
        return [ParamSpec("mu", "1", 0.0, -0.5, 0.5, 0.01, plausible=(0.0, 0.08)),
                ParamSpec("f", "N", 0.0, -50.0, 50.0, 1.0, plausible=(0.0, 4.0))]

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        if "tension" not in preds:
            return
        pr = preds["tension"]
        a = _direction(ctx, 0, pr.value.shape)
        mu, f = float(values[0]), float(values[1])
        base = pr.value.copy()
        fac = 1.0 - a * mu
        pr.value = base * fac - a * f
        pr.d_pose = pr.d_pose * fac[..., None]
        pr.d_theta = pr.d_theta * fac[..., None]
        c = ctx.cols.start
        pr.d_theta[..., c] = -a * base
        pr.d_theta[..., c + 1] = -a


class LoadcellHysteresis(Effect):
    """Load-cell hysteresis: reading = tau - s h (N), s = +1 when the load last rose, -1 when it last fell
    (``Context.approach[..., 1]``); one h common to the cells (same model, same datasheet)."""

    name = "loadcell_hysteresis"
    order = 33  # the cell's own error, after gain and offset
    description = "load-cell hysteresis: half the difference between falling and rising load, N"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: 0 <= h <= 0.025 % of full scale (0.245 N for 100 kg). Datasheets of S-beam and
        # in-line cells give the hysteresis (largest difference between the falling and the rising curve at
        # one load) as 0.02-0.05 % of full scale; h is half of that difference. A cell reads low on the
        # rising branch: never negative.
        hi = 0.5 * 0.0005 * float(robot.sensors.load_cell_full_scale)
        return [ParamSpec("h", "N", 0.0, -20.0, 20.0, 0.1, plausible=(0.0, hi))]

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        if "tension" not in preds:
            return
        pr = preds["tension"]
        s = _direction(ctx, 1, pr.value.shape)
        pr.value = pr.value - s * float(values[0])
        pr.d_theta[..., ctx.cols.start] = -s


@dataclass
class SagTerms:
    """What the cable weight changes per unit linear density (1 kg/m) at k poses, with pose derivatives
    (k, n, 6): ``tw`` the chord tensions that carry half of every cable's weight at its anchor (N per kg/m),
    ``cell`` what the cell reads on top of the chord tension, g dz / 2 (N per kg/m), ``m`` = lc h^2 (m^3),
    the factor of the sag's extra length (rho g)^2 m / (24 tau^2)."""

    tw: np.ndarray
    dtw: np.ndarray
    cell: np.ndarray
    dcell: np.ndarray
    m: np.ndarray
    dm: np.ndarray


def chord_jacobian(robot: Robot, kin: Kinematics, jac: KinematicJacobians) -> np.ndarray:
    """d rho_i / d zeta (k, n, 3, 6) of the straight segment B_i -> A_i,
    rho = q - r ((1 + cos psi) u + sin psi k): drho = dq - r (1 + cos psi) w dsigma + r (sin psi u - cos psi k) dpsi."""
    r = robot.r[None, :, None, None]
    cp, sp = np.cos(kin.psi), np.sin(kin.psi)
    fk = robot.frames[None, :, 2]
    v = sp[..., None] * kin.u - cp[..., None] * fk  # (k, n, 3)
    return (pose_jacobian_of_points(kin) - r * (1.0 + cp)[..., None, None] * kin.w[..., None] * jac.swivel[:, :, None]
            + r * v[..., None] * jac.psi[:, :, None])


def sag_terms(robot: Robot, poses: np.ndarray) -> SagTerms:
    """:class:`SagTerms` of ``robot`` at poses (k, 6)."""
    kin = inverse_kinematics(robot, poses)
    jac = kinematic_jacobians(robot, kin)
    drho = chord_jacobian(robot, kin, jac)  # (k, n, 3, 6)
    lc = kin.rho_norm
    dlc = np.einsum("kna,knaj->knj", kin.t, drho)
    # half of cable i's weight hangs at anchor i: a point mass lc_i / 2 (per kg/m) there; d tw also has the
    # term of the masses' own change, sum_i tau^(i) d(lc_i / 2), tau^(i) the tensions of 1 kg at anchor i
    each, tw, dtw = point_load_tensions(robot, kin, jac, robot.a_local, 0.5 * lc)
    dtw = dtw + 0.5 * np.einsum("kni,kij->knj", each, dlc)
    g = float(robot.gravity)
    cell = -0.5 * g * kin.rho[..., 2]
    dcell = -0.5 * g * drho[:, :, 2]
    h2 = kin.rho[..., 0] ** 2 + kin.rho[..., 1] ** 2
    dh2 = 2.0 * (kin.rho[..., 0, None] * drho[:, :, 0] + kin.rho[..., 1, None] * drho[:, :, 1])
    return SagTerms(tw, dtw, cell, dcell, lc * h2, dlc * h2[..., None] + lc[..., None] * dh2)


class CableSag(Effect):
    """Cable mass: linear density rho (kg/m), parabolic sag (see the module doc). Tensions: the cells read
    the chord tension (with half the cables' weight on the platform) plus rho g dz / 2; lengths: the
    encoders count the chord plus (rho g)^2 lc h^2 / (24 tau^2). The extra length is second order in rho
    (its column vanishes at rho = 0: the score test sees the tensions only). The absolute lengths
    (``absolute_length``) are left without the sag (below a millimetre for a plausible density)."""

    name = "cable_sag"
    # after elasticity (10: it rebuilds the length readings from the physical quantities, so an earlier sag
    # would be lost), before the length scale (20, which scales the sag too) and the load-cell effects (28+)
    order = 12
    description = "cable linear density (mass and parabolic sag), kg/m"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: 0 <= rho <= 0.07 kg/m. IRMA4U's cables are 2-4 mm ropes (robot YAML and Table I give no
        # diameter; the pulley radii and EA bound of cable_elasticity assume that range): a 4 mm 7x19 steel
        # wire rope weighs 0.062 kg/m (DIN EN 12385-4 tables), a 4 mm Dyneema braid 0.009 kg/m, a 2 mm steel
        # rope 0.016 kg/m. A heavier fit is no cable of this robot.
        return [ParamSpec("density", "kg/m", 0.0, -2.0, 2.0, 0.01, plausible=(0.0, 0.07))]

    def pose_terms(self, robot: Robot, poses: np.ndarray) -> SagTerms:
        return sag_terms(robot, poses)

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        if "tension" not in preds and "length" not in preds:
            return
        rho = float(values[0])
        c = ctx.cols.start
        k = ctx.poses.shape[0]
        if ctx.at.terms is not None and self.name in ctx.at.terms:  # computed with the physical quantities
            at, ref = ctx.at.terms[self.name], ctx.ref.terms[self.name]
        elif "length" in preds:  # the rows and zeta_0 in one evaluation
            both = sag_terms(ctx.robot, np.vstack([ctx.poses, ctx.theta[None, :6]]))
            at, ref = _dataclass_rows(both, slice(0, k)), _dataclass_rows(both, slice(k, k + 1))
        else:
            at = sag_terms(ctx.robot, ctx.poses)
        if "tension" in preds:
            pr = preds["tension"]
            pr.value = pr.value + rho * (at.tw + at.cell)
            pr.d_pose = pr.d_pose + rho * (at.dtw + at.dcell)
            pr.d_theta = pr.d_theta.copy()
            pr.d_theta[..., c] += at.tw + at.cell
        if "length" in preds:
            g = float(ctx.robot.gravity)
            p = ctx.theta.shape[0]

            def part(terms: SagTerms, ph, dpose_to_theta: bool):
                tau = ph.tau + rho * terms.tw
                ok = tau > 1.0  # the simulator's floor: a slack cable's sag is taken at 1 N
                tc = np.where(ok, tau, 1.0)
                a = (rho * g) ** 2 / 24.0
                sag = a * terms.m / tc**2
                d_tc_pose = np.where(ok[..., None], ph.dtau + rho * terms.dtw, 0.0)
                d_pose = a * (terms.dm / tc[..., None] ** 2 - 2.0 * terms.m[..., None] * d_tc_pose / tc[..., None] ** 3)
                d_theta = np.where(ok[..., None], -2.0 * sag[..., None] / tc[..., None] * ph.ttau, 0.0)
                if dpose_to_theta:  # at zeta_0: ph.ttau holds d tau / d zeta_0 already; add the rest
                    extra = np.zeros(sag.shape + (p,))
                    extra[..., :6] = a * (terms.dm / tc[..., None] ** 2 - 2.0 * terms.m[..., None]
                                          * np.where(ok[..., None], rho * terms.dtw, 0.0) / tc[..., None] ** 3)
                    d_theta = d_theta + extra
                d_rho = g * g / 24.0 * (2.0 * rho * terms.m / tc**2
                                        - 2.0 * rho * rho * terms.m * np.where(ok, terms.tw, 0.0) / tc**3)
                return sag, d_pose, d_theta, d_rho

            s1, dp1, dt1, dr1 = part(at, ctx.at, False)
            s0, _, dt0, dr0 = part(ref, ctx.ref, True)
            pr = preds["length"]
            pr.value = pr.value + s1 - s0
            pr.d_pose = pr.d_pose + dp1
            pr.d_theta = pr.d_theta + dt1 - dt0
            pr.d_theta[..., c] += dr1 - dr0


CABLE: dict[str, type[Effect]] = {cls.name: cls for cls in (PulleyFriction, LoadcellHysteresis, CableSag)}
