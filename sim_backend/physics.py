"""Rigid-body platform on elastic, unilateral cables driven by winches: the simulated prototype's physics.

Model (SI units throughout):

* the platform: a 6-DOF rigid body (mass m, centre of mass G at ``com`` in the platform frame, inertia
  about G in the platform frame), gravity along -z, light linear and angular damping (air, cable
  slapping) so that it swings and settles in a few seconds after each tension transition;
* cable i runs from its winch drum over the swivel pulley (entry point d_i, local frame, radius r_i,
  the geometry of ``calib.kinematics``) to the platform anchor A_i. Its unstretched length is
  ``l0_i = l00_i + k_i * theta_i`` with ``k_i`` the transmission (m of cable per rad of motor,
  ``length_per_motor_rev / 2 pi``, negative on IRMA4U: the cable shortens as the motor angle grows).
  Tension ``tau = EA (L - l0) / l0 + c dL/dt`` when taut, 0 when slack (unilateral);
* optional cable mass (kg/m): parabolic sag, which lengthens the path by ``w^2 Lc^3 cos^2(alpha) /
  (24 tau^2)``, loads each anchor with half the cable weight and makes the tension at the pulley (where
  the load cell is) exceed the chord tension by ``w dz / 2``;
* optional friction in the pulleys between the load cell (in the transmission, winch side) and the
  platform (``pulley_mu``, ``pulley_friction`` N, the ``pulley_friction`` hidden effect): the cell reads
  tau (1 - z mu) - z f, z = +1 once the cable was paid out, -1 once reeled in, by more than
  ``FRICTION_SLIDE`` m since the last reversal (a play operator on the motor-side length); the
  platform's dynamics see the platform-side tension; the winch's own Coulomb friction is apart);
* each winch: inertia J at the motor shaft (rotor + drum reflected through the gear), viscous and Coulomb
  friction, motor torque u (positive reels the cable in), an optional holding brake (engaged at power-on
  until the drive is enabled). With ``stiction`` > 0 the Coulomb friction has a stick phase (Karnopp): a winch
  that turns back or is slower than ``coulomb_speed`` while its net torque u + k tau is within ``coulomb``
  stops, as a braked one, until that torque exceeds ``stiction``; sliding, ``coulomb`` acts against the motion.
  The default 0 keeps the regularised friction (coulomb tanh(v / coulomb_speed)) bit for bit: a viscous brake
  at low speed, under which a held platform crept and never rested (issue 29), where the real robot's winches
  stand still in a hold (sc_8_final: lengths within 0.01-0.3 mm over a hold's last 3 s).

Integrator: one step per control period (optionally split into substeps) of a semi-implicit scheme:
the slow dynamics (gravity, damping, gyroscopic terms, motor torques) are explicit (symplectic Euler),
the stiff cable springs are solved implicitly in the 4-dimensional cable space: the tensions at the end
of the step solve ``(I + dt S D) tau = K e + S J v*`` with D = J M^-1 J^T the cable-space inverse
inertia, S = theta_imp dt K + C, which is unconditionally stable for any EA. Slack cables are handled by
an active set (a cable whose solved tension is negative carries none). Everything is plain float math on
lists (n = 4): numpy calls on arrays of four elements cost more than the arithmetic they do.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from calib.errors import CdprError
from calib.kinematics import rotation
from calib.robot import Robot

# m: the cable length the rope must slide back over the pulleys before their friction reverses (its
# pre-sliding, ~0.25 mm for a few N over EA / l ~ 20 kN/m, doubled): the same threshold as the rows'
# approach directions (calib.selfcal measurement_rows, APPROACH_LENGTH)
FRICTION_SLIDE = 5e-4


def play(x: float, state: float, extreme: float, width: float) -> tuple[float, float]:
    """Play (backlash) operator: the direction state (+1, -1, 0 unset) and the extreme of x since the last
    reversal, after x moved; the state reverses once x leaves its extreme by more than ``width``."""
    if state > 0:
        extreme = max(extreme, x)
        if x < extreme - width:
            return -1.0, x
    elif state < 0:
        extreme = min(extreme, x)
        if x > extreme + width:
            return 1.0, x
    elif abs(x - extreme) > width:
        return (1.0 if x > extreme else -1.0), x
    return state, extreme


class SimulationError(CdprError, RuntimeError):
    """The simulation cannot continue (diverged state); the message says when."""


@dataclass(frozen=True)
class WinchParams:
    """One winch: motor rotor and drum inertias kg m^2, drum radius m, friction at the motor shaft (viscous
    N m s/rad, Coulomb N m, static N m), ``coulomb_speed`` rad/s the speed under which it counts as stopped.

    The gear ratio follows from the drum radius and the transmission k (m of cable per rad of motor):
    ratio = drum_radius / |k|, and the inertia at the motor shaft is rotor + drum / ratio^2. With the
    defaults and IRMA4U's k (4.6 mm/rad): ratio 8.7, 5.9e-5 kg m^2, i.e. 2.8 kg moving with each cable.
    ``stiction`` > 0 (N m, >= coulomb; 0.015 N m is 3.3 N of cable tension on IRMA4U): the stick phase of the
    module doc; 0 keeps the regularised friction (coulomb tanh(v / coulomb_speed)).
    """

    rotor_inertia: float = 3.3e-5
    drum_inertia: float = 2.0e-3
    drum_radius: float = 0.04
    viscous: float = 2.0e-4
    coulomb: float = 0.01
    coulomb_speed: float = 0.05
    stiction: float = 0.0

    def inertia_at_motor(self, k: float) -> float:
        """Rotor plus reflected drum inertia, kg m^2, for a transmission of k m/rad."""
        ratio = self.drum_radius / abs(k)
        return self.rotor_inertia + self.drum_inertia / (ratio * ratio)


@dataclass(frozen=True)
class PhysicsParams:
    """Nominal physical parameters of the simulated prototype.

    ea: cable axial stiffness EA, N. The default 2e6 N stretches a 2.3 m cable by 0.23 mm under 200 N; a
    simulated startup takes instead the robot description's figure where it gives one, which the model
    knows too (``SimConfig.physics_params``, ``described_ea``).
    cable_damping: stiffness-proportional cable damping, s (c = cable_damping * EA / l0).
    linear_damping N s/m and angular_damping N m s/rad on the platform (residual swing of a few seconds).
    cable_density: kg/m, 0 for massless cables (the ``cable_sag`` hidden effect sets it).
    pulley_mu (relative) and pulley_friction (N): friction between load cell and platform (the
    ``pulley_friction`` hidden effect sets them).
    substeps per step; stiff_theta: 1 = implicit Euler on the cable springs, 0.5 = trapezoidal-like.
    """

    ea: float = 2.0e6
    cable_damping: float = 2.0e-4
    linear_damping: float = 20.0
    angular_damping: float = 0.6
    cable_density: float = 0.0
    pulley_mu: float = 0.0
    pulley_friction: float = 0.0
    winch: WinchParams = field(default_factory=WinchParams)
    substeps: int = 1
    stiff_theta: float = 1.0


@dataclass(frozen=True)
class Sway:
    """A slow random horizontal push on the platform (air, a hand, a cable's twist): ``amplitude`` m of
    platform position it gives, ``period`` s, ``seed`` of its phases."""

    amplitude: float = 0.0
    period: float = 8.0
    seed: int = 0

    def forces(self, force: float):
        """f(t) -> (fx, fy) N: per axis three sines about 1/period (0.8, 1, 1.25 times it) with random phases,
        weights summing to one, so that the push never exceeds ``force`` N."""
        rng = np.random.default_rng([self.seed, 11])
        w = [2.0 * math.pi / self.period * r for r in (0.8, 1.0, 1.25)]
        ph = rng.uniform(0.0, 2.0 * math.pi, (2, 3)).tolist()
        a = force / 3.0

        def f(t: float) -> tuple[float, float]:
            x, y = ph
            return (a * (math.sin(w[0] * t + x[0]) + math.sin(w[1] * t + x[1]) + math.sin(w[2] * t + x[2])),
                    a * (math.sin(w[0] * t + y[0]) + math.sin(w[1] * t + y[1]) + math.sin(w[2] * t + y[2])))

        return f


@dataclass(frozen=True)
class PhysicsState:
    """A snapshot of the simulated state: time s, pose (6,) m/rad, motor angles (n,) rad, tensions (n,) N."""

    time: float
    pose: np.ndarray
    motor_position: np.ndarray
    cable_tension: np.ndarray


def _solve_spd(a: list[list[float]], b: list[float]) -> list[float]:
    """Solve a small symmetric positive definite system by elimination without pivoting (lists, in place)."""
    n = len(b)
    for c in range(n):
        row = a[c]
        piv = row[c]
        for r in range(c + 1, n):
            ar = a[r]
            f = ar[c] / piv
            for j in range(c + 1, n):
                ar[j] -= f * row[j]
            b[r] -= f * b[c]
    x = [0.0] * n
    for c in range(n - 1, -1, -1):
        row = a[c]
        acc = b[c]
        for j in range(c + 1, n):
            acc -= row[j] * x[j]
        x[c] = acc / row[c]
    return x


def _active_set_solve(a: list[list[float]], b: list[float]) -> list[float]:
    """Tensions (n,) >= 0 solving ``a tau = b`` (a symmetric positive definite, not modified): a cable whose
    solved tension is negative is slack (0) and the system is solved again without it."""
    n = len(b)
    idx = list(range(n))
    a_idx, b_idx = [row[:] for row in a], list(b)  # every cable taut first
    while True:
        x = _solve_spd(a_idx, b_idx)
        tau = [0.0] * n
        for c, i in enumerate(idx):
            tau[i] = x[c]
        taut = [i for i in idx if not tau[i] < 0.0]
        if len(taut) == len(idx):
            return tau
        if not taut:
            return [0.0] * n
        idx = taut
        a_idx = [[a[i][j] for j in idx] for i in idx]
        b_idx = [b[i] for i in idx]


@functools.cache  # one layout per cable count, shared: do not change the dict
def snapshot_parts(n: int) -> dict[str, slice]:
    """Where each part of a :meth:`CablePhysics.snapshot` of ``n`` cables lies, in order: time s, motor angles
    (n) rad, motor velocities (n) rad/s, load-cell tensions (n) N, swivel angles (n) rad, unstretched lengths
    (n) m, centre of mass (3) m, orientation quaternion (4) [w, x, y, z]; the last part ends the tuple."""
    widths = (("time", 1), ("motor_position", n), ("motor_velocity", n), ("cable_tension", n),
              ("swivel_angle", n), ("unstretched_lengths", n), ("xg", 3), ("q", 4))
    parts, at = {}, 0
    for name, width in widths:
        parts[name] = slice(at, at + width)
        at += width
    return parts


class CablePhysics:
    """The simulated prototype (implements ``sim_backend.plant.Plant``).

    ``robot`` is the TRUE robot (hidden effects on geometry, mass and centre of mass already applied);
    ``transmission`` (n,) the true m of cable per rad of motor; ``pose`` the initial pose (6,) and
    ``tensions`` (n,) the tensions in which the platform starts at rest (the initial unstretched lengths
    are chosen so that those tensions hold there: start at a static equilibrium to start at rest).
    """

    def __init__(
        self,
        robot: Robot,
        params: PhysicsParams,
        transmission: np.ndarray,
        pose: np.ndarray,
        tensions: np.ndarray,
        brakes: bool = True,
        sway: Sway | None = None,
    ):
        n = robot.n
        self.n = n
        self.robot = robot
        self.params = params
        self._t = 0.0
        self._k = [float(x) for x in np.asarray(transmission, float).reshape(n)]
        self._d = robot.d.tolist()
        self._fr = robot.frames.tolist()
        self._r = robot.r.tolist()
        self._com = robot.com.tolist()
        self._rb = (robot.a_local - robot.com).tolist()  # anchors relative to G, platform frame
        self._m = float(robot.mass)
        self._g = float(robot.gravity)
        ib = np.asarray(robot.inertia, float)
        self._ib = ib.tolist()
        self._ibinv = np.linalg.inv(ib).tolist()
        self._ea = float(params.ea)
        self._w = float(params.cable_density) * self._g  # cable weight per length, N/m
        self._mu, self._fric = float(params.pulley_mu), float(params.pulley_friction)
        self._z = [0.0] * n  # pulley-friction state: +1 paid out, -1 reeled in, 0 not yet moved
        self._ext = [0.0] * n  # the extreme of the cable's paid-out length since the last reversal, m
        w = params.winch
        self._jm = [w.inertia_at_motor(k) for k in self._k]
        self._bm, self._fc, self._ws = w.viscous, w.coulomb, w.coulomb_speed
        self._fs = max(w.stiction, w.coulomb)  # N m, the torque that breaks a stuck winch free
        self._stick = w.stiction > 0.0  # the stick phase (else the regularised friction of before)
        # state
        pose = np.asarray(pose, float).reshape(6)
        rot = rotation(pose[3:], robot.orientation)[0]
        xg = pose[:3] + rot @ robot.com
        self._xg = xg.tolist()
        self._q = _quat_from_matrix(rot)
        self._v = [0.0, 0.0, 0.0]
        self._wb = [0.0, 0.0, 0.0]
        self._th = [0.0] * n
        self._thd = [0.0] * n
        self._u = [0.0] * n
        self._brake = [bool(brakes)] * n
        self._stuck = [bool(w.stiction > 0.0)] * n  # winches held still by their friction: at rest at first
        tensions = [float(x) for x in np.asarray(tensions, float).reshape(n)]
        self._tau = list(tensions)
        self._tau_cell = list(tensions)
        geo = self._geometry()
        self._l00 = [0.0] * n
        for i in range(n):
            length = geo[i][0] + geo[i][5]
            self._l00[i] = length * self._ea / (self._ea + tensions[i]) if tensions[i] > 0 else length
        self._geo = self._geometry()
        self._tau_cell = self._cell_tensions(self._geo, self._tau)
        if not brakes:
            self._u = [-self._k[i] * tensions[i] for i in range(n)]
        # the sway's force amplitude: the cables' lateral stiffness at power-on (sum tau_i / l_i) times its
        # position amplitude
        stiffness = sum(t / g[0] for t, g in zip(tensions, geo, strict=True) if t > 0)
        self._sway = None if sway is None or sway.amplitude <= 0 else sway.forces(stiffness * sway.amplitude)

    def push(self, t: float) -> tuple[float, float]:
        """The sway's horizontal push (fx, fy) N on the platform at sim time t (s); (0, 0) without a sway."""
        return (0.0, 0.0) if self._sway is None else self._sway(t)

    # --- Plant protocol -------------------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Simulated time since power-on, s."""
        return self._t

    def motor_position(self) -> np.ndarray:
        return np.array(self._th)

    def motor_velocity(self) -> np.ndarray:
        return np.array(self._thd)

    def motor_torque(self) -> np.ndarray:
        return np.array(self._u)

    def set_motor_torque(self, i: int, torque: float) -> None:
        self._u[i] = float(torque)

    def cable_tension(self) -> np.ndarray:
        """(n,) true tension at the load cells (pulley end), N."""
        return np.array(self._tau_cell)

    def swivel_angle(self) -> np.ndarray:
        return np.array([g[4] for g in self._geo])

    def orientation(self) -> np.ndarray:
        return np.array(self.euler())

    # --- beyond the protocol --------------------------------------------------------------------------
    def euler(self) -> tuple[float, float, float]:
        """Roll, pitch, yaw (rad) in the robot's convention, as plain floats."""
        return _euler(_quat_to_matrix(self._q), self.robot.orientation)

    def set_brake(self, i: int, engaged: bool) -> None:
        """Engage (motor shaft locked) or release the holding brake of winch i."""
        self._brake[i] = bool(engaged)
        self._thd[i] = 0.0 if engaged else self._thd[i]
        self._stuck[i] = self._stick and (self._stuck[i] or engaged)  # released: turns once it beats the stiction

    def brake(self, i: int) -> bool:
        return self._brake[i]

    def slip_cable(self, i: int, length: float) -> None:
        """Fault: cable i slips on its drum by ``length`` m (its unstretched length grows: it goes slack)."""
        self._l00[i] += float(length)

    def rezero(self) -> None:
        """Power-on here: the clock and the motor angles restart from 0 (the cables keep their lengths)."""
        for i in range(self.n):
            self._l00[i] += self._k[i] * self._th[i]
        self._th = [0.0] * self.n
        self._t = 0.0

    def pose(self) -> np.ndarray:
        """The true pose (6,) [x, y, z, roll, pitch, yaw] of the platform frame, m and rad."""
        return np.array(pose_of(self._xg, self._q, self._com, self.robot.orientation))

    def cable_lengths(self) -> np.ndarray:
        """(n,) true geometric cable lengths from drum exit over the pulley to the anchor (with sag), m."""
        return np.array([g[0] + g[5] for g in self._geo])

    def unstretched_lengths(self) -> np.ndarray:
        """(n,) unstretched lengths l0 paid out by the winches, m."""
        return np.array([self._l00[i] + self._k[i] * self._th[i] for i in range(self.n)])

    def chord_tension(self) -> np.ndarray:
        """(n,) cable tension along the straight segment (at the anchor for massless cables), N."""
        return np.array(self._tau)

    def snapshot(self) -> tuple[float, ...]:
        """The state the devices read, as one flat tuple laid out as :func:`snapshot_parts` says."""
        n, k, th = self.n, self._k, self._th
        return (self._t, *th, *self._thd, *self._tau_cell, *[g[4] for g in self._geo],
                *[self._l00[i] + k[i] * th[i] for i in range(n)], *self._xg, *self._q)

    def state(self) -> PhysicsState:
        return PhysicsState(self._t, self.pose(), self.motor_position(), self.cable_tension())

    def energy(self) -> float:
        """Mechanical energy, J: kinetic + gravity + cable strain - work of the (constant) motor torques."""
        m = self._m
        ke = 0.5 * m * sum(x * x for x in self._v)
        ib, wb = self._ib, self._wb
        ke += 0.5 * sum(wb[a] * sum(ib[a][b] * wb[b] for b in range(3)) for a in range(3))
        ke += 0.5 * sum(j * x * x for j, x in zip(self._jm, self._thd, strict=True))
        pe = m * self._g * self._xg[2]
        for i in range(self.n):
            l0 = self._l00[i] + self._k[i] * self._th[i]
            e = self._geo[i][0] + self._geo[i][5] - l0
            if e > 0:
                pe += 0.5 * self._ea / l0 * e * e
            pe -= self._u[i] * self._th[i]
        return ke + pe

    # --- geometry -------------------------------------------------------------------------------------
    def _geometry(self) -> list[tuple]:
        """Per cable: (length over pulley, t (3), tb (3) in body, jw (3), swivel, sag extra, dz)."""
        qw, qx, qy, qz = self._q
        r00 = 1 - 2 * (qy * qy + qz * qz)
        r01 = 2 * (qx * qy - qw * qz)
        r02 = 2 * (qx * qz + qw * qy)
        r10 = 2 * (qx * qy + qw * qz)
        r11 = 1 - 2 * (qx * qx + qz * qz)
        r12 = 2 * (qy * qz - qw * qx)
        r20 = 2 * (qx * qz - qw * qy)
        r21 = 2 * (qy * qz + qw * qx)
        r22 = 1 - 2 * (qx * qx + qy * qy)
        xg0, xg1, xg2 = self._xg
        w = self._w
        out = []
        for i in range(self.n):
            b0, b1, b2 = self._rb[i]
            d = self._d[i]
            q0 = xg0 + r00 * b0 + r01 * b1 + r02 * b2 - d[0]
            q1 = xg1 + r10 * b0 + r11 * b1 + r12 * b2 - d[1]
            q2 = xg2 + r20 * b0 + r21 * b1 + r22 * b2 - d[2]
            fi, fj, fk = self._fr[i]
            qi = q0 * fi[0] + q1 * fi[1] + q2 * fi[2]
            qj = q0 * fj[0] + q1 * fj[1] + q2 * fj[2]
            qk = q0 * fk[0] + q1 * fk[1] + q2 * fk[2]
            sw = math.atan2(qj, qi)
            r = self._r[i]
            if r > 0.0:
                ru = math.hypot(qi, qj)
                cs, ss = qi / ru, qj / ru
                ratio = qk / ru
                psi = 2.0 * math.atan(ratio + math.sqrt(ratio * ratio + 1.0 - 2.0 * r / ru))
                cp, sp = math.cos(psi), math.sin(psi)
                # u + nv in the local frame: (1 + cp) u + sp k, with u = cs i + ss j
                a_ = r * (1.0 + cp)
                c_ = r * sp
                ri = qi - a_ * cs
                rj = qj - a_ * ss
                rk = qk - c_
                arc = r * (math.pi - psi)
                rho0 = ri * fi[0] + rj * fj[0] + rk * fk[0]
                rho1 = ri * fi[1] + rj * fj[1] + rk * fk[1]
                rho2 = ri * fi[2] + rj * fj[2] + rk * fk[2]
            else:
                arc = 0.0
                rho0, rho1, rho2 = q0, q1, q2
            lc = math.sqrt(rho0 * rho0 + rho1 * rho1 + rho2 * rho2)
            t0, t1, t2 = rho0 / lc, rho1 / lc, rho2 / lc
            # body-frame direction and moment arm
            tb0 = r00 * t0 + r10 * t1 + r20 * t2
            tb1 = r01 * t0 + r11 * t1 + r21 * t2
            tb2 = r02 * t0 + r12 * t1 + r22 * t2
            jw = (b1 * tb2 - b2 * tb1, b2 * tb0 - b0 * tb2, b0 * tb1 - b1 * tb0)
            sag = 0.0
            if w > 0.0:
                tau = max(self._tau[i], 1.0)
                cos2 = (rho0 * rho0 + rho1 * rho1) / (lc * lc)
                sag = w * w * lc * lc * lc * cos2 / (24.0 * tau * tau)
            out.append((lc + arc, (t0, t1, t2), (tb0, tb1, tb2), jw, sw, sag, -rho2, lc))
        return out

    def _cell_tensions(self, geo: list[tuple], tau: list[float]) -> list[float]:
        w = self._w
        out = list(tau) if w == 0.0 else [tau[i] + 0.5 * w * geo[i][6] if tau[i] > 0.0 else 0.0
                                          for i in range(self.n)]
        if self._mu or self._fric:  # the cell is on the winch side of the pulleys
            mu, f, z = self._mu, self._fric, self._z
            out = [max(t * (1.0 - z[i] * mu) - z[i] * f, 0.0) if t > 0.0 else 0.0 for i, t in enumerate(out)]
        return out

    # --- integration ----------------------------------------------------------------------------------
    def step(self, dt: float, t_end: float | None = None) -> None:
        """Advance the simulation by dt seconds (``params.substeps`` substeps).

        ``t_end``: the exact time to read afterwards (a lockstep caller passes count * period, so that the
        clock does not drift off the grid by summing dt: sensors schedule samples on that grid).
        """
        ns = self.params.substeps
        h = dt / ns
        for _ in range(ns):
            self._substep(h)
        if t_end is not None:
            self._t = float(t_end)
        if not all(map(math.isfinite, self._xg)) or not all(map(math.isfinite, self._tau)):
            raise SimulationError(f"the simulated platform diverged at t = {self._t:.3f} s (unstable commands?).")

    def _substep(self, h: float) -> None:
        """Advance the state by h s: free velocities from the explicit forces, cable tensions from the implicit
        cable-space solve (again without a stuck winch whose net torque breaks it free), their impulses, then
        the winches that stick, the positions, the geometry and the load-cell tensions."""
        n = self.n
        m = self._m
        geo = self._geo
        k = self._k
        vs0, vs1, vs2, ws0, ws1, ws2 = self._free_body_velocities(h)
        (j00, j01, j02), (j10, j11, j12), (j20, j21, j22) = self._ibinv
        # per cable: the body-frame rotation response I^-1 jw, and the right-hand side K e / S + J v* (its body
        # part here, the winch's with each solve)
        ea = self._ea
        p = self.params
        sc = p.stiff_theta * h + p.cable_damping  # s, S = K * sc
        ijw = []
        inv_s = []
        rhs_body = []
        for i, (g, l00, th) in enumerate(zip(geo, self._l00, self._th, strict=True)):
            (t0, t1, t2), (jw0, jw1, jw2) = g[1], g[3]
            l0 = l00 + k[i] * th
            kc = ea / l0
            stretch = g[0] + g[5] - l0
            if g[5] > 0.0:
                # the sag shortens as the tension grows (d sag / d tau = -2 sag / tau): taken into the implicit
                # solve, linearised at the last tension, it gives Ernst's equivalent stiffness
                # kc / (1 + kc 2 sag / tau). Left explicit it is a loop of gain kc 2 sag / tau (6 for a 0.08 kg/m
                # cable at 44 N), which threw the platform off its cables
                tau0 = max(self._tau[i], 1.0)  # the tension the sag was computed with (_geometry)
                slope = 2.0 * g[5] / tau0
                stretch += slope * tau0
                kc = kc / (1.0 + kc * slope)
            s = kc * sc
            rhs_body.append((kc * stretch / s, t0 * vs0 + t1 * vs1 + t2 * vs2 + jw0 * ws0 + jw1 * ws1 + jw2 * ws2))
            inv_s.append(1.0 / s)
            ijw.append((j00 * jw0 + j01 * jw1 + j02 * jw2, j10 * jw0 + j11 * jw1 + j12 * jw2,
                        j20 * jw0 + j21 * jw1 + j22 * jw2))
        # (S^-1 + h D) with D = J M^-1 J^T + K Jm^-1 K, the cable-space inverse inertia (symmetric): the body
        # part here, the winches' diagonal with each solve
        vals = [[0.0] * n for _ in range(n)]
        for i in range(n):
            (t0, t1, t2), (jw0, jw1, jw2) = geo[i][1], geo[i][3]
            row = vals[i]
            for j in range(i, n):
                (u0, u1, u2), (q0, q1, q2) = geo[j][1], ijw[j]
                row[j] = vals[j][i] = (t0 * u0 + t1 * u1 + t2 * u2) / m + (jw0 * q0 + jw1 * q1 + jw2 * q2)
        stuck, fc, fs, u = self._stuck, self._fc, self._fs, self._u
        while True:
            thds, minv = self._free_motor_velocities(h)
            rhs = [a_ + (b_ - k[i] * thds[i]) for i, (a_, b_) in enumerate(rhs_body)]
            a = [[h * v for v in row] for row in vals]
            for i in range(n):
                a[i][i] = h * (vals[i][i] + k[i] * k[i] * minv[i]) + inv_s[i]
            tau = _active_set_solve(a, rhs)
            freed = [i for i in range(n) if stuck[i] and abs(u[i] + k[i] * tau[i]) > fs]
            if not freed:
                break
            for i in freed:  # the friction cannot hold it: it slides from this substep on
                stuck[i] = False
        # velocity update with the cable impulses
        for i, ti in enumerate(tau):
            if ti == 0.0:
                continue
            t = geo[i][1]
            ij = ijw[i]
            c = h * ti
            vs0 -= c * t[0] / m
            vs1 -= c * t[1] / m
            vs2 -= c * t[2] / m
            ws0 -= c * ij[0]
            ws1 -= c * ij[1]
            ws2 -= c * ij[2]
            thds[i] += c * minv[i] * k[i]
        ws_, before = self._ws, self._thd
        for i in range(n if self._stick else 0):  # a winch that stops or turns back, its net torque held, sticks
            if minv[i] and (abs(thds[i]) < ws_ or thds[i] * before[i] < 0.0) and abs(u[i] + k[i] * tau[i]) <= fc:
                stuck[i] = True
                thds[i] = 0.0
        self._v = [vs0, vs1, vs2]
        self._wb = [ws0, ws1, ws2]
        self._thd = thds
        xg = self._xg
        self._xg = [xg[0] + h * vs0, xg[1] + h * vs1, xg[2] + h * vs2]
        self._th = [th + h * thd for th, thd in zip(self._th, thds, strict=True)]
        if self._mu or self._fric:
            for i in range(n):
                self._z[i], self._ext[i] = play(k[i] * self._th[i], self._z[i], self._ext[i], FRICTION_SLIDE)
        self._q = _quat_integrate(self._q, ws0 * h, ws1 * h, ws2 * h)
        self._t += h
        self._tau = tau
        self._geo = self._geometry()
        self._tau_cell = self._cell_tensions(self._geo, tau)

    def _free_body_velocities(self, h: float) -> tuple[float, float, float, float, float, float]:
        """Platform velocity (m/s, 3) and body-frame angular velocity (rad/s, 3) after h s of the explicit forces
        (gravity, damping, sag loads, gyroscopic moment), before the cable impulses."""
        p = self.params
        m = self._m
        (i00, i01, i02), (i10, i11, i12), (i20, i21, i22) = self._ib
        (j00, j01, j02), (j10, j11, j12), (j20, j21, j22) = self._ibinv
        v0, v1, v2 = self._v
        w0, w1, w2 = self._wb
        cl, ca = p.linear_damping, p.angular_damping
        f0, f1, f2 = -cl * v0, -cl * v1, -cl * v2 - m * self._g
        if self._sway is not None:
            sx, sy = self._sway(self._t)
            f0 += sx
            f1 += sy
        iw0 = i00 * w0 + i01 * w1 + i02 * w2
        iw1 = i10 * w0 + i11 * w1 + i12 * w2
        iw2 = i20 * w0 + i21 * w1 + i22 * w2
        mb0 = -(w1 * iw2 - w2 * iw1) - ca * w0
        mb1 = -(w2 * iw0 - w0 * iw2) - ca * w1
        mb2 = -(w0 * iw1 - w1 * iw0) - ca * w2
        if self._w > 0.0:
            geo = self._geo
            rmat = _quat_to_matrix(self._q)
            for i in range(self.n):
                if self._tau[i] <= 0.0:
                    continue
                fz = -0.5 * self._w * geo[i][7]  # half the cable weight hangs on the anchor
                f2 += fz
                # body-frame force = R^T (0, 0, fz)
                fb0, fb1, fb2 = rmat[2][0] * fz, rmat[2][1] * fz, rmat[2][2] * fz
                b0, b1, b2 = self._rb[i]
                mb0 += b1 * fb2 - b2 * fb1
                mb1 += b2 * fb0 - b0 * fb2
                mb2 += b0 * fb1 - b1 * fb0
        return (v0 + h * f0 / m, v1 + h * f1 / m, v2 + h * f2 / m,
                w0 + h * (j00 * mb0 + j01 * mb1 + j02 * mb2),
                w1 + h * (j10 * mb0 + j11 * mb1 + j12 * mb2),
                w2 + h * (j20 * mb0 + j21 * mb1 + j22 * mb2))

    def _free_motor_velocities(self, h: float) -> tuple[list[float], list[float]]:
        """Motor velocities (n,) rad/s after h s of torque, Coulomb friction against the motion (against the
        last net torque for a motor just freed) and implicit viscous friction, before the cable impulses, and
        the inverse effective inertias (n,) 1/(kg m^2); both 0 for a braked (locked) or a stuck motor."""
        bm, fc = self._bm, self._fc
        thds = []
        minv = []
        for i, (x, u, jm, brake, stuck) in enumerate(zip(self._thd, self._u, self._jm, self._brake, self._stuck,
                                                        strict=True)):
            if brake or stuck:
                thds.append(0.0)
                minv.append(0.0)
                continue
            if not self._stick:  # the friction of before: Coulomb regularised, linearly implicit, no stick
                th_ = math.tanh(x / self._ws)
                jeff = jm + h * (bm + fc / self._ws * (1.0 - th_ * th_))
                thds.append(x + h * (u - (bm * x + fc * th_)) / jeff)
                minv.append(1.0 / jeff)
                continue
            way = x if x != 0.0 else u + self._k[i] * self._tau[i]
            fric = fc if way > 0.0 else -fc if way < 0.0 else 0.0
            jeff = jm + h * bm
            thds.append(x + h * (u - bm * x - fric) / jeff)
            minv.append(1.0 / jeff)
        return thds, minv

def _quat_to_matrix(q: list[float]) -> list[list[float]]:
    qw, qx, qy, qz = q
    return [
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
        [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
        [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)],
    ]


def _euler(r: list[list[float]], convention: str) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad) of a rotation matrix given as rows of floats (as calib.kinematics.rotation_to_euler);
    also the AHRS emulator's."""
    if convention == "xyz":
        return (
            math.atan2(-r[1][2], r[2][2]),
            math.asin(max(-1.0, min(1.0, r[0][2]))),
            math.atan2(-r[0][1], r[0][0]),
        )
    if convention == "zyx":
        return (
            math.atan2(r[2][1], r[2][2]),
            math.asin(max(-1.0, min(1.0, -r[2][0]))),
            math.atan2(r[1][0], r[0][0]),
        )
    raise ValueError(f"unknown orientation convention {convention!r}")


