"""From cylinder segments in the global frame to one row per physical tree (spec 9, 10.6).

The thesis stops at the integrated map of cylinders; merging them into trees with a diameter at
breast height is forestmap's step (inferred, parameters below):

1. cylinders of all scans are grouped into stems: two cylinders belong to the same stem when
   their axes, evaluated at a common height, are closer than ``merge_factor`` x the smaller
   radius + ``merge_tolerance_m`` (different stems cannot be closer than the sum of radii),
   and no link joins two stems seen side by side near their bases (:mod:`.stem_groups`);
2. the ground under a stem is the median of the lowest-hit elevation cells in an annulus
   around it, keeping only cells near the annulus' lowest surface (crown hits in cells the
   ground was not seen in are ignored, :func:`ground_under`), falling back to the lowest
   cylinder end, which also bounds it from above (the ground cannot lie above a seen stem);
3. breast height is ``breast_height_m`` (1.3 m) above that ground; the stem position is the
   n_circles-weighted mean of the cylinder axes evaluated there, and DBH is twice the
   weighted mean truncated-cone radius at that height (slope limited to a plausible stem
   taper) over cylinders reaching within ``dbh_reach_m`` of it, preferring cylinders seen from
   within ``dbh_max_range_m`` and weighting by the beam footprint at the observation range
   (:func:`merge_trees`);
4. a stem with no cylinder within ``dbh_reach_m`` of breast height gets a DBH extrapolated down
   (or up) its cylinders' taper when one ends within ``dbh_extrapolate_m``, else none; the
   column ``dbh_note`` says how such a DBH was obtained or why there is none (empty for a DBH
   from a cylinder spanning breast height above a seen ground).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from forestmap_assets.core.mapping.cylinder_radii import (
    dbh_note_for,
    radius_at,
    scan_median,
    weighted_stat,
)
from forestmap_assets.core.mapping.stem_groups import axis_xy, ends, group_stems

TREE_COLUMNS = ["tree_id", "x", "y", "z", "dbh_m", "n_scans", "n_cylinders", "visible_length_m",
                "dbh_note"]


def cylinders_to_global(per_scan: dict[str, pd.DataFrame], poses: dict[str, tuple]) -> pd.DataFrame:
    """Every cylinder of the registered scans in the global frame, with its ``scan`` and
    ``range_m``, the horizontal distance from that scan's sensor to the middle of the cylinder
    axis (the observation range, used to weight radii in :func:`merge_trees`)."""
    from forestmap_assets.core.geometry import transform_points

    frames = []
    for scan, cyl in per_scan.items():
        if scan not in poses or cyl is None or cyl.empty:
            continue
        g = cyl.copy()
        p0 = transform_points(cyl[["x0", "y0", "z0"]].to_numpy(float), poses[scan])
        p1 = transform_points(cyl[["x1", "y1", "z1"]].to_numpy(float), poses[scan])
        g[["x0", "y0", "z0"]] = p0
        g[["x1", "y1", "z1"]] = p1
        mid = 0.5 * (cyl[["x0", "y0"]].to_numpy(float) + cyl[["x1", "y1"]].to_numpy(float))
        g["range_m"] = np.hypot(mid[:, 0], mid[:, 1])
        g.insert(0, "scan", scan)
        frames.append(g)
    cols = ["scan", "cylinder_id", "x0", "y0", "z0", "x1", "y1", "z1", "radius_m", "r0_m", "r1_m", "n_circles", "range_m"]
    if not frames:
        return pd.DataFrame({c: pd.Series(dtype="int64" if c in ("cylinder_id", "n_circles") else "float64") for c in cols}).astype({"scan": "object"})
    out = pd.concat(frames, ignore_index=True)
    return out


def ground_under(xy: np.ndarray, radius: np.ndarray, grid_z: np.ndarray, x0: float, y0: float,
                 cell_m: float, ring_m: tuple[float, float] = (0.15, 1.0),
                 low_quantile: float = 0.1, band_m: float = 0.5) -> np.ndarray:
    """Ground elevation under each stem from the lowest-hit grid; NaN where no cell has data.

    The median of the lowest-hit cells in an annulus around the stem that lie within ``band_m``
    above the annulus' ``low_quantile`` quantile (inferred): far from the scanners the ground
    next to a stem is hit only sparsely, and cells without a ground hit hold their lowest
    *crown* hit, metres up, which moved a plain median by 4-7 m on about one stem in seven
    (simulated 40 m plots, half resolution). ``low_quantile=0, band_m=inf`` gives the plain
    median of every cell.
    """
    out = np.full(len(xy), np.nan)
    if grid_z is None or grid_z.size == 0:
        return out
    ny, nx = grid_z.shape
    reach = int(np.ceil((ring_m[1] + radius.max(initial=0.0)) / cell_m)) + 1
    offs = np.arange(-reach, reach + 1)
    dx, dy = np.meshgrid(offs, offs)
    for k, ((x, y), r) in enumerate(zip(xy, radius, strict=True)):
        ix = int(np.floor((x - x0) / cell_m)) + dx
        iy = int(np.floor((y - y0) / cell_m)) + dy
        cx = x0 + (ix + 0.5) * cell_m
        cy = y0 + (iy + 0.5) * cell_m
        d = np.hypot(cx - x, cy - y)
        ok = (d >= r + ring_m[0]) & (d <= r + ring_m[1]) & (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        if ok.any():
            vals = grid_z[iy[ok], ix[ok]]
            vals = vals[np.isfinite(vals)]
            if vals.size:
                low = np.quantile(vals, low_quantile)
                out[k] = float(np.median(vals[vals <= low + band_m]))
    return out


# the footprint (m) at which merge_trees' near rule stops by default: the own simulator's beam
# (42 mm + 3 mrad, spec 1.1) at dbh_max_range_m = 20 m
NEAR_FOOTPRINT_M = 0.042 + 0.003 * 20.0


def beam_options(beam_exit_m: float, beam_divergence_rad: float) -> dict:
    """:func:`merge_trees` keywords for a campaign's beam: its footprint weights the cylinders,
    and the near rule's range is where that footprint reaches ``NEAR_FOOTPRINT_M`` (20 m for
    the own simulator's beam; a survey-grade beam, 5 mm + 0.3 mrad, never reaches it, so far
    cylinders, which its narrow footprint does not widen, take part). Stored surveys, DBH RMSE
    with the own beam's options / the campaign's: Sylva 1, 2, 29-43 (17 surveys, 753 trees)
    0.567 / 0.520 cm (Sylva 41: a 48.6 cm stem read 41.4 from the one cylinder within 20 m,
    where four from 19-30 m read 46-50), rendered 1, 2, 14-17 1.803 / 1.715; own surveys,
    which name the own beam, unchanged."""
    return {"beam_exit_m": beam_exit_m, "beam_divergence_rad": beam_divergence_rad,
            "dbh_max_range_m": max(NEAR_FOOTPRINT_M - beam_exit_m, 0.0) / max(beam_divergence_rad, 1e-9)}


def merge_trees(
    cyl: pd.DataFrame,
    grid=None,
    *,
    breast_height_m: float = 1.3,
    dbh_reach_m: float = 1.0,
    merge_factor: float = 0.75,
    merge_tolerance_m: float = 0.06,
    range_weighting: bool = True,
    beam_exit_m: float = 0.042,
    beam_divergence_rad: float = 0.003,
    dbh_max_range_m: float | None = 20.0,
    dbh_statistic: str = "mean",
    ground_low_quantile: float = 0.1,
    ground_band_m: float = 0.5,
    max_taper_m_per_m: float | None = 0.01,
    dbh_extrapolate_m: float = 2.0,
    lone_ratio: float | None = 1.4,
    lone_agree: float = 0.3,
    lone_one_scan_ratio: float | None = 1.6,
    lone_one_scan_reach_m: float = 2.5,
    dbh_close_reach_m: float | None = 1.5,
    small_share: float | None = 0.7,
    min_top_m: float | None = None,
    understorey_keep: tuple[int, float] = (3, 0.10),
) -> tuple[pd.DataFrame, np.ndarray]:
    """Trees (``TREE_COLUMNS``) from global cylinders; also each cylinder's tree id.

    ``grid`` is an object with ``z`` (2-D, [iy, ix]), ``x0``, ``y0``, ``cell_m`` (the merged
    lowest-hit elevation map) or None; ``ground_low_quantile`` and ``ground_band_m`` go to
    :func:`ground_under`.

    DBH weighting (inferred; needs the ``range_m`` column of :func:`cylinders_to_global`, else
    plain ``n_circles`` weights): a first-return beam widens a stem by mixed pixels at its
    silhouette by up to the footprint radius, and the footprint grows with range (spec 1.1:
    ``beam_exit_m + beam_divergence_rad * r``, 0.042 m + 3 mrad). Radii seen from far away are
    therefore both noisier and biased high (simulated 40 m plots, cylinder radius error against
    range: -0.2 cm below 10 m, +0.4 cm at 10-15 m, +0.9 cm at 15-20 m, +2.3 cm at 20-25 m,
    +4.2 cm at 25-30 m). So (1) when cylinders near breast height were observed from within
    ``dbh_max_range_m`` (20 m: about the farthest distance of the thesis' pillar study, 18.4 m,
    and the simulator's visibility range; 15 m, also tried, did worse on the same six simulated
    campaigns because a single near cylinder of partial arcs then decides), only those give
    the DBH; (2) with ``range_weighting`` each
    cylinder weighs ``n_circles / footprint(range_m)^2`` (inverse variance with the footprint
    as the error scale); (3) ``dbh_statistic="median"`` takes the weighted median of the
    cylinders' radii at breast height rather than their weighted mean (``"mean"``): a stem
    partly hidden behind a nearer one gives a cylinder of partial arcs whose radius is far too
    small (see ``benchmarks/results.md``, features, "Known limitation"), and with one such
    cylinder among five or six good ones the median ignores it where the mean moves by
    centimetres. ``dbh_max_range_m=None, range_weighting=False, dbh_statistic="mean"`` gives
    the plain ``n_circles``-weighted mean.

    Taper limit and reach (inferred): a cylinder's end radii come from a straight-line fit of
    its circle radii against height, whose slope is noisy (one cylinder of a 22 cm stem seen
    from 18 m fitted a taper of 1.4 cm per metre, three times the stem's), and its radius at
    breast height, near one end, inherits that slope error. ``max_taper_m_per_m`` (0.01 m of
    radius per metre, i.e. 2 cm of diameter per metre: an upper bound of stem taper above the
    butt, a forestry rule of thumb, not fitted to the simulator's stems) limits the slope about
    the cylinder's mid height; ``None`` keeps the fitted cone. With the slope so bounded, a
    cylinder ending within ``dbh_reach_m`` = 1.0 m of breast height (0.6 m before) is off by
    at most 1 cm of radius from taper, less than the 1-4 cm errors of radii seen from beyond
    15 m, so a nearer scan's cylinder just above or below breast height now takes part.
    Simulated 40 m plots, half resolution, seeds 100-102: DBH RMSE 1.20 / 1.82 / 1.25 cm ->
    1.03 / 1.48 / 1.13 cm (``benchmarks/results.md``, mapping section, with further seeds).

    Stems not seen near breast height (inferred, issue 18): when no cylinder ends within
    ``dbh_reach_m`` of breast height but one ends within ``dbh_extrapolate_m`` (2.0 m), the DBH
    is the same weighted statistic of the cylinders' cones continued to breast height, each
    with its own fitted slope limited to 0 .. ``max_taper_m_per_m`` of radius per metre (the
    stem thickening downwards); beyond that there is no DBH. Such stems are mostly a stem seen
    only above the understorey or behind a nearer stem, or a crown part (a branch, a leaning
    top) 5-20 m up that no stem below was merged with: in five simulated 40 m plots (45 trees,
    half resolution, seeds 1, 2, 3, 101, 102) 25 of the 26 trees without a DBH were such crown
    parts, matching no true stem, and one a stem seen only from 4 m up, from 23 m away. Stems
    of the same plots with their cylinders cut off below 1.1 / 1.5 m above breast height
    (about 220 matched stems each): extrapolated DBH RMSE 1.5 / 1.5 cm, bias +0.2 cm (1.6 cm,
    bias +0.1 cm, for the same stems uncut; the clamped end radius of the near rule instead,
    cut at 1.5 m: 2.0 cm, bias -1.4 cm).

    Cylinders that read small (inferred, issue 19): of three or more cylinders giving the DBH,
    those whose radius at breast height is below ``small_share`` (0.7) of the median over their
    scans (each scan's weighted mean, :func:`.cylinder_radii.scan_median`) are left out while
    two or more remain. A circle through a short arc of a half-hidden stem fits far too small, and a near
    scan's weight (its small footprint) let one such cylinder pull the mean: own realistic
    survey 7, a 37 cm stem read 29 cm, its 8.6 cm-radius cylinder from 3.5 m outweighing six
    that read 17-18 cm. Stored surveys, DBH RMSE pooled over own, Sylva and rendered (27
    surveys, silhouette widths where the beam is named): 1.66 -> 1.60 cm (own realistic 7 2.29
    -> 1.92; rendered 2 1.71 -> 1.76 and 3 1.81 -> 1.74; Sylva unchanged). A symmetric trim
    (0.75-1.5 times the median) was tried before the widths and gained 0.02 cm. The median was
    the cylinders' weighted one, which a near scan's two cylinders set alone on own realistic
    seed 22: a 20.2 cm stem read 11.1 cm (now 20.6) from a thin object on its side, r 4 cm,
    7 m away; bench_dbh 17-22 1.40 -> 1.27 cm, no other set moved by more than 0.01 (own
    realistic 1-3, 7-13, 4-6, 14-16, own circular, Sylva, rendered). Where two cylinders of two
    scans give the DBH, the median is over the scans of every cylinder within
    ``dbh_extrapolate_m`` (three or more scans; cones continued) and the one below
    ``small_share`` of it is left out (:func:`_drop_small_of_two`): own realistic seed 132, a
    35.4 cm stem read 17.7 cm, now 36.2; twelve full-resolution own realistic surveys 1.24 ->
    0.93 cm.

    A lone near cylinder too small (inferred, issue 19): when one cylinder, or the cylinders of
    one scan, alone give the DBH and two or more others within ``dbh_extrapolate_m`` of breast
    height agree with each other (within ``lone_agree`` of their weighted median radius at
    breast height, taper limited as above) on a radius ``lone_ratio`` (1.4) times its own or
    more, those others give the DBH. The one is a stem's partial arc (a circle through a short
    arc of a half-hidden stem fits far too small), a stub on the stem, or a thin stem merged
    with a thick one; its being nearest the scanner, or nearest breast height, is why it alone
    was chosen. Own realistic-stem surveys 8 and 9: a 32 cm stem read 12 cm from one cylinder
    seen from 17 m, where three seen from 23-25 m read 34-35 cm, and a 47 cm stem read 28 cm
    from one 13 m away, where four higher up read 47-52 cm; DBH RMSE 3.53 / 3.25 -> 1.54 / 1.28
    cm. Others of two or more scans that all read ``lone_ratio`` times its radius or more
    give the DBH even where they differ among themselves (own realistic seed 49: a 45.5 cm stem
    read 12.4 cm from one scan 17 m away, where two scans at 23 and 28 m read 33 and 50 cm).
    One scan's cylinders and ``lone_agree`` 0.2 -> 0.3: a 44 cm stem read 12.8 cm from two
    cylinders of one scan 17 m away (the others 14-26 cm, 22-29 m), and a 25 cm stem 12.9 cm
    where the others read 22-28 cm; six full-resolution own realistic seeds 2.57 -> 1.33 cm
    (seed 16 5.44 -> 1.09), ten stored ones 1.19 -> 1.20, Sylva, rendered and own circular
    surveys unchanged (benchmarks/results.md "side_radius").

    Only one other scan (inferred, issue 19): when one scan alone gives the DBH and the
    cylinders of other scans within ``lone_one_scan_reach_m`` (2.5 m) of breast height all read
    ``lone_one_scan_ratio`` (1.6, stricter than the two-scan rule's 1.4) times its radius or
    more, they give the DBH (their cones extrapolated, taper limited as above). Held-out own
    realistic seeds 71 and 72: 21-22 cm stems read 12-14 cm from one scan's cylinders 16 m
    away (the near arc of a stem hidden by understorey), where one other scan read 22-26 cm;
    DBH RMSE over seeds 65-74 1.19 -> 1.01 cm, the 54 stored own realistic surveys 1.006 ->
    0.995 (one tree), Sylva, rendered and circular unchanged (results.md "one_other_scan").
    Reach 2.0 -> 2.5 m: PLY seed 84, a 24.7 cm stem read 13.1 cm (partial arcs from 12.5 m)
    where the other scan began 2.03 m above breast height reading 27 cm; PLY seeds 83-90 1.21
    -> 1.03 cm, nothing else changed by > 0.6 cm.

    Near breast height but only far (inferred, issue 19): when every cylinder within
    ``dbh_reach_m`` was seen from beyond ``dbh_max_range_m`` and cylinders within
    ``dbh_close_reach_m`` (1.5 m) were seen from nearer, the near ones give the DBH, their
    cones extrapolated. Held-out seed 67: a 32 cm stem read 22 cm from scans 26 m away, where
    one 13 m away read 32 cm 1.04 m above breast height.

    Understorey (inferred, issue 19): a stem none of whose cylinders reaches ``min_top_m``
    (None: not asked; the tree list's ``understorey_top_m``, 0: off) above its ground is a
    sapling, a bush, a stump or a low branch, not a tree, unless ``understorey_keep`` (3)
    scans or more saw it with a DBH of 0.10 m or more (a stem forked below the height): it
    leaves the list and its cylinders belong to no tree. Own realistic surveys 123-155 (dense
    understorey: saplings 1-4 cm thick read 6-8 cm through the footprint) have about as many
    such "trees" as true stems; with 2.5 m, 320 of the 323 with a DBH of seeds 143-155 leave
    the list and none of their 520 true stems (seed 128: a 12.7 cm stem forked at 2.4 m stays
    by the three scans that saw it). On Sylva's and rendered surveys, which have few, it also
    drops 3 true stems of 440 and 3 of 350 (small trees or far stems seen by one scan in a
    0.5-2 m bit), so it is off unless asked (results.md "understorey").

    ``dbh_note`` (text) is empty for a DBH from a cylinder spanning breast height above a seen
    ground; otherwise it says how the DBH was obtained (a cylinder end near breast height, an
    extrapolated taper, breast height above the lowest cylinder end when the ground under the
    stem was not seen) or why there is none.
    """
    if cyl.empty:
        return pd.DataFrame({c: pd.Series(dtype="float64") for c in TREE_COLUMNS}).astype(
            {"tree_id": "int64", "n_scans": "int64", "n_cylinders": "int64", "dbh_note": "object"}
        ), np.zeros(0, dtype=int)
    labels = group_stems(cyl, merge_factor, merge_tolerance_m)
    rows = []
    zlo = np.minimum(cyl["z0"].to_numpy(float), cyl["z1"].to_numpy(float))
    zhi = np.maximum(cyl["z0"].to_numpy(float), cyl["z1"].to_numpy(float))
    weights = cyl["n_circles"].to_numpy(float)
    radius = cyl["radius_m"].to_numpy(float)
    has_range = "range_m" in cyl and bool(np.isfinite(cyl["range_m"].to_numpy(float)).all())
    obs_range = cyl["range_m"].to_numpy(float) if has_range else np.zeros(len(cyl))
    dbh_weights = weights.copy()
    if has_range and range_weighting:
        dbh_weights = weights / (beam_exit_m + beam_divergence_rad * obs_range) ** 2
    stems = np.unique(labels)
    axes = ends(cyl)  # the cylinders' axis ends, once (a stem's rows of them below, not a frame's)
    # first pass: approximate stem xy (at the lowest visible point) for the ground look-up
    approx_xy = np.array([axis_xy(axes[labels == s], np.full((labels == s).sum(), zlo[labels == s].min())).mean(0)
                          for s in stems])
    approx_r = np.array([np.average(radius[labels == s], weights=weights[labels == s]) for s in stems])
    if grid is not None:
        ground = ground_under(approx_xy, approx_r, grid.z, grid.x0, grid.y0, grid.cell_m,
                              low_quantile=ground_low_quantile, band_m=ground_band_m)
    else:
        ground = np.full(len(stems), np.nan)
    tree_of_cyl = np.zeros(len(cyl), dtype=int)
    low = np.zeros(len(stems), bool)
    seen_at_bh = np.zeros(len(stems), bool)  # cylinders of two or more scans near breast height
    for k, s in enumerate(stems):
        m = labels == s
        ground_seen = bool(np.isfinite(ground[k]))
        # the ground cannot lie above the stem's lowest cylinder end: an annulus whose lowest
        # hits are all crown (a rendered survey: 4.9 m up, the DBH 11.6 cm short) takes that end
        lowest = zlo[m].min()
        ground_above = ground_seen and ground[k] > lowest
        g = min(ground[k], lowest) if ground_seen else lowest
        zbh = g + breast_height_m
        sub = cyl[m]
        zb = np.full(m.sum(), zbh)
        # distance in height from breast height to each cylinder's extent
        gap = np.maximum(0.0, np.maximum(zlo[m] - zbh, zbh - zhi[m]))
        near = gap <= dbh_reach_m
        seen_at_bh[k] = (sub["scan"][near].nunique() if "scan" in sub else int(near.sum())) >= 2
        use = near if near.any() else gap == gap.min()
        w = weights[m][use]
        xy = np.average(axis_xy(axes[m][use], zb[use]), axis=0, weights=w)
        dbh = np.nan
        # cylinders giving the DBH: near breast height, else within the extrapolation limit
        extrapolated = not near.any()
        usable = gap <= dbh_extrapolate_m if extrapolated else near
        if usable.any():
            far = ""
            close = usable & (obs_range[m] <= dbh_max_range_m) if (
                has_range and dbh_max_range_m is not None) else usable
            if (not close.any() and dbh_close_reach_m is not None and has_range
                    and dbh_max_range_m is not None):
                alt = (gap <= dbh_close_reach_m) & (obs_range[m] <= dbh_max_range_m)
                if alt.any():
                    far = (f"the cylinders within {dbh_reach_m:g} m of breast height seen only from "
                           f"{obs_range[m][usable].min():.0f} m or farther")
                    usable, close, extrapolated = alt, alt, True
            pick = close if close.any() else usable
            if small_share is not None and pick.sum() >= 3:  # partial arcs read small
                r_p = radius_at(sub[pick], zb[pick], max_taper_m_per_m, extrapolate=extrapolated)
                small = r_p < small_share * scan_median(r_p, dbh_weights[m][pick],
                                                        sub["scan"].to_numpy()[pick] if "scan" in sub else None)
                if small.any() and (~small).sum() >= 2:
                    pick = pick.copy()
                    pick[np.flatnonzero(pick)[small]] = False
            elif small_share is not None and pick.sum() == 2 and "scan" in sub:
                pick = _drop_small_of_two(sub, pick, gap <= dbh_extrapolate_m, zb, dbh_weights[m],
                                          small_share, max_taper_m_per_m, extrapolated)
            lone = ""
            dbh = 2.0 * weighted_stat(radius_at(sub[pick], zb[pick], max_taper_m_per_m, extrapolate=extrapolated),
                                      dbh_weights[m][pick], dbh_statistic)
            others = (gap <= dbh_extrapolate_m) & ~pick
            one_scan = pick.sum() == 1 or ("scan" in sub and sub["scan"][pick].nunique() == 1)
            if lone_ratio is not None and one_scan and others.sum() >= 2:
                r_o = radius_at(sub[others], zb[others], max_taper_m_per_m, extrapolate=True)
                med = weighted_stat(r_o, dbh_weights[m][others], "median")
                agree = np.abs(r_o - med) <= lone_agree * med
                if (agree.sum() < 2 and "scan" in sub and np.unique(sub["scan"].to_numpy()[others]).size >= 2
                        and (r_o >= lone_ratio * dbh / 2).all()):
                    agree = np.ones(r_o.size, bool)  # every other scan's far thicker, though unlike
                if agree.sum() >= 2 and med >= lone_ratio * dbh / 2:
                    lone = (f"DBH from {int(agree.sum())} cylinders within {dbh_extrapolate_m:g} m of "
                            f"breast height: the one nearest gave {100 * dbh:.1f} cm")
                    dbh = 2.0 * weighted_stat(r_o[agree], dbh_weights[m][others][agree], dbh_statistic)
            if lone_one_scan_ratio is not None and not lone and one_scan and "scan" in sub:
                scans = sub["scan"].to_numpy()
                foreign = (gap <= lone_one_scan_reach_m) & ~np.isin(scans, scans[pick])
                if foreign.any():
                    r_f = radius_at(sub[foreign], zb[foreign], max_taper_m_per_m, extrapolate=True)
                    if (r_f >= lone_one_scan_ratio * dbh / 2).all():
                        lone = (f"DBH from {int(foreign.sum())} cylinders of other scans within "
                                f"{lone_one_scan_reach_m:g} m of breast height: the one nearest gave "
                                f"{100 * dbh:.1f} cm")
                        dbh = 2.0 * weighted_stat(r_f, dbh_weights[m][foreign], dbh_statistic)
            note = dbh_note_for(zlo[m][pick] - g, zhi[m][pick] - g, gap[pick], breast_height_m,
                                dbh_reach_m if extrapolated else None, why=far)
            if note and has_range and dbh_max_range_m is not None and not close.any():
                note += f", seen from {obs_range[m][pick].min():.0f} m or farther"
            note = "; ".join(filter(None, [note, lone]))
        else:
            j = int(np.argmin(gap))
            where = (f"the lowest starts {zlo[m][j] - g:.1f} m" if zlo[m][j] > zbh
                     else f"the highest ends {zhi[m][j] - g:.1f} m")
            note = (f"no DBH: no cylinder within {dbh_extrapolate_m:g} m of breast height "
                    f"({where} above the ground)")
        if not ground_seen or ground_above:
            why = ("ground under the stem not seen" if not ground_seen
                   else f"ground under the stem seen {ground[k] - g:.1f} m above its lowest cylinder")
            note = "; ".join(filter(None, [
                f"{why}: breast height taken {breast_height_m:g} m above the lowest cylinder end", note]))
        # visible length: union of the cylinders' height intervals
        order = np.argsort(zlo[m])
        total, cur_lo, cur_hi = 0.0, None, None
        for lo, hi in zip(zlo[m][order], zhi[m][order], strict=True):
            if cur_hi is None or lo > cur_hi:
                total += 0.0 if cur_hi is None else cur_hi - cur_lo
                cur_lo, cur_hi = lo, hi
            else:
                cur_hi = max(cur_hi, hi)
        total += cur_hi - cur_lo
        tree_of_cyl[m] = k + 1
        n_scans = sub["scan"].nunique() if "scan" in sub else 1
        low[k] = min_top_m is not None and zhi[m].max() < g + min_top_m and not (
            n_scans >= understorey_keep[0] and dbh >= understorey_keep[1])
        rows.append((k + 1, xy[0], xy[1], g, dbh, n_scans, int(m.sum()), total,
                     note))
    return absorb_nested(*drop_trees(pd.DataFrame(rows, columns=TREE_COLUMNS), tree_of_cyl, low), seen_at_bh[~low])


def _drop_small_of_two(sub: pd.DataFrame, pick: np.ndarray, within: np.ndarray, zb: np.ndarray,
                       weights: np.ndarray, small_share: float, max_taper_m_per_m: float | None,
                       extrapolated: bool) -> np.ndarray:
    """Two cylinders of two scans giving the DBH: the one below ``small_share`` of the median over
    three or more scans of the cylinders ``within`` reach of breast height (cones continued,
    taper limited) left out. Own realistic seed 132: a 35 cm stem read 18 cm from a 6 cm arc
    seen 11 m away beside a flared butt 17 m away, where two more scans read 33-35 cm just above."""
    ref = within | pick
    scans = sub["scan"].to_numpy()
    if np.unique(scans[ref]).size < 3 or np.unique(scans[pick]).size < 2:
        return pick
    r_ref = radius_at(sub[ref], zb[ref], max_taper_m_per_m, extrapolate=True)
    med = scan_median(r_ref, weights[ref], scans[ref])
    r_p = radius_at(sub[pick], zb[pick], max_taper_m_per_m, extrapolate=extrapolated)
    small = r_p < small_share * med
    if small.sum() != 1:
        return pick
    out = pick.copy()
    out[np.flatnonzero(pick)[small]] = False
    return out


def absorb_nested(trees: pd.DataFrame, tree_of_cyl: np.ndarray,
                  seen_at_bh: np.ndarray | None = None) -> tuple[pd.DataFrame, np.ndarray]:
    """The tree list less the trees whose axis at breast height lies inside another's section
    (closer than the larger of their radii; two stems cannot overlap): a fork's limb or a crown
    part whose cones were continued down to breast height, or a stray cylinder beside a stem
    that the axis test did not merge (inferred, issue 19). Of two such trees the one with a
    DBH stays, then the one whose cylinders two or more scans saw near breast height
    (``seen_at_bh``, per tree; the stem below a fork, not the limb whose cones were continued
    down to it), then the one of more cylinders, then the thicker; the other leaves the list and
    its cylinders belong to no tree (``tree_of_cyl`` 0), as it would otherwise take half of the
    stem's points at breast height (the nearest axis decides) and hide one silhouette side.
    Own realistic full-resolution seed 19: a 29.4 cm stem and a one-cylinder 15.5 cm "tree"
    8.7 cm from its axis; every scan's far-side edge fell at the axis (benchmarks/results.md,
    "nested"). Own realistic seed 206: a 24.8 cm stem forked 2.1 m up, four scans' cylinders
    spanning breast height (16 in all), gave way to its 18 cm limb (17 cylinders, 2.6 m up and
    more, continued down to the stem's axis) and read 9.9 cm. Trees are numbered again from 1."""
    return drop_trees(trees, tree_of_cyl, nested_trees(trees, seen_at_bh=seen_at_bh))


def nested_trees(trees: pd.DataFrame, overlap_share: float = 0.0, margin_m: float = 0.0,
                 prefer: str = "cylinders", seen_at_bh: np.ndarray | None = None) -> np.ndarray:
    """Which trees leave the list as nested in another (:func:`absorb_nested`): of two trees
    whose axes are closer than the larger radius ``R`` plus ``overlap_share`` of the smaller
    ``r`` plus ``margin_m`` (the smaller's centre within its half radius of the larger's bark:
    two stems that overlap), the one with a DBH stays, then the one ``seen_at_bh`` (when
    given), then (``prefer``) the one of more cylinders or the thicker."""
    r = np.nan_to_num(trees["dbh_m"].to_numpy(float) / 2, nan=0.0)
    gone = np.zeros(len(trees), bool)
    if len(trees) < 2 or r.max() <= 0:
        return gone
    xy = trees[["x", "y"]].to_numpy(float)
    reach = float(r.max() * (1.0 + overlap_share) + margin_m)
    pairs = cKDTree(xy).query_pairs(r=reach, output_type="ndarray")
    d = np.hypot(*(xy[pairs[:, 0]] - xy[pairs[:, 1]]).T) if len(pairs) else np.zeros(0)
    n_cyl = trees["n_cylinders"].to_numpy(int)
    at_bh = np.zeros(len(trees), bool) if seen_at_bh is None else np.asarray(seen_at_bh, bool)

    def rank(i):  # who stays: a DBH first, seen at breast height, then more cylinders or the thicker
        return (r[i] > 0, at_bh[i], n_cyl[i], r[i]) if prefer == "cylinders" else (r[i] > 0, at_bh[i], r[i], n_cyl[i])

    for (i, j), dij in sorted(zip(map(tuple, pairs), d, strict=True), key=lambda t: t[1]):
        big, small = max(r[i], r[j]), min(r[i], r[j])
        if gone[i] or gone[j] or dij >= big + overlap_share * small + margin_m:
            continue
        gone[i if rank(i) < rank(j) else j] = True
    return gone


def drop_trees(trees: pd.DataFrame, tree_of_cyl: np.ndarray, gone: np.ndarray) -> tuple[pd.DataFrame, np.ndarray]:
    """``trees`` less the rows ``gone``, numbered again from 1, and each cylinder's new tree
    (``tree_of_cyl``, 1-based; 0: none, as for the cylinders of a tree gone)."""
    if not gone.any():
        return trees, tree_of_cyl
    new_id = np.where(gone, 0, np.cumsum(~gone))  # old row -> new id (0: absorbed)
    out = trees[~gone].reset_index(drop=True).assign(tree_id=lambda t: np.arange(1, len(t) + 1))
    return out, np.where(tree_of_cyl > 0, new_id[np.maximum(tree_of_cyl, 1) - 1], 0)
