"""First hypotheses for the branch-and-bound search by stem-to-stem voting (inferred speed-up).

The search of spec 6.4 prunes a cell only when its bound falls below the best score found so
far, so it runs much faster when a near-optimal alignment is known from the start (the thesis
starts from the a priori pose). Sub-map points lie on near-vertical stem axes, so the stems'
horizontal positions are a small 2-D point pattern per scan (JP §II-B: "correspondence is solved
implicitly"). Here, for every heading on a coarse grid, every pair (stem of B, stem of A) votes
for the translation that would make them coincide; the (heading, translation) bins with most
votes are the hypotheses. They only raise the search's initial best score; the result of the
search never depends on them (a wrong hypothesis only costs time).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def stem_positions(points: np.ndarray, cell_m: float = 0.2, min_points: int = 4):
    """Horizontal stem positions of a sub-map: 2-D histogram of the points at ``cell_m``, cells
    with at least ``min_points`` grouped into 8-connected blobs; returns (k, 2) weighted centres,
    (k,) point counts and (k,) median heights."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    lo = p[:, :2].min(0)
    ij = np.floor((p[:, :2] - lo) / cell_m).astype(np.int64)
    shape = ij.max(0) + 1
    counts = np.zeros(shape, np.int64)
    np.add.at(counts, (ij[:, 0], ij[:, 1]), 1)
    labels, n = ndimage.label(counts >= min_points, structure=np.ones((3, 3)))
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    lab = labels[ij[:, 0], ij[:, 1]]
    keep = lab > 0
    lab = lab[keep] - 1
    w = np.bincount(lab, minlength=n).astype(float)
    cx = np.bincount(lab, weights=p[keep, 0], minlength=n) / w
    cy = np.bincount(lab, weights=p[keep, 1], minlength=n) / w
    z = ndimage.median(p[keep, 2], lab, index=np.arange(n)) if n else np.zeros(0)
    return np.column_stack([cx, cy]), w, np.asarray(z, dtype=float)


def vote_alignments(
    scan_points: np.ndarray,
    reference_points: np.ndarray,
    centre,
    half_widths,
    *,
    heading_step_deg: float = 1.0,
    bin_m: float = 0.3,
    n_best: int = 6,
    max_stems: int = 120,
    min_separation_m: float = 1.0,
) -> np.ndarray:
    """Up to ``n_best`` hypotheses (dx, dy, dz, dh_deg) of the pose of B (``scan_points``) in
    A's frame inside the box ``centre +- half_widths``, strongest first.

    Votes: heading grid of ``heading_step_deg`` over the box, translation bins of ``bin_m``
    (bilinear split over the four nearest bins), weight ``min(n_i, n_j)`` (point counts of the
    two stems, inferred: long stems seen by both scans count most). ``dz`` is the weighted median
    height difference of the stem pairs that voted for the winning bin. Hypotheses closer than
    ``min_separation_m`` (heading as arc at the mean stem distance) to a stronger one are dropped.
    """
    sa, wa, za = stem_positions(reference_points)
    sb, wb, zb = stem_positions(scan_points)
    if len(sa) == 0 or len(sb) == 0:
        return np.zeros((0, 4))
    ia = np.argsort(-wa)[:max_stems]
    ib = np.argsort(-wb)[:max_stems]
    sa, wa, za, sb, wb, zb = sa[ia], wa[ia], za[ia], sb[ib], wb[ib], zb[ib]
    c = np.asarray(centre, dtype=float)
    h = np.abs(np.asarray(half_widths, dtype=float))
    span = min(h[3], 180.0)
    n_h = max(1, int(np.ceil(2 * span / heading_step_deg)))
    if span >= 180.0:
        heads = c[3] - 180.0 + np.arange(n_h) * (360.0 / n_h)
    else:
        heads = c[3] + np.linspace(-span, span, n_h + 1)
    nx = max(1, int(np.ceil(2 * h[0] / bin_m))) + 1
    ny = max(1, int(np.ceil(2 * h[1] / bin_m))) + 1
    lo = c[:2] - h[:2]
    w_pair = np.minimum(wb[:, None], wa[None, :]).ravel()
    acc = np.zeros((len(heads), nx, ny))
    for k, hd in enumerate(heads):  # one vectorised vote per heading (a few hundred at most)
        r = np.radians(hd)
        rb = sb @ np.array([[np.cos(r), np.sin(r)], [-np.sin(r), np.cos(r)]])
        t = (sa[None, :, :] - rb[:, None, :]).reshape(-1, 2)
        u = (t - lo) / bin_m
        ok = (u[:, 0] >= 0) & (u[:, 1] >= 0) & (u[:, 0] < nx - 1) & (u[:, 1] < ny - 1)
        u, w = u[ok], w_pair[ok]
        i0 = np.floor(u).astype(np.int64)
        f = u - i0
        flat = acc[k].ravel()
        for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            wt = w * np.where(dx, f[:, 0], 1 - f[:, 0]) * np.where(dy, f[:, 1], 1 - f[:, 1])
            flat += np.bincount((i0[:, 0] + dx) * ny + i0[:, 1] + dy, weights=wt, minlength=nx * ny)
    # smooth over neighbouring headings (far stems smear across a heading step)
    mode = "wrap" if span >= 180.0 else "nearest"
    sm = ndimage.uniform_filter1d(acc, 3, axis=0, mode=mode)
    flat_sm = sm.ravel()
    top = min(50 * n_best, flat_sm.size)
    order = np.argpartition(-flat_sm, top - 1)[:top]
    order = order[np.argsort(-flat_sm[order])]
    d_bar = float(np.mean(np.hypot(sb[:, 0], sb[:, 1]))) if len(sb) else 1.0
    out = []
    for flat_i in order:
        k, i, j = np.unravel_index(flat_i, sm.shape)
        if sm[k, i, j] <= 0:
            break
        pose = np.array([lo[0] + i * bin_m, lo[1] + j * bin_m, 0.0, heads[k]])
        if any(_separation(pose, q, d_bar) < min_separation_m for q in out):
            continue
        r = np.radians(pose[3])
        rb = sb @ np.array([[np.cos(r), np.sin(r)], [-np.sin(r), np.cos(r)]]) + pose[:2]
        dist = np.hypot(*(rb[:, None, :] - sa[None, :, :]).transpose(2, 0, 1))
        near = dist < 2 * bin_m
        bi, aj = np.nonzero(near)
        if len(bi):
            dz = za[aj] - zb[bi]
            wz = np.minimum(wb[bi], wa[aj])
            o = np.argsort(dz)
            cw = np.cumsum(wz[o])
            pose[2] = float(dz[o][np.searchsorted(cw, 0.5 * cw[-1])])
        pose[2] = float(np.clip(pose[2], c[2] - h[2], c[2] + h[2]))
        out.append(pose)
        if len(out) == n_best:
            break
    return np.array(out).reshape(-1, 4)


def _separation(p, q, d_bar):
    dh = (p[3] - q[3] + 180.0) % 360.0 - 180.0
    return float(np.hypot(np.hypot(p[0] - q[0], p[1] - q[1]), np.radians(dh) * d_bar))
