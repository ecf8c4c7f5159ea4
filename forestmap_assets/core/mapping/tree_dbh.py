"""The tree list's DBH: the slice, silhouettes and outline of :mod:`.stem_calipers` gathered
about anchors that follow the DBH, and trees that overlap a thicker one's section left out
(issue 19, inferred).

Anchors: the slice's and the silhouettes' gates and starting radius are the cylinders'
(:func:`~.stem_slices.slice_stems`), and a stem whose only cylinder near breast height fitted
one lobe or a partial arc reads far too small: its gate then cuts the far edge from the widths
and the ray test leaves too few slice points, so the DBH cannot leave the cylinders'. Up to
``tp.anchor_passes`` times, a tree whose DBH came out further than ``tp.anchor_share`` from
its anchor (twice the anchor radius) is gathered and fitted again about the new radius (at
most ``tp.anchor_max_share`` times the cylinders'); the cylinders' DBH stays the base the
slice, widths and outline are blended into. Own realistic seed 150: a 22.4 cm fluted stem
whose one cylinder below breast height read 13.1 cm: 15.2 cm, now 23.3 (results.md "anchors").
A tree whose gates keep no scan's two silhouette sides (no width, or single sides only: the
gate about a small, off-centre axis cut the far edges) has nothing to move it, so it is first
gathered about ``tp.anchor_probe`` (1.5) times the cylinders' radius, and the anchors follow
from there (back to the cylinders' where that finds no more, or only single sides: their
distance is measured from the axis, not across the stem, and own realistic 161 ran to 38.7 cm
for a 24.8 cm stem following them). Own realistic seed 159: a 24.8 cm
stem seen by five scans, its cylinders 17.0 cm, read 17.0 with no width, now 25.1; seed 156 a
21.7 cm stem 15.3 from two single sides, now 22.6 (results.md "anchor_probe").

Overlaps: :func:`~.trees.absorb_nested` judged nesting by the cylinders' radii, which read
small on lobed and one-sided stems; with the DBH measured, a tree whose axis lies within
``tp.overlap_share`` of its own radius plus ``tp.overlap_margin_m`` of a thicker tree's bark
(the two stems would overlap) is a stub, a lobe's or a fork limb's cylinder, and leaves the
list (:func:`~.trees.nested_trees`, the thicker staying); the others are measured again, as
the one gone had taken the points and silhouette sides nearer its axis. Own realistic seed
140: a 48.6 cm stem read 41.2 cm beside a 16 cm "tree" 23 cm from its axis, now 47.1; own
realistic seeds 123-155 (1320 trees) with the anchors: DBH RMSE 1.04 -> 0.98 cm, own circular
0.54 -> 0.40, Sylva's and the rendered surveys within 0.03 (results.md "anchors").
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from forestmap_assets.core.mapping.silhouette_edges import edge_candidates
from forestmap_assets.core.mapping.stem_calipers import dbh_about
from forestmap_assets.core.mapping.stem_slices import slice_stems, widest_anchor
from forestmap_assets.core.mapping.trees import drop_trees, nested_trees

if TYPE_CHECKING:
    import pyarrow as pa


def tree_dbh(trees: pd.DataFrame, cyl: pd.DataFrame, tree_of_cyl: np.ndarray, clouds: Mapping[str, np.ndarray],
             poses: pd.DataFrame, tp, images: Mapping[str, pa.Table] | None = None,
             breast_height_m: float = 1.3,
             splats: Mapping[str, tuple[float, float]] | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The trees of :func:`~.trees.merge_trees` (``trees``, ``tree_of_cyl`` over the global
    cylinders ``cyl``) with their DBH (:func:`~.stem_calipers.dbh_about`, same arguments)
    about anchors that follow it, less the trees that overlap a thicker one (module
    docstring); ``fits`` gains ``anchor_dbh_m``."""
    out, fits = _anchored(trees, cyl, tree_of_cyl, clouds, poses, tp, images, breast_height_m, splats)
    if tp.overlap_margin_m > 0:
        gone = nested_trees(out, tp.overlap_share, tp.overlap_margin_m, prefer="thicker")
        if gone.any():
            anchors = fits["anchor_dbh_m"].to_numpy(float)[~gone] / 2
            trees, tree_of_cyl = drop_trees(trees, tree_of_cyl, gone)
            out, fits = _anchored(trees, cyl, tree_of_cyl, clouds, poses, tp, images, breast_height_m, splats,
                                  anchors)
    return out, fits


def _anchored(trees, cyl, tree_of_cyl, clouds, poses, tp, images, breast_height_m, splats, anchors=None):
    """:func:`~.stem_calipers.dbh_about` gathered again about each tree's DBH while it moves
    (module docstring, anchors), from the radii ``anchors`` where given (a tree list measured
    before), else from the cylinders' and the probe's."""
    stems = slice_stems(trees, cyl, tree_of_cyl, breast_height_m)
    start = stems["radius_m"].to_numpy(float)
    # the images' rows within the widest gates any pass may take, found once
    rows = (edge_candidates(images, poses, stems.assign(radius_m=widest_anchor(tp) * start), tp)
            if tp.calipers and images else None)

    edges: dict = {}  # each scan's silhouette edges, kept for the stems a pass leaves alone

    def about(stems):
        return dbh_about(stems, trees, cyl, tree_of_cyl, clouds, poses, tp, images, breast_height_m, splats, rows,
                         edges)

    if anchors is not None:
        stems = stems.assign(radius_m=np.where(start > 0, anchors, start))
    out, fits = about(stems)
    # no silhouette width within the gates: none, or single sides only
    if anchors is None and rows is not None and tp.anchor_passes and tp.anchor_probe > 1:
        probe = ((fits["caliper_scans"].to_numpy() == 0) | fits["caliper_lone_sides"].to_numpy(bool)) & (start > 0)
        if probe.any():
            wide = min(tp.anchor_probe, tp.anchor_max_share) * start
            stems = stems.assign(radius_m=np.where(probe, wide, start))
            out, fits = about(stems)
    for _ in range(tp.anchor_passes):
        anchor = stems["radius_m"].to_numpy(float)
        # single silhouette sides measure from the axis, not across the stem: no anchor to follow
        new = np.where(fits["caliper_lone_sides"].to_numpy(bool), start, out["dbh_m"].to_numpy(float) / 2)
        new = np.minimum(new, tp.anchor_max_share * start)
        moved = np.isfinite(new) & (anchor > 0) & (np.abs(new - anchor) > tp.anchor_share * anchor)
        if not moved.any():
            break
        stems = stems.assign(radius_m=np.where(moved, new, anchor))
        out, fits = about(stems)
    fits["anchor_dbh_m"] = 2 * stems["radius_m"].to_numpy(float)
    anchored = np.flatnonzero(np.abs(stems["radius_m"].to_numpy(float) - start) > 1e-9)
    if len(anchored):
        notes = out["dbh_note"].astype(str).to_numpy(object)
        for i in anchored:
            part = (f"gathered about a {200 * stems['radius_m'].iat[i]:.1f} cm stem, not the "
                    f"cylinders' {200 * start[i]:.1f} cm")
            notes[i] = f"{notes[i]}; {part}" if notes[i] else part
        out["dbh_note"] = notes
    return out, fits
