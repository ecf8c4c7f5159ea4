"""Hue-assisted ICP (men spec 5) against the validation targets V11-V16 of spec 12, plus the box
constraint, the Hessian uncertainty and the pipeline's pair refinement."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.colour_scenes import (
    angle_deg,
    blob,
    building,
    gradient_hue,
    random_rotation,
    rotation_xyz,
    segment_hue,
)
from scipy.spatial import cKDTree

from forestmap_assets.core.registration.hicp import (
    Embedding,
    default_radius,
    hicp,
    icp,
    pose4_to_matrix,
    rigid_transform,
)
from forestmap_assets.core.registration.icp_uncertainty import (
    icp_covariance,
    merged_normal_quality,
    pose_sd,
)

D6_T = np.array([1.014969, 2.00582, 0.706715])  # Table 5.2's translation


def test_v11_svd_recovers_exact_correspondences_with_reflection_guard():
    rng = np.random.default_rng(0)
    for _ in range(5):
        r, t = random_rotation(rng), rng.normal(0, 5, 3)
        d = rng.normal(0, 3, (50, 3))
        r_hat, t_hat = rigid_transform(d, d @ r.T + t)
        np.testing.assert_allclose(r_hat, r, atol=1e-9)
        np.testing.assert_allclose(t_hat, t, atol=1e-9)
    # planar set: the unguarded SVD may return a reflection; the guard keeps det R = +1 exactly
    d = np.column_stack([rng.normal(0, 3, (40, 2)), np.zeros(40)])
    r, t = random_rotation(rng), rng.normal(0, 5, 3)
    r_hat, t_hat = rigid_transform(d, d @ r.T + t)
    assert np.linalg.det(r_hat) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(r_hat, r, atol=1e-9)
    np.testing.assert_allclose(t_hat, t, atol=1e-9)
    # the thesis's printed convention (H = sum m' d'^T, R = V U^T) returns the inverse (App. A)
    d = rng.normal(0, 3, (50, 3))
    m = d @ r.T
    u, _, vt = np.linalg.svd((m - m.mean(0)).T @ (d - d.mean(0)))
    np.testing.assert_allclose(vt.T @ u.T, r.T, atol=1e-9)
    # 4-DoF: rotation about z only
    r4, t4 = pose4_to_matrix((1.0, -2.0, 0.3, 37.0))
    r_hat, t_hat = rigid_transform(d, d @ r4.T + t4, dof=4)
    np.testing.assert_allclose(r_hat, r4, atol=1e-12)
    np.testing.assert_allclose(t_hat, t4, atol=1e-12)
    with pytest.raises(ValueError, match="dof"):
        rigid_transform(d, d, dof=5)


def test_v12_known_6dof_transform_all_weights_same_result_fewer_iterations():
    model = building(5000, seed=0)
    hue = gradient_hue(model, axis=0)
    r_true = rotation_xyz(5, 5, 5)
    data = (model - D6_T) @ r_true  # model = R data + t
    diag = np.linalg.norm(model.max(0) - model.min(0))
    iterations = {}
    for w in (0.0, 0.05, 0.2, 1.0, 10.0, 100.0):
        res = hicp(model, data, hue, hue, weight=w, radius=0.2)
        assert res.converged, (w, res.reason)
        assert angle_deg(res.rotation, r_true) < 0.01
        assert np.linalg.norm(res.translation - D6_T) < 1e-3 * diag
        iterations[w] = res.iterations
        # V16: S reaches 0 and N stabilises no later than S
        hist = res.history
        assert hist["changed"].iloc[-1] == 0
        n_stable = hist.index[hist["n_pairs"].diff().abs().fillna(1) == 0][0]
        s_zero = hist.index[hist["changed"] == 0][0]
        assert n_stable <= s_zero
    moved = data @ res.rotation.T + res.translation
    assert merged_normal_quality(model, moved, 1.0) == pytest.approx(1.0, abs=1e-3)
    # a misregistered copy disturbs the merged surfaces: the score drops
    assert merged_normal_quality(model, data, 1.0) < 0.99
    counts = [iterations[w] for w in (0.05, 0.2, 1.0, 10.0, 100.0)]
    assert counts[0] <= iterations[0.0]
    assert all(a >= b for a, b in zip(counts, counts[1:], strict=False)), iterations
    assert counts[-1] < iterations[0.0]


def test_v13_weight_to_zero_reproduces_plain_icp():
    model = building(3000, seed=1)
    hue = gradient_hue(model, axis=1)
    r_true = rotation_xyz(3, -2, 6)
    data = (model - [0.4, -0.3, 0.2]) @ r_true
    base = icp(model, data, radius=0.15)
    tiny = hicp(model, data, hue, hue, weight=1e-12, radius=0.15)
    assert tiny.iterations == base.iterations
    np.testing.assert_array_equal(tiny.partner, base.partner)
    np.testing.assert_allclose(tiny.matrix, base.matrix, atol=1e-12)
    np.testing.assert_allclose(tiny.history[["error", "n_pairs", "changed"]].to_numpy(),
                               base.history[["error", "n_pairs", "changed"]].to_numpy(), atol=1e-12)
    # w = 0 drops the hue dimension: a 3-D tree, no hue needed
    assert base.embedding.weight == 0.0 and base.embedding.embed(model[:2]).shape == (2, 3)
    with pytest.raises(ValueError, match="hue"):
        hicp(model, data, None, None, weight=0.2)


def test_v14_degenerate_plane_only_hicp_recovers_in_plane_shift():
    """Two overlapping views of one plane that differ by an in-plane shift of 0.3 m; hue is a
    gradient along x (a property of the surface point). The strip is long in y, so with the
    isotropic shared scale the hue changes by more than 1/w per normalised unit along x."""
    spacing = 0.05
    gx, gy = np.arange(0, 1.5 + 1e-9, spacing), np.arange(0, 20, 0.1)
    xx, yy = np.meshgrid(gx, gy)
    model = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    h_model = model[:, 0] / 1.5
    shift = 0.3
    seen = model[:, 0] >= shift - 1e-9  # the data scan sees x in [0.3, 1.5] of the world
    data = model[seen] - [shift, 0, 0]
    h_data = h_model[seen]
    plain = icp(model, data, radius=0.05, scale="isotropic")
    assert abs(plain.translation[0]) < 1e-9  # 3-D ICP cannot see the shift (error = 0.3 m)
    for w in (0.1, 0.2, 1.0):
        res = hicp(model, data, h_model, h_data, weight=w, radius=0.05, scale="isotropic")
        assert abs(res.translation[0] - shift) < spacing, (w, res.translation)
        assert np.abs(res.translation[1:]).max() < spacing


@pytest.mark.parametrize("seed", [0, 1])
def test_v15_hue_pattern_ordering(seed):
    """Bunny-style object, 10-15 deg rotation plus 5 % translation, data = noisy copy."""
    model = blob(3000, seed)
    rng = np.random.default_rng(seed)
    observed = model + rng.normal(0, 0.0005, model.shape)
    r_true = rotation_xyz(8, -6, 10)
    ext = np.linalg.norm(model.max(0) - model.min(0))
    t_true = np.array([0.6, -0.5, 0.4]) / np.linalg.norm([0.6, -0.5, 0.4]) * 0.05 * ext
    data = (observed - t_true) @ r_true
    cont = gradient_hue(model, 2)
    cases = {
        "icp": (None, None, 0.0),
        "continuous": (cont, cont, 1.0),
        "seven": (segment_hue(model, 2), segment_hue(model, 2), 1.0),
        "random": (rng.random(len(model)), rng.random(len(model)), 1.0),
        "noise50": (cont, np.clip(cont * (1 + rng.uniform(-0.5, 0.5, len(model))), 0, 1), 1.0),
    }
    out = {}
    for name, (hm, hd, w) in cases.items():
        res = hicp(model, data, hm, hd, weight=w, radius=0.2)
        moved_err = (model @ res.rotation.T + res.translation) - (model @ r_true.T + t_true)
        out[name] = (res.iterations, float(np.sqrt((moved_err**2).sum(1).mean())))
    assert out["continuous"][0] <= out["seven"][0] < out["icp"][0], out
    assert out["random"][1] >= max(out["continuous"][1], out["seven"][1]), out
    assert out["noise50"][0] >= out["continuous"][0] and out["noise50"][1] >= out["continuous"][1], out


def test_embedding_shared_scale_and_default_radius():
    model = building(2000, seed=2)
    data = model[:500] + 30.0
    per_axis = Embedding.from_clouds(model, weight=0.2)
    assert np.allclose(per_axis.spatial(model).min(0), 0) and np.allclose(per_axis.spatial(model).max(0), 1)
    union = Embedding.from_clouds(model, data, weight=0.2, box="union", scale="isotropic")
    assert np.all(union.scale == union.scale[0]) and union.scale[0] > per_axis.scale.max()
    e = per_axis.embed(model, np.full(len(model), 0.5))
    assert e.shape == (len(model), 4) and np.allclose(e[:, 3], 0.1)
    r = default_radius(e, k=50)
    counts = cKDTree(e).query_ball_point(e[::50], r, return_length=True)
    assert 25 <= np.median(counts) <= 80  # about 50 candidates inside (spec 5.3 rule)


def test_box_constraint_keeps_4dof_iterates_inside():
    model = building(3000, seed=3)
    r4, t4 = pose4_to_matrix((0.5, -0.4, 0.1, 4.0))
    data = (model - t4) @ r4
    free = hicp(model, data, weight=0.0, dof=4, radius=0.15)
    np.testing.assert_allclose(free.pose4, [0.5, -0.4, 0.1, 4.0], atol=1e-6)
    box = (np.array([0.45, -0.4, 0.1, 4.0]), np.array([0.02, 0.02, 0.02, 0.5]))
    held = hicp(model, data, weight=0.0, dof=4, radius=0.15, init=box[0], box=box)
    assert held.hit_box
    assert abs(held.pose4[0] - 0.47) < 1e-9  # clamped on the box edge nearest the truth
    with pytest.raises(ValueError, match="4-DoF"):
        hicp(model, data, weight=0.0, dof=6, box=box)


def test_hessian_covariance_matches_monte_carlo_spread():
    """Independent point noise (no correlated neighbours): the predicted sd of a 4-DoF
    point-to-point ICP agrees with the spread over repeated noisy copies within a factor 1.6."""
    model = building(1500, seed=4)
    rng = np.random.default_rng(4)
    sigma = 0.01
    r4, t4 = pose4_to_matrix((0.3, 0.2, -0.1, 2.0))
    poses, preds = [], []
    for _ in range(25):
        obs = model + rng.normal(0, sigma, model.shape)
        data = (obs - t4) @ r4
        res = hicp(model + rng.normal(0, sigma, model.shape), data, weight=0.0, dof=4, radius=0.2,
                   init=(0.3, 0.2, -0.1, 2.0))
        ok = res.partner >= 0
        moved = data[ok] @ res.rotation.T + res.translation
        cov = icp_covariance(moved, model[res.partner[ok]], res.translation, dof=4, correlation_m=1e-6)
        preds.append(pose_sd(cov))
        poses.append(res.pose4)
    spread = np.std(np.array(poses), axis=0)
    pred = np.median(np.array(preds), axis=0)
    ratio = spread / pred
    assert np.all((ratio > 1 / 1.6) & (ratio < 1.6)), (spread, pred)


def _scene_views(seed=0):
    """One surface seen in two levelled scan frames (resampled + noise), with world-fixed hue."""
    world = building(20000, seed=seed)
    rng = np.random.default_rng(seed)
    hue_w = 0.1 + 0.3 * (0.5 + 0.5 * np.sin(world[:, 0] * 1.3) * np.cos(world[:, 1] * 0.9))
    a = rng.choice(len(world), 12000, replace=False)
    b = rng.choice(len(world), 12000, replace=False)
    ref_pose = (6.0, 4.0, 1.5, 0.0)
    scan_pose = (9.0, 7.0, 1.4, 30.0)
    r_ref, t_ref = pose4_to_matrix(ref_pose)
    r_s, t_s = pose4_to_matrix(scan_pose)
    ref = (world[a] - t_ref) @ r_ref + rng.normal(0, 0.003, (len(a), 3))
    scan = (world[b] - t_s) @ r_s + rng.normal(0, 0.003, (len(b), 3))
    # truth: location of the scan in the reference's levelled frame
    truth = np.array([*(r_ref.T @ (t_s - t_ref)), 30.0])
    return scan, hue_w[b], ref, hue_w[a], truth


@pytest.mark.parametrize("colour", [True, False], ids=["hicp", "point-to-plane"])
def test_refine_pair_improves_branch_and_bound_pose_within_its_box(colour):
    from forestmap_assets.core.registration.refine import refine_pair
    from forestmap_assets.params.men import RefineSettings

    scan, h_scan, ref, h_ref, truth = _scene_views()
    settings = RefineSettings(data_voxel_m=0.1, model_voxel_m=0.0, radius_m=0.3, z_band_m=(-20.0, 20.0),
                              max_range_m=50.0, min_pairs=100, guard="box")
    start = truth + np.array([0.03, -0.02, 0.015, 0.08])
    sd = np.array([0.02, 0.02, 0.01, 0.05])
    row = refine_pair(scan, ref, start, sd, h_scan if colour else None, h_ref if colour else None, settings)
    assert row["method"] == ("hicp" if colour else "point_to_plane")
    assert row["used"] == "refined", row["reason"]
    est = np.array([row[f"ref_{k}"] for k in ("dx", "dy", "dz", "dheading_deg")])
    assert np.linalg.norm(est[:3] - truth[:3]) < 0.006 and abs(est[3] - truth[3]) < 0.02
    assert row["fit_refined_m"] < row["fit_bnb_m"]
    assert 0 < row["ref_sd_x"] < 0.02
    # a box too small to reach the truth: the result stays on its edge and is not used
    row = refine_pair(scan, ref, start, sd / 20, h_scan if colour else None, h_ref if colour else None, settings)
    assert row["at_box_edge"] and row["used"] == "branch_and_bound"
    assert "box" in row["reason"]


def _registrations(scan_id, ref_id, pose, sd):
    import pandas as pd

    return pd.DataFrame([{"scan": scan_id, "reference": ref_id, "status": "accepted",
                          **dict(zip(("dx", "dy", "dz", "dheading_deg"), pose, strict=True)),
                          **dict(zip(("sd_x", "sd_y", "sd_z", "sd_heading_deg"), sd, strict=True))}])


def test_two_way_refinement_moves_as_far_as_the_points_say():
    """A coarse pose 4 cm off with a coarse sigma of 1 mm (the box would keep it): the two-way
    refinement goes to the truth, is used, and its sigma covers its error (issue 19)."""
    from forestmap_assets.core.registration.refine import refine_registrations
    from forestmap_assets.params.men import RefineSettings

    scan, _, ref, _, truth = _scene_views()
    settings = RefineSettings(data_voxel_m=0.1, model_voxel_m=0.0, z_band_m=(-20.0, 20.0), max_range_m=50.0,
                              min_pairs=100)
    start = truth + np.array([0.03, -0.025, 0.015, 0.08])
    out = refine_registrations(_registrations("a", "b", start, [0.001, 0.001, 0.001, 0.002]),
                               {"a": (scan, None), "b": (ref, None)}, settings)
    row = out["refinements"].iloc[0]
    assert row["used"] == "refined", row["reason"]
    est = out["registrations"].iloc[0][["dx", "dy", "dz", "dheading_deg"]].to_numpy(float)
    sd = out["registrations"].iloc[0][["sd_x", "sd_y", "sd_z", "sd_heading_deg"]].to_numpy(float)
    assert np.linalg.norm(est[:3] - truth[:3]) < 0.005 and abs(est[3] - truth[3]) < 0.02
    assert np.all(np.abs(est - truth) < 3 * sd)
    assert row["moved_xy_m"] > 0.03 and row["disagree_xy_m"] < 0.005
    # the old guard refuses the same move: it leaves the coarse sigma's 3-sigma box
    old = refine_registrations(_registrations("a", "b", start, [0.001, 0.001, 0.001, 0.002]),
                               {"a": (scan, None), "b": (ref, None)},
                               RefineSettings(**{**settings.__dict__, "guard": "box"}))
    assert old["refinements"].iloc[0]["used"] == "branch_and_bound"


def test_two_way_refinement_refuses_a_pose_its_points_do_not_support():
    """Scans that share no surface (one cloud moved 30 m away) are not refined; a start outside
    the trust region's reach ends on its edge and is not used."""
    from forestmap_assets.core.registration.refine import refine_registrations
    from forestmap_assets.params.men import RefineSettings

    scan, _, ref, _, truth = _scene_views()
    settings = RefineSettings(data_voxel_m=0.1, model_voxel_m=0.0, z_band_m=(-20.0, 20.0), max_range_m=50.0,
                              min_pairs=100)
    far = refine_registrations(_registrations("a", "b", truth + np.array([30.0, 0, 0, 0]), [0.01] * 4),
                               {"a": (scan, None), "b": (ref, None)}, settings)["refinements"].iloc[0]
    assert far["used"] == "branch_and_bound" and "overlap" in far["reason"]
    tight = RefineSettings(**{**settings.__dict__, "max_shift_m": 0.01})
    edge = refine_registrations(_registrations("a", "b", truth + np.array([0.05, 0.0, 0.0, 0.0]), [0.01] * 4),
                                {"a": (scan, None), "b": (ref, None)}, tight)["refinements"].iloc[0]
    assert edge["used"] == "branch_and_bound" and "trust region" in edge["reason"]
