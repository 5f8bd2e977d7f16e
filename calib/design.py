"""Calibration poses chosen for information (issue 19): optimal plans, sequential choice, separating effects.

Information. The tau-l-sigma-epsilon problem (:mod:`calib.selfcal.problem`) has the global parameters theta
(zeta_0 first) and one pose per equilibrium row; its Jacobian is block-arrow. Eliminating a row's pose by
the Schur complement leaves that row's contribution to the information about theta,

    M_i = G_i^T G_i - G_i^T J_i (J_i^T J_i)^-1 J_i^T G_i       (p, p)

(J_i, G_i: the row's weighted Jacobian with respect to its pose and to theta), and the rows add up: the
information of a plan is M_0 + sum_i M_i, M_0 that of the reference window (absolute tensions, roll and
pitch) and the priors of the devices' constant errors (:func:`planning_model`). Its inverse is the
predicted covariance of theta; the position 1-sigma reported everywhere is
``sqrt(trace)`` of its position block (m), the root-mean-square length of the position error, which is
what the A-optimal design minimises.

Noise. The rows are means of equilibrium windows; every function takes their sigma as an argument, per
channel or per pose (:class:`PoseNoise`). The plans are chosen with the startup loop's noise at each pose
(:data:`LOOP_POSE_NOISE`; per channel, :data:`LOOP_NOISE`: both measured on the simulated prototype with
realistic noise, as the run's own solve weighs its window means); a sequential startup then takes, once its
own solve (``cdpr solve --noise estimate`` on the samples so far) has two rows, that solve's estimate and
1-sigma for its stop rule and that solve's noise, with the loop's dependence on the pose, for its next
choice.
:func:`window_mean_noise` is the sensors' view: the per-sample sigma (SAMPLE_NOISE) over the square root
of the samples in a window, as if the platform were still.

Robot time (:class:`TimeModel`): each transition is a rest-to-rest quintic at the tension rate limit
(15/8 max|delta tau| / rate, at least ``min_transition``), each pose waits ``settle`` s to come to rest and
holds ``hold`` s; the plan's time is the closed tour from the home tensions tau0 back to tau0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.constants import EXPECTED_SETTLE, HOLD_TIME, MAX_TENSION_RATE, MIN_TRANSITION, QUINTIC_PEAK_RATE
from calib.effects import EffectModel
from calib.effects.priors import DeviceAccuracy
from calib.equilibrium import inverse_geometrico_static
from calib.planning import PlanningError, PosePlan, home, order_setpoints
from calib.robot import Robot
from calib.selfcal import CHANNELS, MeasurementModel, Measurements, Problem, channel_width
from calib.workspace import default_volume

# per-sample sigma of the IRMA4U's sensors in a still window (issue 19: load cells ~1 N, encoders ~0.2 mm,
# AHRS ~0.02 deg; swivel encoders their 0.03 deg accuracy): N, m, rad
SAMPLE_NOISE = {
    "tension": 1.0,
    "length": 2e-4,
    "swivel": math.radians(0.03),
    "orientation": np.radians([0.02, 0.02, 0.02]),
}
# sigma of one window mean per channel (N, m, rad) the plans are chosen with: the startup loop's, the median
# over LOOP_RUNS simulated grid startups of the noise each run's own solve ends with, times LOOP_SCALE, which
# makes the grid's predicted 1-sigma the RMS error measured on those runs. How it is measured, and the figures:
# docs/planning.md ("How the loop's noise constants are measured"); checked within 5 % by
# ``python benchmarks/loop_noise.py --runs 20 --cache DIR``.
LOOP_RUNS = 20
LOOP_SCALE = 1.221
LOOP_NOISE = {
    "tension": 0.2466 * LOOP_SCALE,
    "length": 4.383e-5 * LOOP_SCALE,
    "swivel": 6.569e-6 * LOOP_SCALE,
    "orientation": np.array([9.095e-5, 9.095e-5, 1.769e-4]) * LOOP_SCALE,
}


@dataclass(frozen=True)
class PoseNoise:
    """Sigma of one window mean per channel at a pose, as the startup loop gets it (N, m, rad): per channel
    ``scale * sqrt(floor**2 + (force / k)**2)``, k the platform's lateral stiffness at the pose (sum of
    tau_i / l_i, N/m, :func:`lateral_stiffness`): a slow push on the platform (sway, force-control jitter)
    moves a compliant pose more, and a window mean keeps part of that motion. ``force`` is in N (per m of
    length, per rad of swivel angle... times N/m: the channel's reading change per N of push)."""

    floor: dict[str, np.ndarray]
    force: dict[str, float]
    scale: float = 1.0

    def sigma(self, robot: Robot, stiffness: np.ndarray) -> dict[str, np.ndarray]:
        """Per channel (k, width) sigmas at poses of lateral stiffness (k,) N/m."""
        k = np.atleast_1d(np.asarray(stiffness, float))[:, None]
        return {c: self.scale * np.sqrt(np.broadcast_to(np.asarray(self.floor[c], float),
                                                        (k.shape[0], channel_width(c, robot.n)))**2
                                        + (self.force[c] / k)**2) for c in self.floor}

    def matched(self, robot: Robot, stiffness: np.ndarray, noise: dict[str, np.ndarray]) -> PoseNoise:
        """The same dependence on the pose, each channel scaled so that its root-mean-square over poses of
        lateral stiffness ``stiffness`` (k,) N/m is ``noise`` (per channel, e.g. a run's own estimate there):
        a run's noise level with the loop's shape."""
        sig = self.sigma(robot, stiffness)
        f = {c: np.broadcast_to(np.asarray(noise[c], float), sig[c].shape[1:]) / np.sqrt(np.mean(sig[c]**2, axis=0))
             for c in sig}
        return PoseNoise({c: np.asarray(self.floor[c], float) * f[c] for c in sig},
                         {c: self.force[c] * f[c] for c in sig}, self.scale)


def lateral_stiffness(robot: Robot, poses: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Lateral stiffness of the platform held by tensions tau (k, n) N at poses (k, 6): sum tau_i / l_i, N/m."""
    from calib.kinematics import inverse_kinematics

    lengths = inverse_kinematics(robot, np.atleast_2d(poses)).lengths
    return np.sum(np.atleast_2d(tau) / lengths, axis=1)


# the startup loop's window-mean noise per pose (:class:`PoseNoise`): floor and force per channel fitted to the
# noise the simulated grid and A-optimal startups' own solves end with, sigma^2 = floor^2 + force^2 / k^2, then
# ``scale`` makes the grid's predicted 1-sigma (:func:`predict_loop`) its measured RMS error. How, and the
# figures: docs/planning.md ("How the loop's noise constants are measured"); checked within 5 % by
# ``python benchmarks/loop_noise.py --runs 20 --cache DIR``.
LOOP_POSE_NOISE = PoseNoise(
    floor={"tension": 0.2062, "length": 3.611e-5, "swivel": 0.0, "orientation": np.zeros(3)},
    force={"tension": 23.39, "length": 4.29e-3, "swivel": 1.16e-3, "orientation": 0.02406},
    scale=1.457,
)


@dataclass(frozen=True)
class TimeModel:
    """Robot time of a plan, s: transitions at the tension rate limit plus settling and holding per pose."""

    max_tension_rate: float = MAX_TENSION_RATE  # N/s
    min_transition: float = MIN_TRANSITION  # s
    settle: float = EXPECTED_SETTLE  # s to come to rest at a setpoint (the startup's expected settling)
    hold: float = HOLD_TIME  # s logged per window

    def transition(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Durations (s) of the moves from tensions a to b (..., n) N, broadcast."""
        span = np.abs(np.asarray(b, float) - np.asarray(a, float)).max(axis=-1)
        return np.maximum(QUINTIC_PEAK_RATE * span / self.max_tension_rate, self.min_transition)

    def tour(self, tau0: np.ndarray, setpoints: np.ndarray) -> float:
        """Robot time (s) of visiting the setpoints (k, n) in order from tau0 and back, with the home window."""
        sp = np.vstack([tau0, setpoints, tau0])
        return float(self.transition(sp[:-1], sp[1:]).sum() + (len(setpoints) + 1) * (self.settle + self.hold))


def window_mean_noise(robot: Robot, samples: int = 20, per_sample: dict | None = None) -> dict[str, np.ndarray]:
    """Sigma of one window mean per channel (N, m, rad): the per-sample sigma (default SAMPLE_NOISE) over
    sqrt(samples in a window)."""
    base = SAMPLE_NOISE if per_sample is None else per_sample
    n = robot.n
    return {c: np.broadcast_to(np.asarray(v, float), (channel_width(c, n),)) / math.sqrt(samples)
            for c, v in base.items()}


def loop_noise(robot: Robot, sigma: dict | None = None) -> dict[str, np.ndarray]:
    """Sigma of one window mean per channel (N, m, rad) the plans are judged with by default: the startup
    loop's (:data:`LOOP_NOISE`, measured on the simulated prototype with realistic noise), or ``sigma``."""
    base = LOOP_NOISE if sigma is None else sigma
    return {c: np.broadcast_to(np.asarray(v, float), (channel_width(c, robot.n),)).copy()
            for c, v in base.items()}


def planning_model(robot: Robot) -> MeasurementModel:
    """The model the plans are judged with: the rigid model plus the devices' constant errors within their
    datasheet accuracy (load-cell and AHRS biases, Gaussian priors), which window means do not average out."""
    return EffectModel(robot, [DeviceAccuracy()])


def information(robot: Robot, poses: np.ndarray, zeta0: np.ndarray, noise: dict[str, np.ndarray] | PoseNoise,
                model: MeasurementModel | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Information about theta of the reference window, M_0 (p, p), and of one equilibrium row at each pose,
    M (k, p, p), the row's own pose eliminated (module doc); theta is the model's start at zeta0 (default
    model: :func:`planning_model`). ``noise``: one sigma per channel for every window, or a
    :class:`PoseNoise` (each window's at its pose and the model's tensions there)."""
    model = model or planning_model(robot)
    z = np.atleast_2d(np.asarray(poses, float))
    k, n = z.shape[0], robot.n
    meas = Measurements(np.zeros((k, n)), np.zeros((k, n)), np.zeros((k, n)), np.zeros((k, 3)),
                        np.zeros(n), np.zeros(2))
    per_pose = isinstance(noise, PoseNoise)
    unit = {c: np.ones(channel_width(c, n)) for c in CHANNELS}
    theta0 = model.initial_params(np.asarray(zeta0, float))
    ev = Problem(model, meas, unit if per_pose else noise).evaluate(theta0, z)
    g, r, J, G = ev.groups[0]
    g0 = ev.g0
    if per_pose:  # unit weights so far: the residuals are the predictions (readings 0), tensions included
        sig = noise.sigma(robot, lateral_stiffness(robot, z, r[:, g.slices["tension"]]))
        w = 1.0 / np.concatenate([sig[c] for c in g.channels], axis=1)
        J, G = w[..., None] * J, w[..., None] * G
        s0 = noise.sigma(robot, lateral_stiffness(robot, theta0[None, :6], ev.r0[None, :n]))
        w0 = np.r_[1.0 / s0["tension"][0], 1.0 / s0["orientation"][0], np.ones(g0.shape[0] - n - 3)]
        g0 = w0[:, None] * g0
    Jt = J.transpose(0, 2, 1)
    W = Jt @ G
    M = G.transpose(0, 2, 1) @ G - W.transpose(0, 2, 1) @ np.linalg.solve(Jt @ J, W)
    return g0.T @ g0, 0.5 * (M + M.transpose(0, 2, 1))


def position_sigma(info: np.ndarray) -> np.ndarray:
    """sqrt(trace) of the position block of the inverse of information matrices (..., p, p), m; inf where
    the information is singular."""
    info = np.asarray(info, float)
    ridge = 1e-12 * np.trace(info, axis1=-2, axis2=-1)[..., None, None] * np.eye(info.shape[-1])
    cov = np.linalg.inv(info + ridge)
    tr = np.trace(cov[..., :3, :3], axis1=-2, axis2=-1)
    ok = np.linalg.matrix_rank(info) == info.shape[-1]
    return np.where(ok & (tr > 0), np.sqrt(np.abs(tr)), np.inf)


@dataclass(frozen=True)
class CandidateSet:
    """Statically reachable equilibria: poses (m, 6), tension setpoints (m, n) N, and each one's information
    (m, p, p); the reference window's information ``info0`` (p, p) at the home pose under ``tau0``."""

    poses: np.ndarray
    setpoints: np.ndarray
    info: np.ndarray
    info0: np.ndarray
    tau0: np.ndarray
    home_pose: np.ndarray

    @property
    def size(self) -> int:
        return int(self.poses.shape[0])


def candidate_volume(robot: Robot, margin: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Where candidates are sought: the installation volume (:func:`calib.workspace.default_volume`) kept
    ``margin`` m away from the pulleys' horizontal extent, from the plane below them and from the floor (m)."""
    lo, hi = default_volume(robot)
    return lo + margin, hi - margin


def candidates(robot: Robot, noise: dict[str, np.ndarray], step: float = 0.1, lower: np.ndarray | None = None,
               upper: np.ndarray | None = None) -> CandidateSet:
    """The equilibria of the static workspace (tension bounds, stability) on a grid of spacing ``step`` (m)
    inside [lower, upper] (default :func:`candidate_volume`), with their information."""
    vlo, vhi = candidate_volume(robot)
    lo = vlo if lower is None else np.asarray(lower, float)
    hi = vhi if upper is None else np.asarray(upper, float)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise PlanningError(f"robot '{robot.name}' has no workspace bounds (field 'workspace').")
    if not step > 0:
        raise PlanningError(f"the candidate grid step must be positive, got {step!r} m.")
    axes = [np.arange(a, b + step / 2, step) for a, b in zip(lo, hi, strict=True)]
    pos = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], 1)
    with np.errstate(invalid="ignore"):  # positions the cables cannot reach: not feasible, dropped
        sp = inverse_geometrico_static(robot, pos)
    ok = sp.feasible
    if not ok.any():
        raise PlanningError(f"robot '{robot.name}': the static workspace inside {np.round(lo, 3).tolist()} .. "
                            f"{np.round(hi, 3).tolist()} m is empty (no stable equilibrium within the tension bounds).")
    tau0, home_pose = home(robot)
    info0, info = information(robot, sp.poses[ok], home_pose, noise)
    return CandidateSet(sp.poses[ok], sp.tensions[ok], info, info0, tau0, home_pose)


def _best_addition(base: np.ndarray, info: np.ndarray, allowed: np.ndarray) -> tuple[int, float]:
    """The candidate whose information added to ``base`` gives the smallest position sigma."""
    s = position_sigma(base[None] + info)
    s[~allowed] = np.inf
    j = int(np.argmin(s))
    return j, float(s[j])


def select_a_optimal(cands: CandidateSet, k: int, max_rounds: int = 20) -> tuple[np.ndarray, float]:
    """K distinct candidates minimising the predicted position sigma: greedy, then Fedorov exchanges (each
    chosen pose swapped for the best other candidate) until no swap helps. Returns indices (k,), sigma (m)."""
    if not 1 <= k <= cands.size:
        raise PlanningError(f"cannot choose {k} poses among {cands.size} reachable candidates.")
    chosen: list[int] = []
    total = cands.info0.copy()
    free = np.ones(cands.size, bool)
    for _ in range(k):
        j, _ = _best_addition(total, cands.info, free)
        chosen.append(j)
        free[j] = False
        total = total + cands.info[j]
    best = float(position_sigma(total))
    for _ in range(max_rounds):
        improved = False
        for slot in range(k):
            rest = total - cands.info[chosen[slot]]
            j, s = _best_addition(rest, cands.info, free)
            if s < best * (1 - 1e-9):
                free[chosen[slot]], free[j] = True, False
                chosen[slot], total, best, improved = j, rest + cands.info[j], s, True
        if not improved:
            break
    return np.array(chosen), best


@dataclass(frozen=True)
class PlanAssessment:
    """Predicted 1-sigma of zeta_0 (6,) (m, rad), position sigma (sqrt trace, m) and robot time (s) of a plan."""

    sigma: np.ndarray
    position_sigma: float
    robot_time: float

    def to_dict(self) -> dict:
        return {"position_sigma_m": self.position_sigma, "sigma": self.sigma.tolist(), "robot_time_s": self.robot_time}


def assess(robot: Robot, plan: PosePlan, noise: dict[str, np.ndarray], time_model: TimeModel) -> PlanAssessment:
    """The predicted uncertainty of the initial pose and the robot time of a plan."""
    info0, info = information(robot, plan.poses, plan.home_pose, noise)
    total = info0 + info.sum(axis=0)
    cov = np.linalg.inv(total)
    return PlanAssessment(np.sqrt(np.clip(np.diag(cov)[:6], 0, None)), float(position_sigma(total)),
                          time_model.tour(plan.tau0, plan.setpoints))


def predict_loop(robot: Robot, plan: PosePlan, time_model: TimeModel,
                 noise: PoseNoise = LOOP_POSE_NOISE) -> PlanAssessment:
    """What the startup loop's solve of a plan should give: its first pose's window is the reference (the run's
    window search leaves the rest under tau0 out), the other poses are rows, each window with the loop's
    noise at its pose (:data:`LOOP_POSE_NOISE`); robot time as :func:`assess`."""
    info0, info = information(robot, plan.poses[1:], plan.poses[0], noise)
    total = info0 + info.sum(axis=0)
    cov = np.linalg.inv(total)
    return PlanAssessment(np.sqrt(np.clip(np.diag(cov)[:6], 0, None)), float(position_sigma(total)),
                          time_model.tour(plan.tau0, plan.setpoints))


def optimal_plan(robot: Robot, k: int, noise: dict[str, np.ndarray], step: float = 0.1,
                 cands: CandidateSet | None = None) -> PosePlan:
    """K reachable equilibria minimising the predicted position sigma of zeta_0 (A-optimal), in the
    visiting order of the cheapest tour from tau0 (the transition time, as :func:`calib.planning.plan_poses`)."""
    cands = cands or candidates(robot, noise, step)
    idx, _ = select_a_optimal(cands, k)
    order, cost = order_setpoints(cands.tau0, cands.setpoints[idx])
    sel = idx[order]
    sp = inverse_geometrico_static(robot, cands.poses[sel, :3])
    return PosePlan(cands.poses[sel], cands.setpoints[sel], cands.tau0, cands.home_pose,
                    np.full((k, 3), -1), cost, sp.min_stiffness)


@dataclass(frozen=True)
class Separation:
    """Poses that tell two effects apart: poses (m, 6), setpoints (m, n) N, and each one's expected
    difference of the two fitted models' predictions, squared and in units of the noise, after the pose
    itself is refitted (chi2 units: what one such window adds to the difference of the two fits' chi2)."""

    effects: tuple[str, str]
    poses: np.ndarray
    setpoints: np.ndarray
    score: np.ndarray

    def to_dict(self) -> dict:
        return {"effects": list(self.effects), "poses": self.poses.tolist(), "setpoints": self.setpoints.tolist(),
                "expected_delta_chi2": self.score.tolist()}


def separating_poses(robot: Robot, meas: Measurements, noise: dict[str, np.ndarray], theta0: np.ndarray,
                     poses0: np.ndarray, effects: tuple, cands: CandidateSet, count: int = 3,
                     spacing: float = 0.2) -> Separation:
    """The ``count`` candidate equilibria (at least ``spacing`` m apart) where two effects, each fitted to
    the rows ``meas`` (with the devices' constant errors, :func:`calib.fitting.fit`), predict the most
    different readings relative to the noise once the row's pose is refitted: at each candidate setpoint the
    platform of each fitted model rests at that model's equilibrium (direct statics of its true robot)."""
    from calib.equilibrium import direct_statics
    from calib.fitting import fit
    w = np.concatenate([1.0 / np.broadcast_to(noise[c], (channel_width(c, robot.n),)) for c in CHANNELS])
    vals, jacs, ok = [], [], np.ones(cands.size, bool)
    for e in effects:
        f = fit(robot, meas, noise, [DeviceAccuracy(), e], theta0, poses0)
        with np.errstate(invalid="ignore"):
            ds = direct_statics(f.model.true_robot(f.theta), cands.setpoints, cands.poses)
            pr = f.model.predict(ds.poses, f.theta, CHANNELS)
        vals.append(w * np.concatenate([pr[c].value for c in CHANNELS], 1))
        jacs.append(w[:, None] * np.concatenate([pr[c].d_pose for c in CHANNELS], 1))
        ok &= ds.converged
    d = vals[0] - vals[1]
    J = 0.5 * (jacs[0] + jacs[1])  # the row's pose is refitted
    Jt = J.transpose(0, 2, 1)
    x = np.linalg.pinv(Jt @ J, rcond=1e-10) @ (Jt @ d[..., None])
    resid = d - (J @ x)[..., 0]
    score = np.where(ok, np.sum(resid**2, 1), -np.inf)
    score = np.where(np.isfinite(score), score, -np.inf)
    chosen: list[int] = []
    for j in np.argsort(-score):
        if len(chosen) == count or not np.isfinite(score[j]):
            break
        if all(np.linalg.norm(cands.poses[j, :3] - cands.poses[i, :3]) >= spacing for i in chosen):
            chosen.append(int(j))
    if not chosen:
        raise PlanningError("no candidate pose has an equilibrium under both fitted models.")
    idx = np.array(chosen)
    return Separation((effects[0].name, effects[1].name), cands.poses[idx], cands.setpoints[idx], score[idx])
