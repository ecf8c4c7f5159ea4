"""The thesis's test of a new link (Th. 7.1, Table 7.1; spec 8.5, 10.7) and autonomous link
selection (spanning tree first, then loop-closing links tested one at a time).

The thesis publishes the residuals after adding NQ, NR, NS and OT (Table 7.1) but not those
four observations. They are reconstructed here (inferred): in the linearised network adding a
link changes every residual in proportion to one scalar per component, so that scalar is fitted
to the 10 published residuals and turned into an observation with a chosen sigma.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.mapping.chaining import wrap_deg
from forestmap_assets.core.mapping.link_selection import (
    check_link_hypothesis,
    judge_link,
    select_links,
)
from forestmap_assets.core.mapping.optimal_map import solve_incremental, solve_network

TABLES = Path(__file__).parents[1] / "data" / "thesis_tables"
ORDER = list("TSRQON")
VAL = ["dx", "dy", "dz", "dheading_deg"]
SD = ["sd_x", "sd_y", "sd_z", "sd_heading_deg"]
E = ["ex", "ey", "ez", "eheading_deg"]
R = ["rx", "ry", "rz", "rheading"]
COLS = ["scan", "reference", *VAL, *SD]
SIGMA_H = np.array([0.03, 0.03, 0.05, 0.3])  # sigma given to reconstructed hypotheses (inferred)


def _table(name: str) -> pd.DataFrame:
    return pd.read_csv(TABLES / name, dtype={"scan": str, "reference": str},
                       keep_default_na=False)


@pytest.fixture(scope="module")
def forest_obs() -> pd.DataFrame:
    t = _table("table_6_6_forest_local.csv")
    return t[t["estimate"] == "cloud"].reset_index(drop=True)[COLS]


@pytest.fixture(scope="module")
def final_phase(forest_obs):
    return solve_incremental(forest_obs, ORDER).final


def _published(hyp: str) -> pd.DataFrame:
    t = _table("table_7_1_hypothesis_residuals.csv")
    return t[t["hypothesis"] == hyp].reset_index(drop=True)


def _hypothesis(scan, ref, innovation, final) -> pd.DataFrame:
    """Observation of ``scan`` in ``ref``'s frame = the map's prediction + a global innovation."""
    p = final.poses.set_index("scan")[["x", "y", "z", "heading_deg"]].astype(float)
    g = p.loc[scan].to_numpy() - p.loc[ref].to_numpy() + innovation
    phi = np.radians(p.loc[ref, "heading_deg"])
    c, s = np.cos(phi), np.sin(phi)
    local = [c * g[0] + s * g[1], -s * g[0] + c * g[1], g[2], g[3]]
    return pd.DataFrame([[scan, ref, *local, *SIGMA_H]], columns=COLS)


def _residuals_with(obs, hyp, final):
    sol = solve_network(pd.concat([obs, hyp], ignore_index=True), ORDER,
                        headings=final.headings())
    return sol.residuals[E].to_numpy()[: len(obs)]


def _reconstruct(hyp: str, obs, final) -> tuple[pd.DataFrame, np.ndarray]:
    """Fit the hypothesis's global innovation per component to Table 7.1 (least squares on the
    unsigned residuals, coarse-to-fine 1-D search); returns it and the fit's abs errors."""
    scan, ref = hyp[0], hyp[1]
    e0 = _residuals_with(obs, _hypothesis(scan, ref, np.zeros(4), final), final)
    gain = _residuals_with(obs, _hypothesis(scan, ref, np.ones(4), final), final) - e0
    want = _published(hyp)[E].to_numpy()
    nu = np.zeros(4)
    for c, (span, step) in enumerate([(20, 1e-3)] * 3 + [(179.9, 1e-2)]):
        for _ in range(2):
            grid = np.arange(nu[c] - span, nu[c] + span, step)
            cost = ((np.abs(e0[:, c] + np.outer(grid, gain[:, c])) - want[:, c]) ** 2).sum(1)
            nu[c], span, step = grid[np.argmin(cost)], 2 * step, step / 100
    h = _hypothesis(scan, ref, nu, final)
    err = np.abs(np.abs(_residuals_with(obs, h, final)) - want)
    return h, err


