"""Guards for registrations in structured sites (Th. 5.4.1, 7.2-7.3, 11; spec 7.3, 8.6, 11).

The thesis's indoor failures (spec 7.3) are alignments that the score prefers but that the data
do not determine:

* **pair 87**: only parallel wall lines were common; the left wall was matched to the right one,
  and the result slid along the corridor to the edge of the box (the y of both of its results
  lie 4.8-5.0 m from their a priori centres, i.e. on the +-5 m box edge);
* **pair 43** with a prior 3 m off: the box reached the next pillar of a row 7 m apart and the
  shifted pillar pairing won (a 7 m shift); pair 76: "theoretically unreliable along the
  corridor axis".

Three checks (beyond the thesis, which named "a heuristic against matching opposite walls" and
"restricting the search" as future work), all parameters (inferred):

* :func:`constraint_support`: the matched feature points at the chosen pose must constrain every
  horizontal direction. A point matched on a feature with direction ``u`` constrains the
  directions perpendicular to ``u`` only (a wall line none along itself, a vertical pillar all
  horizontal ones); the weakest eigenvalue of ``sum (I - u u^T)`` restricted to xy, times the
  sampling step, is the *support* in metres of matched feature. Parallel lines alone give ~0.
* :func:`rival_alignment`: the best alignment farther than ``exclusion_m`` from the chosen one
  (grid search over the box at the chosen z and heading, refined by short ICP, exact score);
  ``rival_ratio`` = its matched points / the chosen one's. Periodic pillars (43) and sliding
  along a corridor give ratios near 1. (The branch and bound prunes every alignment scoring
  below the best, so its secondary hypotheses only survive near-exact ties.)
* :func:`search_box` / :func:`register_in_box`: a per-pair search box whose axes may be turned
  (``along_deg``) so that it is narrow across a corridor (the thesis's suggested +-0.5 m) and
  long along it; the search runs in the reference frame turned by ``along_deg`` and the result
  is turned back.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from forestmap_assets.core.geometry import transform_points, wrap_deg
from forestmap_assets.core.registration.score import ScoreModel

SEARCH_KEYS = ("xy_m", "x_m", "y_m", "z_m", "heading_deg", "along_deg", "along_m", "across_m")
CHECK_COLUMNS = ["support_m", "weak_direction_deg", "rival_ratio", "rival_separation_m",
                 "rival_dx", "rival_dy"]


# ---- degeneracy of the matched features --------------------------------------------------------
def feature_directions(submap: pd.DataFrame) -> np.ndarray:
    """Unit direction (n, 3) of the feature each sub-map point was sampled from: the principal
    direction of that feature's points (``feature``, ``feature_id`` groups; spec 6.2). Points of
    a one-point feature get the vertical."""
    return _feature_geometry(submap, 0.05)[0]


def _feature_geometry(submap: pd.DataFrame, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Per sub-map point: its feature's unit direction (:func:`feature_directions`) and the
    feature length each point stands for (sampled extent / (points - 1); ``spacing_m`` for a
    one-point feature), so that support is in metres of feature whatever the sampling density
    (``build_submap(cylinder_weight=...)``)."""
    pts = submap[["x", "y", "z"]].to_numpy(float)
    out = np.tile([0.0, 0.0, 1.0], (len(submap), 1))
    metres = np.full(len(submap), float(spacing_m))
    if not len(submap):
        return out, metres
    key = pd.factorize(pd.MultiIndex.from_arrays(
        [submap["feature"].astype(str), submap["feature_id"].astype(np.int64)]))[0]
    order = np.argsort(key, kind="stable")
    k = key[order]
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    ends = np.r_[starts[1:], len(k)]
    first = pts[order[starts]]
    last = pts[order[ends - 1]]
    d = last - first  # features are sampled in order from p0 to p1 (core/submaps.py)
    n = np.linalg.norm(d, axis=1)
    u = np.where(n[:, None] > 1e-9, d / np.maximum(n, 1e-12)[:, None], [0.0, 0.0, 1.0])
    out[order] = np.repeat(u, ends - starts, axis=0)
    count = ends - starts
    per = np.where(count > 1, n / np.maximum(count - 1, 1), spacing_m)
    metres[order] = np.repeat(per, count)
    return out, metres


