"""Fast score and bound evaluation of registration cells (spec 6.3-6.4, inferred data structures).

Map A (the reference) is indexed once per pair by :class:`ReferenceField`:

* a **sparse block grid** of fine voxels (``fine_m``, default 0.1 m; blocks of 8^3 voxels, only
  blocks within ``cap`` of some point of A are stored). Every stored voxel ``v`` lists the
  candidate points ``C_v = {a : dist(a, box_v) <= min(ub_v, cap)}``, ``ub_v = min_a
  maxdist(a, box_v)``. For a query ``q`` in ``box_v`` the nearest point ``a*`` satisfies
  ``dist(a*, box_v) <= |q - a*| <= ub_v``, so ``min_{C_v} |q - a|`` is the **exact**
  nearest-neighbour distance whenever it is ``<= cap``, and otherwise ``D(q) > cap`` (where
  ``ln p(D) == ln k1`` in float64): scores are exact, not interpolated. A voxel of a block that
  is not stored lies farther than ``cap`` from A.
* a coarse grid (``coarse_m``) of rigorous lower bounds ``min_a dist(a, box_v)`` (point boxes of
  occupied coarse voxels, capped at ``coarse_cap_m``), used by bounds beyond ``cap``.

The cell bound of spec 6.4 (Eq. 5.11-5.14) is ``sum_i w_i ln p(max(D_lo,i - Delta_i, 0))`` with a
per-point displacement ``Delta_i`` (translation corner distance + rotation chord
``2 d_e sin(phi_h / 2)``); ``ln p`` of the bound is read from a table rounded towards smaller
distances (an upper bound), and the "quick" score from a table rounded towards larger distances
(a lower bound of the exact score, enough to raise the best score of a search).

**Live points** (inferred, exact): a point whose bound term is ``ln k1`` over a cell (its lower
distance bound is ``>= cap`` everywhere in the cell) contributes exactly ``ln k1`` to the score
and the bound of every sub-cell, so :func:`eval_live` evaluates each cell only on the points
still live in its parent and returns the child's own live list. With an offset box ``[lo, hi]``
(:func:`_eval_live_box`, inferred, exact) the per-axis bound uses the cell's exact asymmetric
box (the lattice bound's cells hold the lattice points ``-(size // 2) .. size - 1 - size // 2``
steps about their pose) and the per-axis range of each point's rotation displacement, keeps
each point's term no larger than its term in the parent cell, and stops a cell early once the
parent's bound minus the drops so far falls below the best score. Kernels are compiled with
numba.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from forestmap_assets.core.registration_.score import ScoreModel

BLOCK = 8  # voxels per block edge (fixed: index arithmetic uses shifts by 3)
_FAST = {"nsz", "arcp", "contract", "reassoc"}  # fast math, but inf stays meaningful


@nb.njit(cache=True)
def _box_dists(a, lo, s):
    """(min, max) distance from point ``a`` to the voxel box ``[lo, lo + s]``."""
    dmin = 0.0
    dmax = 0.0
    for k in range(3):
        lo_k = lo[k]
        hi_k = lo_k + s
        if a[k] < lo_k:
            t = lo_k - a[k]
        elif a[k] > hi_k:
            t = a[k] - hi_k
        else:
            t = 0.0
        dmin += t * t
        u = max(abs(a[k] - lo_k), abs(a[k] - hi_k))
        dmax += u * u
    return math.sqrt(dmin), math.sqrt(dmax)


@nb.njit(cache=True)
def _mark_blocks(ref, origin, s, nb_shape, cap):
    """Block map: -1 for blocks farther than ``cap`` from every point, else a slot number."""
    bs = s * BLOCK
    bmap = np.full(nb_shape[0] * nb_shape[1] * nb_shape[2], -1, np.int32)
    for p in range(ref.shape[0]):
        lo = np.empty(3, np.int64)
        hi = np.empty(3, np.int64)
        for k in range(3):
            lo[k] = max(int(math.floor((ref[p, k] - cap - origin[k]) / bs)), 0)
            hi[k] = min(int(math.floor((ref[p, k] + cap - origin[k]) / bs)), nb_shape[k] - 1)
        for bx in range(lo[0], hi[0] + 1):
            for by in range(lo[1], hi[1] + 1):
                for bz in range(lo[2], hi[2] + 1):
                    bmap[(bx * nb_shape[1] + by) * nb_shape[2] + bz] = 0
    n = 0
    for b in range(bmap.shape[0]):
        if bmap[b] == 0:
            bmap[b] = n
            n += 1
    return bmap, n


@nb.njit(cache=True, inline="always", fastmath=_FAST)
def _slot(ix, iy, iz, bmap, nb_shape):
    """Voxel slot of fine voxel (ix, iy, iz) in the block store, -1 when its block is absent."""
    b = bmap[((ix >> 3) * nb_shape[1] + (iy >> 3)) * nb_shape[2] + (iz >> 3)]
    if b < 0:
        return -1
    return b * 512 + (((ix & 7) << 6) | ((iy & 7) << 3) | (iz & 7))


@nb.njit(cache=True)
def _stamp(ref, origin, s, shape, nb_shape, bmap, cap, ub, mode, count, idx, fill, margin,
           p_start, p_end):
    """One pass over the voxels within ``cap`` of each point ``p_start <= p < p_end``: mode 0
    lowers ``ub``, mode 1 counts candidates, mode 2 writes them."""
    r = int(math.ceil(cap / s)) + 1
    lo = np.empty(3)
    for p in range(p_start, p_end):
        a = ref[p]
        cx = int((a[0] - origin[0]) / s)
        cy = int((a[1] - origin[1]) / s)
        cz = int((a[2] - origin[2]) / s)
        for ix in range(max(cx - r, 0), min(cx + r + 1, shape[0])):
            lo[0] = origin[0] + ix * s
            for iy in range(max(cy - r, 0), min(cy + r + 1, shape[1])):
                lo[1] = origin[1] + iy * s
                for iz in range(max(cz - r, 0), min(cz + r + 1, shape[2])):
                    lo[2] = origin[2] + iz * s
                    dmin, dmax = _box_dists(a, lo, s)
                    if dmin > cap:
                        continue
                    v = _slot(ix, iy, iz, bmap, nb_shape)
                    if mode == 0:
                        if dmax < ub[v]:
                            ub[v] = dmax
                    elif dmin <= ub[v] + margin:
                        if mode == 1:
                            count[v + 1] += 1
                        else:
                            idx[fill[v]] = p
                            fill[v] += 1


@nb.njit(cache=True, parallel=True)
def _build_candidates(ref, origin, s, shape, nb_shape, bmap, n_blocks, cap, margin, n_parts):
    """CSR candidate lists per stored fine voxel (see module docstring), the points split into
    ``n_parts`` consecutive ranges stamped in parallel (same lists, same order as one pass)."""
    nvox = n_blocks * 512
    n = ref.shape[0]
    cut = np.empty(n_parts + 1, np.int64)
    for t in range(n_parts + 1):
        cut[t] = (n * t) // n_parts
    ubs = np.full((n_parts, nvox), np.inf)
    counts = np.zeros((n_parts, nvox + 1), np.int64)
    idx = np.empty(0, np.int32)
    fill = np.empty(0, np.int64)
    for t in nb.prange(n_parts):
        _stamp(ref, origin, s, shape, nb_shape, bmap, cap, ubs[t], 0, counts[t], idx, fill,
               margin, cut[t], cut[t + 1])
    ub = np.empty(nvox)
    for v in nb.prange(nvox):
        m = np.inf
        for t in range(n_parts):
            m = min(m, ubs[t, v])
        ub[v] = m
    for t in nb.prange(n_parts):
        _stamp(ref, origin, s, shape, nb_shape, bmap, cap, ub, 1, counts[t], idx, fill,
               margin, cut[t], cut[t + 1])
    count = np.zeros(nvox + 1, np.int64)
    for v in range(nvox):
        tot = 0
        for t in range(n_parts):
            tot += counts[t, v + 1]
        count[v + 1] = count[v] + tot
    # each part writes after the earlier parts' candidates of the same voxel
    fills = np.empty((n_parts, nvox), np.int64)
    for v in nb.prange(nvox):
        f = count[v]
        for t in range(n_parts):
            fills[t, v] = f
            f += counts[t, v + 1]
    idx = np.empty(count[nvox], np.int32)
    for t in nb.prange(n_parts):
        _stamp(ref, origin, s, shape, nb_shape, bmap, cap, ub, 2, counts[t], idx, fills[t],
               margin, cut[t], cut[t + 1])
    return count, idx, np.minimum(ub + margin, cap).astype(np.float32)


@nb.njit(cache=True)
def _build_buckets(ref, origin, s, nb_shape, bmap, n_blocks):
    """CSR of the points inside each stored fine voxel (for the per-axis bound's range search)."""
    nvox = n_blocks * 512
    count = np.zeros(nvox + 1, np.int64)
    slots = np.empty(ref.shape[0], np.int64)
    for p in range(ref.shape[0]):
        ix = int((ref[p, 0] - origin[0]) / s)
        iy = int((ref[p, 1] - origin[1]) / s)
        iz = int((ref[p, 2] - origin[2]) / s)
        v = _slot(ix, iy, iz, bmap, nb_shape)
        slots[p] = v
        count[v + 1] += 1
    for v in range(nvox):
        count[v + 1] += count[v]
    fill = count[:-1].copy()
    idx = np.empty(ref.shape[0], np.int32)
    for p in range(ref.shape[0]):
        idx[fill[slots[p]]] = p
        fill[slots[p]] += 1
    return count, idx


@nb.njit(cache=True)
def _build_coarse_lb(box_lo, box_hi, origin, s, shape, cap):
    """Lower bound of the distance from each coarse voxel to the boxes ``[box_lo, box_hi]``."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    lb = np.full(nx * ny * nz, cap, np.float32)
    r = int(math.ceil(cap / s)) + 1
    for p in range(box_lo.shape[0]):
        cx = int((0.5 * (box_lo[p, 0] + box_hi[p, 0]) - origin[0]) / s)
        cy = int((0.5 * (box_lo[p, 1] + box_hi[p, 1]) - origin[1]) / s)
        cz = int((0.5 * (box_lo[p, 2] + box_hi[p, 2]) - origin[2]) / s)
        for ix in range(max(cx - r, 0), min(cx + r + 1, nx)):
            gx = max(origin[0] + ix * s - box_hi[p, 0], box_lo[p, 0] - origin[0] - (ix + 1) * s, 0.0)
            for iy in range(max(cy - r, 0), min(cy + r + 1, ny)):
                gy = max(origin[1] + iy * s - box_hi[p, 1], box_lo[p, 1] - origin[1] - (iy + 1) * s, 0.0)
                for iz in range(max(cz - r, 0), min(cz + r + 1, nz)):
                    gz = max(origin[2] + iz * s - box_hi[p, 2], box_lo[p, 2] - origin[2] - (iz + 1) * s, 0.0)
                    d = math.sqrt(gx * gx + gy * gy + gz * gz)
                    v = (ix * ny + iy) * nz + iz
                    if d < lb[v]:
                        lb[v] = d
    return lb


@nb.njit(cache=True, inline="always", fastmath=_FAST)
def _nearest(qx, qy, qz, ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off, cand_idx, cap):
    """Exact nearest distance if ``<= cap``, else ``inf`` (module docstring)."""
    ix = int(math.floor((qx - f_origin[0]) / f_s))
    iy = int(math.floor((qy - f_origin[1]) / f_s))
    iz = int(math.floor((qz - f_origin[2]) / f_s))
    if ix < 0 or iy < 0 or iz < 0 or ix >= f_shape[0] or iy >= f_shape[1] or iz >= f_shape[2]:
        return np.inf
    v = _slot(ix, iy, iz, bmap, nb_shape)
    if v < 0:
        return np.inf
    best = np.inf
    for c in range(cand_off[v], cand_off[v + 1]):
        j = cand_idx[c]
        dx = qx - ref[j, 0]
        dy = qy - ref[j, 1]
        dz = qz - ref[j, 2]
        d2 = dx * dx + dy * dy + dz * dz
        if d2 < best:
            best = d2
    d = math.sqrt(best)
    return d if d <= cap else np.inf


@nb.njit(cache=True, inline="always", fastmath=_FAST)
def _nearest_abox(qx, qy, qz, lip, lx, hx, ly, hy, lz, hz, ref, f_origin, f_s, f_shape,
                  nb_shape, bmap, cand_off, cand_idx, ub, cap):
    """:func:`_nearest_box` over the asymmetric displacement box ``u_a in [l_a, h_a]``
    (``l <= 0 <= h``, ``|u| <= lip``; see there)."""
    ix = int(math.floor((qx - f_origin[0]) / f_s))
    iy = int(math.floor((qy - f_origin[1]) / f_s))
    iz = int(math.floor((qz - f_origin[2]) / f_s))
    if ix < 0 or iy < 0 or iz < 0 or ix >= f_shape[0] or iy >= f_shape[1] or iz >= f_shape[2]:
        return np.inf, np.inf
    v = _slot(ix, iy, iz, bmap, nb_shape)
    if v < 0:
        return np.inf, np.inf
    best = np.inf
    boxb = np.inf
    for c in range(cand_off[v], cand_off[v + 1]):
        j = cand_idx[c]
        dx = ref[j, 0] - qx
        dy = ref[j, 1] - qy
        dz = ref[j, 2] - qz
        d2 = dx * dx + dy * dy + dz * dz
        if d2 < best:
            best = d2
        gx = max(dx - hx, lx - dx, 0.0)
        gy = max(dy - hy, ly - dy, 0.0)
        gz = max(dz - hz, lz - dz, 0.0)
        g2 = gx * gx + gy * gy + gz * gz
        if g2 < boxb:
            boxb = g2
    d = math.sqrt(best)
    if d > cap:
        return np.inf, np.inf
    low = d - lip
    if d + 2.0 * lip <= ub[v]:
        low = max(low, math.sqrt(boxb))
    return d, low


@nb.njit(cache=True, inline="always", fastmath=_FAST)
def _nearest_box(qx, qy, qz, lip, ex, ey, ez, ref, f_origin, f_s, f_shape, nb_shape, bmap,
                 cand_off, cand_idx, ub, cap):
    """Exact nearest distance ``d`` (``inf`` beyond ``cap``) and, in the same candidate loop, a
    lower bound of the nearest distance over the displacement box ``|p - q|_a <= (ex, ey, ez)``,
    ``|p - q| <= lip`` (spec 6.4 "tighter bound", inferred form): :func:`_nearest_abox` with the
    symmetric box. Points farther than ``rho = d + 2 lip`` from ``q`` cannot be nearest anywhere
    in the box; when ``rho <= ub_v`` they are all candidates of ``q``'s voxel, so the per-axis
    bound over the candidates is rigorous; otherwise the Lipschitz bound ``d - lip`` is
    returned."""
    return _nearest_abox(qx, qy, qz, lip, -ex, ex, -ey, ey, -ez, ez, ref, f_origin, f_s,
                         f_shape, nb_shape, bmap, cand_off, cand_idx, ub, cap)


@nb.njit(cache=True, inline="always", fastmath=_FAST)
def _coarse_lower(qx, qy, qz, c_origin, c_s, c_shape, lb, bb_lo, bb_hi):
    ix = int(math.floor((qx - c_origin[0]) / c_s))
    iy = int(math.floor((qy - c_origin[1]) / c_s))
    iz = int(math.floor((qz - c_origin[2]) / c_s))
    if ix < 0 or iy < 0 or iz < 0 or ix >= c_shape[0] or iy >= c_shape[1] or iz >= c_shape[2]:
        gx = max(bb_lo[0] - qx, qx - bb_hi[0], 0.0)
        gy = max(bb_lo[1] - qy, qy - bb_hi[1], 0.0)
        gz = max(bb_lo[2] - qz, qz - bb_hi[2], 0.0)
        return math.sqrt(gx * gx + gy * gy + gz * gz)
    return lb[(ix * c_shape[1] + iy) * c_shape[2] + iz]


@nb.njit(cache=True, inline="always")
def _box_lower(qx, qy, qz, d, lip, ex, ey, ez, ref, f_origin, f_s, f_shape, nb_shape, bmap,
               b_off, b_idx, cap):
    """Tighter lower bound of the nearest distance over a cell (spec 6.4 "tighter bound", inferred
    form): every point within ``rho`` of the evaluation position is bounded per axis by the cell's
    displacement box ``(ex, ey, ez)`` and by the Lipschitz radius ``lip``; points farther than
    ``rho = min(d + 2 lip, cap + lip)`` cannot be nearest (or are beyond ``cap``) anywhere in it."""
    rho = d + 2.0 * lip
    out = np.inf
    if rho > cap + lip:
        rho = cap + lip
        out = cap
    x0 = max(int(math.floor((qx - rho - f_origin[0]) / f_s)), 0)
    x1 = min(int(math.floor((qx + rho - f_origin[0]) / f_s)), f_shape[0] - 1)
    y0 = max(int(math.floor((qy - rho - f_origin[1]) / f_s)), 0)
    y1 = min(int(math.floor((qy + rho - f_origin[1]) / f_s)), f_shape[1] - 1)
    z0 = max(int(math.floor((qz - rho - f_origin[2]) / f_s)), 0)
    z1 = min(int(math.floor((qz + rho - f_origin[2]) / f_s)), f_shape[2] - 1)
    rho2 = rho * rho
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            for iz in range(z0, z1 + 1):
                v = _slot(ix, iy, iz, bmap, nb_shape)
                if v < 0:
                    continue
                for c in range(b_off[v], b_off[v + 1]):
                    j = b_idx[c]
                    vx = abs(ref[j, 0] - qx)
                    vy = abs(ref[j, 1] - qy)
                    vz = abs(ref[j, 2] - qz)
                    n2 = vx * vx + vy * vy + vz * vz
                    if n2 > rho2:
                        continue
                    gx = max(vx - ex, 0.0)
                    gy = max(vy - ey, 0.0)
                    gz = max(vz - ez, 0.0)
                    low = max(math.sqrt(gx * gx + gy * gy + gz * gz), math.sqrt(n2) - lip)
                    if low < out:
                        out = low
    return max(out, 0.0)


@nb.njit(cache=True, parallel=True, fastmath=_FAST)
def _eval_cells(
    poses, pts, delta, rot, e_box, box_max, weight, do_score, do_bound,
    ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off, cand_idx, b_off, b_idx, cap,
    c_origin, c_s, c_shape, lb, bb_lo, bb_hi,
    k1, ln_k1, k2n, inv2s2, table, inv_step,
    out_score, out_bound, active,
):
    """Exact score at each cell's pose and bound over the cell (spec 6.4, Eq. 5.11-5.12)."""
    n_cells = poses.shape[0]
    n = pts.shape[0]
    nt = table.shape[0]
    for c in nb.prange(n_cells):
        ch = math.cos(poses[c, 3])
        sh = math.sin(poses[c, 3])
        tx, ty, tz = poses[c, 0], poses[c, 1], poses[c, 2]
        s_acc = 0.0
        b_acc = 0.0
        for i in range(n):
            qx = ch * pts[i, 0] - sh * pts[i, 1] + tx
            qy = sh * pts[i, 0] + ch * pts[i, 1] + ty
            qz = pts[i, 2] + tz
            d = _nearest(qx, qy, qz, ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off,
                         cand_idx, cap)
            if do_score:
                if d <= cap:
                    s_acc += weight[i] * math.log(k1 + k2n * math.exp(-d * d * inv2s2))
                else:
                    s_acc += weight[i] * ln_k1
            if do_bound:
                if d > cap:
                    d = max(cap, _coarse_lower(qx, qy, qz, c_origin, c_s, c_shape, lb, bb_lo, bb_hi))
                    r = d - delta[i]
                elif delta[i] <= box_max and d - delta[i] < cap:
                    r = _box_lower(
                        qx, qy, qz, d, delta[i], e_box[0] + rot[i], e_box[1] + rot[i], e_box[2],
                        ref, f_origin, f_s, f_shape, nb_shape, bmap, b_off, b_idx, cap,
                    )
                else:
                    r = d - delta[i]
                if r < cap:
                    active[i] = 1
                if r <= 0.0:
                    b_acc += weight[i] * table[0]
                else:
                    k = int(r * inv_step)
                    b_acc += weight[i] * table[min(k, nt - 1)]
        out_score[c] = s_acc
        out_bound[c] = b_acc


@nb.njit(cache=True, parallel=True, fastmath=_FAST)
def _eval_live(
    poses, parent, live_off, live_idx, n_total, pts, d_xy, t_ext, sin_h, box_max, e_box,
    ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off, cand_idx, ub, cap,
    c_origin, c_s, c_shape, lb, bb_lo, bb_hi,
    ln_k1, table_hi, table_lo, inv_step,
    out_bound, out_score, out_off, out_cnt, out_live,
):
    """Bound over each cell and a lower bound of the score at its pose, on the live points of
    its parent cell; writes the cell's own live points (module docstring, spec 6.4)."""
    n_cells = poses.shape[0]
    nt = table_hi.shape[0]
    for c in nb.prange(n_cells):
        p = parent[c]
        ch = math.cos(poses[c, 3])
        sh = math.sin(poses[c, 3])
        tx, ty, tz = poses[c, 0], poses[c, 1], poses[c, 2]
        n_live = live_off[p + 1] - live_off[p]
        dead = n_total - n_live
        s_acc = dead * ln_k1
        b_acc = dead * ln_k1
        w = out_off[c]
        for k in range(live_off[p], live_off[p + 1]):
            i = live_idx[k]
            qx = ch * pts[i, 0] - sh * pts[i, 1] + tx
            qy = sh * pts[i, 0] + ch * pts[i, 1] + ty
            qz = pts[i, 2] + tz
            rot = 2.0 * d_xy[i] * sin_h
            delta = t_ext + rot
            if delta <= box_max:
                d, r = _nearest_box(qx, qy, qz, delta, e_box[0] + rot, e_box[1] + rot, e_box[2],
                                    ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off,
                                    cand_idx, ub, cap)
            else:
                d = _nearest(qx, qy, qz, ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off,
                             cand_idx, cap)
                r = d - delta
            if d > cap:
                s_acc += ln_k1
                r = max(cap, _coarse_lower(qx, qy, qz, c_origin, c_s, c_shape, lb, bb_lo, bb_hi))
                r -= delta
            else:
                s_acc += table_lo[min(int(d * inv_step) + 1, nt - 1)]
            if r >= cap:
                b_acc += ln_k1
                continue
            out_live[w] = i
            w += 1
            if r <= 0.0:
                b_acc += table_hi[0]
            else:
                b_acc += table_hi[min(int(r * inv_step), nt - 1)]
        out_cnt[c] = w - out_off[c]
        out_bound[c] = b_acc
        out_score[c] = s_acc


@nb.njit(cache=True, parallel=True, fastmath=_FAST)
def _eval_live_box(
    poses, parent, live_off, live_idx, n_total, pts, d_xy, t_ext, chord, box_max,
    lo, hi, s_lo, s_hi, eps_fac, par_terms, par_bound, thresh,
    ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off, cand_idx, ub, cap,
    c_origin, c_s, c_shape, lb, bb_lo, bb_hi,
    ln_k1, table_hi, table_lo, inv_step,
    out_bound, out_score, out_off, out_cnt, out_live, out_terms,
):
    """:func:`_eval_live` over the asymmetric offset box ``[lo, hi]`` (dx, dy, dz, dh about each
    cell's pose): the per-axis bound of a point uses the exact per-axis range of its displacement
    ``t + (cos a - 1) p + sin a J p`` (``p`` the rotated point, ``sin a`` in ``[s_lo, s_hi]``,
    ``1 - cos a <= eps_fac``) instead of a symmetric box widened by the rotation chord.

    Parent terms (inferred, exact): a point's bound term over the parent cell (``par_terms``,
    aligned with ``live_idx``) also bounds it over the child, so the child keeps the smaller of
    the two (``out_terms``, aligned with ``out_live``), and ``R = par_bound - sum (parent term
    - child term)`` over the points done so far bounds the child: once ``R < thresh`` the cell
    is pruned without its remaining points (bound ``R``, score ``-inf``)."""
    n_cells = poses.shape[0]
    nt = table_hi.shape[0]
    for c in nb.prange(n_cells):
        p = parent[c]
        ch = math.cos(poses[c, 3])
        sh = math.sin(poses[c, 3])
        tx, ty, tz = poses[c, 0], poses[c, 1], poses[c, 2]
        n_live = live_off[p + 1] - live_off[p]
        dead = n_total - n_live
        s_acc = dead * ln_k1
        b_acc = dead * ln_k1
        rem = par_bound[p]
        stopped = False
        w = out_off[c]
        for k in range(live_off[p], live_off[p + 1]):
            if rem < thresh:
                stopped = True
                break
            tp = par_terms[k]
            i = live_idx[k]
            px = ch * pts[i, 0] - sh * pts[i, 1]
            py = sh * pts[i, 0] + ch * pts[i, 1]
            qx = px + tx
            qy = py + ty
            qz = pts[i, 2] + tz
            delta = t_ext + chord * d_xy[i]
            if delta <= box_max:
                epx = eps_fac * px
                epy = eps_fac * py
                rx_lo = min(-py * s_lo, -py * s_hi) + min(0.0, -epx)
                rx_hi = max(-py * s_lo, -py * s_hi) + max(0.0, -epx)
                ry_lo = min(px * s_lo, px * s_hi) + min(0.0, -epy)
                ry_hi = max(px * s_lo, px * s_hi) + max(0.0, -epy)
                d, r = _nearest_abox(qx, qy, qz, delta, lo[0] + rx_lo, hi[0] + rx_hi,
                                     lo[1] + ry_lo, hi[1] + ry_hi, lo[2], hi[2], ref, f_origin,
                                     f_s, f_shape, nb_shape, bmap, cand_off, cand_idx, ub, cap)
            else:
                d = _nearest(qx, qy, qz, ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off,
                             cand_idx, cap)
                r = d - delta
            if d > cap:
                s_acc += ln_k1
                r = max(cap, _coarse_lower(qx, qy, qz, c_origin, c_s, c_shape, lb, bb_lo, bb_hi))
                r -= delta
            else:
                s_acc += table_lo[min(int(d * inv_step) + 1, nt - 1)]
            if r >= cap:
                b_acc += ln_k1
                rem -= tp - ln_k1
                continue
            if r <= 0.0:
                term = table_hi[0]
            else:
                term = table_hi[min(int(r * inv_step), nt - 1)]
            term = min(term, tp)
            out_live[w] = i
            out_terms[w] = term
            w += 1
            b_acc += term
            rem -= tp - term
        out_cnt[c] = w - out_off[c]
        if stopped:
            out_bound[c] = rem
            out_score[c] = -np.inf
        else:
            out_bound[c] = b_acc
            out_score[c] = s_acc


@nb.njit(cache=True, parallel=True, fastmath=_FAST)
def _exact_live(
    poses, live_off, live_idx, n_total, pts,
    ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off, cand_idx, cap,
    k1, ln_k1, k2n, inv2s2, out_score,
):
    """Exact scores of cells from their live points (dead points score exactly ``ln k1``)."""
    for c in nb.prange(poses.shape[0]):
        ch = math.cos(poses[c, 3])
        sh = math.sin(poses[c, 3])
        tx, ty, tz = poses[c, 0], poses[c, 1], poses[c, 2]
        acc = (n_total - (live_off[c + 1] - live_off[c])) * ln_k1
        for k in range(live_off[c], live_off[c + 1]):
            i = live_idx[k]
            qx = ch * pts[i, 0] - sh * pts[i, 1] + tx
            qy = sh * pts[i, 0] + ch * pts[i, 1] + ty
            qz = pts[i, 2] + tz
            d = _nearest(qx, qy, qz, ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off,
                         cand_idx, cap)
            if d <= cap:
                acc += math.log(k1 + k2n * math.exp(-d * d * inv2s2))
            else:
                acc += ln_k1
        out_score[c] = acc


@nb.njit(cache=True)
def _compact(keep, off, cnt, live):
    """CSR of the live lists of the kept cells."""
    n = 0
    for c in range(keep.shape[0]):
        if keep[c]:
            n += cnt[c]
    new_off = np.zeros(int(keep.sum()) + 1, np.int64)
    new_live = np.empty(n, live.dtype)
    j = 0
    w = 0
    for c in range(keep.shape[0]):
        if keep[c]:
            new_live[w : w + cnt[c]] = live[off[c] : off[c] + cnt[c]]
            w += cnt[c]
            new_off[j + 1] = w
            j += 1
    return new_off, new_live


class ReferenceField:
    """Nearest-neighbour index of map A for exact scores and rigorous bounds (module docstring).

    ``fine_m`` (0.1 m), ``coarse_m`` (0.3 m), ``coarse_cap_m`` (3 m), ``table_step_m`` (0.1 mm)
    and ``box_max_m`` (largest displacement for which the per-axis bound is tried, 0.2 m) are
    (inferred) implementation parameters; they change speed, never the result.
    """

    def __init__(
        self,
        reference: np.ndarray,
        model: ScoreModel,
        fine_m: float = 0.1,
        coarse_m: float = 0.3,
        coarse_cap_m: float = 3.0,
        table_step_m: float = 0.0001,
        box_max_m: float = 0.2,
        list_margin_m: float = 0.05,
    ):
        ref = np.ascontiguousarray(np.asarray(reference, dtype=np.float64).reshape(-1, 3))
        if len(ref) == 0:
            raise ValueError("reference: no points")
        self.model = model
        self.ref = ref
        self.cap = model.cap_m
        self.bb_lo = ref.min(0)
        self.bb_hi = ref.max(0)
        margin = self.cap + fine_m
        self.f_s = float(fine_m)
        self.f_origin = self.bb_lo - margin
        f_shape = np.ceil((self.bb_hi + margin - self.f_origin) / fine_m).astype(np.int64) + 1
        self.nb_shape = (f_shape + BLOCK - 1) // BLOCK
        self.f_shape = self.nb_shape * BLOCK
        self.bmap, self.n_blocks = _mark_blocks(ref, self.f_origin, self.f_s, self.nb_shape, self.cap)
        self.cand_off, self.cand_idx, self.ub = _build_candidates(
            ref, self.f_origin, self.f_s, self.f_shape, self.nb_shape, self.bmap, self.n_blocks,
            self.cap, float(list_margin_m), max(1, min(nb.get_num_threads(), len(ref) // 500)),
        )
        self.b_off, self.b_idx = _build_buckets(
            ref, self.f_origin, self.f_s, self.nb_shape, self.bmap, self.n_blocks
        )
        self.box_max_m = float(box_max_m)
        # coarse lower-bound grid from the point boxes of occupied coarse voxels
        self.c_s = float(coarse_m)
        cmargin = coarse_cap_m + coarse_m
        self.c_origin = self.bb_lo - cmargin
        self.c_shape = np.ceil((self.bb_hi + cmargin - self.c_origin) / coarse_m).astype(np.int64) + 1
        key = np.floor((ref - self.c_origin) / coarse_m).astype(np.int64)
        lin = (key[:, 0] * self.c_shape[1] + key[:, 1]) * self.c_shape[2] + key[:, 2]
        order = np.argsort(lin, kind="stable")
        lin_sorted = lin[order]
        starts = np.flatnonzero(np.r_[True, lin_sorted[1:] != lin_sorted[:-1]])
        box_lo = np.minimum.reduceat(ref[order], starts, axis=0)
        box_hi = np.maximum.reduceat(ref[order], starts, axis=0)
        self.lb = _build_coarse_lb(
            box_lo, box_hi, self.c_origin, self.c_s, self.c_shape, float(coarse_cap_m)
        )
        self.table_step = float(table_step_m)
        n_tab = int(np.ceil(self.cap / table_step_m)) + 2
        dist = np.arange(n_tab) * table_step_m
        # ln p at step k: read at floor(d / step) it bounds ln p(d) from above (bounds), read at
        # floor(d / step) + 1 from below (quick scores)
        self.table = model.log_p(dist)
        self.table[-1] = model.ln_k1

    # geometry arguments shared by the kernels
    def _geo(self):
        return (self.ref, self.f_origin, self.f_s, self.f_shape, self.nb_shape, self.bmap,
                self.cand_off, self.cand_idx)

    def evaluate(
        self,
        poses: np.ndarray,
        points: np.ndarray,
        delta: np.ndarray | None = None,
        rot: np.ndarray | None = None,
        e_box: np.ndarray | None = None,
        weight: np.ndarray | None = None,
        score: bool = True,
        bound: bool = True,
        active: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Exact scores ``sum_i w_i ln p(D_i(T))`` at ``poses`` (k, 4: dx, dy, dz, dh in radians)
        and bounds ``sum_i w_i ln p(max(D_i - delta_i, 0))`` (spec 6.4); NaN where not asked.

        With ``rot`` (per-point rotation chord) and ``e_box`` (translation half-extents of the
        cell about the pose) the bound of points with ``delta_i <= box_max_m`` uses the tighter
        per-axis form (:func:`_box_lower`). ``active`` (uint8, n), when given, is set to 1 for
        every point whose bound term exceeds ``ln k1`` in some cell."""
        poses = np.ascontiguousarray(np.asarray(poses, dtype=np.float64).reshape(-1, 4))
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        n = len(pts)
        delta = np.zeros(n) if delta is None else np.ascontiguousarray(delta, dtype=np.float64)
        weight = np.ones(n) if weight is None else np.ascontiguousarray(weight, dtype=np.float64)
        use_box = rot is not None and e_box is not None
        rot = np.zeros(n) if rot is None else np.ascontiguousarray(rot, dtype=np.float64)
        e_box = np.zeros(3) if e_box is None else np.ascontiguousarray(e_box, dtype=np.float64)
        box_max = self.box_max_m if use_box else -1.0
        flags = np.zeros(n, np.uint8) if active is None else active
        out_s = np.full(len(poses), np.nan)
        out_b = np.full(len(poses), np.nan)
        if len(poses) == 0:
            return out_s, out_b
        m = self.model
        _eval_cells(
            poses, pts, delta, rot, e_box, box_max, weight, bool(score), bool(bound),
            *self._geo(), self.b_off, self.b_idx, self.cap,
            self.c_origin, self.c_s, self.c_shape, self.lb, self.bb_lo, self.bb_hi,
            m.k1, m.ln_k1, m.k2 / (m.sigma_m * np.sqrt(2 * np.pi)), 0.5 / m.sigma_m**2,
            self.table, 1.0 / self.table_step, out_s, out_b, flags,
        )
        return out_s, out_b

    def eval_live(self, poses, parent, live_off, live_idx, pts, d_xy, e, tight: bool,
                  lo=None, hi=None, par_terms=None, par_bound=None, thresh=-np.inf):
        """Cells ``poses`` (radians) with largest offsets ``e`` (4,) to their faces, each
        evaluated on the live points of ``parent`` (CSR ``live_off``/``live_idx``).

        Returns (bound, quick score lower bound, child live CSR offsets, child live points).
        ``tight`` enables the per-axis bound for displacements up to ``box_max_m``, over the
        asymmetric offset box ``[lo, hi]`` (4,: dx, dy, dz m, dh rad about each pose, within
        ``+-e``) when given (:func:`_eval_live_box`; then also ``par_terms``/``par_bound``/
        ``thresh``, the parent terms and early stop there, and a sixth result, the child live
        points' terms)."""
        if tight and lo is not None:
            return self._eval_live_box(poses, parent, live_off, live_idx, pts, d_xy, e, lo, hi,
                                       par_terms, par_bound, thresh)
        n_cells = len(poses)
        counts = np.diff(live_off)[parent]
        out_off = np.zeros(n_cells + 1, np.int64)
        np.cumsum(counts, out=out_off[1:])
        out_live = np.empty(int(out_off[-1]), np.int32)
        out_cnt = np.zeros(n_cells, np.int64)
        out_b = np.empty(n_cells)
        out_s = np.empty(n_cells)
        t_ext = float(np.sqrt(np.sum(np.asarray(e[:3]) ** 2)))
        sin_h = float(np.sin(min(e[3], np.pi) / 2.0))
        m = self.model
        _eval_live(
            np.ascontiguousarray(poses, dtype=np.float64), parent.astype(np.int64), live_off,
            live_idx, len(pts), pts, d_xy, t_ext, sin_h, self.box_max_m if tight else -1.0,
            np.ascontiguousarray(e[:3], dtype=np.float64),
            *self._geo(), self.ub, self.cap,
            self.c_origin, self.c_s, self.c_shape, self.lb, self.bb_lo, self.bb_hi,
            m.ln_k1, self.table, self.table, 1.0 / self.table_step,
            out_b, out_s, out_off, out_cnt, out_live,
        )
        return out_b, out_s, out_off, out_cnt, out_live

    def _eval_live_box(self, poses, parent, live_off, live_idx, pts, d_xy, e, lo, hi,
                       par_terms=None, par_bound=None, thresh=-np.inf):
        e = np.asarray(e, dtype=np.float64)
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        if np.any(lo > 1e-12) or np.any(hi < -1e-12) or np.any(np.maximum(-lo, hi) > e + 1e-12):
            raise ValueError("eval_live: the offset box [lo, hi] must hold 0 and lie within +-e")
        n_cells = len(poses)
        counts = np.diff(live_off)[parent]
        out_off = np.zeros(n_cells + 1, np.int64)
        np.cumsum(counts, out=out_off[1:])
        out_live = np.empty(int(out_off[-1]), np.int32)
        out_cnt = np.zeros(n_cells, np.int64)
        out_b = np.empty(n_cells)
        out_s = np.empty(n_cells)
        t_ext = float(np.sqrt(np.sum(e[:3] ** 2)))
        a_max = min(float(e[3]), np.pi)
        chord = 2.0 * np.sin(a_max / 2.0)
        # range of sin a over [lo_h, hi_h] (lo_h <= 0 <= hi_h; sin rises on [-pi/2, pi/2]) and
        # the largest 1 - cos a
        s_lo = -1.0 if lo[3] <= -np.pi / 2 else float(np.sin(lo[3]))
        s_hi = 1.0 if hi[3] >= np.pi / 2 else float(np.sin(hi[3]))
        eps_fac = float(1.0 - np.cos(a_max))
        if par_terms is None:
            par_terms = np.full(len(live_idx), np.inf)
            par_bound = np.full(len(live_off) - 1, np.inf)
        out_t = np.empty(len(out_live))
        m = self.model
        _eval_live_box(
            np.ascontiguousarray(poses, dtype=np.float64), parent.astype(np.int64), live_off,
            live_idx, len(pts), pts, d_xy, t_ext, chord, self.box_max_m, lo, hi, s_lo, s_hi,
            eps_fac, par_terms, np.asarray(par_bound, dtype=np.float64), float(thresh),
            *self._geo(), self.ub, self.cap,
            self.c_origin, self.c_s, self.c_shape, self.lb, self.bb_lo, self.bb_hi,
            m.ln_k1, self.table, self.table, 1.0 / self.table_step,
            out_b, out_s, out_off, out_cnt, out_live, out_t,
        )
        return out_b, out_s, out_off, out_cnt, out_live, out_t

    def exact_live(self, poses, live_off, live_idx, pts) -> np.ndarray:
        """Exact scores of cells at ``poses`` from their own live lists."""
        if len(live_off) != len(poses) + 1:
            raise ValueError(f"exact_live: {len(poses)} cells but {len(live_off) - 1} live lists")
        m = self.model
        out = np.empty(len(poses))
        _exact_live(
            np.ascontiguousarray(poses, dtype=np.float64), live_off, live_idx, len(pts), pts,
            *self._geo(), self.cap, m.k1, m.ln_k1, m.k2 / (m.sigma_m * np.sqrt(2 * np.pi)),
            0.5 / m.sigma_m**2, out,
        )
        return out


def compact_live(keep: np.ndarray, off: np.ndarray, cnt: np.ndarray, live: np.ndarray):
    """Live CSR of the kept cells (``keep`` bool)."""
    return _compact(np.ascontiguousarray(keep, dtype=np.bool_), off, cnt, live)
