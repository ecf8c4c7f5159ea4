"""Axis (projection-plane normal) of each circle model by the concatenation method (spec 3.7; Th.
4.6.3):
summed vectors to valid circle centres of the same chain above and below, tilt clamped from
vertical."""

from __future__ import annotations

import numpy as np

from forestmap_assets.core.features._circle_kernels import _nb_axes, resolve_engine


def estimate_axes(
    centres: np.ndarray,
    valid: np.ndarray,
    normals: np.ndarray,
    radius: np.ndarray,
    chain: np.ndarray,
    span_m: float,
    max_tilt_deg: float,
    engine: str = "auto",
) -> tuple[np.ndarray, np.ndarray]:
    """Axis (projection-plane normal) per circle by the concatenation method (spec 3.7).

    For circle c0, the vectors to valid circle centres of the same chain above (within
    ``span_m``) are summed, likewise the vectors from those below; both sums are normalised and
    averaged with weights proportional to their numbers of circles (inferred). Neighbours
    outside the +-``max_tilt_deg`` cone (with the circle radius as tolerance, inferred) are
    ignored. Normals farther than ``max_tilt_deg`` from vertical are clamped to the cone.
    Returns (normals, has_estimate); circles without valid neighbours keep their normal.
    """
    engine = resolve_engine(engine)
    n = centres.shape[0]
    new = normals.copy()
    has = np.zeros(n, bool)
    fin = np.all(np.isfinite(centres), axis=1)
    vidx = np.flatnonzero(valid & fin)
    if vidx.size == 0:
        return new, has
    q = np.flatnonzero(fin)
    tan_max = float(np.tan(np.radians(max_tilt_deg)))
    if engine == "numba":
        sa, sb, na, nb = _axes_by_cells(centres, chain, radius, vidx, q, float(span_m), tan_max)
    else:
        big = 1e5
        vkey = chain[vidx] * big + centres[vidx, 2]
        order = np.argsort(vkey, kind="stable")
        sv, skey = vidx[order], vkey[order]
        qkey = chain[q] * big + centres[q, 2]
        lo = np.searchsorted(skey, qkey - span_m, "left")
        hi = np.searchsorted(skey, qkey + span_m, "right")
        cnt = hi - lo
        a = np.repeat(q, cnt)
        first = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        b = sv[lo[np.repeat(np.arange(q.size), cnt)] + (np.arange(a.size) - np.repeat(first, cnt))]
        d = centres[b] - centres[a]
        dz = d[:, 2]
        dh = np.hypot(d[:, 0], d[:, 1])
        ok = (b != a) & (chain[b] == chain[a]) & (np.linalg.norm(d, axis=1) <= span_m)
        ok &= (dz != 0) & (dh <= np.abs(dz) * tan_max + radius[a])
        a, d, dz = a[ok], d[ok], dz[ok]
        up = np.where((dz > 0)[:, None], d, -d)
        above = dz > 0
        sa = np.stack([np.bincount(a[above], up[above, i], n) for i in range(3)], 1)
        sb = np.stack([np.bincount(a[~above], up[~above, i], n) for i in range(3)], 1)
        na = np.bincount(a[above], minlength=n).astype(float)
        nb = np.bincount(a[~above], minlength=n).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        ua = sa / np.linalg.norm(sa, axis=1, keepdims=True)
        ub = sb / np.linalg.norm(sb, axis=1, keepdims=True)
    ua = np.where(na[:, None] > 0, ua, 0.0)
    ub = np.where(nb[:, None] > 0, ub, 0.0)
    m = na[:, None] * ua + nb[:, None] * ub
    norm = np.linalg.norm(m, axis=1)
    has = (na + nb > 0) & (norm > 0)
    new[has] = m[has] / norm[has, None]
    return clamp_tilt(new, max_tilt_deg), has


def _axes_by_cells(centres, chain, radius, vidx, q, span_m: float, tan_max: float):
    """The numba engine's sums: valid circles binned by chain and ``span_m`` cells in x and y
    (see :func:`_nb_axes`)."""
    cells = np.floor(centres[:, :2] / span_m)
    lo = cells[q].min(axis=0)
    cells = np.where(np.isfinite(cells), cells - lo, 0).astype(np.int64)
    n_x, n_y = (int(v) + 1 for v in cells[q].max(axis=0))
    ch = np.unique(chain, return_inverse=True)[1].astype(np.int64)
    key = (ch * n_x + cells[:, 0]) * n_y + cells[:, 1]
    order = np.lexsort((centres[vidx, 2], key[vidx]))
    sv = vidx[order]
    qcell = np.ascontiguousarray(np.stack([ch[q], cells[q, 0], cells[q, 1]], 1))
    return _nb_axes(np.ascontiguousarray(centres), radius, q, qcell, key[sv], np.ascontiguousarray(centres[sv, 2]),
                    sv, n_x, n_y, span_m, tan_max, centres.shape[0])


def clamp_tilt(n: np.ndarray, max_tilt_deg: float) -> np.ndarray:
    """Unit normals pointing up, tilted at most ``max_tilt_deg`` from vertical (spec 3.7)."""
    n = np.where(n[:, 2:3] < 0, -n, n)
    tilt = np.arccos(np.clip(n[:, 2], -1, 1))
    lim = np.radians(max_tilt_deg)
    over = tilt > lim
    if over.any():
        h = n[over, :2]
        hn = np.linalg.norm(h, axis=1, keepdims=True)
        n = n.copy()
        n[over, :2] = h / np.where(hn > 0, hn, 1.0) * np.sin(lim)
        n[over, 2] = np.cos(lim)
    return n
