"""Certified anchor calibration (Sandretto et al.): codac q-intersection meaning, rigour of the thick
spheres, outlier rejection over random datasets, identifiability, the pulley bound of IRMA4U, the NWLS
comparison and the laser-tracker dataset generator."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from calib.certify import CertifyConfig, certify_anchors, n_allowed_failures
from calib.certify._bounds import cable_shells
from calib.certify._pulley import pulley_length_bound, workspace_region
from calib.certify._rounding import codac, codac_rounding
from calib.certify._solver import solve_cable
from calib.kinematics import inverse_kinematics, rotation
from calib.lasertracker import (
    MeasurementFileError,
    model_lengths,
    read_measurements_csv,
    simulate_tracker_dataset,
    write_measurements_csv,
)
from calib.robot import load_robot

PAPER_DL = (-0.0006, 0.0037)


@pytest.fixture(scope="module")
def reelax8():
    return load_robot("reelax8")


@pytest.fixture(scope="module")
def irma4u():
    return load_robot("irma4u")


# --- codac's q-intersection integer -------------------------------------------------------------------


def test_codac_version_is_the_pinned_one():
    assert codac.version.__version__ == "2.1.2"


def test_codac_qinter_integer_counts_the_boxes_allowed_to_fail():
    """Two boxes agree on [0.5, 1], a third is far away. In Codac 2 the integer is the number of boxes that may
    be dropped: 1 gives the agreement of the other two. Under the IBEX/paper meaning (number that must hold),
    1 would give the hull of all three boxes, [0, 6]."""
    with codac_rounding():
        boxes = [codac.IntervalVector([[0, 1]]), codac.IntervalVector([[0.5, 2]]), codac.IntervalVector([[5, 6]])]
        assert codac.qinter(1, boxes) == codac.IntervalVector([[0.5, 1]])
        assert codac.qinter(0, boxes).is_empty()
        assert codac.qinter(2, boxes) == codac.IntervalVector([[0, 6]])
        ctcs = [codac.CtcWrapper(b) for b in boxes]
        got = codac.CtcQInter(1, ctcs).contract(codac.IntervalVector([[-10, 10]]))
        assert got == codac.IntervalVector([[0.5, 1]])


def test_importing_the_package_leaves_round_to_nearest_and_codac_rounds_outward():
    a, b = np.float64(1.0), np.float64(3.0)
    assert float(a / b) == 0.3333333333333333  # round to nearest outside the codac computations
    with codac_rounding():
        third = codac.Interval(1.0) / codac.Interval(3.0)
    assert third.lb() < third.ub()  # outward rounding inside
    assert float(a / b) == 0.3333333333333333


def test_fraction_q_maps_to_the_number_allowed_to_fail():
    assert n_allowed_failures(0.75, 42) == 10  # 32 of 42 must hold
    assert n_allowed_failures(1.0, 42) == 0
    assert n_allowed_failures(0.5, 4) == 2
    result = certify_anchors(load_robot("reelax8"), *_tiny_dataset(), CertifyConfig(q=0.75), cables=[0])
    assert result.required == 32


def _tiny_dataset():
    ds = simulate_tracker_dataset(load_robot("reelax8"), 42, seed=11)
    return ds.poses, ds.lengths


# --- thick spheres -------------------------------------------------------------------------------------


def test_shells_without_tolerances_have_the_model_error_as_thickness(reelax8):
    ds = simulate_tracker_dataset(reelax8, 20, seed=1, pose_tol=0.0, angle_tol=0.0)
    box = np.stack([reelax8.d[2] - 0.01, reelax8.d[2] + 0.01], 1)
    sh = cable_shells(reelax8, 2, ds.poses, ds.lengths[:, 2], box[:, 0], box[:, 1], pose_tol=0.0, angle_tol=0.0,
                      platform_tol=0.0, model_error=PAPER_DL)
    np.testing.assert_allclose(sh.thickness, PAPER_DL[1] - PAPER_DL[0], atol=1e-8)
    dist = np.linalg.norm(sh.centres - ds.true_anchors[2], axis=1)
    assert np.all((sh.r_lo <= dist) & (dist <= sh.r_hi))


def test_shells_hold_at_the_worst_corners_of_the_tolerances(reelax8):
    """For anchors anywhere in the initial box and true poses anywhere in the tolerance box of the measured one
    (its 64 corners and random points), |B0 - a| - |B - a| stays within the radius widening of the shell, and
    the corners come close to it (the bound is not loose)."""
    rng = np.random.default_rng(5)
    pose_tol, angle_tol, bt, big = 0.001, 0.01, 0.001, 10.0
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=6)))
    scale = np.array([pose_tol] * 3 + [angle_tol] * 3)
    for cable in (0, 3, 6):
        measured = simulate_tracker_dataset(reelax8, 6, seed=cable).poses
        box = np.stack([reelax8.d[cable] - 0.01, reelax8.d[cable] + 0.01], 1)
        anchors = np.concatenate([rng.uniform(box[:, 0], box[:, 1], (30, 3)),
                                  np.array(list(itertools.product(*box)))])
        for rot_bound in ("centred", "naive"):
            sh = cable_shells(reelax8, cable, measured, np.full(len(measured), big), box[:, 0], box[:, 1],
                              pose_tol=pose_tol, angle_tol=angle_tol, platform_tol=bt, model_error=(0.0, 0.0),
                              rotation_bound=rot_bound)
            worst = 0.0
            for k, z in enumerate(measured):
                true = z + np.concatenate([corners, rng.uniform(-1, 1, (200, 6))]) * scale
                b = reelax8.a_local[cable] + rng.choice([-bt, bt], (len(true), 3))
                pts = true[:, :3] + np.einsum("kab,kb->ka", rotation(true[:, 3:], reelax8.orientation), b)
                dist = np.linalg.norm(pts[:, None, :] - anchors[None], axis=-1)
                gap = np.linalg.norm(sh.centres[k] - anchors, axis=1)[None, :] - dist
                assert np.all(gap >= sh.r_lo[k] - big) and np.all(gap <= sh.r_hi[k] - big)
                worst = max(worst, np.abs(gap).max() / (sh.r_hi[k] - big))
            if rot_bound == "centred":
                assert worst > 0.6, worst


def test_centred_rotation_bound_is_tighter_than_the_naive_interval_product(reelax8):
    """The orientation part of the shell thickness (no position or model error): the naive product of the
    three interval rotations is wider for every measurement, and much wider at larger Euler angles."""
    ratios = {}
    for angle_range in (0.1, 0.5):
        ds = simulate_tracker_dataset(reelax8, 42, seed=2, angle_range=angle_range)
        r = []
        for cable in range(reelax8.n):
            box = np.stack([reelax8.d[cable] - 0.01, reelax8.d[cable] + 0.01], 1)
            kw = dict(pose_tol=0.0, angle_tol=0.01, platform_tol=0.0, model_error=(0.0, 0.0))
            centred = cable_shells(reelax8, cable, ds.poses, ds.lengths[:, cable], box[:, 0], box[:, 1], **kw)
            naive = cable_shells(reelax8, cable, ds.poses, ds.lengths[:, cable], box[:, 0], box[:, 1],
                                 rotation_bound="naive", **kw)
            assert np.all(centred.thickness < naive.thickness)
            r.append(naive.thickness / centred.thickness)
        ratios[angle_range] = np.mean(r)
    assert ratios[0.1] > 1.05 and ratios[0.5] > 1.3, ratios


# --- the certified programme ---------------------------------------------------------------------------


def test_fifty_datasets_with_outliers_boxes_contain_truth_and_outliers_are_named(reelax8):
    """Done-when 1: 50 random 42-measurement datasets, 1 to 8 outlier poses (up to 20 %, lengths off by 5 to
    20 cm), q = 75 %: every box contains the true anchor, the outliers named are exactly the outlier poses;
    the plain intersection (q = 100 %) is empty for every cable."""
    for seed in range(50):
        n_out = 1 + seed % 8
        ds = simulate_tracker_dataset(reelax8, 42, seed=1000 + seed, outliers=n_out / 42)
        assert len(ds.outliers) == n_out
        res = certify_anchors(reelax8, ds.poses, ds.lengths, CertifyConfig(q=0.75))
        for a in res.anchors:
            assert a.contains(ds.true_anchors[a.cable - 1]), (seed, a.cable, a.box, ds.true_anchors[a.cable - 1])
            assert a.outliers == ds.outliers, (seed, a.cable)
        plain = certify_anchors(reelax8, ds.poses, ds.lengths, CertifyConfig(q=1.0))
        assert all(a.box is None for a in plain.anchors), seed


def test_solution_set_is_the_same_with_and_without_the_paving_on_a_degenerate_case():
    """Three exact spheres through the point (1, 2, 3) with tiny thickness: the paving narrows the
    contracted box to the point (within the resolution) and keeps it."""
    from calib.certify._bounds import Shells

    truth = np.array([1.0, 2.0, 3.0])
    centres = truth + np.array([[3.0, 0, 0], [0, 3.0, 0], [0, 0, 3.0], [2.0, 2.0, 0]])
    r = np.linalg.norm(centres - truth, axis=1)
    sh = Shells(centres, r - 1e-4, r + 1e-4)
    box = np.stack([truth - 0.05, truth + 0.05], 1)
    sol = solve_cable(sh, box, 0, resolution=1e-4)
    assert np.all(sol.box[:, 0] <= truth) and np.all(truth <= sol.box[:, 1])
    assert np.all(sol.box[:, 1] - sol.box[:, 0] < 1e-3)
    assert sol.outliers == ()


def test_boxes_shrink_with_spread_poses_and_clustered_poses_leave_dimensions_uncontracted(reelax8):
    """Done-when 2, at the paper's tolerances with a rough +-5 cm initial guess, q = 100 %, no outliers."""
    cfg = CertifyConfig(q=1.0, anchor_tol=0.05)
    ds = simulate_tracker_dataset(reelax8, 42, seed=3)
    means, flat = [], []
    for n in (6, 12, 24, 42):
        res = certify_anchors(reelax8, ds.poses[:n], ds.lengths[:n], cfg)
        assert all(a.contains(ds.true_anchors[a.cable - 1]) for a in res.anchors)
        means.append(np.mean([a.widths for a in res.anchors]))
        flat.append(sum(len(a.uncontracted) for a in res.anchors))
    assert all(later < earlier for earlier, later in zip(means, means[1:], strict=False)), means
    assert means[-1] < 0.6 * means[0]
    assert flat[-1] == 0 and flat[0] > 0, flat

    clustered = simulate_tracker_dataset(reelax8, 42, seed=3, clustered=True, cluster_size=0.1)
    span = np.ptp(clustered.true_poses[:, :3], axis=0)
    assert np.all(span <= 0.1)
    res = certify_anchors(reelax8, clustered.poses, clustered.lengths, cfg)
    assert all(a.contains(clustered.true_anchors[a.cable - 1]) for a in res.anchors)
    n_flat = sum(len(a.uncontracted) for a in res.anchors)
    assert n_flat >= 12, n_flat
    assert np.mean([a.widths for a in res.anchors]) > 1.8 * means[-1]


