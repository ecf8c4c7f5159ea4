"""Fast score and bound evaluation of registration cells (spec 6.3-6.4, inferred data structures).

Map A (the reference) is indexed once per pair by :class:`ReferenceField`: a **sparse block grid**
of fine voxels (``fine_m``, default 0.2 m; blocks of 8^3 voxels, only blocks within ``cap`` of A
stored) whose voxels list candidate points ``C_v = {a : dist(a, box_v) <= min(ub_v, cap)}``,
``ub_v = min_a maxdist(a, box_v)``, so ``min_{C_v} |q - a|`` is the **exact** nearest distance
of a query ``q`` in ``box_v`` whenever it is ``<= cap`` (otherwise ``ln p(D) == ln k1``): scores
are exact, not interpolated (:mod:`._field_index_kernels`); and a coarse grid (``coarse_m``) of
rigorous lower bounds ``min_a dist(a, box_v)`` used by bounds beyond ``cap``. Each list is
sorted by ``dist(a, box_v)`` (kept in ``cand_lb``), and the nearest-distance loops stop
at the first candidate as far as the nearest found (the same minimum). The lookups, not the
arithmetic, bound the speed: 0.2 m voxels (a third of the 0.1 m index's memory, 33 MB for a
12,000-point sub-map of 120 stems) made the branch and bound 13-22 % faster than 0.1 m on
Sylva's, own realistic and rendered dense pairs, with the same results
(``benchmarks/results.md``, "session40").

The cell bound of spec 6.4 (Eq. 5.11-5.14) is ``sum_i w_i ln p(max(D_lo,i - Delta_i, 0))`` with a
per-point displacement ``Delta_i`` (translation corner distance + rotation chord
``2 d_e sin(phi_h / 2)``); ``ln p`` of the bound is read from a table rounded towards smaller
distances (an upper bound), the "quick" score from one rounded towards larger distances (a lower
bound of the exact score). **Live points** (inferred, exact): a point whose bound term is ``ln k1``
over a cell contributes exactly ``ln k1`` to every sub-cell, so :meth:`ReferenceField.eval_live`
evaluates each cell only on the points still live in its parent and returns the child's own live
list; with an offset box ``[lo, hi]`` the per-axis bound uses the cell's exact asymmetric box,
keeps each point's term no larger than in the parent cell and stops a cell early once the parent's
bound minus the drops so far falls below the best score (kernels: :mod:`._score_bound_kernels`)."""

from __future__ import annotations

import numba as nb
import numpy as np

from forestmap_assets.core.registration._field_index_kernels import (
    BLOCK,
    _build_buckets,
    _build_candidates,
    _build_coarse_lb,
    _mark_blocks,
)
from forestmap_assets.core.registration._score_bound_kernels import (
    _compact,
    _eval_cells,
    _eval_live,
    _eval_live_box,
    _exact_live,
)
from forestmap_assets.core.registration.score import ScoreModel


