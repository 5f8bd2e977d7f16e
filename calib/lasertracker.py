"""Simulated laser-tracker calibration datasets and the MEASUREMENTS.csv format of `cdpr certify anchors`.

A dataset is a set of platform poses measured externally (a laser tracker: position +-pose_tol m per axis,
orientation +-angle_tol rad per Euler angle) together with the cable lengths at those poses. The true
lengths come from the robot's own length model (straight cables, or the swivel-pulley model of
calib.kinematics for robots with pulleys) evaluated with the *true* fixed points, which differ from the
nominal ones by up to ``anchor_offset`` per axis. The cable model error follows the Sandretto paper
(eq. 1-2): the model distance ||B - A|| lies in L + [dL], so a measured length is L = distance - e with e
drawn uniformly in [dL]. Outlier poses have every cable length off by 5 to 20 cm (random sign).

CSV format (../shared/spec/cli.md): one line per pose, ``x,y,z,roll,pitch,yaw,l_1..l_m`` (m, rad); an
optional header line and ``#`` comment lines are allowed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.errors import CdprError
from calib.kinematics import inverse_kinematics, rotation
from calib.robot import Robot

POSE_FIELDS = ("x", "y", "z", "roll", "pitch", "yaw")


class MeasurementFileError(CdprError, ValueError):
    """A MEASUREMENTS.csv that cannot be used; the message names the file, line, field and value."""


@dataclass(frozen=True)
class TrackerDataset:
    """A simulated laser-tracker dataset with its ground truth.

    poses: (k, 6) measured poses (m, rad); lengths: (k, n) cable lengths (m); true_poses: (k, 6);
    true_anchors: (n, 3) true fixed points (m); outliers: indices of the outlier poses (0-based);
    model_errors: (k, n) the cable model error e drawn for each length, distance - length (m).
    """

    robot: str
    poses: np.ndarray
    lengths: np.ndarray
    true_poses: np.ndarray
    true_anchors: np.ndarray
    outliers: tuple[int, ...]
    model_errors: np.ndarray


def _inside_frame(robot: Robot, points: np.ndarray) -> np.ndarray:
    """(k,) True where all of a pose's platform points (k, n, 3) lie inside the frame spanned by the anchors.

    A frame whose anchors span 3-D (ReelAx8) is their convex hull; a flat one (IRMA4U: all pulleys at one
    height) is the prism below the horizontal hull of the anchors.
    """
    from scipy.spatial import Delaunay  # here: scipy.spatial costs every cdpr command ~0.25 s at start-up

    d = np.asarray(robot.d)
    centred = d - d.mean(axis=0)
    if np.linalg.matrix_rank(centred, tol=1e-6) == 3:
        hull = Delaunay(d)
        inside = hull.find_simplex(points.reshape(-1, 3)) >= 0
    else:
        hull = Delaunay(d[:, :2])
        inside = (hull.find_simplex(points[..., :2].reshape(-1, 2)) >= 0) & (
            points[..., 2].reshape(-1) < d[:, 2].min()
        )
    return inside.reshape(points.shape[:2]).all(axis=1)


def model_lengths(robot: Robot, anchors: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Cable lengths (k, n) at poses (k, 6) with fixed points ``anchors`` (n, 3): the robot's length model, m."""
    if robot.has_pulleys:
        return inverse_kinematics(robot.replace(d=anchors), poses).lengths
    rot = rotation(poses[:, 3:], robot.orientation)
    pts = poses[:, None, :3] + np.einsum("kab,nb->kna", rot, robot.a_local)
    return np.linalg.norm(pts - anchors[None], axis=-1)


def _feasible_poses(robot: Robot, n_poses: int, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray,
                    angle_range: float, tries: int = 50) -> np.ndarray | None:
    """Up to n_poses poses uniform in [lo, hi] x [-angle_range, angle_range]^3 keeping the platform inside the
    frame, or None when fewer are found after ``tries`` batches."""
    out = np.zeros((0, 6))
    for _ in range(tries):
        batch = np.concatenate(
            [rng.uniform(lo, hi, (4 * n_poses, 3)), rng.uniform(-angle_range, angle_range, (4 * n_poses, 3))], 1
        )
        rot = rotation(batch[:, 3:], robot.orientation)
        pts = batch[:, None, :3] + np.einsum("kab,nb->kna", rot, robot.a_local)
        out = np.concatenate([out, batch[_inside_frame(robot, pts)]])
        if len(out) >= n_poses:
            return out[:n_poses]
    return None


def _draw_true_poses(robot: Robot, n_poses: int, rng: np.random.Generator, clustered: bool,
                     cluster_size: float, angle_range: float) -> np.ndarray:
    lo, hi = np.asarray(robot.workspace_lower), np.asarray(robot.workspace_upper)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"robot '{robot.name}': field 'workspace' is missing; cannot draw poses.")
    for _ in range(20):
        if clustered:  # a cube of side cluster_size about a feasible pose, kept inside the workspace
            seed_pose = _feasible_poses(robot, 1, rng, lo, hi, angle_range)
            if seed_pose is None:
                break
            half = np.minimum(cluster_size / 2.0, (hi - lo) / 2.0)
            centre = np.clip(seed_pose[0, :3], lo + half, hi - half)
            poses = _feasible_poses(robot, n_poses, rng, centre - half, centre + half, angle_range)
        else:
            poses = _feasible_poses(robot, n_poses, rng, lo, hi, angle_range)
        if poses is not None:
            return poses
    raise ValueError(f"robot '{robot.name}': no pose of the workspace keeps the platform inside the frame.")