def test_table_7_1_verdicts_from_published_residuals():
    """The decision rule on Table 7.1 as printed: NQ, NR, NS rejected, OT accepted; without the
    NO row (zero by construction in the baseline) the worst components are those of spec 10.7
    (OQ x 45.8, OR x 76.7, OS x 54.6 sigma); OT's largest are 1.3 (x/y/heading) and 5.7 (z)."""
    expect = {"NQ": ("O", "Q", "x", 45.8), "NR": ("O", "R", "x", 76.7),
              "NS": ("O", "S", "x", 54.6), "OT": None}
    for hyp, worst in expect.items():
        t = _published(hyp)
        res = t[["scan", "reference"]].copy()
        res[R] = t[E].to_numpy() / t[SD].to_numpy()
        full = judge_link(res, np.zeros(len(res), bool), hyp[0], hyp[1])
        no_no = judge_link(res.iloc[:-1], np.zeros(len(res) - 1, bool), hyp[0], hyp[1])
        if worst is None:
            assert full.verdict == "ok" and no_no.verdict == "ok"
            r = res[R].to_numpy()
            assert np.abs(r[:, [0, 1, 3]]).max() == pytest.approx(1.3, abs=0.05)
            assert np.abs(r[:, 2]).max() == pytest.approx(5.65, abs=0.1)
            continue
        assert full.verdict == "inconsistent" and not full.accepted
        assert full.worst_pair == ("N", "O")  # NO itself: 59-145 deg heading residuals
        assert no_no.verdict == "inconsistent"
        assert (*no_no.worst_pair, no_no.worst_component) == worst[:3]
        assert no_no.worst_sigmas == pytest.approx(worst[3], abs=0.1)
        assert f"{worst[0]}-{worst[1]}" in no_no.reason and "x residual" in no_no.reason


def test_baseline_table_6_10_passes_the_rule():
    t = _table("table_6_10_forest_residuals.csv")
    res = t[["scan", "reference"]].copy()
    res[R] = t[E].to_numpy() / t[SD].to_numpy()
    v = judge_link(res, np.zeros(len(res), bool), "N", "O")
    assert v.verdict == "ok" and v.worst_component == "z"
    assert v.worst_pair in {("Q", "S"), ("O", "S")} and 5.0 < v.worst_sigmas < 6.0
    # ... and a 3-sigma z threshold (no z tolerance) would have rejected the thesis's own map
    assert judge_link(res, np.zeros(len(res), bool), "N", "O",
                      z_residual_sigmas=3.0).verdict == "inconsistent"


def test_table_7_1_ot_reproduced_and_accepted(forest_obs, final_phase):
    """OT (left out by the thesis, found consistent in 7.1): with one fitted scalar per component
    the 10 published residuals are reproduced to 0.025 m / 0.15 deg (our map differs from the
    thesis's by up to 0.075 deg in heading), and the link test accepts it."""
    hyp, err = _reconstruct("OT", forest_obs, final_phase)
    assert err[:, :3].max() < 0.025 and err[:, 3].max() < 0.15
    v = check_link_hypothesis(forest_obs, hyp, "T", baseline=final_phase, scans=ORDER)
    assert v.verdict == "ok" and v.accepted
    assert v.worst_sigmas < 6.0  # like the baseline: z of QS / OS
    # the reconstructed OT agrees with the thesis's own final pose of O to a few cm / 0.1 deg
    o = _table("table_6_8_forest_phases.csv").query("phase == 5 and scan == 'O'")
    np.testing.assert_allclose(hyp[VAL].to_numpy(dtype=float)[0, :3],
                               o[["x", "y", "z"]].to_numpy()[0], atol=0.06)
    assert abs(wrap_deg(hyp["dheading_deg"].iloc[0] - o["heading_deg"].iloc[0])) < 0.1


def test_ot_from_thesis_pose_is_accepted(forest_obs, final_phase):
    """Independently of any fit: OT observed at the thesis's final pose of O is consistent."""
    o = _table("table_6_8_forest_phases.csv").query("phase == 5 and scan == 'O'")
    hyp = pd.DataFrame([["O", "T", *o[["x", "y", "z", "heading_deg"]].to_numpy()[0],
                         0.03, 0.03, 0.04, 0.2]], columns=COLS)
    v = check_link_hypothesis(forest_obs, hyp, "T", baseline=final_phase, scans=ORDER)
    assert v.verdict == "ok", v.reason


@pytest.mark.parametrize("hyp", ["NQ", "NR", "NS"])
def test_table_7_1_false_hypotheses_rejected(forest_obs, final_phase, hyp):
    """NQ, NR, NS (too few common trees): reconstructed from Table 7.1 they are rejected by a
    wide margin. (Their published residuals do not follow the linear one-scalar pattern, e.g.
    the heading column, so the reconstruction is only approximate: not asserted.)"""
    h, _ = _reconstruct(hyp, forest_obs, final_phase)
    v = check_link_hypothesis(forest_obs, h, "T", baseline=final_phase, scans=ORDER)
    assert v.verdict == "inconsistent" and not v.accepted
    assert v.worst_sigmas > 10.0
    assert v.worst_pair is not None and v.worst_pair in {
        (a, b) for a, b in zip(forest_obs["scan"], forest_obs["reference"], strict=True)}
    assert "sigma >" in v.reason


