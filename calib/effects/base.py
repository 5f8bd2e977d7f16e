"""The effect protocol and the model that composes effects around the rigid-body measurement model.

An effect is a physical phenomenon the rigid model of Zoffoli eq. 8-13 leaves out. It declares its
parameters (:class:`ParamSpec`: name, unit, the value meaning "absent", bounds) and acts at one of two
stages:

* ``robot`` effects change the robot description itself (pulley radii and positions, centre of mass, mass):
  ``modify(robot, values) -> Robot``; the physical quantities (cable lengths L, swivel angles, modelled
  tensions) are recomputed with it; ``physical_columns`` gives dL/dq, dsigma/dq and dtau/dq (k, n, q) at k
  poses (default: forward differences; built-in effects analytic, or exact where the dependence is linear).
* ``reading`` effects change what a sensor reports of the physical quantities (cable elasticity between
  the motor encoder and the geometric length, transmission ratio errors, load-cell offsets and gains, the
  AHRS mounting): ``transform(ctx, values, preds)`` edits the channel predictions in place, value, pose
  derivatives and theta derivatives alike (chain rule), and fills its own theta columns ``ctx.cols``.
  Reading effects run in ``order`` (physical before sensor), each on the output of the previous one.

:class:`EffectModel` wraps a robot with a list of effects and has the interface of
``calib.selfcal.model.MeasurementModel`` (``param_names``, ``initial_params``, ``predict``,
``absolute_readings``), so ``calib.selfcal.problem.Problem`` and the LM solver use it unchanged: theta is
[zeta_0 (6), the first effect's parameters, the second's, ...].
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from calib.kinematics import convert_euler, inverse_kinematics, kinematic_jacobians
from calib.robot import Robot
from calib.selfcal import model as rigid
from calib.selfcal.model import CHANNELS, ChannelPrediction, encoder_lengths, held_tensions, orientation_prediction
from calib.statics import tension_model


@dataclass(frozen=True)
class ParamSpec:
    """One effect parameter: name, unit, the value meaning the effect is absent, bounds, a typical size
    (used for finite-difference steps and for reporting), optionally the standard deviation of a
    Gaussian prior centred on ``absent`` (what a datasheet says of a device's constant error; None: free),
    and the physically plausible range (lo, hi) of the value: a fit that leaves it is no explanation (the
    diagnosis never recommends it); each built-in effect says in a comment where its range comes from."""

    name: str
    unit: str
    absent: float = 0.0
    lower: float = -np.inf
    upper: float = np.inf
    scale: float = 1.0
    prior: float | None = None
    plausible: tuple[float, float] = (-np.inf, np.inf)


@dataclass
class Implausible:
    """A fitted value outside its plausible range: ``effect.param`` = value (unit), range (lo, hi)."""

    param: str
    value: float
    unit: str
    lo: float
    hi: float

    def __str__(self) -> str:
        if self.unit == "rad":
            return (f"{self.param} = {np.degrees(self.value):.3g} deg outside [{np.degrees(self.lo):.3g}, "
                    f"{np.degrees(self.hi):.3g}] deg")
        unit = "" if self.unit == "1" else f" {self.unit}"
        return f"{self.param} = {self.value:.4g}{unit} outside [{self.lo:.4g}, {self.hi:.4g}]{unit}"


@dataclass
class Physical:
    """Absolute physical quantities at k poses with the current robot: cable lengths L (k, n) m as the
    encoders count them (unstretched by the robot's axial stiffness: calib.selfcal.model.encoder_lengths),
    swivel angles (k, n) rad, modelled tensions tau (k, n) N; their pose derivatives (k, n, 6) and theta
    derivatives (k, n, p) (robot-effect columns; zeta_0 columns are zero here)."""

    L: np.ndarray
    sigma: np.ndarray
    tau: np.ndarray
    dL: np.ndarray
    dsigma: np.ndarray
    dtau: np.ndarray
    tL: np.ndarray
    tsigma: np.ndarray
    ttau: np.ndarray
    ahrs: np.ndarray | None = None  # (k, 3) the orientations in the AHRS's convention, rad
    dahrs: np.ndarray | None = None  # (k, 3, 3) their derivatives with respect to the poses' angles
    terms: dict | None = None  # effect name -> its per-pose terms (``Effect.pose_terms``), all rows at once
    derivatives: bool = True  # False: the derivatives are zero (computed for residuals only, no Jacobian)


@dataclass
class Context:
    """What a reading effect sees: the robot (robot effects applied), the poses (k, 6), theta (p,), the
    columns of theta that are its own (``cols``), the physical quantities at the poses (``at``) and at
    zeta_0 (``ref``, whose theta derivatives include the zeta_0 columns), and the times of the rows (k,),
    s after the reference sample (None where the readings carry no times), and the directions of the rows
    (k, n, 4): [..., 0] the way each cable last moved before the row (+1 paid out, -1 reeled in), [..., 1]
    the way its tension last changed (+1 rising, -1 falling), [..., 2] the way its swivel last turned (+1 up),
    [..., 3] the way it last turned before the reference sample; 0 or None: unknown (older callers pass the
    first two only). ``robot_cols``: the theta columns of the robot effects, and ``robot_at(theta)`` the robot
    with them at theta, for a reading effect whose edit depends on the geometry they change (None: no columns)."""

    robot: Robot
    poses: np.ndarray
    theta: np.ndarray
    cols: slice
    at: Physical
    ref: Physical
    times: np.ndarray | None = None
    approach: np.ndarray | None = None
    robot_cols: tuple[int, ...] = ()
    robot_at: Callable[[np.ndarray], Robot] | None = None


class Effect:
    """Base class of an effect. Subclasses set ``name``, ``stage`` ('robot' or 'reading'), ``order``
    (reading effects: lower runs first; elasticity 10, length scale 20, load cells 30, AHRS 40) and
    ``params(robot) -> list[ParamSpec]``, and implement ``modify`` (robot stage) or ``transform`` (reading
    stage). ``report(values)`` turns fitted values into the reported parameters (default: by name)."""

    name: str = ""
    stage: str = "reading"
    order: int = 50
    description: str = ""
    fd_steps: float = 1e-6  # relative to each parameter's scale
    # an effect editing the physical quantities (Context.at/ref), not readings: absolute_readings runs it at zeta_0
    edits_physical: bool = False
    # the effect's readings of other channels use the modelled tensions (``Context.at.tau``, e.g. a stretch):
    # a model predicting no tension skips the statics only when none of its reading effects does
    reads_tension: bool = True

    def params(self, robot: Robot) -> list[ParamSpec]:
        raise NotImplementedError

    def modify(self, robot: Robot, values: np.ndarray) -> Robot:
        """Robot stage: the robot as it is with these parameter values."""
        raise NotImplementedError

    def physical_columns(
        self, robot: Robot, values: np.ndarray, poses: np.ndarray, recompute
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Robot stage: dL/dq, dsigma/dq, dtau/dq (k, n, q) at the poses. ``recompute(values)`` returns the
        (L, sigma, tau) arrays with this effect's values replaced (everything else fixed). Default: forward
        differences of relative step ``fd_steps`` (q + 1 evaluations; the truncation error, of the order of
        the step, is far below the rounding error of a step of 1e-6 of a parameter's typical size)."""
        specs = self.params(robot)
        cols = [[], [], []]
        base = base_quantities(recompute, values)
        for j, s in enumerate(specs):
            h = self.fd_steps * s.scale
            vp = values.copy()
            vp[j] += h
            plus = recompute(vp)
            for c in range(3):
                diff = plus[c] - base[c]
                cols[c].append((np.angle(np.exp(1j * diff)) if c == 1 else diff) / h)
        return tuple(np.stack(c, axis=-1) for c in cols)

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        """Reading stage: change ``preds`` in place (values, d_pose, d_theta; fill d_theta[..., ctx.cols])."""
        raise NotImplementedError

    def pose_terms(self, robot: Robot, poses: np.ndarray):
        """Reading stage: what ``transform`` needs that depends on the robot and the poses (k, 6) only, as a
        dataclass of arrays with k leading rows (``Context.at.terms[name]``): computed with the physical
        quantities, for every row at once (several runs' rows in one call); None: nothing."""
        return None

    def absolute_length(self, ref: Physical, values: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """Reading stage: the absolute length (n,) the encoders count at zeta_0, given the geometric (or
        previously transformed) one; default unchanged."""
        return lengths

    def absolute_swivel(self, ref: Physical, values: np.ndarray, swivel: np.ndarray) -> np.ndarray:
        """Reading stage: the absolute swivel angles (n,) rad the encoders show at zeta_0, given the geometric
        (or previously transformed) ones; default unchanged."""
        return swivel

    def absolute_yaw(self, robot: Robot, zeta0: np.ndarray, values: np.ndarray, yaw: float) -> float:
        """Reading stage: the absolute yaw (rad, the AHRS's convention) the AHRS shows at zeta_0, given the one
        of the platform's own orientation; default unchanged."""
        return yaw

    def report(self, robot: Robot, values: np.ndarray) -> dict[str, float]:
        """Reported parameters, e.g. ``{"EA": 15020.0}`` (default: the parameters by name)."""
        return {s.name: float(v) for s, v in zip(self.params(robot), values, strict=True)}

    def implausible(self, robot: Robot, values: np.ndarray) -> list[Implausible]:
        """The parameters whose value lies outside its plausible range (``ParamSpec.plausible``)."""
        return [Implausible(f"{self.name}.{s.name}", float(v), s.unit, *s.plausible)
                for s, v in zip(self.params(robot), values, strict=True)
                if not s.plausible[0] <= v <= s.plausible[1]]


def add_tension_offsets(cols: slice, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
    """Load cell i reads tau_i + values_i (N): the tension prediction shifted, its theta columns ``cols``
    the identity (what TensionOffset and the devices' priors share)."""
    if "tension" not in preds:
        return
    pr = preds["tension"]
    pr.value = pr.value + values[None]
    pr.d_theta[..., cols] = np.eye(values.shape[0])[None]


def base_quantities(recompute, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(L, sigma, tau) at the effect's own values: those the model computed already when ``recompute``
    carries them (``recompute.base``), else recomputed."""
    base = getattr(recompute, "base", None)
    return recompute(values) if base is None else base


def physical(robot: Robot, poses: np.ndarray, p: int, tension: bool = True, held: np.ndarray | None = None,
             derivatives: bool = True) -> Physical:
    """L, swivel and modelled tensions with pose derivatives at poses (k, 6) (zero without ``derivatives``: the
    same values, no Jacobians); theta columns zero (p). Without ``tension`` the tensions and derivatives are
    NaN (no statics). ``held``: calib.selfcal.model.held_tensions."""
    kin = inverse_kinematics(robot, poses)
    k, n = kin.lengths.shape
    jac = kinematic_jacobians(robot, kin) if derivatives else None
    dL, ds = (np.zeros((k, n, 6)), np.zeros((k, n, 6))) if jac is None else (jac.lengths, jac.swivel)
    if tension or np.any(robot.compliance):  # an elastic cable's encoder length needs its tension
        tm = tension_model(robot, kin=kin, jac=jac, derivatives=derivatives)
        tau, dtau = tm.tau, tm.jacobian if derivatives else np.zeros((k, n, 6))
    else:
        tau, dtau = np.full((k, n), np.nan), np.full((k, n, 6), np.nan)
    tau, dtau = held_tensions(tau, dtau, held)
    z = np.zeros((k, n, p))
    ahrs, dahrs = convert_euler(kin.poses[:, 3:], robot.orientation, robot.ahrs_convention, kin.R, kin.H)
    L, dL = encoder_lengths(robot, kin.lengths, tau, dL, dtau)
    return Physical(L, kin.swivel, tau, dL, ds, dtau, z, z.copy(), z.copy(), ahrs, dahrs, derivatives=derivatives)


def _dataclass_rows(d, rows: slice):
    """A dataclass of arrays with the poses first, at some of the poses (views; None stays None)."""
    return type(d)(*(None if (v := getattr(d, f.name)) is None else v[rows] for f in dataclasses.fields(d)))


def physical_rows(ph: Physical, rows: slice) -> Physical:
    """The physical quantities of some of the poses (views), the effects' pose terms included."""
    a, t = ph.ahrs is not None, ph.terms
    return Physical(ph.L[rows], ph.sigma[rows], ph.tau[rows], ph.dL[rows], ph.dsigma[rows], ph.dtau[rows],
                    ph.tL[rows], ph.tsigma[rows], ph.ttau[rows], ph.ahrs[rows] if a else None,
                    ph.dahrs[rows] if a else None,
                    None if t is None else {n: _dataclass_rows(v, rows) for n, v in t.items()}, ph.derivatives)


def wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi]."""
    return np.angle(np.exp(1j * a))


class EffectModel:
    """The rigid-body measurement model with effects composed around it (interface of MeasurementModel).

    ``values`` of every effect start at their ``absent`` values (``initial_params``); theta is zeta_0 then
    the effects' parameters in the order given.
    """

    def __init__(self, robot: Robot, effects: Sequence[Effect] = ()):
        self.robot = robot
        self.effects = list(effects)
        names = [e.name for e in self.effects]
        if len(set(names)) != len(names):
            raise ValueError(f"effect listed twice in {', '.join(names)}")
        self.specs: list[list[ParamSpec]] = [e.params(robot) for e in self.effects]
        self.slices: list[slice] = []
        start = 6
        for s in self.specs:
            self.slices.append(slice(start, start + len(s)))
            start += len(s)
        self._p = start
        self._robot_cols = tuple(j for e, sl in zip(self.effects, self.slices, strict=True) if e.stage == "robot"
                                 for j in range(sl.start, sl.stop))

    @property
    def param_names(self) -> tuple[str, ...]:
        """zeta_0's six coordinates, then ``effect.param`` for every effect parameter."""
        out = ["x0", "y0", "z0", "roll0", "pitch0", "yaw0"]
        for e, specs in zip(self.effects, self.specs, strict=True):
            out += [f"{e.name}.{s.name}" for s in specs]
        return tuple(out)

    @property
    def n_params(self) -> int:
        return self._p

    def absent_values(self) -> np.ndarray:
        """The effect part of theta with every effect absent (p - 6,)."""
        return np.array([s.absent for specs in self.specs for s in specs], dtype=float)

    def initial_params(self, zeta0: np.ndarray, values: np.ndarray | None = None) -> np.ndarray:
        """Global vector [zeta_0, effect values] (absent values unless given)."""
        v = self.absent_values() if values is None else np.asarray(values, float)
        return np.r_[np.asarray(zeta0, float), v]

    def priors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Theta indices (q,) of the parameters with a prior, their prior means and standard deviations."""
        idx, mean, sd = [], [], []
        for sl, specs in zip(self.slices, self.specs, strict=True):
            for j, s in enumerate(specs):
                if s.prior is not None:
                    idx.append(sl.start + j)
                    mean.append(s.absent)
                    sd.append(s.prior)
        return np.array(idx, dtype=int), np.array(mean, dtype=float), np.array(sd, dtype=float)

    def report(self, theta: np.ndarray) -> dict[str, dict[str, float]]:
        """Fitted parameters of every effect, as the effects report them."""
        return {e.name: e.report(self.robot, np.asarray(theta[sl])) for e, sl in zip(self.effects, self.slices,
                                                                                        strict=True)}

    def true_robot(self, theta: np.ndarray) -> Robot:
        """The robot with every robot-stage effect applied at theta."""
        robot = self.robot
        for e, sl in zip(self.effects, self.slices, strict=True):
            if e.stage == "robot":
                robot = e.modify(robot, np.asarray(theta[sl]))
        return robot

    def needs_tension(self, channels: Sequence[str]) -> bool:
        """Whether predicting ``channels`` needs the modelled tensions (the statics)."""
        return "tension" in channels or any(e.stage == "reading" and e.reads_tension for e in self.effects)

    def _physical(self, theta: np.ndarray, poses: np.ndarray, tension: bool = True,
                  held: np.ndarray | None = None, derivatives: bool = True) -> tuple[Robot, Physical]:
        p = theta.shape[0]
        robot = self.true_robot(theta)
        ph = physical(robot, poses, p, tension, held, derivatives)
        ph.terms = {e.name: t for e in self.effects if e.stage == "reading"
                    and (t := e.pose_terms(robot, poses)) is not None}
        for idx, (e, sl) in enumerate(zip(self.effects, self.slices, strict=True)):
            if e.stage != "robot" or not derivatives:  # the robot effects' theta columns stay zero
                continue

            def recompute(vals, idx=idx, sl=sl):
                th = theta.copy()
                th[sl] = vals
                r = self.robot
                for e2, sl2 in zip(self.effects, self.slices, strict=True):
                    if e2.stage == "robot":
                        r = e2.modify(r, np.asarray(th[sl2]))
                kin = inverse_kinematics(r, poses)
                tau = held_tensions(tension_model(r, kin=kin, derivatives=False).tau, None, held)[0]
                return encoder_lengths(r, kin.lengths, tau)[0], kin.swivel, tau

            recompute.base = (ph.L, ph.sigma, ph.tau)  # at theta itself: computed above, the same way
            dL, ds, dt = e.physical_columns(robot, np.asarray(theta[sl]), poses, recompute)
            ph.tL[..., sl], ph.tsigma[..., sl], ph.ttau[..., sl] = dL, ds, dt
        return robot, ph

    def physical(self, theta: np.ndarray, poses: np.ndarray, derivatives: bool = True) -> tuple[Robot, Physical]:
        """The robot with its robot effects at theta, the physical quantities at poses (k, 6) with their pose and theta
        (p,) derivatives (zero without ``derivatives``): what ``predict`` computes at its poses and zeta_0."""
        z = np.asarray(poses, float).reshape(-1, 6)
        return self._physical(np.asarray(theta, float), z, derivatives=derivatives)

    def cable_tensions(self, theta: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """The tensions (k, n) N the statics give the cables at poses (k, 6), the robot effects at theta."""
        return rigid.statics_tensions(self.true_robot(np.asarray(theta, float)), poses)

    def predict(
        self, poses: np.ndarray, theta: np.ndarray, channels: Sequence[str], times: np.ndarray | None = None,
        approach: np.ndarray | None = None, physical: tuple[Robot, Physical] | None = None,
        held_tension: np.ndarray | None = None,
    ) -> dict[str, ChannelPrediction]:
        """Predicted readings of ``channels`` at poses (k, 6) for theta (p,), effects included; ``times`` (k,)
        s after the reference sample, for the effects that depend on time; ``approach`` (k, n, 4) the
        directions of cable motion, load change and swivel turn before each row and the reference's swivel
        turn (:class:`Context`), for the effects that depend on them;
        ``physical``: ``self.physical(theta, [poses; zeta_0])`` if already computed; ``held_tension`` (k, n) N:
        where finite, a row's cable's held tension (calib.selfcal.model.held_tensions; not with ``physical``)."""
        z = np.asarray(poses, dtype=float).reshape(-1, 6)
        theta = np.asarray(theta, dtype=float)
        k = z.shape[0]
        # the poses and zeta_0 in one call (everything is per pose): the model's geometry and statics once
        if physical is None:
            held = None if held_tension is None else np.vstack([held_tension, np.full((1, self.robot.n), np.nan)])
            physical = self._physical(theta, np.vstack([z, theta[None, :6]]), self.needs_tension(channels), held)
        robot, both = physical
        at, ref = physical_rows(both, slice(0, k)), physical_rows(both, slice(k, k + 1))
        for name in ("L", "sigma", "tau"):  # the reference pose is zeta_0 itself: fold d/dpose into theta
            getattr(ref, "t" + name)[..., :6] += getattr(ref, "d" + name)
        out: dict[str, ChannelPrediction] = {}
        for name in channels:
            if name == "tension":
                out[name] = ChannelPrediction(at.tau.copy(), at.dtau.copy(), at.ttau.copy())
            elif name == "length":
                out[name] = ChannelPrediction(at.L - ref.L, at.dL.copy(), at.tL - ref.tL)
            elif name == "swivel":
                out[name] = ChannelPrediction(wrap(at.sigma - ref.sigma), at.dsigma.copy(), at.tsigma - ref.tsigma)
            elif name == "orientation":
                out[name] = orientation_prediction(robot, z, theta, (at.ahrs, at.dahrs, ref.ahrs, ref.dahrs))
            else:
                raise ValueError(f"unknown channel {name!r} (known: {', '.join(CHANNELS)})")
        readers = sorted((i for i, e in enumerate(self.effects) if e.stage == "reading"),
                         key=lambda i: self.effects[i].order)
        for i in readers:
            ctx = Context(robot, z, theta, self.slices[i], at, ref, times, approach, self._robot_cols,
                          self.true_robot if both.derivatives else None)  # no derivatives: no robot_at columns
            self.effects[i].transform(ctx, np.asarray(theta[self.slices[i]]), out)
        return out

    def absolute_readings(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        """Absolute values of the relative sensors at the reference pose: cable lengths (n,) m as the
        encoders count them (e.g. unstretched, with cable elasticity), swivel angles (n,) rad, yaw rad in the
        AHRS's own convention (``robot.ahrs_convention``, as the rigid model's
        ``MeasurementModel.absolute_readings``: the yaw of zeta_0 is in ``robot.orientation``)."""
        robot, ref = self._physical(theta, theta[None, :6])
        order = sorted(range(len(self.effects)), key=lambda i: self.effects[i].order)
        for i in order:  # effects that edit the physical geometry act on it first (their order is lowest)
            e, values = self.effects[i], np.asarray(theta[self.slices[i]])
            if e.stage == "reading" and e.edits_physical:
                at = dataclasses.replace(ref)
                e.transform(Context(robot, theta[None, :6], theta, self.slices[i], at, dataclasses.replace(ref)),
                            values, {})
                ref = at
        lengths, swivel = ref.L[0], ref.sigma[0]
        yaw = float(convert_euler(theta[None, 3:6], robot.orientation, robot.ahrs_convention)[0][0, 2])
        for i in order:
            e, values = self.effects[i], np.asarray(theta[self.slices[i]])
            if e.stage == "reading" and not e.edits_physical:
                lengths = e.absolute_length(ref, values, lengths)
                swivel = e.absolute_swivel(ref, values, swivel)
                yaw = e.absolute_yaw(robot, theta[:6], values, yaw)
        return {"length": lengths, "swivel": swivel, "yaw": yaw}


class Projected(Effect):
    """An effect restricted to a subspace of its parameters: values = absent + B @ p (B (q, r)). Used for
    the components of an effect that a data set can observe (the others stay at their absent values)."""

    def __init__(self, inner: Effect, basis: np.ndarray, labels: Sequence[str] | None = None):
        self.inner = inner
        self.basis = np.asarray(basis, float)
        self.name = inner.name
        self.stage = inner.stage
        self.order = inner.order
        self.description = inner.description
        self.labels = list(labels) if labels is not None else [f"c{j + 1}" for j in range(self.basis.shape[1])]
        self.reads_tension = inner.reads_tension

    def _absent(self, robot: Robot) -> np.ndarray:
        return np.array([s.absent for s in self.inner.params(robot)], float)

    def full_values(self, robot: Robot, values: np.ndarray) -> np.ndarray:
        return self._absent(robot) + self.basis @ np.asarray(values, float)

    def params(self, robot: Robot) -> list[ParamSpec]:
        specs = self.inner.params(robot)
        scale = float(np.median([s.scale for s in specs]))
        return [ParamSpec(lab, "mixed", 0.0, -np.inf, np.inf, scale) for lab in self.labels]

    _override: np.ndarray | None = None

    def modify(self, robot: Robot, values: np.ndarray) -> Robot:
        full = self._override if self._override is not None else self.full_values(robot, values)
        return self.inner.modify(robot, full)

    def physical_columns(self, robot, values, poses, recompute):
        full = self.full_values(robot, values)

        def recompute_full(v):  # the inner effect perturbs its full values: evaluate them as they are
            self._override = np.asarray(v, float)
            try:
                return recompute(values)
            finally:
                self._override = None

        cols = self.inner.physical_columns(robot, full, poses, recompute_full)
        return tuple(c @ self.basis for c in cols)

    def pose_terms(self, robot: Robot, poses: np.ndarray):
        return self.inner.pose_terms(robot, poses)

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        q = self.basis.shape[0]
        p = ctx.theta.shape[0]
        for pr in preds.values():
            pr.d_theta = np.concatenate([pr.d_theta, np.zeros(pr.d_theta.shape[:2] + (q,))], axis=2)
        inner_ctx = dataclasses.replace(ctx, cols=slice(p, p + q))
        self.inner.transform(inner_ctx, self.full_values(ctx.robot, values), preds)
        for pr in preds.values():
            extra = pr.d_theta[..., p:]
            pr.d_theta = pr.d_theta[..., :p]
            pr.d_theta[..., ctx.cols] = extra @ self.basis

    def report(self, robot: Robot, values: np.ndarray) -> dict[str, float]:
        return self.inner.report(robot, self.full_values(robot, values))

    def implausible(self, robot: Robot, values: np.ndarray) -> list[Implausible]:
        return self.inner.implausible(robot, self.full_values(robot, values))

    def covariance(self, cov: np.ndarray) -> np.ndarray:
        """Covariance of the inner (full) parameters from the covariance of the projected ones."""
        return self.basis @ cov @ self.basis.T
