"""The channels a run is viewed on, live (acquisition/live.py) and in its MCAP export (acquisition/export_mcap.py).

One set of topics, one schema each, built by the same functions for both, so that a recorded run opens in
the layout a live one was watched in (docs/foxglove-layout.json):

- ``/samples`` (``cdpr.Sample``, JSON): the run log's columns by name, one message per logged sample.
- ``/windows`` (``cdpr.Window``, JSON), ``/events`` (``cdpr.Event``, JSON), ``/solution`` (export only).
- ``/estimate`` (``cdpr.Estimate``, JSON): the online estimate of the initial pose after each window of a
  sequential startup, with its position 1-sigma.
- ``/supervisor`` (``cdpr.Supervisor``, JSON): the safety supervisor's state, its tension bounds and any stop.
- ``/log`` (``foxglove.Log``): one line per phase, window, estimate and stop.
- ``/scene`` (``foxglove.SceneUpdate``): the frame, the pulleys, the cables from their pulley exit points to
  the platform anchors coloured by tension, the platform at its estimated pose, the planned poses as ghosts.
- ``/tf`` (``foxglove.FrameTransform``): ``world`` -> ``platform`` at the estimated pose.

The platform's estimated pose is the direct statics of the measured tensions (:func:`calib.equilibrium.
direct_statics`: the pose at which the model holds the platform in equilibrium under what the load cells
read), warm-started from the last one. Its geometry is :mod:`calib.scene`'s, from the robot description.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from calib.robot import Robot
from calib.scene import cable_segments, frame_edges, quaternion, tension_colours

WORLD, PLATFORM = "world", "platform"
NUMBER_OR_NULL = {"type": ["number", "null"]}
ARRAY = {"type": "array", "items": {"type": "number"}}


def json_schema(title: str, properties: dict[str, Any], required: list[str]) -> bytes:
    """A JSON Schema (draft 2020-12) of an object with ``properties``, as bytes."""
    return json.dumps({"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
                       "type": "object", "properties": properties, "required": required}).encode()


WINDOW_SCHEMA = json_schema("cdpr.Window", {
    "first": {"type": "integer"}, "last": {"type": "integer"}, "t_first": {"type": "number"},
    "t_last": {"type": "number"}, "setpoint": {"type": "integer"}, "source": {"type": "string"}},
    ["first", "last", "t_first", "t_last", "setpoint", "source"])
EVENT_SCHEMA = json_schema("cdpr.Event", {"t": {"type": "number"}, "kind": {"type": "string"},
                                          "message": {"type": "string"}}, ["t", "kind", "message"])
ESTIMATE_SCHEMA = json_schema("cdpr.Estimate", {
    "pose": {"type": "integer"}, "t": {"type": "number"}, "initial_pose": ARRAY,
    "initial_pose_sigma": {"type": ["array", "null"], "items": {"type": "number"}},
    "position_sigma_m": NUMBER_OR_NULL}, ["pose", "t", "initial_pose", "position_sigma_m"])
SUPERVISOR_SCHEMA = json_schema("cdpr.Supervisor", {
    "t": {"type": "number"}, "state": {"type": "string", "enum": ["watching", "stopping", "stopped"]},
    "slack_N": {"type": "number"}, "overload_N": {"type": "number"}, "stop": {"type": ["string", "null"]}},
    ["t", "state", "slack_N", "overload_N", "stop"])


def sample_schema(kinds: dict[str, str]) -> bytes:
    """The ``cdpr.Sample`` schema of columns named in order, each of numpy dtype kind 'f', 'i' or other."""
    props = {name: NUMBER_OR_NULL if k == "f" else {"type": "integer"} if k in "iub" else {"type": "string"}
             for name, k in kinds.items()}
    return json_schema("cdpr.Sample", props, list(kinds))


def startup_columns(n: int) -> dict[str, str]:
    """The columns (name -> dtype kind) of a startup's samples.csv for n cables, in their order."""
    cols = {"t": "f"} | {f"{g}_{i + 1}": "f" for g in ("tau", "tau_ref", "dl", "dsigma") for i in range(n)}
    return cols | {"roll": "f", "pitch": "f", "dyaw": "f", "phase": "U", "setpoint": "i", "tick": "i"}


def number(v: Any) -> float | None:
    """A JSON number, or None for NaN and infinities."""
    x = float(v)
    return x if math.isfinite(x) else None


def foxglove_schemas() -> dict[str, Any]:
    """The well-known Foxglove schemas of /log, /scene and /tf (``name``, ``encoding``, ``data``)."""
    from foxglove import messages as fm

    return {"/log": fm.Log.get_schema(), "/scene": fm.SceneUpdate.get_schema(),
            "/tf": fm.FrameTransform.get_schema()}


