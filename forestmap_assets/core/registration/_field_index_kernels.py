"""Numba kernels that build the index of :class:`~.score_field.ReferenceField` (spec 6.3-6.4,
inferred): the sparse block map (``BLOCK``^3 fine voxels per block, :func:`_slot` maps a voxel to
its slot), the exact-nearest candidate lists per fine voxel, point buckets and the coarse grid of
rigorous distance lower bounds."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

BLOCK = 8  # voxels per block edge (fixed: index arithmetic uses shifts by 3)


_FAST = {"nsz", "arcp", "contract", "reassoc"}  # fast math, but inf stays meaningful


@nb.njit(cache=True, inline="always")
def _gap(a, lo, s):
    """Distance from ``a`` to ``[lo, lo + s]`` on one axis (:func:`_box_dists`, :func:`_stamp`)."""
    hi = lo + s
    if a < lo:
        return lo - a
    if a > hi:
        return a - hi
    return 0.0


@nb.njit(cache=True)
def _box_dists(a, lo, s):
    """(min, max) distance from point ``a`` to the voxel box ``[lo, lo + s]``."""
    dmin = 0.0
    dmax = 0.0
    for k in range(3):
        t = _gap(a[k], lo[k], s)
        dmin += t * t
        u = max(abs(a[k] - lo[k]), abs(a[k] - (lo[k] + s)))
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
def _stamp(
    ref, origin, s, shape, nb_shape, bmap, cap, ub, mode, count, idx, lbs, fill, margin, p_start,
    p_end,
):
    """One pass over the voxels within ``cap`` of each point ``p_start <= p < p_end``: mode 0
    lowers ``ub``, mode 1 counts candidates, mode 2 writes them (``idx``) with their distance
    from the voxel (``lbs``, float32, a micrometre less, so that rounding never raises it). A
    column of voxels is visited only over the heights its horizontal distance leaves within
    ``cap`` (and a voxel more each way; the test of each voxel is unchanged): the same voxels, a
    third of the visits."""
    r = int(math.ceil(cap / s)) + 1
    lo = np.empty(3)
    for p in range(p_start, p_end):
        a = ref[p]
        cx = int((a[0] - origin[0]) / s)
        cy = int((a[1] - origin[1]) / s)
        cz = int((a[2] - origin[2]) / s)
        for ix in range(max(cx - r, 0), min(cx + r + 1, shape[0])):
            lo[0] = origin[0] + ix * s
            gx = _gap(a[0], lo[0], s)
            for iy in range(max(cy - r, 0), min(cy + r + 1, shape[1])):
                lo[1] = origin[1] + iy * s
                gy = _gap(a[1], lo[1], s)
                g2 = gx * gx + gy * gy  # as _box_dists sums it: no voxel of the column is nearer
                if math.sqrt(g2) > cap:
                    continue
                h = math.sqrt(max(cap * cap - g2, 0.0))
                z0 = max(int(math.floor((a[2] - h - origin[2]) / s)) - 1, cz - r, 0)
                z1 = min(int(math.floor((a[2] + h - origin[2]) / s)) + 1, cz + r, shape[2] - 1)
                for iz in range(z0, z1 + 1):
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
                            lbs[fill[v]] = max(dmin - 1e-6, 0.0)
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
    lbs = np.empty(0, np.float32)
    fill = np.empty(0, np.int64)
    for t in nb.prange(n_parts):
        _stamp(
            ref,
            origin,
            s,
            shape,
            nb_shape,
            bmap,
            cap,
            ubs[t],
            0,
            counts[t],
            idx,
            lbs,
            fill,
            margin,
            cut[t],
            cut[t + 1],
        )
    ub = np.empty(nvox)
    for v in nb.prange(nvox):
        m = np.inf
        for t in range(n_parts):
            m = min(m, ubs[t, v])
        ub[v] = m
    for t in nb.prange(n_parts):
        _stamp(
            ref,
            origin,
            s,
            shape,
            nb_shape,
            bmap,
            cap,
            ub,
            1,
            counts[t],
            idx,
            lbs,
            fill,
            margin,
            cut[t],
            cut[t + 1],
        )
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
    lbs = np.empty(count[nvox], np.float32)
    for t in nb.prange(n_parts):
        _stamp(
            ref,
            origin,
            s,
            shape,
            nb_shape,
            bmap,
            cap,
            ub,
            2,
            counts[t],
            idx,
            lbs,
            fills[t],
            margin,
            cut[t],
            cut[t + 1],
        )
    _sort_candidates(count, idx, lbs)
    return count, idx, lbs, np.minimum(ub + margin, cap).astype(np.float32)


@nb.njit(cache=True, parallel=True)
def _sort_candidates(count, idx, lbs):
    """Each voxel's candidates in ascending order of their distance from the voxel (``lbs``):
    no candidate after one as far as the nearest found so far can be nearer to any point of the
    voxel, so the nearest-distance loops stop there (:mod:`._distance_kernels`). An insertion
    sort: the lists are short."""
    for v in nb.prange(count.shape[0] - 1):
        for c in range(count[v] + 1, count[v + 1]):
            key, j = lbs[c], idx[c]
            m = c - 1
            while m >= count[v] and lbs[m] > key:
                lbs[m + 1] = lbs[m]
                idx[m + 1] = idx[m]
                m -= 1
            lbs[m + 1] = key
            idx[m + 1] = j


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
            gx = max(
                origin[0] + ix * s - box_hi[p, 0], box_lo[p, 0] - origin[0] - (ix + 1) * s, 0.0
            )
            for iy in range(max(cy - r, 0), min(cy + r + 1, ny)):
                gy = max(
                    origin[1] + iy * s - box_hi[p, 1], box_lo[p, 1] - origin[1] - (iy + 1) * s, 0.0
                )
                for iz in range(max(cz - r, 0), min(cz + r + 1, nz)):
                    gz = max(
                        origin[2] + iz * s - box_hi[p, 2],
                        box_lo[p, 2] - origin[2] - (iz + 1) * s,
                        0.0,
                    )
                    d = math.sqrt(gx * gx + gy * gy + gz * gz)
                    v = (ix * ny + iy) * nz + iz
                    if d < lb[v]:
                        lb[v] = d
    return lb
