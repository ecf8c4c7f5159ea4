"""The fast branch and bound (``method='fast'``, default; spec 6.4 with inferred exact speed-ups)
on a :class:`~.score_field.ReferenceField`.

Coarse levels are bounded with voxel clusters of B's points; below, every cell carries the list of
its *live* points (a point whose distance lower bound is ``>= cap`` everywhere in a cell scores
exactly ``ln k1`` in all its sub-cells, so it is dropped from them), evaluated in memory-bounded
chunks of ``LIVE_CHUNK`` entries. Fine levels use the per-axis ("tighter", spec 6.4) bound over the
cell's exact (asymmetric) offset box with the per-axis range of each point's rotation
displacement, never above the point's term in the parent cell (whose running sum stops a child
early once it cannot reach the best). **Lattice bound** (default, ``bound='lattice'``, inferred):
only lattice scores compete, so each cell is bounded over its final-lattice poses (a single final
cell's bound is its score): same lattice maximum, 2-3x fewer cell-point evaluations on forest
pairs. Cells within ``lattice_margin`` of the best survive; the clouds are then grown by a flood
fill with exact scores to every connected final cell within ``cloud_margin`` of the best
(:func:`grow_cloud`), the cloud of the JP eq. 6 statistics and of the calibrated sigmas of
:mod:`.pair_registrations` (which then match the cell bound's: pair error/sd RMS
0.95/0.84/0.63/1.53 vs 0.93/0.82/0.63/1.57 on 30 quarter-resolution pairs). The pruned mass of the
peak-mass share uses the scores at the pruned cells' evaluation points (spec 6.7, inferred). A
reference sub-map's field is built once per process and reused by every pair it is the reference
of (:func:`reference_field`)."""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np

from forestmap_assets.core.radius_grid import RadiusGrid
from forestmap_assets.core.registration.first_hypotheses import (
    _FACE,
    _first_hypotheses,
    refine_local,
)
from forestmap_assets.core.registration.score import ScoreModel
from forestmap_assets.core.registration.search_lattice import (
    SearchLattice,
    _extent,
    _lattice_extent,
    _logsumexp,
    _offset_box,
    point_clusters,
)

LIVE_CHUNK = 4_000_000  # live entries per evaluation chunk (memory bound, inferred)
LOCAL_GRID_CELL_M = 0.3  # columns of the reference's radius grid (refine_local's radii 0.15-0.6 m)


def _eval_live_chunked(
    field,
    poses,
    par,
    off,
    idx,
    pts,
    d_xy,
    e,
    tight,
    best,
    limit=None,
    margin=0.0,
    lo=None,
    hi=None,
    terms=None,
    par_bound=None,
):
    """:meth:`~.score_field.ReferenceField.eval_live` over chunks of at most ``limit`` live
    entries (bounded memory); each chunk keeps the live lists of its cells whose bound reaches
    the best score known so far (raised by the chunk's quick scores). Returns bounds, quick
    scores, the mask of cells with lists (a superset of the level's survivors) and their CSR.
    ``margin``: cells whose bound reaches ``best - margin`` survive (``bound='lattice'``).
    With ``lo``/``hi`` (the asymmetric bound) the parents' per-point ``terms`` (aligned with
    ``idx``) and bounds ``par_bound`` tighten and stop the children early; the kept cells'
    terms are returned as a sixth result (None otherwise)."""
    from forestmap_assets.core.registration.score_field import compact_live

    limit = LIVE_CHUNK if limit is None else limit
    n = len(poses)
    csum = np.cumsum(np.diff(off)[par])
    bounds, scores = np.empty(n), np.empty(n)
    pre = np.zeros(n, bool)
    offs, lives, tvals, total, start = [np.zeros(1, np.int64)], [], [], 0, 0
    while start < n:
        base = csum[start - 1] if start else 0
        end = max(start + 1, int(np.searchsorted(csum, base + limit, side="right")))
        out = field.eval_live(
            poses[start:end],
            par[start:end],
            off,
            idx,
            pts,
            d_xy,
            e,
            tight,
            lo=lo,
            hi=hi,
            par_terms=terms,
            par_bound=par_bound,
            thresh=best - margin,
        )
        b, s, c_off, c_cnt, c_live = out[:5]
        bounds[start:end], scores[start:end] = b, s
        best = max(best, float(np.max(s)))
        k = b >= best - margin
        pre[start:end] = k
        o, lv = compact_live(k, c_off, c_cnt, c_live)
        if len(out) > 5:
            tvals.append(compact_live(k, c_off, c_cnt, out[5])[1])
        offs.append(o[1:] + total)
        lives.append(lv)
        total += len(lv)
        start = end
    t_all = np.concatenate(tvals) if tvals else None
    return bounds, scores, pre, np.concatenate(offs), np.concatenate(lives), t_all


