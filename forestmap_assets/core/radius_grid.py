"""The nearest point within a small radius, for the fine registration's point pairs (issue 16,
inferred): the points sorted into vertical columns of a square grid, each column by height.

A query visits the columns its radius reaches and, in each, the points between its height minus
and plus the radius (a binary search). It gives what a k-d tree's nearest-neighbour query with a
distance bound gives (``cKDTree.query(q, distance_upper_bound=r)``: the same rows and distances,
``inf`` and ``n`` where no point is nearer than ``r``), 2-3.5 times faster on a levelled scan's
thinned points, whose stems and ground fill few of a column's heights."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from forestmap_assets.core._cloud_kernels import bounds
from forestmap_assets.core._radius_grid_kernels import build_columns, nearest_within

MAX_COLUMNS = 1 << 24  # a wider cloud gets wider columns (the queries stay exact)


class RadiusGrid:
    """``points`` (n, 3) in columns of ``cell_m`` (about the largest query radius: a query then
    visits at most 3 x 3 columns). ``data`` and ``n`` as a ``cKDTree``'s."""

    def __init__(self, points: np.ndarray, cell_m: float):
        self.data = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        self.n = len(self.data)
        if not cell_m > 0:
            raise ValueError(f"cell_m: must be positive, got {cell_m}")
        self.lo, self.hi, finite = bounds(self.data) if self.n else (np.zeros(3), np.zeros(3), True)
        if not finite:
            raise ValueError("points: a radius grid needs finite points")
        span = (self.hi - self.lo)[:2]
        cell = float(cell_m)
        while np.prod(np.floor(span / cell) + 1) > MAX_COLUMNS:
            cell *= 2.0
        self.cell = cell
        self.nx, self.ny = (int(v) + 1 for v in np.floor(span / cell))
        self._start, self._order, self._points = build_columns(self.data, self.lo, cell, self.nx, self.ny)

    @property
    def columns(self) -> tuple:
        """What the grid's kernels read: the sorted points, their input rows, the column
        offsets, the grid's corner, cell and size (``nx``, ``ny``)."""
        return self._points, self._order, self._start, self.lo, self.cell, self.nx, self.ny

    def query(self, points: np.ndarray, radius_m: float, rows: np.ndarray | None = None):
        """Distance to the nearest point nearer than ``radius_m`` and its row (``inf`` and
        :attr:`n` where there is none) for each of ``points``; with ``rows``, only for those
        (the others are ``inf`` and :attr:`n`)."""
        q = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        d = np.full(len(q), np.inf)
        idx = np.full(len(q), self.n, dtype=np.int64)
        if self.n == 0 or len(q) == 0:
            return d, idx
        sel = np.arange(len(q), dtype=np.int64) if rows is None else np.asarray(rows, dtype=np.int64)
        nearest_within(q, sel, float(radius_m), self._points, self._order, self._start, self.lo,
                       self.cell, self.nx, self.ny, d, idx)
        return d, idx


def nearest(index: RadiusGrid | cKDTree, points: np.ndarray, radius_m: float, rows: np.ndarray | None = None,
            workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Distance and row of each point's nearest ``index`` point nearer than ``radius_m`` (``inf``
    and ``index.n`` where none is), from a grid or a k-d tree (its query on ``workers``
    threads); with ``rows``, only for those points (the others: none)."""
    if isinstance(index, RadiusGrid):
        return index.query(points, radius_m, rows)
    if rows is None:
        return index.query(points, distance_upper_bound=radius_m, workers=workers)
    d, idx = np.full(len(points), np.inf), np.full(len(points), index.n)
    d[rows], idx[rows] = index.query(points[rows], distance_upper_bound=radius_m, workers=workers)
    return d, idx
