"""Simulation configuration (``--sim-config FILE``): hidden effects, faults and physics overrides.

The YAML file (every section optional; nothing is on by default)::

    effects:                                   # what the controller and the run log never see
      cable_elasticity: {EA: 20000.0}          # N, axial stiffness of every cable (nominal: the robot
                                               #   description's axial_stiffness, else 2e6 N)
      length_scale: {k: [0.01, 0, 0, -0.01]}   # per winch: reported length change = (1 + k) x true change
      tension_offset: {offset: [2, 0, -1, 0]}  # N, per load-cell channel
      tension_gain: {gain: [0.02, 0, 0, 0]}    # relative, per channel: reading = (1 + gain) tau + offset
      pulley_radius: {delta: 0.002}            # m, added to every pulley radius (or a list, one per pulley)
      ahrs_mounting: {roll: 0.01, pitch: -0.005}   # rad, tilt of the AHRS on the platform
      com_offset: {offset: [0.0, 0.0, 0.02]}   # m, true centre of mass minus the model's, platform frame
      mass_scale: {scale: 0.05}                # relative: true mass = (1 + scale) model mass
      pulley_position: {offset: [[0.01, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]}   # m, per pulley
      cable_sag: {density: 0.05}               # kg/m, cable mass per length (parabolic sag)
      pulley_friction: {mu: 0.03, f: 1.5}      # friction between load cell and platform: the cell reads
                                               #   tau (1 - a mu) - a f, a = +1 paid out, -1 reeled in
      loadcell_hysteresis: {h: 0.2}            # N: the cells read tau - s h, s = +1 rising load, -1 falling
    faults:                                    # at a given simulated time t (s)
      - {kind: can_frames_lost, t: 12.0, duration: 0.5, fraction: 1.0}
      - {kind: drive_fault, t: 12.0, drive: 2}             # drives, channels and cables count from 1
      - {kind: loadcell_stuck, t: 12.0, channel: 3}
      - {kind: loadcell_disconnected, t: 12.0}
      - {kind: ahrs_corrupt, t: 12.0, bytes: 16}
      - {kind: cable_slack, t: 12.0, cable: 1, length: 0.05}   # the cable slips on its drum by 'length' m
    physics: {linear_damping: 20.0}            # overrides of sim_backend.physics.PhysicsParams (SI)
    initial: {spread: 0.03}                    # m, power-on position randomised within this of home
    sensors:                                   # per-sample noise (standard deviation) of the emulated sensors
      loadcell_sigma: 0.1                      #   N, every load-cell channel
      encoder_sigma: 0.0                       #   m of cable length (winch encoders; 0: their counts only)
      swivel_sigma: 0.0                        #   rad (swivel encoders; 0: their counts only)
      ahrs_sigma: [0.03, 0.03, 0.1]            #   deg: roll, pitch, yaw
    sway: {amplitude: 0.002, period: 8.0}      # slow random horizontal push on the platform: m of position
                                               #   amplitude it gives, s of period (off without the section)
    wobble: {decay: 4.0}                       # a lightly damped platform: s for its swing to fall by 1/e
                                               #   (sets the platform's linear and angular damping; the
                                               #   nominal 20 N s/m damps the prototype's in 1.3 s)

The values shown for ``sensors`` are the prototype's (the defaults); ``sway`` is a force on the platform in
the physics (sim_backend.physics.Sway): the force control answers it with the tensions held, so the platform
swings about the equilibrium of those tensions and the lengths, angles and AHRS follow it. ``wobble`` leaves
the platform swinging when a tension move ends (its damping from the decay time, ``damping_for``), as a real
platform does: the samples before it rests are not at rest.

Effect names are those of the diagnosis (spec/cli.md). Validation errors name file, field and value.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from calib.errors import CdprError
from calib.fields import FieldReader, read_yaml
from calib.robot import Robot
from sim_backend.physics import PhysicsParams, Sway, WinchParams, transmission_of

EFFECTS = (
    "cable_elasticity",
    "length_scale",
    "tension_offset",
    "tension_gain",
    "pulley_radius",
    "ahrs_mounting",
    "com_offset",
    "mass_scale",
    "pulley_position",
    "cable_sag",
    "pulley_friction",
    "loadcell_hysteresis",
)
FAULTS = ("can_frames_lost", "drive_fault", "loadcell_stuck", "loadcell_disconnected", "ahrs_corrupt", "cable_slack")


class SimConfigError(CdprError, ValueError):
    """An unusable simulation configuration; the message names the file, field and value."""


@dataclass(frozen=True)
class HiddenEffects:
    """The hidden effects, None when off. Per-cable tuples have n entries; units as in the module doc."""

    cable_elasticity: float | None = None  # EA, N
    length_scale: tuple[float, ...] | None = None  # relative, per winch
    tension_offset: tuple[float, ...] | None = None  # N, per channel
    tension_gain: tuple[float, ...] | None = None  # relative, per channel
    pulley_radius: tuple[float, ...] | None = None  # m, per pulley
    ahrs_mounting: tuple[float, float] | None = None  # roll, pitch, rad
    com_offset: tuple[float, float, float] | None = None  # m, platform frame
    mass_scale: float | None = None  # relative
    pulley_position: tuple[tuple[float, float, float], ...] | None = None  # m, per pulley
    cable_sag: float | None = None  # kg/m
    pulley_friction: tuple[float, float] | None = None  # mu (relative), f (N)
    loadcell_hysteresis: float | None = None  # h, N

    def active(self) -> list[str]:
        """Names of the effects that are on."""
        return [f.name for f in dataclasses.fields(self) if getattr(self, f.name) is not None]


@dataclass(frozen=True)
class Fault:
    """A fault injected at simulated time ``t`` (s). ``target`` is the 0-based drive/channel/cable index."""

    kind: str
    t: float
    target: int | None = None
    duration: float = 0.0  # s (can_frames_lost)
    fraction: float = 1.0  # share of frames lost (can_frames_lost)
    n_bytes: int = 0  # ahrs_corrupt
    length: float = 0.0  # m (cable_slack)


@dataclass(frozen=True)
class SensorNoise:
    """Per-sample noise (standard deviation) of the emulated sensors; the defaults are the prototype's."""

    loadcell_sigma: float = 0.1  # N
    encoder_sigma: float = 0.0  # m of cable length
    swivel_sigma: float = 0.0  # rad
    ahrs_sigma: tuple[float, float, float] = (0.03, 0.03, 0.1)  # deg: roll, pitch, yaw




