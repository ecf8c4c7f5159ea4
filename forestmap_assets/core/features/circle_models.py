"""Circle models of scan-line segments (spec 3; Th. 4.6.2-4.6.4, Table 4.2; JP II-A eqs (1)-(4)):
points of each
segment and its chain neighbours (spec 3.2) projected on the plane perpendicular to the axis (spec
3.1), fitted,
validated (spec 3.5), back-projected (spec 3.6); initial vertical-axis phase, then iterations until
stable (spec 3.8)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from forestmap_assets.core.features._circle_kernels import FIT_CODES, _nb_phase, resolve_engine
from forestmap_assets.core.features.circle_axes import estimate_axes
from forestmap_assets.core.features.circle_fit import _reduce, fit_groups_numpy
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.core.features.segment_neighbours import neighbour_pairs, segment_layout
from forestmap_assets.core.features.segments import pixel_xyz, segment_pixels
from forestmap_assets.params import CircleParams, SegmentationParams

CIRCLE_COLUMNS: dict[str, str] = {
    "iteration": "int64",
    "segment_id": "int64",
    "row": "int64",
    "chain_id": "int64",
    "cx": "float64",
    "cy": "float64",
    "cz": "float64",
    "radius_m": "float64",
    "nx": "float64",
    "ny": "float64",
    "nz": "float64",
    "n_points": "int64",
    "n_inliers": "int64",
    "mean_residual_m": "float64",
    "rms_residual_m": "float64",
    "valid": "bool",
    "reject_reason": "str",
}


REJECT_REASONS = ("", "fit", "too_few_points", "size", "convexity", "symmetry", "no_axis")


def empty_circles() -> pd.DataFrame:
    """A well-formed circle-model table with no rows."""
    return pd.DataFrame({k: pd.Series([], dtype=v) for k, v in CIRCLE_COLUMNS.items()})


def plane_frames(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane orthonormal axes (e1, e2) for unit normals ``n`` (k, 3) (spec 3.1).

    e1 is the x axis made orthogonal to n, e2 = n x e1; for n = (0, 0, 1) this is (x, y).
    """
    ex = np.array([1.0, 0.0, 0.0])
    ey = np.array([0.0, 1.0, 0.0])
    ref = np.where(np.abs(n[:, :1]) < 0.9, ex, ey)
    e1 = ref - np.sum(ref * n, 1, keepdims=True) * n
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(n, e1)
    return e1, e2


@dataclass
class _SegData:
    row: np.ndarray
    chain: np.ndarray
    col0: np.ndarray
    col1: np.ndarray
    r_mid: np.ndarray
    width: np.ndarray
    pptr: np.ndarray  # CSR offsets into pts
    pts: np.ndarray  # (P, 3) levelled inlier points grouped by segment
    el_step: float

    def __post_init__(self) -> None:
        # computed once for every phase: the coordinates as contiguous columns (the kernel's
        # input), each segment's centroid, whose dot with an axis is the mean height of the
        # segment's points along it (5 phases of per-point heights: 0.15 s a scan of 0.7 M
        # points), and the segments' neighbour layout (only the rows within reach change)
        self.columns = tuple(np.ascontiguousarray(self.pts[:, i]) for i in range(3))
        own = np.diff(self.pptr)
        self.centroid = _reduce(self.pts, self.pptr) / np.maximum(own, 1)[:, None]
        self.layout = segment_layout(self) if self.row.size else None


