"""Robot descriptions: YAML files validated into frozen dataclasses.

A description holds the geometry of the cables (pulley entry points d_i, local pulley frames, pulley radii,
platform anchors), the platform's inertial data, the orientation convention, sensor specifications, the
noise levels used as weights (Zoffoli eq. 18), the workspace bounds (eq. 19) and the tension limits.
Units: SI throughout (m, kg, N, rad); the YAML may give angles in degrees where the key says ``_deg``.
Built-in robots live in ``calib/robots/*.yaml`` and are loaded with :func:`load_robot`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calib.errors import CdprError
from calib.fields import FieldReader, read_yaml

ORIENTATIONS = ("xyz", "zyx")
AXES = {"x": 0, "y": 1, "z": 2, "roll": 3, "pitch": 4, "yaw": 5}


class RobotDescriptionError(CdprError, ValueError):
    """A robot description that cannot be used; the message names the file, field and value."""


@dataclass(frozen=True, eq=False)
class SensorSpec:
    """Specifications of the prototype's sensors (Zoffoli paper, Section 4)."""

    motor_encoder_bits: int = 20
    motor_encoder_accuracy: float = math.radians(0.144)  # rad, on the motor axis
    length_per_motor_rev: tuple[float, ...] = ()  # m of cable per motor revolution, one per winch
    swivel_encoder_bits: int = 16
    swivel_counts_per_rev: int = 65536
    swivel_encoder_accuracy: float = math.radians(0.03)  # rad
    load_cell_full_scale: float = 100.0 * 9.81  # N
    load_cell_accuracy: float = 0.0002  # fraction of full scale
    ahrs_roll_pitch_accuracy: float = math.radians(0.2)  # rad
    ahrs_yaw_accuracy: float = math.radians(1.0)  # rad
    # Euler convention of the angles the AHRS reports ("" = the robot's own); an Xsens MTi reports "zyx"
    ahrs_convention: str = ""

    @property
    def load_cell_uncertainty(self) -> float:
        """Load-cell uncertainty in N (accuracy times full scale)."""
        return self.load_cell_accuracy * self.load_cell_full_scale


@dataclass(frozen=True)
class NoiseLevels:
    """Standard deviations used as NWLS weights, per channel (eq. 17-18): N, m, rad, rad."""

    tension: float
    length: float
    swivel: float
    orientation: float