def described_ea(robot: Robot) -> float | None:
    """The one axial stiffness EA (N) the simulator gives every cable of ``robot``: its description's
    ``cables[].axial_stiffness`` (the figure the measurement model uses too); None without one (the
    simulator's nominal ``PhysicsParams.ea`` then, which the model does not know: an inextensible default
    made a braked platform set at a given pose diverge, tests/test_sim_backend.py)."""
    if robot.axial_stiffness is None:
        return None
    ea = np.asarray(robot.axial_stiffness, float)
    if not np.all(ea == ea[0]) or not np.isfinite(ea[0]):
        raise SimConfigError(f"robot '{robot.name}': cables[].axial_stiffness = {ea.tolist()}: the simulator "
                             "takes one axial stiffness for every cable.")
    return float(ea[0])


@dataclass(frozen=True)
class SimConfig:
    """A validated simulation configuration."""

    effects: HiddenEffects = field(default_factory=HiddenEffects)
    faults: tuple[Fault, ...] = ()
    physics: PhysicsParams = field(default_factory=PhysicsParams)
    initial_spread: float = 0.03  # m
    source: str = "<nominal>"
    sensors: SensorNoise = field(default_factory=SensorNoise)
    sway: Sway | None = None  # amplitude (m) and period (s); its seed is the backend's
    wobble: float | None = None  # s: e-folding time of the platform's swing (sets its damping), None: nominal
    ea_given: bool = False  # physics.ea set in the file (else the robot description's axial stiffness, if any)

    def true_robot(self, robot: Robot) -> Robot:
        """The robot as the simulated prototype really is: geometry, mass and centre of mass with effects."""
        e = self.effects
        changes: dict[str, Any] = {}
        if e.pulley_radius is not None:
            changes["r"] = robot.r + np.asarray(e.pulley_radius)
        if e.pulley_position is not None:
            changes["d"] = robot.d + np.asarray(e.pulley_position)
        if e.com_offset is not None:
            changes["com"] = robot.com + np.asarray(e.com_offset)
        if e.mass_scale is not None:
            changes["mass"] = robot.mass * (1.0 + e.mass_scale)
        return robot.replace(**changes) if changes else robot

    def true_transmission(self, robot: Robot) -> np.ndarray:
        """(n,) true m of cable per rad of motor: the nominal ratio divided by (1 + length_scale).

        So the length change the drives report (nominal ratio x motor angle) is (1 + k) times the true one,
        the convention of the diagnosis' ``length_scale`` effect.
        """
        k = transmission_of(robot)
        if self.effects.length_scale is not None:
            k = k / (1.0 + np.asarray(self.effects.length_scale))
        return k

    def physics_params(self, robot: Robot | None = None) -> PhysicsParams:
        """Physics parameters with the cable effects (EA, cable mass) applied, and with ``robot`` (the true
        one) the wobble's damping (:func:`damping_for`) and the cables' axial stiffness of its description
        (:func:`described_ea`: what the model knows too) unless ``physics.ea`` or the hidden
        ``cable_elasticity`` sets another."""
        p = self.physics
        if self.wobble is not None and robot is not None:
            lin, ang = damping_for(robot, self.wobble)
            p = dataclasses.replace(p, linear_damping=lin, angular_damping=ang)
        if robot is not None and not self.ea_given and (ea := described_ea(robot)) is not None:
            p = dataclasses.replace(p, ea=ea)
        if self.effects.cable_elasticity is not None:
            p = dataclasses.replace(p, ea=self.effects.cable_elasticity)
        if self.effects.cable_sag is not None:
            p = dataclasses.replace(p, cable_density=self.effects.cable_sag)
        if self.effects.pulley_friction is not None:
            mu, f = self.effects.pulley_friction
            p = dataclasses.replace(p, pulley_mu=mu, pulley_friction=f)
        return p

    def described_robot(self, robot: Robot) -> Robot:
        """The description of the simulated prototype: ``robot`` with the cables' axial stiffness the simulator
        gives them where ``robot`` names none (``physics.ea`` of this file, else the nominal
        ``PhysicsParams.ea``), so that the model solving a simulated run knows the stretch the simulator
        makes; a hidden ``cable_elasticity`` stays hidden (the description keeps the nominal figure)."""
        if robot.axial_stiffness is not None:
            return robot
        return robot.replace(axial_stiffness=np.full(robot.n, float(self.physics.ea)))

    def tension_offset(self, n: int) -> np.ndarray:
        return np.zeros(n) if self.effects.tension_offset is None else np.asarray(self.effects.tension_offset)

    def tension_gain(self, n: int) -> np.ndarray:
        """(n,) gain factors 1 + gain of the load-cell channels."""
        g = np.zeros(n) if self.effects.tension_gain is None else np.asarray(self.effects.tension_gain)
        return 1.0 + g

    def pulley_friction(self) -> tuple[float, float]:
        """(mu, f N) of the friction between the load cells and the platform; (0, 0) when off."""
        return (0.0, 0.0) if self.effects.pulley_friction is None else self.effects.pulley_friction

    def loadcell_hysteresis(self) -> float:
        """h, N: half the difference between the cells' falling and rising readings; 0 when off."""
        return 0.0 if self.effects.loadcell_hysteresis is None else float(self.effects.loadcell_hysteresis)

    def ahrs_mounting(self) -> tuple[float, float]:
        return (0.0, 0.0) if self.effects.ahrs_mounting is None else self.effects.ahrs_mounting