def pose_of(xg, q, com, convention: str) -> list[float]:
    """Pose [x, y, z, roll, pitch, yaw] of the platform frame from G's position, the quaternion and com."""
    r = _quat_to_matrix(q)
    p = [xg[a] - (r[a][0] * com[0] + r[a][1] * com[1] + r[a][2] * com[2]) for a in range(3)]
    return p + list(_euler(r, convention))


def _quat_from_matrix(r: np.ndarray) -> list[float]:
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax([r[0, 0], r[1, 1], r[2, 2]]))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    nq = math.sqrt(sum(x * x for x in q))
    return [float(x) / nq for x in q]


def _quat_integrate(q: list[float], a0: float, a1: float, a2: float) -> list[float]:
    """q * exp(a / 2) for a body-frame rotation vector a (rad), renormalised."""
    ang = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    if not ang < 1e3:
        return [math.nan] * 4
    if ang < 1e-12:
        dw, dx, dy, dz = 1.0, 0.5 * a0, 0.5 * a1, 0.5 * a2
    else:
        sh = math.sin(0.5 * ang) / ang
        dw, dx, dy, dz = math.cos(0.5 * ang), a0 * sh, a1 * sh, a2 * sh
    qw, qx, qy, qz = q
    rw = qw * dw - qx * dx - qy * dy - qz * dz
    rx = qw * dx + qx * dw + qy * dz - qz * dy
    ry = qw * dy - qx * dz + qy * dw + qz * dx
    rz = qw * dz + qx * dy - qy * dx + qz * dw
    nq = 1.0 / math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
    return [rw * nq, rx * nq, ry * nq, rz * nq]


def transmission_of(robot: Robot) -> np.ndarray:
    """Nominal transmission (n,) m of cable per rad of motor from ``robot.sensors.length_per_motor_rev``."""
    lpr = robot.sensors.length_per_motor_rev
    if len(lpr) != robot.n:
        raise ValueError(
            f"robot '{robot.name}': field 'sensors.length_per_motor_rev' = {list(lpr)!r} must give one value "
            f"per cable ({robot.n}) for the simulator."
        )
    return np.asarray(lpr, float) / (2.0 * math.pi)
