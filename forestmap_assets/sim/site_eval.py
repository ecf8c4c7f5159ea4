"""Scoring a structured-site campaign against its truth, and a plain (Dagster-free) core driver.

* :func:`line_recall`: wall/ceiling line features of one scan against the truth corner lines
  (spec 5, 13.16): recall = share of the *visible* truth corner (sampled every 0.1 m, ray-cast
  visibility, :func:`~.site_truth.visible_line_samples`) lying within ``match_xy_m`` horizontally
  and
  ``match_z_m`` vertically of a detected line whose direction is within ``match_deg``; precision
  = share of detected line length near some truth line; position error = horizontal and vertical
  distance of the detected lines' points to their truth line.
* :func:`pillar_detection`: cylinders of one scan against the truth pillars/poles.
* :func:`extract_scan_features` / :func:`campaign_features`: segments -> circles -> cylinders,
  lines and the sub-map of every scan with the campaign's parameters (the same core functions
  the Dagster assets call), for benchmarks and tests that must not pay for the orchestrator.
* :func:`pose_errors_vs_truth`: estimated poses (frame of the first scan) against truth.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from forestmap_assets.core.geometry import wrap_deg
from forestmap_assets.core.registration.submaps import sample_segments

LINE_EXTRA = ("max_beams", "step_fraction", "hit_margin_m", "min_wall_extent_m",
              "top_tolerance_m", "wall_depth_cells", "border_xy", "link_cells",
              "split_at_outliers")


def _point_line_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray):
    """Horizontal distance (n, m), vertical offset (n, m) and along-line position t in [0, 1]
    of points ``p`` (n, 3) to segments ``a -> b`` (m, 3) (xy distance to the clamped segment)."""
    ab = (b - a)[None, :, :2]
    ap = p[:, None, :2] - a[None, :, :2]
    L2 = np.maximum((ab**2).sum(-1), 1e-12)
    t = np.clip((ap * ab).sum(-1) / L2, 0.0, 1.0)
    foot = a[None, :, :] + t[..., None] * (b - a)[None, :, :]
    dxy = np.hypot(p[:, None, 0] - foot[..., 0], p[:, None, 1] - foot[..., 1])
    dz = p[:, None, 2] - foot[..., 2]
    return dxy, dz, t


def _directions_xy(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    d = (p1 - p0)[:, :2]
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def line_recall(
    detected: pd.DataFrame,
    truth_visible: pd.DataFrame,
    truth_lines: pd.DataFrame,
    *,
    match_xy_m: float = 0.2,
    match_z_m: float = 0.25,
    match_deg: float = 10.0,
    sample_m: float = 0.1,
) -> dict:
    """Recall, precision and position error of detected lines (spec 5, 13.16; inferred scoring).

    ``detected``: line table (``x0..z1``) in the same frame as ``truth_visible`` (visible truth
    samples ``line_id, x, y, z``) and ``truth_lines`` (``line_id, x0..z1``). Returns ``recall``
    (share of visible truth samples matched), ``precision`` (share of detected length within
    ``match_xy_m`` / ``match_z_m`` of a parallel truth line), ``xy_error_m`` / ``z_error_m``
    (median absolute horizontal / vertical distance of matched detected samples to their truth
    line), ``xy_rmse_m`` and the counts.
    """
    out = {"n_detected": int(len(detected)), "detected_length_m": 0.0,
           "visible_truth_m": float(len(truth_visible) * sample_m), "recall": np.nan,
           "precision": np.nan, "xy_error_m": np.nan, "z_error_m": np.nan, "xy_rmse_m": np.nan}
    tl = truth_lines.set_index("line_id")
    ta = tl[["x0", "y0", "z0"]].to_numpy(float)
    tb = tl[["x1", "y1", "z1"]].to_numpy(float)
    tdir = _directions_xy(ta, tb)
    if len(detected):
        da = detected[["x0", "y0", "z0"]].to_numpy(float)
        db = detected[["x1", "y1", "z1"]].to_numpy(float)
        ddir = _directions_xy(da, db)
        out["detected_length_m"] = float(np.linalg.norm(db - da, axis=1).sum())
    if len(truth_visible):
        if len(detected):
            p = truth_visible[["x", "y", "z"]].to_numpy(float)
            dxy, dz, _ = _point_line_distance(p, da, db)
            own = tl.index.get_indexer(truth_visible["line_id"])
            par = np.abs(tdir[own] @ ddir.T) >= np.cos(np.radians(match_deg))
            hit = ((dxy <= match_xy_m) & (np.abs(dz) <= match_z_m) & par).any(axis=1)
            out["recall"] = float(hit.mean())
        else:
            out["recall"] = 0.0
    if len(detected):
        pts, seg = sample_segments(da, db, sample_m)
        dxy, dz, _ = _point_line_distance(pts, ta, tb)
        par = np.abs(ddir[seg] @ tdir.T) >= np.cos(np.radians(match_deg))
        cost = np.where(par, dxy + np.abs(dz) * (match_xy_m / match_z_m), np.inf)
        k = np.argmin(cost, axis=1)
        rows = np.arange(len(pts))
        ok = par[rows, k] & (dxy[rows, k] <= match_xy_m) & (np.abs(dz[rows, k]) <= match_z_m)
        out["precision"] = float(ok.mean())
        if ok.any():
            exy, ez = dxy[rows, k][ok], dz[rows, k][ok]
            out["xy_error_m"] = float(np.median(exy))
            out["z_error_m"] = float(np.median(np.abs(ez)))
            out["xy_rmse_m"] = float(np.sqrt(np.mean(exy**2)))
    return out


def pillar_surface_points(points: np.ndarray, pillars: pd.DataFrame, *,
                          tolerance_m: float = 0.05) -> np.ndarray:
    """Per truth pillar (``x, y, radius_m``, frame of ``points``): how many of the scan's points
    lie within ``tolerance_m`` of its surface, i.e. whether the scan sees it at all (a pillar in
    range may stand round a corner or behind a wall)."""
    xy = np.asarray(points, dtype=float).reshape(-1, 3)[:, :2]
    xy = xy[np.isfinite(xy).all(1)]
    if len(pillars) == 0 or len(xy) == 0:
        return np.zeros(len(pillars), dtype=np.int64)
    from scipy.spatial import cKDTree

    tree = cKDTree(xy)
    out = []
    for x, y, r in pillars[["x", "y", "radius_m"]].to_numpy(float):
        idx = tree.query_ball_point([x, y], r + tolerance_m)
        d = np.hypot(xy[idx, 0] - x, xy[idx, 1] - y)
        out.append(int(np.sum(np.abs(d - r) <= tolerance_m)))
    return np.asarray(out, dtype=np.int64)


def pillar_detection(cylinders: pd.DataFrame, pillars: pd.DataFrame, *, match_m: float = 0.3,
                     max_range_m: float | None = None) -> pd.DataFrame:
    """Truth pillars (``x, y, radius_m``, frame of the cylinders) with the matched cylinders:
    ``n_cylinders``, ``radius_est_m`` (length-weighted mean radius), ``axis_error_m`` (xy
    distance of the axis at the cylinder's mid height), ``range_m`` (from the origin)."""
    out = pillars.copy()
    out["range_m"] = np.hypot(out["x"], out["y"])
    out["n_cylinders"] = 0
    out["radius_est_m"] = np.nan
    out["axis_error_m"] = np.nan
    if max_range_m is not None:
        out = out[out["range_m"] <= max_range_m].copy()
    if len(cylinders) == 0 or len(out) == 0:
        return out.reset_index(drop=True)
    mid = 0.5 * (cylinders[["x0", "y0"]].to_numpy(float) + cylinders[["x1", "y1"]].to_numpy(float))
    length = cylinders["length_m"].to_numpy(float) if "length_m" in cylinders else np.linalg.norm(
        cylinders[["x1", "y1", "z1"]].to_numpy(float) - cylinders[["x0", "y0", "z0"]].to_numpy(
            float), axis=1)
    d = np.hypot(out["x"].to_numpy()[:, None] - mid[None, :, 0],
                 out["y"].to_numpy()[:, None] - mid[None, :, 1])
    near = d <= match_m
    rad = cylinders["radius_m"].to_numpy(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = near * length[None, :]
        out["n_cylinders"] = near.sum(axis=1)
        out["radius_est_m"] = np.where(w.sum(1) > 0, (w * rad[None, :]).sum(1) / w.sum(1), np.nan)
        out["axis_error_m"] = np.where(near.any(1), (w * d).sum(1) / np.maximum(w.sum(1), 1e-12),
                                       np.nan)
    return out.reset_index(drop=True)


def extract_scan_features(image, params, *, circle_options: dict | None = None) -> dict:
    """Segments, circle models, cylinder segments, line segments and the sub-map of one range
    image with ``params`` (a :class:`~forestmap_assets.params.Params`), exactly the core calls
    of the feature assets (``circle_options`` go to ``fit_circle_models``)."""
    from forestmap_assets.core.features.cylinders import extract_features
    from forestmap_assets.core.features.wall_lines import extract_line_segments
    from forestmap_assets.core.registration.submaps import build_submap

    feats = extract_features(image, params, **(circle_options or {}))
    lp = params.lines
    feats["line_segments"] = extract_line_segments(image, lp,
                                                   **{k: getattr(lp, k) for k in LINE_EXTRA})
    feats["submaps"] = build_submap(feats["cylinder_segments"], feats["line_segments"],
                                    params.submaps.spacing_m,
                                    getattr(params.submaps, "cylinder_weight", 1))
    return feats


def campaign_features(folder: str | Path, params=None, *, circle_options: dict | None = None,
                      scans: Sequence[str] | None = None, progress=None) -> dict[str, dict]:
    """:func:`extract_scan_features` of every scan of a campaign folder (its own parameters
    unless ``params`` is given): ``{scan id: features}``."""
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.io.readers import read_scan

    camp = load_campaign(folder)
    p = params or camp.params
    out = {}
    for entry in camp.scans:
        if scans is not None and entry.id not in scans:
            continue
        img = read_scan(entry.path, angular_step_deg=camp.angular_step_deg, tilt_deg=entry.tilt_deg)
        out[entry.id] = extract_scan_features(img, p, circle_options=circle_options)
        if progress:
            f = out[entry.id]
            progress(f"scan {entry.id}: {len(f['cylinder_segments'])} cylinders, "
                     f"{len(f['line_segments'])} lines, {len(f['submaps'])} submap points")
    return out


def truth_relative(truth_poses: pd.DataFrame, scan: str, reference: str) -> np.ndarray:
    """True (dx, dy, dz, dheading) of ``scan`` in the levelled frame of ``reference``."""
    from forestmap_assets.core.geometry import relative_pose

    t = truth_poses.set_index(truth_poses["scan"].astype(str))
    a = t.loc[str(scan), ["x", "y", "z", "heading_deg"]].to_numpy(float)
    b = t.loc[str(reference), ["x", "y", "z", "heading_deg"]].to_numpy(float)
    return np.asarray(relative_pose(tuple(a), tuple(b)), dtype=float)


def pose_errors_vs_truth(poses: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """Per scan: ``ex, ey, ez, exy, eheading_deg`` of estimated poses (frame of the first scan)
    against truth; unregistered scans get NaN."""
    t = truth.assign(scan=truth["scan"].astype(str)).set_index("scan")
    p = poses.assign(scan=poses["scan"].astype(str)).set_index("scan").reindex(t.index)
    out = pd.DataFrame(index=t.index)
    for c in ("x", "y", "z"):
        out[f"e{c}"] = p[c].astype(float) - t[c]
    out["exy"] = np.hypot(out["ex"], out["ey"])
    out["eheading_deg"] = wrap_deg((p["heading_deg"].astype(float) - t["heading_deg"]).to_numpy())
    return out.reset_index()


def scan_site(site, *, resolution: str = "full", seed: int = 0, height_m: float = 1.3,
              scanner_kwargs: dict | None = None) -> list:
    """Scan a :class:`~.site_assembly.Site` from each of its scan positions (cart at ``height_m`` above
    the ground, levelled); returns the :class:`~.scanner.ScanResult` list (world poses in
    ``result.pose``)."""
    from forestmap_assets.sim.scanner import ScanPose, VirtualScanner

    scanner = VirtualScanner(site, resolution=resolution, **(scanner_kwargs or {}))
    xy = np.asarray(site.scan_xy, float).reshape(-1, 2)
    z = site.ground.height(xy[:, 0], xy[:, 1]) + height_m
    seeds = np.random.SeedSequence(seed).spawn(len(xy))
    return [scanner.scan(ScanPose(float(x), float(y), float(zz), float(h)),
                         np.random.default_rng(ss))
            for (x, y), zz, h, ss in zip(xy, z, site.scan_heading_deg, seeds, strict=True)]


def relative_truth(scan_pose, reference_pose) -> np.ndarray:
    """True (dx, dy, dz, dheading) between two :class:`~.scanner.ScanPose` (spec 6.1)."""
    from forestmap_assets.core.geometry import relative_pose

    return np.asarray(relative_pose(
        (scan_pose.x, scan_pose.y, scan_pose.z, scan_pose.heading_deg),
        (reference_pose.x, reference_pose.y, reference_pose.z, reference_pose.heading_deg)))