def test_empty_enclosure_when_too_few_measurements_agree(reelax8):
    ds = simulate_tracker_dataset(reelax8, 20, seed=4, outliers=0.5)
    res = certify_anchors(reelax8, ds.poses, ds.lengths, CertifyConfig(q=0.9), cables=[0, 1])
    assert [a.box for a in res.anchors] == [None, None]
    assert res.to_json()["anchors"][0]["box"] is None


def test_bad_configuration_and_shapes_are_rejected(reelax8):
    poses, lengths = _tiny_dataset()
    with pytest.raises(ValueError, match="q = 0"):
        certify_anchors(reelax8, poses, lengths, CertifyConfig(q=0.0))
    with pytest.raises(ValueError, match="model_error"):
        certify_anchors(reelax8, poses, lengths, CertifyConfig(model_error=(0.01, 0.0)))
    with pytest.raises(ValueError, match="expected"):
        certify_anchors(reelax8, poses, lengths[:, :4])


# --- NWLS beside the boxes -----------------------------------------------------------------------------


def test_nwls_is_inside_without_outliers_and_pulled_out_by_them(reelax8):
    clean = simulate_tracker_dataset(reelax8, 42, seed=6)
    res = certify_anchors(reelax8, clean.poses, clean.lengths, CertifyConfig(q=1.0), cables=[0, 4])
    for a in res.anchors:
        assert a.nwls_inside
        assert np.linalg.norm(a.nwls - clean.true_anchors[a.cable - 1]) < 0.006
    dirty = simulate_tracker_dataset(reelax8, 42, seed=6, outliers=0.2)
    plain = certify_anchors(reelax8, dirty.poses, dirty.lengths, CertifyConfig(q=0.75), cables=[0, 4])
    robust = certify_anchors(reelax8, dirty.poses, dirty.lengths, CertifyConfig(q=0.75, nwls_loss="cauchy"),
                             cables=[0, 4])
    for a, b in zip(plain.anchors, robust.anchors, strict=True):
        truth = dirty.true_anchors[a.cable - 1]
        assert not a.nwls_inside
        assert np.linalg.norm(b.nwls - truth) < 0.5 * np.linalg.norm(a.nwls - truth)