def constraint_support(scan_submap: pd.DataFrame, ref_submap: pd.DataFrame, pose,
                       *, match_m: float = 0.1, spacing_m: float = 0.05) -> dict:
    """How well the features matched at ``pose`` (scan in the reference frame) fix the
    horizontal translation: ``support_m`` (weakest direction, metres of matched feature),
    ``strong_m``, ``weak_direction_deg`` (reference frame) and ``matched`` (points within
    ``match_m``; inferred ~3 sigma). Each matched point counts the length of scan feature it
    was sampled for (``spacing_m`` only for one-point features)."""
    out = {"support_m": 0.0, "strong_m": 0.0, "weak_direction_deg": np.nan, "matched": 0}
    if not len(scan_submap) or not len(ref_submap):
        return out
    q = transform_points(scan_submap[["x", "y", "z"]].to_numpy(float), pose)
    d, j = cKDTree(ref_submap[["x", "y", "z"]].to_numpy(float)).query(
        q, distance_upper_bound=match_m)
    m = np.isfinite(d)
    if not m.any():
        return out
    metres = _feature_geometry(scan_submap, spacing_m)[1]
    u = feature_directions(ref_submap)[j[m]]
    wt = metres[m]  # metres of the scan's feature each matched point stands for
    info = np.eye(2) * wt.sum() - np.einsum("n,ni,nj->ij", wt, u[:, :2], u[:, :2])
    w, v = np.linalg.eigh(info)
    out.update(support_m=float(w[0]), strong_m=float(w[1]),
               weak_direction_deg=float(np.degrees(np.arctan2(v[1, 0], v[0, 0]))),
               matched=int(m.sum()))
    return out


