"""Exports beyond the CSVs: registered point cloud (LAZ, PLY), GeoJSON trees, map, report.

The asset store is filled by hand with small, known tables (no pipeline run), so every number
in the exports can be checked against what went in.
"""

from __future__ import annotations

import json
import re

import laspy
import numpy as np
import pandas as pd
import pytest
from helpers.campaign_files import write_campaign
from upath import UPath

from forestmap_assets.core.features.elevation import ElevationGrid, elevation_to_table
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.core.geometry import transform_points
from forestmap_assets.core.mapping.point_cloud import registered_cloud, voxel_keep
from forestmap_assets.io.campaign import load_campaign
from forestmap_assets.io.store import default_store_url, write_bundle_atomic, write_table_atomic
from forestmap_assets.orchestration.timings import stage_timings
from forestmap_assets.outputs.exports import (
    EXPORTS,
    campaign_cloud,
    read_ply,
    write_exports,
    write_geojson,
    write_laz,
    write_ply,
)
from forestmap_assets.outputs.progress import Progress

POSES = pd.DataFrame(
    {
        "scan": ["T", "S", "R"],
        "x": [0.0, 4.0, np.nan],
        "y": [0.0, -1.0, np.nan],
        "z": [0.0, 0.3, np.nan],
        "heading_deg": [0.0, 90.0, np.nan],
        "sd_x": [0.0, 0.02, np.nan],
        "sd_y": [0.0, 0.02, np.nan],
        "sd_z": [0.0, 0.1, np.nan],
        "sd_heading_deg": [0.0, 0.1, np.nan],
        "registered": [True, True, False],
    }
)


# ---- point cloud -------------------------------------------------------------------------


def test_voxel_keep_keeps_one_measured_point_per_voxel():
    pts = np.array(
        [
            [0.01, 0.01, 0.01],
            [0.06, 0.03, 0.03],
            [0.08, 0.05, 0.05],  # voxel (0,0,0): centroid (0.05, 0.03, 0.03)
            [0.15, 0.05, 0.05],  # voxel (1,0,0)
            [np.nan, 0.0, 0.0],
        ]
    )
    keep = voxel_keep(pts, 0.1)
    assert keep.tolist() == [1, 3]  # the point nearest its voxel's centroid; NaN left out
    # the grid is anchored at the frame origin, not at the cloud's corner: shifted by half a
    # voxel, the same three points fall in three voxels
    assert len(voxel_keep(pts[:3] + 0.05, 0.1)) == 3
    assert voxel_keep(pts, 0.0).tolist() == [0, 1, 2, 3]
    rng = np.random.default_rng(0)
    cloud = rng.uniform(0, 1, (5000, 3))
    kept = cloud[voxel_keep(cloud, 0.25)]
    assert len(kept) == 64
    assert len(np.unique(np.floor(kept / 0.25), axis=0)) == 64


def test_registered_cloud_places_scans_with_their_poses():
    rng = np.random.default_rng(1)
    t = pd.DataFrame(rng.uniform(-2, 2, (300, 3)), columns=["x", "y", "z"]).assign(r=1, g=2, b=3)
    s = pd.DataFrame(rng.uniform(-2, 2, (300, 3)), columns=["x", "y", "z"]).assign(r=4, g=5, b=6)
    r = pd.DataFrame(rng.uniform(-2, 2, (50, 3)), columns=["x", "y", "z"]).assign(r=7, g=8, b=9)
    cloud = registered_cloud({"T": t, "S": s, "R": r}, POSES, 0.0, scan_ids=["T", "S", "R"])
    assert list(cloud.columns) == ["x", "y", "z", "scan", "r", "g", "b"]
    assert set(cloud["scan"]) == {0, 1}  # R is not registered
    got = cloud[cloud["scan"] == 1][["x", "y", "z"]].to_numpy()
    want = transform_points(s[["x", "y", "z"]].to_numpy(), (4.0, -1.0, 0.3, 90.0))
    np.testing.assert_allclose(got, want)
    assert (cloud.loc[cloud["scan"] == 1, "r"] == 4).all()
    thin = registered_cloud({"T": t, "S": s}, POSES, 0.5, scan_ids=["T", "S", "R"])
    assert len(thin) == len(np.unique(np.floor(thin[["x", "y", "z"]].to_numpy() / 0.5), axis=0))
    assert len(thin) < len(cloud)


