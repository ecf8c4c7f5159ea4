"""Horizontal wall/ceiling border lines (spec 5; Th. 4.7, Figs 4.22-4.25, Table 4.3).

Pipeline (spec 5 steps 1-6):

1. :func:`occupancy_grid`: a 3-D grid of cubic ``cell_m`` cells in the levelled scan frame, built
   by casting each beam: cells before the hit are *free*, the hit cell is *occupied*, all others
   *unknown*; beams without return mark nothing.
2. :func:`border_cells`: the border between the free space and unknown/occupied space, projected
   to a 2-D (x, y) image whose value is the border height ("the highest location where a laser
   beam hit was recorded", Th. Fig. B.17).
3. :func:`border_chains`: ordered chains ("point data queues") of consecutive border cells.
4. :func:`tangent_splits`: split a chain where its tangent direction, taken over
   ``tangent_interval_m``, turns by more than ``tangent_change_deg``.
5. :func:`fit_line`: 3-D line by SVD (largest-variance direction), end points at the furthest
   projections of the points within ``end_distance_m`` of the line.
6. Acceptance: length >= ``min_length_m``, inclination within +-``max_inclination_deg``.

Steps 1-4 are largely inferred in the spec (Figs 4.22 and 4.24 are not available in text); every
inferred choice below is marked "(inferred)" and is a keyword argument of
:func:`extract_line_segments`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import pandas as pd
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.params import LineParams

LINE_COLUMNS = ["line_id", "x0", "y0", "z0", "x1", "y1", "z1", "n_points", "length_m"]
BORDER_COLUMNS = ["ix", "iy", "x", "y", "z", "top_free_z"]

UNKNOWN, FREE, OCCUPIED = np.uint8(0), np.uint8(1), np.uint8(2)

# 4-neighbour offsets (step 2).
_N4 = ((1, 0), (-1, 0), (0, 1), (0, -1))


def empty_line_table() -> pd.DataFrame:
    """The well-formed empty line-segment table (columns of the shared schema)."""
    return pd.DataFrame(
        {
            c: pd.Series(dtype="int64" if c in ("line_id", "n_points") else "float64")
            for c in LINE_COLUMNS
        }
    )


# ---- step 1: occupancy grid -------------------------------------------------------------------
@dataclass(frozen=True)
class OccupancyGrid:
    """Dense 3-D occupancy grid (spec 5 step 1) in the levelled scan frame.

    ``state[i, j, k]`` is ``UNKNOWN``, ``FREE`` or ``OCCUPIED`` for the cell with global indices
    ``lo + (i, j, k)``, covering ``[(lo_x + i) * cell_m, (lo_x + i + 1) * cell_m)`` etc., so that
    grids of different scans share cell boundaries.
    """

    state: np.ndarray
    lo: np.ndarray
    cell_m: float

    @property
    def free_columns(self) -> np.ndarray:
        """(nx, ny) bool: xy columns with at least one free cell (spec 5 step 2)."""
        return (self.state == FREE).any(axis=2)

    @property
    def top_free_z(self) -> np.ndarray:
        """(nx, ny) z of the top of the highest free cell per column, NaN for non-free columns."""
        free = self.state == FREE
        nz = free.shape[2]
        top = nz - 1 - np.argmax(free[:, :, ::-1], axis=2)
        z = (self.lo[2] + top + 1) * self.cell_m
        return np.where(free.any(axis=2), z, np.nan)

    def cell_index(self, points: np.ndarray) -> np.ndarray:
        """Array indices (n, 3) into ``state`` of points (n, 3), without bounds checks."""
        return np.floor(np.asarray(points) / self.cell_m).astype(np.int64) - self.lo


def _beam_subsample(valid: np.ndarray, max_beams: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (row, col) indices of the beams cast for free space (inferred).

    Rows (elevations) are thinned first and all azimuths kept, because every xy column is crossed
    by beams of many elevations but only of its own azimuth: thinning azimuth would leave holes in
    the projected free space at long range.
    """
    rows, cols = valid.shape
    n = int(valid.sum())
    if n <= max_beams:
        return np.nonzero(valid)
    row_stride = int(min(np.ceil(n / max_beams), max(1, rows // 8)))
    kept_rows = np.arange(row_stride // 2, rows, row_stride)
    n_rows = int(valid[kept_rows].sum())
    col_stride = max(1, int(np.ceil(n_rows / max_beams)))
    kept_cols = np.arange(col_stride // 2, cols, col_stride)
    sub = np.zeros_like(valid)
    sub[np.ix_(kept_rows, kept_cols)] = True
    return np.nonzero(valid & sub)


def occupancy_grid(
    image: RangeImage,
    cell_m: float,
    max_range_m: float,
    *,
    max_beams: int = 100_000,
    step_fraction: float = 0.5,
    hit_margin_m: float | None = None,
    max_cells: int = 150_000_000,
    chunk_samples: int = 2_000_000,
) -> OccupancyGrid:
    """Cast every beam through a cubic ``cell_m`` grid (spec 5 step 1, Th. 4.7.1).

    Each beam is sampled at ``step_fraction * cell_m`` steps from the sensor up to its hit
    (inferred sampled traversal instead of Amanatides-Woo); cells with a sample are free, cells
    with a hit are occupied (occupied wins), the rest unknown. Beams without return mark nothing.
    (inferred) The last ``hit_margin_m`` (default one cell) before a hit is not marked free, so
    range noise and grazing incidence do not mark wall cells that happen to hold no hit as free.
    A beam longer than ``max_range_m`` marks free space up to ``max_range_m`` and no hit
    (inferred). Hits use every pixel; free space uses at most ``max_beams`` beams (inferred).
    """
    if cell_m <= 0 or max_range_m <= 0:
        raise ValueError("cell_m and max_range_m must be positive")
    r = image.range_m.astype(np.float64)
    valid = image.valid
    xyz = image.xyz
    hit_mask = valid & (r <= max_range_m)
    hits = xyz[hit_mask]

    v, u = _beam_subsample(valid, max_beams)
    beam_r = r[v, u]
    dirs = xyz[v, u] / beam_r[:, None]
    lengths = np.minimum(beam_r, max_range_m)
    ends = dirs * lengths[:, None]
    margin = cell_m if hit_margin_m is None else float(hit_margin_m)
    free_len = np.where(beam_r <= max_range_m, np.maximum(beam_r - margin, 0.0), lengths)

    extent = np.vstack([np.zeros((1, 3)), hits, ends])
    lo = np.floor(extent.min(axis=0) / cell_m).astype(np.int64)
    hi = np.floor(extent.max(axis=0) / cell_m).astype(np.int64)
    shape = tuple(int(s) for s in (hi - lo + 1))
    if int(np.prod(shape)) > max_cells:
        raise ValueError(
            f"occupancy grid of {shape} cells exceeds max_cells={max_cells}; "
            "use a larger cell_m or a smaller max_range_m"
        )
    state = np.zeros(shape, dtype=np.uint8)
    flat = state.reshape(-1)

    step = step_fraction * cell_m
    n_samples = np.ceil(free_len / step).astype(np.int64)  # samples at t = j * step < free_len
    total = int(n_samples.sum())
    n_chunks = max(1, int(np.ceil(total / chunk_samples)))
    increment = dirs * (step / cell_m)  # one sample step, in cells
    for part in np.array_split(np.arange(lengths.size), n_chunks):
        if part.size == 0:
            continue
        ns = n_samples[part]
        beam = np.repeat(np.arange(part.size), ns)
        j = np.arange(beam.size) - np.repeat(np.cumsum(ns) - ns, ns)  # sample number on its beam
        cells = np.floor(increment[part][beam] * j[:, None] - lo).astype(np.intp)
        flat[np.ravel_multi_index(cells.T, shape, mode="clip")] = FREE

    if hits.size:
        cells = np.floor(hits / cell_m).astype(np.intp) - lo
        flat[np.ravel_multi_index(cells.T, shape, mode="clip")] = OCCUPIED
    return OccupancyGrid(state=state, lo=lo, cell_m=float(cell_m))


# ---- step 2: border of the free space, projected to xy ----------------------------------------
def _shift(a: np.ndarray, dx: int, dy: int, fill) -> np.ndarray:
    """``b[i, j] = a[i + dx, j + dy]`` with ``fill`` outside ``a``."""
    b = np.full_like(a, fill)
    nx, ny = a.shape
    if abs(dx) >= nx or abs(dy) >= ny:
        return b
    b[max(0, -dx) : nx - max(0, dx), max(0, -dy) : ny - max(0, dy)] = a[
        max(0, dx) : nx - max(0, -dx), max(0, dy) : ny - max(0, -dy)
    ]
    return b


def _column_hit_stats(grid: OccupancyGrid, hits: np.ndarray) -> dict[str, np.ndarray]:
    """Per xy column of ``grid``: highest and lowest hit z, and the mean xy of the hits within
    one cell of the highest hit (the top of the wall in that column)."""
    nx, ny, _ = grid.state.shape
    out = {
        "zmax": np.full(nx * ny, -np.inf),
        "zmin": np.full(nx * ny, np.inf),
        "x": np.full(nx * ny, np.nan),
        "y": np.full(nx * ny, np.nan),
    }
    if hits.size:
        idx = grid.cell_index(hits)[:, :2]
        inside = (idx >= 0).all(axis=1) & (idx[:, 0] < nx) & (idx[:, 1] < ny)
        h, idx = hits[inside], idx[inside]
        key = idx[:, 0] * ny + idx[:, 1]
        np.maximum.at(out["zmax"], key, h[:, 2])
        np.minimum.at(out["zmin"], key, h[:, 2])
        top = h[:, 2] >= out["zmax"][key] - grid.cell_m
        cnt = np.bincount(key[top], minlength=nx * ny)
        with np.errstate(invalid="ignore", divide="ignore"):
            out["x"] = np.bincount(key[top], h[top, 0], minlength=nx * ny) / cnt
            out["y"] = np.bincount(key[top], h[top, 1], minlength=nx * ny) / cnt
    out["zmax"] = np.where(np.isfinite(out["zmax"]), out["zmax"], np.nan)
    out["zmin"] = np.where(np.isfinite(out["zmin"]), out["zmin"], np.nan)
    return {k: v.reshape(nx, ny) for k, v in out.items()}


def _wall_behind(
    free: np.ndarray, stats: dict[str, np.ndarray], dx: int, dy: int, depth: int
) -> dict[str, np.ndarray]:
    """Hit statistics of the non-free columns directly behind each column in direction (dx, dy):
    the run of up to ``depth`` consecutive non-free columns starting at the 4-neighbour."""
    zmax = np.full(free.shape, np.nan)
    zmin = np.full(free.shape, np.nan)
    x = np.full(free.shape, np.nan)
    y = np.full(free.shape, np.nan)
    run = np.ones(free.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        for k in range(1, depth + 1):
            run &= ~_shift(free, k * dx, k * dy, False)
            k_zmax = np.where(run, _shift(stats["zmax"], k * dx, k * dy, np.nan), np.nan)
            k_zmin = np.where(run, _shift(stats["zmin"], k * dx, k * dy, np.nan), np.nan)
            higher = k_zmax > zmax
            better = np.isnan(zmax) | higher
            take = better & np.isfinite(k_zmax)
            x = np.where(take, _shift(stats["x"], k * dx, k * dy, np.nan), x)
            y = np.where(take, _shift(stats["y"], k * dx, k * dy, np.nan), y)
            zmax = np.where(take, k_zmax, zmax)
            zmin = np.where(np.isfinite(k_zmin) & ~(k_zmin >= zmin), k_zmin, zmin)
    first_non_free = ~_shift(free, dx, dy, False)
    return {"zmax": zmax, "zmin": zmin, "x": x, "y": y, "first_non_free": first_non_free}


def border_cells(
    grid: OccupancyGrid,
    hits: np.ndarray,
    *,
    min_wall_extent_m: float = 0.5,
    top_tolerance_m: float | None = None,
    wall_depth_cells: int = 2,
    border_xy: Literal["hits", "edge", "centre"] = "hits",
) -> pd.DataFrame:
    """Border cells of the xy-projected free space with their height (spec 5 step 2).

    A column is free if any of its cells is free; a border cell is a free column with a non-free
    4-neighbour (spec 5, inferred form). (inferred) The non-free side must be a *wall*: the run
    of up to ``wall_depth_cells`` non-free columns behind the neighbour (a wall surface straddling
    a cell boundary spreads its hits over two columns) holds hits spanning at least
    ``min_wall_extent_m`` vertically, whose highest one reaches the top of the free space of the
    border column within ``top_tolerance_m`` (default one cell). This keeps the edge of the
    scanned ground and gaps in the sampled free space out of the border. The height ``z`` is the
    highest hit of the border column and the wall behind it (Th. Fig. B.17); ``x, y`` are the
    mean of the wall's hits within one cell of its highest hit (``border_xy="hits"``), or the
    cell edge facing the wall, or the cell centre. ``ix, iy`` are global cell indices.
    """
    tol = grid.cell_m if top_tolerance_m is None else float(top_tolerance_m)
    free = grid.free_columns
    top_free = grid.top_free_z
    stats = _column_hit_stats(grid, hits)
    nx, ny = free.shape
    ci, cj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    centre_x = (grid.lo[0] + ci + 0.5) * grid.cell_m
    centre_y = (grid.lo[1] + cj + 0.5) * grid.cell_m

    z = np.full((nx, ny), -np.inf)
    sx = np.zeros((nx, ny))
    sy = np.zeros((nx, ny))
    count = np.zeros((nx, ny), dtype=np.int64)
    with np.errstate(invalid="ignore"):
        for dx, dy in _N4:
            w = _wall_behind(free, stats, dx, dy, max(1, wall_depth_cells))
            top = np.fmax(w["zmax"], stats["zmax"])
            wall = (
                free
                & w["first_non_free"]
                & (top >= top_free - tol)
                & (w["zmax"] - w["zmin"] >= min_wall_extent_m)
            )
            z = np.where(wall, np.maximum(z, top), z)
            if border_xy == "hits":
                px, py = w["x"], w["y"]
            elif border_xy == "edge":
                px, py = centre_x + 0.5 * dx * grid.cell_m, centre_y + 0.5 * dy * grid.cell_m
            else:
                px, py = centre_x, centre_y
            sx += np.where(wall, px, 0.0)
            sy += np.where(wall, py, 0.0)
            count += wall
    i, j = np.nonzero(count > 0)
    return pd.DataFrame(
        {
            "ix": (grid.lo[0] + i).astype(np.int64),
            "iy": (grid.lo[1] + j).astype(np.int64),
            "x": sx[i, j] / count[i, j],
            "y": sy[i, j] / count[i, j],
            "z": z[i, j],
            "top_free_z": top_free[i, j],
        },
        columns=BORDER_COLUMNS,
    )


def border_height_image(border: pd.DataFrame) -> tuple[np.ndarray, int, int]:
    """The 2-D border-height image of spec 5 step 2: ``(img[iy, ix] z or NaN, ix0, iy0)``."""
    if border.empty:
        return np.full((0, 0), np.nan), 0, 0
    ix0, iy0 = int(border["ix"].min()), int(border["iy"].min())
    img = np.full((int(border["iy"].max()) - iy0 + 1, int(border["ix"].max()) - ix0 + 1), np.nan)
    img[border["iy"].to_numpy() - iy0, border["ix"].to_numpy() - ix0] = border["z"].to_numpy()
    return img, ix0, iy0


# ---- step 3: ordered chains of border cells ---------------------------------------------------
def _adjacency(ix: np.ndarray, iy: np.ndarray, link_cells: int) -> sparse.csr_matrix:
    """Symmetric adjacency of cells within Chebyshev distance ``link_cells``, weighted by the
    Euclidean distance in cells (``link_cells=1``: the 8-neighbourhood)."""
    n = ix.size
    k = link_cells
    x0, y0 = ix.min(), iy.min()
    ids = np.full((ix.max() - x0 + 2 * k + 1, iy.max() - y0 + 2 * k + 1), -1, dtype=np.int64)
    gx, gy = ix - x0 + k, iy - y0 + k
    ids[gx, gy] = np.arange(n)
    forward = [(dx, dy) for dx in range(0, k + 1) for dy in range(-k, k + 1) if dx > 0 or dy > 0]
    rows, cols, w = [], [], []
    for dx, dy in forward:
        other = ids[gx + dx, gy + dy]
        ok = other >= 0
        rows.append(np.nonzero(ok)[0])
        cols.append(other[ok])
        w.append(np.full(ok.sum(), np.hypot(dx, dy)))
    r, c, wt = np.concatenate(rows), np.concatenate(cols), np.concatenate(w)
    a = sparse.coo_matrix((wt, (r, c)), shape=(n, n)).tocsr()
    return (a + a.T).tocsr()


def _tree_diameter(tree: sparse.csr_matrix, start: int) -> np.ndarray:
    """Node indices of the longest path of the tree component holding ``start``, in order.

    Double sweep: the node ``a`` furthest from ``start``, then ``b`` furthest from ``a``; on a
    tree the a-b path is exactly the nodes with ``d(a, v) + d(v, b) = d(a, b)``.
    """
    d0 = csgraph.dijkstra(tree, directed=False, indices=start)
    a = int(np.argmax(np.where(np.isfinite(d0), d0, -1.0)))
    da = csgraph.dijkstra(tree, directed=False, indices=a)
    b = int(np.argmax(np.where(np.isfinite(da), da, -1.0)))
    db = csgraph.dijkstra(tree, directed=False, indices=b)
    on_path = np.nonzero(np.abs(da + db - da[b]) < 1e-6)[0]
    return on_path[np.argsort(da[on_path])]


def border_chains(
    ix: np.ndarray, iy: np.ndarray, min_cells: int = 3, link_cells: int = 2
) -> list[np.ndarray]:
    """Ordered chains ("point data queues") of consecutive border cells (spec 5 step 3).

    (inferred) Cells within ``link_cells`` (Chebyshev) of each other are consecutive, which
    bridges single missing cells of a wall seen at grazing incidence (1 = 8-connectivity). Each
    connected component is reduced to its minimum spanning tree and the tree's longest path
    becomes a chain; the chain's cells and their neighbours within ``link_cells`` are removed and
    the remaining cells are chained again (branches), until no component has ``min_cells``
    cells. A closed border (a room) becomes one chain whose ends are adjacent. Returns index
    arrays into ``ix``/``iy``.
    """
    ix, iy = np.asarray(ix, dtype=np.int64), np.asarray(iy, dtype=np.int64)
    remaining = np.arange(ix.size)
    chains: list[np.ndarray] = []
    while remaining.size >= min_cells:
        sub_x, sub_y = ix[remaining], iy[remaining]
        tree = csgraph.minimum_spanning_tree(_adjacency(sub_x, sub_y, link_cells))
        tree = (tree + tree.T).tocsr()
        n_comp, label = csgraph.connected_components(tree, directed=False)
        sizes = np.bincount(label, minlength=n_comp)
        big = np.nonzero(sizes >= min_cells)[0]
        if big.size == 0:
            break
        first = np.full(n_comp, -1)
        first[label[::-1]] = np.arange(label.size)[::-1]
        k = link_cells
        used = np.zeros((np.ptp(sub_x) + 2 * k + 1, np.ptp(sub_y) + 2 * k + 1), bool)
        gx, gy = sub_x - sub_x.min() + k, sub_y - sub_y.min() + k
        for comp in big:
            path = _tree_diameter(tree, int(first[comp]))
            chains.append(remaining[path])
            used[gx[path], gy[path]] = True
        used = ndimage.binary_dilation(used, structure=np.ones((2 * k + 1, 2 * k + 1), bool))
        remaining = remaining[~used[gx, gy]]
    return chains


# ---- step 4: splitting at tangent direction changes -------------------------------------------
def turning_angles(points_xy: np.ndarray, interval_m: float, closed: bool = False) -> np.ndarray:
    """Tangent direction change (deg) at each chain point (spec 5 step 4, inferred form).

    The tangent before point i is the chord from the point ``interval_m`` of arc length behind
    to i, the tangent after it the chord from i to the point ``interval_m`` ahead; the change is
    the angle between them. Near the ends of an open chain, where less than half an interval is
    available on a side, the change is 0. A closed chain wraps around.
    """
    p = np.asarray(points_xy, dtype=np.float64)[:, :2]
    n = p.shape[0]
    if n < 3:
        return np.zeros(n)
    seg = np.hypot(*np.diff(p, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    idx = np.arange(n)
    if closed:
        perimeter = s[-1] + float(np.hypot(*(p[0] - p[-1])))
        s = np.concatenate([s - perimeter, s, s + perimeter])
        p = np.concatenate([p, p, p])
        idx = idx + n
    back = np.clip(np.searchsorted(s, s[idx] - interval_m, side="right") - 1, 0, len(s) - 1)
    ahead = np.clip(np.searchsorted(s, s[idx] + interval_m, side="left"), 0, len(s) - 1)
    u = p[idx] - p[back]
    w = p[ahead] - p[idx]
    ok = (s[idx] - s[back] >= 0.5 * interval_m) & (s[ahead] - s[idx] >= 0.5 * interval_m)
    cos = np.einsum("ij,ij->i", u, w) / np.maximum(np.hypot(*u.T) * np.hypot(*w.T), 1e-12)
    return np.where(ok, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), 0.0)


def tangent_splits(angles_deg: np.ndarray, threshold_deg: float) -> np.ndarray:
    """Indices where a new segment starts: the largest turning point of every run of points
    whose tangent change exceeds ``threshold_deg`` (spec 5 step 4)."""
    above = np.asarray(angles_deg) > threshold_deg
    if not above.any():
        return np.zeros(0, dtype=np.int64)
    edges = np.diff(np.concatenate([[0], above.astype(np.int8), [0]]))
    run = np.cumsum(edges[:-1] == 1)
    members = np.nonzero(above)[0]
    order = np.lexsort((-np.asarray(angles_deg)[members], run[members]))
    _, first = np.unique(run[members][order], return_index=True)
    return np.sort(members[order][first])


# ---- step 5: 3-D line fit ---------------------------------------------------------------------
def fit_line(
    points: np.ndarray, end_distance_m: float
) -> tuple[np.ndarray, np.ndarray, int, float]:
    """SVD line through 3-D points (spec 5 step 5).

    Direction: largest-variance right singular vector; pass point: the centroid; end points: the
    furthest projections of the points within ``end_distance_m`` of the line. Returns
    ``(p0, p1, n_inliers, max_distance)``.
    """
    pts = np.asarray(points, dtype=np.float64)
    c = pts.mean(axis=0)
    q = pts - c
    direction = np.linalg.svd(q, full_matrices=False)[2][0]
    t = q @ direction
    dist = np.linalg.norm(q - t[:, None] * direction, axis=1)
    inl = dist <= end_distance_m
    if not inl.any():
        return c, c, 0, float(dist.max())
    p0, p1 = c + t[inl].min() * direction, c + t[inl].max() * direction
    return p0, p1, int(inl.sum()), float(dist.max())


def _chord_farthest(points: np.ndarray) -> int:
    """Interior index furthest from the chord joining the first and last point (3-D)."""
    a, b = points[0], points[-1]
    ab = b - a
    q = points - a
    nab = np.linalg.norm(ab)
    if nab < 1e-9:
        dist = np.linalg.norm(q, axis=1)
    else:
        dist = np.linalg.norm(np.cross(q, ab / nab), axis=1)
    dist[[0, -1]] = -1.0
    return int(np.argmax(dist))


def _segment_lines(
    pts: np.ndarray, params: LineParams, split_at_outliers: bool
) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Fit lines to one tangent-split segment; (inferred) if some point lies further than
    ``end_distance_m`` from the fit, split at the point furthest from the chord and recurse
    (split-and-merge), so a corner the tangent test missed still separates two walls."""
    out = []
    stack = [(0, pts.shape[0])]
    while stack:
        a, b = stack.pop()
        seg = pts[a:b]
        if seg.shape[0] < 3:
            continue
        if np.linalg.norm(seg[-1] - seg[0]) < params.min_length_m and np.ptp(
            seg, axis=0
        ).max() < params.min_length_m:
            continue
        p0, p1, n_in, dmax = fit_line(seg, params.end_distance_m)
        if split_at_outliers and dmax > params.end_distance_m and seg.shape[0] > 4:
            k = a + _chord_farthest(seg)
            stack.extend([(a, k + 1), (k, b)])
            continue
        out.append((p0, p1, n_in))
    return out


def extract_line_segments(
    image: RangeImage,
    params: LineParams,
    *,
    max_beams: int = 100_000,
    step_fraction: float = 0.5,
    hit_margin_m: float | None = None,
    min_wall_extent_m: float = 0.5,
    top_tolerance_m: float | None = None,
    wall_depth_cells: int = 2,
    border_xy: Literal["hits", "edge", "centre"] = "hits",
    link_cells: int = 2,
    split_at_outliers: bool = True,
) -> pd.DataFrame:
    """Horizontal wall/ceiling border lines of one scan (spec 5, Th. 4.7, Table 4.3).

    Returns the shared line-segment table ``line_id, x0, y0, z0, x1, y1, z1, n_points,
    length_m`` in the levelled scan frame; empty (well-formed) when ``params.enabled`` is False
    or the image has no returns. Keyword arguments are the inferred choices documented in
    :func:`occupancy_grid`, :func:`border_cells` and :func:`_segment_lines`.
    """
    if not params.enabled or not image.valid.any():
        return empty_line_table()
    grid = occupancy_grid(
        image,
        params.cell_m,
        params.max_range_m,
        max_beams=max_beams,
        step_fraction=step_fraction,
        hit_margin_m=hit_margin_m,
    )
    hits = image.xyz[image.valid & (image.range_m <= params.max_range_m)]
    border = border_cells(
        grid,
        hits,
        min_wall_extent_m=min_wall_extent_m,
        top_tolerance_m=top_tolerance_m,
        wall_depth_cells=wall_depth_cells,
        border_xy=border_xy,
    )
    if len(border) < 3:
        return empty_line_table()
    pts_all = border[["x", "y", "z"]].to_numpy()
    ix, iy = border["ix"].to_numpy(), border["iy"].to_numpy()

    found: list[tuple[np.ndarray, np.ndarray, int]] = []
    for chain in border_chains(ix, iy, min_cells=3, link_cells=link_cells):
        gap = max(abs(ix[chain[0]] - ix[chain[-1]]), abs(iy[chain[0]] - iy[chain[-1]]))
        closed = chain.size > 4 and gap <= link_cells
        pts = pts_all[chain]
        angles = turning_angles(pts, params.tangent_interval_m, closed=closed)
        splits = tangent_splits(angles, params.tangent_change_deg)
        if closed and splits.size:
            pts = np.roll(pts, -splits[0], axis=0)
            splits = splits - splits[0]
        bounds = np.unique(np.concatenate([[0], splits, [pts.shape[0]]]))
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            found.extend(_segment_lines(pts[a:b], params, split_at_outliers))

    if not found:
        return empty_line_table()
    p0 = np.array([f[0] for f in found])
    p1 = np.array([f[1] for f in found])
    n_pts = np.array([f[2] for f in found], dtype=np.int64)
    d = p1 - p0
    length = np.linalg.norm(d, axis=1)
    incl = np.degrees(np.arctan2(np.abs(d[:, 2]), np.hypot(d[:, 0], d[:, 1])))
    keep = (length >= params.min_length_m) & (incl <= params.max_inclination_deg) & (n_pts >= 2)
    if not keep.any():
        return empty_line_table()
    order = np.argsort(-length[keep], kind="stable")
    p0, p1 = p0[keep][order], p1[keep][order]
    n_pts, length = n_pts[keep][order], length[keep][order]
    return pd.DataFrame(
        {
            "line_id": np.arange(p0.shape[0], dtype=np.int64),
            "x0": p0[:, 0],
            "y0": p0[:, 1],
            "z0": p0[:, 2],
            "x1": p1[:, 0],
            "y1": p1[:, 1],
            "z1": p1[:, 2],
            "n_points": n_pts,
            "length_m": length,
        },
        columns=LINE_COLUMNS,
    )
