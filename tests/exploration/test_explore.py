"""``forestmap explore``: the survey loop in a virtual plot (men_spec 7.7, checklist item 29)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import yaml

from forestmap_assets.explore.baseline_survey import grid_positions, random_positions
from forestmap_assets.explore.planned_survey import explore
from forestmap_assets.explore.survey_record import STEP_COLUMNS
from forestmap_assets.explore.survey_writer import SurveyWriter
from forestmap_assets.explore.virtual_plot import make_plot
from forestmap_assets.io.campaign import load_campaign


def test_virtual_plot_frames_and_free_positions():
    vp, _ = make_plot(20.0, 10, seed=4, resolution="quarter")
    pts = np.array([[1.0, 2.0], [-5.0, 7.5]])
    assert np.allclose(vp.to_world(vp.to_global(pts)), pts)
    assert np.allclose(vp.to_global([[vp.origin.x, vp.origin.y]]), 0.0)
    poly = vp.plot_polygon()
    assert np.allclose(np.linalg.norm(poly[1] - poly[0]), 20.0)
    stems = vp.forest.stems
    on_stem = stems[["x_base", "y_base"]].to_numpy()[:1]
    assert not vp.is_free(on_stem)[0]
    moved = vp.free_near(on_stem[0], np.random.default_rng(0))
    assert vp.is_free(moved)[0] and np.hypot(*(moved - on_stem[0])) < 3.0
    rnd = random_positions(vp, 5, np.random.default_rng(1))
    assert rnd.shape == (5, 2) and vp.is_free(rnd[1:]).all() and (np.abs(rnd) <= 10.0).all()
    grid = grid_positions(5, 30.0)
    assert np.allclose(grid, [[-10, -7.5], [0, -7.5], [10, -7.5], [7.5, 7.5], [-7.5, 7.5]])
    assert np.allclose(np.sort(grid_positions(9, 30.0)[:, 0]), np.repeat([-10.0, 0.0, 10.0], 3))


def test_survey_writer_manifest_is_a_valid_campaign(tmp_path):
    vp, ss = make_plot(16.0, 6, seed=5, resolution="quarter")
    w = SurveyWriter(
        tmp_path / "c",
        vp,
        search={"xy_m": 1.2, "z_m": 1.25, "heading_deg": 20.0},
        rng_noise=np.random.default_rng(0),
        params={"registration": {"method": "thesis"}},
    )
    w.add_scan(vp.origin)
    second = vp.pose_at(
        vp.free_near([vp.origin.x + 4, vp.origin.y], np.random.default_rng(1), 0.5),
        30.0,
        np.random.default_rng(2),
    )
    w.add_scan(second)
    w.add_pair("S", "T", (4.0, 0.0, 0.0, 30.0))
    w.write_manifest()
    c = load_campaign(tmp_path / "c")
    assert c.scan_ids == ["T", "S"] and c.pairs[0].reference == "T"
    assert c.params.registration.xy_m == 1.2 and c.angular_step_deg is not None
    assert c.params.registration.method == "thesis"
    truth = pd.read_csv(tmp_path / "c" / "truth" / "poses.csv")
    assert np.allclose(truth.iloc[0, 1:], 0.0) and np.hypot(
        truth.x[1], truth.y[1]
    ) == pytest.approx(np.hypot(second.x - vp.origin.x, second.y - vp.origin.y))
    trees = pd.read_csv(tmp_path / "c" / "truth" / "trees.csv")
    assert (trees["n_visible_scans"] <= 2).all() and trees["n_visible_scans"].max() >= 1
    assert len(pd.read_csv(tmp_path / "c" / "truth" / "plot.csv")) == 4


@pytest.mark.slow
def test_explore_two_scans_closes_the_loop(tmp_path):
    out = tmp_path / "survey"
    light = {"cloud_spacing_m": None, "picture": False, "report": False}
    res = explore(
        out,
        plot_size=18.0,
        trees=18,
        seed=1,
        budget=2,
        resolution="quarter",
        min_gain=0.0,
        export_kwargs=light,
    )
    steps = res.steps
    assert list(steps.columns) == STEP_COLUMNS and len(steps) == 2
    first, second = steps.iloc[0], steps.iloc[1]
    assert 0.2 < first.coverage < second.coverage <= 1.0
    assert second.gain == pytest.approx(second.coverage - first.coverage)
    # the planner's position kept enough stems in common to register, and it did register
    assert second.predicted_common_stems >= 5 and second.expected_new_m2 > 5
    assert second.registered and second.pose_error_m < 0.1 and second.heading_error_deg < 1.0
    # the surveyor arrived near the planned position (walking error 0.3 m per axis)
    assert np.hypot(second.true_x - second.planned_x, second.true_y - second.planned_y) < 1.5
    doc = yaml.safe_load((out / "campaign.yaml").read_text())
    assert [s["id"] for s in doc["scans"]] == ["T", "S"]
    assert doc["pairs"][0]["scan"] == "S" and doc["pairs"][0]["reference"] == second.reference
    for name in (
        "explore/steps.csv",
        "explore/step_00.png",
        "explore/step_01.png",
        "explore/proposals_01.csv",
        "outputs/poses.csv",
        "outputs/trees.csv",
        "truth/plot.csv",
    ):
        assert (out / name).is_file(), name
    assert res.stop_reason == "budget reached" and res.trees_with_dbh >= 3 and res.all_registered
