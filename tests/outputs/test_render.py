"""Pictures: the 3-D map (pyvista off-screen, matplotlib fallback) and the 2-D figures."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from matplotlib.image import imread

from forestmap_assets.core.features.elevation import ElevationGrid
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.outputs import render
from forestmap_assets.outputs.figures.common import png_bytes
from forestmap_assets.outputs.figures.elevation import (
    elevation_figure,
    ground_limits,
    remove_spikes,
)
from forestmap_assets.outputs.figures.range_images import (
    circle_mask,
    cylinder_outlines,
    range_image_panels,
)
from forestmap_assets.outputs.figures.range_pictures import NO_RETURN_RGB, range_mask_picture
from forestmap_assets.outputs.figures.registration import (
    cloud_weights,
    score_cloud_evolution,
    score_snapshots,
)


def sloped_grid(n: int = 200, cell: float = 0.1, spike: bool = True) -> ElevationGrid:
    """A 20 m x 20 m ground rising 0.1 m per metre in x, with a 6 m branch-hit spike."""
    x0 = y0 = -10.0
    xs = x0 + (np.arange(n) + 0.5) * cell
    z = np.tile(0.1 * xs, (n, 1)) - 1.5
    if spike:
        z[100:104, 100:104] = 4.5
    z[:10, :10] = np.nan
    return ElevationGrid(z, x0, y0, cell)


def scene():
    cylinders = pd.DataFrame(
        {
            "scan": ["T", "T", "S"],
            "cylinder_id": [0, 1, 0],
            "x0": [2.0, -3.0, 4.0],
            "y0": [1.0, 2.0, -4.0],
            "z0": [-1.2, -1.5, -1.0],
            "x1": [2.1, -3.0, 4.0],
            "y1": [1.0, 2.1, -4.0],
            "z1": [3.0, 2.5, 4.0],
            "radius_m": [0.2, 0.15, 0.3],
            "r0_m": [0.22, 0.15, 0.31],
            "r1_m": [0.18, 0.15, 0.29],
            "n_circles": [40, 30, 50],
        }
    )
    poses = pd.DataFrame(
        {
            "scan": ["T", "S", "R"],
            "x": [0.0, 5.0, np.nan],
            "y": [0.0, 1.0, np.nan],
            "z": [0.0, 0.2, np.nan],
            "heading_deg": [0.0, 90.0, np.nan],
            "sd_x": [0.0, 0.02, np.nan],
            "sd_y": [0.0, 0.03, np.nan],
            "sd_z": [0.0, 0.1, np.nan],
            "sd_heading_deg": [0.0, 0.1, np.nan],
            "registered": [True, True, False],
        }
    )
    return cylinders, poses


# ---- meshes ------------------------------------------------------------------------------


def test_tube_mesh_is_a_truncated_cone_around_each_axis():
    cylinders, _ = scene()
    sides = 12
    verts, faces, owner = render.tube_mesh_arrays(cylinders, sides)
    assert verts.shape == (len(cylinders) * 2 * sides, 3)
    assert owner.max() == len(cylinders) - 1
    assert len(owner) == len(cylinders) * (sides + 2)  # side quads + two caps each
    for k, r in enumerate(cylinders.itertuples()):
        p0, p1 = np.array([r.x0, r.y0, r.z0]), np.array([r.x1, r.y1, r.z1])
        axis = (p1 - p0) / np.linalg.norm(p1 - p0)
        bottom = verts[k * 2 * sides : k * 2 * sides + sides]
        top = verts[k * 2 * sides + sides : (k + 1) * 2 * sides]
        np.testing.assert_allclose(np.linalg.norm(bottom - p0, axis=1), r.r0_m, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(top - p1, axis=1), r.r1_m, atol=1e-9)
        np.testing.assert_allclose((bottom - p0) @ axis, 0.0, atol=1e-9)  # rings square to the axis


def test_surface_has_two_triangles_per_complete_cell():
    z = np.zeros((4, 5))
    z[0, 0] = np.nan  # removes the one quad that uses it
    verts, tris = render.surface_arrays(ElevationGrid(z, 0.0, 0.0, 0.6))
    assert len(verts) == 20
    assert len(tris) == 2 * (3 * 4 - 1)
    assert not np.isin(0, tris)  # the vertex without value is used by no triangle


@pytest.mark.slow
def test_remove_spikes_drops_branch_hits_and_keeps_the_slope():
    grid = sloped_grid()
    clean = remove_spikes(grid, spike_m=1.0)
    assert np.isnan(clean.z[100:104, 100:104]).all()
    keep = np.isfinite(grid.z) & ~np.isnan(clean.z)
    assert keep.sum() == np.isfinite(grid.z).sum() - 16
    assert remove_spikes(grid, spike_m=None) is grid
    lo, hi = ground_limits(grid)
    assert (
        hi < 0.0
    )  # the spike (4.5 m) does not stretch the colour scale; the ground tops at -0.5 m
    assert lo < -2.0


# ---- the 3-D map ---------------------------------------------------------------------------


def test_render_map_off_screen(tmp_path):
    cylinders, poses = scene()
    path = render.render_map(
        tmp_path / "map.png",
        cylinders,
        sloped_grid(),
        poses,
        title="test",
        window_size=(800, 400),
        fallback=False,
    )
    img = imread(path)[..., :3]
    assert img.shape[:2] == (400, 800)
    assert not render._blank(img)
    # bark-coloured pixels (the stems) and a range of ground colours are present
    bark = np.all(np.abs(img - np.array(render.BARK_RGB)) < 0.12, axis=-1)
    assert bark.sum() > 50
    assert len(np.unique((img * 255).astype(int).reshape(-1, 3), axis=0)) > 200


def test_render_map_falls_back_to_matplotlib(tmp_path, monkeypatch):
    cylinders, poses = scene()

    def broken(*args, **kwargs):
        raise RuntimeError("no OpenGL here")

    monkeypatch.setattr(render, "map_image", broken)
    path = render.render_map(
        tmp_path / "map.png", cylinders, sloped_grid(), poses, title="fallback"
    )
    assert imread(path).shape[0] > 100
    with pytest.raises(RuntimeError):
        render.render_map(tmp_path / "map2.png", cylinders, sloped_grid(), poses, fallback=False)


# ---- range-image pictures -------------------------------------------------------------------


def wall_image(rows=40, cols=360, step=0.5):
    az = (np.arange(cols) - cols / 2) * step
    el = 10.0 - np.arange(rows) * step
    return RangeImage(np.full((rows, cols), 10.0, np.float32), az, el)


def test_circle_mask_marks_the_angular_width_of_each_circle():
    image = wall_image()
    d, r, az = 5.0, 0.25, 30.0
    circles = pd.DataFrame(
        {
            "iteration": [1, 1],
            "row": [5, 6],
            "chain_id": [0, 0],
            "valid": [True, False],
            "cx": [d * np.cos(np.radians(az))] * 2,
            "cy": [d * np.sin(np.radians(az))] * 2,
            "cz": [0.0, 0.0],
            "radius_m": [r, r],
        }
    )
    mask = circle_mask(image, circles)
    assert mask.sum() == mask[5].sum()  # the invalid circle is not drawn
    cols = np.flatnonzero(mask[5])
    half = np.degrees(np.arcsin(r / d))
    assert image.azimuth_deg[cols].min() >= az - half - 1e-9
    assert image.azimuth_deg[cols].max() <= az + half + 1e-9
    assert len(cols) == pytest.approx(2 * half / 0.5, abs=1.5)


def test_cylinder_outline_follows_the_axis_in_azimuth_and_elevation():
    image = wall_image()
    cyl = pd.DataFrame(
        {
            "x0": [0.0],
            "y0": [4.0],
            "z0": [-1.0],
            "x1": [0.0],
            "y1": [4.0],
            "z1": [1.0],
            "radius_m": [0.2],
        }
    )
    (poly,) = cylinder_outlines(image, cyl)
    assert poly[:, 0].min() == pytest.approx(90 - np.degrees(np.arcsin(0.2 / 4.0)), abs=1e-6)
    assert poly[:, 0].max() == pytest.approx(90 + np.degrees(np.arcsin(0.2 / 4.0)), abs=1e-6)
    assert poly[:, 1].max() == pytest.approx(np.degrees(np.arctan2(1, 4)), abs=1e-6)


def test_range_image_panels_and_score_cloud_figures():
    image = wall_image()
    fig = range_image_panels(image, title="t")
    assert len([a for a in fig.axes if a.get_label() != "<colorbar>"]) == 1
    levels = pd.DataFrame(
        {
            "level": [0, 0, 1, 1, 1],
            "cell_m": 1.0,
            "cell_x_m": [1, 1, 0.5, 0.5, 0.5],
            "cell_y_m": [1, 1, 0.5, 0.5, 0.5],
            "cell_z_m": 0.5,
            "cell_heading_deg": 2.0,
            "dx": [0.5, -0.5, 0.25, 0.75, -0.25],
            "dy": [0.5, 0.5, 0.25, 0.25, 0.25],
            "dz": 0.0,
            "dh_deg": 0.0,
            "score": [-10.0, np.nan, -5.0, -6.0, -9.0],
            "bound": [1.0, 0.5, 0.0, 0.0, 0.0],
        }
    )
    assert score_snapshots(levels) == [0, 1]
    w = cloud_weights(levels["score"].to_numpy(), floor=-20.0)
    assert w[1] > 0 and w[1] < 1e-2 * w[0]  # an only-bounded cell keeps a token weight
    reg = {"scan": "S", "reference": "T", "dx": 0.4, "dy": 0.25, "sd_x": 0.1, "sd_y": 0.05}
    fig = score_cloud_evolution(
        levels, reg, floor=-20.0, a_priori=(0, 0, 0, 0), half_widths=(1, 1, 0.5, 4)
    )
    assert sum(ax.get_visible() for ax in fig.axes) >= 3


def test_elevation_figure_labels_its_colour_scale_and_crops_to_the_plot():
    grid = sloped_grid()
    _, poses = scene()
    trees = pd.DataFrame({"x": [2.0, -3.0], "y": [1.0, 2.0], "dbh_m": [0.4, np.nan]})
    fig = elevation_figure(grid, poses, trees, margin_m=2.0)
    labels = [ax.get_ylabel() for ax in fig.axes]
    assert any("elevation" in s and "(m)" in s for s in labels)
    main = fig.axes[0]
    assert main.get_xlim()[0] >= -3.0 - 2.0 - 0.1 and main.get_xlim()[1] <= 5.0 + 2.0 + 0.1
    assert png_bytes(fig)[:4] == b"\x89PNG"


def test_elevation_picture_for_the_dagster_ui():
    import io

    from PIL import Image

    from forestmap_assets.outputs.figures.common import NO_VALUE
    from forestmap_assets.outputs.figures.elevation_pictures import elevation_picture

    grid = sloped_grid(n=199)  # 199 cells: the last block of 2 x 2 is padded
    scans = pd.DataFrame({"scan": ["A", "B"], "x": [-5.0, 5.0], "y": [5.0, -5.0]})
    pic = elevation_picture(grid, scans, "plot 7: merged elevation map", max_width=100)
    assert pic.caption.startswith("plot 7: merged elevation map: ground z ")
    assert "2 placed scans" in pic.caption and "2 x 2 cells" in pic.caption
    px = np.asarray(Image.open(io.BytesIO(pic.png)).convert("RGB")).astype(int)
    assert px.shape == (100, 100, 3)
    # north up: the grid's first rows (y -10 m, no value in its first 10 x 10 cells) at the bottom
    assert tuple(px[-2, 1]) == tuple(int(NO_VALUE[k : k + 2], 16) for k in (1, 3, 5))
    # the ground rises in x: darker (lower) on the left, paler on the right, the spike left out
    row = px[20]
    assert row[5].sum() < row[50].sum() < row[95].sum()
    # the scans' dots: A at x -5, y 5 -> column 25, row 25 (blocks of 0.2 m below y 10 m, the padded top)
    for (u, v) in ((25, 25), (75, 75)):
        assert px[v, u].sum() == 0, (u, v)


def test_range_mask_picture_for_the_dagster_ui():
    import io

    from PIL import Image

    image = wall_image()
    image.range_m[30:, :] = np.nan  # no return in the lowest rows
    mask = np.zeros(image.shape, bool)
    mask[5:9, 100:110] = True
    pic = range_mask_picture(image, mask, "segments, scan T", label="segments", max_width=900)
    assert pic.caption.startswith("segments, scan T (red: segments, 40 pixels)")
    assert "azimuth" in pic.caption and "no return" in pic.caption
    px = np.asarray(Image.open(io.BytesIO(pic.png)).convert("RGB"))
    assert px.shape == (40, 360, 3)
    assert tuple(px[6, 105]) != tuple(px[6, 200]) and px[6, 105, 0] > 180 > px[6, 105, 1]
    assert tuple(px[35, 10]) == NO_RETURN_RGB
    # a wide image is shrunk in blocks: a one-pixel mark survives, outlines are drawn
    small = range_mask_picture(image, mask[:, ::-1], "x", max_width=100,
                               outlines=[np.array([[-50.0, 5.0], [50.0, 5.0], [50.0, 0.0]])])
    px = np.asarray(Image.open(io.BytesIO(small.png)).convert("RGB"))
    assert px.shape == (10, 90, 3) and "4 x 4" in small.caption and "orange: 1" in small.caption
    assert (px[..., 0] > 180).sum() > 0


