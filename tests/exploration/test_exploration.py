"""Exploration grid, completeness, frontier, paths, visibility and next vantage positions
(men_spec 3.5-3.6, 7; validation targets V19-V22 and their forest adaptation)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.exploration.candidates import PROPOSAL_COLUMNS, evaluate_positions
from forestmap_assets.core.exploration.frontier import (
    GROUND,
    OBSTACLE,
    UNMAPPED,
    classify_cells,
    coverage_figures,
    frontier_cells,
)
from forestmap_assets.core.exploration.grid import ExplorationGrid, local_ground
from forestmap_assets.core.exploration.occlusion import detect_occlusions
from forestmap_assets.core.exploration.paths import (
    astar,
    navigable_cells,
    path_distances,
    path_from,
    walked_cells,
)
from forestmap_assets.core.exploration.planner import plan_next_vantage
from forestmap_assets.core.exploration.planner_thesis import preferred_heading, zone_of
from forestmap_assets.core.exploration.surface import observed_surface, surface_points
from forestmap_assets.core.exploration.visibility import (
    stem_visibility,
    visible_cells,
    visible_stems,
)
from forestmap_assets.core.features.elevation import ElevationGrid
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.params.men import ExplorationConfig


def _grid(bounds=(0.0, 10.0, 0.0, 10.0), cell=0.5, z_range=(-0.5, 3.0), dz=0.1, plot=None):
    return ExplorationGrid.from_bounds(bounds, cell, z_range, dz=dz, plot=plot)


def _cells_points(grid, ix, iy, heights, n=5):
    """n points per height at the centres of cells (ix, iy)."""
    xy = grid.cell_xy(np.atleast_1d(ix), np.atleast_1d(iy))
    pts = [np.column_stack([xy, np.full(len(xy), h)]) for h in np.atleast_1d(heights)]
    return np.repeat(np.concatenate(pts), n, axis=0)


# ---- V19, V20 ----------------------------------------------------------------------------------
def test_v19_grid_indexing():
    g = ExplorationGrid.from_bounds((-30.0, 5.0, -10.0, 10.0), 0.2, (-2.0, 3.0), n_z=25)
    assert (g.nx, g.ny, g.nz) == (175, 100, 25) and g.dz == pytest.approx(0.2)
    idx, ok = g.flat_index([-30 + 0.1], [-10 + 0.1], [-2 + 0.1])
    assert ok[0] and idx[0] == 0
    idx, ok = g.flat_index([-30 + 2.1 * 0.2], [-10 + 3.5 * 0.2], [-2 + 1.5 * 0.2])
    assert idx[0] == 2 * 100 * 25 + 3 * 25 + 1
    g.add_points(
        np.array([[-29.9, -9.9, -1.9], [-29.9, -9.9, -1.95], [100.0, 0.0, 0.0], [-29.9, -9.9, 9.0]])
    )
    assert g.counts[0] == 2 and g.counts.sum() == 2  # outside B dropped; above the top -> ``above``
    assert g.above[0, 0] == 1 and g.points[0, 0] == 3


def test_v20_classification_thesis_heights_and_sticky_obstacles():
    # thesis form: absolute heights, ground ~ -1.6 m, obstacle above -1.3 m, ceiling cut at 1.2 m
    g = ExplorationGrid.from_bounds((0.0, 4.0, 0.0, 4.0), 0.2, (-2.0, 3.0), n_z=25)
    kw = dict(obstacle_min_m=-1.3, clearance_m=1.2, min_obstacle_points=1)
    floor = _cells_points(g, np.arange(10), np.zeros(10, int), -1.6)
    g.add_points(floor)
    wall = _cells_points(g, [5], [5], np.arange(-1.6, 1.0, 0.1))
    g.add_points(wall)
    c = classify_cells(g, **kw)
    assert (c[np.arange(10), 0] == GROUND).all()
    assert c[5, 5] == OBSTACLE
    assert (c == UNMAPPED).sum() == c.size - 11
    # a later scan with only floor points in the wall cell: once O, stays O (Eqs. 6.1-6.2)
    g.add_points(_cells_points(g, [5], [5], -1.6, n=50))
    assert classify_cells(g, **kw)[5, 5] == OBSTACLE
    # a ceiling above the cut does not make a hallway cell an obstacle
    g.add_points(_cells_points(g, [1], [0], 2.4))
    assert classify_cells(g, **kw)[1, 0] == GROUND


def test_forest_heights_relative_to_local_ground_on_a_slope():
    # a 20 % slope: 2 m of relief over the grid; thresholds relative to the ground, not to a height
    g = _grid()
    xc, yc = g.centres()
    ground = 0.2 * xc[:, None] + 0.0 * yc[None, :]
    elev = ElevationGrid(
        z=np.repeat((0.2 * (np.arange(100) * 0.1 + 0.05))[None, :], 100, axis=0),
        x0=0.0,
        y0=0.0,
        cell_m=0.1,
    )
    g.ground_z = local_ground(elev, g, window_m=0.5)
    assert np.abs(g.ground_z - ground).max() < 0.12
    ix, iy = np.meshgrid(np.arange(g.nx), np.arange(g.ny), indexing="ij")
    pts = np.column_stack([g.cell_xy(ix.ravel(), iy.ravel()), ground.ravel() + 0.05])
    g.add_points(pts)
    bush = g.cell_xy([10], [10])[0]
    g.add_points(np.array([[bush[0], bush[1], 0.2 * bush[0] + h] for h in (0.4, 0.6, 0.8, 1.0)]))
    c = classify_cells(g)
    assert c[10, 10] == OBSTACLE and (c == OBSTACLE).sum() == 1
    assert (c == GROUND).sum() == c.size - 1
    # the thesis's fixed-height rule would call the upper half of the slope obstacles
    flat = ExplorationGrid.from_bounds((0.0, 10.0, 0.0, 10.0), 0.5, (-0.5, 3.0), dz=0.1)
    flat.add_points(np.repeat(pts, 5, axis=0))
    assert (classify_cells(flat) == OBSTACLE).sum() > 0.3 * c.size


def test_local_ground_ignores_a_bush_and_fills_gaps():
    g = _grid()
    z = np.full((100, 100), -1.0)
    z[40:50, 40:50] = 0.0  # a bush whose lowest hit is 1 m above the ground
    z[:, 80:] = np.nan  # no data on the east side
    elev = ElevationGrid(z=z, x0=0.0, y0=0.0, cell_m=0.1)
    gz = local_ground(elev, g, window_m=1.0)
    assert np.allclose(gz, -1.0)
    empty = ElevationGrid(z=np.full((1, 1), np.nan), x0=0.0, y0=0.0, cell_m=0.1)
    assert np.allclose(local_ground(empty, g, default_z=-1.5), -1.5)


def test_frontier_and_coverage_figures():
    g = _grid(plot=[[0, 0], [10, 0], [10, 10], [0, 10]])
    ix, iy = np.meshgrid(np.arange(10), np.arange(g.ny), indexing="ij")  # west half mapped
    g.add_points(np.column_stack([g.cell_xy(ix.ravel(), iy.ravel()), np.zeros(ix.size)]))
    c = classify_cells(g)
    fr = frontier_cells(c, g.in_plot)
    assert fr[9].all() and fr.sum() == g.ny
    cov = coverage_figures(g, c)
    assert cov["coverage"] == pytest.approx(0.5) and cov["unmapped_share"] == pytest.approx(0.5)
    assert cov["median_points_per_m2"] == pytest.approx(1 / 0.25)
    # a frontier against cells outside the plot is no frontier
    inside = np.zeros(g.shape, bool)
    inside[:10] = True
    assert not frontier_cells(c, inside).any()


# ---- paths ----------------------------------------------------------------------------------
def test_astar_matches_dijkstra_and_walks_around_a_wall():
    nav = np.ones((30, 20), bool)
    nav[15, :17] = False  # a wall with a gap at the top
    d, pred = path_distances(nav, (2, 2), 0.5)
    path, length = astar(nav, (2, 2), (28, 2), 0.5)
    assert length == pytest.approx(d[28, 2])
    assert nav[path[:, 0], path[:, 1]].all() and (path[:, 1] >= 17).any()
    steps = np.abs(np.diff(path, axis=0))
    assert steps.max() == 1 and (steps.sum(1) >= 1).all()
    p2 = path_from(pred, (28, 2), nav.shape)
    seg = np.hypot(*np.diff(p2, axis=0).T).sum() * 0.5
    assert seg == pytest.approx(d[28, 2]) and tuple(p2[0]) == (2, 2)
    nav[15, :] = False
    d, _ = path_distances(nav, (2, 2), 0.5)
    assert np.isinf(d[28, 2]) and astar(nav, (2, 2), (28, 2))[1] == np.inf


def test_no_corner_cutting_and_clearance():
    nav = np.ones((5, 5), bool)
    nav[1, 2] = nav[2, 1] = False
    path, length = astar(nav, (1, 1), (2, 2), 1.0)
    assert length > np.sqrt(2) + 1e-9  # the diagonal between two blocked cells is not allowed
    classes = np.full((20, 20), GROUND, np.uint8)
    classes[10, 10] = OBSTACLE
    nav = navigable_cells(classes, 0.25, obstacle_clearance_m=0.5)
    assert not nav[10, 12] and nav[10, 13] and nav[0, 0]


# ---- visibility -------------------------------------------------------------------------------
def test_visible_cells_respect_trunks_obstacles_and_blind_disc():
    g = _grid((-10.0, 10.0, -10.0, 10.0), 0.25)
    occ = np.zeros(g.shape, bool)
    stems = np.array([[3.0, 0.0, 0.3]])
    vis = visible_cells(
        g, [[0.0, 0.0]], occ, stems, radius_m=9.0, blind_radius_m=1.5, n_rays=1440
    )[0]
    vis = vis.reshape(g.shape)

    def seen(x, y):
        ix, iy, _ = g.cell_of(x, y)
        return bool(vis[ix, iy])

    assert not seen(0.2, 0.1) and not seen(1.0, 0.0)  # the blind disc under the scanner
    assert seen(2.0, 0.0) and seen(0.0, 5.0) and seen(-6.0, -3.0)
    assert not seen(6.0, 0.0) and not seen(8.0, 0.3)  # in the trunk's shadow
    assert seen(6.0, 2.5) and not seen(9.5, 0.0)  # beside the shadow; beyond the radius
    # an obstacle cell stops the ray and is itself seen
    ox, oy, _ = g.cell_of(0.0, 4.0)
    occ[ox, oy] = True
    vis2 = visible_cells(
        g, [[0.0, 0.0]], occ, stems, radius_m=9.0, blind_radius_m=1.5, n_rays=1440
    )[0]
    vis2 = vis2.reshape(g.shape)
    assert vis2[ox, oy] and not vis2[g.cell_of(0.0, 7.0)[0], g.cell_of(0.0, 7.0)[1]]


def test_visible_stems_hidden_by_a_nearer_trunk_and_range():
    stems = np.array([[3.0, 0.0, 0.4], [6.0, 0.0, 0.15], [6.0, 3.0, 0.15], [20.0, 0.0, 0.3]])
    vis = visible_stems([[0.0, 0.0], [6.0, -3.0]], stems, range_m=15.0)
    assert vis[0].tolist() == [True, False, True, False]  # (6, 0) behind (3, 0); (20, 0) too far
    assert vis[1].tolist() == [True, True, False, True]  # (6, 3) behind (6, 0); (20, 0) at 14.3 m
    assert not visible_stems([[0.0, 0.0]], stems, range_m=2.0).any()
    # too few pixels across a thin far stem for the pipeline to find it
    narrow = visible_stems([[0.0, 0.0]], stems, range_m=15.0, min_width_rad=0.1)[0]
    assert narrow.tolist() == [True, False, False, False]
    cfg = ExplorationConfig(angular_step_deg=0.44, stem_min_pixels=4)
    assert stem_visibility(cfg)["min_width_rad"] == pytest.approx(np.radians(0.44) * 4)


# ---- V21 heading, zones -----------------------------------------------------------------------
def test_v21_preferred_heading():
    cur = np.array([0.0, 0.0])
    h, fu, fw = preferred_heading(cur, [[3.0, 4.0]], np.zeros((0, 2)), 10.0)
    assert np.allclose(h / np.linalg.norm(h), [0.6, 0.8]) and np.allclose(fw, 0)
    h, _, _ = preferred_heading(
        cur, [[3.0, 0.0], [-3.0, 0.0], [0.0, 2.0], [0.0, -2.0]], np.zeros((0, 2)), 10.0
    )
    assert np.allclose(h, 0.0, atol=1e-12)
    d, diag = 2.0, 10.0
    h, fu, fw = preferred_heading(cur, np.zeros((0, 2)), [[d, 0.0]], diag, w_wall=0.5)
    assert np.allclose(fw, [-0.5 * diag**2 / d**2, 0.0])  # away from the wall, W_w D^2 / d^2
    # opposite attraction and repulsion: the tangential force (F_w,y, -F_w,x) is added
    h, fu, fw = preferred_heading(
        cur, [[5.0, 0.1]], [[1.0, -0.01]], 10.0, tangential_trigger_deg=150
    )
    ft = h - fu - fw
    assert np.allclose(ft, [fw[1], -fw[0]]) and abs(ft @ fw) < 1e-9 and np.linalg.norm(ft) > 0


def test_zones():
    assert zone_of(np.radians([0.0, 22.0, 23.0, 90.0, 180.0, 337.0, -10.0])).tolist() == [
        0,
        0,
        1,
        2,
        4,
        7,
        0,
    ]


# ---- observed surface -------------------------------------------------------------------------
def _ground_scan(step_deg: float, height=1.5, max_range=20.0, post=None):
    az = np.arange(-180.0, 180.0, step_deg)
    el = np.arange(-2.0, -60.0, -step_deg)
    a, e = np.meshgrid(np.radians(az), np.radians(el))
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)
    r = np.where(d[..., 2] < 0, height / -d[..., 2], np.nan)
    if post is not None:  # a box post (x0, x1, y0, y1) from the ground to above the scanner
        x0, x1, y0, y1 = post
        with np.errstate(divide="ignore", invalid="ignore"):
            t = x0 / d[..., 0]
        p = t[..., None] * d
        hit = (t > 0) & (p[..., 1] >= y0) & (p[..., 1] <= y1) & (p[..., 2] >= -height)
        r = np.where(hit & (t < r), t, r)
    r = np.where(r < max_range, r, np.nan)
    return RangeImage(r.astype(np.float32), az, el)


def test_observed_surface_fills_between_beams_but_not_across_occlusions():
    image = _ground_scan(1.0, post=(4.0, 4.3, -0.5, 0.5))
    ob = detect_occlusions(image)
    filled = observed_surface(image, ob.tilt_pair, ob.pan_pair, wrap=ob.wrap)
    bare = observed_surface(
        image, np.ones_like(ob.tilt_pair), np.ones_like(ob.pan_pair), wrap=ob.wrap
    )
    assert filled["n_points"].sum() == bare["n_points"].sum() == int(image.valid.sum())
    assert bare["n_filled"].sum() == 0 and filled["n_filled"].sum() > 0
    g_f, g_b = (
        ExplorationGrid.from_bounds((-12, 12, -12, 12), 0.25, (-3.0, 3.0), dz=0.1)
        for _ in range(2)
    )
    for g, s in ((g_f, filled), (g_b, bare)):
        pts, n_p, n_f = surface_points(s, 0.05, (0.0, 0.0, 1.5, 0.0), max_range_m=11.0)
        g.add_points(pts, n_p + n_f, measured=n_p)
    ring = np.hypot(*np.meshgrid(*g_f.centres(), indexing="ij"))
    band = (ring > 7.0) & (ring < 10.0)
    seen_f = (g_f.hist.sum(2) > 0)[band].mean()
    seen_b = (g_b.hist.sum(2) > 0)[band].mean()
    assert seen_b < 0.6 < 0.9 < seen_f  # rings of ground hits 0.6-0.9 m apart at 1 deg steps
    shadow = g_f.cell_of(7.0, 0.0)
    assert g_f.hist[shadow[0], shadow[1]].sum() == 0  # behind the post stays unseen


# ---- planning -----------------------------------------------------------------------------------
def _half_mapped_scene(n_stems=14, seed=3):
    """A 20 m plot mapped west of x = 8 m from a scan at (3, 10), stems scattered."""
    rng = np.random.default_rng(seed)
    g = ExplorationGrid.from_bounds(
        (0.0, 20.0, 0.0, 20.0), 0.25, (-0.5, 3.0), dz=0.1, plot=[[0, 0], [20, 0], [20, 20], [0, 20]]
    )
    g.ground_z = np.zeros(g.shape)
    xc, _ = g.centres()
    ix, iy = np.meshgrid(np.flatnonzero(xc < 8.0), np.arange(g.ny), indexing="ij")
    g.add_points(np.column_stack([g.cell_xy(ix.ravel(), iy.ravel()), np.full(ix.size, 0.02)]))
    stems = np.column_stack(
        [rng.uniform(1, 19, n_stems), rng.uniform(1, 19, n_stems), rng.uniform(0.1, 0.2, n_stems)]
    )
    stems = stems[np.hypot(stems[:, 0] - 3, stems[:, 1] - 10) > 2.5]
    return g, stems


def test_plan_ranks_reachable_frontier_positions_with_overlap():
    g, stems = _half_mapped_scene()
    cfg = ExplorationConfig(min_common_stems=3, n_rays=360)
    plan = plan_next_vantage(g, stems, np.array([[3.0, 10.0]]), ["T"], cfg)
    props = plan.proposals
    assert list(props.columns) == PROPOSAL_COLUMNS and len(props) > 5
    assert props["rank"].tolist() == list(range(1, len(props) + 1))
    top = props[props["feasible"]]
    assert len(top) and (top["common_stems"] >= 3).all() and (top["reference_scan"] == "T").all()
    assert (top["score"].diff().dropna() <= 1e-9).all()
    best = top.iloc[0]
    assert 6.5 <= best.x <= 9.0 and best.expected_new_m2 > 20  # on the frontier, seeing the east
    assert (
        np.isfinite(top["path_m"]).all() and best.path_m >= np.hypot(best.x - 3, best.y - 10) - 0.5
    )
    path = plan.paths[1]
    assert (
        np.hypot(*(path[0] - [3.0, 10.0])) < 0.3 and np.hypot(*(path[-1] - [best.x, best.y])) < 1e-9
    )
    assert plan.coverage["coverage"] == pytest.approx(0.4, abs=0.02)
    # an impossible overlap requirement leaves no feasible position
    strict = plan_next_vantage(
        g,
        stems,
        np.array([[3.0, 10.0]]),
        ["T"],
        ExplorationConfig(min_common_stems=100, n_rays=360),
    )
    assert not strict.proposals["feasible"].any()
    area = plan_next_vantage(
        g,
        stems,
        np.array([[3.0, 10.0]]),
        ["T"],
        ExplorationConfig(overlap_rule="area", min_overlap=0.5, n_rays=360),
    )
    ok = area.proposals[area.proposals["feasible"]]
    assert len(ok) and (ok["overlap_share"] >= 0.5).all()


def test_stems_without_dbh_attract_a_second_look():
    g, stems = _half_mapped_scene()
    cur = np.array([[3.0, 10.0]])
    base = plan_next_vantage(
        g, stems, cur, ["T"], ExplorationConfig(min_common_stems=3, n_rays=360)
    )
    # the stem farthest from the best plain proposal has no DBH yet
    b0 = base.proposals.iloc[0]
    far = int(np.argmax(np.hypot(stems[:, 0] - b0.x, stems[:, 1] - b0.y)))
    incomplete = np.zeros(len(stems), bool)
    incomplete[far] = True
    cfg = ExplorationConfig(min_common_stems=3, n_rays=360, stem_bonus_m2=500.0)
    plan = plan_next_vantage(g, stems, cur, ["T"], cfg, incomplete=incomplete)
    best = plan.proposals.iloc[0]
    assert best.incomplete_stems == 1 and b0.incomplete_stems == 0
    assert best.expected_gain_m2 == pytest.approx(best.expected_new_m2 + 500.0)
    seen = visible_stems([[best.x, best.y]], stems, range_m=cfg.stem_range_m)[0]
    assert seen[far]


def test_v22_thesis_strategy():
    g, stems = _half_mapped_scene()
    cfg = ExplorationConfig(
        strategy="thesis", overlap_rule="area", min_overlap=0.5, coverage_radius_m=8.0, n_rays=360
    )
    plan = plan_next_vantage(g, stems, np.array([[3.0, 10.0]]), ["T"], cfg)
    props = plan.proposals
    assert 1 <= len(props) <= 10 and plan.zone is not None
    cur = np.array([3.0, 10.0])
    # every candidate is a reachable frontier cell in the selected zone (chosen one may be shrunk)
    cand = props.iloc[1:]
    assert plan.frontier[cand["ix"], cand["iy"]].all()
    ang = np.arctan2(cand["y"] - cur[1], cand["x"] - cur[0])
    assert (zone_of(ang) == plan.zone).all()
    chosen = props.iloc[0]
    path = plan.paths[1]
    assert np.hypot(*(path[-1] - [chosen.x, chosen.y])) < 1e-9  # the vantage lies on the A* path
    assert chosen.overlap_share >= 0.5
    # the next cell farther along the full path to the candidate has overlap < 50 %
    full, _ = astar(
        navigable_cells(plan.classes, g.cell_m, walked=walked_cells(g, cur[None], 1.8)),
        plan.current,
        _candidate_of(plan, cfg, g),
        g.cell_m,
    )
    k = len(path)
    if k < len(full):
        nxt = evaluate_positions(
            g,
            plan.classes,
            g.cell_xy(full[k : k + 1, 0], full[k : k + 1, 1]),
            stems,
            cur[None],
            ["T"],
            cfg,
        )
        assert nxt["overlap_share"].iloc[0] < 0.5


def _candidate_of(plan, cfg, g):
    """The thesis candidate the chosen vantage was shrunk from (recomputed as the planner does)."""
    cur = g.cell_xy(*plan.current)[0]
    walked = walked_cells(g, cur[None], cfg.blind_radius_m)
    nav = navigable_cells(
        plan.classes, g.cell_m, obstacle_clearance_m=cfg.obstacle_clearance_m, walked=walked
    )
    dist, _ = path_distances(nav, plan.current, g.cell_m)
    fc = np.argwhere(plan.frontier & np.isfinite(dist))
    fxy = g.cell_xy(fc[:, 0], fc[:, 1])
    fz = zone_of(np.arctan2(fxy[:, 1] - cur[1], fxy[:, 0] - cur[0]))
    zc = fc[fz == plan.zone]
    top = zc[np.argsort(-dist[zc[:, 0], zc[:, 1]], kind="stable")[:10]]
    ang = np.arctan2(*(g.cell_xy(top[:, 0], top[:, 1]) - cur)[:, ::-1].T)
    diff = np.abs((ang - plan.zone * np.pi / 4 + np.pi) % (2 * np.pi) - np.pi)
    return tuple(top[np.argsort(diff, kind="stable")[0]])


# ---- Dagster assets ----------------------------------------------------------------------
@pytest.mark.slow
def test_assets_occlusion_and_next_vantage_points(tmp_path):
    from dagster import Definitions, materialize
    from upath import UPath

    from forestmap_assets.access import load_asset
    from forestmap_assets.assets import campaign_assets
    from forestmap_assets.assets.common import asset_key
    from forestmap_assets.assets.exploration import exploration_assets
    from forestmap_assets.core.features.elevation import elevation_to_table, merge_elevation
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.io.store import (
        ParquetStore,
        default_store_url,
        write_bundle_atomic,
        write_table_atomic,
    )
    from forestmap_assets.sim import simulate_campaign

    folder = simulate_campaign(
        tmp_path / "plot",
        scans=1,
        trees=10,
        plot_size=16.0,
        seed=2,
        resolution="quarter",
        no_prior=True,
        write_labels=False,
    )
    campaign = load_campaign(folder)
    assets = campaign_assets(campaign)
    if not any(
        asset_key(campaign, "occlusion_boundaries") in getattr(a, "keys", ()) for a in assets
    ):
        assets = assets + exploration_assets(campaign)
    defs = Definitions(assets=assets, resources={"io_manager": ParquetStore()})
    from forestmap_assets.orchestration.instance import get_instance
    from forestmap_assets.orchestration.runner import QUIET

    instance = get_instance()
    instance.add_dynamic_partitions(f"{campaign.key}__scans", ["T"])
    res = materialize(
        list(defs.assets),
        instance=instance,
        partition_key="T",
        resources=defs.resources,
        selection=[
            asset_key(campaign, s)
            for s in ("range_images", "elevation_maps", "occlusion_boundaries")
        ],
        run_config=QUIET,
    )
    assert res.success
    occ = load_asset("occlusion_boundaries", campaign=campaign, scan="T")
    assert set(occ) == {"boundaries", "surface", "info"} and len(occ["boundaries"]) > 100
    assert occ["surface"]["n_filled"].sum() > 0
    # the map the pipeline would have made of this one scan (truth: stems, pose 0)
    truth = pd.read_csv(folder / "truth" / "trees.csv")
    tree_list = truth.assign(n_scans=1, n_cylinders=1, visible_length_m=2.0)[
        ["tree_id", "x", "y", "z", "dbh_m", "n_scans", "n_cylinders", "visible_length_m"]
    ]
    elev = merge_elevation(
        [(load_asset("elevation_maps", campaign=campaign, scan="T"), (0, 0, 0, 0))], 0.1
    )
    scans = pd.DataFrame(
        {
            "scan": ["T"],
            "x": [0.0],
            "y": [0.0],
            "z": [0.0],
            "heading_deg": [0.0],
            "sd_x": [0.0],
            "sd_y": [0.0],
            "sd_z": [0.0],
            "sd_heading_deg": [0.0],
            "registered": [True],
        }
    )
    base = UPath(default_store_url()) / campaign.key
    write_bundle_atomic(
        {
            "cylinders": pd.DataFrame({"scan": ["T"], "x0": [0.0]}),
            "elevation": elevation_to_table(elev),
            "scans": scans,
        },
        base / "integrated_map.bundle",
    )
    write_table_atomic(tree_list, base / "tree_list.parquet")
    res = materialize(
        list(defs.assets),
        instance=instance,
        resources=defs.resources,
        selection=[asset_key(campaign, "next_vantage_points")],
        run_config=QUIET,
    )
    assert res.success
    out = load_asset("next_vantage_points", campaign=campaign)
    assert set(out) == {"proposals", "paths", "coverage", "cells", "picture"}
    assert bytes(out["picture"]["png"].iloc[0])[:4] == b"\x89PNG"  # the report shows it
    cov = out["coverage"]["coverage"].iloc[0]
    assert 0.2 < cov < 1.0, cov
    props = out["proposals"]
    assert len(props) and props["feasible"].iloc[0] and props["common_stems"].iloc[0] >= 5
    assert set(out["cells"]["cell_class"]) == {"unmapped", "ground", "obstacle"}
    mats = [e for e in res.get_asset_materialization_events()]
    meta = mats[-1].materialization.metadata
    assert "picture" in meta and "coverage" in meta and "proposals" in meta


def test_config_from_a_parameter_section():
    from dataclasses import asdict

    from forestmap_assets.params import Params

    section = getattr(Params(), "exploration", None)
    if section is not None:  # the parameter model's defaults are the planner's
        assert asdict(ExplorationConfig.from_params(section)) == asdict(ExplorationConfig())
    values = {"cell_m": 0.5, "plot": [[0, 0], [4, 0], [4, 4]], "other": 1}
    cfg = ExplorationConfig.from_params(values)
    assert cfg.cell_m == 0.5 and cfg.plot == ((0.0, 0.0), (4.0, 0.0), (4.0, 4.0))
    with pytest.raises(TypeError):
        ExplorationConfig(unknown=1)
