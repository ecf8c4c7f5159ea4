"""The refinement objectives' common scale of the network (core/mapping/objective_scale.py)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.mapping.objective_scale import (
    gap_scale,
    objective_scale,
    scale_floor,
    scale_sd,
    shorten_links,
    stem_gap,
    take_out,
    widen_links,
)


def _links(spread_per_m, rng, refined=True):
    n = len(spread_per_m)
    ang = rng.uniform(-np.pi, np.pi, n)
    length = rng.uniform(5.0, 15.0, n)
    return pd.DataFrame({"scan": [f"s{i}" for i in range(n)], "reference": "r",
                         "dx": length * np.cos(ang), "dy": length * np.sin(ang), "dz": 0.0, "dheading_deg": 0.0,
                         "sd_x": 0.001, "sd_y": 0.001, "sd_z": 0.0008, "sd_heading_deg": 0.005,
                         "refined": refined, "objective_spread_m": np.asarray(spread_per_m) * length})


def test_a_common_lengthening_is_a_scale_and_noise_is_not():
    rng = np.random.default_rng(1)
    # rendered-like: every link about 0.35 mm/m longer with the symmetric objective
    links = _links(0.00035 + rng.normal(0, 0.0001, 11), rng)
    scale, t, n = objective_scale(links)
    assert n == 11 and t > 5 and abs(scale - 0.00035) < 0.0001
    # Sylva-like: differences of either sign, no common part
    noisy = _links(rng.normal(0, 0.0003, 9), rng)
    assert objective_scale(noisy)[0] == 0.0
    # too few refined links, or links the refinement did not replace, give none
    assert objective_scale(links.head(2)) == (0.0, 0.0, 2)
    assert objective_scale(_links(np.full(6, 0.0004), rng, refined=False))[2] == 0


def test_links_and_scans_take_the_scale_along_their_baselines():
    rng = np.random.default_rng(2)
    links = _links(np.full(4, 0.0004), rng)
    links.loc[0, "refined"] = False
    wide = widen_links(links, 0.0004)
    assert wide.loc[0, "sd_x"] == links.loc[0, "sd_x"]  # branch and bound: not refined
    grown = np.hypot(0.001, 0.0004 * links[["dx", "dy"]].to_numpy()[1:])
    np.testing.assert_allclose(wide[["sd_x", "sd_y"]].to_numpy()[1:], grown)
    assert widen_links(links, 0.0) is links
    poses = pd.DataFrame({"scan": ["r", "a"], "x": [0.0, 12.0], "y": [0.0, -5.0], "sd_x": [0.0, 0.002],
                          "sd_y": [0.0, 0.002]})
    out = scale_sd(poses, -0.0004)
    np.testing.assert_allclose(out["sd_x"], [0.0, np.hypot(0.002, 0.0048)])
    np.testing.assert_allclose(out["sd_y"], [0.0, np.hypot(0.002, 0.002)])
    # a floor per metre (mapping.scale_sd_floor) when the objectives show no larger scale
    floored = scale_sd(poses, 0.0, floor=0.00008)
    np.testing.assert_allclose(floored["sd_x"], [0.0, np.hypot(0.002, 0.00096)])
    np.testing.assert_allclose(scale_sd(poses, -0.0004, floor=0.00008)["sd_x"], out["sd_x"])
    assert scale_sd(poses, 0.0) is poses


def test_a_wide_beam_takes_the_wider_scale_floor():
    """The own simulator's 3 mrad beam: networks 0.16-0.24 mm/m short or 0.17 mm/m long that no
    link shows; a campaign with no named beam (Sylva's, rendered) keeps the plain floor."""
    assert scale_floor(8e-5, 2e-4, 3.0, 1.0) == 2e-4
    assert scale_floor(8e-5, 2e-4, 0.0, 1.0) == 8e-5
    assert scale_floor(8e-5, 2e-4, 1.0, 1.0) == 8e-5  # the symmetric objective's limit, not wide
    assert scale_floor(3e-4, 2e-4, 3.0, 1.0) == 3e-4


def test_a_clear_scale_is_taken_out_of_the_refined_links():
    rng = np.random.default_rng(3)
    links = _links(0.00035 + rng.normal(0, 0.00005, 6), rng)
    links.loc[0, "refined"] = False  # a branch-and-bound link keeps its length
    scale, t, _ = objective_scale(links)
    assert t > 6
    short, sigma = take_out(links, scale, t, correct_t=6.0)
    assert sigma == 0.0
    np.testing.assert_allclose(short.loc[0, ["dx", "dy"]].to_numpy(float), links.loc[0, ["dx", "dy"]].to_numpy(float))
    before = np.hypot(links["dx"], links["dy"]).to_numpy()[1:]
    after = np.hypot(short["dx"], short["dy"]).to_numpy()[1:]
    np.testing.assert_allclose(before - after, scale * before)  # along each baseline, per metre
    np.testing.assert_allclose(np.arctan2(short["dy"], short["dx"]), np.arctan2(links["dy"], links["dx"]))
    # under the threshold (or the campaign's default, inf) the scale stays a sigma
    kept, sigma = take_out(links, scale, t, correct_t=float("inf"))
    assert kept is links and sigma == scale
    same, sigma = take_out(links, 0.0, 0.0, 6.0)
    assert same is links and sigma == 0.0
    assert shorten_links(links, 0.0) is links


def test_the_stems_gap_is_their_mean_lengthening_per_metre_over_the_refined_links():
    rng = np.random.default_rng(3)
    links = _links(np.zeros(8), rng)
    stretch = -0.0004 + rng.normal(0, 0.0001, 8)  # the stems put every baseline shorter
    refinements = links[["scan", "reference"]].assign(bnb_dx=links.dx * (1 + stretch), bnb_dy=links.dy * (1 + stretch))
    gap, n = stem_gap(links, refinements)
    assert n == 8 and abs(gap - stretch.mean()) < 1e-12
    # links kept at their branch-and-bound pose do not count; too few refined links give none
    links.loc[:5, "refined"] = False
    assert stem_gap(links, refinements) == (0.0, 2)
    assert stem_gap(links, None) == (0.0, 0)


def test_only_the_gap_beyond_the_stems_own_bias_is_a_scale_sigma():
    # Sylva's stems put baselines 0.14-0.37 mm/m longer on their own: no scale sigma from that
    assert gap_scale(+0.00025, 0.5, 3e-4) == 0.0
    assert gap_scale(-0.0003, 0.5, 3e-4) == 0.0
    # a render with 1 cm noise and 12 mm splats parted by -0.65 mm/m: half of the 0.35 beyond
    assert np.isclose(gap_scale(-0.00065, 0.5, 3e-4), 0.000175)
    assert np.isclose(gap_scale(-0.00065, 0.5), 0.000325)  # no allowance: half the gap
