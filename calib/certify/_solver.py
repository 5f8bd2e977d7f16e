"""Contractor programme of the Sandretto paper on codac: FixP(QInter(q, hc4r(F_1), ..., hc4r(F_N))), then a
paving where contraction alone stalls.

One codac CtcInverse (forward-backward, HC4-revise) per measurement contracts a box of anchors onto the
thick sphere |a - c_k|^2 in [r_lo_k, r_hi_k]^2. Careful: codac 2's CtcQInter / qinter take the number of
contractors allowed to *fail*, not (as IBEX and the paper) the number that must hold; ``n_fail`` below is
always that codac count.

The paving then looks for the six faces of the hull of the solution set: for each axis and side, a
best-first search pops the box with the lowest (highest) bound, contracts it and bisects it, until a box of
the paving resolution, or a box whose every point is a solution, reaches the top of the queue. Every
solution lies in a queued box, so that bound is a guaranteed outer bound; the next search starts from the
queue the previous one left. Each box first classifies the measurements by the exact range of |a - c_k|
over the box (floating point with a margin far above rounding): spheres that contain the whole box or miss
it entirely are counted, and only the undecided ones are contracted, with the failures still allowed.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from calib.certify._bounds import Shells
from calib.certify._rounding import codac, codac_rounding

_CLASSIFY_MARGIN = 1e-9  # m, far above the rounding error of a distance of a few metres


@dataclass(frozen=True)
class CableSolution:
    """The outcome of one cable: boxes as (3, 2) arrays [[lo, hi], ...] in m, or None when empty.

    contracted: FixP(QInter) on the initial box alone (the paper's programme); box: the enclosure after the
    paving; outliers: measurements whose thick sphere misses ``box`` (0-based); boxes: boxes contracted;
    exhausted: the box budget ran out (the hull is still guaranteed, only less tight).
    """

    contracted: np.ndarray | None
    box: np.ndarray | None
    outliers: tuple[int, ...]
    boxes: int
    exhausted: bool


def shell_contractors(shells: Shells) -> list:
    """One codac CtcInverse per measurement: |a - c_k|^2 in [r_lo_k, r_hi_k]^2 (a in m)."""
    a = codac.VectorVar(3)
    out = []
    for c, lo, hi in zip(shells.centres, shells.r_lo, shells.r_hi, strict=True):
        f = codac.AnalyticFunction([a], codac.sqr(a[0] - float(c[0])) + codac.sqr(a[1] - float(c[1]))
                                   + codac.sqr(a[2] - float(c[2])))
        out.append(codac.CtcInverse(f, codac.sqr(codac.Interval(float(lo), float(hi))), False))
    return out


def _to_array(x: codac.IntervalVector) -> np.ndarray | None:
    if x.is_empty():
        return None
    return np.array([[x[j].lb(), x[j].ub()] for j in range(3)])


def fixpoint(step, x: codac.IntervalVector, ratio: float) -> codac.IntervalVector:
    """Apply ``step`` until no dimension of the box shrinks by more than ``ratio`` (relative width)."""
    while True:
        before = np.array(x.diam())
        x = step(x)
        if x.is_empty():
            return x
        after = np.array(x.diam())
        shrink = np.where(before > 0, (before - after) / np.where(before > 0, before, 1.0), 0.0)
        if float(shrink.max()) <= ratio:
            return x


def _qinter_step(ctcs: list, n_fail: int):
    def step(x: codac.IntervalVector) -> codac.IntervalVector:
        boxes = [c.contract(codac.IntervalVector(x)) for c in ctcs]
        return codac.qinter(n_fail, boxes) & x

    return step


def _distance_range(shells: Shells, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact min and max of |a - c_k| over the box [lo, hi] (k,), m."""
    c = shells.centres
    near = np.maximum(0.0, np.maximum(lo - c, c - hi))
    far = np.maximum(np.abs(c - lo), np.abs(c - hi))
    return np.linalg.norm(near, axis=1), np.linalg.norm(far, axis=1)


def _node(shells: Shells, ctcs: list, full, n_fail: int, x: codac.IntervalVector, resolution: float,
          ratio: float) -> tuple[str, codac.IntervalVector]:
    """Contract one paving box: ('empty' | 'inner' | 'leaf' | 'split', contracted box)."""
    b = _to_array(x)
    dmin, dmax = _distance_range(shells, b[:, 0], b[:, 1])
    failed = (dmax < shells.r_lo - _CLASSIFY_MARGIN) | (dmin > shells.r_hi + _CLASSIFY_MARGIN)
    holds = (dmin >= shells.r_lo + _CLASSIFY_MARGIN) & (dmax <= shells.r_hi - _CLASSIFY_MARGIN)
    allowed = n_fail - int(failed.sum())
    if allowed < 0:
        return "empty", x
    undecided = np.flatnonzero(~failed & ~holds)
    if len(undecided) <= allowed:
        return "inner", x  # every point of the box satisfies enough measurements
    if 2 * len(undecided) > len(ctcs):
        # the prebuilt QInter over all measurements is equivalent (decided ones give x or the empty box)
        # and cheaper than contracting the undecided ones one by one from Python
        x = fixpoint(full.contract, x, ratio)
    else:
        x = fixpoint(_qinter_step([ctcs[k] for k in undecided], allowed), x, ratio)
    if x.is_empty():
        return "empty", x
    return ("leaf" if x.max_diam() <= resolution else "split"), x


def _extreme(shells: Shells, ctcs: list, full, n_fail: int, cover: list[tuple[codac.IntervalVector, bool]],
             j: int, side: int, resolution: float, budget: int,
             ratio: float) -> tuple[float | None, list[tuple[codac.IntervalVector, bool]], int, bool]:
    """Best-first search of the lowest (side 0) or highest (side 1) value of axis j over the solution set.

    ``cover`` is a list of (box, final) whose union contains every solution; final boxes (inner or of the
    resolution) are not bisected further. The queue always covers the solution set, so its best bound is a
    valid outer bound; the search stops when a final box reaches the top. Returns (bound or None when the
    set is empty, the remaining cover for the next search, boxes contracted, budget exhausted).
    """
    sign = 1.0 if side == 0 else -1.0

    def key(x: codac.IntervalVector) -> float:
        return sign * (x[j].lb() if side == 0 else x[j].ub())

    heap = [(key(x), i, x, final) for i, (x, final) in enumerate(cover)]
    heapq.heapify(heap)
    counter = len(heap)
    used = 0
    while heap:
        k, _, x, final = heap[0]
        if final or used >= budget:
            return sign * k, [(item[2], item[3]) for item in heap], used, not final
        heapq.heappop(heap)
        used += 1
        status, x = _node(shells, ctcs, full, n_fail, x, resolution, ratio)
        if status == "empty":
            continue
        if status in ("inner", "leaf"):
            counter += 1
            heapq.heappush(heap, (key(x), counter, x, True))
            continue
        width = np.array(x.diam())
        for part in x.bisect(int(np.argmax(width)), 0.5):
            counter += 1
            heapq.heappush(heap, (key(part), counter, part, False))
    return None, [], used, False


def solve_cable(
    shells: Shells,
    box: np.ndarray,
    n_fail: int,
    *,
    resolution: float = 5e-4,
    max_boxes: int = 20000,
    ratio: float = 0.01,
    paving_ratio: float = 0.1,
) -> CableSolution:
    """Enclose the anchors of ``box`` (3, 2) satisfying all but ``n_fail`` thick spheres (codac meaning).

    ``ratio`` is the fixpoint criterion of the root contraction (the paper's 1 %), ``paving_ratio`` that of
    the paving's boxes, where bisection takes over sooner.
    """
    with codac_rounding():
        return _solve_cable(shells, box, n_fail, resolution, max_boxes, ratio, paving_ratio)


def _solve_cable(shells: Shells, box: np.ndarray, n_fail: int, resolution: float, max_boxes: int,
                 ratio: float, paving_ratio: float) -> CableSolution:
    n = len(shells.r_lo)
    ctcs = shell_contractors(shells)
    x0 = codac.IntervalVector([[float(lo), float(hi)] for lo, hi in box])
    full = codac.CtcQInter(n_fail, ctcs)
    root = fixpoint(full.contract, x0, ratio)
    contracted = _to_array(root)
    if contracted is None:
        return CableSolution(None, None, (), 1, False)

    hull = contracted.copy()
    cover = [(root, False)]
    visited, exhausted = 0, False
    for j in range(3):
        for side in (0, 1):
            bound, cover, used, out_of_budget = _extreme(shells, ctcs, full, n_fail, cover, j, side, resolution,
                                                         max_boxes - visited, paving_ratio)
            visited += used
            exhausted |= out_of_budget
            if bound is None:
                return CableSolution(contracted, None, (), visited, exhausted)
            hull[j, side] = bound
    final = codac.IntervalVector([[float(lo), float(hi)] for lo, hi in hull])
    outliers = tuple(k for k in range(n) if ctcs[k].contract(codac.IntervalVector(final)).is_empty())
    return CableSolution(contracted, hull, outliers, visited, exhausted)

