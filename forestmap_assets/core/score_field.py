"""Fast score and bound evaluation of registration cells (spec 6.3-6.4, inferred data structures).

Map A (the reference) is indexed once per pair by :class:`ReferenceField`:

* a fine voxel grid (``fine_m``, default 0.1 m) whose every voxel ``v`` lists the candidate points
  ``C_v = {a : dist(a, box_v) <= min(ub_v, cap)}``, with ``ub_v = min_a maxdist(a, box_v)``. For a
  query ``q`` in ``box_v`` the nearest point ``a*`` satisfies ``dist(a*, box_v) <= |q - a*| <= ub_v``,
  so ``min_{C_v} |q - a|`` is the **exact** nearest-neighbour distance whenever it is ``<= cap``,
  and otherwise ``D(q) > cap`` (where ``ln p(D) == ln k1`` in float64): scores are exact, not
  interpolated;
* a coarse grid (``coarse_m``, 0.25 m) of rigorous lower bounds ``min_a dist(a, box_v)`` (point
  boxes of occupied coarse voxels, capped at ``coarse_cap_m``), used by bounds beyond ``cap``.

The cell bound of spec 6.4 (Eq. 5.11-5.14) is ``sum_i w_i ln p(max(D_lo,i - Delta_i, 0))`` with a
per-point displacement ``Delta_i`` (translation corner distance + rotation chord
``2 d_e sin(phi_h / 2)``); ``ln p`` of the bound is read from a table rounded towards smaller
distances (an upper bound). Kernels are compiled with numba (an added dependency, for speed).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .score import ScoreModel


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
def _stamp(ref, origin, s, shape, cap, ub, mode, count, idx, fill):
    """One pass over the voxels within ``cap`` of each point: mode 0 sets ``ub``, mode 1 counts
    candidates, mode 2 writes them."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    r = int(math.ceil(cap / s)) + 1
    lo = np.empty(3)
    for p in range(ref.shape[0]):
        a = ref[p]
        cx = int((a[0] - origin[0]) / s)
        cy = int((a[1] - origin[1]) / s)
        cz = int((a[2] - origin[2]) / s)
        for ix in range(max(cx - r, 0), min(cx + r + 1, nx)):
            lo[0] = origin[0] + ix * s
            for iy in range(max(cy - r, 0), min(cy + r + 1, ny)):
                lo[1] = origin[1] + iy * s
                for iz in range(max(cz - r, 0), min(cz + r + 1, nz)):
                    lo[2] = origin[2] + iz * s
                    v = (ix * ny + iy) * nz + iz
                    dmin, dmax = _box_dists(a, lo, s)
                    if mode == 0:
                        if dmin <= cap and dmax < ub[v]:
                            ub[v] = dmax
                    elif dmin <= min(ub[v], cap):
                        if mode == 1:
                            count[v + 1] += 1
                        else:
                            idx[fill[v]] = p
                            fill[v] += 1


@nb.njit(cache=True)
def _build_candidates(ref, origin, s, shape, cap):
    """CSR candidate lists per fine voxel (see module docstring)."""
    nvox = shape[0] * shape[1] * shape[2]
    ub = np.full(nvox, np.inf)
    count = np.zeros(nvox + 1, np.int64)
    idx = np.empty(0, np.int32)
    fill = np.empty(0, np.int64)
    _stamp(ref, origin, s, shape, cap, ub, 0, count, idx, fill)
    _stamp(ref, origin, s, shape, cap, ub, 1, count, idx, fill)
    for v in range(nvox):
        count[v + 1] += count[v]
    fill = count[:-1].copy()
    idx = np.empty(count[nvox], np.int32)
    _stamp(ref, origin, s, shape, cap, ub, 2, count, idx, fill)
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


