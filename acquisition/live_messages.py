"""The messages of a run's view (acquisition/live.py): one :class:`Frame` of a run in, the topics and messages
of the live view, the replay and the MCAP export out."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from acquisition.scene import SceneModel, log_message, number
from calib.robot import Robot
from calib.scene import quaternion


@dataclass(frozen=True)
class Frame:
    """One moment of a run for the view: log time (ns), run time t (s; NaN before the run log starts), the
    readings as logged (tau (n,) N, tau_ref (n,) N, dl (n,) m and dsigma (n,) rad since power-on, roll, pitch,
    dyaw rad), phase, setpoint, SYNC tick, and whether it is a row of samples.csv."""

    t_ns: int
    t: float
    tau: np.ndarray
    tau_ref: np.ndarray
    dl: np.ndarray
    dsigma: np.ndarray
    roll: float
    pitch: float
    dyaw: float
    phase: str
    setpoint: int
    tick: int
    logged: bool


class RunView:
    """The messages of a run's view (topic, message), frame by frame; remembers the phase and the supervisor's
    state to log their changes. Shared by the live startup, the live replay and the MCAP export."""

    def __init__(self, robot: Robot, ghosts: np.ndarray | None, slack: float, overload: float):
        self.robot = robot
        self.scene = SceneModel.for_robot(robot, ghosts)
        self.slack, self.overload = float(slack), float(overload)
        self._phase: tuple[str, int] | None = None
        self._state: tuple[str, str | None] | None = None
        self._state_ns = 0

    @property
    def stop(self) -> str | None:
        """The stop the supervisor reported last (None: no stop)."""
        return None if self._state is None else self._state[1]

    def set_ghosts(self, ghosts: np.ndarray) -> None:
        """The planned poses (k, 6) shown as ghosts (a sequential plan grows)."""
        self.scene = SceneModel.for_robot(self.robot, ghosts)

    def sample(self, f: Frame) -> dict[str, Any]:
        """The /samples message: the columns of samples.csv by name."""
        n = self.robot.n
        msg: dict[str, Any] = {"t": number(f.t)}
        for g, a in (("tau", f.tau), ("tau_ref", f.tau_ref), ("dl", f.dl), ("dsigma", f.dsigma)):
            vals = np.asarray(a, dtype=float).tolist()
            for i in range(n):
                msg[f"{g}_{i + 1}"] = number(vals[i])
        msg.update(roll=number(f.roll), pitch=number(f.pitch), dyaw=number(f.dyaw), phase=str(f.phase),
                   setpoint=int(f.setpoint), tick=int(f.tick))
        return msg

    def frame(self, f: Frame, pose: np.ndarray | None, scene: bool = True, solved: np.ndarray | None = None
              ) -> list[tuple[str, Any]]:
        """The messages of one frame: its sample (if logged), the scene and transform at ``pose`` (6,) (None:
        unknown; ``solved``: the solve's initial pose, see SceneModel.update), and a log line when the phase or
        setpoint changes."""
        out: list[tuple[str, Any]] = []
        if f.logged:
            out.append(("/samples", self.sample(f)))
        if (f.phase, f.setpoint) != self._phase:
            self._phase = (f.phase, f.setpoint)
            where = f" setpoint {f.setpoint}" if f.setpoint >= 0 else ""
            out.append(("/log", log_message(f.t_ns, f"phase {f.phase}{where}")))
        if scene:
            label = f"{f.phase}" + (f" {f.setpoint}" if f.setpoint >= 0 else "")
            q = quaternion(pose, self.robot.orientation)[0] if pose is not None and np.all(np.isfinite(pose)) else None
            out.append(("/scene", self.scene.update(f.t_ns, pose, f.tau, label, solved, q)))
            if pose is not None:
                out.append(("/tf", self.scene.transform(f.t_ns, pose, q)))
        return out

    def supervisor(self, t_ns: int, t: float, state: str, stop: str | None, every_ns: int = 1_000_000_000
                   ) -> list[tuple[str, Any]]:
        """/supervisor when its state changes, else once per ``every_ns``; a stop is also a /log error."""
        key = (state, stop)
        if key == self._state and t_ns - self._state_ns < every_ns:
            return []
        out: list[tuple[str, Any]] = [("/supervisor", {"t": number(t) if number(t) is not None else 0.0,
                                                      "state": state, "slack_N": self.slack,
                                                      "overload_N": self.overload, "stop": stop})]
        if key != self._state and state != "watching":
            out.append(("/log", log_message(t_ns, f"supervisor: {state}" + (f": {stop}" if stop else ""),
                                            "Error" if stop else "Warning")))
        self._state, self._state_ns = key, t_ns
        return out

    @staticmethod
    def window(t_ns: int, first: int, last: int, t_first: float, t_last: float, setpoint: int,
               source: str) -> list[tuple[str, Any]]:
        msg = {"first": int(first), "last": int(last), "t_first": float(t_first), "t_last": float(t_last),
               "setpoint": int(setpoint), "source": source}
        return [("/windows", msg), ("/log", log_message(t_ns, f"equilibrium window of setpoint {setpoint}: samples "
                                                          f"{first}..{last} ({t_first:.1f}..{t_last:.1f} s)"))]

    @staticmethod
    def event(t_ns: int, ev: dict[str, Any]) -> list[tuple[str, Any]]:
        msg = {"t": float(ev["t"]), "kind": str(ev["kind"]), "message": str(ev["message"])}
        return [("/events", msg), ("/log", log_message(t_ns, f"{msg['kind']}: {msg['message']}", "Error"))]

    @staticmethod
    def estimate(t_ns: int, pose: int, t: float, initial_pose, sigma, position_sigma: float | None
                 ) -> list[tuple[str, Any]]:
        p = [float(v) for v in initial_pose][:6]
        ps = None if position_sigma is None else number(position_sigma)
        msg = {"pose": int(pose), "t": float(t), "initial_pose": p,
               "initial_pose_sigma": None if sigma is None else [number(v) for v in sigma][:6],
               "position_sigma_m": ps}
        text = (f"online estimate after pose {pose}: x0 {p[0]:+.4f} {p[1]:+.4f} {p[2]:+.4f} m"
                + (f", 1-sigma {1000 * ps:.2f} mm" if ps is not None else " (reference window)"))
        return [("/estimate", msg), ("/log", log_message(t_ns, text))]