# --- IRMA4U: pulley entry points -----------------------------------------------------------------------


def test_pulley_bound_encloses_random_poses_of_the_workspace(irma4u):
    bound = pulley_length_bound(irma4u, *workspace_region(irma4u, 0.1))
    rng = np.random.default_rng(7)
    lo, hi = irma4u.workspace_lower, irma4u.workspace_upper
    poses = np.concatenate([rng.uniform(lo, hi, (4000, 3)), rng.uniform(-0.1, 0.1, (4000, 3))], 1)
    kin = inverse_kinematics(irma4u, poses)
    diff = np.linalg.norm(kin.q, axis=-1) - kin.lengths
    assert np.all(diff >= bound.lo) and np.all(diff <= bound.hi)
    # the wrapped cable is longer than the straight segment by 2 to 7 cm on this prototype
    assert -0.08 < bound.interval[0] < -0.05 and -0.035 < bound.interval[1] < -0.015


def test_irma4u_pulley_entry_points_are_enclosed(irma4u):
    ds = simulate_tracker_dataset(irma4u, 42, seed=8, outliers=0.1)
    res = certify_anchors(irma4u, ds.poses, ds.lengths, CertifyConfig(q=0.75, anchor_tol=0.03))
    lo, hi = res.pulley_error
    assert res.model_error == pytest.approx((PAPER_DL[0] + lo, PAPER_DL[1] + hi))
    err = np.abs(model_lengths(irma4u, ds.true_anchors, ds.true_poses) - ds.lengths)
    for a in res.anchors:
        assert a.contains(ds.true_anchors[a.cable - 1])
        # shells are ~7 cm thick here (pulley bound): every pose named is an outlier, and every length off by
        # more than 10 cm is named
        assert set(a.outliers) <= set(ds.outliers)
        assert {k for k in ds.outliers if err[k, a.cable - 1] > 0.10} <= set(a.outliers)