def _stamp(ns: int):
    from foxglove.messages import Timestamp

    return Timestamp(sec=int(ns // 1_000_000_000), nsec=int(ns % 1_000_000_000))


def _vec(p):
    from foxglove.messages import Vector3

    return Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _point(p):
    from foxglove.messages import Point3

    return Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _colour(c):
    from foxglove.messages import Color

    return Color(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=float(c[3]))


def _pose(p, q):
    from foxglove.messages import Pose, Quaternion

    return Pose(position=_vec(p), orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


IDENTITY = (0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class SceneModel:
    """The 3D scene of one robot: its frame and pulleys, the planned poses (k, 6) as ghosts, the cables coloured
    from blue at ``low`` N to red at ``high`` N (default the robot's tau_min and tau_max)."""

    robot: Robot
    ghosts: np.ndarray
    low: float
    high: float
    platform_size: tuple[float, float, float]

    @classmethod
    def for_robot(cls, robot: Robot, ghosts: np.ndarray | None = None) -> SceneModel:
        a = np.asarray(robot.a_local, dtype=float)
        span = a.max(0) - a.min(0)
        size = (max(float(span[0]), 0.05), max(float(span[1]), 0.05), 0.04)
        g = np.empty((0, 6)) if ghosts is None else np.asarray(ghosts, dtype=float).reshape(-1, 6)
        return cls(robot, g, float(robot.tau_min), float(robot.tau_max), size)

    def update(self, t_ns: int, pose: np.ndarray | None, tau: np.ndarray, label: str = "",
               solved: np.ndarray | None = None, q: np.ndarray | None = None):
        """A complete ``foxglove.SceneUpdate`` (every entity, so a late viewer or a seek sees the whole scene):
        the platform and its cables at ``pose`` (6,) (left out when None), cable colours from ``tau`` (n,) N;
        ``solved`` (6,): the solve's initial pose, drawn as entity ``solution`` (platform and cables, green);
        ``q`` (4,): the platform's quaternion at ``pose`` if the caller has it (else computed)."""
        from foxglove.messages import (
            CubePrimitive,
            KeyValuePair,
            LinePrimitive,
            LinePrimitiveLineType,
            SceneEntity,
            SceneUpdate,
            TextPrimitive,
        )

        robot, stamp = self.robot, _stamp(t_ns)
        frame, pulleys, ghosts = self._fixed
        entities = [SceneEntity(timestamp=stamp, frame_id=WORLD, id="frame", lines=frame),
                    SceneEntity(timestamp=stamp, frame_id=WORLD, id="pulleys", spheres=pulleys)]
        if ghosts is not None:
            entities.append(SceneEntity(timestamp=stamp, frame_id=WORLD, id="ghosts", cubes=ghosts[0],
                                        texts=ghosts[1]))
        if solved is not None:
            seg = cable_segments(robot, solved)
            green = _colour((0.3, 0.9, 0.4, 0.6))
            entities.append(SceneEntity(
                timestamp=stamp, frame_id=WORLD, id="solution",
                cubes=[CubePrimitive(pose=_pose(solved[:3], quaternion(solved, robot.orientation)[0]),
                                     size=_vec(self.platform_size), color=green)],
                lines=[LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=2.0, scale_invariant=True,
                                     color=green,
                                     points=[_point(p) for p in np.stack([seg.exits[0], seg.anchors[0]], 1)
                                             .reshape(-1, 3)])]))
        if pose is not None and np.all(np.isfinite(pose)):
            seg = cable_segments(robot, pose)
            cols = tension_colours(tau, self.low, self.high)
            pts = np.stack([seg.exits[0], seg.anchors[0]], 1).reshape(-1, 3)
            entities.append(SceneEntity(
                timestamp=stamp, frame_id=WORLD, id="cables", lines=[LinePrimitive(
                    type=LinePrimitiveLineType.LineList, thickness=4.0, scale_invariant=True,
                    points=[_point(p) for p in pts], colors=[_colour(c) for c in np.repeat(cols, 2, axis=0)])],
                metadata=[KeyValuePair(key=f"tau_{i + 1}", value=f"{v:.2f}") for i, v in enumerate(tau)]))
            q = quaternion(pose, robot.orientation)[0] if q is None else q
            ring = np.r_[np.arange(robot.n), 0]
            entities.append(SceneEntity(
                timestamp=stamp, frame_id=WORLD, id="platform",
                cubes=[CubePrimitive(pose=_pose(pose[:3], q), size=_vec(self.platform_size),
                                     color=_colour((1.0, 0.75, 0.2, 0.9)))],
                lines=[LinePrimitive(type=LinePrimitiveLineType.LineStrip, thickness=2.0, scale_invariant=True,
                                     color=_colour((1.0, 0.75, 0.2, 1.0)),
                                     points=[_point(p) for p in seg.anchors[0][ring]])]))
        if label:
            white = _colour((1.0, 1.0, 1.0, 1.0))
            top = np.asarray(robot.d, float)
            entities.append(SceneEntity(timestamp=stamp, frame_id=WORLD, id="label", texts=[TextPrimitive(
                pose=_pose([top[:, 0].mean(), top[:, 1].mean(), top[:, 2].max() + 0.2], IDENTITY), billboard=True,
                font_size=14.0, scale_invariant=True, color=white, text=label)]))
        return SceneUpdate(entities=entities)

    @cached_property
    def _fixed(self) -> tuple[list, list, tuple[list, list] | None]:
        """The primitives that never move, built once: the frame's lines, the pulleys, the ghosts (or None)."""
        from foxglove.messages import (
            CubePrimitive,
            LinePrimitive,
            LinePrimitiveLineType,
            SpherePrimitive,
            TextPrimitive,
        )

        robot = self.robot
        grey, white = _colour((0.6, 0.6, 0.6, 1.0)), _colour((1.0, 1.0, 1.0, 1.0))
        frame = [LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=2.0, scale_invariant=True, color=grey,
                               points=[_point(p) for p in frame_edges(robot).reshape(-1, 3)])]
        pulleys = [SpherePrimitive(pose=_pose(d, IDENTITY), size=_vec([2 * r] * 3), color=white)
                   for d, r in zip(robot.d, robot.r, strict=True)]
        if not len(self.ghosts):
            return frame, pulleys, None
        q = quaternion(self.ghosts, robot.orientation)
        blue = (0.5, 0.7, 1.0)
        cubes = [CubePrimitive(pose=_pose(g[:3], qk), size=_vec(self.platform_size), color=_colour((*blue, 0.25)))
                 for g, qk in zip(self.ghosts, q, strict=True)]
        texts = [TextPrimitive(pose=_pose(g[:3] + [0, 0, 0.08], IDENTITY), billboard=True, font_size=12.0,
                               scale_invariant=True, color=_colour((*blue, 0.8)), text=str(j))
                 for j, g in enumerate(self.ghosts)]
        return frame, pulleys, (cubes, texts)

    def transform(self, t_ns: int, pose: np.ndarray, q: np.ndarray | None = None):
        """``foxglove.FrameTransform`` world -> platform at ``pose`` (6,) (``q``: its quaternion, if known)."""
        from foxglove.messages import FrameTransform, Quaternion

        q = quaternion(pose, self.robot.orientation)[0] if q is None else q
        return FrameTransform(timestamp=_stamp(t_ns), parent_frame_id=WORLD, child_frame_id=PLATFORM,
                              translation=_vec(pose[:3]),
                              rotation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


def log_message(t_ns: int, text: str, level: str = "Info"):
    """A ``foxglove.Log`` line from cdpr (level Debug, Info, Warning, Error or Fatal)."""
    from foxglove.messages import Log, LogLevel

    return Log(timestamp=_stamp(t_ns), level=getattr(LogLevel, level), message=text, name="cdpr")


class PoseTracker:
    """The platform's estimated pose from the measured tensions: the direct statics (calib.equilibrium). The
    first update solves it to convergence; each later one takes one Newton step on the equilibrium equations
    from the previous estimate (one residual and Jacobian evaluation: the tensions change little between two
    updates, so the estimate converges at rest and follows a transition over successive updates)."""

    MAX_STEP = (0.2, 0.3)  # m, rad: the largest step per update, as direct_statics limits its own

    def __init__(self, robot: Robot):
        self.robot = robot
        self.pose: np.ndarray | None = None

    def update(self, tau: np.ndarray) -> np.ndarray | None:
        """The estimate (6,) after the tensions (n,) N; None while a tension is missing or before a first
        converged solve."""
        from calib.equilibrium import direct_statics
        from calib.statics import equilibrium_residual

        t = np.asarray(tau, dtype=float)
        if not np.all(np.isfinite(t)):
            return None if self.pose is None else self.pose.copy()
        if self.pose is None:
            res = direct_statics(self.robot, t)
            if not res.converged[0]:
                return None
            self.pose = res.poses[0]
            return self.pose.copy()
        r, jac = equilibrium_residual(self.robot, self.pose[None], t[None])
        try:
            step = np.linalg.solve(jac[0], -r[0])
        except np.linalg.LinAlgError:
            return self.pose.copy()
        scale = max(np.abs(step[:3]).max() / self.MAX_STEP[0], np.abs(step[3:]).max() / self.MAX_STEP[1], 1.0)
        z = self.pose + step / scale
        if np.all(np.isfinite(z)):
            self.pose = z
        return self.pose.copy()


def static_poses(robot: Robot, tau: np.ndarray, guess: np.ndarray | None = None) -> np.ndarray:
    """The direct statics (k, 6) of tensions (k, n) N, converged (NaN rows where a tension is missing or the
    solve did not converge); ``guess`` (k, 6) or None for the robot's default."""
    from calib.equilibrium import direct_statics

    t = np.asarray(tau, dtype=float)
    out = np.full((len(t), 6), np.nan)
    ok = np.all(np.isfinite(t), 1)
    if ok.any():
        res = direct_statics(robot, t[ok], guess=None if guess is None else np.asarray(guess)[ok])
        out[np.flatnonzero(ok)[res.converged]] = res.poses[res.converged]
    return out
