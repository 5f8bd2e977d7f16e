"""Noise of a window mean, from the run itself.

A measurement row is the mean of a channel over an equilibrium window, so its uncertainty is that of a mean,
not the scatter of one sample: for white noise it is sqrt(N) times smaller, for samples correlated in time
(a controller's ripple, a slow sway of the platform, a filtered AHRS) larger than that. Per channel group
(tensions, cable lengths, swivel angles pooled over the cables; roll and pitch pooled, yaw apart) the
estimate pools every still window:

- in each window a polynomial is removed: the mean for tensions (held by the force control, no platform
  motion to reject), a quadratic for lengths, swivel angles, roll, pitch and yaw (a smooth motion of the
  platform, settling or a slow sway, is real, the same in every kinematic channel, and the row's pose
  follows it: it is not noise of the readings);
- the pooled lag-1 ratio of those residuals gives the lag-1 autocorrelation ``rho`` of an AR(1) model of
  the noise, and their pooled power its variance gamma0, both against their exact expectations for the
  windows' sizes (the removed polynomial biases both; Marriott and Pope 1954 give the first-order bias for
  a removed mean, here it is computed exactly);
- the variance of the mean of N samples of that AR(1) process is gamma0 f(rho, N) / N with
  f = 1 + 2 sum_k (1 - k/N) rho^k (the effective sample size is N / f);
- a reading whose second differences are mostly zero sits on its counts (encoders of a still platform): its
  window mean is then uncertain by the resolution alone; at a solution each window mean of the lengths and
  swivel angles also keeps its quantisation error, sized from the window's own readings
  (:func:`quantisation_variance`, Widrow's quantisation of an average: the within-window scatter cannot see it);
- the floor is the sensor's resolution (quantisation step / sqrt 12): a reading that does not move is
  uncertain by that much however long it is averaged.

The row weights take one sigma per channel, that of a window of the harmonic mean size of the windows used
(variances go as 1/N). Constant per-device errors within the datasheet accuracy (a load-cell offset, an AHRS
tilt) are not noise of a mean: the solve and the diagnosis carry them as parameters with priors.

At a solution the estimate is refined (calib.selfcal.solve, noise 'estimate'): :func:`pose_free_noise` takes the
platform's motion out of the kinematic groups, and :func:`variance_factors` / :func:`rescaled_sigma` bring a
group down to what its window means scatter by around the fit, and up only where the model misses it by more
than sqrt(MISFIT_FACTOR) times its noise (model error: it must not pull the poses to its misfit; issue 28).
The swivel rows' cables (:data:`PER_CABLE`) get factors of their own, shrunk toward the group's by empirical
Bayes (:func:`cable_factors`), while the group's sigma is still a noise's (issue 29, docs/windows.md).
The reference window's own noise,
which every relative row carries at once, is a parameter with a prior (calib.effects.priors.ReferenceNoise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calib.chi2 import chi2_sf
from calib.robot import Robot
from calib.selfcal.quantisation import quantisation_variance
from calib.selfcal.shrinkage import cable_factors

QUANTISED = 0.5  # fewer non-zero second differences than this share: a quantised reading, not noise
RHO_MAX = 0.98  # an AR(1) coefficient above this is a drift, not noise: cap the correction (N / f >= ~1)


@dataclass(frozen=True)
class ChannelNoise:
    """One channel group: ``sample`` the standard deviation of one sample (SI), ``rho`` the lag-1
    autocorrelation, ``n_eff`` the effective number of independent samples of a typical window, ``mean`` the
    standard deviation of a window mean (before the floor) and ``floor`` the resolution floor."""

    sample: float
    rho: float
    n_eff: float
    mean: float
    floor: float


@dataclass(frozen=True)
class WindowNoise:
    """Per-channel sigmas of a window mean (``sigma``: (n,) or (3,) arrays, N, m, rad), the window size they
    are for (``window_size``: harmonic mean of the windows' sample counts) and each group's figures."""

    sigma: dict[str, np.ndarray]
    window_size: float
    groups: dict[str, ChannelNoise] = field(default_factory=dict)


def resolution_floor(robot: Robot) -> dict[str, np.ndarray]:
    """Per channel, the quantisation step of the sensors over sqrt(12) (N, m, rad)."""
    s, n = robot.sensors, robot.n
    lpr = np.abs(np.asarray(s.length_per_motor_rev, float)) if s.length_per_motor_rev else np.full(n, 0.03)
    q = math.sqrt(12.0)
    return {
        "tension": np.full(n, 0.01 / q),
        "length": np.broadcast_to(lpr / 2.0**s.motor_encoder_bits / q, (n,)).copy(),
        "swivel": np.full(n, 2 * math.pi / s.swivel_counts_per_rev / q),
        "orientation": np.full(3, 1e-5),
    }


def ar1_factor(rho: float, n: float) -> float:
    """f(rho, N) = 1 + 2 sum_{k=1}^{N-1} (1 - k/N) rho^k: Var(mean of N) = gamma0 f / N for an AR(1)."""
    if rho <= 0.0 or n <= 1:
        return 1.0
    m = int(math.ceil(n)) - 1
    k = np.arange(1, m + 1, dtype=float)
    return float(1.0 + 2.0 * np.sum((1.0 - k / n) * rho**k))


_RHO_GRID = np.linspace(0.0, RHO_MAX, 99)
DEGREE = {"tension": 0, "length": 2, "swivel": 2, "tilt": 2, "yaw": 2}  # polynomial removed per window


def _expectations(size: int, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """For the residuals d of a degree-``degree`` polynomial fitted to ``size`` samples of a unit-variance
    AR(1) of coefficient rho (the grid): E[d'd] and E[sum d_t d_t+1], exactly: tr(M Sigma) and
    tr(M S M Sigma)/2 with M the residual projector and S the symmetric lag-1 shift; Sigma is Toeplitz
    (rho^|i-j|), so each trace is a sum over lags of rho^lag times the matching diagonal sums of M or MSM."""
    t = np.linspace(-1.0, 1.0, size)
    X = np.vander(t, degree + 1)
    M = np.eye(size) - X @ np.linalg.pinv(X)
    half_msm = 0.5 * (M[:, :-1] @ M[1:, :] + M[:, 1:] @ M[:-1, :])  # M S M / 2, S = up + down shift
    powers = _RHO_GRID[:, None] ** np.arange(size)[None, :]  # (grid, lags)

    lag = np.abs(np.subtract.outer(np.arange(size), np.arange(size))).ravel()

    def diagonal_sums(A: np.ndarray) -> np.ndarray:  # [tr A, tr_1 A + tr_-1 A, ...]: sums over |i - j| = lag
        return np.bincount(lag, weights=A.ravel(), minlength=size)

    return powers @ diagonal_sums(M), powers @ diagonal_sums(half_msm)


def _pooled(blocks: list[np.ndarray], degree: int) -> tuple[float, float, float]:
    """Sample variance gamma0 and lag-1 autocorrelation rho of the noise of one channel group and the
    harmonic mean window size, from the residuals of a polynomial of ``degree`` fitted in each window
    (blocks (N_w, c)): rho is the AR(1) whose expected pooled lag-1 ratio of those residuals equals the
    measured one, gamma0 the pooled residual power over its expectation for that rho (exact for any window
    size, the fitted polynomial's bias included)."""
    dd = dl = 0.0
    e0 = np.zeros(_RHO_GRID.size)
    e1 = np.zeros(_RHO_GRID.size)
    moving = total = 0
    inv_n = []
    cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for x in blocks:
        size = x.shape[0]
        if size < degree + 4:
            continue
        t = np.linspace(-1.0, 1.0, size)
        X = np.vander(t, degree + 1)
        d = x - X @ np.linalg.lstsq(X, x, rcond=None)[0]
        d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
        moving += int(np.count_nonzero(d2))
        total += d2.size
        dd += float(np.sum(d * d))
        dl += float(np.sum(d[1:] * d[:-1]))
        if size not in cache:
            cache[size] = _expectations(size, degree)
        a, b = cache[size]
        e0 += a * x.shape[1]
        e1 += b * x.shape[1]
        inv_n.append(1.0 / size)
    nh = 1.0 / float(np.mean(inv_n)) if inv_n else 1.0
    if total == 0 or dd <= 0.0 or moving < QUANTISED * total:
        return 0.0, 0.0, nh  # a reading that mostly sits on one count: its resolution is its noise
    ratio = e1 / e0  # increasing in rho
    i = int(np.clip(np.searchsorted(ratio, dl / dd), 0, _RHO_GRID.size - 1))
    return dd / float(e0[i]), float(_RHO_GRID[i]), nh


def _group(blocks: list[np.ndarray], floor: float, degree: int) -> ChannelNoise:
    gamma0, rho, nh = _pooled(blocks, degree)
    f = ar1_factor(rho, nh)
    mean = math.sqrt(gamma0 * f / nh)
    return ChannelNoise(math.sqrt(gamma0), rho, nh / f, mean, floor)


def window_mean_noise(robot: Robot, sig: dict[str, np.ndarray], windows) -> WindowNoise:
    """Sigma of a window mean per channel from the run's own samples in ``windows`` (objects with ``slice``,
    ``quasi``); quasi windows are left out unless there is nothing else."""
    floor = resolution_floor(robot)
    still = [w for w in windows if not getattr(w, "quasi", False)] or list(windows)
    ori = np.stack([sig["roll"], sig["pitch"], sig["dyaw"]], 1)
    parts = {
        "tension": [sig["tau"][w.slice] for w in still],
        "length": [sig["dl"][w.slice] for w in still],
        "swivel": [sig["dsigma"][w.slice] for w in still],
        "tilt": [ori[w.slice, :2] for w in still],
        "yaw": [ori[w.slice, 2:] for w in still],
    }
    groups = {c: _group(b, float(np.max(floor["orientation" if c in ("tilt", "yaw") else c])), DEGREE[c])
              for c, b in parts.items()}
    n = robot.n
    sigma = {c: np.maximum(np.full(n, groups[c].mean), floor[c]) for c in ("tension", "length", "swivel")}
    sigma["orientation"] = np.maximum(np.array([groups["tilt"].mean, groups["tilt"].mean, groups["yaw"].mean]),
                                      floor["orientation"])
    sizes = [w.size for w in still if w.size >= 3]
    nh = 1.0 / float(np.mean([1.0 / s for s in sizes])) if sizes else 1.0
    return WindowNoise(sigma, nh, groups)


KINEMATIC = ("length", "swivel")  # the groups whose window means lose the pose motion (see pose_free_noise)
VCE_ROUNDS = 4  # variance-component rounds of the per-sample pose fit (the sigmas settle in 2-3)


@dataclass(frozen=True)
class PoseFreeNoise:
    """What :func:`pose_free_noise` estimates: per kinematic group the sigma of one sample's pose-free part
    (``sample``, SI), its window-mean figures (``groups``, as :class:`ChannelNoise`) and per channel the quantisation
    error of a window mean (``quantisation``: (n,) SI, :func:`quantisation_variance` averaged over the
    windows), which no later rescaling may go below; the per-sample poses it fitted and their windows
    (``poses``, ``owner``: what calib.selfcal.sway sizes the sway from)."""

    noise: WindowNoise
    sample: dict[str, float]
    quantisation: dict[str, np.ndarray] = field(default_factory=dict)
    poses: np.ndarray | None = None  # (N, 6) the per-sample poses of the still windows (m, rad)
    owner: np.ndarray | None = None  # (N,) the window (index into the spans) of each of them


def pose_free_noise(model, sig: dict[str, np.ndarray], spans: list[tuple[slice, np.ndarray]],
                    ref: dict[str, np.ndarray], theta: np.ndarray, base: WindowNoise,
                    rounds: int = VCE_ROUNDS) -> PoseFreeNoise:
    """Noise of the length and swivel-angle window means (:data:`KINEMATIC`) without the platform's
    motion inside the windows (roll, pitch and yaw keep ``base``'s group figures: the AHRS channels only weigh
    the per-sample pose fits). The force control moves winches and platform together: every kinematic
    reading follows the pose, and that motion is absorbed by each row's own pose, so it is not noise of the
    row. Each sample of each still window gets its own pose (the measurement model ``model`` at the solved
    ``theta``, started from its window's pose; ``spans``: (window slice, pose (6,)) pairs, ``ref``: the
    reference window's means the rows are relative to), its cables held at the window's tension (the
    model's ``cable_tensions`` at the window's pose: the sway of a force-controlled hold moves the pose at
    that tension, it does not stretch the cables by the statics' tension of each swaying pose); the per-group
    sigma of a sample's remainder is
    estimated by variance components (Helmert: sum of squared residuals over the sum of the redundancy
    numbers 1 - h_ii of the whitened pose fit, re-weighted ``rounds`` times); the remainders' lag-1
    correlation in each window gives the AR(1) factor of their window mean, as in :func:`window_mean_noise`.
    A reading that sat on one count for a whole window keeps its quantisation error in the mean: the
    share of such readings adds q^2/12 times that share. Tensions keep ``base``'s figures (the force
    control holds them; their jitter is not a pose motion)."""
    from calib.selfcal.lm import solve_poses
    from calib.selfcal.problem import Measurements, Problem

    robot = model.robot
    n = robot.n
    idx = np.concatenate([np.arange(s.start, s.stop) for s, _ in spans])
    owner = np.concatenate([np.full(s.stop - s.start, j) for j, (s, _) in enumerate(spans)])
    ori = np.stack([sig["roll"], sig["pitch"], sig["dyaw"] - ref["ori"][2]], 1)[idx]
    Z = np.array([z for _, z in spans], float)
    # force control holds each cable's tension through a window while the platform sways: a sample's cables
    # stretch under its window's tension (the statics' at the window's pose, as its row models it), not
    # under the tension the statics would give the sample's swaying pose
    held = model.cable_tensions(theta, Z)[owner]
    meas = Measurements(np.full((idx.size, n), np.nan), sig["dl"][idx] - ref["dl"],
                        sig["dsigma"][idx] - ref["dsigma"], ori, np.full(n, np.nan), np.full(2, np.nan),
                        held_tau=held)
    Z = Z[owner]
    floor = resolution_floor(robot)
    g = base.groups
    per = {"length": max(g["length"].sample, floor["length"].max()),  # per-sample sigmas to start from
           "swivel": max(g["swivel"].sample, floor["swivel"].max()),
           "tilt": max(g["tilt"].sample, 1e-5), "yaw": max(g["yaw"].sample, 1e-5)}
    cols = {"length": slice(0, n), "swivel": slice(n, 2 * n), "tilt": slice(2 * n, 2 * n + 2),
            "yaw": slice(2 * n + 2, 2 * n + 3)}
    e = lev = None
    for _ in range(max(1, rounds)):
        sigma = {"tension": np.ones(n), "length": np.full(n, per["length"]), "swivel": np.full(n, per["swivel"]),
                 "orientation": np.array([per["tilt"], per["tilt"], per["yaw"]])}
        kin = Problem(model, meas, sigma)
        Z, _ = solve_poses(kin, theta, Z, max_iter=30, tol=1e-10)
        (grp, r, J, _), = kin.evaluate(theta, Z).groups
        # redundancy numbers of the whitened per-sample pose fit: 1 - diag(J (J'J)^-1 J')
        lev = 1.0 - np.einsum("kci,kij,kcj->kc", J, np.linalg.pinv(J.transpose(0, 2, 1) @ J), J)
        e = r / grp.weight
        per |= {c: math.sqrt(float(np.sum(e[:, s] ** 2) / max(float(np.sum(lev[:, s])), 1e-12)))
                for c, s in cols.items() if c in KINEMATIC}
    raw = {"length": sig["dl"], "swivel": sig["dsigma"]}
    step = {c: np.asarray(floor[c], float) * math.sqrt(12.0) for c in KINEMATIC}  # floor is step / sqrt 12
    groups = dict(base.groups)
    quant, sigma_out = {}, dict(base.sigma)
    for c in KINEMATIC:
        s = cols[c]
        blocks = [e[owner == j, s] for j in range(len(spans))]
        gamma0, rho, nh = _pooled(blocks, 0)
        red = float(np.mean(lev[:, s]))
        gamma0 = gamma0 / max(red, 1e-12)  # the pose fit took 1 - red of each sample's variance
        f = ar1_factor(rho, nh)
        # the quantisation error of a window mean, from each window's readings (Widrow): the within-window
        # scatter cannot see it (a reading on one count has none), yet it stays in the mean
        var_q = quantisation_variance([raw[c][sl] for sl, _ in spans], step[c])
        quant[c] = np.sqrt(var_q)
        mean = math.sqrt(gamma0 * f / nh + float(np.mean(var_q)))
        groups[c] = ChannelNoise(math.sqrt(gamma0), rho, nh / f, mean, float(np.max(floor[c])))
        sigma_out[c] = np.sqrt(gamma0 * f / nh + var_q)  # per cable: the group's noise, the cable's quantisation
    sigma_out["orientation"] = np.array([groups["tilt"].mean, groups["tilt"].mean, groups["yaw"].mean])
    return PoseFreeNoise(WindowNoise(sigma_out, base.window_size, groups), per, quant, Z, owner)


VCE_GROUPS = ("tension", "length", "swivel", "tilt", "yaw")
# a group (or a cable's rows) needs more degrees of freedom r than this for a component of its own: the weight
# a Helmert factor of r degrees of freedom sets, 1/factor, has a finite expectation (r / (r - 2) times the
# true weight) only for r > 2; with fewer the group keeps its within-window sigma
VCE_MIN_REDUNDANCY = 2.0
# model error is a stronger verdict than noise: a group is found dominated by it (scaled up to its rows' scatter,
# the unjudged groups floored at the sensors' specifications) only on at least this many degrees of freedom
# (issue 28: with fewer, a real run's small AHRS and length groups were scaled by one noisy factor each)
MISFIT_MIN_REDUNDANCY = 5.0
# groups whose cables get components of their own where each cable's rows carry them (variance_factors'
# per_cable; rescaled_sigma shrinks them toward the group's level by empirical Bayes, cable_factors, and splits
# only a group whose level is a noise's, not a model error's). grid2 (about 3 degrees of freedom a cable) pools
# on most runs; the real runs, whose swivel rows sit hundreds of times above their noise, are not split
PER_CABLE: tuple[str, ...] = ("swivel",)
_GROUP_SLICE = {"tilt": ("orientation", slice(0, 2)), "yaw": ("orientation", slice(2, 3))}  # group -> channel rows
NOISE_LEVEL = 0.01  # a group's rows scatter as noise while its factor x redundancy is inside this two-sided chi2 band
VCE_SETTLED = 0.98  # a factor above this is 1: nothing left to shrink
# a factor above this: the group's rows scatter around the fit by more than ~3 times the noise of a window mean
# (far beyond what a mis-estimated noise does: the within-window estimate is within ~1.6x of the scatter of
# window means on effect-free runs, tests/test_noise.py): the misfit is model error, the window scatter no
# longer weighs the group
MISFIT_FACTOR = 10.0


def variance_factors(problem, theta: np.ndarray, poses: np.ndarray, per_cable: tuple[str, ...] = ()
                     ) -> dict[str, tuple[float, float]]:
    """Per channel group (tensions, lengths, swivel angles, roll and pitch, yaw; the reference row's tensions
    and roll/pitch count with their group), Helmert's variance factor of the window means at a solution and
    the group's redundancy: sum r_i^2 / sum (1 - h_ii) of the weighted residuals r, h the hat matrix of the
    whitened fit over theta and every pose (dense: a few hundred rows). 1 when the group's sigma is what its
    rows scatter by around the fitted model. For the groups in ``per_cable`` each cable's rows also get
    their own factor and redundancy, under the key "group.i" (i from 0)."""
    ev = problem.evaluate(theta, poses)
    k, p = poses.shape[0], theta.size
    n = problem.model.robot.n
    res, rows, labels, cables = [], [], [], []
    for g, r, J, G in ev.groups:
        m = g.idx.size
        full = np.zeros((m, r.shape[1], p + 6 * k))
        full[..., :p] = G
        full[np.arange(m)[:, None], :, p + 6 * g.idx[:, None] + np.arange(6)[None, :]] = J.transpose(0, 2, 1)
        names, which = [], []
        for c in g.channels:
            names += ["tilt", "tilt", "yaw"] if c == "orientation" else [c] * n
            which += [-1, -1, -1] if c == "orientation" else list(range(n))
        keep = g.weight > 0
        res.append(r[keep])
        rows.append(full[keep])
        labels.append(np.broadcast_to(np.array(names), r.shape)[keep])
        cables.append(np.broadcast_to(np.array(which), r.shape)[keep])
    ref: list[str] = []
    for c in problem.ref_channels:
        ref += [c] * n if c == "tension" else ["tilt", "tilt", "yaw"]
    ref += ["prior"] * (ev.r0.size - len(ref))
    g0 = np.zeros((ev.r0.size, p + 6 * k))
    g0[:, :p] = ev.g0
    keep0 = np.r_[problem.ref_weight > 0, np.ones(ev.r0.size - problem.ref_weight.size, bool)]
    res.append(ev.r0[keep0])
    rows.append(g0[keep0])
    labels.append(np.array(ref)[keep0])
    cables.append(np.full(len(ref), -1)[keep0])  # the reference row and the priors: their group's only
    r, lab, cable = np.concatenate(res), np.concatenate(labels), np.concatenate(cables)
    q, _ = np.linalg.qr(np.vstack(rows))
    red = 1.0 - np.sum(q * q, axis=1)
    out = {}

    def factor(m: np.ndarray) -> tuple[float, float]:
        return float(np.sum(r[m] ** 2) / max(float(np.sum(red[m])), 1e-12)), float(np.sum(red[m]))

    for c in VCE_GROUPS:
        m = lab == c
        if m.any():
            out[c] = factor(m)
        if c in per_cable:
            out |= {f"{c}.{i}": factor(m & (cable == i)) for i in range(n) if np.any(m & (cable == i))}
    return out


def rescaled_sigma(sigma: dict[str, np.ndarray], factors: dict[str, tuple[float, float]],
                   floor: dict[str, np.ndarray] | None = None, within: dict[str, np.ndarray] | None = None,
                   lower: dict[str, np.ndarray] | None = None, follow: bool = True,
                   rejected: bool = False) -> dict[str, np.ndarray] | None:
    """The sigmas rescaled by the groups' variance factors (groups with at least VCE_MIN_REDUNDANCY degrees
    of freedom): a group whose rows scatter less than its sigma says (factor < VCE_SETTLED) is scaled by
    sqrt(factor); a group whose rows scatter by more than sqrt(MISFIT_FACTOR) times its sigma is dominated by
    model error, not noise, and gets the sigma its rows scatter by (sqrt(factor) times), so that it weighs
    what the model explains of it instead of pulling the pose to its own misfit; in between nothing changes
    (a moderate misfit stays in chi2, where the sigma_scale rule sees it). Once a group is found dominated
    by model error, the groups the fit cannot judge (too few degrees of freedom: the rows' own poses take
    their readings whole, e.g. the AHRS angles weighed by their window scatter) are floored at ``floor``
    (the sensors' specifications): their window scatter says nothing of the model's error there, and would
    let them dictate the poses. A group whose cables have components of their own (``factors`` "group.i",
    :func:`variance_factors`' per_cable) is split among them (:func:`cable_factors`) only while its rows
    scatter as noise does and its sigma is still a noise's: not above sqrt(MISFIT_FACTOR) times its
    within-window figure (``within``). A sigma raised to a misfit in an earlier round holds model error, and
    a split would down-weight the cables the model misses most (issue 28's guard against model error: on the
    real sc_27_medium_a the swivel rows scatter ~2200x their within-window variance, cable 1's 2-4x the others').
    No channel is brought below ``lower`` (the quantisation error of its window means,
    :attr:`PoseFreeNoise.quantisation`): the rows' own poses absorb part of their scatter, never the error a
    reading that does not dither keeps. A level raised to model error in an earlier round (above
    sqrt(MISFIT_FACTOR) times ``within``) follows its rows' scatter both ways, floored at ``within``, unless
    ``follow`` is off (then it keeps the dead band of a noise level). ``rejected``: the fit's chi2 is beyond its
    band under these sigmas (the model is rejected for its noise, :func:`rejects`): a group whose own rows reject
    their sigma as well (their chi2, factor x redundancy, above the upper NOISE_LEVEL / 2 tail on its degrees of
    freedom) gets the sigma its rows scatter by (Helmert's step, floored at ``within``) whatever its redundancy
    and factor: neither the dead band nor the redundancy a misfit verdict otherwise needs holds there, since a
    group weighed far below its scatter takes its rows' poses with it and shows little redundancy because of that
    weight (issue 29, docs/windows.md: "Ends whose chi2 rejects their noise"). None when nothing changes."""
    out = {c: np.array(v, float) for c, v in sigma.items()}
    changed = False

    def scale(c: str, s: float) -> None:
        if c == "tilt":
            out["orientation"][:2] *= s
        elif c == "yaw":
            out["orientation"][2] *= s
        else:
            out[c] = out[c] * s

    groups = {c: v for c, v in factors.items() if "." not in c}
    misfit = any(red >= MISFIT_MIN_REDUNDANCY and f > MISFIT_FACTOR for f, red in groups.values())
    for c, (f, red) in groups.items():
        ch, sl = _GROUP_SLICE.get(c, (c, slice(None)))
        if rejected and rejects(f * red, red):
            base = np.asarray(within[ch], float)[sl] if within is not None else out[ch][sl]
            out[ch][sl] = np.maximum(out[ch][sl] * math.sqrt(f), base)
            changed = True
            continue
        if red < VCE_MIN_REDUNDANCY or (f > MISFIT_FACTOR and red < MISFIT_MIN_REDUNDANCY):
            if misfit and floor is not None:
                low = out[ch][sl] < np.asarray(floor[ch], float)[sl]
                if low.any():
                    out[ch][sl] = np.maximum(out[ch][sl], np.asarray(floor[ch], float)[sl])
                    changed = True
            continue
        if follow and within is not None and \
                np.any(sigma[ch][sl] > math.sqrt(MISFIT_FACTOR) * np.asarray(within[ch], float)[sl]):
            # a level raised to a model error's in an earlier round follows its rows' scatter both ways (Helmert's
            # fixed point, sigma^2 = ssq / r): sized first at a poorly fitted pose, it is re-sized at each better
            # one instead of staying where the first round put it (the dead band below is for noise levels)
            if abs(f - 1.0) > 1.0 - VCE_SETTLED:
                out[ch][sl] = np.maximum(out[ch][sl] * math.sqrt(f), np.asarray(within[ch], float)[sl])
                changed = True
            continue
        if not VCE_SETTLED <= f <= MISFIT_FACTOR:
            scale(c, math.sqrt(max(f, 1e-6)))
            changed = True
        if f > MISFIT_FACTOR:
            continue  # model error: the group's rows together, as they scatter
        cable = [factors.get(f"{c}.{i}") for i in range(out[c].size)] if c not in ("tilt", "yaw") else [None]
        if not all(v is not None and v[1] >= VCE_MIN_REDUNDANCY for v in cable):
            continue  # no components of its cables (not asked for, or too few degrees of freedom)
        if within is not None and np.any(sigma[c] > math.sqrt(MISFIT_FACTOR) * np.asarray(within[c], float)):
            continue  # its level is a model error's (raised in an earlier round), not noise to share out
        p = chi2_sf(f * red, red)
        if 2.0 * min(p, 1.0 - p) >= NOISE_LEVEL:
            # the cables' own components split the group's level among them (f_i / f each, f_i shrunk toward
            # the pooled level by their degrees of freedom: cable_factors), where the group scatters as its
            # noise does: beyond that it holds model error, which the split would only share out
            shrunk = cable_factors(np.array([v[0] for v in cable]), np.array([v[1] for v in cable]), out[c])
            split = np.sqrt(np.maximum(shrunk, 1e-6) / max(f, 1e-6))
            if np.max(np.abs(split - 1.0)) > 1.0 - VCE_SETTLED:
                out[c] = out[c] * split
                changed = True
    for c, low in (lower or {}).items():
        out[c] = np.maximum(out[c], np.minimum(np.asarray(low, float), sigma[c]))  # never below it, nor raised
    return out if changed else None


def rejects(chi2: float, dof: float) -> bool:
    """Whether rows whose weighted squared residuals sum to ``chi2`` on ``dof`` degrees of freedom reject their
    sigmas: chi2 above the upper NOISE_LEVEL / 2 tail of its distribution (the end of a solve judged so:
    calib.selfcal._solve; a group's rows: :func:`rescaled_sigma`'s ``rejected``)."""
    return dof > 0 and chi2 > dof and chi2_sf(chi2, dof) < NOISE_LEVEL / 2.0


def sigma_change(old: dict[str, np.ndarray], new: dict[str, np.ndarray]) -> float:
    """The largest relative change of any channel's sigma from ``old`` to ``new`` (|new / old - 1|)."""
    return max(float(np.max(np.abs(np.asarray(new[c], float) / np.asarray(old[c], float) - 1.0))) for c in old)


def reference_sigma(rows: dict[str, np.ndarray], within: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per channel, the sigma of a window mean the reference window's noise is sized from
    (priors.ReferenceNoise.for_rows scales it to the reference's own size): the rows' sigma after their
    variance components (``rows``) where those brought it below its within-window figure (``within``), that
    figure otherwise. The reference mean is a window mean of the same readings as the rows: where the rows'
    means scatter less than the within-window figure says (it holds motion a mean averages out), so does
    the reference's (kept at the within-window figure, its prior was about twice the reference error on
    simulated startups and the initial position's sigma too wide, docs/windows.md). Where the variance
    components raise a group (the model misses its rows: model error), the reference reading does not carry
    that misfit and keeps the within-window figure."""
    return {c: np.minimum(np.asarray(rows[c], float), np.asarray(within[c], float)) for c in within}
