"""The built-in effects (names of spec/cli.md), each with analytic (or exact) Jacobian columns.

Reading effects: cable_elasticity (encoders count the unstretched length l0 = L / (1 + tau / EA)),
length_scale (per winch: length reading = (1 + k_i) * true change of the unstretched length),
tension_gain and tension_offset (load cell i reads (1 + g_i) tau_i + o_i), ahrs_mounting (the AHRS frame
is tilted by Rx(roll) Ry(pitch) on the platform: it reads the angles of R(zeta) Rx(roll) Ry(pitch)),
ahrs_yaw_drift (yaw reading + rate * t).
Robot effects: pulley_radius (common, or per pulley), pulley_position (d_i, 3 per pulley), com_offset
(3, platform frame), mass_scale (true mass = (1 + s) model mass).
"""

from __future__ import annotations

import math

import numpy as np

from calib.effects.base import Context, Effect, Implausible, ParamSpec, add_tension_offsets, base_quantities
from calib.kinematics import euler_axes, inverse_kinematics, rotation, rotation_to_euler
from calib.robot import Robot
from calib.selfcal.model import ChannelPrediction


def _scale_channel(pred: ChannelPrediction, factor: np.ndarray) -> None:
    """Multiply a channel's value and derivatives by factor (c,) in place."""
    pred.value = pred.value * factor
    pred.d_pose = pred.d_pose * factor[None, :, None]
    pred.d_theta = pred.d_theta * factor[None, :, None]


class ChannelGain(Effect):
    """A gain per reading of one channel: reading = (1 + g_i) x the prediction (``channel``; parameters
    ``prefix``_i, plausible within +-``bound``). Subclasses set the three and say where the bound comes from."""

    channel: str = ""
    prefix: str = "g"
    bound: float = 0.03

    def params(self, robot: Robot) -> list[ParamSpec]:
        return [ParamSpec(f"{self.prefix}_{i + 1}", "1", 0.0, -0.5, 0.5, 0.01, plausible=(-self.bound, self.bound))
                for i in range(robot.n)]

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        if self.channel not in preds:
            return
        pr = preds[self.channel]
        base = pr.value.copy()
        _scale_channel(pr, 1.0 + np.asarray(values, float))
        pr.d_theta[..., ctx.cols] = base[..., None] * np.eye(values.shape[0])[None]


