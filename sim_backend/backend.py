"""The simulated prototype as a set of devices: physics + emulated CAN nodes + serial devices, in lockstep.

:class:`SimBackend` creates the physics at a power-on equilibrium, a simulated CAN channel with a
unique name carrying the emulated CiA 402 drives and CiA 406 encoders (canopen LocalNodes), serial lines for
the load-cell amplifier and the AHRS (socket pairs the drivers open as ``cdprsim://`` ports, or ptys with
``serial_lines="pty"``: ``sim_backend.pty``), and one SYNC subscriber that runs the lockstep. The channel is a
``cdpr_sim`` one (``sim_backend.sim_bus``, a python-can interface plugin): a frame the master sends is handled in
the master's own thread before its send returns, answers included, and the master's network has decoded the
answers by then. The physics and the serial devices run one control period ahead of
the CAN nodes, in a child process on a machine with two cores (``sim_backend.plant_link``). For each SYNC
``count`` the master sends:

1. the state of the plant at ``count * control_period`` is published to the nodes (:attr:`physics`);
2. every drive applies the last RPDO targets (``apply_targets``) and engages the winch brake in every state
   but operation enabled, as a servo's holding brake does;
3. the plant core takes these commands: the load-cell amplifier writes the tick's line and the AHRS its
   sample (when one is due), the physics steps to the next SYNC with the new commands (a synchronous target
   acts from the SYNC after it arrives, as on a CiA 402 drive, so the torque computed from the readings of
   SYNC ``count`` acts from SYNC ``count + 1`` on), then the serial and cable faults due at the next SYNC
   are injected and its load-cell line is made;
4. every node transmits its TPDOs (``on_sync``);
5. the handler returns once the plant core has confirmed that the serial samples of step 3 are on their lines
   (``PlantLink.sent``): the master, reading its serial ports after the SYNC, finds this SYNC's samples
   whether the plant's process ran at once or a second later (a loaded machine).

The simulated clock is the physics time, exactly ``count * control_period`` at SYNC ``count`` (0 at
power-on); the load-cell line written at SYNC ``count`` has device sequence ``count - 1``, the AHRS samples
on its own output-rate grid of that clock. Nothing here reads wall time, so a run costs far less wall time
than robot time and the same seed gives the same frames and bytes, with or without the child process. An
exception inside the lockstep (it runs inside the master's SYNC send) is kept in :attr:`SimBackend.errors`;
the nodes then stay silent. The drivers connect through :attr:`SimBackend.devices` (a
``drivers.config.DeviceConfig``); :meth:`SimBackend.truth` gives the true pose now or at an earlier tick.
"""

from __future__ import annotations

import itertools
import math
import os
import threading
from dataclasses import dataclass
from pathlib import Path

import canopen
import numpy as np

from calib.equilibrium import direct_statics
from calib.robot import Robot
from calib.statics import tension_model
from drivers.can_bus import SYNC_COB_ID
from drivers.config import AhrsConfig, CanConfig, DeviceConfig, NodeConfig, SerialConfig
from sim_backend.can_drive_emulator import CanDriveEmulator, DriveEmulatorConfig
from sim_backend.can_encoder_emulator import CanEncoderEmulator
from sim_backend.config import SimConfig, SimConfigError, load_sim_config
from sim_backend.loadcell_emulator import LoadCellEmulator
from sim_backend.physics import CablePhysics, Sway, pose_of, snapshot_parts
from sim_backend.plant_link import (
    ANSWER_TIMEOUT,
    ChildPlantLink,
    InProcessPlantLink,
    PlantCore,
    PlantLink,
    PlantView,
    child_process_possible,
)
from sim_backend.pty import close_socket_line, open_pty_pair, open_socket_line
from sim_backend.sim_bus import SimBus
from sim_backend.xsens_emulator import XsensEmulator, XsensNoise

DRIVE_IDS = (1, 2, 3, 4, 5, 6, 7, 8)
ENCODER_IDS = (11, 12, 13, 14, 15, 16, 17, 18)
_CAN_FAULTS = ("can_frames_lost", "drive_fault")  # faults the CAN nodes act out; the plant core has the others
PRETENSION = 50.0  # N, the power-on pretension around which the resting tensions are drawn
_channel_ids = itertools.count(1)


