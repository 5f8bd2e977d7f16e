"""Calibration pose planning (Zoffoli Sec. 3.2.1) and paths for the kinematic method.

Equilibrium method: an nx x ny x nz grid of positions in the workspace bounds (eq. 19); at each the inverse
geometrico-static problem gives the orientation and the tension setpoint (Appendix A). The poses are
visited in the order that minimises the total transition cost of a closed tour that starts and ends at the
home tension tau0. The transition cost between two setpoints is the largest tension change over the
cables, max_i |tau_a,i - tau_b,i| (N): with a rate-limited tension trajectory the transition time is that
change divided by the maximum tension rate, so the tour minimises the time spent in transitions.

Kinematic method: a serpentine path through the same grid, densified so that consecutive waypoints are a
few centimetres apart, each waypoint an equilibrium with its tensions; following the tensions linearly in
time between waypoints moves the platform quasi-statically at a roughly constant speed.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from calib.equilibrium import direct_statics, inverse_geometrico_static
from calib.errors import CdprError
from calib.robot import Robot


class PlanningError(CdprError, ValueError):
    """The requested plan cannot be made (a grid point outside the static workspace, bad grid)."""


@dataclass(frozen=True)
class PosePlan:
    """Planned equilibrium poses and tension setpoints, in visiting order."""

    poses: np.ndarray  # (k, 6) ideal poses [x, y, z, roll, pitch, yaw], m and rad
    setpoints: np.ndarray  # (k, n) tension setpoints, N
    tau0: np.ndarray  # (n,) home tensions, N
    home_pose: np.ndarray  # (6,) equilibrium under tau0
    grid_index: np.ndarray  # (k, 3) grid indices (ix, iy, iz) of each visited pose
    transition_cost: float  # N: sum of max_i |delta tau_i| over the closed tour tau0 -> ... -> tau0
    min_stiffness: np.ndarray  # (k,) smallest free-motion stiffness eigenvalue (positive: stable)

    def to_dict(self) -> dict:
        return {
            "poses": self.poses.tolist(),
            "setpoints": self.setpoints.tolist(),
            "tau0": self.tau0.tolist(),
            "home_pose": self.home_pose.tolist(),
            "transition_cost": self.transition_cost,
            "transition_cost_rule": "sum over the closed tour from tau0 of max_i |delta tau_i| (N)",
        }


def _grid_counts(grid: int | tuple[int, int, int]) -> tuple[int, int, int]:
    counts = (grid, grid, grid) if isinstance(grid, int) else tuple(int(g) for g in grid)
    if len(counts) != 3 or any(c < 1 for c in counts):
        raise PlanningError(f"grid must be a positive integer or three of them, got {grid!r}.")
    return counts  # type: ignore[return-value]


def grid_positions(robot: Robot, grid: int | tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Positions (k, 3) of the regular grid in the workspace bounds and their grid indices (k, 3)."""
    counts = _grid_counts(grid)
    if not np.all(np.isfinite(robot.workspace_lower)):
        raise PlanningError(f"robot '{robot.name}' has no workspace bounds (field 'workspace').")
    axes = [
        np.linspace(lo, hi, c) if c > 1 else np.array([(lo + hi) / 2])
        for lo, hi, c in zip(robot.workspace_lower, robot.workspace_upper, counts, strict=True)
    ]
    idx = np.array(list(itertools.product(*[range(c) for c in counts])))
    pos = np.stack([axes[j][idx[:, j]] for j in range(3)], axis=1)
    return pos, idx


def transition_costs(tensions: np.ndarray) -> np.ndarray:
    """Pairwise cost matrix (m, m): the largest tension change between two setpoints, N."""
    t = np.asarray(tensions, dtype=float)
    return np.abs(t[:, None, :] - t[None, :, :]).max(axis=2)


def _tour_exact(cost: np.ndarray) -> list[int]:
    """Held-Karp: the cheapest closed tour from node 0 through all nodes (m <= 13)."""
    m = cost.shape[0]
    full = 1 << (m - 1)
    best = np.full((full, m), np.inf)
    parent = np.full((full, m), -1, dtype=int)
    for j in range(1, m):
        best[1 << (j - 1), j] = cost[0, j]
    for mask in range(1, full):
        for j in range(1, m):
            if not mask & (1 << (j - 1)) or not np.isfinite(best[mask, j]):
                continue
            for nxt in range(1, m):
                bit = 1 << (nxt - 1)
                if mask & bit:
                    continue
                c = best[mask, j] + cost[j, nxt]
                if c < best[mask | bit, nxt]:
                    best[mask | bit, nxt] = c
                    parent[mask | bit, nxt] = j
    last = int(np.argmin(best[full - 1, 1:] + cost[1:, 0])) + 1
    order, mask = [], full - 1
    while last > 0:
        order.append(last)
        prev = parent[mask, last]
        mask &= ~(1 << (last - 1))
        last = prev
    return order[::-1]


def _tour_heuristic(cost: np.ndarray) -> list[int]:
    """Nearest neighbour from node 0, improved by 2-opt until no move helps."""
    m = cost.shape[0]
    tour = [0]
    left = set(range(1, m))
    while left:
        nxt = min(left, key=lambda j: cost[tour[-1], j])
        tour.append(nxt)
        left.remove(nxt)
    tour.append(0)
    improved = True
    while improved:
        improved = False
        for a in range(1, len(tour) - 2):
            for b in range(a + 1, len(tour) - 1):
                old = cost[tour[a - 1], tour[a]] + cost[tour[b], tour[b + 1]]
                new = cost[tour[a - 1], tour[b]] + cost[tour[a], tour[b + 1]]
                if new < old - 1e-12:
                    tour[a : b + 1] = tour[a : b + 1][::-1]
                    improved = True
    return tour[1:-1]