@dataclass(frozen=True, eq=False)
class Robot:
    """A cable robot with n cables. Arrays are read-only numpy arrays.

    Attributes:
        d: (n, 3) pulley entry points D_i in the fixed frame (for straight cables: the fixed anchors), m.
        frames: (n, 3, 3) rows are the local pulley unit vectors i_i, j_i, k_i in the fixed frame.
        r: (n,) pulley radii, m; 0 means a straight cable from d_i with no swivel pulley.
        a_local: (n, 3) platform anchors A_i in the platform frame, m.
        mass: platform mass, kg. com: (3,) centre of mass in the platform frame, m. gravity: m/s^2.
        inertia: (3, 3) inertia about the centre of mass in the platform frame, kg m^2.
        orientation: ``xyz`` (R = Rx(roll) Ry(pitch) Rz(yaw)) or ``zyx`` (R = Rz(yaw) Ry(pitch) Rx(roll)).
        controlled: indices of the pose coordinates whose equilibrium equations define the tension
            model (eq. 11-12), n of them; 0..2 are x, y, z forces, 3..5 are moments about the
            roll, pitch and yaw axes of the Euler parameterisation.
        axial_stiffness: (n,) each cable's axial stiffness EA, N (its datasheet figure; inf where none is
            given: an inextensible cable), or None when no cable gives one.
    """

    name: str
    d: np.ndarray
    frames: np.ndarray
    r: np.ndarray
    a_local: np.ndarray
    mass: float
    com: np.ndarray
    gravity: float = 9.81
    inertia: np.ndarray = field(default_factory=lambda: np.eye(3) * 0.1)
    orientation: str = "xyz"
    controlled: tuple[int, ...] = (0, 1, 2, 5)
    sensors: SensorSpec = field(default_factory=SensorSpec)
    noise: NoiseLevels = field(default_factory=lambda: NoiseLevels(10.0, 0.01, math.radians(1), math.radians(2)))
    workspace_lower: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))
    workspace_upper: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    tau0: np.ndarray | None = None
    tau_min: float = 10.0
    tau_max: float = 500.0
    home_pose: np.ndarray | None = None
    description: str = ""
    source: str = ""
    axial_stiffness: np.ndarray | None = None

    @property
    def n(self) -> int:
        """Number of cables."""
        return int(self.d.shape[0])

    @property
    def ahrs_convention(self) -> str:
        """Euler convention of the AHRS readings (the sensor's own, else the robot's)."""
        return self.sensors.ahrs_convention or self.orientation

    @property
    def has_pulleys(self) -> bool:
        return bool(np.any(self.r > 0))

    @property
    def compliance(self) -> np.ndarray:
        """(n,) 1/EA of each cable, 1/N (0: inextensible)."""
        if self.axial_stiffness is None:
            return np.zeros(self.n)
        return 1.0 / np.asarray(self.axial_stiffness, float)

    @property
    def weight(self) -> float:
        """m g, N."""
        return self.mass * self.gravity

    def replace(self, **changes: Any) -> Robot:
        """A copy with some fields changed (arrays are converted and frozen)."""
        return _freeze(dataclasses.replace(self, **changes))

    def to_dict(self) -> dict[str, Any]:
        """The description as plain YAML-ready data (the schema :func:`robot_from_dict` reads)."""
        names = ("x", "y", "z")
        cables = []
        for i in range(self.n):
            c: dict[str, Any] = {"pulley_point": _lst(self.d[i])}
            if self.r[i] > 0:
                c["frame"] = {ax: _lst(self.frames[i, j]) for j, ax in enumerate(names)}
                c["pulley_radius"] = float(self.r[i])
            c["platform_anchor"] = _lst(self.a_local[i])
            if self.axial_stiffness is not None and math.isfinite(self.axial_stiffness[i]):
                c["axial_stiffness"] = float(self.axial_stiffness[i])
            cables.append(c)
        inv = {v: k for k, v in AXES.items()}
        out: dict[str, Any] = {
            "name": self.name,
            "description": self.description,
            "source": self.source,
            "orientation": self.orientation,
            "cables": cables,
            "platform": {"mass": self.mass, "com": _lst(self.com), "inertia": self.inertia.tolist()},
            "gravity": self.gravity,
            "controlled": [inv[c] for c in self.controlled],
            "tensions": {"min": self.tau_min, "max": self.tau_max},
            "noise": {
                "tension": self.noise.tension,
                "length": self.noise.length,
                "swivel_deg": math.degrees(self.noise.swivel),
                "orientation_deg": math.degrees(self.noise.orientation),
            },
            "sensors": _sensors_to_dict(self.sensors),
        }
        if self.tau0 is not None:
            out["tensions"]["tau0"] = _lst(self.tau0)
        if np.all(np.isfinite(self.workspace_lower)):
            out["workspace"] = {"lower": _lst(self.workspace_lower), "upper": _lst(self.workspace_upper)}
        if self.home_pose is not None:
            out["home_pose"] = _lst(self.home_pose)
        return out


def _lst(a: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(a).ravel()]


def _sensors_to_dict(s: SensorSpec) -> dict[str, Any]:
    return {
        "motor_encoder_bits": s.motor_encoder_bits,
        "motor_encoder_accuracy_deg": math.degrees(s.motor_encoder_accuracy),
        "length_per_motor_rev": list(s.length_per_motor_rev),
        "swivel_encoder_bits": s.swivel_encoder_bits,
        "swivel_counts_per_rev": s.swivel_counts_per_rev,
        "swivel_encoder_accuracy_deg": math.degrees(s.swivel_encoder_accuracy),
        "load_cell_full_scale": s.load_cell_full_scale,
        "load_cell_accuracy": s.load_cell_accuracy,
        "ahrs_roll_pitch_accuracy_deg": math.degrees(s.ahrs_roll_pitch_accuracy),
        "ahrs_yaw_accuracy_deg": math.degrees(s.ahrs_yaw_accuracy),
        **({"ahrs_convention": s.ahrs_convention} if s.ahrs_convention else {}),
    }


