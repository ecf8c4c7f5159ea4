"""Neighbouring segments of a circle model (spec 3.2, "overlapping segments above and below"):
for each segment, the segments of its chain within a number of rows whose column intervals
overlap its own (used by :mod:`.circle_models`, whose ``_SegData`` carries ``row``, ``chain``,
``col0`` and ``col1``)."""

from __future__ import annotations

import numpy as np

from forestmap_assets.core.features._neighbour_kernels import HAVE_NUMBA, nb_neighbour_pairs


def neighbour_pairs(sd, k_rows: np.ndarray, compiled: bool = True,
                    layout: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (s, t): t in the chain of s, |row_t - row_s| <= k_rows[s], column intervals overlap
    (spec 3.2, "overlapping segments above and below"). Sorted by s, then as the segments'
    (chain, row) and index; includes (s, s).

    The segments of one row of a chain are disjoint column intervals, so in (chain, row, col0)
    order their ``col1`` ascend too and the ones overlapping [col0_s, col1_s] in a row are one
    run found by two binary searches per row offset: the work follows the pairs, not the
    segments a row holds (a fine render's ground chain has up to 100 a row; listing every
    segment of the rows and filtering took 5 s of a 16 s scan). ``compiled``: the runs listed by
    the numba kernel where it exists (the same pairs), which finds a row's segments in a table
    of each chain's rows (:func:`_row_cells`) and searches only among them: on a scan rendered
    inside a registered cloud (88 k segments, 5.4 M pairs over a run's four phases) 0.75 s on
    one thread when both searches spanned every segment, 0.18 s now; else in numpy.
    ``layout``: :func:`segment_layout` of ``sd``, when the caller keeps it for several calls
    (the circle models' phases: only the rows within reach change)."""
    n = sd.row.size
    nrows, key, order, width, by_c1, cells = layout or segment_layout(sd)
    if cells is None:  # overlapping segments in a row: the plain listing
        return neighbour_pairs_listed(sd, k_rows, key)
    k_max = int(k_rows.max(initial=-1))
    if k_max < 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    c0 = sd.col0[order]
    if compiled and HAVE_NUMBA:
        i64 = lambda a: np.ascontiguousarray(a, dtype=np.int64)  # noqa: E731
        return nb_neighbour_pairs(i64(c0), i64(sd.col1[order]), i64(order), *cells,
                                  i64(sd.row), i64(sd.col0), i64(sd.col1), i64(k_rows))
    by_c0 = key[order] * width + c0
    offs = np.arange(-k_max, k_max + 1)
    s = np.repeat(np.arange(n), offs.size)
    d = np.tile(offs, n)
    sel = np.abs(d) <= k_rows[s]
    s, d = s[sel], d[sel]
    row = sd.row[s] + d
    inside = (row >= 0) & (row < nrows)  # not into the rows of the next or previous chain
    s, q = s[inside], (key[s] + d)[inside]
    lo = np.searchsorted(by_c1, q * width + sd.col0[s], "left")
    hi = np.searchsorted(by_c0, q * width + sd.col1[s], "right")
    cnt = np.maximum(hi - lo, 0)
    ps = np.repeat(s, cnt)
    first = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    pt = order[np.repeat(lo, cnt) + (np.arange(ps.size) - np.repeat(first, cnt))]
    ordered = np.lexsort((pt, key[pt], ps))
    return ps[ordered], pt[ordered]


def segment_layout(sd) -> tuple:
    """What :func:`neighbour_pairs` needs of the segments ``sd`` whatever the rows within reach:
    ``(nrows, key, order, width, by_c1, cells)``: ``key`` chain and row, ``order`` the (chain,
    row, col0) order, ``by_c1`` the sorted segments' (key, col1) codes, ``cells`` the chains'
    rows (:func:`_row_cells`), None where a row holds overlapping segments (``by_c1`` does not
    ascend)."""
    nrows = int(sd.row.max()) + 2
    key = sd.chain * nrows + sd.row
    order = np.lexsort((sd.col0, key))
    width = int(max(sd.col1.max(), sd.col0.max())) + 2
    by_c1 = key[order] * width + sd.col1[order]
    disjoint = not np.any(np.diff(by_c1) < 0)
    cells = _row_cells(sd.chain, sd.row, order) if disjoint else None
    return nrows, key, order, width, by_c1, cells


def _row_cells(chain: np.ndarray, row: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, ...]:
    """Where each chain's rows start among the segments sorted by (chain, row) (``order``): a
    dense index ``chain_idx`` of the chains, their rows ``row_lo .. row_hi``, the first cell
    ``cell_of_row`` of each chain's rows, and ``run_start`` (cells + 1): the sorted position of
    each cell's first segment, so row ``r`` of chain ``c`` holds the sorted segments
    ``run_start[cell] .. run_start[cell + 1]`` with ``cell = cell_of_row[c] + r - row_lo[c]``.
    Returns ``cell_of_row, row_lo, row_hi, chain_idx, run_start``."""
    chains, chain_idx = np.unique(chain, return_inverse=True)
    chain_idx = chain_idx.astype(np.int64).ravel()
    row = np.asarray(row, np.int64)
    row_lo = np.full(chains.size, np.iinfo(np.int64).max, np.int64)
    row_hi = np.full(chains.size, -1, np.int64)
    np.minimum.at(row_lo, chain_idx, row)
    np.maximum.at(row_hi, chain_idx, row)
    cell_of_row = np.concatenate([[0], np.cumsum(row_hi - row_lo + 1)]).astype(np.int64)
    c = chain_idx[order]
    cells = cell_of_row[c] + row[order] - row_lo[c]
    run_start = np.searchsorted(cells, np.arange(cell_of_row[-1] + 1)).astype(np.int64)
    return cell_of_row[:-1].copy(), row_lo, row_hi, chain_idx, run_start


def neighbour_pairs_listed(sd, k_rows: np.ndarray, key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`neighbour_pairs` by listing every segment of the rows within reach and keeping
    the overlapping ones (for rows whose segments overlap)."""
    n = sd.row.size
    order = np.argsort(key, kind="stable")
    skey = key[order]
    lo = np.searchsorted(skey, key - k_rows, "left")
    hi = np.searchsorted(skey, key + k_rows, "right")
    cnt = np.maximum(hi - lo, 0)
    s = np.repeat(np.arange(n), cnt)
    first = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    t = order[lo[s] + (np.arange(s.size) - first[s])]
    ok = (sd.chain[t] == sd.chain[s]) & (sd.col0[t] <= sd.col1[s]) & (sd.col1[t] >= sd.col0[s])
    return s[ok], t[ok]
