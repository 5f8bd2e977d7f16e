"""Joint-space force control: one tension controller per winch on load-cell feedback, all winches in one step.

The command of winch i is a motor torque (N m). A cable tension tau (N) needs the motor torque
radius_i * tau, where radius_i = -length_per_motor_rev_i / (2 pi) is the signed transmission radius (m/rad):
the cable pulls the drum towards paying out, so the motor must push the other way. The controller works in
tension units and converts at the end:

    u = tau_ref + kp e + I,    e = tau_ref - tau_meas,    dI/dt = ki e  if |e_f| > deadband, else -I / T_leak  (N)
    e_f = tau_ref - m,    T_f dm/dt = tau_meas - m             (the dead band judges a low-passed reading)
    torque = rate_limit(clip(radius u, torque_min, torque_max))                                   (N m)

The dead band judges the tension reading through a first-order low-pass of ``integral_filter`` s (the
reference unfiltered); the integral, once on, integrates the raw error (no lag in the loop). A winch its
friction holds still does not follow the command, so with the band on the raw reading the load cells' noise
excursions beyond it (1 N per tick against 1.5 N: 13 % of the ticks) pumped the integral in a random walk
until the winch broke free and stuck elsewhere (stick-slip hunting in a hold, issue 29); filtered, that noise
is sigma sqrt(dt / 2 T_f) (0.16 N for 1 N at 200 Hz), and only a sustained error switches the integral on.
Inside the dead band the integral leaks away in ``integral_leak`` s: what it learnt against the sliding
friction of a move would otherwise keep a stopped winch's net torque at the edge of its friction band, where
the proportional term's share of the noise breaks it free again and again.

Anti-windup by conditional integration (the integral is frozen while the command is held by the bounds or
the rate limit and the error would push it further) and a bound on the integral itself. Cables only pull:
the tension command is never below ``min_command``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from calib.robot import Robot
from drivers.interfaces import DeviceError


@dataclass(frozen=True)
class ControllerConfig:
    """Gains and limits of the tension controller. Tension-equivalent units unless named otherwise."""

    rate: float = 500.0  # Hz, control rate (200-500)
    # the drives apply a target at the SYNC after it arrives (CiA 402 synchronous RPDO): the tension read at
    # SYNC n answers a torque first at SYNC n + 2. With that delay kp 0.5, ki 15 keeps the loop stable from a
    # soft cable (EA 10 kN, winch-cable resonance near 6 Hz) to the nominal one (EA 2 MN); kp 1, ki 30 does not
    kp: float = 0.5  # N of command per N of tension error
    ki: float = 15.0  # N of command per N s of error (1/s)
    integral_limit: float = 60.0  # N, bound of |I|
    min_command: float = 5.0  # N, lowest tension command (cables only pull)
    max_command: float = 400.0  # N, highest tension command
    max_command_rate: float = 1500.0  # N/s, rate limit of the torque command expressed in tension
    integral_deadband: float = 1.5  # N, errors smaller than this are not integrated (no friction hunting)
    # s, time constant of the low-pass on the reading the integral's dead band judges (0: the raw reading);
    # 0.1 s makes 1 N of per-tick cell noise 0.16 N at 200 Hz, well inside the dead band
    integral_filter: float = 0.1
    # s, while the filtered error is inside the dead band the integral decays with this time constant (0: held)
    integral_leak: float = 1.0

    def __post_init__(self) -> None:
        if not 50.0 <= self.rate <= 2000.0:
            raise ValueError(f"controller rate must be within 50..2000 Hz, got {self.rate!r}.")
        for name in ("kp", "ki", "integral_limit", "min_command", "max_command_rate", "integral_filter",
                     "integral_leak"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"controller field '{name}' must be non-negative, got {getattr(self, name)!r}.")
        if self.max_command <= self.min_command:
            raise ValueError(f"controller max_command {self.max_command} must exceed min_command {self.min_command}.")

    @property
    def period(self) -> float:
        return 1.0 / self.rate


def transmission_radius(robot: Robot) -> np.ndarray:
    """Signed transmission radius (n,) m/rad: motor torque = radius * cable tension."""
    lpr = np.asarray(robot.sensors.length_per_motor_rev, dtype=float)
    if lpr.shape != (robot.n,):
        raise ValueError(
            f"robot '{robot.name}': field 'sensors.length_per_motor_rev' must give one value per cable ({robot.n})."
        )
    return -lpr / (2.0 * math.pi)


class TensionController:
    """PI tension control with feed-forward, anti-windup and torque rate limits, for n winches at once.

    One step runs per control tick on n <= 8 channels, where numpy's per-call cost (about 1 us per ufunc,
    some thirty of them) would be most of the step: :meth:`update` works channel by channel on floats, with
    the same operations in the same order as the array formulas above (the results are the same doubles).
    """

    def __init__(self, radius: np.ndarray, config: ControllerConfig | None = None):
        r = np.asarray(radius, dtype=float)
        if r.ndim != 1 or np.any(r == 0):
            raise ValueError(f"transmission radii must be a non-zero vector, got {r.tolist()}.")
        self.config = config or ControllerConfig()
        self.n = len(r)
        self._radius = r.tolist()
        self._integral = [0.0] * self.n  # N
        self._filtered = [math.nan] * self.n  # N, the low-passed reading the integral sees (NaN: none yet)
        self._command = [0.0] * self.n  # last tension-equivalent command, N
        self._feedback = [True] * self.n  # channels whose load cell is trusted
        self._saturated = [False] * self.n

    @property
    def radius(self) -> np.ndarray:
        """Signed transmission radii (n,) m/rad."""
        return np.array(self._radius)

    @property
    def integral(self) -> np.ndarray:
        """Integral term (n,) N."""
        return np.array(self._integral)

    @property
    def command(self) -> np.ndarray:
        """Last tension-equivalent command (n,) N."""
        return np.array(self._command)

    @property
    def feedback(self) -> np.ndarray:
        """Channels (n,) bool whose load cell is trusted."""
        return np.array(self._feedback, dtype=bool)

    @property
    def saturated(self) -> np.ndarray:
        """Channels (n,) bool whose command was held by a bound or the rate limit at the last step."""
        return np.array(self._saturated, dtype=bool)

    def reset(self, command: np.ndarray | None = None) -> None:
        """Zero the integral; the rate limit starts from ``command`` (N, tension-equivalent) or zero."""
        self._integral = [0.0] * self.n
        self._filtered = [math.nan] * self.n
        self._command = [0.0] * self.n if command is None else np.broadcast_to(
            np.asarray(command, dtype=float), (self.n,)).tolist()

    def open_loop(self, channels: np.ndarray) -> None:
        """Stop using the load cells of ``channels`` (bool or index array): feed-forward only, integral kept."""
        fb = self.feedback
        fb[channels] = False
        self._feedback = fb.tolist()

    def update(self, tau_ref: np.ndarray, tau_meas: np.ndarray, dt: float) -> np.ndarray:
        """One control step: references and measurements (n,) N, step dt (s); returns motor torques (n,) N m."""
        c = self.config
        kp, ki, lo, hi, band, lim_i = (c.kp, c.ki, c.min_command, c.max_command, c.integral_deadband,
                                       c.integral_limit)
        step = c.max_command_rate * dt
        gain = 1.0 if c.integral_filter <= 0.0 else dt / (c.integral_filter + dt)  # backward-Euler low-pass
        filtered = self._filtered
        keep = 1.0 if c.integral_leak <= 0.0 else c.integral_leak / (c.integral_leak + dt)
        ref = np.asarray(tau_ref, dtype=float).tolist()
        meas = np.asarray(tau_meas, dtype=float).tolist()
        integral, command, feedback = self._integral, self._command, self._feedback
        saturated = [False] * self.n
        torque = [0.0] * self.n
        # the bounds as comparisons, not min(max()) calls (a dozen builtin calls fewer per tick); they give what
        # min(max(x, lo), hi) gives, a NaN included: it fails both tests and stays NaN, as with np.clip
        for i, radius in enumerate(self._radius):
            fb = feedback[i]
            err = ref[i] - meas[i] if fb else 0.0
            raw = ref[i] + kp * err + integral[i]
            bounded = lo if raw < lo else hi if raw > hi else raw
            prev = command[i]
            a, b = prev - step, prev + step
            limited = a if bounded < a else b if bounded > b else bounded
            sat = (limited < raw and err > 0) or (limited > raw and err < 0)
            saturated[i] = sat
            m = filtered[i]
            m = filtered[i] = meas[i] if m != m else m + gain * (meas[i] - m)  # m != m: NaN, the first reading
            ef = ref[i] - m if fb else 0.0
            v = (integral[i] + ki * err * dt if abs(ef) > band else keep * integral[i]) if not sat and fb \
                else integral[i]
            integral[i] = -lim_i if v < -lim_i else lim_i if v > lim_i else v
            command[i] = limited
            torque[i] = radius * limited
        self._saturated = saturated
        return np.array(torque)

    def torque_for(self, tension: np.ndarray) -> np.ndarray:
        """Feed-forward torque (n,) N m for tensions (n,) N."""
        return np.array(self._radius) * np.asarray(tension, dtype=float)


# ---- the device set the loop drives ---------------------------------------------------------------------


@dataclass
class Snapshot:
    """What the loop saw at one tick. Lengths and swivels are deltas since the devices' power-on (m, rad).
    Read-only: a snapshot shares the arrays that did not change with the one before it."""

    tick: int  # clock tick index
    t: float  # s, tick time on the loop's clock
    sync: int  # SYNC counter sent at this tick (0 when the rig sends none)
    tau: np.ndarray  # (n,) N, load cells
    dl: np.ndarray  # (n,) m, cable-length change (winch encoders times the transmission)
    dsigma: np.ndarray  # (n,) rad, swivel-angle change
    roll: float  # rad
    pitch: float  # rad
    yaw: float  # rad, relative to the AHRS start-up heading
    ahrs_time: int = -1  # AHRS SampleTimeFine of the reading used (1e-4 s), -1 if unknown
    missing: tuple[str, ...] = ()  # devices that gave no new reading at this tick


class Rig:
    """The robot's devices as the control loop sees them: one SYNC per tick, the readings of the tick, the
    torque commands. ``lockstep`` waits for the readings answering each SYNC (simulated prototype, with a wall
    ``timeout`` per device); otherwise the latest readings are taken (real robot).

    drives, encoders: per cable, in cable order (drivers.interfaces.WinchDrive / SwivelEncoder); loadcells,
    ahrs: the serial devices; ``send_sync()`` returns the SYNC counter it sent (drivers.can_bus.SyncProducer).
    ``ahrs_period``: the AHRS output period (s); in lockstep the AHRS sample due at a tick is awaited.
    """

    def __init__(self, drives, encoders, loadcells, ahrs, send_sync, period: float, lockstep: bool,
                 ahrs_period: float = 0.01, timeout: float = 0.5):
        self.drives = list(drives)
        self.encoders = list(encoders)
        self.loadcells = loadcells
        self.ahrs = ahrs
        self.send_sync = send_sync
        self.period = float(period)
        self.lockstep = lockstep
        self.ahrs_period = float(ahrs_period)
        self.timeout = float(timeout)
        self.n = len(self.drives)
        self.dead: set[str] = set()  # devices no longer awaited (declared stale)
        self._last: Snapshot | None = None
        self._lc_seq = -1
        self._seq: dict[str, int] = {}
        self._last_fresh: dict[str, float] = {}
        self._link_errors0: dict[str, int] = {}
        self.closer = None  # set by whoever opened the devices
        self._drive_names = [self.drive_name(i) for i in range(self.n)]
        self._encoder_names = [self.encoder_name(i) for i in range(len(self.encoders))]
        self._devices = [*zip(self._drive_names, self.drives, strict=True),
                         *zip(self._encoder_names, self.encoders, strict=True),
                         ("load cells", self.loadcells), ("AHRS", self.ahrs)]
        # a CAN node may answer every n-th SYNC only (its ``every``, with ``due(count)``): its period is n ticks
        self._periods = {name: self.period * getattr(dev, "every", 1) for name, dev in self._devices}
        self._periods["AHRS"] = max(self.ahrs_period, self.period)
        # (name, device, due(count) or None for every SYNC) of the CAN nodes, in cable order
        self._drive_slots = [(nm, d, getattr(d, "due", None)) for nm, d in zip(self._drive_names, self.drives,
                                                                                  strict=True)]
        self._encoder_slots = [(nm, e, getattr(e, "due", None)) for nm, e in zip(self._encoder_names, self.encoders,
                                                                                    strict=True)]

    def close(self) -> None:
        """Release every device (safe to call twice)."""
        closer, self.closer = self.closer, None
        if closer is not None:
            closer()

    # names used in messages and in the supervisor's books
    def drive_name(self, i: int) -> str:
        return f"winch drive {i + 1}"

    def encoder_name(self, i: int) -> str:
        return f"swivel encoder {i + 1}"

    @property
    def devices(self) -> list[tuple[str, object]]:
        """(name, device) of every device, drives and encoders in cable order (a new list)."""
        return list(self._devices)

    def periods(self) -> dict[str, float]:
        """Nominal period of each device's readings, s (a new dict)."""
        return dict(self._periods)

    def statuses(self) -> list[str]:
        return [f"{name}: {dev.status()}" for name, dev in self.devices]

    def faults(self) -> dict[str, str | None]:
        """Pending fault of every device (None when fine)."""
        out = {}
        for name, dev in self._devices:
            try:
                out[name] = dev.fault()
            except Exception as exc:  # a driver that cannot even say: that is a fault too
                out[name] = f"fault query failed ({exc})"
        return out

    def link_errors(self) -> dict[str, int]:
        """Corrupted frames seen on each serial link since :meth:`mark_links` (checksum errors, resyncs)."""
        out = {}
        for name, dev in (("load cells", self.loadcells), ("AHRS", self.ahrs)):
            s = dev.stats
            out[name] = s.checksum_errors + s.resyncs - self._link_errors0.get(name, 0)
        return out

    def mark_links(self) -> None:
        """Count link errors from now on."""
        for name, dev in (("load cells", self.loadcells), ("AHRS", self.ahrs)):
            s = dev.stats
            self._link_errors0[name] = s.checksum_errors + s.resyncs

    def ages(self, t: float) -> dict[str, tuple[float, float]]:
        """Seconds of loop time since each device's last new reading, with its nominal period."""
        per, fresh = self._periods, self._last_fresh
        return {name: (t - fresh.get(name, t), per[name]) for name, _ in self._devices}

    def command(self, torques: np.ndarray) -> None:
        """Cyclic torque targets (n,) N m, sent before the next SYNC (errors ignored during a safe stop)."""
        for d, tq in zip(self.drives, torques, strict=True):
            try:
                d.set_torque(float(tq))
            except Exception:  # DeviceError: a drive that cannot take it; the supervisor sees its fault
                if not self.dead:
                    raise

    def _wait_sync(self, name: str, dev, count: int, deadline: float):
        """The reading of ``dev`` answering SYNC ``count`` (lockstep), or its latest (None if too late);
        ``deadline``: wall time (time.monotonic) to give up at."""
        r = dev.latest()
        if not self.lockstep or name in self.dead or (r is not None and r.sync_count >= count):
            return r
        timeout = max(deadline - _now(), 1e-4)
        waiter = getattr(dev, "wait_for_sync", None)
        if waiter is not None:
            try:
                return waiter(count, timeout)
            except Exception:  # DeviceError: too late; the staleness rule decides
                return dev.latest()
        end = _now() + timeout
        while _now() < end:
            r = dev.latest()
            if r is not None and r.sync_count >= count:
                return r
            _sleep(2e-5)
        return dev.latest()

    def tick(self, tick_index: int, t: float, timeout: float | None = None) -> Snapshot:
        """Send SYNC, gather the readings of this tick; missing ones keep their previous value."""
        budget = self.timeout if timeout is None else timeout
        count = int(self.send_sync() or 0)
        deadline = _now() + budget  # one wall-time budget for all the tick's readings

        def left() -> float:
            return max(deadline - _now(), 1e-4)

        prev = self._last
        n = self.n
        missing = []
        # the arrays of the last snapshot stand where nothing new came (most ticks: the CAN nodes answer every
        # n-th SYNC); one is copied only when a reading changes it (snapshots are read, never written)
        if prev is None:
            dl, dsigma = np.full(n, np.nan), np.full(n, np.nan)
        else:
            dl, dsigma = prev.dl, prev.dsigma
        lockstep, seqs, fresh = self.lockstep, self._seq, self._last_fresh
        for i, (name, d, due) in enumerate(self._drive_slots):
            if due is not None and not due(count):  # not answering this SYNC: its last values stand
                continue
            r = self._wait_sync(name, d, count, deadline)
            if r is not None and (not lockstep or r.sync_count >= count) and (prev is None or r.seq != seqs.get(name)):
                if prev is not None and dl is prev.dl:
                    dl = dl.copy()
                dl[i] = r.delta_length
                seqs[name] = r.seq
                fresh[name] = t
            else:
                missing.append(name)
        for i, (name, e, due) in enumerate(self._encoder_slots):
            if due is not None and not due(count):
                continue
            r = self._wait_sync(name, e, count, deadline)
            if r is not None and (not lockstep or r.sync_count >= count) and (prev is None or r.seq != seqs.get(name)):
                if prev is not None and dsigma is prev.dsigma:
                    dsigma = dsigma.copy()
                dsigma[i] = r.delta_angle
                seqs[name] = r.seq
                fresh[name] = t
            else:
                missing.append(name)
        tau = np.full(n, np.nan) if prev is None else prev.tau
        r = self.loadcells.latest()
        if self.lockstep and "load cells" not in self.dead:
            try:
                r = self.loadcells.wait_for(self._lc_seq + 1, left())
            except DeviceError:  # no sample this tick: the staleness supervision judges the silence
                r = self.loadcells.latest()
        if r is not None and r.device_seq != self._lc_seq:
            tau = np.asarray(r.tau, dtype=float).copy()
            self._lc_seq = r.device_seq
            self._last_fresh["load cells"] = t
        else:
            missing.append("load cells")
        roll, pitch, yaw, stf = (np.nan, np.nan, np.nan, -1) if prev is None else (
            prev.roll, prev.pitch, prev.yaw, prev.ahrs_time)
        if self.lockstep and "AHRS" not in self.dead:
            sim_t = count * self.period  # the simulated prototype steps one period per SYNC from power-on
            due = int(round(math.floor(sim_t / self.ahrs_period + 1e-9) * self.ahrs_period * 1e4))
            # the AHRS samples on its own grid: between two samples there is nothing to read (its port is
            # read, and any device message seen, at the next tick that has a sample due)
            if prev is not None and stf >= due:
                a = None  # the sample due is the one held: the previous values stand
            else:
                a = self.ahrs.latest()
                if a is None or a.sample_time_fine < due:
                    a = _wait_ahrs(self.ahrs, due, left())
        else:
            a = self.ahrs.latest()
        if a is not None and a.sample_time_fine != stf:
            roll, pitch, yaw, stf = a.roll, a.pitch, a.yaw, a.sample_time_fine
            self._last_fresh["AHRS"] = t
        elif a is not None and (not self.lockstep or prev is None):
            roll, pitch, yaw, stf = a.roll, a.pitch, a.yaw, a.sample_time_fine
        snap = Snapshot(tick_index, t, count, tau, dl, dsigma, float(roll), float(pitch), float(yaw), int(stf),
                        tuple(missing))
        self._last = snap
        return snap


def _wait_ahrs(ahrs, stf: int, timeout: float):
    """The AHRS reading with SampleTimeFine >= stf, waiting up to ``timeout`` s; the latest one if none came."""
    deadline = _now() + timeout
    r = ahrs.latest()
    while r is None or r.sample_time_fine < stf:
        left = deadline - _now()
        if left <= 0:
            return ahrs.latest()
        try:
            r = ahrs.wait_for((r.seq if r is not None else -1) + 1, left)
        except DeviceError:
            return ahrs.latest()
    return r


_now = time.monotonic
_sleep = time.sleep