# --- dataset generator and file format -----------------------------------------------------------------


def test_generator_respects_frame_tolerances_model_error_and_outliers(reelax8):
    ds = simulate_tracker_dataset(reelax8, 42, seed=9, outliers=0.2, anchor_offset=0.004)
    assert len(ds.outliers) == 8
    assert np.all(np.abs(ds.true_anchors - reelax8.d) <= 0.004)
    assert np.all(np.abs(ds.poses[:, :3] - ds.true_poses[:, :3]) <= 0.001)
    assert np.all(np.abs(ds.poses[:, 3:] - ds.true_poses[:, 3:]) <= 0.01)
    dist = model_lengths(reelax8, ds.true_anchors, ds.true_poses)
    err = dist - ds.lengths
    inliers = np.setdiff1d(np.arange(42), ds.outliers)
    assert np.all((err[inliers] >= PAPER_DL[0]) & (err[inliers] <= PAPER_DL[1]))
    off = np.abs(err[list(ds.outliers)])
    assert np.all((off >= 0.05 - 0.0037) & (off <= 0.2 + 0.0037))
    # platform points inside the convex hull of the anchors: below the upper and above the lower ones
    rot = rotation(ds.true_poses[:, 3:], reelax8.orientation)
    pts = ds.true_poses[:, None, :3] + np.einsum("kab,nb->kna", rot, reelax8.a_local)
    assert pts[..., 2].min() > reelax8.d[:, 2].min() and pts[..., 2].max() < reelax8.d[:, 2].max()
    spread = np.ptp(ds.true_poses[:, :3], axis=0)
    assert np.all(spread > 0.8)


def test_csv_round_trip_and_errors_name_line_and_field(tmp_path, reelax8):
    ds = simulate_tracker_dataset(reelax8, 5, seed=10)
    f = tmp_path / "m.csv"
    write_measurements_csv(f, ds.poses, ds.lengths)
    poses, lengths = read_measurements_csv(f, 8)
    np.testing.assert_allclose(poses, ds.poses, atol=1e-11)
    np.testing.assert_allclose(lengths, ds.lengths, atol=1e-11)
    rows = f.read_text().splitlines()
    rows[3] = rows[3].replace(rows[3].split(",")[7], "abc", 1)
    f.write_text("\n".join(rows) + "\n")
    with pytest.raises(MeasurementFileError, match=r"m\.csv: line 4, field 'l_2' = 'abc'"):
        read_measurements_csv(f, 8)
    with pytest.raises(MeasurementFileError, match="line 2 has 14 fields, expected 10"):
        read_measurements_csv(f, 4)
