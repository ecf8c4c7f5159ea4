"""DBH from one outline fitted to the merged slice and the silhouettes' sides together (issue 19,
inferred).

The slice's bins (:mod:`.stem_slices`) measure the outline ``r(psi)`` where the scans saw the bark;
a silhouette side (:mod:`.stem_calipers`) measures its support ``h(phi)``, the tangent's distance
from the centre along its outward normal ``phi``. To first order in the out-of-roundness both are
the same series about the centre, ``a0 + dx cos + dy sin + a2 cos 2 + b2 sin 2``, so one weighted
least squares takes both (:func:`~.stem_slices.slice_dbh` with ``sides``): where the scans saw a
stem from one side only, the front arc fixes the centre across each line of sight (its left-right
symmetry) and a single tangent then fixes the radius, which neither gives alone (the arc's
curvature is 15-25 % off the mean radius; a lone side's distance moves with the axis, which the
partial arcs pulled towards the scanners). No coverage is asked of the slice; a side's weight
is its pixel's quantisation less what its several lines average out (``outline_side_weight``),
plus half of ``caliper_width_sd_m``, and a side farther than ``outline_side_reject_m`` from the
outline after the first round (an occluder the edge test missed) is left out.

The fit's own sd of the DBH (its normal equations') roughly follows its errors on simulated
realistic stems (0.4 cm where it is under 0.5 cm, 1.0 where it is 1.0-1.5, 2.0 where it is
1.5-3), so the tree's DBH so far takes it with the weight ``ref^2 / (ref^2 + sd^2)``, ``ref``
the error of that DBH (:func:`blend_outline`): ``outline_ref_sd_m`` where the widths took part,
``outline_ref_cylinders_sd_m`` where the cylinders alone gave it. Simulated plots:
``benchmarks/results.md``, section "outline".
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.mapping.stem_slices import slice_dbh

OUTLINE_COLUMNS = ["tree", "outline_dbh_m", "outline_sd_m"]


def outline_dbhs(stems: pd.DataFrame, slices: pd.DataFrame, sensors: np.ndarray, sides: pd.DataFrame,
                 tp) -> pd.DataFrame:
    """The joint outline DBH (``OUTLINE_COLUMNS``, ``tree`` the row of ``stems``) of each stem
    with sides: ``stems`` of :func:`~.stem_slices.slice_stems`, its slice points ``slices`` and
    ``sensors`` (:func:`~.stem_slices.gather_slices`), ``sides`` of
    :func:`~.stem_calipers.side_table` with their weights ``w``; ``tp`` the tree parameters."""
    rows = []
    if sides.empty or not len(stems):
        return pd.DataFrame({c: pd.Series(dtype="float64") for c in OUTLINE_COLUMNS})
    order = np.argsort(slices["tree"].to_numpy(), kind="stable")
    s = slices.iloc[order]
    bounds = np.searchsorted(s["tree"].to_numpy(), np.arange(len(stems) + 1))
    xy = s[["x", "y"]].to_numpy(float)
    sens = sensors[s["scan"].to_numpy()] if len(s) else np.zeros((0, 2))
    centre, radius = stems[["x", "y"]].to_numpy(float), stems["radius_m"].to_numpy(float)
    for t, g in sides.groupby("tree"):
        i = int(t)
        if not radius[i] > 0:
            continue
        lo, hi = bounds[i], bounds[i + 1]
        fit = slice_dbh(xy[lo:hi], sens[lo:hi], tuple(centre[i]), float(radius[i]), min_coverage_deg=0.0,
                        sides=(g["phi"].to_numpy(float), g["h"].to_numpy(float), g["w"].to_numpy(float)),
                        side_reject_m=tp.outline_side_reject_m, **_slice_options(tp))
        if np.isfinite(fit.dbh_m) and np.isfinite(fit.sd_m):
            rows.append((i, fit.dbh_m, fit.sd_m))
    return pd.DataFrame(rows, columns=OUTLINE_COLUMNS)


def _slice_options(tp) -> dict:
    """The slice fit's settings shared with :func:`~.stem_slices.merged_slice_dbh`, without its
    cylinder-radius prior and leave-one-out (the sides place the outline)."""
    return dict(max_incidence_deg=tp.slice_max_incidence_deg, bin_deg=tp.slice_bin_deg,
                min_points=tp.slice_min_points, ellipse_prior=tp.slice_ellipse_prior,
                trim_sigmas=tp.slice_trim_sigmas, range_sigma_m=tp.range_sigma_m,
                outline_sd_m=tp.slice_outline_sd_m, edge_footprints=tp.slice_edge_footprints,
                beam_exit_m=tp.beam_exit_m, beam_divergence_rad=1e-3 * tp.beam_divergence_mrad)


def blend_outline(trees: pd.DataFrame, fits: pd.DataFrame, outline: pd.DataFrame,
                  ref_sd_m) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``trees`` with ``dbh_m = (1 - w) dbh_m + w outline``, ``w = ref^2 / (ref^2 + sd^2)``, where
    a tree has a DBH and a joint outline (``ref_sd_m`` the error of the DBH so far, one value or
    one per row of ``outline``); ``fits`` gains ``outline_dbh_m, outline_sd_m`` and a blended
    tree's ``dbh_note`` says how much."""
    out, fits = trees.copy(), fits.copy()
    fits["outline_dbh_m"], fits["outline_sd_m"] = np.nan, np.nan
    rows = outline["tree"].to_numpy(int)
    fits.loc[fits.index[rows], "outline_dbh_m"] = outline["outline_dbh_m"].to_numpy()
    fits.loc[fits.index[rows], "outline_sd_m"] = outline["outline_sd_m"].to_numpy()
    dbh = out["dbh_m"].to_numpy(float).copy()
    notes = out["dbh_note"].astype(str).to_numpy(object)
    w = ref_sd_m**2 / (ref_sd_m**2 + outline["outline_sd_m"].to_numpy(float) ** 2)
    for i, wi, d in zip(rows, w, outline["outline_dbh_m"].to_numpy(float), strict=True):
        if np.isfinite(dbh[i]):
            dbh[i] = (1.0 - wi) * dbh[i] + wi * d
            part = f"{wi:.0%} from one outline fitted to the slice and the silhouette sides"
            notes[i] = f"{notes[i]}; {part}" if notes[i] else part
    out["dbh_m"], out["dbh_note"] = dbh, notes
    return out, fits
