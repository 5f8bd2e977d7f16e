"""Benchmark: certified anchor calibration (issue 8).

Target: <= 1 s per cable for 42 measurements. Also prints the widths obtained at the paper's tolerances beside
the widths of the paper's Table 2, the effect of the tolerances on them, the centred against the naive
rotation bound, and the pulley bound of IRMA4U. Run: python benchmarks/bench_certify.py [--datasets N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from calib.certify import CertifyConfig, certify_anchors
from calib.certify._pulley import pulley_length_bound, workspace_region
from calib.lasertracker import simulate_tracker_dataset
from calib.robot import load_robot

# Widths (mm) of the paper's Table 2 boxes, x, y, z per anchor
PAPER_WIDTHS = np.array([[0, 2, 1], [20, 20, 20], [20, 20, 20], [20, 12, 20],
                         [0, 3, 1], [20, 20, 20], [1, 0, 0], [17, 2, 5]], float)


def per_cable_times(robot, datasets: int, outliers: float, config: CertifyConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per-cable wall times (s) and widths (m) over random 42-measurement datasets."""
    times, widths = [], []
    for seed in range(datasets):
        ds = simulate_tracker_dataset(robot, 42, seed=500 + seed, outliers=outliers)
        res = certify_anchors(robot, ds.poses, ds.lengths, config)
        for a in res.anchors:
            times.append(a.seconds)
            widths.append(a.widths if a.box is not None else np.full(3, np.nan))
            assert a.contains(ds.true_anchors[a.cable - 1]), (seed, a.cable)
    return np.array(times), np.array(widths)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--datasets", type=int, default=10)
    args = ap.parse_args()
    reelax8, irma4u = load_robot("reelax8"), load_robot("irma4u")
    paper = CertifyConfig(q=0.75)

    print("== time per cable, 42 measurements, q = 0.75, paper tolerances (target <= 1 s) ==")
    for name, robot, out in (("reelax8, 20% outliers", reelax8, 0.2), ("reelax8, no outliers", reelax8, 0.0),
                             ("irma4u, 10% outliers", irma4u, 0.1)):
        t0 = time.perf_counter()
        times, _ = per_cable_times(robot, args.datasets, out, paper)
        print(f"{name:24s} mean {times.mean():.3f} s  median {np.median(times):.3f} s  max {times.max():.3f} s "
              f"({len(times)} cables, {time.perf_counter() - t0:.1f} s in all)")

    print("\n== ReelAx8 widths (mm), mean over datasets, x y z per anchor ==")
    settings = [
        ("paper tolerances, q=0.75, 20% outliers", paper, 0.2),
        ("paper tolerances, q=1, no outliers", CertifyConfig(q=1.0), 0.0),
        ("angle tol 1 mrad, q=1, no outliers", CertifyConfig(q=1.0, angle_tol=0.001), 0.0),
        ("pose 0.1 mm, 1 mrad, q=1, no outliers", CertifyConfig(q=1.0, pose_tol=1e-4, angle_tol=0.001), 0.0),
        ("exact poses ([dL] only), q=1", CertifyConfig(q=1.0, pose_tol=0.0, angle_tol=0.0), 0.0),
        ("naive rotation, paper tol, q=1", CertifyConfig(q=1.0, rotation_bound="naive"), 0.0),
        ("paper tol, +-5 cm start, q=1", CertifyConfig(q=1.0, anchor_tol=0.05), 0.0),
        ("naive rotation, +-5 cm start, q=1", CertifyConfig(q=1.0, anchor_tol=0.05, rotation_bound="naive"), 0.0),
    ]
    print(f"{'Table 2 of the paper':40s}", " ".join(f"{w[0]:3.0f}/{w[1]:3.0f}/{w[2]:3.0f}" for w in PAPER_WIDTHS))
    for label, cfg, out in settings:
        widths, fixp = [], []
        for seed in range(args.datasets):
            ds = simulate_tracker_dataset(reelax8, 42, seed=700 + seed, outliers=out,
                                          pose_tol=cfg.pose_tol, angle_tol=cfg.angle_tol)
            res = certify_anchors(reelax8, ds.poses, ds.lengths, cfg)
            widths.append([a.widths for a in res.anchors])
            fixp.append([a.contracted[:, 1] - a.contracted[:, 0] for a in res.anchors])
        w = np.mean(widths, axis=0) * 1e3
        print(f"{label:40s}", " ".join(f"{x[0]:3.0f}/{x[1]:3.0f}/{x[2]:3.0f}" for x in w),
              f" mean {w.mean():.1f} (FixP(QInter) alone {np.mean(fixp) * 1e3:.1f})")

    bound = pulley_length_bound(irma4u, *workspace_region(irma4u, 0.1))
    print(f"\n== IRMA4U pulley effect |B - d| - l over the workspace (Euler angles +-0.1 rad) ==\n"
          f"[{bound.interval[0] * 1e3:.1f}, {bound.interval[1] * 1e3:.1f}] mm including a {bound.margin * 1e3:.1f} mm "
          f"sampling margin; max |.| = {max(abs(bound.interval[0]), abs(bound.interval[1])) * 1e3:.1f} mm")


if __name__ == "__main__":
    main()
