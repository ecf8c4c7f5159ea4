"""A renderer's splat widening taken back from the stems' slices (issue 19, inferred).

Scans rendered inside a registered cloud widen every surface across the rays by
``round(s / (r step)) r step`` (:func:`~forestmap_assets.core.registration.splat_widening.widening`):
a pixel beside a stem's point takes the depth of the nearest splat covering it, and the nearest
one lies towards the stem's front. A stem's slice so reads, at the silhouette, the depth of a
point ``w`` nearer its centre line, and its outline comes out wide. Each refined pair that fits
better with the widening taken back says how large the splats are
(:func:`~forestmap_assets.core.registration.splat_widening.choose_splat`); :func:`scan_splats`
gives each scan the median over its refined pairs, and :func:`splat_back` moves each slice point
that far across its ray towards the stem's centre line (no farther than the line), as the
refinement moves every point, and :func:`splat_edges_back` brings each silhouette side in by
the same widening (before the campaign's own widening, :mod:`.silhouette_widening`, is measured
on what is left; beyond the slice trees' range it then tapers off rather than following the
cylinders, which were fitted on the widened arcs: +3.4 cm on rendered 56 with 12 mm splats). A
pixel holding its own source point was not widened, and a pixel a splat filled lies up to half a
pixel beyond the model, so a 30 cm stem rendered with 12 mm splats from
three scans reads +1.6 cm and, taken back, +0.5 cm (tests/mapping/test_slice_splats.py). Tree
lists of stored rendered surveys, DBH RMSE (bias) in cm, before the rays' bins (stem_slices) ->
with them -> with them and the splats taken back: 7 mm splats, 46-48, 0.77 (-0.19) -> 0.79
(+0.08) -> 0.71 (+0.02); 1 cm noise and 12 mm splats, 61, 1.46 (+0.08) -> 2.26 (+1.51) -> 1.41
(+0.63); 12 mm splats, 56, 2.19 (+1.48) -> 3.26 (+2.52) -> 1.93 (+0.99). Scans whose pairs chose
no splat (Sylva's, the own simulator's) keep their points."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.features.range_image import table_azimuth_step
from forestmap_assets.core.registration.splat_widening import widening


def scan_splats(refinements: pd.DataFrame | None) -> dict[str, float]:
    """Each scan's splat radius (m): the median of ``splat_m`` over the refined pairs it is in
    (0 where a pair's refinement chose none); scans without a refined pair are left out."""
    if refinements is None or refinements.empty or "splat_m" not in refinements:
        return {}
    used = refinements[(refinements["used"] == "refined") & refinements["splat_m"].notna()]
    both = pd.concat([used[["scan", "splat_m"]], used[["reference", "splat_m"]].rename(columns={"reference": "scan"})])
    return {str(s): float(v) for s, v in both.groupby("scan")["splat_m"].median().items()}


def link_splats(links: pd.DataFrame, refinements: pd.DataFrame | None) -> np.ndarray:
    """Each link's splat radius (m) its refinement took back (``splat_m`` of the pair's refined
    row; 0 where none, or where the pair was not refined)."""
    if refinements is None or refinements.empty or "splat_m" not in refinements or links.empty:
        return np.zeros(len(links))
    used = refinements[refinements["used"] == "refined"].drop_duplicates(["scan", "reference"])
    m = links[["scan", "reference"]].merge(used[["scan", "reference", "splat_m"]], on=["scan", "reference"], how="left")
    return np.nan_to_num(m["splat_m"].to_numpy(float))


def shared_scan_correlations(links: pd.DataFrame, refinements: pd.DataFrame | None, branch, refined,
                             footprint_free_z: float | None = None, wide_beam: bool = False) -> np.ndarray:
    """Each link's correlation (n, 4: x, y, z, heading) with the other links of its scans:
    ``refined`` where the link was refined, else ``branch`` (``mapping.scan_correlation``,
    ``refined_scan_correlation``); a refined link's z takes ``footprint_free_z`` where no
    footprint meets the ground, the beam not ``wide_beam`` and no splat taken back
    (``mapping.footprint_free_z_correlation``; measured 0.11 on Sylva's surveys against 0.28 with
    the own 3 mrad beam and 0.33 with splats, results.md "footprint_z")."""
    is_refined = links["refined"].to_numpy(bool) if "refined" in links else np.zeros(len(links), bool)
    rho = np.where(is_refined[:, None], np.asarray(refined, float), np.asarray(branch, float))
    if footprint_free_z is not None and not wide_beam and len(links):
        rho[is_refined & ~(link_splats(links, refinements) > 0), 2] = footprint_free_z
    return rho


def splat_back(xy: np.ndarray, sensor_xy: np.ndarray, centre_xy: np.ndarray, range_m: np.ndarray,
               splat_m: float, step_rad: float) -> np.ndarray:
    """Slice points ``xy`` (n, 2, global) seen from ``sensor_xy`` (2,) at ranges ``range_m``,
    each moved across its ray by the splats' widening towards its stem's centre ``centre_xy``
    (n, 2), at most onto the ray through the centre."""
    w = widening(range_m, splat_m, step_rad)
    if not w.any():
        return xy
    ray = xy - sensor_xy
    u = ray / np.maximum(np.hypot(*ray.T), 1e-12)[:, None]
    perp = np.column_stack([-u[:, 1], u[:, 0]])
    off = ((centre_xy - xy) * perp).sum(1)  # the centre's signed distance across the ray
    return xy + perp * (np.sign(off) * np.minimum(w, np.abs(off)))[:, None]


def splat_steps(poses: pd.DataFrame, tables) -> dict[str, tuple[float, float]]:
    """``scan -> (splat_m, angular step)`` of the placed scans (``poses`` with ``splat_m``) whose
    refined pairs chose a splat and whose stored range image (``tables``) gives the step."""
    if "splat_m" not in poses:
        return {}
    out = {}
    for sid, splat in zip(poses["scan"].astype(str), poses["splat_m"].to_numpy(float), strict=True):
        if splat > 0 and sid in tables:
            step = table_azimuth_step(tables[sid])[0]
            if step > 0:
                out[sid] = (float(splat), float(step))
    return out


def splat_edges_back(edges: pd.DataFrame, splats: dict[str, tuple[float, float]] | None) -> pd.DataFrame:
    """Silhouette edges (:data:`~.silhouette_edges.EDGE_COLUMNS`) of the scans in ``splats`` with each
    side's distance ``h_m`` less the splats' widening at its range: the side the renderer moved
    outwards by that much."""
    if not splats or edges.empty:
        return edges
    h = edges["h_m"].to_numpy(float).copy()
    scans = edges["scan"].astype(str).to_numpy()
    for sid, (splat, step) in splats.items():
        on = scans == sid
        h[on] -= widening(edges["range_m"].to_numpy(float)[on], splat, step)
    return edges.assign(h_m=h)