def simulate_tracker_dataset(
    robot: Robot,
    n_poses: int,
    *,
    seed: int | None = None,
    outliers: float = 0.0,
    clustered: bool = False,
    cluster_size: float = 0.1,
    angle_range: float = 0.1,
    pose_tol: float = 0.001,
    angle_tol: float = 0.01,
    model_error: tuple[float, float] = (-0.0006, 0.0037),
    anchor_offset: float = 0.005,
    outlier_range: tuple[float, float] = (0.05, 0.20),
) -> TrackerDataset:
    """Draw a laser-tracker dataset of ``n_poses`` poses.

    Poses are uniform over the robot's workspace (positions, m) with Euler angles uniform in +-angle_range
    (rad), keeping every platform point inside the frame; ``clustered`` confines the positions to a cube
    of side ``cluster_size`` (m) at a random place of the workspace. Measurement errors are uniform inside
    +-pose_tol (m) and +-angle_tol (rad); the true fixed points are the nominal ones moved by up to
    +-anchor_offset (m) per axis; ``outliers`` is the fraction of outlier poses (rounded down).
    """
    if n_poses < 1:
        raise ValueError(f"n_poses = {n_poses} must be at least 1.")
    if not 0.0 <= outliers < 1.0:
        raise ValueError(f"outliers = {outliers} must be a fraction in [0, 1).")
    if model_error[0] > model_error[1]:
        raise ValueError(f"model_error = {model_error} must be (lo, hi) with lo <= hi.")
    rng = np.random.default_rng(seed)
    true_anchors = np.asarray(robot.d) + rng.uniform(-anchor_offset, anchor_offset, robot.d.shape)
    true_poses = _draw_true_poses(robot, n_poses, rng, clustered, cluster_size, angle_range)
    model_errors = rng.uniform(model_error[0], model_error[1], (n_poses, robot.n))
    lengths = model_lengths(robot, true_anchors, true_poses) - model_errors
    n_out = int(math.floor(outliers * n_poses + 1e-9))
    bad = np.sort(rng.choice(n_poses, size=n_out, replace=False)) if n_out else np.zeros(0, int)
    if n_out:
        size = rng.uniform(outlier_range[0], outlier_range[1], (n_out, robot.n))
        sign = rng.choice([-1.0, 1.0], size=(n_out, robot.n))
        lengths[bad] += sign * size
    measured = true_poses.copy()
    measured[:, :3] += rng.uniform(-pose_tol, pose_tol, (n_poses, 3))
    measured[:, 3:] += rng.uniform(-angle_tol, angle_tol, (n_poses, 3))
    return TrackerDataset(robot.name, measured, lengths, true_poses, true_anchors, tuple(int(i) for i in bad),
                          model_errors)


def write_measurements_csv(path: str | Path, poses: np.ndarray, lengths: np.ndarray) -> None:
    """Write MEASUREMENTS.csv: a header, then ``x,y,z,roll,pitch,yaw,l_1..l_m`` per pose (m, rad)."""
    poses, lengths = np.atleast_2d(poses), np.atleast_2d(lengths)
    header = ",".join(POSE_FIELDS + tuple(f"l_{i + 1}" for i in range(lengths.shape[1])))
    rows = [",".join(f"{v:.12g}" for v in row) for row in np.concatenate([poses, lengths], axis=1)]
    Path(path).write_text("\n".join([header, *rows]) + "\n")


def read_measurements_csv(path: str | Path, n_cables: int) -> tuple[np.ndarray, np.ndarray]:
    """Read MEASUREMENTS.csv for a robot with ``n_cables`` cables: poses (k, 6) and lengths (k, n), SI units.

    Raises MeasurementFileError naming the file, line, field and value on bad input.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise MeasurementFileError(f"{path}: cannot be read ({exc.strerror}).") from exc
    names = POSE_FIELDS + tuple(f"l_{i + 1}" for i in range(n_cables))
    rows: list[list[float]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = [f.strip() for f in stripped.split(",")]
        if not rows and fields and fields[0].lower() == "x":
            continue  # header line
        if len(fields) != len(names):
            raise MeasurementFileError(
                f"{path}: line {lineno} has {len(fields)} fields, expected {len(names)} "
                f"(x,y,z,roll,pitch,yaw and {n_cables} cable lengths)."
            )
        values = []
        for name, field in zip(names, fields, strict=True):
            try:
                v = float(field)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise MeasurementFileError(
                    f"{path}: line {lineno}, field '{name}' = {field!r} is not a finite number."
                )
            if name.startswith("l_") and v <= 0:
                raise MeasurementFileError(
                    f"{path}: line {lineno}, field '{name}' = {field!r} must be a positive length."
                )
            values.append(v)
        rows.append(values)
    if not rows:
        raise MeasurementFileError(f"{path}: contains no measurement line.")
    data = np.array(rows)
    return data[:, :6], data[:, 6:]