@nb.njit(cache=True, inline="always")
def _nearest(qx, qy, qz, ref, f_origin, f_s, f_shape, cand_off, cand_idx, cap):
    """Exact nearest distance if ``<= cap``, else ``inf`` (module docstring)."""
    ix = int(math.floor((qx - f_origin[0]) / f_s))
    iy = int(math.floor((qy - f_origin[1]) / f_s))
    iz = int(math.floor((qz - f_origin[2]) / f_s))
    if ix < 0 or iy < 0 or iz < 0 or ix >= f_shape[0] or iy >= f_shape[1] or iz >= f_shape[2]:
        return np.inf
    v = (ix * f_shape[1] + iy) * f_shape[2] + iz
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


@nb.njit(cache=True, inline="always")
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
def _box_lower(qx, qy, qz, d, lip, ex, ey, ez, ref, f_origin, f_s, f_shape, b_off, b_idx, cap):
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
            v0 = (ix * f_shape[1] + iy) * f_shape[2]
            for c in range(b_off[v0 + z0], b_off[v0 + z1 + 1]):
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


@nb.njit(cache=True, parallel=True)
def _eval_cells(
    poses, pts, delta, rot, e_box, box_max, weight, do_score, do_bound,
    ref, f_origin, f_s, f_shape, cand_off, cand_idx, b_off, b_idx, cap,
    c_origin, c_s, c_shape, lb, bb_lo, bb_hi,
    k1, ln_k1, k2n, inv2s2, table, inv_step,
    out_score, out_bound, active,
):
    """Score at each cell's pose and bound over the cell (spec 6.4, Eq. 5.11-5.12)."""
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
            d = _nearest(qx, qy, qz, ref, f_origin, f_s, f_shape, cand_off, cand_idx, cap)
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
                        ref, f_origin, f_s, f_shape, b_off, b_idx, cap,
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


class ReferenceField:
    """Nearest-neighbour index of map A for exact scores and rigorous bounds (module docstring).

    ``fine_m`` (0.1 m), ``coarse_m`` (0.25 m), ``coarse_cap_m`` (3 m) and ``table_step_m``
    (0.1 mm) are (inferred) implementation parameters; they change speed, never the result.
    """

    def __init__(
        self,
        reference: np.ndarray,
        model: ScoreModel,
        fine_m: float = 0.1,
        coarse_m: float = 0.25,
        coarse_cap_m: float = 3.0,
        table_step_m: float = 0.0001,
        box_max_m: float = 0.2,
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
        self.f_shape = np.ceil((self.bb_hi + margin - self.f_origin) / fine_m).astype(np.int64) + 1
        self.cand_off, self.cand_idx = _build_candidates(
            ref, self.f_origin, self.f_s, self.f_shape, self.cap
        )
        # points bucketed by fine voxel (CSR), for the per-axis bound's range search
        fk = np.floor((ref - self.f_origin) / fine_m).astype(np.int64)
        flin = (fk[:, 0] * self.f_shape[1] + fk[:, 1]) * self.f_shape[2] + fk[:, 2]
        self.b_idx = np.argsort(flin, kind="stable").astype(np.int32)
        nvox = int(np.prod(self.f_shape))
        self.b_off = np.zeros(nvox + 1, np.int64)
        np.cumsum(np.bincount(flin, minlength=nvox), out=self.b_off[1:])
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
        self.table = model.log_p(np.arange(n_tab) * table_step_m)
        self.table[-1] = model.ln_k1

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
        """Scores ``sum_i w_i ln p(D_i(T))`` at ``poses`` (k, 4: dx, dy, dz, dh in radians) and
        bounds ``sum_i w_i ln p(max(D_i - delta_i, 0))`` (spec 6.4); NaN where not asked.

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
            self.ref, self.f_origin, self.f_s, self.f_shape, self.cand_off, self.cand_idx,
            self.b_off, self.b_idx, self.cap,
            self.c_origin, self.c_s, self.c_shape, self.lb, self.bb_lo, self.bb_hi,
            m.k1, m.ln_k1, m.k2 / (m.sigma_m * np.sqrt(2 * np.pi)), 0.5 / m.sigma_m**2,
            self.table, 1.0 / self.table_step, out_s, out_b, flags,
        )
        return out_s, out_b
