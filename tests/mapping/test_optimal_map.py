"""Lu-Milios optimal map with incremental re-solving (spec 8.1-8.5) against Tables 6.6-6.10."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.mapping.chaining import chain_poses, project_relative, wrap_deg
from forestmap_assets.core.mapping.optimal_map import solve_incremental, solve_network
from forestmap_assets.core.mapping.residuals import residual_arrays

TABLES = Path(__file__).parents[1] / "data" / "thesis_tables"
ORDER = list("TSRQON")
POSE = ["x", "y", "z", "heading_deg"]
SD = ["sd_x", "sd_y", "sd_z", "sd_heading_deg"]
VAL = ["dx", "dy", "dz", "dheading_deg"]
E = ["ex", "ey", "ez", "eheading_deg"]
COLS = ["scan", "reference", *VAL, *SD]


def _table(name: str) -> pd.DataFrame:
    return pd.read_csv(TABLES / name, dtype={"scan": str, "reference": str},
                       keep_default_na=False)


@pytest.fixture(scope="module")
def forest_obs() -> pd.DataFrame:
    t = _table("table_6_6_forest_local.csv")
    return t[t["estimate"] == "cloud"].reset_index(drop=True)[COLS]


@pytest.fixture(scope="module")
def forest_map(forest_obs):
    return solve_incremental(forest_obs, ORDER)


def _thesis_phase(k: int) -> pd.DataFrame:
    t = _table("table_6_8_forest_phases.csv")
    return t[t["phase"] == k].set_index("scan")


def test_table_6_8_every_phase(forest_map):
    """Table 6.8 (= JP Table I) to 0.02 m and 0.1 deg in all five phases; headings are not
    wrapped, as printed (O = 264.76)."""
    assert [p.scans for p in forest_map.phases] == [ORDER[:k] for k in range(2, 7)]
    for k, phase in enumerate(forest_map.phases, start=1):
        want = _thesis_phase(k)
        got = phase.poses.set_index("scan")
        assert got["registered"].all()
        assert (got.loc["T", POSE + SD] == 0).all()
        got = got.loc[want.index]
        np.testing.assert_allclose(got[["x", "y", "z"]].to_numpy(dtype=float),
                                   want[["x", "y", "z"]].to_numpy(), atol=0.02)
        np.testing.assert_allclose(got["heading_deg"].to_numpy(dtype=float),
                                   want["heading_deg"].to_numpy(), atol=0.1)


def test_table_6_9_translation_sigmas(forest_map):
    t = _table("table_6_9_forest_phase_sd.csv")
    for k, phase in enumerate(forest_map.phases, start=1):
        want = t[t["phase"] == k].set_index("scan")
        got = phase.poses.set_index("scan").loc[want.index]
        np.testing.assert_allclose(got[["sd_x", "sd_y", "sd_z"]].to_numpy(dtype=float),
                                   want[["sd_x", "sd_y", "sd_z"]].to_numpy(), atol=0.01)


@pytest.mark.xfail(strict=True, reason="spec 10.8: with the published Table 6.6 sigmas the "
                   "heading sigmas come out 0.20-0.24 deg where Table 6.9 prints 0.13-0.18; the "
                   "thesis's own phase-2 heading of S moves >= 0.02 deg (-38.71 -> -38.68) where a "
                   "heading-only weighted mean allows <= 0.007 deg (loop misclosure <= 0.035 "
                   "deg x weight share 0.2, even with unrounded inputs), so its heading "
                   "covariances had cross terms that were not published")
def test_table_6_9_heading_sigmas(forest_map):
    t = _table("table_6_9_forest_phase_sd.csv")
    for k, phase in enumerate(forest_map.phases, start=1):
        want = t[t["phase"] == k].set_index("scan")
        got = phase.poses.set_index("scan").loc[want.index]
        np.testing.assert_allclose(got["sd_heading_deg"].to_numpy(dtype=float),
                                   want["sd_heading_deg"].to_numpy(), atol=0.02)


def test_heading_sigma_is_the_heading_subnetwork(forest_map):
    """Phase 2 heading sigma by hand: loop ST (0.27), RS (0.24), RT (0.48)."""
    w = 1 / np.array([0.27, 0.24, 0.48]) ** 2
    a = np.array([[w[0] + w[1], -w[1]], [-w[1], w[1] + w[2]]])
    want = np.sqrt(np.diag(np.linalg.inv(a)))
    got = forest_map.phases[1].poses.set_index("scan").loc[["S", "R"], "sd_heading_deg"]
    np.testing.assert_allclose(got.to_numpy(dtype=float), want, rtol=1e-9)


def test_table_6_7_projection_with_phase_4_headings(forest_obs):
    """Projecting Table 6.6 with the thesis's phase-4 headings reproduces Table 6.7 to 0.01.
    (Th. typo?) rows asserted at their recomputed values: RS x 0.83 -> 0.88, QS y -2.58 ->
    -2.53, OQ y -0.52 -> -0.50, OS y -3.09 -> -3.01 (spec 10.6; Table 6.10 agrees with 0.88
    and -3.01), and, beyond the spec's list, QS x 6.08 -> 6.09, OS x 10.88 -> 10.90 (the printed
    QS and OS rows fit an S heading of about -39.1 deg, not Table 6.8's -38.66) and NO x
    1.26 -> 1.28."""
    h4 = {"T": 0.0, **_thesis_phase(4)["heading_deg"].to_dict()}
    sol = solve_network(forest_obs, ORDER, headings=h4)
    printed = _table("table_6_7_forest_projected.csv").set_index(["scan", "reference"])
    corrected = {("R", "S"): {"dx": 0.88}, ("Q", "S"): {"dx": 6.09, "dy": -2.53},
                 ("O", "Q"): {"dy": -0.50}, ("O", "S"): {"dx": 10.90, "dy": -3.01},
                 ("N", "O"): {"dx": 1.28}}
    got = sol.projected.set_index(["scan", "reference"]).loc[printed.index]
    for key, values in corrected.items():
        assert "recomputes" in printed.loc[key, "note"]
        for col, v in values.items():
            assert abs(printed.loc[key, col] - got.loc[key, col]) > 0.0105  # printed differs
            printed.loc[key, col] = v
    np.testing.assert_allclose(got[VAL].to_numpy(dtype=float), printed[VAL].to_numpy(),
                               atol=0.0105)
    # OS sigma_x is printed 0.02, below both local sigmas (0.03, 0.04): no rotation of a
    # diagonal covariance gives that (cross terms again, see test_chaining); ours lies between.
    assert 0.03 <= got.loc[("O", "S"), "sd_x"] <= 0.04
    printed.loc[("O", "S"), "sd_x"] = got.loc[("O", "S"), "sd_x"]
    np.testing.assert_allclose(got[SD].to_numpy(dtype=float), printed[SD].to_numpy(),
                               atol=0.0105)
    # the unwrapped heading of OS stays 303.45 as published
    assert got.loc[("O", "S"), "dheading_deg"] == pytest.approx(303.45)


def test_table_6_10_from_thesis_poses(forest_obs):
    """Eq. (11) with Table 6.7's projection (phase-4 headings) and Table 6.8's final poses gives
    Table 6.10 to 0.011 m / 0.01 deg (poses printed to 0.01)."""
    h4 = {"T": 0.0, **_thesis_phase(4)["heading_deg"].to_dict()}
    sol = solve_network(forest_obs, ORDER, headings=h4)
    p5 = _thesis_phase(5)
    poses = np.vstack([np.zeros(4), p5.loc[ORDER[1:], POSE].to_numpy()])
    idx = {s: k for k, s in enumerate(ORDER)}
    i = sol.projected["scan"].map(idx).to_numpy()
    j = sol.projected["reference"].map(idx).to_numpy()
    e, _ = residual_arrays(i, j, sol.projected[VAL].to_numpy(), sol.projected[SD].to_numpy(),
                           poses)
    want = _table("table_6_10_forest_residuals.csv")[E].to_numpy()
    np.testing.assert_allclose(np.abs(e[:, :3]), want[:, :3], atol=0.011)
    np.testing.assert_allclose(np.abs(e[:, 3]), want[:, 3], atol=0.01)


def test_table_6_10_from_our_solution(forest_map):
    """Our own final map's residuals against Table 6.10: within 0.025 m and 0.1 deg (our poses
    differ from Table 6.8 by up to 0.015 m / 0.075 deg, see the heading-sigma xfail above).
    As in the thesis only z of QS and OS exceeds 3 sigma, and with the z tolerance (8 sigma)
    every pair is ``ok``; NO is a single link with zero residual."""
    res = forest_map.final.residuals
    want = _table("table_6_10_forest_residuals.csv")
    assert list(res["scan"] + res["reference"]) == list(want["pair"])
    np.testing.assert_allclose(np.abs(res[E[:3]].to_numpy()), want[E[:3]].to_numpy(),
                               atol=0.025)
    np.testing.assert_allclose(np.abs(res["eheading_deg"]), want["eheading_deg"], atol=0.1)
    r = np.abs(res[["rx", "ry", "rz", "rheading"]].to_numpy())
    over = {(a + b, c) for a, b, row in zip(res["scan"], res["reference"], r, strict=True)
            for c, v in zip("xyzh", row, strict=True) if v > 3}
    assert over == {("QS", "z"), ("OS", "z")}
    assert (res["verdict"] == "ok").all()
    np.testing.assert_allclose(res.iloc[-1][E].to_numpy(dtype=float), 0.0, atol=1e-9)


def _simulate(n=7, seed=0, noise=0.0, extra_links=6):
    rng = np.random.default_rng(seed)
    truth = np.column_stack([rng.uniform(-15, 15, (n, 2)), rng.uniform(-1, 1, n),
                             rng.uniform(-180, 180, n)])
    truth[0] = 0.0
    pairs = [(k, rng.integers(0, k)) for k in range(1, n)]  # a tree, new -> older
    while len(pairs) < n - 1 + extra_links:
        a, b = rng.choice(n, 2, replace=False)
        if (a, b) not in pairs and (b, a) not in pairs:
            pairs.append((int(a), int(b)))
    i, j = np.array(pairs).T
    phi = np.radians(truth[j, 3])
    dxy = truth[i, :2] - truth[j, :2]
    local = np.column_stack([np.cos(phi) * dxy[:, 0] + np.sin(phi) * dxy[:, 1],
                             -np.sin(phi) * dxy[:, 0] + np.cos(phi) * dxy[:, 1],
                             truth[i, 2] - truth[j, 2], wrap_deg(truth[i, 3] - truth[j, 3])])
    sd = np.column_stack([rng.uniform(0.02, 0.06, (len(i), 2)), rng.uniform(0.03, 0.2, len(i)),
                          rng.uniform(0.1, 0.4, len(i))])
    local = local + noise * sd * rng.standard_normal(sd.shape)
    names = [f"s{k}" for k in range(n)]
    obs = pd.DataFrame({"scan": [names[k] for k in i], "reference": [names[k] for k in j]})
    obs[VAL], obs[SD] = local, sd
    return names, truth, obs


def test_noise_free_network_recovers_truth():
    names, truth, obs = _simulate()
    om = solve_incremental(obs, names)
    got = om.final.poses[POSE].to_numpy(dtype=float)
    np.testing.assert_allclose(got[:, :3], truth[:, :3], atol=1e-9)
    np.testing.assert_allclose(wrap_deg(got[:, 3] - truth[:, 3]), 0.0, atol=1e-9)
    assert np.abs(om.final.residuals[E].to_numpy()).max() < 1e-9


@pytest.mark.parametrize("covariance", ["published", "full"])
def test_estimate_is_dense_lu_milios_formula(covariance):
    """x = (H'C^-1 H)^-1 H'C^-1 d and C_x = (H'C^-1 H)^-1 (Eq. 3.20-3.21) with H, C built
    densely here, independently of the solver's block assembly."""
    names, _, obs = _simulate(n=6, seed=4, noise=1.0)
    first = solve_network(obs, names, iterate=True)
    heads, hvars = first.headings(), first.heading_variances()
    sol = solve_network(obs, names, headings=heads, heading_variances=hvars,
                        covariance=covariance)
    n, m = len(names), len(obs)
    idx = {s: k for k, s in enumerate(names)}
    i, j = obs["scan"].map(idx).to_numpy(), obs["reference"].map(idx).to_numpy()
    h_ref = np.array([heads[s] for s in obs["reference"]])
    d = obs[VAL].to_numpy(dtype=float).copy()
    d[:, 3] = np.array([heads[a] - heads[b] for a, b in zip(obs["scan"], obs["reference"],
                                                             strict=True)])
    d[:, 3] += wrap_deg(obs["dheading_deg"].to_numpy() - d[:, 3])
    dg, cg = project_relative(d, obs[SD].to_numpy(), h_ref,
                              np.array([hvars[s] for s in obs["reference"]]), covariance)
    big_h = np.zeros((4 * m, 4 * (n - 1)))
    big_c = np.zeros((4 * m, 4 * m))
    for k in range(m):
        if i[k] > 0:
            big_h[4 * k:4 * k + 4, 4 * (i[k] - 1):4 * i[k]] = np.eye(4)
        if j[k] > 0:
            big_h[4 * k:4 * k + 4, 4 * (j[k] - 1):4 * j[k]] = -np.eye(4)
        big_c[4 * k:4 * k + 4, 4 * k:4 * k + 4] = cg[k]
    ci = np.linalg.inv(big_c)
    cx = np.linalg.inv(big_h.T @ ci @ big_h)
    x = cx @ big_h.T @ ci @ dg.reshape(-1)
    np.testing.assert_allclose(sol.poses[POSE].to_numpy(dtype=float)[1:].reshape(-1), x,
                               atol=1e-9)
    np.testing.assert_allclose(sol.covariance[4:, 4:], cx, rtol=1e-7, atol=1e-12)
    if covariance == "full":
        assert np.any(np.abs(sol.projected["cov_xy"]) > 0)


def test_heading_unwrapping_and_iteration(forest_obs):
    """OS given as -56.55 instead of 303.45 (same rotation) gives the same map; iterating the
    projection converges to a fixed point of the heading used for projection."""
    wrapped = forest_obs.copy()
    wrapped.loc[(wrapped["scan"] == "O") & (wrapped["reference"] == "S"), "dheading_deg"] = -56.55
    a = solve_incremental(forest_obs, ORDER).final.poses
    b = solve_incremental(wrapped, ORDER).final.poses
    np.testing.assert_allclose(a[POSE[:3]].to_numpy(dtype=float),
                               b[POSE[:3]].to_numpy(dtype=float), atol=1e-9)
    np.testing.assert_allclose(wrap_deg(a["heading_deg"] - b["heading_deg"]), 0.0, atol=1e-9)
    phases = solve_incremental(forest_obs, ORDER, iterate=True).phases
    assert max(p.iterations for p in phases) >= 2
    it = phases[-1]
    h = it.headings()
    used = it.projected["projection_heading_deg"].to_numpy()
    np.testing.assert_allclose(used, [h[r] for r in it.projected["reference"]], atol=1e-6)


def test_unreached_scan_is_not_registered(forest_obs):
    extra = pd.DataFrame([["X", "Y", 1.0, 0.0, 0.0, 0.0, 0.1, 0.1, 0.1, 1.0]], columns=COLS)
    sol = solve_incremental(pd.concat([forest_obs, extra], ignore_index=True),
                            ORDER + ["X", "Y"]).final
    p = sol.poses.set_index("scan")
    assert not p.loc["X", "registered"] and not p.loc["Y", "registered"]
    assert p.loc[["X", "Y"], POSE + SD].isna().all().all()
    assert p.loc[ORDER, "registered"].all()
    assert len(sol.residuals) == len(forest_obs)


def test_gauss_newton_is_a_stationary_point_of_the_likelihood():
    """linearisation='gauss_newton' (beyond the thesis): the numerical gradient of the
    negative log-likelihood (residuals in the reference's frame, diagonal sigmas there) vanishes
    at the solution, which the thesis's projection linearisation only approaches."""
    names, _, obs = _simulate(n=6, seed=5, noise=1.0)
    idx = {s: k for k, s in enumerate(names)}
    i, j = obs["scan"].map(idx).to_numpy(), obs["reference"].map(idx).to_numpy()
    d, sd = obs[VAL].to_numpy(dtype=float), obs[SD].to_numpy(dtype=float)

    def cost(flat):
        x = np.vstack([np.zeros(4), flat.reshape(-1, 4)])
        phi = np.radians(x[j, 3])
        dp = x[i, :2] - x[j, :2]
        e = np.column_stack([np.cos(phi) * dp[:, 0] + np.sin(phi) * dp[:, 1] - d[:, 0],
                             -np.sin(phi) * dp[:, 0] + np.cos(phi) * dp[:, 1] - d[:, 1],
                             x[i, 2] - x[j, 2] - d[:, 2],
                             wrap_deg(x[i, 3] - x[j, 3] - d[:, 3])])
        return 0.5 * np.sum((e / sd) ** 2)

    def grad(flat):
        h = 1e-6
        return np.array([(cost(flat + h * u) - cost(flat - h * u)) / (2 * h)
                         for u in np.eye(flat.size)])

    gn = solve_network(obs, names, linearisation="gauss_newton")
    pr = solve_network(obs, names, iterate=True)
    g_gn = grad(gn.poses[POSE].to_numpy(dtype=float)[1:].reshape(-1))
    g_pr = grad(pr.poses[POSE].to_numpy(dtype=float)[1:].reshape(-1))
    assert np.abs(g_gn).max() < 1e-4
    assert np.abs(g_pr).max() > 100 * np.abs(g_gn).max()
    assert gn.iterations > pr.iterations
    assert np.isfinite(gn.covariance[4:, 4:]).all()


def test_gauss_newton_matches_gtsam_pose2():
    """The peer: GTSAM's Pose2 between-factors (x, y, heading) plus 1-D z factors give the same
    map as linearisation='gauss_newton' (to 1 mm; Pose2's log map differs at second order)."""
    gtsam = pytest.importorskip("gtsam")
    names, _, obs = _simulate(n=8, seed=6, noise=1.0)
    ours = solve_network(obs, names, linearisation="gauss_newton").poses[POSE].to_numpy(float)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose2(gtsam.symbol("x", 0), gtsam.Pose2(0, 0, 0),
                                     gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
    graph.add(gtsam.PriorFactorDouble(gtsam.symbol("z", 0), 0.0,
                                      gtsam.noiseModel.Isotropic.Sigma(1, 1e-9)))
    idx = {s: k for k, s in enumerate(names)}
    for row in obs.itertuples():
        i, j, dphi = idx[row.scan], idx[row.reference], np.radians(row.dheading_deg)
        rot = np.array([[np.cos(dphi), np.sin(dphi)], [-np.sin(dphi), np.cos(dphi)]])
        cov = np.zeros((3, 3))  # sigmas given in the reference frame; Pose2 error in scan frame
        cov[:2, :2] = rot @ np.diag([row.sd_x ** 2, row.sd_y ** 2]) @ rot.T
        cov[2, 2] = np.radians(row.sd_heading_deg) ** 2
        graph.add(gtsam.BetweenFactorPose2(gtsam.symbol("x", j), gtsam.symbol("x", i),
                                           gtsam.Pose2(row.dx, row.dy, dphi),
                                           gtsam.noiseModel.Gaussian.Covariance(cov)))
        graph.add(gtsam.BetweenFactorDouble(gtsam.symbol("z", j), gtsam.symbol("z", i), row.dz,
                                            gtsam.noiseModel.Isotropic.Sigma(1, row.sd_z)))
    init = chain_poses(obs, names)[POSE].to_numpy(dtype=float)  # start as odometry would
    for k in range(len(names)):
        values.insert(gtsam.symbol("x", k),
                      gtsam.Pose2(init[k, 0], init[k, 1], np.radians(init[k, 3])))
        values.insert(gtsam.symbol("z", k), init[k, 2])
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    peer = np.array([[result.atPose2(gtsam.symbol("x", k)).x(),
                      result.atPose2(gtsam.symbol("x", k)).y(),
                      result.atDouble(gtsam.symbol("z", k)),
                      np.degrees(result.atPose2(gtsam.symbol("x", k)).theta())]
                     for k in range(len(names))])
    np.testing.assert_allclose(ours[:, :3], peer[:, :3], atol=1e-3)
    np.testing.assert_allclose(wrap_deg(ours[:, 3] - peer[:, 3]), 0.0, atol=0.01)