def _freeze(robot: Robot) -> Robot:
    for f in dataclasses.fields(robot):
        v = getattr(robot, f.name)
        if isinstance(v, np.ndarray):
            a = np.array(v, dtype=float)
            a.setflags(write=False)
            object.__setattr__(robot, f.name, a)
    return robot


class _Reader(FieldReader):
    """Typed access to a robot description's fields (calib/fields.py)."""

    error = RobotDescriptionError

    def get(self, m: dict, key: str, path: str, default: Any = dataclasses.MISSING) -> Any:
        if not isinstance(m, dict):
            raise self.fail(path.rsplit(".", 1)[0] or path, m, "must be a mapping")
        if key not in m:
            if default is dataclasses.MISSING:
                raise self.missing(path)
            return default
        return m[key]

    def number(self, value: Any, path: str, positive: bool = False, nonneg: bool = False) -> float:
        self.finite(value, path)
        if positive and value <= 0:
            raise self.fail(path, value, "must be positive")
        if nonneg and value < 0:
            raise self.fail(path, value, "must not be negative")
        return float(value)

    def vector(self, value: Any, path: str, size: int) -> np.ndarray:
        if not isinstance(value, list | tuple) or len(value) != size:
            raise self.fail(path, value, f"must be a list of {size} numbers")
        return np.array([self.number(x, f"{path}[{j}]") for j, x in enumerate(value)])