def _fast_search(
    points,
    reference,
    lattice: SearchLattice,
    model,
    field,
    keep_levels=True,
    starts=None,
    cluster_ratio=0.1,
    score_top=8,
    tight=True,
    n_refine=8,
    refine_at_m=(),
    max_cells=60_000,
    lattice_bound=False,
    margin=0.0,
    heading_scale=1.0,
):
    """Level-synchronous search (spec 6.4) on a :class:`~.score_field.ReferenceField` with live
    points per cell (:func:`~.score_field.eval_live`), started from the best of ``starts``.

    Coarse levels (translation half-diagonal at least ``1/cluster_ratio`` times a point
    cluster's radius) are bounded with voxel clusters of B's points; the quick score (a lower
    bound of the exact lattice score) is evaluated for the ``score_top`` highest-bound cells
    there and for every cell below. Final cells get exact scores. ``refine_at_m``: as in the
    plain search, ICP from the best cells when cells first get smaller than these sizes.
    More than ``max_cells`` survivors at a level (an ambiguous problem: too few distinctive
    points for the box, inferred budget) stop the search: returns ``{"aborted": reason}``.
    ``lattice_bound``: bound each cell over its final-lattice points only
    (:func:`_lattice_extent`) and keep cells whose bound reaches ``best - margin``.
    """
    from forestmap_assets.core.registration.score_field import compact_live

    pts = np.ascontiguousarray(points, dtype=np.float64)
    n = len(pts)
    d_xy = np.hypot(pts[:, 0], pts[:, 1])
    tree = RadiusGrid(reference, LOCAL_GRID_CELL_M)  # refine_local's partners, as a k-d tree's
    schedule = lattice.schedule(heading_scale)
    sizes, sz = [], lattice.n.copy()
    for k in schedule:
        sz = sz.copy()
        sz[k] //= 2
        sizes.append(sz)
    clusters = []
    for v in (1.6, 0.8, 0.4, 0.2, 0.1):
        rep, cnt, rad = point_clusters(pts, v)
        if len(rep) < 0.7 * n:
            clusters.append((float(rad.max()), rep, cnt, rad))
    n_eval = 0
    centre_idx = (lattice.n // 2)[None, :]
    start_poses = lattice.pose(centre_idx)
    if starts is not None and len(starts):
        start_poses = np.vstack([start_poses, starts])
    _, best = _first_hypotheses(pts, lattice, field, tree, start_poses)

    root_off = np.array([0, n], np.int64)
    root_idx = np.arange(n, dtype=np.int32)
    live_off = live_idx = None  # None: every cell's parent is the root (all points live)
    cells = np.zeros((1, 4), np.int64)
    level_rows, pruned_lse = [], []
    refined = 0
    plan = list(zip(schedule, sizes, strict=True)) or [(None, lattice.n.copy())]
    bounds = scores = np.zeros(1)
    for li, (k, size) in enumerate(plan):
        m = len(cells)
        if k is not None:
            cells = np.concatenate([cells, cells + np.eye(4, dtype=np.int64)[k] * size[k]])
        parent = np.concatenate([np.arange(m), np.arange(m)]) if k is not None else np.arange(m)
        n_eval += len(cells)
        e = _lattice_extent(lattice, size) if lattice_bound else _extent(lattice, size)
        t_ext = float(np.sqrt(np.sum(e[:3] ** 2)))
        sin_h = np.sin(min(e[3], np.pi) / 2.0)
        poses = lattice.pose(cells + size // 2)
        last = li == len(plan) - 1
        cl = next((c for c in clusters if c[0] <= cluster_ratio * t_ext), None)
        if cl is not None and live_off is None and not last:
            r_max, rep, cnt, rad = cl
            delta = t_ext + 2.0 * np.hypot(rep[:, 0], rep[:, 1]) * sin_h + rad
            s_est, bounds = field.evaluate(poses, rep, delta, weight=cnt)
            scores = np.full(len(cells), np.nan)
            top = np.argsort(-bounds)[:score_top]
            scores[top] = field.evaluate(poses[top], pts, bound=False)[0]
            mass = np.where(np.isnan(scores), s_est, scores)
            new_live = None
        else:
            off, idx = (root_off, root_idx) if live_off is None else (live_off, live_idx)
            par = np.zeros(len(cells), np.int64) if live_off is None else parent
            lo, hi = _offset_box(lattice, size, lattice_bound)
            if live_off is None:
                live_terms = live_bound = None
            bounds, scores, pre, pre_off, pre_live, pre_terms = _eval_live_chunked(
                field,
                poses,
                par,
                off,
                idx,
                pts,
                d_xy,
                e,
                tight,
                best,
                margin=margin,
                lo=lo,
                hi=hi,
                terms=live_terms,
                par_bound=live_bound,
            )
            new_live = (pre, pre_off, pre_live, pre_terms)
            mass = scores
        if last:
            # cells without live lists had bounds below a best raised inside the chunks
            keep0 = (bounds >= best - margin) & pre
            exact = np.full(len(cells), -np.inf)
            if keep0.any():
                lo_, li_ = compact_live(keep0[pre], pre_off[:-1], np.diff(pre_off), pre_live)
                exact[keep0] = field.exact_live(poses[keep0], lo_, li_, pts)
            scores = np.where(keep0, exact, scores)
        best = max(best, float(np.nanmax(scores, initial=-np.inf)))
        cell_m = float(np.max(size * lattice.step * lattice.metric_scale))
        if refined < len(refine_at_m) and cell_m <= refine_at_m[refined] and not last:
            while refined < len(refine_at_m) and cell_m <= refine_at_m[refined]:
                refined += 1
            top = np.argsort(-bounds)[:n_refine]
            found = np.array([refine_local(pts, tree, p0) for p0 in poses[top]])
            idx_f = lattice.nearest_index(found)
            best = max(
                best, float(np.max(field.evaluate(lattice.pose(idx_f), pts, bound=False)[0]))
            )
        keep = bounds >= best - margin
        vol = float(np.prod(size))
        pruned_lse.append(_logsumexp(mass[~keep]) + np.log(vol) if (~keep).any() else -np.inf)
        cells, scores, bounds = cells[keep], scores[keep], bounds[keep]
        if len(cells) > max_cells and not last:
            return dict(
                aborted=f"ambiguous: {len(cells)} cells of {cell_m:.2f} m survive "
                f"(> {max_cells}); too little distinctive overlap for the box"
            )
        if new_live is not None:
            pre, pre_off, pre_live, pre_terms = new_live
            live_off, live_idx = compact_live(keep[pre], pre_off[:-1], np.diff(pre_off), pre_live)
            live_terms = (
                None
                if pre_terms is None
                else compact_live(keep[pre], pre_off[:-1], np.diff(pre_off), pre_terms)[1]
            )
            live_bound = bounds  # the kept cells' bounds, parents of the next level
        if keep_levels:
            level_rows.append((li, size.copy(), cells + size // 2, scores, bounds))
    return dict(
        cells=cells,
        scores=scores,
        bounds=bounds,
        best=best,
        pruned_lse=pruned_lse,
        level_rows=level_rows,
        n_eval=n_eval,
    )


def grow_cloud(
    out: dict,
    field,
    points,
    lattice: SearchLattice,
    seeds: np.ndarray,
    survivors: np.ndarray,
    adjacency: int,
    margin: float,
    max_cells: int,
):
    """Cells (k, 4) and exact scores (k,) that extend the final clouds ``seeds`` of a
    ``bound='lattice'`` search: every final-lattice cell connected to them (``adjacency``; the
    search's ``survivors`` are not added again) whose exact score lies within ``margin`` of the
    best (inferred:
    the cloud the JP eq. 6 statistics and the tempered sigmas of :mod:`.pair_registrations` are
    taken from, which the search alone keeps only within ``lattice_margin``). A flood fill with
    exact scores; it stops at ``max_cells`` cells or ``4 max_cells`` evaluations. The cells are
    also appended to the last level of ``out['level_rows']``."""
    scores = out["scores"]
    none = np.zeros((0, 4), np.int64), np.zeros(0)
    if len(seeds) == 0:
        return none
    n = lattice.n.astype(np.int64)
    mult = np.array([n[1] * n[2] * n[3], n[2] * n[3], n[3], 1], dtype=np.int64)
    if adjacency == 80:
        offs = np.array(np.meshgrid(*[[-1, 0, 1]] * 4, indexing="ij")).reshape(4, -1).T
        offs = offs[np.any(offs != 0, axis=1)]
    else:
        offs = _FACE
    s_star = float(np.max(scores))
    seen = set((survivors @ mult).tolist())
    frontier = seeds
    new_cells, new_scores = [], []
    total = len(survivors)
    budget = 4 * max_cells
    while len(frontier) and total < max_cells:
        nb = (frontier[:, None, :] + offs[None, :, :]).reshape(-1, 4)
        if lattice.wrap:
            nb[:, 3] %= n[3]
        nb = nb[np.all((nb >= 0) & (nb < n), axis=1)]
        keys, first = np.unique(nb @ mult, return_index=True)
        fresh = np.fromiter((k not in seen for k in keys.tolist()), bool, len(keys))
        nb, keys = nb[first[fresh]], keys[fresh]
        if len(nb) == 0 or len(nb) > budget:
            break
        budget -= len(nb)
        seen.update(keys.tolist())
        sc = field.evaluate(lattice.pose(nb), points, bound=False)[0]
        keep = sc >= s_star - margin
        frontier = nb[keep]
        new_cells.append(frontier)
        new_scores.append(sc[keep])
        total += int(keep.sum())
    if not new_cells:
        return none
    add_c = np.concatenate(new_cells)
    add_s = np.concatenate(new_scores)
    if out.get("level_rows"):  # a final lattice cell's bound: its score
        li, size, idx, s_, b_ = out["level_rows"][-1]
        out["level_rows"][-1] = (
            li,
            size,
            np.concatenate([idx, add_c]),
            np.concatenate([s_, add_s]),
            np.concatenate([b_, add_s]),
        )
    return add_c, add_s


_FIELDS: OrderedDict = OrderedDict()


FIELD_CACHE_SIZE = 2  # reference fields kept per process (inferred; tens of MB each)


def reference_field(reference_points: np.ndarray, model: ScoreModel):
    """The :class:`~.score_field.ReferenceField` of a reference sub-map, built once per process
    and reused while the same points come back (every pair a scan is the reference of, e.g. the
    candidate pairs of ``register_candidates``; keyed by a hash of the points and the score
    constants, so a changed sub-map never reuses a stale field)."""
    from forestmap_assets.core.registration.score_field import ReferenceField

    ref = np.ascontiguousarray(reference_points, dtype=np.float64)
    key = (hashlib.blake2b(ref.tobytes(), digest_size=16).hexdigest(), ref.shape, model)
    field = _FIELDS.pop(key, None) or ReferenceField(ref, model)
    _FIELDS[key] = field
    while len(_FIELDS) > FIELD_CACHE_SIZE:
        _FIELDS.popitem(last=False)
    return field