@dataclass(frozen=True)
class TruthSample:
    """The true state at one SYNC tick: sync count, sim time s, pose (6,) m/rad, load-cell tensions (n,) N."""

    sync_count: int
    time: float
    pose: np.ndarray
    tensions: np.ndarray


def power_on_state(robot: Robot, seed: int, spread: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """A plausible power-on equilibrium (pose (6,), tensions (n,)) of ``robot`` (the TRUE robot).

    The platform rests under a low pretension: tensions PRETENSION * (1 + e) with e drawn from the seed, so
    that the resting position falls within ``spread`` m (per axis) of the pose the equal pretension holds.
    """
    rng = np.random.default_rng([seed, 7])
    base = np.full(robot.n, PRETENSION)
    home = direct_statics(robot, base)
    if not home.converged[0]:
        raise SimConfigError(f"robot '{robot.name}': no equilibrium under a pretension of {PRETENSION} N.")
    for scale in (0.06, 0.03, 0.015, 0.0):
        tau = base * (1.0 + scale * rng.uniform(-1.0, 1.0, robot.n))
        res = direct_statics(robot, tau, guess=home.poses)
        if res.converged[0] and np.abs(res.poses[0, :3] - home.poses[0, :3]).max() <= max(spread, 1e-9):
            return res.poses[0], tau
    return home.poses[0], base


class SimBackend:
    """The simulated IRMA4U prototype behind real device protocols (use as a context manager).

    robot: the robot description the controller uses (the model); sim_config: a :class:`SimConfig`, a YAML
    path or None (nominal); seed: all randomness (power-on pose, sensor noise, frame loss); control_period:
    s of simulated time per SYNC; initial_pose: (6,) to start from instead of the seeded power-on pose (the
    platform is let settle there with the brakes on before power-on); ahrs_rate: the AHRS output rate (Hz)
    that :attr:`devices` asks the driver to request, as the ``ahrs: rate`` of a device file does;
    plant_process: run the physics and the serial devices in a child process (None: when the machine has a
    second core for it; the results are the same either way); serial_lines: ``"socket"`` (default: a Unix socket
    pair per device, which wakes its reader from the device's write) or ``"pty"`` (a pseudo-terminal per device,
    its slave a device path as a USB adapter's; its bytes reach the reader through a kernel worker thread, late
    on a loaded machine: docs/live.md). The same bytes reach the drivers either way.

    :attr:`physics` is the plant as the CAN nodes see it at the last SYNC (``sim_backend.plant_link.PlantView``).
    """

    def __init__(
        self,
        robot: Robot,
        sim_config: SimConfig | str | Path | None = None,
        seed: int = 0,
        control_period: float = 0.005,
        initial_pose: np.ndarray | None = None,
        heartbeat_period: float = 0.1,
        ahrs_rate: float = 100.0,
        plant_process: bool | None = None,
        serial_lines: str = "socket",
    ):
        if not 0.0 < control_period <= 0.1:
            raise SimConfigError(f"SimBackend: control_period = {control_period!r} s must be in (0, 0.1].")
        self.robot = robot
        self.config = sim_config if isinstance(sim_config, SimConfig) else load_sim_config(sim_config, robot.n)
        self.seed = int(seed)
        self.control_period = float(control_period)
        self.heartbeat_period = float(heartbeat_period)
        self.ahrs_rate = float(ahrs_rate)
        self.true_robot = self.config.true_robot(robot)
        self.initial_pose = None if initial_pose is None else np.asarray(initial_pose, float).reshape(6)
        self.plant_process = plant_process
        if serial_lines not in ("socket", "pty"):
            raise SimConfigError(f"SimBackend: serial_lines = {serial_lines!r} is neither 'socket' nor 'pty'.")
        self.serial_lines = serial_lines
        self.physics: PlantView | None = None
        self.devices: DeviceConfig | None = None
        self.drives: list[CanDriveEmulator] = []
        self.encoders: list[CanEncoderEmulator] = []
        self._nodes: list = []  # drives then encoders
        self.sync_count = 0
        self.errors: list[str] = []  # exceptions raised inside the lockstep (the SYNC handler)
        self._lock = threading.RLock()
        self._history: list[tuple[int, tuple[float, ...]]] = []  # (SYNC count, PlantView state) per tick
        self._push = None  # the sway's force law (sway_push), made when first asked
        self._link: PlantLink | None = None
        self._fds: list[int] = []
        self._urls: list[str] = []  # the socket lines' URLs (their driver's ends are held until close)
        self._bus: SimBus | None = None
        self._network = None
        self._started = False

    # -- life cycle ---------------------------------------------------------------------------------------
    def __enter__(self) -> SimBackend:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> SimBackend:
        """Power on: physics at rest, CAN nodes booted, serial devices listening."""
        if self._started:
            return self
        n = self.robot.n
        if n > len(DRIVE_IDS):
            raise SimConfigError(f"robot '{self.robot.name}': the simulator handles at most {len(DRIVE_IDS)} cables.")
        seeds = np.random.SeedSequence(self.seed).spawn(2 * n + 2)  # drives, encoders, load cells, AHRS
        rngs = [np.random.default_rng(s) for s in seeds]
        try:
            physics = self._make_physics()
            noise = self.config.sensors
            k_true = self.config.true_transmission(self.robot)
            lc_fd, lc_path = self._open_line("loadcells")
            loadcells = LoadCellEmulator(
                lc_fd, rngs[2 * n], channels=n, offsets=self.config.tension_offset(n),
                gains=self.config.tension_gain(n), rate_hz=1.0 / self.control_period,
                full_scale=self.robot.sensors.load_cell_full_scale, accuracy=self.robot.sensors.load_cell_accuracy,
                noise_std=noise.loadcell_sigma, hysteresis=self.config.loadcell_hysteresis(),
            )
            ahrs_fd, ahrs_path = self._open_line("ahrs")
            roll, pitch = self.config.ahrs_mounting()
            r_sd, p_sd, y_sd = noise.ahrs_sigma
            ahrs = XsensEmulator(ahrs_fd, rngs[2 * n + 1], mounting_roll=roll, mounting_pitch=pitch,
                                 input_convention=self.robot.orientation,
                                 output_convention=self.robot.ahrs_convention,
                                 noise=XsensNoise(roll_pitch_std=r_sd, pitch_std=p_sd, yaw_std=y_sd))
            core = PlantCore(physics, loadcells, ahrs, self.control_period,
                             [f for f in self.config.faults if f.kind not in _CAN_FAULTS])
            torques = [float(x) for x in physics.motor_torque()]
            brakes = [physics.brake(i) for i in range(n)]
            self.physics = PlantView(n, physics.snapshot(), torques, brakes, self.robot.orientation)
            self._link = self._open_link(core)
            self._link.advance(0, torques, brakes)  # the state of the first SYNC
            channel = f"cdpr-sim-{os.getpid()}-{next(_channel_ids)}-{id(self):x}"
            self._network = canopen.Network()  # no notifier: the bus hands it the frames (in the sender's thread)
            self._network.bus = self._bus = SimBus(channel, listeners=self._network.listeners)
            for i in range(n):
                self.drives.append(
                    CanDriveEmulator(self._network, DRIVE_IDS[i], self.physics, i, rng=rngs[i],
                                     control_period=self.control_period,
                                     config=DriveEmulatorConfig(position_noise=noise.encoder_sigma / abs(k_true[i])))
                )
            for i in range(n):
                self.encoders.append(CanEncoderEmulator(self._network, ENCODER_IDS[i], self.physics, i,
                                                        noise=noise.swivel_sigma, rng=rngs[n + i]))
            self._nodes = self.drives + self.encoders  # in the order they answer a SYNC
            self._schedule_faults()
            self.devices = DeviceConfig(
                can=CanConfig(interface="cdpr_sim", channel=channel, bitrate=1_000_000,
                              heartbeat_period=self.heartbeat_period),
                drives=tuple(NodeConfig(f"winch {i + 1}", DRIVE_IDS[i]) for i in range(n)),
                encoders=tuple(NodeConfig(f"swivel {i + 1}", ENCODER_IDS[i]) for i in range(n)),
                loadcells=SerialConfig(lc_path, 115200),
                ahrs=AhrsConfig(ahrs_path, 115200, self.ahrs_rate),
                source=f"<simulated prototype, seed {self.seed}>",
                # the serial devices answer their handshakes from the plant's process (or its threads here),
                # which a loaded machine may run seconds late: waited for as long as the link's own guard
                answer_timeout=ANSWER_TIMEOUT,
            )
            self._record()
            self._network.subscribe(SYNC_COB_ID, self._on_sync)
        except BaseException:
            self.close()
            raise
        self._started = True
        return self

    def close(self) -> None:
        """Stop the lockstep, detach the nodes, release the bus and the ptys (safe to call twice)."""
        net = self._network
        if net is not None:
            try:
                net.unsubscribe(SYNC_COB_ID, self._on_sync)
            except (KeyError, ValueError):
                pass
        link, self._link = self._link, None
        if link is not None:
            link.close()
        for node in self.drives + self.encoders:
            node.close()
        self.drives, self.encoders, self._nodes = [], [], []
        if net is not None:
            net.disconnect()
            self._network = None
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None
        for fd in self._fds:
            try:
                os.close(fd)
            except OSError:
                pass
        self._fds = []
        for url in self._urls:
            close_socket_line(url)
        self._urls = []
        self._started = False

    # -- setup helpers ------------------------------------------------------------------------------------
    def _open_line(self, name: str) -> tuple[int, str]:
        """A serial line for device ``name``: (the device's fd, the port the driver opens), closed by close()."""
        if self.serial_lines == "pty":
            fd, port = open_pty_pair()
        else:
            fd, port = open_socket_line(name)
            self._urls.append(port)
        self._fds.append(fd)
        return fd, port

    def _new_physics(self) -> CablePhysics:
        """The plant at power-on, before any step."""
        robot = self.true_robot
        params = self.config.physics_params(robot)
        k = self.config.true_transmission(self.robot)
        if self.initial_pose is None:
            pose, tau = power_on_state(robot, self.seed, self.config.initial_spread)
            return CablePhysics(robot, params, k, pose, tau, brakes=True, sway=self._sway())
        tau = tension_model(robot, self.initial_pose, derivatives=False).tau[0]
        if not np.all(tau > 0):
            raise SimConfigError(
                f"SimBackend: initial_pose = {self.initial_pose.tolist()} needs a slack cable (model tensions "
                f"{np.round(tau, 2).tolist()} N)."
            )
        return CablePhysics(robot, params, k, self.initial_pose, tau, brakes=True, sway=self._sway())

    def sway_push(self, times: np.ndarray) -> np.ndarray:
        """(k, 2) N: the sway's horizontal push on the platform at the sim times ``times`` (s), zero without a
        sway (the plant's own force law, so that a benchmark can tell the platform's rest under the push)."""
        ts = np.atleast_1d(np.asarray(times, float))
        if self._push is None:
            self._push = self._new_physics().push
        push = self._push
        return np.array([push(float(t)) for t in ts]).reshape(ts.size, 2)

    def _make_physics(self) -> CablePhysics:
        ph = self._new_physics()
        if self.initial_pose is None:
            return ph
        for _ in range(int(round(5.0 / self.control_period))):  # settle on the locked winches
            ph.step(self.control_period, t_end=self.sync_count * self.control_period)
        ph.rezero()
        return ph

    def _sway(self) -> Sway | None:
        """The configuration's sway with its phases drawn from this backend's seed."""
        sw = self.config.sway
        return None if sw is None else Sway(sw.amplitude, sw.period, self.seed)

    def _open_link(self, core: PlantCore) -> PlantLink:
        """The core in a child process when asked or possible (forked here, before the CAN bus and its nodes
        exist: it needs none of them), else in this process."""
        if self.plant_process is False or (self.plant_process is None and not child_process_possible()):
            return InProcessPlantLink(core)
        try:
            return ChildPlantLink(core)
        except OSError:  # no process left to fork: the same simulation, on one core
            if self.plant_process:
                raise
            return InProcessPlantLink(core)

    def _schedule_faults(self) -> None:
        """CAN faults go to the nodes (they act on their own sim time); the plant core has the others."""
        for f in self.config.faults:
            if f.kind == "can_frames_lost":
                for node in self.drives + self.encoders:
                    node.lose_frames(f.fraction, start=f.t, duration=f.duration)
            elif f.kind == "drive_fault":
                self.drives[f.target].schedule_fault(f.t)

    # -- the lockstep -------------------------------------------------------------------------------------
    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        try:
            self.tick(data[0] if data else 0)
        except Exception as exc:  # not the master's problem at its send: keep it for the caller
            self.errors.append(f"{type(exc).__name__}: {exc}")

    def tick(self, counter: int = 0) -> int:
        """One SYNC (``counter``: its counter byte, 0 if none): the state of this SYNC -> targets -> the plant
        core (faults, serial samples, physics step to the next SYNC) -> TPDOs. Returns the SYNC count."""
        with self._lock:
            view = self.physics
            view.publish(self._link.collect())  # raises SimulationError if the core failed: nodes stay silent
            self.sync_count += 1
            count, t = self.sync_count, view.time
            self._link.emit(count)  # the serial samples first: on the wire by the time the master reads them
            for drive in self.drives:
                drive.apply_targets()  # the drive also engages or releases its winch's brake with its state
            self._link.advance(count, view.torques, view.brakes)  # in the child: while the nodes answer
            for node in self._nodes:
                if node.idle_at(count, t):  # nothing due: the node counts this SYNC at its next full one
                    node.last_sync_count = count
                else:
                    node.on_sync(count, counter)
            # the SYNC's serial samples are on their lines before the master's send returns: its reads find
            # them however late the plant's process ran (lockstep, not a race against a wall-time timeout)
            self._link.sent(count)
            self._record()
            return self.sync_count

    @property
    def plant_pid(self) -> int | None:
        """Process ID of the plant's child process (None when the plant runs in this process)."""
        return getattr(self._link, "pid", None)

    def plant_waited(self) -> float:
        """Seconds the SYNC handler has waited so far for the plant's child process to answer (0 in process)."""
        return float(getattr(self._link, "waited", 0.0))

    def plant_timing(self) -> dict[str, dict[str, float]]:
        """The plant child's hand-over per SYNC so far ({} in process): ``wake`` (the emit to the child running),
        ``confirm`` (the SYNC handler's wait for the samples), ``step`` (the commands to the state posted),
        ``collect`` (the handler's wait for the state), each ``plant_link.Durations.summary``."""
        timing = getattr(self._link, "timing", {})
        return {k: d.summary() for k, d in timing.items()}

    def _record(self) -> None:
        self._history.append((self.sync_count, self.physics.state))

    # -- truth --------------------------------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Simulated time since power-on, s."""
        return self.physics.time

    def _sample(self, rec) -> TruthSample:
        count, state = rec
        parts = snapshot_parts(self.robot.n)
        pose = pose_of(state[parts["xg"]], state[parts["q"]], self.true_robot.com.tolist(), self.robot.orientation)
        return TruthSample(count, state[0], np.array(pose), np.array(state[parts["cable_tension"]]))

    def truth(self, at_time: float | None = None, sync_count: int | None = None) -> TruthSample:
        """The true state now, at the last tick at or before sim time ``at_time`` (s), or at SYNC ``sync_count``."""
        with self._lock:
            hist = self._history
            if sync_count is not None:
                if not 0 <= sync_count <= hist[-1][0]:
                    raise ValueError(f"sync_count = {sync_count} is not between 0 and {hist[-1][0]}.")
                i = min(sync_count, len(hist) - 1)
                while hist[i][0] > sync_count:  # a tick that failed left no record: the one before it
                    i -= 1
                return self._sample(hist[i])
            if at_time is None:
                return self._sample(hist[-1])
            if at_time < 0 or not math.isfinite(at_time):
                raise ValueError(f"at_time = {at_time!r} s is not a time since power-on.")
            lo, hi = 0, len(hist) - 1
            while lo < hi:  # last record with time <= at_time
                mid = (lo + hi + 1) // 2
                if hist[mid][1][0] <= at_time + 1e-12:
                    lo = mid
                else:
                    hi = mid - 1
            return self._sample(hist[lo])
