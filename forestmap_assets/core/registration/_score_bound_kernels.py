"""Numba kernels that evaluate scores and cell bounds on a :class:`~.score_field.ReferenceField`
(spec 6.3-6.4, Eq. 5.11-5.14): cell evaluation over all points or a cell's live points (symmetric
``+-e`` or exact asymmetric offset box), exact scores of final cells and live-list compaction;
the distance kernels they call are in :mod:`._distance_kernels`."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from forestmap_assets.core.registration._distance_kernels import (
    _box_lower,
    _coarse_lower,
    _nearest,
    _nearest_abox,
    _nearest_box,
)
from forestmap_assets.core.registration._field_index_kernels import _FAST


@nb.njit(cache=True, parallel=True, fastmath=_FAST)
def _eval_cells(
    poses,
    pts,
    delta,
    rot,
    e_box,
    box_max,
    weight,
    do_score,
    do_bound,
    ref,
    f_origin,
    f_s,
    f_shape,
    nb_shape,
    bmap,
    cand_off,
    cand_idx,
    cand_lb,
    b_off,
    b_idx,
    cap,
    c_origin,
    c_s,
    c_shape,
    lb,
    bb_lo,
    bb_hi,
    k1,
    ln_k1,
    k2n,
    inv2s2,
    table,
    inv_step,
    out_score,
    out_bound,
    active,
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
            d = _nearest(
                qx, qy, qz, ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off, cand_idx,
                cand_lb, cap,
            )
            if do_score:
                if d <= cap:
                    s_acc += weight[i] * math.log(k1 + k2n * math.exp(-d * d * inv2s2))
                else:
                    s_acc += weight[i] * ln_k1
            if do_bound:
                if d > cap:
                    d = max(
                        cap, _coarse_lower(qx, qy, qz, c_origin, c_s, c_shape, lb, bb_lo, bb_hi)
                    )
                    r = d - delta[i]
                elif delta[i] <= box_max and d - delta[i] < cap:
                    r = _box_lower(
                        qx,
                        qy,
                        qz,
                        d,
                        delta[i],
                        e_box[0] + rot[i],
                        e_box[1] + rot[i],
                        e_box[2],
                        ref,
                        f_origin,
                        f_s,
                        f_shape,
                        nb_shape,
                        bmap,
                        b_off,
                        b_idx,
                        cap,
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
    poses,
    parent,
    live_off,
    live_idx,
    n_total,
    pts,
    d_xy,
    t_ext,
    sin_h,
    box_max,
    e_box,
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
    c_origin,
    c_s,
    c_shape,
    lb,
    bb_lo,
    bb_hi,
    ln_k1,
    table_hi,
    table_lo,
    inv_step,
    out_bound,
    out_score,
    out_off,
    out_cnt,
    out_live,
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
                d, r = _nearest_box(
                    qx,
                    qy,
                    qz,
                    delta,
                    e_box[0] + rot,
                    e_box[1] + rot,
                    e_box[2],
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
            else:
                d = _nearest(
                    qx, qy, qz, ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off, cand_idx,
                    cand_lb, cap,
                )
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
    poses,
    parent,
    live_off,
    live_idx,
    n_total,
    pts,
    d_xy,
    t_ext,
    chord,
    box_max,
    lo,
    hi,
    s_lo,
    s_hi,
    eps_fac,
    par_terms,
    par_bound,
    thresh,
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
    c_origin,
    c_s,
    c_shape,
    lb,
    bb_lo,
    bb_hi,
    ln_k1,
    table_hi,
    table_lo,
    inv_step,
    out_bound,
    out_score,
    out_off,
    out_cnt,
    out_live,
    out_terms,
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
                d, r = _nearest_abox(
                    qx,
                    qy,
                    qz,
                    delta,
                    lo[0] + rx_lo,
                    hi[0] + rx_hi,
                    lo[1] + ry_lo,
                    hi[1] + ry_hi,
                    lo[2],
                    hi[2],
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
            else:
                d = _nearest(
                    qx, qy, qz, ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off, cand_idx,
                    cand_lb, cap,
                )
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
    poses,
    live_off,
    live_idx,
    n_total,
    pts,
    ref,
    f_origin,
    f_s,
    f_shape,
    nb_shape,
    bmap,
    cand_off,
    cand_idx,
    cand_lb,
    cap,
    k1,
    ln_k1,
    k2n,
    inv2s2,
    out_score,
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
            d = _nearest(
                qx, qy, qz, ref, f_origin, f_s, f_shape, nb_shape, bmap, cand_off, cand_idx,
                cand_lb, cap,
            )
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