def robot_from_dict(data: Any, origin: str = "<robot>") -> Robot:
    """Validate a robot description mapping (the YAML schema of calib/robots/irma4u.yaml)."""
    rd = _Reader(origin)
    if not isinstance(data, dict):
        raise RobotDescriptionError(f"{origin}: a robot description must be a mapping, got {type(data).__name__}.")
    name = str(rd.get(data, "name", "name"))
    orientation = rd.get(data, "orientation", "orientation", "xyz")
    if orientation not in ORIENTATIONS:
        raise rd.fail("orientation", orientation, f"must be one of {', '.join(ORIENTATIONS)}")
    cables = rd.get(data, "cables", "cables")
    if not isinstance(cables, list) or not 1 <= len(cables) <= 12:
        raise rd.fail("cables", cables, "must be a list of 1 to 12 cables")
    n = len(cables)
    d = np.zeros((n, 3))
    frames = np.zeros((n, 3, 3))
    r = np.zeros(n)
    a = np.zeros((n, 3))
    ea = np.full(n, np.inf)
    for i, c in enumerate(cables):
        p = f"cables[{i}]"
        ea_raw = rd.get(c, "axial_stiffness", f"{p}.axial_stiffness", None)
        if ea_raw is not None:
            ea[i] = rd.number(ea_raw, f"{p}.axial_stiffness", positive=True)
        d[i] = rd.vector(rd.get(c, "pulley_point", f"{p}.pulley_point"), f"{p}.pulley_point", 3)
        a[i] = rd.vector(rd.get(c, "platform_anchor", f"{p}.platform_anchor"), f"{p}.platform_anchor", 3)
        r[i] = rd.number(rd.get(c, "pulley_radius", f"{p}.pulley_radius", 0.0), f"{p}.pulley_radius", nonneg=True)
        fr = rd.get(c, "frame", f"{p}.frame", None)
        if fr is None:
            if r[i] > 0:
                raise RobotDescriptionError(f"{origin}: required field '{p}.frame' is missing (pulley_radius > 0).")
            frames[i] = np.eye(3)
        else:
            for j, ax in enumerate("xyz"):
                frames[i, j] = rd.vector(rd.get(fr, ax, f"{p}.frame.{ax}"), f"{p}.frame.{ax}", 3)
            if not np.allclose(frames[i] @ frames[i].T, np.eye(3), atol=1e-9):
                raise rd.fail(f"{p}.frame", fr, "must be three orthonormal unit vectors")
            if np.linalg.det(frames[i]) < 0:
                raise rd.fail(f"{p}.frame", fr, "must be right-handed (z = x cross y)")
    plat = rd.get(data, "platform", "platform")
    mass = rd.number(rd.get(plat, "mass", "platform.mass"), "platform.mass", positive=True)
    com = rd.vector(rd.get(plat, "com", "platform.com"), "platform.com", 3)
    inertia_raw = rd.get(plat, "inertia", "platform.inertia", None)
    if inertia_raw is None:
        inertia = np.eye(3) * mass * 0.01
    else:
        if not isinstance(inertia_raw, list) or len(inertia_raw) != 3:
            raise rd.fail("platform.inertia", inertia_raw, "must be a 3x3 matrix")
        inertia = np.array([rd.vector(row, f"platform.inertia[{j}]", 3) for j, row in enumerate(inertia_raw)])
        if not np.allclose(inertia, inertia.T) or np.any(np.linalg.eigvalsh(inertia) <= 0):
            raise rd.fail("platform.inertia", inertia_raw, "must be symmetric positive definite")
    gravity = rd.number(rd.get(data, "gravity", "gravity", 9.81), "gravity", positive=True)
    ctrl_raw = rd.get(data, "controlled", "controlled", ["x", "y", "z", "yaw"][: min(n, 6)] if n == 4 else None)
    if ctrl_raw is None:
        controlled: tuple[int, ...] = ()
    else:
        valid = isinstance(ctrl_raw, list) and all(c in AXES for c in ctrl_raw)
        if not valid or len(set(ctrl_raw)) != len(ctrl_raw):
            raise rd.fail("controlled", ctrl_raw, f"must be a list of distinct names from {', '.join(AXES)}")
        if len(ctrl_raw) != min(n, 6):
            raise rd.fail("controlled", ctrl_raw, f"must name {min(n, 6)} coordinates (one per cable)")
        controlled = tuple(AXES[c] for c in ctrl_raw)
    ten = rd.get(data, "tensions", "tensions", {})
    tau_min = rd.number(rd.get(ten, "min", "tensions.min", 10.0), "tensions.min", nonneg=True)
    tau_max = rd.number(rd.get(ten, "max", "tensions.max", 500.0), "tensions.max", positive=True)
    if tau_max <= tau_min:
        raise rd.fail("tensions.max", tau_max, f"must exceed tensions.min = {tau_min}")
    tau0_raw = rd.get(ten, "tau0", "tensions.tau0", None)
    tau0 = None if tau0_raw is None else rd.vector(tau0_raw, "tensions.tau0", n)
    nz = rd.get(data, "noise", "noise", {})
    noise = NoiseLevels(
        tension=rd.number(rd.get(nz, "tension", "noise.tension", 10.0), "noise.tension", positive=True),
        length=rd.number(rd.get(nz, "length", "noise.length", 0.01), "noise.length", positive=True),
        swivel=math.radians(
            rd.number(rd.get(nz, "swivel_deg", "noise.swivel_deg", 1.0), "noise.swivel_deg", positive=True)
        ),
        orientation=math.radians(
            rd.number(rd.get(nz, "orientation_deg", "noise.orientation_deg", 2.0), "noise.orientation_deg",
                      positive=True)
        ),
    )
    ws = rd.get(data, "workspace", "workspace", None)
    if ws is None:
        lo, hi = np.full(3, -np.inf), np.full(3, np.inf)
    else:
        lo = rd.vector(rd.get(ws, "lower", "workspace.lower"), "workspace.lower", 3)
        hi = rd.vector(rd.get(ws, "upper", "workspace.upper"), "workspace.upper", 3)
        if np.any(hi <= lo):
            raise rd.fail("workspace.upper", _lst(hi), f"must exceed workspace.lower = {_lst(lo)} on every axis")
    home = rd.get(data, "home_pose", "home_pose", None)
    home_pose = None if home is None else rd.vector(home, "home_pose", 6)
    sensors = _sensors_from_dict(rd, rd.get(data, "sensors", "sensors", {}), n)
    robot = Robot(
        name=name,
        d=d,
        frames=frames,
        r=r,
        a_local=a,
        mass=mass,
        com=com,
        gravity=gravity,
        inertia=inertia,
        orientation=orientation,
        controlled=controlled,
        sensors=sensors,
        noise=noise,
        workspace_lower=lo,
        workspace_upper=hi,
        tau0=tau0,
        tau_min=tau_min,
        tau_max=tau_max,
        home_pose=home_pose,
        description=str(data.get("description", "")),
        source=str(data.get("source", "")),
        axial_stiffness=ea if np.any(np.isfinite(ea)) else None,
    )
    return _freeze(robot)


