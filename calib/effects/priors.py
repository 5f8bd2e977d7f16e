"""The priors every fit of a run carries, never candidates of the diagnosis: the devices' datasheet errors
(:class:`DeviceAccuracy`) and the noise of the reference window's means (:class:`ReferenceNoise`). The
candidate effects are the library of :mod:`calib.effects.builtin`, ``cable`` and ``swivel``."""

from __future__ import annotations

import math

import numpy as np

from calib.effects.base import Context, Effect, ParamSpec, add_tension_offsets
from calib.robot import Robot
from calib.selfcal.model import ChannelPrediction

YAW_RATE_BOUND = math.radians(8.0) / 3600.0  # rad/s: the MTi-630's gyro in-run bias stability (datasheet)


class DeviceAccuracy(Effect):
    """The constant errors a datasheet allows every device, as parameters with a Gaussian prior: load cell
    i reads tau_i + b_i (N), the AHRS reads roll + b_roll and pitch + b_pitch (rad) and its yaw drifts by
    yaw_rate * t (rad/s, t the row's time after the reference sample: an unreferenced heading integrates the
    gyro's residual bias). The prior standard deviation is the bound over sqrt(3) (a uniform error within
    the bound, GUM type B): 0.02 % of full scale for the cells, the roll/pitch accuracy for the AHRS (robot
    ``sensors``), the gyro's in-run bias stability for the yaw rate. Not a candidate
    effect: the diagnosis keeps it in every fit, so that only what exceeds the devices' specifications is
    reported as a missing effect."""

    reads_tension = False  # its readings add to the predictions, never read the tensions
    name = "device_accuracy"
    order = 45
    description = ("per-device constant errors within the datasheet accuracy (load cells N, AHRS roll/pitch rad,"
                   " AHRS yaw drift rad/s)")

    def params(self, robot: Robot) -> list[ParamSpec]:
        s = robot.sensors
        cell = s.load_cell_uncertainty / math.sqrt(3.0)
        ahrs = s.ahrs_roll_pitch_accuracy / math.sqrt(3.0)
        return [ParamSpec(f"b_{i + 1}", "N", 0.0, -np.inf, np.inf, 0.1, prior=cell) for i in range(robot.n)] + [
            ParamSpec("b_roll", "rad", 0.0, -np.inf, np.inf, 1e-3, prior=ahrs),
            ParamSpec("b_pitch", "rad", 0.0, -np.inf, np.inf, 1e-3, prior=ahrs),
            # MTi-630 datasheet: gyro in-run bias stability 8 deg/h, what the filter cannot remove from an
            # unreferenced heading over a startup of minutes (the emulated device drifts within 3.6 deg/h)
            ParamSpec("yaw_rate", "rad/s", 0.0, -np.inf, np.inf, 1e-5, prior=YAW_RATE_BOUND / math.sqrt(3.0)),
        ]

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        n = ctx.robot.n
        a = ctx.cols.start
        add_tension_offsets(slice(a, a + n), values[:n], preds)
        if "orientation" in preds:
            pr = preds["orientation"]
            pr.value = pr.value.copy()
            pr.value[:, :2] += values[n:n + 2]
            pr.d_theta[:, [0, 1], [a + n, a + n + 1]] = 1.0
            if ctx.times is not None:
                t = np.asarray(ctx.times, float)
                pr.value[:, 2] += float(values[n + 2]) * t
                pr.d_theta[:, 2, a + n + 2] = t


def _per_cable(sd) -> float | list[float]:
    """A prior sigma given once for every cable (a float) or per cable (a list of floats; one value if all equal)."""
    v = np.atleast_1d(np.asarray(sd, float)).ravel()
    return float(v[0]) if v.size == 1 or np.all(v == v[0]) else [float(x) for x in v]


class ReferenceNoise(Effect):
    """The noise of the reference window's means. The relative channels (cable lengths, swivel angles, yaw)
    of every row are read relative to the reference window's mean, so that mean's own error e, as large as
    any window mean's, is in every row at once: row reading = model + d, d = -e, one value per cable and
    relative channel. Carried as parameters with a Gaussian prior of the reference mean's sigma, it widens
    the initial pose's sigma by what the reference contributes instead of letting that error pass for
    information (on effect-free simulated runs with a slow sway it made most of the initial position's error).
    Not a candidate effect: the estimate-noise solve and the diagnosis keep it in every fit of a run
    (:meth:`for_rows`); rows without a reference window (equilibrium rows given directly) have none."""

    reads_tension = False  # its readings add to the predictions, never read the tensions
    name = "reference_noise"
    order = 46
    description = "noise of the reference window's means in the relative channels (m, rad)"

    def __init__(self, length: float | list[float] = 0.0, swivel: float | list[float] = 0.0, yaw: float = 0.0):
        """Prior sigmas of the reference means: per relative channel one for every cable, or a list per cable."""
        self.sd = {"length": _per_cable(length), "swivel": _per_cable(swivel), "yaw": float(yaw)}

    @classmethod
    def for_rows(cls, sigma: dict[str, np.ndarray], windows: np.ndarray | None, ref_size: int) -> ReferenceNoise:
        """The reference noise of rows weighed with ``sigma`` (per channel, the sigma of a mean over the
        harmonic-mean size of the rows' windows, (k, 2) first and last sample) for a reference window of
        ``ref_size`` samples: variances go as 1 / size."""
        sizes = None if windows is None else np.asarray(windows, float)[:, 1] - np.asarray(windows, float)[:, 0] + 1
        nh = 1.0 / float(np.mean(1.0 / sizes)) if sizes is not None and sizes.size and np.all(sizes > 0) else 1.0
        scale = math.sqrt(nh / max(int(ref_size), 1))
        o = np.asarray(sigma["orientation"], float)
        return cls(_per_cable(np.asarray(sigma["length"], float) * scale),
                   _per_cable(np.asarray(sigma["swivel"], float) * scale), float(o[2]) * scale)

    def params(self, robot: Robot) -> list[ParamSpec]:
        # the prior is the run's own noise of a mean (calib.selfcal.noise), not a plausibility bound
        out = []
        for c, unit in (("length", "m"), ("swivel", "rad")):
            sd = np.broadcast_to(np.asarray(self.sd[c], float), (robot.n,))
            if np.all(sd > 0):
                out += [ParamSpec(f"d_{c}_{i + 1}", unit, 0.0, -np.inf, np.inf, float(sd[i]), prior=float(sd[i]))
                        for i in range(robot.n)]
        if self.sd["yaw"] > 0:
            out.append(ParamSpec("d_yaw", "rad", 0.0, -np.inf, np.inf, self.sd["yaw"], prior=self.sd["yaw"]))
        return out

    def transform(self, ctx: Context, values: np.ndarray, preds: dict[str, ChannelPrediction]) -> None:
        n, j = ctx.robot.n, 0
        for c in ("length", "swivel"):
            if not np.all(np.asarray(self.sd[c], float) > 0):
                continue
            if c in preds:
                pr = preds[c]
                pr.value = pr.value + values[None, j:j + n]
                pr.d_theta[:, np.arange(n), ctx.cols.start + j + np.arange(n)] = 1.0
            j += n
        if self.sd["yaw"] > 0 and "orientation" in preds:
            pr = preds["orientation"]
            pr.value = pr.value.copy()
            pr.value[:, 2] += values[j]
            pr.d_theta[:, 2, ctx.cols.start + j] = 1.0
