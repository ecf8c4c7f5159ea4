"""Cylinder (truncated-cone) segments from circle models (spec 4; Th. 4.6.3, Fig. 4.16; JP II-A).

Valid circles of the final iteration are walked bottom-up along their vertical chains
(spec 4, step 1, inferred order). A cylinder segment grows while

* the next circle's normal deviates from the normal of the cylinder's **first** circle by at
  most ``curvature_deg`` (step 2a; the circle breaking the test starts the next cylinder, so a
  curved trunk becomes a sequence of cylinders),
* the next circle overlaps the previous one (its centre lies within the mean of the two radii
  across the axis, inferred reading of "overlapping circle models", step 2b), and
* the empty gap to it, measured along the axis, is at most ``max_gap_m`` (step 2c).

A chain ends where a scan line holds no segment overlapping it (a thin stem seen from 15-25 m
with two or three returns a line, some lines without enough), yet the walk's 0.24 m gap test
(step 2c) spans such missing lines. So chains are first linked end to end (inferred,
:func:`chain_stacks`): a chain whose lowest valid circle continues another chain's highest one
(above it by at most ``max_gap_m`` along that circle's normal, overlapping it across, of a like
radius) is walked as that chain's continuation when neither has another candidate. Sylva's survey 23:
5 of 45 stems (10-14 cm, seen from 14-25 m) had 5-40 valid circles each in 4-11 chains of
0.1-0.4 m, so no cylinder and no tree.

A cylinder is kept when it holds at least ``min_circles`` circles and is at least
``min_length_m`` long (step 6), and (inferred consistency check, ``axis_normal_deg``) when the
line through its circle centres deviates from the mean normal of its circles by at most the
curvature threshold: every circle was fitted in a plane perpendicular to its normal, so the
centres of a real cylinder lie along that normal. Branches crossing the scan lines obliquely and
foliage give chains of circles whose normals (clamped to ``max_axis_tilt_deg`` of vertical) and
centre line disagree by 20-45 deg; stems by 1-3 deg (95th percentile 3 deg on simulated forests,
see ``benchmarks/results.md``). Its axis is the principal direction (largest variance) of the
member centres, its end points the projections of the extreme centres on that line (step 5),
its radius the mean circle radius (step 4); truncated-cone end radii come from a linear fit of
radius against position along the axis.

The walk is vectorised: each pass cuts, in every chain at once, the current cylinder at its
first violating circle, so the number of passes is the largest number of cylinders in a chain.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.features.circle_models import final_circles, fit_circle_models
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.core.features.segments import feature_scan_lines, segment_scan_lines
from forestmap_assets.params import CylinderParams, Params

CYLINDER_COLUMNS: dict[str, str] = {
    "cylinder_id": "int64",
    "x0": "float64",
    "y0": "float64",
    "z0": "float64",
    "x1": "float64",
    "y1": "float64",
    "z1": "float64",
    "radius_m": "float64",
    "r0_m": "float64",
    "r1_m": "float64",
    "n_circles": "int64",
    "length_m": "float64",
    "chain_id": "int64",
    "tilt_deg": "float64",
}


def empty_cylinders() -> pd.DataFrame:
    """A well-formed cylinder-segment table with no rows."""
    return pd.DataFrame({k: pd.Series([], dtype=v) for k, v in CYLINDER_COLUMNS.items()})


def _group_starts(keys: np.ndarray) -> np.ndarray:
    """Indices where a new value starts in a sorted key array."""
    return np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))


def chain_stacks(c: np.ndarray, nrm: np.ndarray, rad: np.ndarray, chain: np.ndarray,
                 max_gap_m: float, radius_share: float = 0.3) -> np.ndarray:
    """The stack of each valid circle: its chain, or the lowest chain of the chains linked end
    to end (module docstring). Chain B continues chain A when B's lowest circle lies above A's
    highest by at most ``max_gap_m`` along that circle's normal, within the mean of their radii
    across it, with radii within ``radius_share`` of the larger, and when neither chain has
    another such partner. ``c`` (n, 3) centres, ``nrm`` normals, ``rad`` radii and ``chain`` ids
    of the valid circles; returns (n,) stack ids (chain ids)."""
    from scipy.spatial import cKDTree

    ids, inv = np.unique(chain, return_inverse=True)
    inv = inv.ravel()
    if ids.size < 2:
        return chain
    order = np.lexsort((c[:, 2], inv))
    first = np.searchsorted(inv[order], np.arange(ids.size))
    last = np.concatenate([first[1:], [order.size]]) - 1
    bot, top = order[first], order[last]  # each chain's lowest and highest circle
    reach = 0.5 * (rad[top] + rad.max())
    pairs = cKDTree(c[bot, :2]).query_ball_point(c[top, :2], reach + 1e-9)
    a = np.repeat(np.arange(ids.size), [len(q) for q in pairs])
    b = np.fromiter((j for q in pairs for j in q), np.int64, a.size)
    d = c[bot[b]] - c[top[a]]
    along = np.einsum("ij,ij->i", d, nrm[top[a]])
    across = np.linalg.norm(d - along[:, None] * nrm[top[a]], axis=1)
    ok = (a != b) & (along > 0) & (along <= max_gap_m) & (across <= 0.5 * (rad[top[a]] + rad[bot[b]]))
    ok &= c[bot[b], 2] > c[top[a], 2]  # B starts above A's end: no interleaving
    ok &= np.abs(rad[bot[b]] - rad[top[a]]) <= radius_share * np.maximum(rad[bot[b]], rad[top[a]])
    a, b = a[ok], b[ok]
    # only unambiguous links: near a scanner a stem breaks into many short chains side by side
    # (partial arcs of every size), and walking them end to end would join pieces of them
    sole = (np.bincount(a, minlength=ids.size)[a] == 1) & (np.bincount(b, minlength=ids.size)[b] == 1)
    a, b = a[sole], b[sole]
    pred = np.full(ids.size, -1, np.int64)
    pred[b] = a
    root = np.arange(ids.size)
    for _ in range(ids.size):  # follow the predecessors to each path's first chain
        up = pred[root] >= 0
        if not up.any():
            break
        root = np.where(up, pred[root], root)
    return ids[root][inv]


def cylinder_membership(circles: pd.DataFrame, params: CylinderParams | None = None, *,
                        reference: str = "first") -> np.ndarray:
    """Cylinder id per row of ``circles`` (a final-iteration circle table), -1 if none.

    ``reference``: the normal the curvature test compares with, ``"first"`` (the cylinder's
    first circle, Th. 4.6.3) or ``"running"`` (the mean normal of the circles so far, inferred
    alternative).
    """
    p = params or CylinderParams()
    n = len(circles)
    member = np.full(n, -1, np.int64)
    if n == 0:
        return member
    valid = circles["valid"].to_numpy(bool)
    c = circles[["cx", "cy", "cz"]].to_numpy(np.float64)
    nrm = circles[["nx", "ny", "nz"]].to_numpy(np.float64)
    rad = circles["radius_m"].to_numpy(np.float64)
    chain = circles["chain_id"].to_numpy(np.int64)
    idx = np.flatnonzero(valid & np.all(np.isfinite(c), 1) & np.isfinite(rad))
    if idx.size == 0:
        return member
    if p.link_chains:
        chain = chain.copy()
        chain[idx] = chain_stacks(c[idx], nrm[idx], rad[idx], chain[idx], p.max_gap_m)
    order = idx[np.lexsort((c[idx, 2], chain[idx]))]  # bottom-up within each chain
    c, nrm, rad, chain = c[order], nrm[order], rad[order], chain[order]
    m = order.size
    # --- breaks between consecutive circles: new chain, gap along the axis, no overlap -------
    d = np.diff(c, axis=0)
    along = np.abs(np.einsum("ij,ij->i", d, nrm[:-1]))
    across = np.linalg.norm(d - along[:, None] * nrm[:-1] * np.sign(
        np.einsum("ij,ij->i", d, nrm[:-1]))[:, None], axis=1)
    brk = np.ones(m, bool)
    brk[1:] = (chain[1:] != chain[:-1]) | (along > p.max_gap_m)
    brk[1:] |= across > 0.5 * (rad[1:] + rad[:-1])
    run = np.cumsum(brk) - 1
    run_start = np.flatnonzero(brk)
    run_end = np.concatenate([run_start[1:], [m]])  # exclusive
    # --- curvature splitting, one pass per cylinder of the longest run ----------------------
    cos_thr = np.cos(np.radians(p.curvature_deg))
    cyl_of = np.full(m, -1, np.int64)
    start = run_start.copy()
    active = np.ones(run_start.size, bool)
    pos = np.arange(m)
    next_id = 0
    csum = np.concatenate([np.zeros((1, 3)), np.cumsum(nrm, axis=0)])
    while active.any():
        st = start[run]  # current start of each circle's run
        live = active[run] & (pos >= st)
        st = np.minimum(st, m - 1)  # finished runs (start == end) are not live
        if reference == "running":
            ref = csum[pos] - csum[st]  # sum of normals from the start up to the previous
            ref = np.where((pos > st)[:, None], ref, nrm[st])
            ref /= np.linalg.norm(ref, axis=1, keepdims=True)
        elif reference == "first":
            ref = nrm[st]
        else:
            raise ValueError(f"reference: unknown {reference!r} (expected 'first' or 'running')")
        viol = live & (np.einsum("ij,ij->i", nrm, ref) < cos_thr)
        cand = np.where(viol, pos, m)
        first_viol = np.minimum.reduceat(cand, run_start)
        stop = np.minimum(first_viol, run_end)  # exclusive end of each run's current cylinder
        seg_len = np.where(active, stop - start, 0)
        ids = np.full(run_start.size, -1, np.int64)
        ids[active] = next_id + np.arange(np.count_nonzero(active))
        next_id += np.count_nonzero(active)
        take = live & (pos < stop[run])
        cyl_of[take] = ids[run[take]]
        start = np.where(active, np.maximum(stop, start + (seg_len == 0)), start)
        active &= start < run_end
    member[order] = cyl_of
    return member


def assemble_cylinders(circles_final: pd.DataFrame, params: CylinderParams | None = None, *,
                       reference: str = "first", axis_normal_deg: float | None = None,
                       return_membership: bool = False):
    """Cylinder segments from the final circle models (spec 4, Th. 4.6.3).

    ``circles_final``: circle-model rows of one iteration (e.g. :func:`final_circles`); only
    ``valid`` rows are used. Returns a table with :data:`CYLINDER_COLUMNS` in the levelled scan
    frame: ``x0, y0, z0`` the lower and ``x1, y1, z1`` the upper axis end point, ``radius_m``
    the mean circle radius, ``r0_m, r1_m`` the truncated-cone end radii (linear fit of radius
    against axial position), ``n_circles``, ``length_m``, ``chain_id`` and ``tilt_deg`` (axis
    angle from vertical). ``axis_normal_deg``: see :func:`_axis_normal_limit` (inferred
    centre-line / normal consistency check). With ``return_membership`` also returns a table
    ``segment_id, cylinder_id`` of the member circles.
    """
    p = params or CylinderParams()
    circles_final = circles_final.reset_index(drop=True)
    member = cylinder_membership(circles_final, p, reference=reference)
    table = _cylinder_table(circles_final, member, p, axis_normal_deg)
    keep_ids = table.attrs.pop("kept_ids")
    if not return_membership:
        return table
    remap = np.full(max(int(member.max(initial=-1)), 0) + 1, -1, np.int64)
    remap[keep_ids] = np.arange(keep_ids.size)
    mem = np.where(member >= 0, remap[np.maximum(member, 0)], -1)
    sel = mem >= 0
    segment_id = circles_final["segment_id"].to_numpy(np.int64) if len(circles_final) else \
        np.zeros(0, np.int64)
    mapping = pd.DataFrame({"segment_id": segment_id[sel], "cylinder_id": mem[sel]})
    return table, mapping


def _axis_normal_limit(p: CylinderParams, axis_normal_deg: float | None) -> float:
    """Largest allowed angle (deg) between a cylinder's centre line and its circles' mean normal
    (inferred): ``axis_normal_deg`` argument, else ``p.axis_normal_deg`` when the parameter model
    has it, else the curvature threshold ``p.curvature_deg`` (the thesis' bound on how far
    normals within one cylinder may turn). ``inf`` disables the check."""
    if axis_normal_deg is None:
        axis_normal_deg = getattr(p, "axis_normal_deg", None)
    return float(p.curvature_deg if axis_normal_deg is None else axis_normal_deg)


def _cylinder_table(circles: pd.DataFrame, member: np.ndarray, p: CylinderParams,
                    axis_normal_deg: float | None = None) -> pd.DataFrame:
    sel = np.flatnonzero(member >= 0)
    if sel.size == 0:
        out = empty_cylinders()
        out.attrs["kept_ids"] = np.zeros(0, np.int64)
        return out
    cid = member[sel]
    order = np.argsort(cid, kind="stable")
    sel, cid = sel[order], cid[order]
    starts = _group_starts(cid)
    counts = np.diff(np.concatenate([starts, [cid.size]]))
    ids = cid[starts]
    c = circles[["cx", "cy", "cz"]].to_numpy(np.float64)[sel]
    rad = circles["radius_m"].to_numpy(np.float64)[sel]
    chain = circles["chain_id"].to_numpy(np.int64)[sel]
    # principal axis (largest variance) of the member centres
    mean = np.add.reduceat(c, starts, axis=0) / counts[:, None]
    dev = c - np.repeat(mean, counts, axis=0)
    cov = np.add.reduceat(dev[:, :, None] * dev[:, None, :], starts, axis=0)
    _, vec = np.linalg.eigh(cov)
    axis = vec[:, :, 2]
    axis = np.where(axis[:, 2:3] < 0, -axis, axis)
    t = np.einsum("ij,ij->i", dev, np.repeat(axis, counts, axis=0))
    tmin = np.minimum.reduceat(t, starts)
    tmax = np.maximum.reduceat(t, starts)
    p0 = mean + tmin[:, None] * axis
    p1 = mean + tmax[:, None] * axis
    length = tmax - tmin
    # radius: mean; truncated cone: least-squares line r(t) = alpha + beta t
    rmean = np.add.reduceat(rad, starts) / counts
    tm = np.add.reduceat(t, starts) / counts
    tt = t - np.repeat(tm, counts)
    stt = np.add.reduceat(tt * tt, starts)
    str_ = np.add.reduceat(tt * (rad - np.repeat(rmean, counts)), starts)
    with np.errstate(invalid="ignore", divide="ignore"):
        beta = np.where(stt > 0, str_ / stt, 0.0)
    r0 = rmean + beta * (tmin - tm)
    r1 = rmean + beta * (tmax - tm)
    keep = (counts >= p.min_circles) & (length >= p.min_length_m)
    # consistency of the centre line with the circles' projection normals (inferred)
    nrm = circles[["nx", "ny", "nz"]].to_numpy(np.float64)[sel]
    nmean = np.add.reduceat(nrm, starts, axis=0)
    nmean /= np.maximum(np.linalg.norm(nmean, axis=1, keepdims=True), 1e-12)
    deviation = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", nmean, axis)), 0, 1)))
    keep &= ~(deviation > _axis_normal_limit(p, axis_normal_deg))
    tilt = np.degrees(np.arccos(np.clip(axis[:, 2], -1, 1)))
    out = pd.DataFrame({
        "cylinder_id": np.arange(int(keep.sum()), dtype=np.int64),
        "x0": p0[keep, 0], "y0": p0[keep, 1], "z0": p0[keep, 2],
        "x1": p1[keep, 0], "y1": p1[keep, 1], "z1": p1[keep, 2],
        "radius_m": rmean[keep], "r0_m": r0[keep], "r1_m": r1[keep],
        "n_circles": counts[keep].astype(np.int64), "length_m": length[keep],
        "chain_id": chain[starts][keep], "tilt_deg": tilt[keep],
    }).astype(CYLINDER_COLUMNS)
    out.attrs["kept_ids"] = ids[keep]
    return out


def extract_features(image: RangeImage, params: Params | None = None,
                     **circle_options) -> dict[str, pd.DataFrame]:
    """Segments -> circle models -> cylinder segments of one range image (spec 2-4), on its
    scan lines thinned to ``segmentation.min_line_step_deg`` (:func:`feature_scan_lines`).

    Returns ``{"segments", "circle_models", "cylinder_segments"}``; ``circle_models`` holds every
    iteration (column ``iteration``), cylinders use the final one. ``circle_options`` are passed
    to :func:`fit_circle_models` (e.g. ``fit``, ``engine``, ``symmetry_statistic``).
    """
    p = params or Params()
    image = feature_scan_lines(image, p.segmentation.min_line_step_deg)
    segments = segment_scan_lines(image, p.segmentation)
    circles = fit_circle_models(image, segments, p.circles, p.segmentation, **circle_options)
    cylinders = assemble_cylinders(final_circles(circles), p.cylinders)
    return {"segments": segments, "circle_models": circles, "cylinder_segments": cylinders}