def _circle_phase(
    sd: _SegData,
    normals: np.ndarray,
    todo: np.ndarray,
    k_max: int,
    collect_height_m: float,
    fit: str,
    robust_sigmas: float,
    max_rounds: int,
    min_points: int,
    max_batch_points: int,
    engine: str,
    max_fit_points: int = 0,
) -> dict[str, np.ndarray]:
    """Fit the circles of segments ``todo`` with axes ``normals``; per-segment result arrays.
    ``max_fit_points`` > 0: a segment whose neighbours hold more points takes every
    ``ceil(points / max_fit_points)``-th point of each neighbour segment, one point later on
    each next neighbour, before the height filter (both engines): the whole arc stays sampled
    (the same columns of every scan line would shorten it and bias the linear fit)."""
    n_seg = sd.row.size
    res = {k: np.full(n_seg, np.nan) for k in ("cx", "cy", "cz", "r", "me", "rms", "md", "dc")}
    res["n_points"] = np.zeros(n_seg, np.int64)
    res["n_inliers"] = np.zeros(n_seg, np.int64)
    res["ok"] = np.zeros(n_seg, bool)
    if not todo.any():
        return res
    e1, e2 = plane_frames(normals)
    hbar = np.einsum("ij,ij->i", sd.centroid, normals)  # mean height of a segment's points
    # rows needed to cover +-collect_height along n (pruning only; the exact test is per point)
    tilt = np.arccos(np.clip(normals[:, 2], -1, 1))
    pitch_v = sd.r_mid * sd.el_step
    need = (collect_height_m + sd.width * np.sin(tilt)) / (pitch_v * np.cos(tilt))
    k_rows = np.minimum(k_max, np.ceil(need) + 1).astype(np.int64)
    k_rows = np.where(todo, k_rows, -1)
    ps, pt = neighbour_pairs(sd, k_rows, layout=sd.layout)
    keep = todo[ps]
    ps, pt = ps[keep], pt[keep]
    segs = np.flatnonzero(todo)
    if engine == "numba":
        pair_ptr = np.searchsorted(ps, np.concatenate([segs, [n_seg]]))
        out, ok, npts = _nb_phase(
            *sd.columns,
            sd.pptr,
            segs,
            pair_ptr,
            pt,
            np.ascontiguousarray(normals),
            e1,
            e2,
            hbar,
            collect_height_m,
            FIT_CODES[fit],
            float(robust_sigmas),
            int(max_rounds),
            int(min_points),
            6,
            int(max_fit_points),
        )
        _store(
            res,
            segs,
            out[:, 0],
            out[:, 1],
            out[:, 2],
            ok,
            np.nan_to_num(out[:, 7]).astype(np.int64),
            out[:, 3],
            out[:, 4],
            out[:, 5],
            out[:, 6],
            npts,
            e1,
            e2,
            normals,
        )
        return res
    # numpy engine: batches of circles bounded in gathered points (memory), in segment order
    pair_n = np.diff(sd.pptr)[pt]
    per_seg = np.bincount(ps, weights=pair_n, minlength=n_seg).astype(np.int64)
    csum = np.cumsum(per_seg[segs])
    cuts = np.searchsorted(
        csum, np.arange(max_batch_points, csum[-1] + max_batch_points, max_batch_points), "right"
    )
    bounds = np.unique(np.concatenate([[0], cuts, [segs.size]]))
    pair_start = np.searchsorted(ps, segs)
    pair_end = np.searchsorted(ps, segs, "right")
    for b0, b1 in zip(bounds[:-1], bounds[1:], strict=True):
        bseg = segs[b0:b1]
        if bseg.size == 0:
            continue
        pa, pb = pair_start[b0], pair_end[b1 - 1]
        s, t, cnt = ps[pa:pb], pt[pa:pb], pair_n[pa:pb]
        g = np.repeat(s, cnt)
        first = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        within = np.arange(g.size) - np.repeat(first, cnt)  # position in its neighbour segment
        pidx = np.repeat(sd.pptr[t], cnt) + within
        if max_fit_points > 0:  # every stride-th point of each neighbour, staggered (as the kernel)
            stride = np.maximum(1, -(-per_seg // max_fit_points))[g]
            nth = np.repeat(np.arange(s.size) - np.searchsorted(s, s), cnt)  # neighbour's rank
            keep = (within + nth) % stride == 0
            g, pidx = g[keep], pidx[keep]
        p = sd.pts[pidx]
        nn = normals[g]
        h = np.einsum("ij,ij->i", p, nn)
        inside = np.abs(h - hbar[g]) <= collect_height_m
        g, p, h = g[inside], p[inside], h[inside]
        x = np.einsum("ij,ij->i", p, e1[g])
        z = np.einsum("ij,ij->i", p, e2[g])
        gcount = np.bincount(g, minlength=n_seg)[bseg]
        ptr = np.concatenate([[0], np.cumsum(gcount)])
        fr = fit_groups_numpy(
            x,
            z,
            ptr,
            h=h,
            fit=fit,
            robust_sigmas=robust_sigmas,
            max_rounds=max_rounds,
            min_points=min_points,
        )
        _store(
            res,
            bseg,
            fr.x0,
            fr.z0,
            fr.r,
            fr.ok,
            fr.n_inliers,
            fr.mean_residual,
            fr.rms_residual,
            fr.mean_h,
            fr.mean_dist,
            gcount,
            e1,
            e2,
            normals,
        )
    return res


def _store(
    res, idx, x0, z0, r, ok, n_inl, me, rms, mean_h, mean_dist, n_points, e1, e2, normals
) -> None:
    """Back-project circle centres to 3-D (spec 3.6) and store per-segment results."""
    c3 = x0[:, None] * e1[idx] + z0[:, None] * e2[idx] + mean_h[:, None] * normals[idx]
    res["cx"][idx], res["cy"][idx], res["cz"][idx] = c3[:, 0], c3[:, 1], c3[:, 2]
    res["r"][idx] = r
    res["me"][idx], res["rms"][idx] = me, rms
    res["md"][idx] = mean_dist
    res["dc"][idx] = np.hypot(x0, z0)
    res["n_points"][idx] = n_points
    res["n_inliers"][idx] = n_inl
    res["ok"][idx] = ok


def _validate(
    res: dict[str, np.ndarray],
    todo: np.ndarray,
    sym_limit: float,
    seg_params: SegmentationParams,
    min_points: int,
    statistic: str,
    range_sigma_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Validity checks of spec 3.5; returns (valid, reject_reason) per segment."""
    n = todo.size
    reason = np.full(n, "", dtype=object)
    r = res["r"]
    with np.errstate(invalid="ignore"):
        stat = res["me"].copy()
        if statistic == "noise_corrected":
            # (inferred) remove the shift -sigma^2/(2r) that pure range noise gives the mean
            # signed residual of an algebraic circle fit, and test only a larger negative mean.
            stat = np.minimum(stat + range_sigma_m**2 / (2 * r), 0.0)
        elif statistic != "mean":
            raise ValueError(f"symmetry statistic: unknown {statistic!r}")
        checks = [
            ("fit", ~res["ok"] | ~np.isfinite(r)),
            ("too_few_points", res["n_inliers"] < min_points),
            ("size", (2 * r < seg_params.min_width_m) | (2 * r > seg_params.max_width_m)),
            ("convexity", ~(res["dc"] > res["md"])),
            ("symmetry", ~(np.abs(stat) <= sym_limit)),
        ]
    for name, fail in checks:
        reason[(reason == "") & fail & todo] = name
    reason[~todo] = "no_axis"
    return reason == "", reason


def fit_circle_models(
    image: RangeImage,
    segments: pd.DataFrame,
    params: CircleParams | None = None,
    seg_params: SegmentationParams | None = None,
    *,
    fit: str | None = None,
    symmetry_statistic: str | None = None,
    stable_centre_m: float = 0.001,
    stable_radius_m: float = 0.001,
    stable_normal_deg: float = 0.5,
    stable_share: float = 0.8,
    stable_gain: float = 0.15,
    max_batch_points: int = 2_000_000,
    engine: str = "auto",
) -> pd.DataFrame:
    """Circle models of every segment, every iteration (spec 3.1-3.8).

    Iteration 0 (initial phase): vertical axis, +-``initial_neighbour_segments`` neighbours,
    symmetry threshold relaxed by ``initial_symmetry_factor`` (inferred x2). Iterations >= 1:
    axis from the previous iteration's valid circles (concatenation method, ``axis_span_m``),
    up to ``max_neighbour_segments`` neighbours within +-``collect_height_m`` along the axis.
    At least ``iterations`` iterations run; more follow, up to ``max_iterations``, until the
    circles are stable: a share ``stable_share`` of the circles valid in both iterations moved
    by less than ``stable_centre_m`` / ``stable_radius_m`` / ``stable_normal_deg`` and at most
    ``1 - stable_share`` of them changed validity (inferred; 0.8 gives the thesis' "usually two
    iterations" on clean and cluttered synthetic forests, where a few clutter circles never
    settle), or when that share rose by less than ``stable_gain`` in the last iteration (inferred:
    on rough, splatted stems half the normals wobble by more than 0.5 deg for ever; a scan
    rendered in a registered cloud went on to the cap of 5 with 54 % settled, for the same
    poses as after 2).
    In iterations >= 1 a segment is refitted when it was valid or received an axis estimate
    from valid neighbours; others keep their previous state with reason ``no_axis``.

    ``symmetry_statistic`` overrides ``params.symmetry_statistic``: ``"mean"`` (spec 3.5:
    |mean signed residual| <= T_sym) or ``"noise_corrected"`` (inferred alternative, see
    :func:`_validate`; with 2.5 cm range noise the linear fit's mean signed residual is biased
    by about -sigma^2/(2r), -4.2 mm on a 7.5 cm stem, so the "mean" test rejects thin trunks
    beyond ~10 m: the thesis' "a strict threshold misses distant trunks", spec 11).
    ``fit`` overrides ``params.fit``: ``"linear"`` (Eq. 4.10, default), ``"geometric"`` or
    ``"ray"`` (refinements, see :func:`fit_circles_2d`). The iterations always use the linear
    fit of the thesis; a refinement is applied to the final iteration's circles only (same
    points, same axes), so the axis estimation and the stopping rule do not depend on it.
    ``engine``:
    ``"numpy"`` (batched arrays), ``"numba"`` (compiled per-circle loop, same maths) or
    ``"auto"`` (numba when installed).

    Returns one row per segment and iteration with columns :data:`CIRCLE_COLUMNS`; ``cx, cy,
    cz`` is the back-projected 3-D centre (levelled frame), ``n*`` the projection normal,
    ``n_points`` the collected points and ``n_inliers`` the robust inliers.
    """
    cp = params or CircleParams()
    sp = seg_params or SegmentationParams()
    fit = fit or cp.fit
    symmetry_statistic = symmetry_statistic or cp.symmetry_statistic
    if len(segments) == 0:
        return empty_circles()
    seg_idx, pr, pc, _ = segment_pixels(image, segments)
    pts = pixel_xyz(image, pr, pc)
    n_seg = len(segments)
    pptr = np.concatenate([[0], np.cumsum(np.bincount(seg_idx, minlength=n_seg))])
    el_step = np.radians(image.elevation_step_deg or image.azimuth_step_deg or 0.108)
    sd = _SegData(
        segments["row"].to_numpy(np.int64),
        segments["chain_id"].to_numpy(np.int64),
        segments["col0"].to_numpy(np.int64),
        segments["col1"].to_numpy(np.int64),
        segments["r_mid"].to_numpy(np.float64),
        segments["width_m"].to_numpy(np.float64),
        pptr,
        pts,
        el_step,
    )
    min_points = sp.min_points
    common = dict(
        collect_height_m=cp.collect_height_m,
        robust_sigmas=cp.robust_sigmas,
        max_rounds=cp.robust_max_rounds,
        min_points=min_points,
        max_batch_points=max_batch_points,
        engine=resolve_engine(engine),
        max_fit_points=cp.max_fit_points,
    )
    normals = np.tile([0.0, 0.0, 1.0], (n_seg, 1))
    todo = np.ones(n_seg, bool)
    tables = []
    prev: dict[str, np.ndarray] | None = None
    prev_valid = np.zeros(n_seg, bool)
    prev_reason = np.full(n_seg, "", dtype=object)
    prev_normals = normals.copy()
    prev_share = None
    for it in range(cp.max_iterations + 1):
        if prev is not None:
            centres = np.stack([prev["cx"], prev["cy"], prev["cz"]], 1)
            new_n, has = estimate_axes(
                centres,
                prev_valid,
                normals,
                prev["r"],
                sd.chain,
                cp.axis_span_m,
                cp.max_axis_tilt_deg,
                engine,
            )
            todo = (has | prev_valid) & np.all(np.isfinite(centres), axis=1)
            normals = np.where(todo[:, None], new_n, normals)
        k_max = cp.initial_neighbour_segments if it == 0 else cp.max_neighbour_segments
        sym = cp.symmetry_threshold_m * (cp.initial_symmetry_factor if it == 0 else 1.0)

        def phase(
            fit_kind,
            prev=prev,
            prev_reason=prev_reason,
            todo=todo,
            normals=normals,
            k_max=k_max,
            sym=sym,
        ):
            res = _circle_phase(sd, normals, todo, k_max, fit=fit_kind, **common)
            valid, reason = _validate(
                res, todo, sym, sp, min_points, symmetry_statistic, sp.range_sigma_m
            )
            if prev is not None:  # carry the previous state of segments not refitted
                for k in res:
                    res[k] = np.where(todo, res[k], prev[k])
                reason = np.where(todo, reason, np.where(prev_reason == "", "no_axis", prev_reason))
                valid = todo & valid
            return res, valid, reason

        res, valid, reason = phase("linear")
        share = None
        if prev is not None:
            share, flips = _settled(
                prev, res, prev_valid, valid, prev_normals, normals,
                stable_centre_m, stable_radius_m, stable_normal_deg,
            )
        last = it == cp.max_iterations or (
            share is not None
            and it >= cp.iterations
            and (
                (share >= stable_share and flips <= 1 - stable_share)
                or (prev_share is not None and share - prev_share < stable_gain)
            )
        )
        prev_share = share
        if last and fit != "linear":  # refine the final circles (same points and axes)
            res, valid, reason = phase(fit)
        tables.append(_phase_table(it, segments, res, normals, valid, reason))
        if last:
            break
        prev, prev_valid, prev_reason, prev_normals = res, valid, reason, normals.copy()
    out = pd.concat(tables, ignore_index=True)
    return out.astype(CIRCLE_COLUMNS)


def _settled(a, b, va, vb, na, nb, dc, dr, dn_deg) -> tuple[float, float]:
    """Share of the circles valid in both iterations that moved less than the stop rule's
    limits, and the share of circles whose validity changed."""
    both = va & vb
    if not both.any():
        return 1.0, 0.0
    ca = np.stack([a["cx"], a["cy"], a["cz"]], 1)[both]
    cb = np.stack([b["cx"], b["cy"], b["cz"]], 1)[both]
    ang = np.degrees(np.arccos(np.clip(np.sum(na[both] * nb[both], 1), -1, 1)))
    small = (np.linalg.norm(ca - cb, axis=1) < dc) & (np.abs(a["r"][both] - b["r"][both]) < dr)
    small &= ang < dn_deg
    flips = np.count_nonzero(va != vb) / max(np.count_nonzero(va | vb), 1)
    return float(small.mean()), float(flips)


def _phase_table(it, segments, res, normals, valid, reason) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "iteration": np.full(len(segments), it, np.int64),
            "segment_id": segments["segment_id"].to_numpy(np.int64),
            "row": segments["row"].to_numpy(np.int64),
            "chain_id": segments["chain_id"].to_numpy(np.int64),
            "cx": res["cx"],
            "cy": res["cy"],
            "cz": res["cz"],
            "radius_m": res["r"],
            "nx": normals[:, 0],
            "ny": normals[:, 1],
            "nz": normals[:, 2],
            "n_points": res["n_points"],
            "n_inliers": res["n_inliers"],
            "mean_residual_m": res["me"],
            "rms_residual_m": res["rms"],
            "valid": valid,
            "reject_reason": reason.astype(object),
        }
    )


def final_circles(circles: pd.DataFrame) -> pd.DataFrame:
    """Rows of the last iteration of a circle-model table."""
    if len(circles) == 0:
        return circles
    return circles[circles["iteration"] == circles["iteration"].max()].reset_index(drop=True)