class ReferenceField:
    """Nearest-neighbour index of map A for exact scores and rigorous bounds (module docstring).

    ``fine_m`` (0.2 m), ``coarse_m`` (0.3 m), ``coarse_cap_m`` (3 m), ``table_step_m`` (0.1 mm)
    and ``box_max_m`` (largest displacement for which the per-axis bound is tried, 0.2 m) are
    (inferred) implementation parameters; they change speed, never the result.
    """

    def __init__(
        self,
        reference: np.ndarray,
        model: ScoreModel,
        fine_m: float = 0.2,
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
        self.bmap, self.n_blocks = _mark_blocks(
            ref, self.f_origin, self.f_s, self.nb_shape, self.cap
        )
        self.cand_off, self.cand_idx, self.cand_lb, self.ub = _build_candidates(
            ref,
            self.f_origin,
            self.f_s,
            self.f_shape,
            self.nb_shape,
            self.bmap,
            self.n_blocks,
            self.cap,
            float(list_margin_m),
            max(1, min(nb.get_num_threads(), len(ref) // 500)),
        )
        self.b_off, self.b_idx = _build_buckets(
            ref, self.f_origin, self.f_s, self.nb_shape, self.bmap, self.n_blocks
        )
        self.box_max_m = float(box_max_m)
        # coarse lower-bound grid from the point boxes of occupied coarse voxels
        self.c_s = float(coarse_m)
        cmargin = coarse_cap_m + coarse_m
        self.c_origin = self.bb_lo - cmargin
        self.c_shape = (
            np.ceil((self.bb_hi + cmargin - self.c_origin) / coarse_m).astype(np.int64) + 1
        )
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
        return (
            self.ref,
            self.f_origin,
            self.f_s,
            self.f_shape,
            self.nb_shape,
            self.bmap,
            self.cand_off,
            self.cand_idx,
            self.cand_lb,
        )

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
            poses,
            pts,
            delta,
            rot,
            e_box,
            box_max,
            weight,
            bool(score),
            bool(bound),
            *self._geo(),
            self.b_off,
            self.b_idx,
            self.cap,
            self.c_origin,
            self.c_s,
            self.c_shape,
            self.lb,
            self.bb_lo,
            self.bb_hi,
            m.k1,
            m.ln_k1,
            m.k2 / (m.sigma_m * np.sqrt(2 * np.pi)),
            0.5 / m.sigma_m**2,
            self.table,
            1.0 / self.table_step,
            out_s,
            out_b,
            flags,
        )
        return out_s, out_b

    def eval_live(
        self,
        poses,
        parent,
        live_off,
        live_idx,
        pts,
        d_xy,
        e,
        tight: bool,
        lo=None,
        hi=None,
        par_terms=None,
        par_bound=None,
        thresh=-np.inf,
    ):
        """Cells ``poses`` (radians) with largest offsets ``e`` (4,) to their faces, each
        evaluated on the live points of ``parent`` (CSR ``live_off``/``live_idx``).

        Returns (bound, quick score lower bound, child live CSR offsets, child live points).
        ``tight`` enables the per-axis bound for displacements up to ``box_max_m``, over the
        asymmetric offset box ``[lo, hi]`` (4,: dx, dy, dz m, dh rad about each pose, within
        ``+-e``) when given (:func:`_eval_live_box`; then also ``par_terms``/``par_bound``/
        ``thresh``, the parent terms and early stop there, and a sixth result, the child live
        points' terms)."""
        if tight and lo is not None:
            return self._eval_live_box(
                poses,
                parent,
                live_off,
                live_idx,
                pts,
                d_xy,
                e,
                lo,
                hi,
                par_terms,
                par_bound,
                thresh,
            )
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
            np.ascontiguousarray(poses, dtype=np.float64),
            parent.astype(np.int64),
            live_off,
            live_idx,
            len(pts),
            pts,
            d_xy,
            t_ext,
            sin_h,
            self.box_max_m if tight else -1.0,
            np.ascontiguousarray(e[:3], dtype=np.float64),
            *self._geo(),
            self.ub,
            self.cap,
            self.c_origin,
            self.c_s,
            self.c_shape,
            self.lb,
            self.bb_lo,
            self.bb_hi,
            m.ln_k1,
            self.table,
            self.table,
            1.0 / self.table_step,
            out_b,
            out_s,
            out_off,
            out_cnt,
            out_live,
        )
        return out_b, out_s, out_off, out_cnt, out_live

    def _eval_live_box(
        self,
        poses,
        parent,
        live_off,
        live_idx,
        pts,
        d_xy,
        e,
        lo,
        hi,
        par_terms=None,
        par_bound=None,
        thresh=-np.inf,
    ):
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
            np.ascontiguousarray(poses, dtype=np.float64),
            parent.astype(np.int64),
            live_off,
            live_idx,
            len(pts),
            pts,
            d_xy,
            t_ext,
            chord,
            self.box_max_m,
            lo,
            hi,
            s_lo,
            s_hi,
            eps_fac,
            par_terms,
            np.asarray(par_bound, dtype=np.float64),
            float(thresh),
            *self._geo(),
            self.ub,
            self.cap,
            self.c_origin,
            self.c_s,
            self.c_shape,
            self.lb,
            self.bb_lo,
            self.bb_hi,
            m.ln_k1,
            self.table,
            self.table,
            1.0 / self.table_step,
            out_b,
            out_s,
            out_off,
            out_cnt,
            out_live,
            out_t,
        )
        return out_b, out_s, out_off, out_cnt, out_live, out_t

    def exact_live(self, poses, live_off, live_idx, pts) -> np.ndarray:
        """Exact scores of cells at ``poses`` from their own live lists."""
        if len(live_off) != len(poses) + 1:
            raise ValueError(f"exact_live: {len(poses)} cells but {len(live_off) - 1} live lists")
        m = self.model
        out = np.empty(len(poses))
        _exact_live(
            np.ascontiguousarray(poses, dtype=np.float64),
            live_off,
            live_idx,
            len(pts),
            pts,
            *self._geo(),
            self.cap,
            m.k1,
            m.ln_k1,
            m.k2 / (m.sigma_m * np.sqrt(2 * np.pi)),
            0.5 / m.sigma_m**2,
            out,
        )
        return out


def compact_live(keep: np.ndarray, off: np.ndarray, cnt: np.ndarray, live: np.ndarray):
    """Live CSR of the kept cells (``keep`` bool)."""
    return _compact(np.ascontiguousarray(keep, dtype=np.bool_), off, cnt, live)