def _sensors_from_dict(rd: _Reader, s: Any, n: int) -> SensorSpec:
    if not isinstance(s, dict):
        raise rd.fail("sensors", s, "must be a mapping")
    base = SensorSpec()

    def num(key: str, default: float, deg: bool = False, **kw: bool) -> float:
        v = s.get(key)
        if v is None:
            return default
        x = rd.number(v, f"sensors.{key}", **kw)
        return math.radians(x) if deg else x

    conv = s.get("ahrs_convention", "")
    if conv not in ("", *ORIENTATIONS):
        raise rd.fail("sensors.ahrs_convention", conv, f"must be one of {', '.join(ORIENTATIONS)}")
    lpr = s.get("length_per_motor_rev")
    if lpr is None or lpr == []:
        lpr_t: tuple[float, ...] = ()
    else:
        lpr_t = tuple(float(x) for x in rd.vector(lpr, "sensors.length_per_motor_rev", n))
        if any(x == 0 for x in lpr_t):
            raise rd.fail("sensors.length_per_motor_rev", lpr, "must not contain zeros")
    return SensorSpec(
        motor_encoder_bits=int(num("motor_encoder_bits", base.motor_encoder_bits, positive=True)),
        motor_encoder_accuracy=num("motor_encoder_accuracy_deg", base.motor_encoder_accuracy, deg=True, nonneg=True),
        length_per_motor_rev=lpr_t,
        swivel_encoder_bits=int(num("swivel_encoder_bits", base.swivel_encoder_bits, positive=True)),
        swivel_counts_per_rev=int(num("swivel_counts_per_rev", base.swivel_counts_per_rev, positive=True)),
        swivel_encoder_accuracy=num("swivel_encoder_accuracy_deg", base.swivel_encoder_accuracy, deg=True, nonneg=True),
        load_cell_full_scale=num("load_cell_full_scale", base.load_cell_full_scale, positive=True),
        load_cell_accuracy=num("load_cell_accuracy", base.load_cell_accuracy, nonneg=True),
        ahrs_roll_pitch_accuracy=num(
            "ahrs_roll_pitch_accuracy_deg", base.ahrs_roll_pitch_accuracy, deg=True, nonneg=True
        ),
        ahrs_yaw_accuracy=num("ahrs_yaw_accuracy_deg", base.ahrs_yaw_accuracy, deg=True, nonneg=True),
        ahrs_convention=conv,
    )


def builtin_robot_names() -> list[str]:
    """Names of the robots shipped in calib/robots."""
    folder = resources.files("calib") / "robots"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def load_robot(name_or_path: str | Path | dict = "irma4u") -> Robot:
    """A robot from a built-in name, a YAML file path, or an already parsed mapping."""
    if isinstance(name_or_path, dict):
        return robot_from_dict(name_or_path, "<robot mapping>")
    text_name = str(name_or_path)
    if text_name in builtin_robot_names():
        ref = resources.files("calib") / "robots" / f"{text_name}.yaml"
        return robot_from_dict(yaml.safe_load(ref.read_text()), f"calib/robots/{text_name}.yaml")
    path = Path(text_name)
    if not path.exists():
        raise RobotDescriptionError(
            f"robot '{text_name}' is neither a built-in robot ({', '.join(builtin_robot_names())}) nor a file."
        )
    return robot_from_dict(read_yaml(path, RobotDescriptionError, "robot description"), str(path))


def builtin_robot_yaml(name: str) -> str:
    """The YAML text of a built-in robot, as shipped."""
    if name not in builtin_robot_names():
        raise RobotDescriptionError(f"no built-in robot named '{name}' (known: {', '.join(builtin_robot_names())}).")
    return (resources.files("calib") / "robots" / f"{name}.yaml").read_text()