# ---- rival alignments --------------------------------------------------------------------------
def _scores(tree: cKDTree, pts: np.ndarray, poses: np.ndarray, model: ScoreModel,
            chunk: int = 2_000_000) -> np.ndarray:
    """Exact log-likelihoods (spec 6.3) of ``poses`` (k, 4; heading deg)."""
    out = np.empty(len(poses))
    per = max(1, chunk // max(len(pts), 1))
    for a in range(0, len(poses), per):
        p = poses[a:a + per]
        h = np.radians(p[:, 3])
        c, s = np.cos(h), np.sin(h)
        q = np.empty((len(p), len(pts), 3))
        q[..., 0] = c[:, None] * pts[:, 0] - s[:, None] * pts[:, 1] + p[:, 0, None]
        q[..., 1] = s[:, None] * pts[:, 0] + c[:, None] * pts[:, 1] + p[:, 1, None]
        q[..., 2] = pts[:, 2] + p[:, 2, None]
        dist = tree.query(q.reshape(-1, 3), distance_upper_bound=model.cap_m)[0]
        out[a:a + per] = model.log_p(dist.reshape(len(p), -1)).sum(axis=1)
    return out


def matched_from_score(score, n_points: int, model: ScoreModel):
    """Matched-point equivalent of a score: (s - n ln k1) / (ln p0 - ln k1)."""
    return (np.asarray(score, float) - model.floor(n_points)) / (model.ln_p0 - model.ln_k1)


def _in_box(poses: np.ndarray, centre, half_widths, box_heading_deg: float) -> np.ndarray:
    """Which poses (k, 4; heading deg) lie in the box ``centre +- half_widths`` (axes turned by
    ``box_heading_deg``)."""
    c, s = np.cos(np.radians(box_heading_deg)), np.sin(np.radians(box_heading_deg))
    dx, dy = poses[:, 0] - centre[0], poses[:, 1] - centre[1]
    u, v = c * dx + s * dy, -s * dx + c * dy
    tol = 1e-9
    ok = (np.abs(u) <= half_widths[0] + tol) & (np.abs(v) <= half_widths[1] + tol)
    ok &= np.abs(poses[:, 2] - centre[2]) <= half_widths[2] + tol
    ok &= np.abs(wrap_deg(poses[:, 3] - centre[3])) <= min(half_widths[3], 180.0) + tol
    return ok


def rival_alignment(
    scan_submap: pd.DataFrame,
    ref_submap: pd.DataFrame,
    pose,
    centre,
    half_widths,
    params,
    *,
    exclusion_m: float = 1.0,
    min_support_m: float = 1.0,
    grid_m: float | None = None,
    top_k: int = 12,
    box_heading_deg: float = 0.0,
    match_m: float = 0.1,
    spacing_m: float = 0.05,
) -> dict:
    """The best *credible* alignment of the box farther than ``exclusion_m`` (xy) from ``pose``.

    Exact scores on an xy grid (``grid_m``, default the larger half-width / 40, at least 0.1 m)
    at the chosen z and heading; the ``top_k`` local maxima are refined by 4-DoF ICP
    (:func:`~.first_hypotheses.refine_local`), kept inside the box and re-scored. A rival is
    credible when its own matched features fix the pose (:func:`constraint_support` >=
    ``min_support_m``): an alignment that slides along a corridor on wall lines alone is not an
    alternative to one anchored by pillars, a pillar row shifted by one period is. Returns
    ``rival_ratio`` (credible rival's matched points / the chosen pose's; 0 when none; inferred
    ambiguity measure), its ``rival_dx, rival_dy, rival_separation_m`` and ``support_m``, and
    ``any_rival_ratio`` (best rival, credible or not).
    """
    from forestmap_assets.core.registration.first_hypotheses import refine_local

    model = ScoreModel.from_params(params)
    pts = scan_submap[["x", "y", "z"]].to_numpy(float).reshape(-1, 3)
    ref = ref_submap[["x", "y", "z"]].to_numpy(float).reshape(-1, 3)
    out = {"rival_ratio": 0.0, "rival_separation_m": np.nan, "rival_dx": np.nan,
           "rival_dy": np.nan, "rival_support_m": np.nan, "any_rival_ratio": 0.0,
           "best_matched": 0.0}
    if not len(pts) or not len(ref):
        return out
    tree = cKDTree(ref)
    pose = np.asarray(pose, float)
    centre = np.asarray(centre, float)
    best = _scores(tree, pts, pose[None], model)[0]
    hx, hy = float(half_widths[0]), float(half_widths[1])
    step = grid_m or max(0.1, max(hx, hy) / 40.0)
    uu, vv = np.meshgrid(np.arange(-hx, hx + 1e-9, step), np.arange(-hy, hy + 1e-9, step),
                         indexing="ij")
    c, s = np.cos(np.radians(box_heading_deg)), np.sin(np.radians(box_heading_deg))
    gx = centre[0] + c * uu - s * vv
    gy = centre[1] + s * uu + c * vv
    far = np.hypot(gx - pose[0], gy - pose[1]) > exclusion_m
    if not far.any():
        return out
    cand = np.column_stack([gx[far], gy[far], np.full(far.sum(), pose[2]),
                            np.full(far.sum(), pose[3])])
    grid = np.full(uu.shape, -np.inf)
    grid[far] = _scores(tree, pts, cand, model)
    from scipy.ndimage import maximum_filter

    peaks = (grid == maximum_filter(grid, size=3, mode="nearest")) & far
    idx = np.flatnonzero(peaks.ravel())
    idx = idx[np.argsort(-grid.ravel()[idx])][:top_k]
    starts = np.column_stack([gx.ravel()[idx], gy.ravel()[idx], np.full(idx.size, pose[2]),
                              np.full(idx.size, pose[3])])
    refined = []
    for p0 in starts:
        p = refine_local(pts, tree, np.r_[p0[:3], np.radians(p0[3])], radius_m=2 * step)
        p = np.r_[p[:3], np.degrees(p[3])]
        inside = _in_box(p[None], centre, half_widths, box_heading_deg)[0]
        if not inside or np.hypot(p[0] - pose[0], p[1] - pose[1]) <= exclusion_m:
            p = p0  # ICP left the box or walked back into the chosen alignment
        refined.append(p)
    allp = np.vstack([starts, np.array(refined)])
    rs = _scores(tree, pts, allp, model)
    n = len(pts)
    bm = float(matched_from_score(best, n, model))
    ratio = matched_from_score(rs, n, model) / bm if bm > 0 else np.zeros(len(rs))
    out.update(best_matched=bm, any_rival_ratio=float(ratio.max()))
    for k in np.argsort(-rs):
        sup = constraint_support(scan_submap, ref_submap, allp[k], match_m=match_m,
                                 spacing_m=spacing_m)["support_m"]
        if sup >= min_support_m:
            out.update(rival_ratio=float(ratio[k]), rival_dx=float(allp[k, 0]),
                       rival_dy=float(allp[k, 1]), rival_support_m=float(sup),
                       rival_separation_m=float(np.hypot(allp[k, 0] - pose[0],
                                                         allp[k, 1] - pose[1])))
            break
    return out


def assess_pair(scan_submap: pd.DataFrame, ref_submap: pd.DataFrame, pose, centre,
                half_widths, params, *, box_heading_deg: float = 0.0,
                min_support_m: float = 1.0, max_rival_ratio: float = 0.8,
                exclusion_m: float = 1.0, match_m: float = 0.1,
                spacing_m: float = 0.05) -> tuple[str, dict]:
    """Reason to reject a registration at ``pose`` ('' if none) and the figures of
    :func:`constraint_support` and :func:`rival_alignment` (``CHECK_COLUMNS``).

    ``degenerate``: the weakest horizontal direction has less than ``min_support_m`` of matched
    feature (e.g. only parallel wall lines match, pair 87); ``ambiguous``: a credible alignment
    more than ``exclusion_m`` away matches at least ``max_rival_ratio`` as many points (a
    pillar row shifted by its period, pair 43). Thresholds (inferred) are in
    benchmarks/results.md, "Structured sites".
    """
    sup = constraint_support(scan_submap, ref_submap, pose, match_m=match_m, spacing_m=spacing_m)
    figures = {"support_m": sup["support_m"], "weak_direction_deg": sup["weak_direction_deg"],
               "rival_ratio": 0.0, "rival_separation_m": np.nan, "rival_dx": np.nan,
               "rival_dy": np.nan}
    if sup["support_m"] < min_support_m:
        return (f"degenerate: the matched features fix the pose only weakly along "
                f"{sup['weak_direction_deg']:.0f} deg ({sup['support_m']:.2f} m of support < "
                f"{min_support_m:g} m; e.g. only parallel wall lines match)"), figures
    if not np.isfinite(max_rival_ratio):  # rival test off (forest preset): not searched
        figures["rival_ratio"] = np.nan
        return "", figures
    riv = rival_alignment(scan_submap, ref_submap, pose, centre, half_widths, params,
                          exclusion_m=exclusion_m, min_support_m=min_support_m,
                          box_heading_deg=box_heading_deg, match_m=match_m, spacing_m=spacing_m)
    figures.update({k: riv[k] for k in ("rival_ratio", "rival_separation_m", "rival_dx",
                                        "rival_dy")})
    if riv["rival_ratio"] >= max_rival_ratio:
        return (f"ambiguous: an alignment {riv['rival_separation_m']:.2f} m away, also fixed by "
                f"its features, matches {100 * riv['rival_ratio']:.0f}% as many points (>= "
                f"{100 * max_rival_ratio:.0f}%)"), figures
    return "", figures


# ---- per-pair search boxes ---------------------------------------------------------------------
def search_box(default: tuple[float, float, float], override: Mapping[str, float] | None = None
               ) -> tuple[float, float, float, float, float]:
    """Half-widths ``(hx, hy, hz, hheading)`` and box axis heading of one pair.

    ``default`` = the campaign's (xy_m, z_m, heading_deg). ``override`` (a pair's ``search`` in
    campaign.yaml, keys ``SEARCH_KEYS``): ``xy_m`` both horizontal half-widths, ``x_m``/``y_m``
    one each (reference frame axes), ``z_m``, ``heading_deg``; ``along_deg`` turns the box's
    first axis to that heading in the reference's levelled frame, with ``along_m`` and
    ``across_m`` the half-widths along and across (e.g. a corridor along -90 deg:
    ``{along_deg: -90, across_m: 0.5}``, the thesis's suggestion for pair 87, spec 7.3).
    """
    xy, z, h = (float(v) for v in default)
    o = dict(override or {})
    bad = sorted(set(o) - set(SEARCH_KEYS))
    if bad:
        raise ValueError(f"search: unknown key {bad[0]!r} (allowed: {', '.join(SEARCH_KEYS)})")
    for k, v in o.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise ValueError(f"search.{k}: expected a number, got {v!r}")
        if k != "along_deg" and not v > 0:
            raise ValueError(f"search.{k}: expected a positive number, got {v!r}")
    if ("along_m" in o or "across_m" in o) and "along_deg" not in o:
        raise ValueError("search: along_m / across_m need along_deg (the corridor's heading)")
    if "along_deg" in o and ("x_m" in o or "y_m" in o):
        raise ValueError("search: use along_m / across_m with along_deg, not x_m / y_m")
    hx = hy = float(o.get("xy_m", xy))
    hx, hy = float(o.get("x_m", hx)), float(o.get("y_m", hy))
    hx, hy = float(o.get("along_m", hx)), float(o.get("across_m", hy))
    return (hx, hy, float(o.get("z_m", z)), float(o.get("heading_deg", h)),
            float(wrap_deg(o.get("along_deg", 0.0))))


def register_in_box(scan_points, ref_points, centre, half_widths, params, *,
                    box_heading_deg: float = 0.0, **kwargs):
    """:func:`~.register.register_pair` in a box whose x axis points along
    ``box_heading_deg`` (reference frame): the reference points are turned by
    ``-box_heading_deg``, the box centre likewise, the search runs axis-aligned there, and the
    result (peak, centre, hypotheses) is turned back; sigmas become the diagonal of the turned
    covariance ``R diag(sd^2) R^T``. ``box_heading_deg = 0`` is a plain ``register_pair``."""
    from forestmap_assets.core.registration.register import register_pair

    a = float(box_heading_deg)
    if a == 0.0:
        return register_pair(scan_points, ref_points, centre, half_widths, params, **kwargs)
    ref = transform_points(np.asarray(ref_points, float).reshape(-1, 3), (0, 0, 0, -a))
    c = np.asarray(centre, float)
    cr = transform_points(c[None, :3], (0, 0, 0, -a))[0]
    res = register_pair(scan_points, ref, (*cr, c[3] - a), half_widths, params, **kwargs)
    if not res.ok:
        return res
    ca, sa = np.cos(np.radians(a)), np.sin(np.radians(a))

    def back(p):
        p = np.asarray(p, float)
        return (float(ca * p[0] - sa * p[1]), float(sa * p[0] + ca * p[1]), float(p[2]),
                float(wrap_deg(p[3] + a)))

    res.box_frame = {"peak": res.peak, "centre": (*cr, c[3] - a), "final_step": res.final_step,
                     "box_heading_deg": a}  # for judge_in_box
    res.peak = back(res.peak)
    res.centre = back(res.centre)
    sd = np.asarray(res.sigma, float)
    res.sigma = (float(np.sqrt(ca**2 * sd[0] ** 2 + sa**2 * sd[1] ** 2)),
                 float(np.sqrt(sa**2 * sd[0] ** 2 + ca**2 * sd[1] ** 2)), float(sd[2]),
                 float(sd[3]))
    step = np.asarray(res.final_step, float)
    res.final_step = (float(np.hypot(ca * step[0], sa * step[1])),
                      float(np.hypot(sa * step[0], ca * step[1])), float(step[2]), float(step[3]))
    hyp = res.hypotheses
    if len(hyp):
        hyp = hyp.copy()
        for pre in ("peak_", ""):
            x, y = hyp[f"{pre}dx"].to_numpy(float), hyp[f"{pre}dy"].to_numpy(float)
            hyp[f"{pre}dx"], hyp[f"{pre}dy"] = ca * x - sa * y, sa * x + ca * y
            hyp[f"{pre}dh_deg"] = wrap_deg(hyp[f"{pre}dh_deg"].to_numpy(float) + a)
        res.hypotheses = hyp
    lv = res.levels
    if len(lv):
        lv = lv.copy()
        x, y = lv["dx"].to_numpy(float), lv["dy"].to_numpy(float)
        lv["dx"], lv["dy"] = ca * x - sa * y, sa * x + ca * y
        lv["dh_deg"] = wrap_deg(lv["dh_deg"].to_numpy(float) + a)
        res.levels = lv
    return res


# ---- secondary hypotheses in the coarse-to-fine history (spec 6.5, Th. Figs 5.8-5.9) -----------
HISTORY_COLUMNS = ["level", "cell_m", "dx", "dy", "dz", "dh_deg", "score", "peak_score_at_level",
                   "separation_m", "level_mass_share"]


def history_hypotheses(levels: pd.DataFrame, peak, *, separation_m: float = 1.0,
                       max_cell_m: float = 0.3) -> pd.DataFrame:
    """Levels of the branch and bound at which an alignment far from the final peak held the
    best score (spec 6.5; Th. Figs 5.8-5.9: for pair 43 "the maximum-score location jumps
    between hypotheses at coarse levels, and only one cloud survives below about 0.08 m").

    ``levels``: every level's surviving cells (``register_pair(...).levels``: ``level, cell_m,
    dx, dy, dz, dh_deg, score``). A level counts when its cells are at most ``max_cell_m`` and
    its best-scoring cell lies more than ``separation_m`` (xy) from the final ``peak``; the row
    gives that cell, the best score of the cells near the peak (``peak_score_at_level``), and
    the leader's share of the two masses ``exp(s)`` at that level (>= 0.5: at that resolution
    the search preferred the other alignment). Inferred thresholds: a wrong result's competitor
    stays in the lead to finer cells than a correct result's (benchmarks/results.md,
    "Structured sites"). Empty when no level qualifies."""
    rows = []
    if len(levels) == 0 or "score" not in levels:
        return pd.DataFrame(columns=HISTORY_COLUMNS)
    p = np.asarray(peak, dtype=float)
    lv = levels[np.isfinite(levels["score"].to_numpy(float))]
    lv = lv[lv["cell_m"].to_numpy(float) <= max_cell_m]
    for level, g in lv.groupby("level", sort=True):
        sep = np.hypot(g["dx"].to_numpy(float) - p[0], g["dy"].to_numpy(float) - p[1])
        s = g["score"].to_numpy(float)
        k = int(np.argmax(s))
        if sep[k] <= separation_m:
            continue
        near = s[sep <= separation_m]
        s_near = float(near.max()) if near.size else -np.inf
        share = 1.0 / (1.0 + np.exp(min(s_near - s[k], 700.0)))
        c = g.iloc[k]
        rows.append({"level": int(level), "cell_m": float(c["cell_m"]), "dx": float(c["dx"]),
                     "dy": float(c["dy"]), "dz": float(c["dz"]), "dh_deg": float(c["dh_deg"]),
                     "score": float(s[k]), "peak_score_at_level": s_near,
                     "separation_m": float(sep[k]), "level_mass_share": float(share)})
    return pd.DataFrame(rows, columns=HISTORY_COLUMNS)


def assess_history(levels: pd.DataFrame, peak, d_bar_m: float, *, separation_m: float = 1.0,
                   max_cell_m: float | None = 0.3) -> tuple[str, dict | None]:
    """Reason to reject a registration whose coarse-to-fine history was contested ('' if none;
    ``max_cell_m`` None: not checked) and the finest late leader of :func:`history_hypotheses`
    as a secondary-hypothesis row (None if none): ``registration.HYPOTHESIS_COLUMNS`` plus
    ``source``, ``level``, ``cell_m``; its cell at that level (no cloud, so no sigmas), its
    share of that level's two masses as ``mass_share``, and its separation from ``peak`` (xyz,
    heading as arc at ``d_bar_m``)."""
    if max_cell_m is None:
        return "", None
    hist = history_hypotheses(levels, peak, separation_m=separation_m, max_cell_m=max_cell_m)
    if hist.empty:
        return "", None
    h = hist.iloc[int(np.argmin(hist["cell_m"].to_numpy(float)))]
    pose = h[["dx", "dy", "dz", "dh_deg"]].to_numpy(float)
    sep = pose - np.asarray(peak, dtype=float)
    sep[3] = np.radians(wrap_deg(sep[3])) * d_bar_m
    row = dict(zip(("peak_dx", "peak_dy", "peak_dz", "peak_dh_deg"), pose, strict=True))
    row.update(dict(zip(("dx", "dy", "dz", "dh_deg"), pose, strict=True)))
    row.update(peak_score=float(h["score"]), sd_x=np.nan, sd_y=np.nan, sd_z=np.nan,
               sd_heading_deg=np.nan, n_cells=1, mass_share=float(h["level_mass_share"]),
               separation_m=float(np.linalg.norm(sep)), source="coarse-to-fine history",
               level=int(h["level"]), cell_m=float(h["cell_m"]))
    return (f"ambiguous: with {row['cell_m']:.2f} m cells the search preferred an alignment "
            f"{float(h['separation_m']):.2f} m away (a secondary hypothesis of the coarse-to-fine "
            f"history, Th. Fig. 5.8)"), row