class CableElasticity(Effect):
    """Elastic cables: the encoders count the unstretched length l0 = L / (1 + c tau), c = 1/EA (1/N)."""

    name = "cable_elasticity"
    order = 10
    description = "axial cable compliance 1/EA: encoders see L / (1 + tau / EA)"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: EA >= 5 kN. A 2 mm steel rope has EA ~ 300 kN, a 2-4 mm UHMWPE (Dyneema) rope 20-200 kN
        # (E ~ 60-100 GPa on ~50 % of the section); creep and the rope's bedding on the drum soften it by a
        # factor of a few at most. A fit softer than 5 kN means something else stretches the lengths.
        return [ParamSpec("compliance", "1/N", 0.0, 0.0, 1e-2, 1e-5, plausible=(0.0, 2e-4))]

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        if "length" not in preds:
            return
        c = float(values[0])

        def parts(ph):
            den = 1.0 + c * ph.tau
            l0 = ph.L / den
            d_l = 1.0 / den
            d_tau = -ph.L * c / den**2
            d_c = -ph.L * ph.tau / den**2
            return l0, d_l, d_tau, d_c

        l0, a_l, a_t, a_c = parts(ctx.at)
        r0, b_l, b_t, b_c = parts(ctx.ref)
        pr = preds["length"]
        pr.value = l0 - r0
        pr.d_pose = a_l[..., None] * ctx.at.dL + a_t[..., None] * ctx.at.dtau
        pr.d_theta = (a_l[..., None] * ctx.at.tL + a_t[..., None] * ctx.at.ttau) - (
            b_l[..., None] * ctx.ref.tL + b_t[..., None] * ctx.ref.ttau
        )
        pr.d_theta[..., ctx.cols] = (a_c - b_c)[..., None]

    def absolute_length(self, ref, values: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        return lengths / (1.0 + float(values[0]) * ref.tau[0])

    def report(self, robot: Robot, values: np.ndarray) -> dict[str, float]:
        c = float(values[0])
        return {"EA": (1.0 / c) if c != 0 else math.inf, "compliance": c}


class LengthScale(ChannelGain):
    """Transmission-ratio error per winch: length reading = (1 + k_i) true change of length."""

    name = "length_scale"
    order = 20
    description = "per-winch transmission ratio error k_i"
    channel, prefix = "length", "k"
    # plausible: |k_i| <= 5 %. The length per motor revolution is a number configured in the controller
    # (drum radius and gear ratio), and the lab's own files of one run disagree on it: the controller's
    # per-winch ratios (0.028807, 0.028652, 0.028448, 0.028641 m/rev, raw log of sc_8_final) and the
    # authors' parser's common 0.0280645 m/rev differ by 1.4-2.6 % (acquisition/importers.py), so a
    # configured ratio can be off by that much; the rope's layer on the drum then shifts the effective
    # radius by up to half a rope diameter (1-2 mm, a further 1-2 % of a ~50 mm drum radius).
    bound = 0.05


class TensionGain(ChannelGain):
    """Load-cell gain error per channel: reading = (1 + g_i) tau_i."""

    name = "tension_gain"
    order = 30
    description = "per-channel load-cell gain error g_i"
    channel = "tension"
    # plausible: |g_i| <= 3 %. A load cell's rated-output tolerance is 0.1-1 % (uncalibrated S-beam cells,
    # typical datasheets), the amplifier's gain error <= 0.5 %, and a rope leaving the cell's pulley a
    # few degrees off its axis changes the force on the cell by (1 - cos) ~ 0.1-1 %.
    bound = 0.03


class TensionOffset(Effect):
    """Load-cell offset per channel: reading = tau_i + o_i (N)."""

    name = "tension_offset"
    order = 31
    description = "per-channel load-cell offset o_i, N"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: |o_i| <= 2 % of the cell's full scale (robot sensors.load_cell_full_scale: 19.6 N for
        # 100 kg). Zero balance of a load cell is specified within +-1 % of rated output (typical S-beam
        # datasheets), the amplifier's zero within a fraction of that, and the tare of the hardware hanging
        # on the cell (sheave, shackle) is at most a few newtons.
        fs = 0.02 * float(robot.sensors.load_cell_full_scale)
        return [ParamSpec(f"o_{i + 1}", "N", 0.0, -100.0, 100.0, 1.0, plausible=(-fs, fs)) for i in range(robot.n)]

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        add_tension_offsets(ctx.cols, values, preds)


class AhrsMounting(Effect):
    """AHRS tilted on the platform by Rx(roll) Ry(pitch): it reads the Euler angles of R(zeta) M."""

    name = "ahrs_mounting"
    order = 40
    description = "roll and pitch tilt of the AHRS on the platform, rad"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: a tilt of at most 3 deg: the AHRS sits on a machined bracket screwed to the platform;
        # a bracket bent or shimmed by more than a few degrees would be seen by eye.
        tilt = (-math.radians(3.0), math.radians(3.0))
        return [ParamSpec("roll", "rad", 0.0, -0.5, 0.5, 0.01, plausible=tilt),
                ParamSpec("pitch", "rad", 0.0, -0.5, 0.5, 0.01, plausible=tilt)]

    @staticmethod
    def _read(conv: str, angles: np.ndarray, a: float, b: float, sensor: str | None = None):
        """Measured angles (k, 3) in the sensor's convention, d(measured)/d(angles) (k, 3, 3) and
        d(measured)/d(a, b) (k, 3, 2); ``conv`` is the robot's convention of ``angles``."""
        sensor = sensor or conv
        R = rotation(angles, conv)
        M = rotation(np.array([[a, b, 0.0]]), "xyz")[0]
        meas = rotation_to_euler(R @ M, sensor)
        Hinv = np.linalg.inv(euler_axes(meas, sensor))
        d_ang = Hinv @ euler_axes(angles, conv)
        ex, ey = np.array([1.0, 0, 0]), np.array([0, math.cos(a), math.sin(a)])
        w = np.stack([R @ ex, R @ ey], axis=-1)  # (k, 3, 2): world rotation axes of d a and d b
        return meas, d_ang, Hinv @ w

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        if "orientation" not in preds:
            return
        conv, sensor = ctx.robot.orientation, ctx.robot.ahrs_convention
        a, b = float(values[0]), float(values[1])
        meas, d_ang, d_ab = self._read(conv, ctx.poses[:, 3:], a, b, sensor)
        m0, d0, d0ab = self._read(conv, ctx.theta[None, 3:6], a, b, sensor)
        pr = preds["orientation"]
        val = meas.copy()
        val[:, 2] = np.angle(np.exp(1j * (meas[:, 2] - m0[0, 2])))
        pr.value = val
        pr.d_pose = np.zeros_like(pr.d_pose)
        pr.d_pose[:, :, 3:] = d_ang
        pr.d_theta = np.zeros_like(pr.d_theta)
        pr.d_theta[:, 2, 3:6] = -d0[0, 2]
        cols = d_ab.copy()
        cols[:, 2] -= d0ab[0, 2]
        pr.d_theta[..., ctx.cols] = cols

    def absolute_yaw(self, robot: Robot, zeta0: np.ndarray, values: np.ndarray, yaw: float) -> float:
        """The yaw the tilted AHRS shows at zeta_0: that of R(zeta_0) M in its own convention."""
        meas, _, _ = self._read(robot.orientation, np.asarray(zeta0, float)[None, 3:6], float(values[0]),
                                float(values[1]), robot.ahrs_convention)
        return float(meas[0, 2])


class AhrsYawDrift(Effect):
    """The AHRS yaw drifts at a constant rate: yaw reading = true yaw change + rate * t (rad/s), t the row's
    time after the reference sample. Without a magnetometer the heading is the integral of a gyro whose bias
    is never observed; an MTi in VRU mode drifts by up to tens of degrees per hour. Needs the rows' times
    (runs have them; rows without times leave it unobservable)."""

    name = "ahrs_yaw_drift"
    order = 41
    description = "constant drift rate of the AHRS yaw, rad/s"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: |rate| <= 180 deg/h (0.05 deg/s). The heading here is gyro-only: the MTi-630 runs with
        # its magnetometer off (Zoffoli et al. 2025, Section 4: the startup yaw is set to 0, the magnetic north
        # being unreliable near the motors). Its gyros' turn-on bias repeats only within +-0.5 deg/s, and the
        # filter estimates it from gravity for roll and pitch, but for the heading only from the magnetometer,
        # Active Heading Stabilization or a NoRotation update (Xsens knowledge base, "Bias repeatability of
        # gyroscopes"); the 8 deg/h in-run bias stability of the datasheet bounds its change during a run, not
        # the part left unestimated. A tenth of the turn-on repeatability is the bound taken; the real runs
        # show 25-61 deg/h (issue 28). More than that is a turning platform or a broken heading.
        rate = math.radians(180.0) / 3600.0
        return [ParamSpec("rate", "rad/s", 0.0, -0.01, 0.01, 1e-4, plausible=(-rate, rate))]

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        if "orientation" not in preds or ctx.times is None:
            return
        t = np.asarray(ctx.times, float)
        pr = preds["orientation"]
        pr.value = pr.value.copy()
        pr.value[:, 2] += float(values[0]) * t
        pr.d_theta[:, 2, ctx.cols.start] = t

    def report(self, robot: Robot, values: np.ndarray) -> dict[str, float]:
        return {"rate": float(values[0]), "deg_per_hour": math.degrees(float(values[0])) * 3600.0}


class PulleyRadius(Effect):
    """Pulley radius error, m: one common value (``per_pulley=False``) or one per pulley."""

    name = "pulley_radius"
    stage = "robot"
    description = "error of the swivel pulleys' radius, m"

    def __init__(self, per_pulley: bool = False):
        self.per_pulley = per_pulley

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: |dr| <= 5 mm. The effective radius is the groove's radius plus half the rope diameter;
        # groove depth, rope diameter (2-4 mm) and its flattening under load change it by a few mm at most.
        ok = (-0.005, 0.005)
        if self.per_pulley:
            return [ParamSpec(f"dr_{i + 1}", "m", 0.0, -0.02, 0.05, 0.001, plausible=ok) for i in range(robot.n)]
        return [ParamSpec("dr", "m", 0.0, -0.02, 0.05, 0.001, plausible=ok)]

    def modify(self, robot: Robot, values: np.ndarray) -> Robot:
        has = robot.r > 0
        return robot.replace(r=np.where(has, robot.r + values, robot.r))

    def physical_columns(self, robot, values, poses, recompute):
        _, _, dtau = super().physical_columns(robot, values, poses, recompute)
        kin = inverse_kinematics(robot, poses)
        cp, sp = np.cos(kin.psi), np.sin(kin.psi)
        tu = np.einsum("kna,kna->kn", kin.t, kin.u)
        tk = np.einsum("kna,na->kn", kin.t, robot.frames[:, 2])
        dl = np.where(robot.r[None] > 0, (np.pi - kin.psi) - (1 + cp) * tu - sp * tk, 0.0)  # (k, n)
        if self.per_pulley:
            dL = dl[..., None] * np.eye(robot.n)[None]
        else:
            dL = dl[..., None]
        return dL, np.zeros_like(dL), dtau


def pulley_gauge_basis(robot: Robot) -> np.ndarray:
    """Orthonormal basis (3n, 3n - 4) of pulley displacements that are not a gauge motion: a common
    translation of all pulleys, or a common rotation about the vertical through their centroid, moves the
    fixed frame, not the robot (the readings cannot see it; the AHRS yaw is relative)."""
    n = robot.n
    c = robot.d.mean(axis=0)
    G = np.zeros((3 * n, 4))
    for i in range(n):
        G[3 * i : 3 * i + 3, :3] = np.eye(3)
        G[3 * i : 3 * i + 3, 3] = np.cross([0.0, 0.0, 1.0], robot.d[i] - c)
    U, _, _ = np.linalg.svd(G, full_matrices=True)
    return U[:, 4:]


class PulleyPosition(Effect):
    """Pulley entry-point errors (m, fixed frame): the 3n - 4 observable deformation modes of the pulley
    set (see :func:`pulley_gauge_basis`); reported as per-pulley offsets dx_i, dy_i, dz_i of zero mean
    translation and zero mean rotation about the vertical."""

    name = "pulley_position"
    stage = "robot"
    description = "error of the pulleys' entry points D_i (deformation of the pulley set), m"

    def __init__(self):
        self._bases: dict[bytes, np.ndarray] = {}  # pulley_gauge_basis by pulley points (an SVD per call)

    def basis(self, robot: Robot) -> np.ndarray:
        key = robot.d.tobytes()
        if key not in self._bases:
            if len(self._bases) > 8:
                self._bases.clear()
            self._bases[key] = pulley_gauge_basis(robot)
        return self._bases[key]

    def params(self, robot: Robot) -> list[ParamSpec]:
        return [ParamSpec(f"mode_{j + 1}", "m", 0.0, -0.2, 0.2, 0.001) for j in range(3 * robot.n - 4)]

    # plausible: every pulley within 3 cm of its nominal point, per coordinate. The frame's pulley points
    # are measured with a tape or a laser meter to about 1 cm; the frame's deflection under ~200 N of
    # tension and the swivel's play add millimetres.
    PLAUSIBLE = 0.03

    def implausible(self, robot: Robot, values: np.ndarray) -> list[Implausible]:
        lim = self.PLAUSIBLE
        return [Implausible(f"{self.name}.{k}", v, "m", -lim, lim)
                for k, v in self.report(robot, values).items() if abs(v) > lim]

    def modify(self, robot: Robot, values: np.ndarray) -> Robot:
        return robot.replace(d=robot.d + (self.basis(robot) @ values).reshape(robot.n, 3))

    def physical_columns(self, robot, values, poses, recompute):
        _, _, dtau = super().physical_columns(robot, values, poses, recompute)
        kin = inverse_kinematics(robot, poses)
        k, n = kin.lengths.shape
        dL = np.zeros((k, n, 3 * n))
        ds = np.zeros((k, n, 3 * n))
        for i in range(n):  # q = a - d: dL = t . dq, dsigma = w . dq / (q . u)
            dL[:, i, 3 * i : 3 * i + 3] = -kin.t[:, i]
            ds[:, i, 3 * i : 3 * i + 3] = -kin.w[:, i] / kin.rho_u[:, i, None]
        B = self.basis(robot)
        return dL @ B, ds @ B, dtau

    def report(self, robot: Robot, values: np.ndarray) -> dict[str, float]:
        off = (self.basis(robot) @ values).reshape(robot.n, 3)
        return {f"d{ax}_{i + 1}": float(off[i, j]) for i in range(robot.n) for j, ax in enumerate("xyz")}


class ComOffset(Effect):
    """Centre-of-mass error (m, platform frame): the tensions are linear in it (exact columns)."""

    name = "com_offset"
    stage = "robot"
    description = "centre of mass offset in the platform frame, m"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: 2 cm across, 5 cm along the platform's axis. The centre of mass comes from the CAD model
        # of a ~0.3 m platform; unmodelled parts (AHRS, wiring, bolts: a few hundred grams of 13 kg at
        # <= 0.2 m) move it by millimetres, a misplaced battery or ballast by a centimetre or two.
        return [ParamSpec(f"d{ax}", "m", 0.0, -0.2, 0.2, 0.01, plausible=lim)
                for ax, lim in (("x", (-0.02, 0.02)), ("y", (-0.02, 0.02)), ("z", (-0.05, 0.05)))]

    def modify(self, robot: Robot, values: np.ndarray) -> Robot:
        return robot.replace(com=robot.com + values)

    def physical_columns(self, robot, values, poses, recompute):
        L, _, tau = base_quantities(recompute, values)
        cols = []
        for j in range(3):
            v = values.copy()
            v[j] += 1.0
            cols.append(recompute(v)[2] - tau)  # exact: tau is affine in the centre of mass
        dtau = np.stack(cols, axis=-1)
        z = np.zeros(L.shape + (3,))
        return z, z.copy(), dtau


class MassScale(Effect):
    """Platform mass error: true mass = (1 + s) model mass; the tensions scale with it (exact)."""

    name = "mass_scale"
    stage = "robot"
    description = "relative error of the platform mass"

    def params(self, robot: Robot) -> list[ParamSpec]:
        # plausible: |s| <= 3 %. The platform is weighed (12.992 kg for IRMA4U, Table I); the rope hanging
        # between pulleys and platform (~0.1 kg) and parts mounted after weighing (AHRS, wiring) add a few
        # hundred grams at most.
        return [ParamSpec("s", "1", 0.0, -0.5, 0.5, 0.01, plausible=(-0.03, 0.03))]

    def modify(self, robot: Robot, values: np.ndarray) -> Robot:
        return robot.replace(mass=robot.mass * (1.0 + float(values[0])))

    def physical_columns(self, robot, values, poses, recompute):
        L, _, tau = base_quantities(recompute, values)
        z = np.zeros(L.shape + (1,))
        return z, z.copy(), (tau / (1.0 + float(values[0])))[..., None]


BUILTIN: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (
        CableElasticity,
        LengthScale,
        TensionOffset,
        TensionGain,
        PulleyRadius,
        AhrsMounting,
        AhrsYawDrift,
        ComOffset,
        MassScale,
        PulleyPosition,
    )
}
