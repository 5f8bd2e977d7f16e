"""Static workspace over a grid of positions (Zoffoli Appendix A; Idà & Carricato 2024).

Each grid position is tested by the inverse geometrico-static problem: it belongs to the static workspace
when an equilibrium orientation exists, its tensions respect the bounds (eq. A3) and it is stable (eq. A4).
The boundary is the set of member points with at least one grid neighbour (6-connectivity) outside the
workspace or outside the grid.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from calib.equilibrium import StaticPose, inverse_geometrico_static
from calib.robot import Robot


@dataclass(frozen=True)
class WorkspaceMap:
    axes: tuple[np.ndarray, np.ndarray, np.ndarray]  # grid coordinates along x, y, z, m
    positions: np.ndarray  # (N, 3)
    solution: StaticPose  # per position: pose, tensions, flags
    boundary: np.ndarray  # (N,) bool

    @property
    def member(self) -> np.ndarray:
        return self.solution.feasible

    def summary(self) -> dict:
        m = self.member
        p = self.positions[m]
        return {
            "points": int(len(m)),
            "in_workspace": int(m.sum()),
            "boundary": int(self.boundary.sum()),
            "extent_lower": p.min(0).tolist() if len(p) else None,
            "extent_upper": p.max(0).tolist() if len(p) else None,
        }


def default_volume(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """The installation volume: the pulley points' horizontal extent, from the floor (z = 0) to below them."""
    lo = np.r_[robot.d[:, :2].min(0), 0.0]
    hi = np.r_[robot.d[:, :2].max(0), robot.d[:, 2].min() - 0.2]
    return lo, hi


def static_workspace(
    robot: Robot, lower: np.ndarray | None = None, upper: np.ndarray | None = None, step: float = 0.1,
    progress: Callable[[int, int], None] | None = None, chunk: int = 500,
) -> WorkspaceMap:
    """Evaluate the static workspace on a regular grid with spacing ``step`` (m) inside [lower, upper].

    The positions are solved ``chunk`` at a time; ``progress(done, total)`` is called after each chunk. A
    position where a cable cannot leave its pulley (the anchor within the pulley radius: no tangent, NaN
    lengths) is outside the workspace, without numpy's warning."""
    lo, hi = default_volume(robot)
    lo = lo if lower is None else np.asarray(lower, float)
    hi = hi if upper is None else np.asarray(upper, float)
    axes = tuple(np.arange(a, b + step / 2, step) for a, b in zip(lo, hi, strict=True))
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    pos = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], 1)
    parts = []
    for a in range(0, len(pos), chunk):
        with np.errstate(invalid="ignore"):
            parts.append(inverse_geometrico_static(robot, pos[a : a + chunk]))
        if progress is not None:
            progress(min(a + chunk, len(pos)), len(pos))
    sol = StaticPose(*(np.concatenate([getattr(q, f.name) for q in parts]) for f in fields(StaticPose)))
    member = sol.feasible.reshape(gx.shape)
    padded = np.pad(member, 1, constant_values=False)
    inner = np.ones_like(member)
    for ax in range(3):
        for shift in (-1, 1):
            inner &= np.roll(padded, shift, axis=ax)[1:-1, 1:-1, 1:-1]
    boundary = (member & ~inner).ravel()
    return WorkspaceMap(axes, pos, sol, boundary)  # type: ignore[arg-type]


def plot_workspace(ws: WorkspaceMap, robot: Robot, path: str | Path) -> Path:
    """A PNG of the workspace boundary points, the pulley points and the calibration bounds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    b = ws.positions[ws.boundary]
    if len(b):
        sc = ax.scatter(b[:, 0], b[:, 1], b[:, 2], c=ws.solution.tensions[ws.boundary].max(1), s=6, cmap="viridis")
        fig.colorbar(sc, ax=ax, shrink=0.6, label="largest tension (N)")
    ax.scatter(robot.d[:, 0], robot.d[:, 1], robot.d[:, 2], marker="^", c="red", s=40, label="pulleys")
    if np.all(np.isfinite(robot.workspace_lower)):
        lo, hi = robot.workspace_lower, robot.workspace_upper
        for x in (lo[0], hi[0]):
            for y in (lo[1], hi[1]):
                label = "calibration poses' bounds (eq. 19)" if (x, y) == (lo[0], lo[1]) else None
                ax.plot([x, x], [y, y], [lo[2], hi[2]], "k-", lw=0.8, label=label)
        for z in (lo[2], hi[2]):
            ax.plot([lo[0], hi[0], hi[0], lo[0], lo[0]], [lo[1], lo[1], hi[1], hi[1], lo[1]], [z] * 5, "k-", lw=0.8)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_box_aspect(None, zoom=0.85)  # room for the z label, which the colorbar would otherwise cut
    ax.set_title(f"{robot.name}: static workspace boundary ({int(ws.member.sum())} of {len(ws.member)} points)")
    ax.legend(loc="upper left")
    out = Path(path)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out
