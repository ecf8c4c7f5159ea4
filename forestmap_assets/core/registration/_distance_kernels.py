"""Numba kernels of the nearest distance and the cell lower bounds on a
:class:`~.score_field.ReferenceField` (spec 6.3-6.4, Eq. 5.11-5.14): exact nearest distances from
the candidate lists (plain, symmetric ``+-e`` box, asymmetric offset box), coarse and per-axis
box lower bounds."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from forestmap_assets.core.registration._field_index_kernels import _FAST, _slot


@nb.njit(cache=True, inline="always", fastmath=_FAST)
def _nearest(
    qx, qy, qz, ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off, cand_idx, cand_lb, cap
):
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
        lb = np.float64(cand_lb[c])
        if lb * lb >= best:  # the rest are as far from the whole voxel
            break
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
def _nearest_abox(
    qx,
    qy,
    qz,
    lip,
    lx,
    hx,
    ly,
    hy,
    lz,
    hz,
    ref,
    f_origin,
    f_s,
    f_shape,
    nb_shape,
    bmap,
    cand_off,
    cand_idx,
    cand_lb,
    ub,
    cap,
):
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
    start, end = cand_off[v], cand_off[v + 1]
    for c in range(start, end):
        lb = np.float64(cand_lb[c])
        if lb * lb >= best:  # the rest are as far from the whole voxel
            break
        j = cand_idx[c]
        dx = ref[j, 0] - qx
        dy = ref[j, 1] - qy
        dz = ref[j, 2] - qz
        d2 = dx * dx + dy * dy + dz * dz
        if d2 < best:
            best = d2
    d = math.sqrt(best)
    if d > cap:
        return np.inf, np.inf
    low = d - lip
    if d + 2.0 * lip <= ub[v]:
        # the box's reach beyond the voxel: a candidate lb from the voxel is at least lb - reach
        # from every position of the box
        rx = max(-lx, hx)
        ry = max(-ly, hy)
        rz = max(-lz, hz)
        reach = math.sqrt(rx * rx + ry * ry + rz * rz)
        boxb = np.inf
        for c in range(start, end):
            lb = np.float64(cand_lb[c]) - reach
            if lb > 0.0 and lb * lb >= boxb:
                break
            j = cand_idx[c]
            dx = ref[j, 0] - qx
            dy = ref[j, 1] - qy
            dz = ref[j, 2] - qz
            gx = max(dx - hx, lx - dx, 0.0)
            gy = max(dy - hy, ly - dy, 0.0)
            gz = max(dz - hz, lz - dz, 0.0)
            g2 = gx * gx + gy * gy + gz * gz
            if g2 < boxb:
                boxb = g2
        low = max(low, math.sqrt(boxb))
    return d, low


@nb.njit(cache=True, inline="always", fastmath=_FAST)
def _nearest_box(
    qx,
    qy,
    qz,
    lip,
    ex,
    ey,
    ez,
    ref,
    f_origin,
    f_s,
    f_shape,
    nb_shape,
    bmap,
    cand_off,
    cand_idx,
    cand_lb,
    ub,
    cap,
):
    """Exact nearest distance ``d`` (``inf`` beyond ``cap``) and, in the same candidate loop, a
    lower bound of the nearest distance over the displacement box ``|p - q|_a <= (ex, ey, ez)``,
    ``|p - q| <= lip`` (spec 6.4 "tighter bound", inferred form): :func:`_nearest_abox` with the
    symmetric box. Points farther than ``rho = d + 2 lip`` from ``q`` cannot be nearest anywhere
    in the box; when ``rho <= ub_v`` they are all candidates of ``q``'s voxel, so the per-axis
    bound over the candidates is rigorous; otherwise the Lipschitz bound ``d - lip`` is
    returned."""
    return _nearest_abox(
        qx,
        qy,
        qz,
        lip,
        -ex,
        ex,
        -ey,
        ey,
        -ez,
        ez,
        ref,
        f_origin,
        f_s,
        f_shape,
        nb_shape,
        bmap,
        cand_off,
        cand_idx,
        cand_lb,
        ub,
        cap,
    )


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
def _box_lower(
    qx, qy, qz, d, lip, ex, ey, ez, ref, f_origin, f_s, f_shape, nb_shape, bmap, b_off, b_idx, cap
):
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
