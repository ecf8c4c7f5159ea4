"""The thesis's plain branch and bound (``method='thesis'``, spec 6.4, Eq. 5.11-5.14, Th. ch. 5)
and the exhaustive lattice search it must agree with (spec 13.4).

Level-synchronous divide and conquer: every level halves the longest dimension of all surviving
cells, evaluates each new cell at its evaluation point with k-d tree nearest distances of every
point (:class:`KdEvaluator`) and bounds it over the whole cell with
``sum_i ln p(max(D_i - Delta_i, 0))``, ``Delta_i = |e_xyz| + 2 d_i sin(e_h / 2)``; cells whose
bound is below the best score so far are pruned (ties survive). Coarse levels are bounded with
voxel clusters of B's points, and points whose term is ``ln k1`` in every cell of a level are
dropped (inferred speed-ups that do not change the result). The pruned mass of the peak-mass
share (spec 6.7) keeps the bound-weighted, conservative form here."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from forestmap_assets.core.registration.first_hypotheses import refine_local
from forestmap_assets.core.registration.score import ScoreModel
from forestmap_assets.core.registration.search_lattice import (
    SearchLattice,
    _extent,
    _logsumexp,
    point_clusters,
    to_output_pose,
)


class KdEvaluator:
    """The thesis's plain evaluation (spec 6.4): nearest distances of every point by k-d tree."""

    def __init__(self, reference: np.ndarray, model: ScoreModel, chunk: int = 400_000):
        self.tree = cKDTree(reference)
        self.model = model
        self.cap = model.cap_m
        self.chunk = chunk

    def __call__(
        self,
        poses,
        points,
        delta,
        score=True,
        bound=True,
        rot=None,
        e_box=None,
        weight=None,
        active=None,
    ):
        model = self.model
        n = len(points)
        w = np.ones(n) if weight is None else weight
        out_s = np.full(len(poses), np.nan)
        out_b = np.full(len(poses), np.nan)
        per = max(1, self.chunk // max(n, 1))
        for a in range(0, len(poses), per):
            p = poses[a : a + per]
            c, s = np.cos(p[:, 3]), np.sin(p[:, 3])
            q = np.empty((len(p), n, 3))
            q[..., 0] = c[:, None] * points[:, 0] - s[:, None] * points[:, 1] + p[:, 0, None]
            q[..., 1] = s[:, None] * points[:, 0] + c[:, None] * points[:, 1] + p[:, 1, None]
            q[..., 2] = points[:, 2] + p[:, 2, None]
            d = self.tree.query(q.reshape(-1, 3), distance_upper_bound=self.cap + delta.max())[0]
            d = d.reshape(len(p), n)
            if score:
                out_s[a : a + per] = model.log_p(d) @ w
            if bound:
                r = np.maximum(d - delta, 0.0)
                out_b[a : a + per] = model.log_p(r) @ w
                if active is not None:
                    active |= np.any(r < self.cap, axis=0).astype(np.uint8)
        return out_s, out_b


def _branch_and_bound(
    points,
    lattice: SearchLattice,
    evaluate,
    beam_width=0,
    keep_levels=True,
    seeds=None,
    cluster_ratio=0.25,
    ln_k1=0.0,
    score_top=32,
    tree=None,
    n_refine=16,
    refine_at_m=(2.5, 1.2, 0.6),
):
    """Level-synchronous search (spec 6.4); returns final cells, scores, bounds and bookkeeping.

    Levels whose translation half-diagonal ``|e|`` is at least ``1/cluster_ratio`` times a point
    cluster's radius are bounded with voxel clusters of B's points (weight = member count,
    displacement + cluster radius; score not evaluated there: NaN). Points whose bound term is
    ``ln k1`` in every cell of a level are dropped from deeper levels (their term is exactly
    ``ln k1`` below; inferred speed-ups that do not change the result).
    """
    d_xy_all = np.hypot(points[:, 0], points[:, 1])
    schedule = lattice.schedule()
    n_eval = 0
    clusters = []
    for v in (1.6, 0.8, 0.4, 0.2, 0.1):
        rep, cnt, rad = point_clusters(points, v)
        if len(rep) < 0.7 * len(points):
            clusters.append((float(rad.max()), rep, cnt, rad))
    state = dict(pts=points, d_xy=d_xy_all, offset=0.0)

    def ev(idx, size, track=False):
        """(scores, bounds) of cells; clusters at coarse levels; updates the active point set."""
        nonlocal n_eval
        n_eval += len(idx)
        e = _extent(lattice, size)
        t_ext = float(np.sqrt(np.sum(e[:3] ** 2)))
        sin_h = np.sin(min(e[3], np.pi) / 2.0)
        poses = lattice.pose(idx + size // 2)
        for r_max, rep, cnt, rad in clusters:
            if r_max <= cluster_ratio * t_ext:
                d_rep = np.hypot(rep[:, 0], rep[:, 1])
                delta = t_ext + 2.0 * d_rep * sin_h + rad
                _, b = evaluate(poses, rep, delta, score=False, bound=True, weight=cnt)
                s = np.full(len(idx), np.nan)
                top = np.argsort(-b)[:score_top]  # scores of the most promising cells only
                s[top] = (
                    evaluate(poses[top], state["pts"], np.zeros(len(state["pts"])), bound=False)[0]
                    + state["offset"]
                )
                return s, b
        pts, d_xy = state["pts"], state["d_xy"]
        active = np.zeros(len(pts), np.uint8) if track else None
        s, b = evaluate(
            poses,
            pts,
            t_ext + 2.0 * d_xy * sin_h,
            rot=2.0 * d_xy * sin_h,
            e_box=e[:3],
            active=active,
        )
        s, b = s + state["offset"], b + state["offset"]
        if track and active.sum() < len(pts):
            drop = active == 0
            state["offset"] += float(drop.sum()) * ln_k1
            state["pts"], state["d_xy"] = pts[~drop], d_xy[~drop]
        return s, b

    start = (lattice.n // 2)[None, :]
    if seeds is not None and len(seeds):
        start = np.vstack([start, lattice.nearest_index(seeds)])
    best = float(np.max(ev(start, np.ones(4, np.int64))[0]))
    size = lattice.n.copy()
    cells = np.zeros((1, 4), np.int64)
    # cell sizes after each level
    sizes = []
    sz = lattice.n.copy()
    for k in schedule:
        sz = sz.copy()
        sz[k] //= 2
        sizes.append(sz)

    def beam(width):
        """Inferred first hypothesis: the search with only the ``width`` highest-bound cells
        kept per level (not exhaustive; it only raises ``best``)."""
        nonlocal best
        cells_b = np.zeros((1, 4), np.int64)
        for lv, k in enumerate(schedule):
            sz = sizes[lv]
            cells_b = np.concatenate([cells_b, cells_b + np.eye(4, dtype=np.int64)[k] * sz[k]])
            s, b = ev(cells_b, sz)
            best = max(best, float(np.nanmax(s, initial=-np.inf)))
            keep = b >= best
            cells_b, b = cells_b[keep], b[keep]
            if len(cells_b) > width:
                cells_b = cells_b[np.argpartition(-b, width)[:width]]

    if beam_width:
        beam(beam_width)
    level_rows = []
    pruned_lse = []
    refined = 0
    scores = bounds = np.array([best])
    for li, k in enumerate(schedule):
        size = sizes[li]
        cells = np.concatenate([cells, cells + np.eye(4, dtype=np.int64)[k] * size[k]])
        scores, bounds = ev(cells, size, track=True)
        best = max(best, float(np.nanmax(scores, initial=-np.inf)))
        cell_m = float(np.max(size * lattice.step * lattice.metric_scale))
        if tree is not None and refined < len(refine_at_m) and cell_m <= refine_at_m[refined]:
            while refined < len(refine_at_m) and cell_m <= refine_at_m[refined]:
                refined += 1
            top = np.argsort(-bounds)[:n_refine]
            starts = lattice.pose(cells[top] + size // 2)
            found = np.array([refine_local(points, tree, p0) for p0 in starts])
            idx = lattice.nearest_index(found)
            best = max(best, float(np.max(ev(idx, np.ones(4, np.int64))[0])))
        keep = bounds >= best
        vol = float(np.prod(size))
        pruned_lse.append(_logsumexp(bounds[~keep]) + np.log(vol) if (~keep).any() else -np.inf)
        cells, scores, bounds = cells[keep], scores[keep], bounds[keep]
        if keep_levels:
            level_rows.append((li, size.copy(), cells + size // 2, scores, bounds))
    if not schedule:
        scores, bounds = ev(cells, size)
        if keep_levels:
            level_rows.append((0, size.copy(), cells, scores, bounds))
    keep = bounds >= best  # the last best may have come after the last prune
    return dict(
        cells=cells[keep],
        scores=scores[keep],
        bounds=bounds[keep],
        best=best,
        pruned_lse=pruned_lse,
        level_rows=level_rows,
        n_eval=n_eval,
    )


def exhaustive_search(
    scan_points: np.ndarray, reference_points: np.ndarray, centre, half_widths, params=None
) -> tuple[np.ndarray, np.ndarray]:
    """Every final-lattice pose of the box (k, 4: dx, dy, dz, dh_deg) and its exact score by
    k-d tree (the reference for spec 13.4); only for small problems."""
    from forestmap_assets.params import RegistrationParams

    params = params or RegistrationParams()
    scan = np.asarray(scan_points, dtype=float).reshape(-1, 3)
    ref = np.asarray(reference_points, dtype=float).reshape(-1, 3)
    d_bar = float(np.mean(np.hypot(scan[:, 0], scan[:, 1])))
    lattice = SearchLattice.build(centre, half_widths, params.final_cell_m, d_bar)
    idx = np.array(np.meshgrid(*[np.arange(v) for v in lattice.n], indexing="ij")).reshape(4, -1).T
    poses = lattice.pose(idx)
    ev = KdEvaluator(ref, ScoreModel.from_params(params))
    s, _ = ev(poses, scan, np.zeros(len(scan)), score=True, bound=False)
    return to_output_pose(poses), s