def test_registered_cloud_is_the_same_in_threads():
    """Scans thinned in threads give the cloud of one thread, row for row; points without a
    finite coordinate are left out; float32 columns are placed like float64 ones."""
    rng = np.random.default_rng(3)
    t = pd.DataFrame(rng.uniform(-3, 3, (4000, 3)).astype(np.float32), columns=["x", "y", "z"])
    s = pd.DataFrame(rng.uniform(-3, 3, (3000, 3)), columns=["x", "y", "z"]).assign(intensity=0.5)
    t.loc[7, "y"] = np.nan
    t = t.assign(intensity=rng.uniform(0, 1, len(t)).astype(np.float32))
    one = registered_cloud({"T": t, "S": s}, POSES, 0.3, scan_ids=["T", "S", "R"], threads=1)
    two = registered_cloud({"T": t, "S": s}, POSES, 0.3, scan_ids=["T", "S", "R"], threads=2)
    pd.testing.assert_frame_equal(one, two)
    assert one[["x", "y", "z"]].notna().all().all()
    every = registered_cloud({"S": s}, POSES, 0.0, scan_ids=["T", "S", "R"], threads=2)
    np.testing.assert_allclose(every[["x", "y", "z"]].to_numpy(),
                               transform_points(s[["x", "y", "z"]].to_numpy(), (4.0, -1.0, 0.3, 90.0)),
                               rtol=0, atol=1e-12)


