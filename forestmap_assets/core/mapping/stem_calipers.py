"""DBH from the widths of the stems' silhouettes (issue 19, inferred).

A scanner whose ranges are noisy (the thesis scanner: 2.5 cm, spec Table 6.1) still measures
angles finely. In each scan line the bearings of a stem's outermost pixels fix the two tangent
lines from the scanner to its section, and their distances from the axis add up to the
section's width across the line of sight. Averaged over directions, the widths of an
out-of-round section give its girth / pi (Cauchy's formula); the curvature of a one-sided arc,
which the circle models and the slice's outline fit see, can be 15-25 % off the mean radius.

Per scan, stem and scan line (rows of the range image within ``caliper_half_height_m`` of
breast height, inside :mod:`.stem_slices`' gate; steps 1 and 2: :mod:`.silhouette_edges`):

1. the stem's outermost pixel on each side is a silhouette edge when the first return beyond
   it in that line (within ``look_m`` across) is farther by more than ``edge_step_m``, or there
   is none; a nearer return (an occluder), or the end of an image short of the full circle,
   voids it;
2. the tangent's distance from the axis is ``D sin(|beta| + step / 2) - f(r)``: ``D`` the
   axis's distance from the scanner, ``beta`` the pixel's bearing from the axis direction,
   ``step`` the image's azimuth step (the true edge lies on average half a step beyond the
   last pixel that hit), ``f(r) = (beam_exit + divergence r) / 2`` the footprint radius at the
   edge's range (a first-return beam returns the stem while any part of its footprint touches
   it, spec 1.1), so the silhouette needs the campaign's beam (``sensor`` in campaign.yaml);
3. a side's distance is the mean over its lines within a pixel of their median (at least
   ``min_rows`` lines; a leaning, rough stem's edge crosses pixels from line to line); a scan
   with both sides gives a width, kept when its half lies within ``radius_range`` (shares) of
   the tree's radius (a single side: its distance), and a tree's caliper DBH is the mean
   width of an out-of-round section fitted to its scans' widths and their directions,
   weighted by their pixels' size (:func:`width_function`); a tree whose
   every scan saw one side only gets a circle fitted to the sides of several scans when they
   surround the stem (:func:`_one_sided_dbh`), else twice the mean distance of two or more
   sides that agree (:func:`_side_radius_dbh`).

:func:`blend_calipers` mixes that DBH with the outline's or the cylinders' (weight: the
points' scatter about the outlines against the calipers' own error, the median sd of the
trees' caliper DBH, which grows with the pixels' size). Simulated plots: ``benchmarks/results.md``,
section "DBH from silhouette widths".
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from forestmap_assets.core.mapping.silhouette_edges import tree_edges
from forestmap_assets.core.mapping.silhouette_widening import Widening, campaign_widening
from forestmap_assets.core.mapping.slice_splats import splat_edges_back
from forestmap_assets.core.mapping.stem_outline import blend_outline, outline_dbhs
from forestmap_assets.core.mapping.stem_slices import (
    gather_half_height,
    merged_slice_dbh,
    slice_points,
    within_band,
)

if TYPE_CHECKING:
    import pyarrow as pa

CALIPER_COLUMNS = ["tree", "caliper_dbh_m", "caliper_sd_m", "n_scans", "lone_sides"]


def caliper_dbh(edges: pd.DataFrame, radius_m: np.ndarray, *, min_rows: int = 2,
                radius_range: tuple[float, float] = (0.5, 2.0), width_sd_m: float = 0.008,
                one_sided_spread: float | None = 0.5, one_sided_agree: float = 0.25,
                ellipse_prior: float = 0.04, side_min: int = 2) -> pd.DataFrame:
    """Each tree's caliper DBH (``CALIPER_COLUMNS``; ``lone_sides`` where it is twice the sides'
    distance from the axis, :func:`_side_radius_dbh`) from the
    silhouette edges of all scans (``EDGE_COLUMNS``; step 3 of the module docstring): the
    scans' widths weighted by their precision (the pixel across at the edge, ``quantum_m``,
    and ``width_sd_m`` for the footprint's model and the section's own widths);
    ``radius_m`` (trees,) the trees' current radii, of which half a width, or a single side's
    distance, must lie within ``radius_range`` (shares: the cylinders' radius may be far too
    small where partial arcs made it, but a side at half of it is a stem cut by an occluder the
    edge test missed; an axis off across the line of sight moves a width's two sides by
    opposite amounts, so a width is judged whole). A tree
    without a width from any scan may still get one from sides of several scans
    (:func:`_one_sided_dbh`, with ``one_sided_spread``; None: not), else from ``side_min`` or
    more sides that agree (:func:`_side_radius_dbh`; 0: not). The widths of several
    directions fit an out-of-round section (:func:`width_function`, ``ellipse_prior``)."""
    if edges.empty:
        return _no_calipers()
    sides = side_table(edges, min_rows)
    r = radius_m[sides["tree"].to_numpy(int)]
    in_range = ((sides["h"] >= radius_range[0] * r) & (sides["h"] <= radius_range[1] * r)).to_numpy()
    sides = sides.assign(in_range=in_range)
    # a width's direction: its sides' normals (opposite), doubled
    sides = sides.assign(c2=np.cos(2 * sides["phi"]), s2=np.sin(2 * sides["phi"]))
    both = sides.groupby(["tree", "scan"]).agg(width=("h", "sum"), n=("side", "size"), quantum=("quantum", "max"),
                                               c2=("c2", "mean"), s2=("s2", "mean")).reset_index()
    # a width is kept in range as a whole: an axis off across the line of sight moves its two
    # sides by opposite amounts and leaves their sum alone (one side may read under half)
    half = 0.5 * both["width"] / radius_m[both["tree"].to_numpy(int)]
    both = both[((both["n"] == 2) & (half >= radius_range[0]) & (half <= radius_range[1])).to_numpy()]
    sides = sides[sides["in_range"].to_numpy()]  # single sides: each in range
    # a width's variance: each side's edge uniform within one pixel across, plus width_sd_m
    both["w"] = 1.0 / (both["quantum"] ** 2 / 6.0 + width_sd_m**2)
    out = width_function(both, ellipse_prior).assign(lone_sides=False)[CALIPER_COLUMNS]
    if one_sided_spread is not None:
        rest = sides[~sides["tree"].isin(out["tree"])]
        extra = _one_sided_dbh(rest, radius_m, one_sided_spread, one_sided_agree, width_sd_m)
        out = pd.concat([out, extra], ignore_index=True) if len(extra) else out
    if side_min > 0:
        rest = sides[~sides["tree"].isin(out["tree"])]
        extra = _side_radius_dbh(rest, radius_m, side_min, one_sided_agree, width_sd_m)
        out = pd.concat([out, extra], ignore_index=True) if len(extra) else out
    return out


def side_table(edges: pd.DataFrame, min_rows: int) -> pd.DataFrame:
    """One row per tree, scan and silhouette side seen on ``min_rows`` or more lines: ``h`` the
    mean distance of the lines within a pixel of the side's median (a leaning or rough stem's
    edge crosses pixels from line to line, so the mean resolves what one line cannot), ``size``
    those lines, ``quantum`` the pixel across, ``phi`` the outward normal."""
    key = ["tree", "scan", "side"]
    med = edges.groupby(key)["h_m"].transform("median")
    near = np.abs(edges["h_m"] - med) <= edges["quantum_m"]
    sides = edges[near.to_numpy()].groupby(key).agg(h=("h_m", "mean"), size=("h_m", "size"),
                                                    quantum=("quantum_m", "median"),
                                                    phi=("phi", "median")).reset_index()
    return sides[(sides["size"] >= min_rows).to_numpy()].reset_index(drop=True)


def width_function(widths: pd.DataFrame, ellipse_prior: float) -> pd.DataFrame:
    """Each tree's mean width ``caliper_dbh_m`` from its scans' widths (``tree, width, w, c2,
    s2``: width, inverse variance, cos and sin of twice the direction): a second-order section
    ``r = R (1 + c cos 2(psi - theta))`` is ``2R (1 - c cos 2(a - theta))`` wide across the line
    of sight ``a`` (its support function), so the widths fit ``w0 + a2 cos 2a + b2 sin 2a`` by
    weighted least squares with a ridge prior of sd ``ellipse_prior x w0`` on ``a2, b2`` (0: the
    weighted mean). Widths from two directions 90 deg apart, or three 60 deg apart, average the
    ellipse out either way; two widths of equal weight give their mean (each can carry its own
    ellipse term); from three directions or more the fit takes out part of what the mean keeps.
    A tree's ``caliper_sd_m`` is its widths' own (the weighted mean's), ``n_scans`` their number."""
    t = widths["tree"].to_numpy(int)
    trees, k = np.unique(t, return_inverse=True)
    w = widths["w"].to_numpy(float)
    y = widths["width"].to_numpy(float)
    basis = np.column_stack([np.ones_like(y), widths["c2"].to_numpy(float), widths["s2"].to_numpy(float)])
    sw = np.bincount(k, w)
    mean = np.bincount(k, w * y) / sw
    if ellipse_prior > 0:  # per tree: the weighted normal equations, the prior on a2, b2
        normal = np.zeros((trees.size, 3, 3))
        rhs = np.zeros((trees.size, 3))
        np.add.at(normal, k, w[:, None, None] * basis[:, :, None] * basis[:, None, :])
        np.add.at(rhs, k, (w * y)[:, None] * basis)
        lam = 1.0 / (ellipse_prior * mean) ** 2
        normal[:, 1, 1] += lam
        normal[:, 2, 2] += lam
        dbh = np.linalg.solve(normal, rhs[..., None])[:, 0, 0]
    else:
        dbh = mean
    return pd.DataFrame({"tree": trees, "caliper_dbh_m": dbh, "caliper_sd_m": np.sqrt(1.0 / sw),
                         "n_scans": np.bincount(k)})


def _no_calipers() -> pd.DataFrame:
    return pd.DataFrame({c: pd.Series(dtype="bool" if c == "lone_sides" else "float64") for c in CALIPER_COLUMNS})


def _side_weights(sides: pd.DataFrame, width_sd_m: float) -> np.ndarray:
    """A single side's inverse variance: its edge uniform within one pixel across
    (``quantum``), plus half of ``width_sd_m`` (:mod:`.stem_outline` scales it by
    ``outline_side_weight``)."""
    return 1.0 / (sides["quantum"].to_numpy(float) ** 2 / 12.0 + (0.5 * width_sd_m) ** 2)


def _one_sided_dbh(sides: pd.DataFrame, radius_m: np.ndarray, spread: float, agree: float,
                   width_sd_m: float) -> pd.DataFrame:
    """Caliper DBH of trees whose scans each saw one silhouette side only (the other hidden):
    the sides' distances ``h`` at their outward normals ``phi``, from 3 or more sides of 2 or
    more scans whose normals spread around the stem (the mean of their unit vectors shorter
    than ``spread``), fit a circle about an unknown centre, ``h = a0 + dx cos phi + dy sin phi``
    (least squares, weights from the pixels). Kept where ``a0`` lies within ``agree`` (share) of
    the cylinders' radius and the centre moved less than it: sides that crowd one direction,
    or a stem cut by an occluder the edge test missed, leave the centre undetermined."""
    rows = []
    for t, g in sides.groupby("tree"):
        phi = g["phi"].to_numpy(float)
        if len(g) < 3 or g["scan"].nunique() < 2 or np.abs(np.exp(1j * phi).mean()) > spread:
            continue
        a_mat = np.column_stack([np.ones(phi.size), np.cos(phi), np.sin(phi)])
        w = _side_weights(g, width_sd_m)
        normal = a_mat.T @ (a_mat * w[:, None])
        a = np.linalg.solve(normal, a_mat.T @ (w * g["h"].to_numpy(float)))
        r0 = radius_m[int(t)]
        if abs(a[0] - r0) > agree * r0 or np.hypot(a[1], a[2]) > r0:
            continue
        rows.append((int(t), 2.0 * a[0], 2.0 * float(np.sqrt(np.linalg.inv(normal)[0, 0])), int(g["scan"].nunique()),
                     False))
    return pd.DataFrame(rows, columns=CALIPER_COLUMNS)


def _side_radius_dbh(sides: pd.DataFrame, radius_m: np.ndarray, side_min: int, agree: float,
                     width_sd_m: float) -> pd.DataFrame:
    """Caliper DBH of the trees left without one (no width, sides too few or crowded for
    :func:`_one_sided_dbh`): twice their sides' mean distance from the slice's axis (weights
    from the pixels), from ``side_min`` or more sides within ``agree`` (share of that mean) of
    each other, and not under ``1 - agree`` of the tree's radius ``radius_m``. A tangent's
    normal lies across its line of sight, so an axis that partial arcs pulled towards the
    scanners (and shrank the cylinders' radius with) moves a side only by its offset across
    that line; a side under the cylinders' radius is more often an axis off across it, or an
    edge an occluder cut. Own realistic, the other DBH rules of this session in place (DBH RMSE
    without / with, cm): stored 1-3, 7-13 1.23 / 1.20, bench_dbh seeds 4-6, 14-16 1.65 / 1.32,
    17-22 1.41 / 1.27, 23-28 1.30 / 1.31 (the floor set here), 29-34 1.83 / 1.76
    (benchmarks/results.md "side_radius"). Such a DBH carries the axis's error across the lines
    of sight, which sides from one direction cannot show: :func:`dbh_about` blends the outline
    into it as into the cylinders' (``outline_ref_cylinders_sd_m``; results.md "lone_sides")."""
    if sides.empty:
        return _no_calipers()
    w = _side_weights(sides, width_sd_m)
    g = sides.assign(w=w, wh=w * sides["h"].to_numpy(float)).groupby("tree")
    a = g.agg(sw=("w", "sum"), swh=("wh", "sum"), lo=("h", "min"), hi=("h", "max"), n=("h", "size"),
              n_scans=("scan", "nunique"))
    h = a["swh"] / a["sw"]
    keep = ((a["hi"] - a["lo"] <= agree * h) & (a["n"] >= side_min)
            & (h >= (1.0 - agree) * radius_m[a.index.to_numpy(int)])).to_numpy()
    return pd.DataFrame({"tree": a.index[keep].to_numpy(int), "caliper_dbh_m": 2.0 * h.to_numpy()[keep],
                         "caliper_sd_m": 2.0 / np.sqrt(a["sw"].to_numpy()[keep]),
                         "n_scans": a["n_scans"].to_numpy()[keep], "lone_sides": True})


def tree_calipers(tables: Mapping[str, pa.Table], poses: pd.DataFrame, stems: pd.DataFrame, tp,
                  edges: pd.DataFrame | None = None) -> pd.DataFrame:
    """:func:`caliper_dbh` of ``stems`` (``x, y, zbh, radius_m, slope_x, slope_y``, global
    frame; rows are the trees) from their :func:`tree_edges` (``edges``, if the caller has
    them); ``tp`` the tree parameter section (``params.TreeParams``)."""
    edges = tree_edges(tables, poses, stems, tp) if edges is None else edges
    radius = np.nan_to_num(stems["radius_m"].to_numpy(float), nan=0.0)
    return caliper_dbh(edges, radius, min_rows=tp.caliper_min_rows, radius_range=tuple(tp.caliper_radius_range),
                       width_sd_m=tp.caliper_width_sd_m, one_sided_spread=tp.caliper_one_sided_spread or None,
                       one_sided_agree=tp.caliper_one_sided_agree, ellipse_prior=tp.caliper_ellipse_prior,
                       side_min=tp.caliper_side_min)


def blend_calipers(trees: pd.DataFrame, calipers: pd.DataFrame, noise_m: float, noise_ref_m: float) -> tuple[pd.DataFrame, float]:
    """``trees`` with ``dbh_m = (1 - w) dbh_m + w caliper`` where a tree has a caliper DBH,
    ``w = s^2 / (s^2 + noise_ref_m^2)``: ``s`` (``noise_m``) the points' scatter about the
    stems' outlines, which limits the outline and the cylinders, against ``noise_ref_m``, the
    calipers' own error (the widths' quantisation and the footprint's model). Returns the trees
    and ``w``."""
    out = trees.copy()
    if calipers.empty or not np.isfinite(noise_m) or noise_m <= 0 or not np.isfinite(noise_ref_m):
        return out, 0.0
    w = float(noise_m**2 / (noise_m**2 + noise_ref_m**2))
    rows = calipers["tree"].to_numpy(int)
    dbh = out["dbh_m"].to_numpy(float).copy()
    has = np.isfinite(dbh[rows])
    dbh[rows[has]] = (1 - w) * dbh[rows[has]] + w * calipers["caliper_dbh_m"].to_numpy(float)[has]
    out["dbh_m"] = dbh
    return out, w


def outline_refs(trees: pd.Series, calipers: pd.DataFrame, weight: float, tp) -> np.ndarray:
    """The error of the DBH so far of ``trees`` (rows), which the outline is blended with:
    ``tp.outline_ref_sd_m`` where widths took part (``weight`` > 0), else the cylinders' own
    ``tp.outline_ref_cylinders_sd_m``. Lone sides' distances are measured from the cylinders'
    axis and share its error (:func:`_side_radius_dbh`), so they count as no width."""
    whole = calipers["tree"].to_numpy(int)[~calipers["lone_sides"].to_numpy(bool)]
    widths = np.isin(trees.to_numpy(int), whole) & (weight > 0)
    return np.where(widths, tp.outline_ref_sd_m, tp.outline_ref_cylinders_sd_m)


def dbh_about(stems: pd.DataFrame, trees: pd.DataFrame, cyl: pd.DataFrame, tree_of_cyl: np.ndarray,
              clouds: Mapping[str, np.ndarray], poses: pd.DataFrame, tp,
              images: Mapping[str, pa.Table] | None = None, breast_height_m: float = 1.3,
              splats: Mapping[str, tuple[float, float]] | None = None,
              candidates: Mapping[str, np.ndarray] | None = None,
              reuse: dict | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The trees' DBH from the merged slices (:func:`~.stem_slices.merged_slice_dbh`, same
    arguments) gathered about ``stems`` (:func:`~.stem_slices.slice_stems`, their ``radius_m``
    the gates' anchors: :func:`~.tree_dbh.tree_dbh`), blended with the silhouettes' widths
    when ``tp.calipers`` and the scans' range images ``images`` (``EDGE_COLUMNS_NEEDED``) are
    given, then with one outline fitted to the slice and the silhouette sides together
    (:mod:`.stem_outline`, ``tp.outline_ref_sd_m``). With ``tp.caliper_widening`` "campaign"
    the edges first lose :func:`~.silhouette_widening.campaign_widening`. The fits gain
    ``caliper_dbh_m, caliper_sd_m, caliper_scans, caliper_lone_sides, caliper_widening_m,
    caliper_widening_per_m, caliper_widening_far_m`` (and ``outline_dbh_m, outline_sd_m``); a
    blended tree's ``dbh_note`` says so. ``splats``: the scans whose splat widening the slices and sides take
    back (:func:`~.slice_splats.splat_steps`); with any, the campaign widening beyond the slice
    trees' range tapers off instead of following the cylinders, whose arcs kept the splats
    (:mod:`.slice_splats`). ``candidates``: the images' rows :func:`tree_edges` may look at
    (:func:`edge_candidates`), if the caller has them; ``reuse``: :func:`tree_edges`'."""
    with_outline = bool(tp.calipers and images and tp.outline_ref_sd_m > 0)
    slices, sensors = slice_points(clouds, poses, stems, tp, gather_half_height(tp) if with_outline else None, splats)
    out, fits = merged_slice_dbh(trees, cyl, tree_of_cyl, clouds, poses, tp, breast_height_m, stems=stems,
                                 gathered=(within_band(slices, stems, tp.slice_half_height_m), sensors))
    fits["caliper_dbh_m"], fits["caliper_sd_m"], fits["caliper_scans"] = np.nan, np.nan, 0
    fits["caliper_lone_sides"] = False
    if not (tp.calipers and images):
        return out, fits
    edges = splat_edges_back(tree_edges(images, poses, stems, tp, candidates, reuse), splats)
    calipers = tree_calipers(images, poses, stems, tp, edges=edges)
    widening = Widening()
    if tp.caliper_widening == "campaign" and len(edges):
        edge_range = edges.groupby("tree")["range_m"].median().reindex(range(len(stems))).to_numpy(float)
        # the cylinders were fitted on splat-widened arcs: no reference where splats came off
        cylinder_dbh = None if splats else fits["dbh_cylinders_m"].to_numpy(float)
        widening = campaign_widening(calipers, fits["dbh_slice_m"].to_numpy(float), edge_range,
                                     tp.caliper_widening_min_trees, cylinder_dbh)
        if widening:
            edges = edges.assign(h_m=edges["h_m"] - 0.5 * widening(edges["range_m"].to_numpy(float)))
            calipers = tree_calipers(images, poses, stems, tp, edges=edges)
    fits["caliper_widening_m"], fits["caliper_widening_per_m"] = widening.a, widening.b
    fits["caliper_widening_far_m"] = widening.far_m
    noise = float(np.nanmedian(fits["sigma_m"])) if fits["sigma_m"].notna().any() else float("nan")
    # the calipers' own error: their trees' median sd (the pixels' size: the scanner's step and
    # the ranges), times caliper_sd_factor
    ref = tp.caliper_sd_factor * float(np.median(calipers["caliper_sd_m"])) if len(calipers) else np.nan
    out, weight = blend_calipers(out, calipers, noise, ref)
    rows = fits.index[calipers["tree"].to_numpy(int)]
    for col, src in (("caliper_dbh_m", "caliper_dbh_m"), ("caliper_sd_m", "caliper_sd_m"), ("caliper_scans", "n_scans"),
                     ("caliper_lone_sides", "lone_sides")):
        fits.loc[rows, col] = calipers[src].to_numpy()
    if weight > 0:
        notes = out["dbh_note"].astype(str).to_numpy(object)
        for i, k, lone in zip(calipers["tree"].to_numpy(int), calipers["n_scans"].to_numpy(int),
                              calipers["lone_sides"].to_numpy(bool), strict=True):
            if np.isfinite(out["dbh_m"].iat[i]):
                part = f"{weight:.0%} from the silhouette {'sides' if lone else 'widths'} of {k} scan{'s' if k > 1 else ''}"
                notes[i] = f"{notes[i]}; {part}" if notes[i] else part
        out["dbh_note"] = notes
    if with_outline and len(edges):
        sides = side_table(edges, tp.caliper_min_rows)
        sides = sides.assign(w=tp.outline_side_weight * _side_weights(sides, tp.caliper_width_sd_m))
        outline = outline_dbhs(stems, within_band(slices, stems, tp.outline_half_height_m), sensors, sides, tp)
        out, fits = blend_outline(out, fits, outline, outline_refs(outline["tree"], calipers, weight, tp))
    return out, fits