def order_setpoints(tau0: np.ndarray, setpoints: np.ndarray) -> tuple[list[int], float]:
    """Visiting order (indices into setpoints) of the cheapest closed tour from tau0, and its cost (N)."""
    nodes = np.vstack([tau0, setpoints])
    cost = transition_costs(nodes)
    # whole micro-newtons: a symmetric grid has many tours of equal cost, and costs that differ only in their
    # last bits (another libm, another x87 precision) would pick different ones; integral costs sum exactly,
    # so ties are exact and the first tour found wins on every machine
    q = np.rint(cost * 1e6)
    order = _tour_exact(q) if len(nodes) <= 13 else _tour_heuristic(q)
    path = [0, *order, 0]
    total = float(sum(cost[a, b] for a, b in zip(path[:-1], path[1:], strict=True)))
    return [j - 1 for j in order], total


def home(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """(tau0, home pose): the home tensions of the description (or the centre-top equilibrium) and its pose."""
    if robot.tau0 is not None:
        tau0 = np.asarray(robot.tau0, dtype=float)
        res = direct_statics(robot, tau0)
        if not res.converged[0]:
            raise PlanningError(f"robot '{robot.name}': no equilibrium found under tensions.tau0 = {tau0.tolist()}.")
        return tau0, res.poses[0]
    top = np.r_[(robot.workspace_lower[:2] + robot.workspace_upper[:2]) / 2, robot.workspace_upper[2]]
    sp = inverse_geometrico_static(robot, top[None])
    return sp.tensions[0], sp.poses[0]


def plan_poses(robot: Robot, grid: int | tuple[int, int, int] = 2) -> PosePlan:
    """Equilibrium calibration poses on a grid in the workspace bounds, in the cheapest visiting order."""
    pos, idx = grid_positions(robot, grid)
    sp = inverse_geometrico_static(robot, pos)
    bad = np.flatnonzero(~sp.feasible)
    if bad.size:
        j = int(bad[0])
        why = (
            "no equilibrium orientation"
            if not sp.converged[j]
            else "tensions outside [tensions.min, tensions.max]"
            if not sp.within_bounds[j]
            else "an unstable equilibrium"
        )
        raise PlanningError(
            f"robot '{robot.name}': grid position {np.round(pos[j], 4).tolist()} has {why}; "
            f"{bad.size} of {len(pos)} grid points are outside the static workspace (shrink 'workspace')."
        )
    tau0, home_pose = home(robot)
    order, total = order_setpoints(tau0, sp.tensions)
    return PosePlan(
        poses=sp.poses[order],
        setpoints=sp.tensions[order],
        tau0=tau0,
        home_pose=home_pose,
        grid_index=idx[order],
        transition_cost=total,
        min_stiffness=sp.min_stiffness[order],
    )


@dataclass(frozen=True)
class KinematicPath:
    """Waypoints of a constant-speed path through the workspace, each an equilibrium."""

    poses: np.ndarray  # (m, 6)
    tensions: np.ndarray  # (m, n), N
    times: np.ndarray  # (m,) s, arrival time at each waypoint from the start of the path
    speed: float  # m/s


def kinematic_path(
    robot: Robot, grid: int | tuple[int, int, int] = 2, speed: float = 0.05, spacing: float = 0.05
) -> KinematicPath:
    """A serpentine through the grid (x fastest, then y, then z from the top), densified every ``spacing`` m.

    The platform is driven quasi-statically through equilibria, so tensions between waypoints are
    interpolated linearly in time; waypoint times follow from the path length at ``speed``.
    """
    pos, idx = grid_positions(robot, grid)
    nx, ny, nz = _grid_counts(grid)
    corners = []
    for iz in range(nz - 1, -1, -1):
        ys = range(ny) if (nz - 1 - iz) % 2 == 0 else range(ny - 1, -1, -1)
        for row, iy in enumerate(ys):
            xs = range(nx) if row % 2 == 0 else range(nx - 1, -1, -1)
            for ix in xs:
                corners.append(np.flatnonzero((idx == [ix, iy, iz]).all(1))[0])
    tau0, home_pose = home(robot)
    pts = [home_pose[:3]] + [pos[c] for c in corners] + [home_pose[:3]]
    dense = [pts[0]]
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        steps = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
        dense.extend(a + (b - a) * s / steps for s in range(1, steps + 1))
    dense_arr = np.array(dense)
    sp = inverse_geometrico_static(robot, dense_arr)
    if not sp.feasible.all():
        j = int(np.flatnonzero(~sp.feasible)[0])
        where = np.round(dense_arr[j], 4).tolist()
        raise PlanningError(f"robot '{robot.name}': the kinematic path leaves the static workspace at {where}.")
    seg = np.linalg.norm(np.diff(dense_arr, axis=0), axis=1)
    times = np.r_[0.0, np.cumsum(seg) / speed]
    return KinematicPath(sp.poses, sp.tensions, times, speed)