def test_single_link_cannot_be_checked(forest_obs, final_phase):
    """NO when N was added (Th. 7.1): no parallel path, so the test cannot judge it."""
    phase4 = solve_incremental(forest_obs, ORDER[:5]).final
    no = forest_obs[forest_obs["scan"] == "N"]
    v = check_link_hypothesis(forest_obs[forest_obs["scan"] != "N"], no, "T", baseline=phase4)
    assert v.verdict == "untestable" and v.accepted and "parallel path" in v.reason


def test_new_link_itself_inconsistent(forest_obs, final_phase):
    """A loose link (heading sigma 1 deg) 6 deg off barely moves the map, so no existing pair
    objects; its own residual (about 6 sigma) does (check_new_link, beyond the thesis)."""
    h = _hypothesis("O", "T", np.array([0.0, 0.0, 0.0, 6.0]), final_phase)
    h["sd_heading_deg"] = 1.0
    v = check_link_hypothesis(forest_obs, h, "T", baseline=final_phase, scans=ORDER)
    assert v.verdict == "inconsistent" and v.worst_pair == ("O", "T")
    assert v.worst_component == "heading" and 5.0 < v.worst_sigmas < 6.5
    assert "itself" in v.reason
    lenient = check_link_hypothesis(forest_obs, h, "T", baseline=final_phase, scans=ORDER,
                                    check_new_link=False)
    assert lenient.verdict == "ok"


def test_select_links_forest_with_hypotheses(forest_obs, final_phase):
    """All 14 candidates (Table 6.6, OT, NQ, NR, NS), the false ones given a middling
    confidence above some true loop links: the tree takes the most confident links, NQ, NR
    and NS are rejected as loop closures with reasons, OT and the thesis's 10 are admitted."""
    extra = [_reconstruct(h, forest_obs, final_phase)[0] for h in ("NQ", "NR", "NS")]
    o = _table("table_6_8_forest_phases.csv").query("phase == 5 and scan == 'O'")
    ot = pd.DataFrame([["O", "T", *o[["x", "y", "z", "heading_deg"]].to_numpy()[0],
                        0.03, 0.03, 0.04, 0.2]], columns=COLS)
    cand = pd.concat([forest_obs, ot, *extra], ignore_index=True)
    cand["confidence"] = [0.9, 0.8, 0.5, 0.7, 0.4, 0.6, 0.8, 0.7, 0.5, 0.9, 0.3, 0.6, 0.6, 0.6]
    sel = select_links(cand, "T")
    links = sel.links.set_index(sel.links["scan"] + sel.links["reference"])
    assert set(sel.rejected.index.map(lambda k: links.index[k])) == {"NQ", "NR", "NS"}
    assert (links.loc[["NQ", "NR", "NS"], "status"] == "rejected").all()
    assert all("inconsistent" in r for r in links.loc[["NQ", "NR", "NS"], "reason"])
    assert links.loc["NO", "role"] == "tree"
    assert (links["role"] == "tree").sum() == 5 and (links["role"] == "loop").sum() == 6
    assert sorted(links.loc[links["status"] == "admitted", "step"]) == list(range(11))
    assert sel.unregistered == []
    p = sel.solution.poses.set_index("scan")
    assert p["registered"].all()
    q = final_phase.poses.set_index("scan").loc[p.index]
    np.testing.assert_allclose(p[["x", "y", "z"]].to_numpy(dtype=float),
                               q[["x", "y", "z"]].to_numpy(dtype=float), atol=0.03)
    assert (sel.solution.residuals["verdict"] == "ok").all()


def test_select_links_reports_unreached_scans(forest_obs):
    extra = pd.DataFrame([["X", "Y", 1.0, 0.0, 0.0, 0.0, 0.1, 0.1, 0.1, 1.0]], columns=COLS)
    sel = select_links(pd.concat([forest_obs, extra], ignore_index=True), "T")
    assert sel.unregistered == ["Y", "X"]
    row = sel.links.iloc[-1]
    assert row["status"] == "unreached" and "not reached" in row["reason"]
    p = sel.solution.poses.set_index("scan")
    assert not p.loc["X", "registered"] and np.isnan(p.loc["X", "x"])
    # without a confidence column the tightest clouds go first: NO (sigma 0.02..0.32) in tree
    assert (sel.links["status"] != "rejected").all()


