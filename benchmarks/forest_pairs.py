"""Registration pairs from simulated forest campaigns (real submaps, truth poses, shared stems).

Used by ``bench_registration.py``. For a campaign written by ``forestmap simulate`` it computes
each scan's sub-map with the pipeline's own core functions (range image -> segments -> circle
models -> cylinder segments -> submap, the chain of the ``submaps`` asset), caches them in
``<campaign>/bench_submaps.parquet``, and lists every scan pair with its true relative pose (location
of ``scan`` in the levelled frame of ``reference``, spec 6.1) and the number of stems visible in
both scans (truth labels, same rule as ``sim.campaign.visible_trees``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from forestmap_assets.core.geometry import relative_pose

# circle-model options the circle_models asset passes from CircleParams (assets/features.py)
CIRCLE_OPTIONS = ("fit", "symmetry_statistic", "stable_centre_m", "stable_radius_m",
                  "stable_normal_deg", "stable_share", "max_batch_points", "engine")


def campaign_submap_tables(folder: Path, progress=print) -> dict[str, pd.DataFrame]:
    """Sub-map tables (``x, y, z, feature, feature_id``, the ``submaps`` asset's) per scan id,
    computed once with the pipeline's core functions and cached next to the campaign."""
    folder = Path(folder)
    cache = folder / "bench_submaps.parquet"
    if cache.exists():
        table = pd.read_parquet(cache)
        return {str(s): g.drop(columns="scan").reset_index(drop=True)
                for s, g in table.groupby("scan", sort=True)}
    from forestmap_assets.core.features.circle_models import fit_circle_models
    from forestmap_assets.core.features.cylinders import assemble_cylinders
    from forestmap_assets.core.features.segments import feature_scan_lines, segment_scan_lines
    from forestmap_assets.core.registration.submaps import build_submap
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.io.readers import read_scan

    camp = load_campaign(folder)
    p = camp.params
    out = {}
    for entry in camp.scans:
        image = read_scan(entry.path, angular_step_deg=camp.angular_step_deg, tilt_deg=entry.tilt_deg)
        # the calls of the segments, circle_models, cylinder_segments and submaps assets
        image = feature_scan_lines(image, p.segmentation.min_line_step_deg)
        seg = segment_scan_lines(image, p.segmentation,
                                 max_window_px=p.segmentation.max_window_px)
        cp = p.circles
        circ = fit_circle_models(image, seg, cp, p.segmentation,
                                 **{k: getattr(cp, k) for k in CIRCLE_OPTIONS})
        final = circ[circ["iteration"] == circ["iteration"].max()] if len(circ) else circ
        cyl = assemble_cylinders(final, p.cylinders, reference=p.cylinders.curvature_reference)
        out[entry.id] = build_submap(cyl, None, p.submaps.spacing_m)
        progress(f"  {folder.name}/{entry.id}: {len(cyl)} cylinders, {len(out[entry.id])} points")
    pd.concat([t.assign(scan=s) for s, t in out.items()], ignore_index=True).to_parquet(cache)
    return out


def campaign_submaps(folder: Path, progress=print) -> dict[str, np.ndarray]:
    """Sub-map points (n, 3) per scan id (:func:`campaign_submap_tables`)."""
    from forestmap_assets.core.registration.submaps import submap_points

    return {s: submap_points(t) for s, t in campaign_submap_tables(folder, progress).items()}


def visible_stems(folder: Path, scan_id: str, pose, max_range_m: float = 20.0,
                  min_length_m: float = 1.0, max_gap_m: float = 0.25) -> set[int]:
    """Tree ids whose stem is visible in scan ``scan_id`` (truth labels; the simulator's rule)."""
    folder = Path(folder)
    with np.load(folder / "truth" / "labels" / f"{scan_id}.npz") as lab, \
            np.load(folder / "scans" / f"{scan_id}.npz") as sc:
        kind, tree = lab["kind"], lab["tree_id"]
        rng = sc["range"]
        el = np.radians(sc["elevation_deg"])[:, None]
        az = np.radians(sc["azimuth_deg"])[None, :]
    sel = (kind == 1) & np.isfinite(rng) & (rng <= max_range_m)
    z = (rng * np.sin(el) * np.ones_like(az))[sel] + pose[2]
    t = tree[sel].astype(np.int64)
    stems = pd.read_csv(folder / "truth" / "stems.csv").set_index("tree_id")
    h = z - stems["z_base"].reindex(t).to_numpy()
    order = np.lexsort((h, t))
    t, h = t[order], h[order]
    dh = np.diff(h)
    covered = np.where((t[1:] == t[:-1]) & (dh <= max_gap_m), dh, 0.0)
    length = np.bincount(t[1:], weights=covered, minlength=t.max() + 1)
    return set(np.flatnonzero(length >= min_length_m).tolist())


def campaign_pairs(folder: Path) -> pd.DataFrame:
    """Every unordered scan pair ``scan, reference, truth (dx, dy, dz, dh), shared_stems``."""
    folder = Path(folder)
    poses = pd.read_csv(folder / "truth" / "poses.csv").set_index("scan")
    ids = list(poses.index)
    vis = {s: visible_stems(folder, s, poses.loc[s].to_numpy(float)) for s in ids}
    rows = []
    for i, ref in enumerate(ids):
        for scan in ids[i + 1:]:
            rel = relative_pose(poses.loc[scan].to_numpy(float), poses.loc[ref].to_numpy(float))
            rows.append(dict(campaign=folder.name, scan=scan, reference=ref, tx=rel[0], ty=rel[1],
                             tz=rel[2], th=rel[3], shared_stems=len(vis[scan] & vis[ref])))
    return pd.DataFrame(rows)


def stems_in_scan_frame(folder: Path, scan_id: str) -> pd.DataFrame:
    """Truth stem base positions (``tree_id, x, y``) in the levelled frame of ``scan_id``."""
    folder = Path(folder)
    poses = pd.read_csv(folder / "truth" / "poses.csv").set_index("scan")
    x, y, _, h = poses.loc[scan_id].to_numpy(float)
    stems = pd.read_csv(folder / "truth" / "stems.csv")
    c, s = np.cos(np.radians(h)), np.sin(np.radians(h))
    dx, dy = stems["x_base"] - x, stems["y_base"] - y
    return pd.DataFrame({"tree_id": stems["tree_id"], "x": c * dx + s * dy, "y": -s * dx + c * dy})


def sector_crop(folder: Path, scan: str, reference: str, points, width_deg: float = 50.0,
                max_range_m: float = 15.0, shared_range=(1, 4), min_points: int = 150):
    """A low-overlap variant of a pair: ``scan``'s sub-map points within an azimuth sector of
    ``width_deg`` (and ``max_range_m``) chosen so that it holds ``shared_range`` of the stems
    visible in both scans. ``points``: (n, 3) array or sub-map table. Returns (the same type
    cropped, shared stems in the sector) or None."""
    folder = Path(folder)
    poses = pd.read_csv(folder / "truth" / "poses.csv").set_index("scan")
    shared = (visible_stems(folder, scan, poses.loc[scan].to_numpy(float))
              & visible_stems(folder, reference, poses.loc[reference].to_numpy(float)))
    st = stems_in_scan_frame(folder, scan)
    st = st[st.tree_id.isin(shared)]
    az_st = np.degrees(np.arctan2(st.y, st.x))
    r_st = np.hypot(st.x, st.y)
    xyz = points[["x", "y", "z"]].to_numpy(float) if isinstance(points, pd.DataFrame) else points
    az_p = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    r_p = np.hypot(xyz[:, 0], xyz[:, 1])
    for centre in np.arange(-180.0, 180.0, 10.0):
        in_st = (np.abs((az_st - centre + 180) % 360 - 180) <= width_deg / 2) & (r_st <= max_range_m)
        k = int(in_st.sum())
        if not shared_range[0] <= k <= shared_range[1]:
            continue
        sel = (np.abs((az_p - centre + 180) % 360 - 180) <= width_deg / 2) & (r_p <= max_range_m)
        if sel.sum() >= min_points:
            return (points[sel].reset_index(drop=True) if isinstance(points, pd.DataFrame)
                    else points[sel]), k
    return None


def campaign_elevation(folder: Path, progress=print) -> dict[str, pd.DataFrame]:
    """Lowest-hit elevation grid (``ix, iy, z, n``) per scan id, as the ``elevation_maps`` asset
    computes it (:func:`~forestmap_assets.core.features.elevation.elevation_grid` of the levelled range
    image with the campaign's elevation parameters), cached next to the campaign."""
    folder = Path(folder)
    cache = folder / "bench_elevation.npz"
    cols = ("ix", "iy", "z", "n")
    if cache.exists():
        with np.load(cache) as z:
            ids = sorted({k.split("/")[0] for k in z.files})
            return {s: pd.DataFrame({c: z[f"{s}/{c}"] for c in cols}) for s in ids}
    from forestmap_assets.core.features.elevation import elevation_grid
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.io.readers import read_scan

    camp = load_campaign(folder)
    ep = camp.params.elevation
    out = {}
    for entry in camp.scans:
        image = read_scan(entry.path, angular_step_deg=camp.angular_step_deg, tilt_deg=entry.tilt_deg)
        out[entry.id] = elevation_grid(image, ep, max_distance_m=ep.max_distance_m)
        progress(f"  {folder.name}/{entry.id}: {len(out[entry.id])} elevation cells")
    np.savez(cache, **{f"{s}/{c}": t[c].to_numpy() for s, t in out.items() for c in cols})
    return out


def benchmark_box(forest_box: bool, truth, pa: pd.DataFrame, pb: pd.DataFrame, rng,
                  max_xy_m: float):
    """Search box (centre, half-widths) of a benchmark pair: the forest box (issue 4: +-5 m,
    +-1.25 m, +-60 deg) centred 4.5 m and 32 deg off the truth (the thesis's worst a priori
    errors), or the no-prior box (full heading circle, xy out to the shorter sub-map reach,
    at most ``max_xy_m``)."""
    if forest_box:
        ang = rng.uniform(0, 2 * np.pi)
        centre = np.asarray(truth) + np.array([4.5 * np.cos(ang), 4.5 * np.sin(ang),
                                               rng.uniform(-0.3, 0.3),
                                               32.0 * rng.choice([-1, 1])])
        return centre, (5.0, 5.0, 1.25, 60.0)
    reach = min(np.hypot(pa.x, pa.y).max(), np.hypot(pb.x, pb.y).max(), max_xy_m)
    return np.zeros(4), (reach, reach, 1.25, 180.0)
