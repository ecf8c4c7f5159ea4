"""Compiled listing of a segment's neighbours (:func:`.segment_neighbours.neighbour_pairs`),
cached on disk; ``HAVE_NUMBA`` says whether it exists."""

from __future__ import annotations

import numpy as np

try:
    from numba import njit, prange

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba is a dependency; the numpy listing remains
    HAVE_NUMBA = False

if HAVE_NUMBA:

    @njit(cache=True, inline="always")
    def _first_in(a, lo, hi, v, right):  # pragma: no cover - compiled
        """np.searchsorted(a[lo:hi], v, "right" if right else "left") + lo."""
        while lo < hi:
            mid = (lo + hi) >> 1
            if a[mid] < v or (right and a[mid] == v):
                lo = mid + 1
            else:
                hi = mid
        return lo

    @njit(cache=True, parallel=True)
    def nb_neighbour_pairs(c0s, c1s, order, cell_of_row, row_lo, row_hi, chain, run_start, row, col0,
                           col1, k_rows):  # pragma: no cover - compiled
        """Pairs (s, t) of :func:`.segment_neighbours.neighbour_pairs`: for each s the rows
        ``row[s] - k .. row[s] + k`` of its chain in turn. The segments sorted by (chain, row,
        col0) have their column starts ``c0s`` and ends ``c1s`` (both ascending within a row);
        a chain's rows ``row_lo .. row_hi`` are the cells ``cell_of_row[chain] + row - row_lo``
        of ``run_start``, so a row's run of segments is found without a search, and its
        overlapping ones by two binary searches within the run. Listed by index (so the pairs
        come out sorted by s, then (chain, row), then t, as the numpy listing's lexsort puts
        them). Segments in parallel, each writing its own slice."""
        n = chain.size
        count = np.zeros(n, np.int64)
        for s in prange(n):
            k = k_rows[s]
            ch = chain[s]
            c = 0
            for r in range(max(row[s] - k, row_lo[ch]), min(row[s] + k, row_hi[ch]) + 1):
                cell = cell_of_row[ch] + r - row_lo[ch]
                a, b = run_start[cell], run_start[cell + 1]
                lo = _first_in(c1s, a, b, col0[s], False)
                hi = _first_in(c0s, lo, b, col1[s], True)
                c += max(hi - lo, 0)
            count[s] = c
        start = np.zeros(n + 1, np.int64)
        for s in range(n):
            start[s + 1] = start[s] + count[s]
        ps = np.empty(start[n], np.int64)
        pt = np.empty(start[n], np.int64)
        for s in prange(n):
            k = k_rows[s]
            ch = chain[s]
            m = start[s]
            for r in range(max(row[s] - k, row_lo[ch]), min(row[s] + k, row_hi[ch]) + 1):
                cell = cell_of_row[ch] + r - row_lo[ch]
                a, b = run_start[cell], run_start[cell + 1]
                lo = _first_in(c1s, a, b, col0[s], False)
                hi = _first_in(c0s, lo, b, col1[s], True)
                m0 = m
                for j in range(lo, hi):  # the run by index: insertion sort in place (short runs)
                    v = order[j]
                    i = m
                    while i > m0 and pt[i - 1] > v:
                        pt[i] = pt[i - 1]
                        i -= 1
                    pt[i] = v
                    ps[m] = s
                    m += 1
        return ps, pt

else:  # pragma: no cover
    nb_neighbour_pairs = None
