"""The swivel-pulley geometry family (issue 28): what the rigid pulley model of Zoffoli eq. 1-5 takes as exact.

The model puts the pulley's groove tangent to the swivel axis k_i at D_i, the pulley plane through that axis,
and reads the swivel angle with an encoder "mounted directly on the swivel axes" (Zoffoli et al. 2025,
Section 4). On the real runs the swivel channel keeps the largest misfit once the load cells and the AHRS
are modelled (issue 28): three ways the pulleys can differ from that, each with exact Jacobian columns.

* ``swivel_tilt`` (robot): the swivel axis of pulley i is tilted about its own i_i by a_i (``tilt_i_<i>``)
  and then about the tilted j_i by b_i (``tilt_j_<i>``): the local frame becomes (Rx(a_i) Ry(b_i))^T F_i.
  A tilt about k_i itself is a swivel offset, which the relative encoders cannot see: it is left out.
* ``swivel_entry`` (reading of the geometry): the groove entry point sits e_i off the swivel axis along the
  pulley's radius u_i and the pulley plane f_i off the axis along w_i. The anchor then lies in the offset
  plane: the swivel angle is atan2(q.j, q.i) - asin(f / rho_u), and the in-plane geometry of eq. 4-5 sees
  rho_u' = sqrt(rho_u^2 - f^2) - e instead of rho_u. The modelled tensions keep the rigid cable directions
  (the direction turns by about f / |rho| < 1e-2 rad, changing a tension by far less than a load cell's
  noise): documented, and the columns say so (none on tensions).
* ``swivel_gain`` (reading): swivel reading = (1 + g_i) * true change of the swivel angle.
* ``swivel_friction`` (reading): the swivel bearing's friction torque M holds the pulley plane short of the
  cable's plane (Zoffoli, footnote 1: the pulley constraints hold "when ... tension forces are sufficient to
  overcome pulley friction"). The cable, out of the pulley plane by delta, turns the pulley with the moment
  tau * lever * delta about its axis, lever = r (1 + cos psi) rho_u / |rho| (the moment of the cable force
  about k_i through D_i, to first order in delta), so the pulley stops delta = M / (tau lever) behind the
  way it last turned: reading = sigma - s M / (tau lever), s = +1 when the swivel last turned up.
"""

from __future__ import annotations

import math

import numpy as np

from calib.effects.base import Context, Effect, ParamSpec, wrap
from calib.effects.builtin import ChannelGain
from calib.kinematics import cross, inverse_kinematics, pose_gradients, rotation
from calib.robot import Robot
from calib.selfcal.model import ChannelPrediction


def _tilt_matrices(values: np.ndarray, n: int) -> np.ndarray:
    """(n, 3, 3) rotations S_i = Rx(a_i) Ry(b_i) of the pulleys' frames, values = [a_1, b_1, a_2, ...]."""
    ab = np.asarray(values, float).reshape(n, 2)
    return rotation(np.column_stack([ab, np.zeros(n)]), "xyz")


class SwivelTilt(Effect):
    """Swivel-axis tilt per pulley (rad): the local frame F_i becomes S_i^T F_i, S_i = Rx(a_i) Ry(b_i);
    parameters tilt_i_<i> = a_i, tilt_j_<i> = b_i."""

    name = "swivel_tilt"
    stage = "robot"
    description = "tilt of each swivel axis about its pulley's i and j axes, rad"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: |a_i|, |b_i| <= 2 deg. The swivel's bearing housing is bolted to the frame with its axis
        # set by the mounting face; IRMA4U's axes are horizontal (robot YAML: k_i = +-x). An axis 2 deg off
        # (35 mm over a metre) is what a frame member bent or a housing shimmed by eye can leave unnoticed;
        # a spirit level (about 0.06 deg per division) would find more. No measurement of the axes exists.
        ok = (-math.radians(2.0), math.radians(2.0))
        return [ParamSpec(f"tilt_{ax}_{i + 1}", "rad", 0.0, -0.3, 0.3, 0.01, plausible=ok)
                for i in range(robot.n) for ax in ("i", "j")]

    def modify(self, robot: Robot, values: np.ndarray) -> Robot:
        S = _tilt_matrices(values, robot.n)
        return robot.replace(frames=np.einsum("nba,nbc->nac", S, robot.frames))

    def physical_columns(self, robot, values, poses, recompute):
        """dL and dsigma exact: with the local components ql = F' q, d ql / d a = ql x (Ry(b)^T e_x) and
        d ql / d b = ql x e_y, and dL = t.dq, dsigma = w.dq / rho_u in the local frame; dtau by differences."""
        _, _, dtau = super().physical_columns(robot, values, poses, recompute)
        kin = inverse_kinematics(robot, poses)  # robot: every robot effect applied (this tilt included)
        n = robot.n
        F = robot.frames  # (n, 3, 3) rows: the tilted i, j, k
        ql = np.einsum("nab,knb->kna", F, kin.q)
        tl = np.einsum("nab,knb->kna", F, kin.t)
        wl = np.einsum("nab,knb->kna", F, kin.w)
        b = np.asarray(values, float).reshape(n, 2)[:, 1]
        axes = [np.stack([np.cos(b), np.zeros(n), np.sin(b)], -1)[None], np.array([0.0, 1.0, 0.0])[None, None]]
        k = ql.shape[0]
        dL = np.zeros((k, n, 2 * n))
        ds = np.zeros((k, n, 2 * n))
        for j, v in enumerate(axes):
            dq = cross(ql, np.broadcast_to(v, ql.shape))
            dL[:, np.arange(n), 2 * np.arange(n) + j] = np.einsum("kna,kna->kn", tl, dq)
            ds[:, np.arange(n), 2 * np.arange(n) + j] = np.einsum("kna,kna->kn", wl, dq) / kin.rho_u
        return dL, ds, dtau