def damping_for(robot: Robot, decay: float) -> tuple[float, float]:
    """Linear (N s/m) and angular (N m s/rad) damping of the platform that make its swing fall by 1/e in
    ``decay`` s: 2 m / decay and 2 I / decay, I the mean of the principal inertias about G (kg m^2)."""
    inertia = float(np.mean(np.diag(np.asarray(robot.inertia, float))))
    return 2.0 * robot.mass / decay, 2.0 * inertia / decay


class _Check(FieldReader):
    """Typed access to a simulation configuration's fields (calib/fields.py)."""

    error = SimConfigError

    def mapping(self, value: Any, fld: str, allowed: tuple[str, ...]) -> dict:
        if not isinstance(value, dict):
            raise self.fail(fld, value, "must be a mapping")
        for key in value:
            if key not in allowed:
                raise self.fail(f"{fld}.{key}" if fld else str(key), value[key], f"is not one of {', '.join(allowed)}")
        return value

    def number(self, value: Any, fld: str, lo: float | None = None, hi: float | None = None, strict=False) -> float:
        self.finite(value, fld)
        if lo is not None and (value < lo or (strict and value == lo)):
            raise self.fail(fld, value, f"must be {'>' if strict else '>='} {lo}")
        if hi is not None and value > hi:
            raise self.fail(fld, value, f"must be <= {hi}")
        return float(value)

    def vector(self, value: Any, fld: str, size: int, lo: float | None = None, hi: float | None = None) -> tuple:
        if not isinstance(value, list | tuple) or len(value) != size:
            raise self.fail(fld, value, f"must be a list of {size} numbers")
        return tuple(self.number(x, f"{fld}[{j}]", lo, hi) for j, x in enumerate(value))

    def required(self, m: dict, key: str, fld: str) -> Any:
        if key not in m:
            raise self.missing(f"{fld}.{key}")
        return m[key]

    def index(self, value: Any, fld: str, n: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= n:
            raise self.fail(fld, value, f"must be an integer from 1 to {n}")
        return value - 1


def _effects(c: _Check, raw: Any, n: int) -> HiddenEffects:
    m = c.mapping(raw, "effects", EFFECTS)
    out: dict[str, Any] = {}
    for name, val in m.items():
        f = f"effects.{name}"
        if name == "cable_elasticity":
            v = c.mapping(val, f, ("EA",))
            out[name] = c.number(c.required(v, "EA", f), f + ".EA", 1.0, strict=True)
        elif name == "length_scale":
            v = c.mapping(val, f, ("k",))
            out[name] = c.vector(c.required(v, "k", f), f + ".k", n, -0.5, 0.5)
        elif name == "tension_offset":
            v = c.mapping(val, f, ("offset",))
            out[name] = c.vector(c.required(v, "offset", f), f + ".offset", n)
        elif name == "tension_gain":
            v = c.mapping(val, f, ("gain",))
            out[name] = c.vector(c.required(v, "gain", f), f + ".gain", n, -0.5, 0.5)
        elif name == "pulley_radius":
            v = c.mapping(val, f, ("delta",))
            d = c.required(v, "delta", f)
            out[name] = (c.number(d, f + ".delta"),) * n if not isinstance(d, list) else c.vector(d, f + ".delta", n)
        elif name == "ahrs_mounting":
            v = c.mapping(val, f, ("roll", "pitch"))
            out[name] = (
                c.number(v.get("roll", 0.0), f + ".roll", -0.5, 0.5),
                c.number(v.get("pitch", 0.0), f + ".pitch", -0.5, 0.5),
            )
        elif name == "com_offset":
            v = c.mapping(val, f, ("offset",))
            out[name] = c.vector(c.required(v, "offset", f), f + ".offset", 3, -0.5, 0.5)
        elif name == "mass_scale":
            v = c.mapping(val, f, ("scale",))
            out[name] = c.number(c.required(v, "scale", f), f + ".scale", -0.5, 0.5)
        elif name == "pulley_position":
            v = c.mapping(val, f, ("offset",))
            rows = c.required(v, "offset", f)
            if not isinstance(rows, list) or len(rows) != n:
                raise c.fail(f + ".offset", rows, f"must be a list of {n} [dx, dy, dz] offsets")
            out[name] = tuple(c.vector(r, f"{f}.offset[{i}]", 3, -0.5, 0.5) for i, r in enumerate(rows))
        elif name == "cable_sag":
            v = c.mapping(val, f, ("density",))
            out[name] = c.number(c.required(v, "density", f), f + ".density", 0.0, 5.0, strict=True)
        elif name == "pulley_friction":
            v = c.mapping(val, f, ("mu", "f"))
            out[name] = (c.number(v.get("mu", 0.0), f + ".mu", 0.0, 0.5),
                         c.number(v.get("f", 0.0), f + ".f", 0.0, 100.0))
        elif name == "loadcell_hysteresis":
            v = c.mapping(val, f, ("h",))
            out[name] = c.number(c.required(v, "h", f), f + ".h", 0.0, 100.0)
    return HiddenEffects(**out)


def _faults(c: _Check, raw: Any, n: int) -> tuple[Fault, ...]:
    if not isinstance(raw, list):
        raise c.fail("faults", raw, "must be a list of faults")
    out = []
    keys = {
        "can_frames_lost": ("duration", "fraction"),
        "drive_fault": ("drive",),
        "loadcell_stuck": ("channel",),
        "loadcell_disconnected": (),
        "ahrs_corrupt": ("bytes",),
        "cable_slack": ("cable", "length"),
    }
    for j, item in enumerate(raw):
        f = f"faults[{j}]"
        if not isinstance(item, dict):
            raise c.fail(f, item, "must be a mapping with 'kind' and 't'")
        kind = c.required(item, "kind", f)
        if kind not in FAULTS:
            raise c.fail(f + ".kind", kind, f"is not one of {', '.join(FAULTS)}")
        c.mapping(item, f, ("kind", "t") + keys[kind])
        t = c.number(c.required(item, "t", f), f + ".t", 0.0)
        if kind == "can_frames_lost":
            out.append(
                Fault(
                    kind,
                    t,
                    duration=c.number(item.get("duration", 1.0), f + ".duration", 0.0, strict=True),
                    fraction=c.number(item.get("fraction", 1.0), f + ".fraction", 0.0, 1.0, strict=True),
                )
            )
        elif kind == "drive_fault":
            out.append(Fault(kind, t, target=c.index(c.required(item, "drive", f), f + ".drive", n)))
        elif kind == "loadcell_stuck":
            out.append(Fault(kind, t, target=c.index(c.required(item, "channel", f), f + ".channel", n)))
        elif kind == "loadcell_disconnected":
            out.append(Fault(kind, t))
        elif kind == "ahrs_corrupt":
            b = item.get("bytes", 8)
            if isinstance(b, bool) or not isinstance(b, int) or b < 1:
                raise c.fail(f + ".bytes", b, "must be a positive integer")
            out.append(Fault(kind, t, n_bytes=b))
        elif kind == "cable_slack":
            out.append(
                Fault(
                    kind,
                    t,
                    target=c.index(c.required(item, "cable", f), f + ".cable", n),
                    length=c.number(item.get("length", 0.05), f + ".length", 0.0, 1.0, strict=True),
                )
            )
    return tuple(sorted(out, key=lambda x: x.t))


def _physics(c: _Check, raw: Any) -> PhysicsParams:
    names = tuple(f.name for f in dataclasses.fields(PhysicsParams) if f.name != "winch")
    wnames = tuple(f.name for f in dataclasses.fields(WinchParams))
    m = c.mapping(raw, "physics", names + ("winch",))
    vals: dict[str, Any] = {}
    for k, v in m.items():
        if k == "winch":
            w = c.mapping(v, "physics.winch", wnames)
            vals["winch"] = WinchParams(**{a: c.number(b, f"physics.winch.{a}", 0.0) for a, b in w.items()})
        elif k == "substeps":
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 100:
                raise c.fail("physics.substeps", v, "must be an integer from 1 to 100")
            vals[k] = v
        elif k == "stiff_theta":
            vals[k] = c.number(v, "physics.stiff_theta", 0.5, 1.0)
        else:
            vals[k] = c.number(v, f"physics.{k}", 0.0, strict=(k == "ea"))
    if "winch" in vals:
        for name in ("rotor_inertia", "drum_radius"):
            if getattr(vals["winch"], name) <= 0:
                raise c.fail(f"physics.winch.{name}", getattr(vals["winch"], name), "must be > 0")
    return PhysicsParams(**vals)


def sim_config_from_dict(data: Any, n: int = 4, origin: str = "<sim config>") -> SimConfig:
    """Validate a simulation configuration mapping for a robot with n cables."""
    c = _Check(origin)
    if data is None:
        data = {}
    m = c.mapping(data, "", ("effects", "faults", "physics", "initial", "sensors", "sway", "wobble"))
    effects = _effects(c, m["effects"], n) if m.get("effects") is not None else HiddenEffects()
    faults = _faults(c, m["faults"], n) if m.get("faults") is not None else ()
    physics = _physics(c, m["physics"]) if m.get("physics") is not None else PhysicsParams()
    spread = 0.03
    if m.get("initial") is not None:
        ini = c.mapping(m["initial"], "initial", ("spread",))
        spread = c.number(ini.get("spread", spread), "initial.spread", 0.0, 0.2)
    sensors = _sensors(c, m["sensors"]) if m.get("sensors") is not None else SensorNoise()
    sway = None
    if m.get("sway") is not None:
        sw = c.mapping(m["sway"], "sway", ("amplitude", "period"))
        sway = Sway(c.number(c.required(sw, "amplitude", "sway"), "sway.amplitude", 0.0, 0.05),
                    c.number(sw.get("period", 8.0), "sway.period", 0.5, 120.0))
    wobble = None
    if m.get("wobble") is not None:
        wb = c.mapping(m["wobble"], "wobble", ("decay",))
        wobble = c.number(c.required(wb, "decay", "wobble"), "wobble.decay", 0.1, 60.0)
    ea_given = isinstance(m.get("physics"), dict) and "ea" in m["physics"]
    return SimConfig(effects, faults, physics, spread, origin, sensors, sway, wobble, ea_given)


def _sensors(c: _Check, raw: Any) -> SensorNoise:
    m = c.mapping(raw, "sensors", tuple(f.name for f in dataclasses.fields(SensorNoise)))
    base = SensorNoise()
    vals: dict[str, Any] = {}
    for name in ("loadcell_sigma", "encoder_sigma", "swivel_sigma"):
        if name in m:
            vals[name] = c.number(m[name], f"sensors.{name}", 0.0, 100.0 if name == "loadcell_sigma" else 0.1)
    if "ahrs_sigma" in m:
        vals["ahrs_sigma"] = c.vector(m["ahrs_sigma"], "sensors.ahrs_sigma", 3, 0.0, 10.0)
    return dataclasses.replace(base, **vals)


def load_sim_config(path: str | Path | None, n: int = 4) -> SimConfig:
    """Read and validate a ``--sim-config`` YAML file (None: the nominal prototype)."""
    if path is None:
        return SimConfig()
    p = Path(path)
    if not p.is_file():
        raise SimConfigError(f"{p}: simulation configuration file not found.")
    return sim_config_from_dict(read_yaml(p, SimConfigError, "simulation configuration"), n, str(p))


def example_names() -> list[str]:
    """Names of the example configurations shipped in sim_backend/examples."""
    folder = resources.files("sim_backend") / "examples"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def example_path(name: str) -> Path:
    """Path of a shipped example configuration, e.g. ``example_path("mass_scale")``."""
    p = Path(str(resources.files("sim_backend") / "examples" / f"{name}.yaml"))
    if not p.is_file():
        known = ", ".join(example_names())
        raise SimConfigError(f"no example simulation configuration named '{name}' (known: {known}).")
    return p
