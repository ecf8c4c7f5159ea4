"""A renderer's splat widening taken back from the stems' slices (core/mapping/slice_splats.py)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pytest

from forestmap_assets.core.mapping.slice_splats import (
    link_splats,
    scan_splats,
    shared_scan_correlations,
    splat_edges_back,
    splat_steps,
)
from forestmap_assets.core.mapping.stem_slices import gather_slices, slice_dbh
from forestmap_assets.sim.cloud_render import render_scan

STEP = np.radians(0.1)


def test_scan_splats_are_the_median_over_refined_pairs():
    ref = pd.DataFrame({"scan": ["B", "C", "C", "D"], "reference": ["A", "A", "B", "A"],
                        "used": ["refined", "refined", "refined", "branch_and_bound"],
                        "splat_m": [0.007, 0.009, 0.007, np.nan]})
    assert scan_splats(ref) == pytest.approx({"A": 0.008, "B": 0.007, "C": 0.008})
    assert scan_splats(None) == {} and scan_splats(ref.drop(columns="splat_m")) == {}
    poses = pd.DataFrame({"scan": ["A", "B", "D"], "splat_m": [0.008, 0.0, 0.0]})
    tables = {s: pa.table({"x": [0.0]}).replace_schema_metadata({"azimuth_deg": "[0.0, 0.1, 0.2]"}) for s in "ABD"}
    steps = splat_steps(poses, tables)
    assert list(steps) == ["A"] and steps["A"] == pytest.approx((0.008, STEP))


def test_each_link_has_the_splat_its_refinement_took_back():
    ref = pd.DataFrame({"scan": ["B", "C", "D"], "reference": ["A", "A", "A"],
                        "used": ["refined", "refined", "branch_and_bound"], "splat_m": [0.007, 0.0, 0.009]})
    links = pd.DataFrame({"scan": ["D", "C", "B", "E"], "reference": ["A", "A", "A", "A"]})
    # D kept its branch-and-bound pose and E has no refinement: no splat taken back on them
    assert link_splats(links, ref).tolist() == [0.0, 0.0, 0.007, 0.0]
    assert link_splats(links, None).tolist() == [0.0] * 4


def test_refined_links_with_no_footprint_share_less_of_a_scans_z():
    ref = pd.DataFrame({"scan": ["B", "C"], "reference": ["A", "A"], "used": ["refined", "refined"],
                        "splat_m": [0.007, 0.0]})
    links = pd.DataFrame({"scan": ["B", "C", "D"], "reference": ["A", "A", "A"], "refined": [True, True, False]})
    branch, refined = (0.25, 0.25, 0.15, 0.05), (0.1, 0.1, 0.3, 0.25)
    rho = shared_scan_correlations(links, ref, branch, refined, footprint_free_z=0.1)
    # B took a splat back, C took none, D kept its branch-and-bound pose
    assert rho.tolist() == [list(refined), [0.1, 0.1, 0.1, 0.25], list(branch)]
    assert shared_scan_correlations(links, ref, branch, refined, 0.1, wide_beam=True)[1, 2] == 0.3
    assert shared_scan_correlations(links, ref, branch, refined)[1, 2] == 0.3
    assert shared_scan_correlations(links.drop(columns="refined"), ref, branch, refined, 0.1).tolist() == [list(branch)] * 3


def test_a_stems_slice_loses_most_of_the_splats_widening():
    """A 30 cm stem (a source cloud of 5 mm spacing) rendered with 12 mm splats
    (sim/cloud_render.render_scan) from three scans 5-9 m away reads 1.6 cm wide; with each
    scan's points moved back across their rays, 0.5 cm (the renderer returns a pixel's own
    source point where it has one, so the points inside the silhouette were not widened and
    are moved a little too far)."""
    centre, radius, splat = np.array([1.0, 2.0]), 0.15, 0.012
    psi, z = np.meshgrid(np.arange(0, 2 * np.pi, 0.005 / radius), np.arange(1.0, 1.6, 0.005))
    cloud = np.column_stack([centre[0] + radius * np.cos(psi.ravel()), centre[1] + radius * np.sin(psi.ravel()),
                             z.ravel()])
    sensors = [centre + d * np.array([np.cos(a), np.sin(a)]) for d, a in ((5.0, 0.3), (7.0, 2.4), (9.0, 4.2))]
    clouds = {f"S{k}": render_scan(cloud, [*s, 0.0], step_deg=0.1, splat_m=splat) for k, s in enumerate(sensors)}
    poses = pd.DataFrame({"scan": list(clouds), "x": [s[0] for s in sensors], "y": [s[1] for s in sensors],
                          "z": 0.0, "heading_deg": 0.0})
    stems = pd.DataFrame({"x": [centre[0]], "y": [centre[1]], "zbh": [1.3], "radius_m": [radius]})
    err = {}
    for name, splats in (("raw", None), ("none chosen", {}), ("back", {s: (splat, STEP) for s in clouds})):
        sl, sens = gather_slices(clouds, poses, stems, splats=splats)
        fit = slice_dbh(sl[["x", "y"]].to_numpy(), sens[sl["scan"].to_numpy()], tuple(centre), radius,
                        beam_exit_m=0.0, beam_divergence_rad=0.0, range_sigma_m=0.0)
        err[name] = fit.dbh_m - 2 * radius
    assert err["raw"] > 0.012 and err["none chosen"] == err["raw"]
    assert 0.0 < err["back"] < 0.007


def test_silhouette_sides_lose_the_splats_widening_of_their_scan():
    """Each side of a scan with a splat comes in by round(s / (r step)) r step: 12 mm splats,
    0.1 deg steps: one pixel at 5 m (8.7 mm) and at 10 m (17.5 mm), none at 20 m."""
    edges = pd.DataFrame({"tree": 0, "scan": ["A", "A", "A", "B"], "side": [1, -1, 1, 1], "row": 0,
                          "h_m": 0.2, "range_m": [5.0, 10.0, 20.0, 5.0], "quantum_m": 0.01, "phi": 0.0})
    out = splat_edges_back(edges, {"A": (0.012, STEP)})
    np.testing.assert_allclose(out["h_m"], [0.2 - 5 * STEP, 0.2 - 10 * STEP, 0.2, 0.2])
    assert splat_edges_back(edges, {}) is edges
