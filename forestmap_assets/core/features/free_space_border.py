"""Border between free and unknown/occupied space (spec 5 steps 2-3; Th. 4.7, Fig. B.17, inferred
details): border cells projected to a 2-D (x, y) border-height image (the highest recorded hit),
then ordered chains ("point data queues") of consecutive border cells."""

from __future__ import annotations

from typing import Literal

import numpy as np
import pandas as pd
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from forestmap_assets.core.features.occupancy_grid import OccupancyGrid

BORDER_COLUMNS = ["ix", "iy", "x", "y", "z", "top_free_z"]


# 4-neighbour offsets (step 2).
_N4 = ((1, 0), (-1, 0), (0, 1), (0, -1))


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
