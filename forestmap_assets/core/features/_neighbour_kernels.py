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
    def _first_at_least(a, v, right):  # pragma: no cover - compiled
        """np.searchsorted(a, v, "right" if right else "left")."""
        lo, hi = 0, a.size
        while lo < hi:
            mid = (lo + hi) >> 1
            if a[mid] < v or (right and a[mid] == v):
                lo = mid + 1
            else:
                hi = mid
        return lo

    @njit(cache=True)
    def _run(by_c1, by_c0, q, width, c0, c1):  # pragma: no cover - compiled
        lo = _first_at_least(by_c1, q * width + c0, False)
        hi = _first_at_least(by_c0, q * width + c1, True)
        return lo, hi

    @njit(cache=True, parallel=True)
    def nb_neighbour_pairs(by_c1, by_c0, order, key, row, col0, col1, k_rows, nrows,
                           width):  # pragma: no cover - compiled
        """Pairs (s, t) of :func:`.segment_neighbours.neighbour_pairs` from its sorted keys:
        for each s the rows ``row[s] - k .. row[s] + k`` of its chain in turn, each row's run of
        overlapping segments found by two binary searches and listed by index (so the pairs
        come out sorted by s, then (chain, row), then t, as the numpy listing's lexsort puts
        them). Segments in parallel, each writing its own slice."""
        n = key.size
        count = np.zeros(n, np.int64)
        for s in prange(n):
            k = k_rows[s]
            c = 0
            for d in range(-k, k + 1):
                r = row[s] + d
                if r < 0 or r >= nrows:
                    continue
                lo, hi = _run(by_c1, by_c0, key[s] + d, width, col0[s], col1[s])
                c += max(hi - lo, 0)
            count[s] = c
        start = np.zeros(n + 1, np.int64)
        for s in range(n):
            start[s + 1] = start[s] + count[s]
        ps = np.empty(start[n], np.int64)
        pt = np.empty(start[n], np.int64)
        for s in prange(n):
            k = k_rows[s]
            m = start[s]
            for d in range(-k, k + 1):
                r = row[s] + d
                if r < 0 or r >= nrows:
                    continue
                lo, hi = _run(by_c1, by_c0, key[s] + d, width, col0[s], col1[s])
                m0 = m
                for a in range(lo, hi):  # the run by index: insertion sort in place (short runs)
                    v = order[a]
                    b = m
                    while b > m0 and pt[b - 1] > v:
                        pt[b] = pt[b - 1]
                        b -= 1
                    pt[b] = v
                    ps[m] = s
                    m += 1
        return ps, pt

else:  # pragma: no cover
    nb_neighbour_pairs = None
