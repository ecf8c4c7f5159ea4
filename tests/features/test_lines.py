"""Wall/ceiling border lines (spec 5, Th. 4.7, Table 4.3) on exactly ray-cast synthetic rooms."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.features.free_space_border import border_cells, border_chains
from forestmap_assets.core.features.occupancy_grid import FREE, OCCUPIED, UNKNOWN, occupancy_grid
from forestmap_assets.core.features.range_image import RangeImage, levelling_rotation
from forestmap_assets.core.features.wall_lines import (
    LINE_COLUMNS,
    empty_line_table,
    extract_line_segments,
    fit_line,
    tangent_splits,
    turning_angles,
)
from forestmap_assets.params import resolve_params

INDOOR = resolve_params("indoor").lines
OUTDOOR = resolve_params("outdoor").lines

# Corridor in the levelled sensor frame: scanner 1.3 m above the floor, ceiling at 2.3 m.
LO = np.array([-4.03, -1.23, -1.3])
HI = np.array([7.94, 1.77, 1.0])


def _image(planes, rows=240, cols=1800, noise=0.01, tilt=(0.0, 0.0), seed=0) -> RangeImage:
    """Exact ray casting from the sensor (inside the convex polytope ``n . p <= h``).

    ``tilt`` = (roll, pitch) of the scanner: rays are generated in the scanner frame and cast in
    the levelled frame, so the image's levelled points must reproduce the scene.
    """
    az = np.linspace(-180.0, 180.0, cols, endpoint=False) + 180.0 / cols
    el = np.linspace(38.7, -38.7, rows)
    a, e = np.radians(az)[None, :], np.radians(el)[:, None]
    d = np.stack(np.broadcast_arrays(np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)), -1)
    d = d @ levelling_rotation(*tilt).T
    n = np.array([p[0] for p in planes], dtype=float)
    h = np.array([p[1] for p in planes], dtype=float)
    nd = d @ n.T
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(nd > 1e-12, h / nd, np.inf).min(axis=-1)
    r = np.where(np.isfinite(r), r, np.nan)
    r = r + np.random.default_rng(seed).normal(0.0, noise, r.shape)
    return RangeImage(r.astype(np.float32), az, el, tilt_deg=tilt)


def _room_planes(ceiling_slope_deg: float = 0.0):
    s = np.radians(ceiling_slope_deg)
    return [
        ((1, 0, 0), HI[0]),
        ((-1, 0, 0), -LO[0]),
        ((0, 1, 0), HI[1]),
        ((0, -1, 0), -LO[1]),
        ((-np.sin(s), 0, np.cos(s)), np.cos(s) * HI[2]),
        ((0, 0, -1), -LO[2]),
    ]


def _inclination(df: pd.DataFrame) -> np.ndarray:
    d = df[["x1", "y1", "z1"]].to_numpy() - df[["x0", "y0", "z0"]].to_numpy()
    return np.degrees(np.arctan2(np.abs(d[:, 2]), np.hypot(d[:, 0], d[:, 1])))


def _wall_coverage(df: pd.DataFrame, axis: int, value: float, z: float, tol: float) -> float:
    """Fraction of a corridor edge (wall at coordinate ``value`` on ``axis``) covered by lines
    whose both ends lie within ``tol`` of the true wall/ceiling corner."""
    other = 1 - axis
    p0 = df[["x0", "y0", "z0"]].to_numpy()
    p1 = df[["x1", "y1", "z1"]].to_numpy()
    on = (
        (np.abs(p0[:, axis] - value) < tol)
        & (np.abs(p1[:, axis] - value) < tol)
        & (np.abs(p0[:, 2] - z) < tol)
        & (np.abs(p1[:, 2] - z) < tol)
    )
    grid = np.linspace(LO[other], HI[other], 400)
    lo = np.minimum(p0[on, other], p1[on, other])[:, None]
    hi = np.maximum(p0[on, other], p1[on, other])[:, None]
    return float(((grid >= lo) & (grid <= hi)).any(axis=0).mean())


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (2.0, -3.0)])
def test_corridor_wall_ceiling_lines_found(tilt):
    df = extract_line_segments(_image(_room_planes(), tilt=tilt), INDOOR)
    assert list(df.columns) == LINE_COLUMNS
    assert df["line_id"].tolist() == list(range(len(df)))
    # Both long walls: >= 85 % of their 12 m recalled within 0.1 m of the corner line.
    assert _wall_coverage(df, axis=1, value=HI[1], z=HI[2], tol=0.1) >= 0.85
    assert _wall_coverage(df, axis=1, value=LO[1], z=HI[2], tol=0.1) >= 0.85
    # End walls (3 m) are found as well.
    assert _wall_coverage(df, axis=0, value=LO[0], z=HI[2], tol=0.1) >= 0.7
    assert _wall_coverage(df, axis=0, value=HI[0], z=HI[2], tol=0.1) >= 0.7
    # Every accepted line is horizontal, long enough, and lies on a wall/ceiling corner.
    assert (_inclination(df) <= 5.0).all()
    assert (df["length_m"] >= INDOOR.min_length_m).all()
    for end in ("0", "1"):
        x, y, z = df[f"x{end}"], df[f"y{end}"], df[f"z{end}"]
        near_wall = np.minimum.reduce(
            [np.abs(x - LO[0]), np.abs(x - HI[0]), np.abs(y - LO[1]), np.abs(y - HI[1])]
        )
        assert (near_wall < 0.15).all() and (np.abs(z - HI[2]) < 0.1).all()
    # Lengths match the end points.
    d = df[["x1", "y1", "z1"]].to_numpy() - df[["x0", "y0", "z0"]].to_numpy()
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), df["length_m"], rtol=1e-9)


def test_corridor_outdoor_preset_coarser_cells():
    df = extract_line_segments(_image(_room_planes(), rows=180, cols=1500), OUTDOOR)
    assert _wall_coverage(df, axis=1, value=HI[1], z=HI[2], tol=0.2) >= 0.8
    assert _wall_coverage(df, axis=1, value=LO[1], z=HI[2], tol=0.2) >= 0.8
    assert (_inclination(df) <= OUTDOOR.max_inclination_deg).all()


def test_inclination_gate_on_sloped_ceiling():
    """Ceiling rising 8 deg along the corridor: its long edge lines are inclined 8 deg."""
    img = _image(_room_planes(ceiling_slope_deg=8.0))
    strict = extract_line_segments(img, INDOOR)
    loose = extract_line_segments(img, INDOOR.model_copy(update={"max_inclination_deg": 15.0}))
    along_x = lambda df: np.abs(df["x1"] - df["x0"]) > 0.9 * df["length_m"]  # noqa: E731
    assert not along_x(strict).any()
    assert (_inclination(strict) <= 5.0).all() and len(strict) >= 2  # the level end-wall lines
    long = loose[along_x(loose)]
    assert len(long) >= 2 and long["length_m"].min() > 8.0
    np.testing.assert_allclose(_inclination(long), 8.0, atol=1.0)


@pytest.mark.slow
@pytest.mark.parametrize("params", [INDOOR, OUTDOOR], ids=["indoor", "outdoor"])
def test_open_ground_plane_gives_no_lines(params):
    img = _image([((0, 0, -1), 1.3)], rows=120, cols=900, noise=0.025)
    assert img.valid.mean() > 0.4
    grid = occupancy_grid(img, params.cell_m, params.max_range_m)
    border = border_cells(grid, img.xyz[img.valid & (img.range_m <= params.max_range_m)])
    assert border.empty
    assert extract_line_segments(img, params).empty


def test_empty_disabled_and_all_nan_give_well_formed_empty_tables():
    img = _image(_room_planes(), rows=60, cols=300)
    off = extract_line_segments(img, INDOOR.model_copy(update={"enabled": False}))
    nan = RangeImage(np.full((20, 40), np.nan, np.float32), np.linspace(0, 39, 40),
                     np.linspace(10, -9, 20))
    for df in (off, extract_line_segments(nan, INDOOR), empty_line_table()):
        assert df.empty and list(df.columns) == LINE_COLUMNS
        assert df["line_id"].dtype == np.int64 and df["n_points"].dtype == np.int64
        assert df["x0"].dtype == np.float64
    assert resolve_params("forest").lines.enabled is False


def test_occupancy_free_before_hit_occupied_at_hit_unknown_elsewhere():
    az = np.array([0.0, 90.0, 180.0])
    img = RangeImage(np.array([[2.05, np.nan, 0.93]], np.float32), az, np.array([0.0]))
    grid = occupancy_grid(img, cell_m=0.1, max_range_m=40.0, hit_margin_m=0.0)
    # The NaN beam (+y) marks nothing: the grid does not even extend along y.
    assert grid.state.shape[1] == 1 and grid.state.shape[2] == 1
    row = grid.state[:, 0, 0]
    ix = np.arange(grid.lo[0], grid.lo[0] + row.size)
    state = dict(zip(ix.tolist(), row.tolist(), strict=True))
    assert state[20] == OCCUPIED and state[-10] == OCCUPIED  # hits at x=2.05 and x=-0.93
    assert all(state[i] == FREE for i in range(-9, 20))
    # A beam beyond max_range marks free space up to max_range and no hit.
    short = occupancy_grid(img, cell_m=0.1, max_range_m=1.0, hit_margin_m=0.0)
    s_row = short.state[:, 0, 0]
    s_ix = np.arange(short.lo[0], short.lo[0] + s_row.size)
    assert s_ix[s_row == OCCUPIED].tolist() == [-10]  # only the 0.93 m hit
    assert s_ix[(s_row == FREE) & (s_ix >= 0)].tolist() == list(range(10))  # x < 1.0
    # A hit margin keeps the last stretch before the hit unmarked.
    margin = occupancy_grid(img, cell_m=0.1, max_range_m=40.0, hit_margin_m=0.25)
    m_row = margin.state[:, 0, 0]
    assert m_row[17 - margin.lo[0]] == FREE  # free for x < 2.05 - 0.25 = 1.8
    assert (m_row[[18 - margin.lo[0], 19 - margin.lo[0]]] == UNKNOWN).all()
    assert m_row[20 - margin.lo[0]] == OCCUPIED


def test_turning_angles_and_tangent_splits_at_a_corner():
    step = 0.1
    leg = np.arange(0.0, 3.0, step)
    pts = np.concatenate([np.c_[leg, 0 * leg], np.c_[3.0 + 0 * leg, leg]])  # 90 deg corner
    ang = turning_angles(pts, interval_m=1.0)
    k = int(np.argmax(ang))
    assert abs(pts[k, 0] - 3.0) < 0.15 and abs(pts[k, 1]) < 0.15
    assert 80.0 < ang[k] <= 95.0
    assert np.all(ang[:5] == 0.0) and np.all(ang[-5:] == 0.0)  # less than half an interval
    splits = tangent_splits(ang, 80.0)
    assert splits.tolist() == [k]
    assert tangent_splits(ang, 120.0).size == 0
    # A closed square: four corners found even where the chain starts and ends.
    side = np.arange(0.0, 2.0, step)
    sq = np.concatenate(
        [np.c_[side, 0 * side], np.c_[2 + 0 * side, side], np.c_[2 - side, 2 + 0 * side],
         np.c_[0 * side, 2 - side]]
    )
    sq = np.roll(sq, 7, axis=0)
    corners = tangent_splits(turning_angles(sq, 0.6, closed=True), 60.0)
    assert len(corners) == 4
    got = {tuple(np.round(sq[c])) for c in corners}
    assert got == {(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)}


def test_fit_line_svd_direction_and_gated_ends():
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 4.0, 81)
    pts = np.c_[1.0 + t, 2.0 + 0.5 * t, np.full_like(t, 1.2)] + rng.normal(0, 0.01, (81, 3))
    far = np.array([[6.0, 6.0, 1.2]])  # beyond the end and 1.34 m off the line
    p0, p1, n_in, dmax = fit_line(np.vstack([pts, far]), end_distance_m=0.15)
    ends = sorted([p0, p1], key=lambda p: p[0])
    np.testing.assert_allclose(ends[0], [1.0, 2.0, 1.2], atol=0.1)  # SVD fit is not robust:
    np.testing.assert_allclose(ends[1], [5.0, 4.0, 1.2], atol=0.1)  # the outlier tilts it
    assert n_in == 81 and dmax > 1.0


def test_border_chains_order_cells_and_close_loops():
    # A 10 x 6 rectangle ring of cells and a separate straight run of 8 cells.
    ring = [(x, 0) for x in range(10)] + [(9, y) for y in range(1, 6)]
    ring += [(x, 5) for x in range(8, -1, -1)] + [(0, y) for y in range(4, 0, -1)]
    run = [(x, 20) for x in range(8)]
    cells = np.array(ring + run)
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(cells))
    ix, iy = cells[perm, 0], cells[perm, 1]
    chains = border_chains(ix, iy, min_cells=3, link_cells=1)
    assert sorted(len(c) for c in chains) == [8, len(ring)]
    for c in chains:
        steps = np.abs(np.diff(np.c_[ix[c], iy[c]], axis=0)).max(axis=1)
        assert (steps == 1).all()  # consecutive cells are neighbours
    loop = max(chains, key=len)
    assert max(abs(ix[loop[0]] - ix[loop[-1]]), abs(iy[loop[0]] - iy[loop[-1]])) == 1