def _in_plane(rho_u: np.ndarray, rho_k: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Length of cable from the groove entry to the anchor (eq. 4-5) for in-plane anchor coordinates rho_u
    (from the entry point along u) and rho_k (along the axis), and its derivatives t_u, t_k (the components of
    the cable's unit vector: dL = t_u drho_u + t_k drho_k)."""
    ratio = rho_k / rho_u
    half = ratio + np.sqrt(ratio * ratio + 1.0 - 2.0 * r / rho_u)
    h2 = half * half
    cp, sp = (1.0 - h2) / (1.0 + h2), 2.0 * half / (1.0 + h2)
    ru, rk = rho_u - r * (1.0 + cp), rho_k - r * sp
    rn = np.hypot(ru, rk)
    return rn + r * (np.pi - 2.0 * np.arctan(half)), ru / rn, rk / rn


class SwivelEntry(Effect):
    """Groove entry point off the swivel axis (m): e_i along the pulley's radius u_i, f_i normal to the
    pulley plane (w_i). Edits the physical lengths and swivel angles (``Context.at``/``ref``) before any
    other reading effect, so that elasticity, sag and scale act on the true geometry."""

    name = "swivel_entry"
    order = 5
    edits_physical = True
    description = "groove entry point off the swivel axis: radial e_i and normal f_i offsets, m"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: |e_i|, |f_i| <= 5 mm. The pulley's fork is machined to put the groove tangent to the
        # swivel axis (Zoffoli eq. 1: the cable enters at D_i on the axis); the rope (2-4 mm) rides in a
        # groove wider than itself, and the fork's bearings and the pulley's axial play add a millimetre or
        # two. More than 5 mm is another pulley or a wrong drawing, not a tolerance.
        ok = (-0.005, 0.005)
        return [ParamSpec(f"{ax}_{i + 1}", "m", 0.0, -0.05, 0.05, 0.001, plausible=ok)
                for i in range(robot.n) for ax in ("e", "f")]

    @staticmethod
    def _changes(robot: Robot, poses: np.ndarray, values: np.ndarray):
        """At poses (k, 6): the changes of L and sigma (k, n), their pose derivatives (k, n, 6) and their
        derivatives with respect to (e_i, f_i) (k, n, 2)."""
        kin = inverse_kinematics(robot, poses)
        ef = np.asarray(values, float).reshape(robot.n, 2)
        e, f = ef[None, :, 0], ef[None, :, 1]
        r = robot.r[None, :]
        s = np.sqrt(kin.rho_u**2 - f**2)
        L1, tu, tk = _in_plane(s - e, kin.rho_k, r)
        L0 = kin.lengths
        fk = np.broadcast_to(robot.frames[None, :, 2], kin.u.shape)
        g = pose_gradients(kin, np.stack([kin.u, fk], axis=2))  # d rho_u, d rho_k: (k, n, 2, 6)
        _, tu0, tk0 = _in_plane(kin.rho_u, kin.rho_k, r)
        dL = (tu * kin.rho_u / s - tu0)[..., None] * g[:, :, 0] + (tk - tk0)[..., None] * g[:, :, 1]
        dS = -np.arcsin(f / kin.rho_u)
        dSd = (f / (kin.rho_u * s))[..., None] * g[:, :, 0]
        cols_L = np.stack([-tu, -tu * f / s], axis=-1)
        cols_S = np.stack([np.zeros_like(s), -1.0 / s], axis=-1)
        return L1 - L0, dS, dL, dSd, cols_L, cols_S

    @classmethod
    def _geometry_columns(cls, ctx: Context, values: np.ndarray, poses: np.ndarray, base: tuple
                          ) -> tuple[np.ndarray, np.ndarray]:
        """d(change of L, sigma)/d(robot effects' columns) (k, n, p): the entry's corrections move with the
        geometry the robot effects change (a tilted swivel axis turns the pulley's u and k): forward differences
        of relative step 1e-6 of max(|value|, 1e-2) per robot column (one inverse kinematics each)."""
        k, n = base[0].shape
        cL, cS = np.zeros((k, n, ctx.theta.size)), np.zeros((k, n, ctx.theta.size))
        for c in ctx.robot_cols if ctx.robot_at is not None and values.any() else ():
            th = ctx.theta.copy()
            h = 1e-6 * max(abs(th[c]), 1e-2)
            th[c] += h
            plus = cls._changes(ctx.robot_at(th), poses, values)
            cL[..., c], cS[..., c] = (plus[0] - base[0]) / h, (plus[1] - base[1]) / h
        return cL, cS

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        n, c0 = ctx.robot.n, ctx.cols.start
        idx = c0 + 2 * np.arange(n)
        a = self._changes(ctx.robot, ctx.poses, values)
        b = self._changes(ctx.robot, ctx.theta[None, :6], values)
        for ph, (dv_L, dv_S, dp_L, dp_S, cL, cS), at_ref in ((ctx.at, a, False), (ctx.ref, b, True)):
            gL, gS = self._geometry_columns(ctx, values, ctx.theta[None, :6] if at_ref else ctx.poses, (dv_L, dv_S))
            tL, tS = ph.tL + gL, ph.tsigma + gS
            rows = np.arange(n)
            for j in range(2):
                tL[:, rows, idx + j] = cL[..., j]
                tS[:, rows, idx + j] = cS[..., j]
            if at_ref:  # zeta_0 is the reference pose: its pose derivatives are theta derivatives
                tL[..., :6] += dp_L
                tS[..., :6] += dp_S
            else:
                ph.dL, ph.dsigma = ph.dL + dp_L, ph.dsigma + dp_S
            ph.L, ph.sigma, ph.tL, ph.tsigma = ph.L + dv_L, ph.sigma + dv_S, tL, tS
        if "length" in preds:
            preds["length"] = ChannelPrediction(ctx.at.L - ctx.ref.L, ctx.at.dL.copy(), ctx.at.tL - ctx.ref.tL)
        if "swivel" in preds:
            preds["swivel"] = ChannelPrediction(wrap(ctx.at.sigma - ctx.ref.sigma), ctx.at.dsigma.copy(),
                                                ctx.at.tsigma - ctx.ref.tsigma)


class SwivelGain(ChannelGain):
    """Swivel-encoder gain error per pulley: reading = (1 + g_i) * true change of the swivel angle."""

    name = "swivel_gain"
    order = 21
    description = "per-pulley swivel encoder gain error g_i"
    channel = "swivel"
    # plausible: |g_i| <= 0.2 %. The swivel encoders are "mounted directly on the swivel axes" (Zoffoli
    # et al. 2025, Section 4): no gear or belt between, so a count is 2 pi / 65536 exactly; what remains is
    # the encoder's accuracy, +-0.03 deg, which over the runs' swivel swing (>= 15 deg) is <= 0.2 % of it.
    # A larger gain is the geometry (a tilted axis scales the swing) or a wrong counts-per-revolution.
    bound = 0.002


def _lever_in_plane(rho_u: np.ndarray, rho_k: np.ndarray, r: np.ndarray) -> np.ndarray:
    """r (1 + cos psi) rho_u / |rho| (m) from the anchor's in-plane coordinates (eq. 4-5)."""
    ratio = rho_k / rho_u
    half = ratio + np.sqrt(ratio * ratio + 1.0 - 2.0 * r / rho_u)
    h2 = half * half
    cp, sp = (1.0 - h2) / (1.0 + h2), 2.0 * half / (1.0 + h2)
    return r * (1.0 + cp) * rho_u / np.hypot(rho_u - r * (1.0 + cp), rho_k - r * sp)


def _lever(robot: Robot, poses: np.ndarray, step: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """The cable's lever about each swivel axis per radian of the pulley plane's lag, r (1 + cos psi) rho_u /
    |rho| (m), at poses (k, 6): (k, n), and its pose derivatives (k, n, 6): the in-plane coordinates' exact
    pose gradients (d rho_u = u.dq, d rho_k = k.dq) times the lever's derivatives in them (central
    differences of a closed form, relative step ``step``: no further inverse kinematics)."""
    kin = inverse_kinematics(robot, np.asarray(poses, float).reshape(-1, 6))
    r = robot.r[None, :]
    lev = _lever_in_plane(kin.rho_u, kin.rho_k, r)
    hu, hk = step * kin.rho_u, step * np.maximum(np.abs(kin.rho_k), kin.rho_u)
    du = (_lever_in_plane(kin.rho_u + hu, kin.rho_k, r) - _lever_in_plane(kin.rho_u - hu, kin.rho_k, r)) / (2 * hu)
    dk = (_lever_in_plane(kin.rho_u, kin.rho_k + hk, r) - _lever_in_plane(kin.rho_u, kin.rho_k - hk, r)) / (2 * hk)
    fk = np.broadcast_to(robot.frames[None, :, 2], kin.u.shape)
    g = pose_gradients(kin, np.stack([kin.u, fk], axis=2))  # (k, n, 2, 6)
    return lev, du[..., None] * g[:, :, 0] + dk[..., None] * g[:, :, 1]


class SwivelFriction(Effect):
    """Friction torque M (N m) of the swivel bearings, common to the pulleys: the pulley plane lags the
    cable's by M / (tau lever) against the way the swivel last turned (``Context.approach[..., 2]`` for the
    rows, ``[..., 3]`` for the reference, whose lag every relative reading carries too)."""

    name = "swivel_friction"
    order = 6  # on the physical swivel angle, before the encoder's gain (21)
    description = "friction torque of the swivel bearings: the pulley lags the cable's plane, N m"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: 0 <= M <= 0.05 N m (friction opposes the motion: never negative). The swivel turns on a
        # pair of small sealed ball bearings and drives its encoder's shaft: 0.02-0.05 N m of breakaway
        # torque for the bearings and seals (as for pulley_friction in calib/effects/cable.py), an encoder's
        # shaft seal a few mN m. More holds the pulley degrees off the cable: a seized bearing, not friction.
        return [ParamSpec("M", "N m", 0.0, -1.0, 1.0, 0.005, plausible=(0.0, 0.05))]

    @staticmethod
    def _lag(ph, robot: Robot, poses: np.ndarray, s: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """s / (tau lever) (k, n) per unit torque; its pose derivatives through the tension (k, n, 6) and
        through the lever (k, n, 6), and its theta derivatives (k, n, p) through the tension."""
        lev, dlev = _lever(robot, poses)
        tau = np.maximum(ph.tau, 1.0)  # a slack cable's pulley: the lag of 1 N, not a division by zero
        g = s / (tau * lev)
        dg = np.where((ph.tau > 1.0)[..., None], -g[..., None] / tau[..., None], 0.0)
        return g, dg * ph.dtau, -(g / lev)[..., None] * dlev, dg * ph.ttau

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        if "swivel" not in preds:
            return
        pr = preds["swivel"]
        a = ctx.approach
        if a is None or np.shape(a)[-1] < 4:
            s = s0 = np.zeros(pr.value.shape)
        else:
            s = np.broadcast_to(np.asarray(a, float)[..., 2], pr.value.shape)
            s0 = np.broadcast_to(np.asarray(a, float)[..., 3], pr.value.shape)
        M = float(values[0])
        g, gp, gl, gt = self._lag(ctx.at, ctx.robot, ctx.poses, s)
        g0, _, gl0, gt0 = self._lag(ctx.ref, ctx.robot, ctx.theta[None, :6], np.ones((1, ctx.robot.n)))
        gt0 = gt0.copy()
        gt0[..., :6] += gl0  # zeta_0 is the reference pose (ref.ttau holds its tension's pose derivatives)
        gp = gp + gl
        pr.value = pr.value - M * (g - s0 * g0)
        pr.d_pose = pr.d_pose - M * gp
        pr.d_theta = pr.d_theta - M * (gt - s0[..., None] * gt0)
        pr.d_theta[..., ctx.cols.start] = -(g - s0 * g0)


SWIVEL: dict[str, type[Effect]] = {cls.name: cls for cls in (SwivelTilt, SwivelEntry, SwivelGain, SwivelFriction)}