def _simulate(n, seed, noise=1.0, extra_links=10):
    rng = np.random.default_rng(seed)
    truth = np.column_stack([rng.uniform(-15, 15, (n, 2)), rng.uniform(-1, 1, n),
                             rng.uniform(-180, 180, n)])
    truth[0] = 0.0
    pairs = [(k, int(rng.integers(0, k))) for k in range(1, n)]
    while len(pairs) < n - 1 + extra_links:
        a, b = (int(v) for v in rng.choice(n, 2, replace=False))
        if (a, b) not in pairs and (b, a) not in pairs:
            pairs.append((a, b))
    i, j = np.array(pairs).T
    phi = np.radians(truth[j, 3])
    dxy = truth[i, :2] - truth[j, :2]
    local = np.column_stack([np.cos(phi) * dxy[:, 0] + np.sin(phi) * dxy[:, 1],
                             -np.sin(phi) * dxy[:, 0] + np.cos(phi) * dxy[:, 1],
                             truth[i, 2] - truth[j, 2], wrap_deg(truth[i, 3] - truth[j, 3])])
    sd = np.column_stack([rng.uniform(0.02, 0.05, (len(i), 2)), rng.uniform(0.03, 0.2, len(i)),
                          rng.uniform(0.1, 0.3, len(i))])
    local = local + noise * sd * rng.standard_normal(sd.shape)
    names = [f"s{k}" for k in range(n)]
    obs = pd.DataFrame({"scan": [names[k] for k in i], "reference": [names[k] for k in j]})
    obs[VAL], obs[SD] = local, sd
    return names, truth, obs


def test_select_links_rejects_corrupted_loop_links():
    """Simulated 8-scan network, 17 noisy links, two of them corrupted (a 2 m shift, a 25 deg
    turn) and given a middling confidence: both rejected, the others admitted, poses within
    4 sigma of the truth."""
    names, truth, obs = _simulate(8, seed=11)
    obs["confidence"] = np.linspace(1.0, 0.2, len(obs))  # tree links (first 7) most confident
    bad = [8, 12]
    obs.loc[bad[0], "dx"] += 2.0
    obs.loc[bad[1], "dheading_deg"] += 25.0
    obs.loc[bad, "confidence"] = 0.6
    sel = select_links(obs, "s0")
    status = sel.links["status"].to_numpy()
    assert (status[bad] == "rejected").all()
    assert (np.delete(status, bad) == "admitted").all()
    p = sel.solution.poses
    err = np.abs(p[["x", "y", "z"]].to_numpy(dtype=float) - truth[:, :3])
    sd = p[["sd_x", "sd_y", "sd_z"]].to_numpy(dtype=float)
    assert np.all(err[1:] < 4 * sd[1:] + 1e-9)
    herr = np.abs(wrap_deg(p["heading_deg"].to_numpy(dtype=float) - truth[:, 3]))
    assert np.all(herr[1:] < 4 * p["sd_heading_deg"].to_numpy(dtype=float)[1:])


def test_an_outvoted_spanning_tree_link_is_left_out():
    """A scan's most confident link, which places it in the spanning tree unchecked, is
    corrupted (+0.1 deg, 2 cm); its three other links agree with each other and with the
    rest of the network. Without the re-selection each of the three is rejected as
    inconsistent with the tree link and the scan sits on the bad link; with it (``outvote``
    2, the default) the tree link is left out, named as outvoted, and the scan is placed
    within 4 sigma of the truth."""
    names, truth, obs = _simulate(6, seed=3, noise=0.0, extra_links=9)
    obs[SD] = [0.003, 0.003, 0.002, 0.008]
    obs["confidence"] = 1.0
    at = obs.index[obs["scan"].eq("s5") | obs["reference"].eq("s5")]
    assert len(at) >= 3
    bad = at[0]
    obs.loc[bad, "dheading_deg"] += 0.1
    obs.loc[bad, "dx"] += 0.02
    obs.loc[bad, "confidence"] = 2.0
    obs.loc[bad, SD] = [0.004, 0.004, 0.003, 0.026]
    plain = select_links(obs, "s0", outvote=0)
    assert plain.links.loc[bad, "role"] == "tree"
    assert (plain.links.loc[at[1:], "status"] == "rejected").all()
    sel = select_links(obs, "s0")
    assert sel.links.loc[bad, "status"] == "rejected"
    assert sel.links.loc[bad, "reason"].startswith("spanning-tree link outvoted")
    assert (sel.links.drop(index=bad)["status"] == "admitted").all()
    p = sel.solution.poses.set_index("scan")
    herr = abs(wrap_deg(p.loc["s5", "heading_deg"] - truth[5, 3]))
    assert herr < 4 * p.loc["s5", "sd_heading_deg"]
    assert abs(wrap_deg(plain.solution.poses.set_index("scan").loc["s5", "heading_deg"] - truth[5, 3])) > 0.05
