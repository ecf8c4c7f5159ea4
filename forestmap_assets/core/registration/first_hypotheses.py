"""First hypotheses of the branch and bound (spec 6.4 'initial best', inferred).

The score at the lattice point nearest the a priori pose is raised before the first level by
stem-to-stem votes (:mod:`.stem_voting`, plus any ``seeds``): each refined by a short 4-DoF ICP
(:func:`refine_local`), its height picked from all lattice heights, and the best ones hill-climbed
on the final lattice (:func:`climb`). They only raise the best *lattice* score and never remove a
cell that could win, so the search result does not depend on them (a poor one only costs time)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from forestmap_assets.core.radius_grid import RadiusGrid, nearest
from forestmap_assets.core.registration.search_lattice import SearchLattice


def refine_local(
    scan: np.ndarray, tree: RadiusGrid | cKDTree, pose: np.ndarray, iters: int = 8, radius_m: float = 0.6
) -> np.ndarray:
    """Inferred first-hypothesis helper: a few 4-DoF ICP steps (xy Procrustes + mean dz) from
    ``pose`` (heading radians) with a shrinking matching radius, on the reference's ``tree``
    (a :class:`~forestmap_assets.core.radius_grid.RadiusGrid` finds the same partners 3 times
    faster). Only used to raise the best score early; the search result does not depend on it."""
    p = np.array(pose, dtype=float)
    ref = tree.data
    for _ in range(iters):
        c, s = np.cos(p[3]), np.sin(p[3])
        q = scan @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]).T + p[:3]
        d, j = nearest(tree, q, radius_m)
        m = np.isfinite(d)
        if m.sum() < 3:
            break
        a, b = scan[m], ref[j[m]]
        ca, cb = a[:, :2].mean(0), b[:, :2].mean(0)
        h = (a[:, :2] - ca).T @ (b[:, :2] - cb)
        phi = np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
        c, s = np.cos(phi), np.sin(phi)
        t_xy = cb - np.array([[c, -s], [s, c]]) @ ca
        p = np.array([t_xy[0], t_xy[1], float(np.mean(b[:, 2] - a[:, 2])), phi])
        radius_m = max(0.15, 0.7 * radius_m)
    return p


_FACE = np.vstack([np.eye(4, dtype=np.int64), -np.eye(4, dtype=np.int64)])


def _clip_index(lattice: SearchLattice, idx: np.ndarray) -> np.ndarray:
    idx = idx.copy()
    if lattice.wrap:
        idx[:, 3] %= lattice.n[3]
    return np.clip(idx, 0, lattice.n - 1)


def climb(
    field,
    points: np.ndarray,
    lattice: SearchLattice,
    idx,
    steps=(16, 8, 4, 2, 1),
    max_moves: int = 100,
):
    """Inferred first-hypothesis helper: hill climbing on the final lattice with exact scores
    from lattice index ``idx`` by face moves of ``steps`` lattice cells. Returns (index, score).
    Only raises the search's initial best score (the bounds are far looser than the gap to the
    true maximum, so a local maximum is enough)."""
    cur = np.asarray(idx, dtype=np.int64).reshape(1, 4)
    s_cur = float(field.evaluate(lattice.pose(cur), points, bound=False)[0][0])
    moves = 0
    for step in steps:
        while moves < max_moves:
            nb_idx = _clip_index(lattice, cur + _FACE * step)
            s = field.evaluate(lattice.pose(nb_idx), points, bound=False)[0]
            j = int(np.argmax(s))
            if s[j] <= s_cur:
                break
            cur, s_cur = nb_idx[j : j + 1], float(s[j])
            moves += 1
    return cur[0], s_cur


def _first_hypotheses(points, lattice, field, tree, starts_rad, n_climb=2, z_stride=4):
    """Best exact lattice score over the hypotheses ``starts_rad`` (k, 4; heading radians):
    each refined by 4-DoF ICP (xy, heading) and its height chosen from the lattice z at that
    (x, y, heading) (every ``z_stride``-th, then the ones next to the best); the ``n_climb``
    best are then hill-climbed on the lattice (inferred, spec 6.4 'initial best')."""
    cand, score = [], []
    nz = int(lattice.n[2])
    stride = max(1, min(z_stride, nz // 8))
    for p0 in np.asarray(starts_rad, dtype=float).reshape(-1, 4):
        idx = lattice.nearest_index(refine_local(points, tree, p0)[None])[0]
        # heights at this (x, y, heading): every ``stride``-th, then all next to the best
        col = np.repeat(idx[None], len(range(0, nz, stride)), axis=0)
        col[:, 2] = np.arange(0, nz, stride)
        s = field.evaluate(lattice.pose(col), points, bound=False)[0]
        k = int(col[int(np.argmax(s)), 2])
        if stride > 1:
            near = np.arange(max(k - stride + 1, 0), min(k + stride, nz))
            col = np.repeat(idx[None], len(near), axis=0)
            col[:, 2] = near
            s = field.evaluate(lattice.pose(col), points, bound=False)[0]
        cand.append(col[int(np.argmax(s))])
        score.append(float(np.max(s)))
    best_idx, best = None, -np.inf
    for k in np.argsort(score)[::-1][:n_climb]:
        idx, s = climb(field, points, lattice, cand[k])
        if s > best:
            best_idx, best = idx, s
    return best_idx, best
