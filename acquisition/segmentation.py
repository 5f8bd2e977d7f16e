"""Setpoints found in a target-tension signal (the IRMA controller's log): where the reference jumps, where each
quintic transition ends, and per sample the phase (hold or transition) and the setpoint index; the importers
(``acquisition/importers.py``) label the samples of a run with it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from acquisition.trajectory import PEAK_RATE


@dataclass
class SetpointSegmentation:
    """Setpoints found in a target-tension signal and the per-sample phase and setpoint index."""

    setpoints: np.ndarray  # (k, n) N
    phase: np.ndarray  # (N,) str: pretension | transition | hold
    index: np.ndarray  # (N,) int, -1 outside holds
    plateaus: list[tuple[int, int]]  # [first, last] sample of each steady target segment after pretension
    cut: list[tuple[int, int]] = field(default_factory=list)  # [first, last] sample of each move left unfinished
    rest: tuple[int, int] | None = None  # [first, last] sample of the power-on rest held before the sequence
    dropped: list[tuple[int, int]] = field(default_factory=list)  # unfinished moves whose destination is in doubt


def reference_jumps(target: np.ndarray, floor: float = 0.05) -> np.ndarray:
    """Samples (sorted) where the target tensions (N, n) jump: the controller restarted its reference from the
    measured tensions to begin a new move. A jump is a step larger than ``floor`` N and three times either
    neighbouring step (a smooth trajectory's steps change gradually)."""
    d = np.abs(np.diff(np.asarray(target, dtype=float), axis=0))
    if d.shape[0] < 2:
        return np.zeros(0, dtype=int)
    prev = np.r_[np.zeros((1, d.shape[1])), d[:-1]]
    nxt = np.r_[d[1:], np.zeros((1, d.shape[1]))]
    return np.flatnonzero(np.any((d > floor) & (d > 3.0 * np.maximum(prev, nxt)), axis=1)) + 1


def quintic_destination(x: np.ndarray, fit_tol: float = 0.05) -> float | None:
    """Where a quintic (minimum-jerk) move x (m,) that starts at rest on x[0] was heading when it was cut:
    the fit of x0 + D s((k - k0) / K), s(u) = 10u^3 - 15u^4 + 6u^5, over its samples k; None when the move is
    not such a quintic (worst residual above ``fit_tol``, N)."""
    from scipy.optimize import least_squares  # here: scipy.optimize costs every cdpr command ~0.2 s

    x = np.asarray(x, dtype=float)
    k = np.arange(x.size, dtype=float)
    a, peak = x[0], float(np.abs(np.diff(x)).max())
    moving = np.flatnonzero(np.abs(x - a) > 1e-6)
    if moving.size < 4 or peak <= 0.0:
        return None

    def shape(p):
        u = np.clip((k - p[0]) / p[1], 0.0, 1.0)
        return u**3 * (10.0 - 15.0 * u + 6.0 * u * u)

    d0 = 1.5 * (x[-1] - a)
    fit = least_squares(lambda p: a + p[2] * shape(p) - x, [moving[0] - 1.0, PEAK_RATE * abs(d0) / peak, d0],
                        bounds=([-x.size, 2.0, -np.inf], [x.size, 100.0 * x.size, np.inf]))
    if not fit.success or np.abs(fit.fun).max() > fit_tol:
        return None
    return float(a + fit.x[2])


def segment_targets(
    target: np.ndarray,
    sample_period: float,
    min_hold: float = 1.0,
    pretension_band: float = 5.0,
    setpoints: np.ndarray | None = None,
    match_tol: float = 0.05,
    bounds: tuple[float, float] = (0.0, math.inf),
    measured: np.ndarray | None = None,
) -> SetpointSegmentation:
    """Find the setpoints of the target tensions (N, n), in order.

    The pretension phase lasts until a target first departs by more than ``pretension_band`` N from its
    first value. After it, every segment where all targets stay constant for at least ``min_hold`` s is a
    hold. A move the controller left unfinished (the reference jumped to begin the next move while a target
    was still on its way, :func:`reference_jumps`) had a setpoint too: each target still moving is extended
    to where its quintic was heading (:func:`quintic_destination`); no sample of it is a hold. Such a
    destination is in doubt, and dropped (``dropped``), when it lies outside the tension ``bounds`` (N, the
    robot's) or less than ``pretension_band`` from where the move began (a restart of the reference, not a
    move). A
    first steady segment entered by a jump of the reference straight from the pretension to within
    ``pretension_band`` of the mean ``measured`` tensions (N, n) of the pretension (the controller holding
    the tensions it measured at power-on) is the rest before the sequence (``rest``, phase ``rest``), not a
    setpoint. Without
    ``setpoints``, these values (consecutive equal ones merged) are the setpoints; with them, each hold takes
    the index of the setpoint it equals within ``match_tol`` N (-1 if none).
    """
    T = np.asarray(target, dtype=float)
    N = T.shape[0]
    phase = np.full(N, "transition", dtype=object)
    index = np.full(N, -1, dtype=int)
    if N == 0:
        return SetpointSegmentation(np.zeros((0, T.shape[1])), phase.astype(str), index, [])
    away = np.flatnonzero(np.max(np.abs(T - T[0]), axis=1) > pretension_band)
    pre_end = int(away[0]) if away.size else N
    phase[:pre_end] = "pretension"
    tol = 1e-9 + 1e-7 * np.abs(T[1:])
    same = np.r_[False, np.all(np.abs(np.diff(T, axis=0)) <= tol, axis=1)]  # same[j]: T[j] == T[j-1]
    min_len = max(2, int(round(min_hold / sample_period)))
    plateaus: list[tuple[int, int]] = []
    j = pre_end
    while j < N:
        k = j
        while k + 1 < N and same[k + 1]:
            k += 1
        if k - j + 1 >= min_len:
            plateaus.append((j, k))
        j = k + 1
    # moves cut by a jump of the reference, their last sample not steady: (first, last, destination)
    cut: list[tuple[int, int, np.ndarray]] = []
    jumps = reference_jumps(T)
    rest = None
    if measured is not None and plateaus and plateaus[0][0] == pre_end and pre_end in jumps:
        held = np.asarray(measured, dtype=float)[:pre_end].mean(axis=0)
        if np.max(np.abs(T[pre_end] - held)) < pretension_band:
            rest = plateaus.pop(0)
    if rest is not None:
        phase[rest[0] : rest[1] + 1] = "rest"
    lo, hi = bounds
    dropped: list[tuple[int, int]] = []
    starts = np.r_[0, jumps]
    for a, b in zip(starts[:-1], starts[1:] - 1, strict=True):
        if b < pre_end or b - a < 4 or same[b]:
            continue
        dest = T[b].copy()
        for i in np.flatnonzero(np.abs(T[b] - T[b - 1]) > tol[b - 1]):
            end = quintic_destination(T[a : b + 1, i])
            dest[i] = np.nan if end is None else end
        if not np.all(np.isfinite(dest)):
            continue
        if np.any((dest < lo) | (dest > hi)) or np.max(np.abs(dest - T[a])) < pretension_band:
            dropped.append((int(a), int(b)))
        else:
            cut.append((int(a), int(b), dest))
    steps = sorted([(a, b, T[a], False) for a, b in plateaus] + [(a, b, v, True) for a, b, v in cut],
                   key=lambda s: s[0])
    found: list[np.ndarray] = []
    for a, b, value, unfinished in steps:
        if not unfinished:
            phase[a : b + 1] = "hold"
        if setpoints is None:
            if not found or np.max(np.abs(found[-1] - value)) > match_tol:
                found.append(value)
            j = len(found) - 1
        else:
            d = np.max(np.abs(np.asarray(setpoints) - value), axis=1)
            j = int(np.argmin(d)) if d.min() <= match_tol else -1
        if not unfinished:
            index[a : b + 1] = j
    sp = np.asarray(setpoints, dtype=float) if setpoints is not None else np.array(found).reshape(-1, T.shape[1])
    return SetpointSegmentation(sp, phase.astype(str), index, plateaus, [(a, b) for a, b, _ in cut], rest, dropped)