def test_laz_and_ply_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    n = 500
    cloud = pd.DataFrame(
        {
            "x": rng.uniform(-20, 20, n),
            "y": rng.uniform(-20, 20, n),
            "z": rng.uniform(-2, 9, n),
            "scan": rng.integers(0, 3, n).astype(np.uint16),
            "intensity": rng.uniform(0, 2, n),
            "r": rng.integers(0, 256, n).astype(np.uint8),
            "g": 7,
            "b": 200,
        }
    )
    ids = ["T", "S", "R"]
    las = laspy.read(write_laz(cloud, tmp_path / "c.laz", ids, "note"))
    np.testing.assert_allclose(las.x, cloud["x"], atol=0.0006)
    np.testing.assert_allclose(las.z, cloud["z"], atol=0.0006)
    assert np.array_equal(np.asarray(las.scan), cloud["scan"].to_numpy())
    assert np.array_equal(np.asarray(las.point_source_id), cloud["scan"].to_numpy())
    assert np.array_equal(np.asarray(las.red) // 257, cloud["r"].to_numpy())
    vlr = next(v for v in las.header.vlrs if v.user_id == "forestmap")
    assert json.loads(vlr.record_data)["scan_ids"] == ids
    assert (tmp_path / "c.laz").read_bytes()[:4] == b"LASF"

    table, comments = read_ply(write_ply(cloud, tmp_path / "c.ply", ids, "note"))
    assert list(table.columns) == ["x", "y", "z", "red", "green", "blue", "intensity", "scan"]
    np.testing.assert_array_equal(table["x"], cloud["x"])
    np.testing.assert_array_equal(table["scan"], cloud["scan"])
    assert "scan 1 S" in comments


def test_geojson_tree_points(tmp_path):
    root = write_campaign(tmp_path / "c")
    campaign = load_campaign(root)
    trees = pd.DataFrame(
        {
            "tree_id": [1, 2],
            "x": [1.5, -2.0],
            "y": [0.5, 3.0],
            "z": [-1.4, -1.6],
            "dbh_m": [0.31, np.nan],
            "n_scans": [2, 1],
            "n_cylinders": [3, 1],
            "visible_length_m": [4.2, 1.1],
        }
    )
    doc = json.loads(write_geojson(trees, tmp_path / "trees.geojson", campaign).read_text())
    assert doc["type"] == "FeatureCollection"
    assert doc["forestmap"]["frame"].endswith("scan T")
    f0, f1 = doc["features"]
    assert f0["geometry"] == {"type": "Point", "coordinates": [1.5, 0.5, -1.4]}
    assert f0["properties"]["dbh_m"] == 0.31 and f1["properties"]["dbh_m"] is None
    assert f1["properties"]["n_scans"] == 1


# ---- everything, from a hand-filled store ----------------------------------------------------


def _store(campaign, name, obj, scan=None):
    base = UPath(default_store_url()) / campaign.key / name
    stem = base / scan if scan else base
    if isinstance(obj, dict):
        write_bundle_atomic(obj, stem.with_name(stem.name + ".bundle"))
    else:
        write_table_atomic(obj, stem.with_name(stem.name + ".parquet"))


@pytest.fixture
def filled(tmp_path):
    root = write_campaign(tmp_path / "camp", scans=("T", "S", "R"))
    campaign = load_campaign(root)
    for sid, seed in (("T", 0), ("S", 1), ("R", 2)):
        rng = np.random.default_rng(seed)
        rows, cols = 30, 120
        az, el = np.linspace(-60, 60, cols), np.linspace(20, -20, rows)
        rng_m = (6 + rng.normal(0, 0.01, (rows, cols))).astype(np.float32)
        rgb = np.full((rows, cols, 3), 40 * (seed + 1), np.uint8)
        _store(campaign, "range_images", RangeImage(rng_m, az, el, rgb=rgb).to_table(), scan=sid)
    regs = pd.DataFrame(
        {
            "scan": ["S", "R"],
            "reference": ["T", "T"],
            "dx": [4.0, np.nan],
            "dy": [-1.0, np.nan],
            "dz": [0.3, np.nan],
            "dheading_deg": [90.0, np.nan],
            "sd_x": [0.02, np.nan],
            "sd_y": [0.02, np.nan],
            "sd_z": [0.1, np.nan],
            "sd_heading_deg": [0.1, np.nan],
            "peak_dx": [4.0, np.nan],
            "peak_dy": [-1.0, np.nan],
            "peak_dz": [0.3, np.nan],
            "peak_dheading_deg": [90.0, np.nan],
            "log_score": [-1000.0, np.nan],
            "n_points": [400, 0],
            "seconds": [1.5, 0.1],
            "status": ["accepted", "failed"],
            "reason": ["", "empty sub-map"],
        }
    )
    _store(
        campaign,
        "pairwise_registrations",
        {
            "registrations": regs,
            "levels": pd.DataFrame({"level": [0]}),
            "hypotheses": pd.DataFrame({"scan": ["S"]}),
        },
    )
    _store(campaign, "refined_registrations",  # what feeds the map: here no pair was refined
           {"registrations": regs.assign(refined=False, refine_method=["point_to_plane", ""]),
            "refinements": pd.DataFrame({"scan": ["S"], "reference": ["T"], "method": ["point_to_plane"],
                                         "used": ["branch_and_bound"], "reason": ["fit not better"]})})
    residuals = pd.DataFrame(
        {
            "scan": ["S"],
            "reference": ["T"],
            "ex": [0.0],
            "ey": [0.0],
            "ez": [0.0],
            "eheading_deg": [0.0],
            "rx": [0.0],
            "ry": [0.0],
            "rz": [0.0],
            "rheading": [0.0],
            "verdict": ["ok"],
        }
    )
    links = regs.iloc[:1].assign(status="admitted", role="tree", step=1)
    _store(campaign, "optimal_map", {"poses": POSES, "links": links, "residuals": residuals})
    _store(campaign, "residual_checks", residuals)
    trees = pd.DataFrame(
        {
            "tree_id": [1, 2, 3],
            "x": [1.0, 3.0, -2.0],
            "y": [2.0, -3.0, 1.0],
            "z": [-1.5, -1.4, -1.6],
            "dbh_m": [0.25, 0.32, np.nan],
            "n_scans": [2, 1, 1],
            "n_cylinders": [3, 1, 1],
            "visible_length_m": [5.0, 2.0, 0.6],
        }
    )
    _store(campaign, "tree_list", trees)
    cylinders = pd.DataFrame(
        {
            "scan": ["T", "S", "S"],
            "cylinder_id": [0, 0, 1],
            "x0": [1.0, 1.02, 3.0],
            "y0": [2.0, 2.0, -3.0],
            "z0": [-1.2, -1.0, -1.1],
            "x1": [1.0, 1.0, 3.0],
            "y1": [2.0, 2.0, -3.0],
            "z1": [3.0, 2.0, 1.0],
            "radius_m": [0.125, 0.13, 0.16],
            "n_circles": [40, 25, 20],
        }
    )
    xs = np.arange(-8, 8, 0.1)
    grid = ElevationGrid(np.tile(-1.5 + 0.02 * xs, (len(xs), 1)), -8.0, -8.0, 0.1)
    _store(
        campaign,
        "integrated_map",
        {"cylinders": cylinders, "elevation": elevation_to_table(grid), "scans": POSES.iloc[:2]},
    )
    return campaign


def test_write_exports_writes_every_file(filled, tmp_path):
    out = tmp_path / "outputs"
    lines = []
    written = write_exports(
        filled, out, cloud_spacing_m=0.2, progress=Progress(bars=False, out=_Lines(lines)),
        timings=stage_timings(filled),
    )
    assert sorted(p.name for p in written) == sorted(EXPORTS)
    assert lines[-1] == "  exports 11/11: report.html"  # one step per file, the two clouds together
    assert (out / "poses.csv").read_text().splitlines()[0] == (
        "scan,x,y,z,heading_deg,sd_x,sd_y,sd_z,sd_heading_deg,registered"
    )
    las = laspy.read(out / "cloud.laz")
    assert set(np.unique(las.scan)) == {0, 1}  # R is not registered, its points are left out
    cloud = campaign_cloud(filled, POSES, 0.2)
    assert len(cloud) == len(
        np.unique(np.floor(cloud[["x", "y", "z"]].to_numpy() / 0.2), axis=0)
    )  # one per voxel
    assert len(las.points) == len(cloud)
    ply, _ = read_ply(out / "cloud.ply")
    np.testing.assert_array_equal(
        ply[["x", "y", "z"]].to_numpy(), cloud[["x", "y", "z"]].to_numpy()
    )
    assert set(ply.loc[ply["scan"] == 1, "red"]) == {80}
    assert (
        json.loads((out / "trees.geojson").read_text())["features"][2]["properties"]["dbh_m"]
        is None
    )
    for png in ("map.png", "elevation.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"

    page = (out / "report.html").read_text()
    assert not re.search(r"""(src|href)=["']?(https?:|//|file:)""", page)  # self-contained
    assert page.count("data:image/png;base64,") >= 5  # map, elevation, network, residuals, DBH
    for needle in (
        "2/3",
        "scans registered",
        "accepted",
        "failed",
        "empty sub-map",
        "Residual checks",
        "DBH",
        "Timings",
        "pairwise_registrations",
    ):
        assert needle in page
    assert '3</div><div class="k">trees' in page


def test_write_exports_without_cloud_and_picture(filled, tmp_path):
    written = write_exports(
        filled, tmp_path / "o", cloud_spacing_m=None, picture=False, report=False
    )
    names = {p.name for p in written}
    assert "cloud.laz" not in names and "map.png" not in names and "report.html" not in names
    assert "trees.geojson" in names and "elevation.png" in names


class _Lines:
    """A text stream collecting lines."""

    def __init__(self, lines):
        self.lines = lines

    def write(self, text):
        self.lines.extend(t for t in text.splitlines() if t)

    def flush(self):
        pass


def test_report_after_the_map_reuses_its_assets_and_drawn_pieces(filled, tmp_path, monkeypatch):
    """The run's report written after the where-to-scan-next stages (cli: map_ready) takes the
    assets the map's files read and the figures drawn while those stages ran: no figure is
    drawn twice and the page is the report a fresh build writes."""
    import forestmap_assets.outputs.figures.common as common
    from forestmap_assets.outputs.report import PIECES, draw_report_pieces, write_report

    out, stored = tmp_path / "outputs", {}
    write_exports(filled, out, cloud_spacing_m=None, map_only=True, stored=stored)
    assert {"optimal_map", "refined_registrations", "tree_list"} <= set(stored)
    draw_report_pieces(filled, out, stored)
    assert {"network", "residuals", "dbh"} <= set(stored[PIECES])
    drawn = []
    real = common.png_bytes
    monkeypatch.setattr(common, "png_bytes", lambda fig, **kw: drawn.append(fig) or real(fig, **kw))
    reused = write_report(filled, out, stored=stored).read_text()
    assert drawn == []
    fresh = write_report(filled, out).read_text()
    assert len(drawn) == 3  # network, residuals, DBH
    stamp = re.compile(r"report written [^<]*")
    assert stamp.sub("", reused) == stamp.sub("", fresh)


def test_map_picture_beside_the_files_and_its_fallback_in_the_calling_thread(filled, tmp_path, monkeypatch):
    """map.png renders in a thread while the other files and the report's figures are made
    (``pieces``); when VTK cannot render, the matplotlib picture is drawn by the calling
    thread, not beside matplotlib's other figures."""
    import threading

    from forestmap_assets.outputs import render
    from forestmap_assets.outputs.report import PIECES

    threads = []

    def broken(*args, **kwargs):
        threads.append(threading.current_thread())
        raise RuntimeError("no OpenGL here")

    real = render.save_map_mpl
    monkeypatch.setattr(render, "map_image", broken)
    monkeypatch.setattr(render, "save_map_mpl",
                        lambda *a, **kw: threads.append(threading.current_thread()) or real(*a, **kw))
    out, stored = tmp_path / "outputs", {}
    written = write_exports(filled, out, cloud_spacing_m=None, map_only=True, stored=stored, pieces=True)
    assert [p.name for p in written][-1] == "map.png"
    assert (out / "map.png").read_bytes()[:4] == b"\x89PNG"
    assert threads[0] is not threading.main_thread() and threads[1] is threading.main_thread()
    assert {"network", "residuals", "dbh"} <= set(stored[PIECES])
    assert not (out / "report.html").exists()
