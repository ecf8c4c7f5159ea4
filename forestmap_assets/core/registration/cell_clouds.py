"""Cell clouds of a finished search (spec 6.5, JP eq. 6) and the features supporting a pose
(spec 6.7, inferred).

Surviving final cells are grouped into connected clouds on the lattice (80- or 8-neighbour
adjacency; heading wraps on a full circle, :func:`lattice_components`); a cloud gives the weighted
centre and standard deviation per DoF (:func:`cloud_statistics`). :func:`matched_stems` counts the
distinct stems (blobs of matched points) that support a pose."""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from forestmap_assets.core.geometry import wrap_deg


def lattice_components(idx: np.ndarray, n: np.ndarray, wrap: bool, adjacency: int = 80):
    """Connected components of lattice cells ``idx`` (k, 4) under 80- (Chebyshev 1) or 8-
    (face) neighbour adjacency; heading index wraps when ``wrap`` (spec 6.5, inferred)."""
    k = len(idx)
    if k == 0:
        return 0, np.zeros(0, np.int64)
    n = np.asarray(n, dtype=np.int64)
    mult = np.array([n[1] * n[2] * n[3], n[2] * n[3], n[3], 1], dtype=np.int64)
    keys = idx @ mult
    order = np.argsort(keys)
    sk = keys[order]
    if adjacency == 80:
        offs = np.array(np.meshgrid(*[[-1, 0, 1]] * 4, indexing="ij")).reshape(4, -1).T
        offs = offs[np.any(offs != 0, axis=1)]
    elif adjacency == 8:
        offs = np.vstack([np.eye(4, dtype=np.int64), -np.eye(4, dtype=np.int64)])
    else:
        raise ValueError(f"adjacency: expected 80 or 8, got {adjacency}")
    rows, cols = [], []
    for off in offs:  # 80 offsets, each vectorised over all cells
        nb = idx + off
        if wrap:
            nb[:, 3] %= n[3]
        ok = np.all((nb >= 0) & (nb < n), axis=1)
        nk = nb @ mult
        pos = np.clip(np.searchsorted(sk, nk), 0, k - 1)
        hit = ok & (sk[pos] == nk)
        rows.append(np.flatnonzero(hit))
        cols.append(order[pos[hit]])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r)), (r, c)), shape=(k, k))
    return connected_components(graph, directed=False)


def cloud_statistics(poses_deg: np.ndarray, weights: np.ndarray, ref_heading_deg: float):
    """Weighted centre and standard deviation per DoF (JP eq. 6); headings unwrapped about
    ``ref_heading_deg``."""
    p = np.array(poses_deg, dtype=float, copy=True)
    p[:, 3] = ref_heading_deg + wrap_deg(p[:, 3] - ref_heading_deg)
    w = np.asarray(weights, dtype=float)
    if not np.isfinite(w).all() or w.sum() <= 0:
        w = np.ones(len(p))
    mean = (w[:, None] * p).sum(0) / w.sum()
    sd = np.sqrt((w[:, None] * (p - mean) ** 2).sum(0) / w.sum())
    mean[3] = wrap_deg(mean[3])
    return mean, sd


def matched_stems(
    scan_points: np.ndarray,
    reference_points: np.ndarray,
    pose_deg,
    *,
    match_m: float = 0.07,
    cell_m: float = 0.2,
    min_points: int = 10,
) -> int:
    """Distinct features supporting a pose (inferred confidence figure, spec 6.7): the scan's
    points within ``match_m`` (2 sigma) of the reference after the pose, grouped into horizontal
    blobs (:func:`~.stem_voting.stem_positions`, ``cell_m``); blobs of at least ``min_points``
    points (0.5 m of stem at 0.05 m spacing) count. One long stem can match hundreds of points,
    so the point count alone cannot tell one coincidence from an overlap."""
    from forestmap_assets.core.registration.stem_voting import stem_positions

    b = np.asarray(scan_points, dtype=float).reshape(-1, 3)
    if len(b) == 0 or len(reference_points) == 0:
        return 0
    h = np.radians(pose_deg[3])
    c, s_ = np.cos(h), np.sin(h)
    q = b @ np.array([[c, s_, 0.0], [-s_, c, 0.0], [0.0, 0.0, 1.0]]) + np.asarray(pose_deg[:3])
    d = cKDTree(reference_points).query(q, distance_upper_bound=match_m)[0]
    hit = np.isfinite(d)
    if not hit.any():
        return 0
    _, counts, _ = stem_positions(b[hit], cell_m=cell_m, min_points=1)
    return int(np.sum(counts >= min_points))
