"""Ground truth of a structured site seen from one scan (spec 10.1, for scoring feature extraction
and registration): truth lines and points in a scan's levelled frame, which mesh parts a scan
hit, and the samples of the corner lines the sensor can see (open3d ray casting)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.sim.scene_mesh import (
    SceneMesh,
)


# ---- truth helpers -----------------------------------------------------------------------------
def lines_in_frame(lines: pd.DataFrame, origin: np.ndarray, heading_deg: float) -> pd.DataFrame:
    """Line table (x0..z1) expressed in a levelled frame at ``origin`` with ``heading_deg``."""
    c, s = np.cos(np.radians(heading_deg)), np.sin(np.radians(heading_deg))
    out = lines.copy()
    for e in ("0", "1"):
        dx = lines[f"x{e}"].to_numpy() - origin[0]
        dy = lines[f"y{e}"].to_numpy() - origin[1]
        out[f"x{e}"], out[f"y{e}"] = c * dx + s * dy, -s * dx + c * dy
        out[f"z{e}"] = lines[f"z{e}"].to_numpy() - origin[2]
    return out


def points_in_frame(
    table: pd.DataFrame, origin: np.ndarray, heading_deg: float, cols=("x", "y", "z")
) -> pd.DataFrame:
    """Point table (``cols``) expressed in a levelled frame at ``origin`` with ``heading_deg``."""
    c, s = np.cos(np.radians(heading_deg)), np.sin(np.radians(heading_deg))
    out = table.copy()
    dx = table[cols[0]].to_numpy(float) - origin[0]
    dy = table[cols[1]].to_numpy(float) - origin[1]
    out[cols[0]], out[cols[1]] = c * dx + s * dy, -s * dx + c * dy
    out[cols[2]] = table[cols[2]].to_numpy(float) - origin[2]
    return out


def visible_parts(
    part: np.ndarray, points_z: np.ndarray, parts: np.ndarray, *, min_extent_m: float = 1.0
) -> np.ndarray:
    """Which of ``parts`` (mesh part ids) were hit over a vertical extent >= ``min_extent_m``
    (per-pixel ``part`` labels and hit heights of one scan)."""
    out = np.zeros(len(parts), bool)
    sel = np.isin(part, parts) & np.isfinite(points_z)
    if not sel.any():
        return out
    p, z = part[sel], points_z[sel]
    lo = pd.Series(z).groupby(p).min()
    hi = pd.Series(z).groupby(p).max()
    ext = (hi - lo).reindex(parts).fillna(0.0).to_numpy()
    return ext >= min_extent_m


def visible_line_samples(
    mesh: SceneMesh,
    lines: pd.DataFrame,
    origin: np.ndarray,
    *,
    spacing_m: float = 0.1,
    max_range_m: float = 40.0,
    inset_m: float = 0.05,
    tolerance_m: float = 0.1,
) -> pd.DataFrame:
    """Sample points every ``spacing_m`` along truth corner lines (world frame) that the sensor
    at ``origin`` can see: the ray towards the point, moved ``inset_m`` down and towards the
    sensor off the corner, reaches it within ``tolerance_m`` (open3d ray casting). Returns
    ``line_id, x, y, z`` of the visible samples (the truth for recall)."""
    import open3d as o3d

    from forestmap_assets.core.registration.submaps import sample_segments

    p0 = lines[["x0", "y0", "z0"]].to_numpy(float)
    p1 = lines[["x1", "y1", "z1"]].to_numpy(float)
    pts, seg = sample_segments(p0, p1, spacing_m)
    if not len(pts):
        return pd.DataFrame(columns=["line_id", "x", "y", "z"])
    v = pts - origin
    dist = np.linalg.norm(v, axis=1)
    horiz = np.column_stack([v[:, :2], np.zeros(len(v))])
    horiz /= np.maximum(np.linalg.norm(horiz, axis=1, keepdims=True), 1e-9)
    target = pts - inset_m * horiz - np.array([0.0, 0.0, inset_m])
    d = target - origin
    n = np.linalg.norm(d, axis=1)
    rays = np.column_stack([np.broadcast_to(origin, d.shape), d / n[:, None]]).astype(np.float32)
    ans = mesh.raycasting_scene().cast_rays(o3d.core.Tensor(rays))
    t_hit = ans["t_hit"].numpy()
    ok = (t_hit >= n - tolerance_m) & (dist <= max_range_m)
    return pd.DataFrame(
        {
            "line_id": lines["line_id"].to_numpy()[seg[ok]],
            "x": pts[ok, 0],
            "y": pts[ok, 1],
            "z": pts[ok, 2],
        }
    )
