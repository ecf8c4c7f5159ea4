"""2-D visibility model (men_spec 7.5 overlap predictor with visibility): cells a scan would see
(rays up to
``coverage_radius_m`` from outside the blind disc, stopped by O cells and exactly by stem discs) and
the mapped
stems it would see (not hidden by nearer trunks, wide enough at the scanner's angular step;
inferred)."""

from __future__ import annotations

import numpy as np

from forestmap_assets.core.exploration import _grid_kernels as kernels
from forestmap_assets.core.exploration.grid import ExplorationGrid
from forestmap_assets.params.men import ExplorationConfig


# ---- visibility ------------------------------------------------------------------------------
def _ray_circle_t(p: np.ndarray, u: np.ndarray, stems: np.ndarray) -> np.ndarray:
    """Distance along rays (n, m) from points ``p`` (n, 2) in directions ``u`` (m, 2) to the first
    stem disc hit (inf: none). ``stems`` rows ``x, y, r``."""
    if not len(stems):
        return np.full((len(p), len(u)), np.inf)
    rel = p[:, None, :] - stems[None, :, :2]  # (n, s, 2)
    b = np.einsum("nsk,mk->nms", rel, u)  # (n, m, s)
    c = (rel**2).sum(-1)[:, None, :] - stems[None, None, :, 2] ** 2
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    t = np.where((disc >= 0) & (t > 0), t, np.inf)
    return t.min(axis=2)


def visible_cells(
    grid: ExplorationGrid,
    positions: np.ndarray,
    occluders: np.ndarray,
    stems: np.ndarray | None = None,
    *,
    radius_m: float = 15.0,
    blind_radius_m: float = 1.8,
    n_rays: int = 720,
    chunk: int = 16,
) -> np.ndarray:
    """2-D visibility model (men_spec 7.5 overlap predictor with visibility): cells (n, nx*ny)
    a scan at each position would see. Rays every ``360/n_rays`` deg are sampled every half cell
    from ``blind_radius_m`` (nothing below the scanner's lowest beam) to ``radius_m``; a ray stops
    at the first ``occluders`` cell (which is itself seen) and at the first stem disc
    (``stems`` rows ``x, y, r``, exact ray-circle intersection: trunk occlusion); each ray is
    walked only as far as it sees (:func:`._grid_kernels.walk_rays`)."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    stems = (
        np.zeros((0, 3)) if stems is None else np.asarray(stems, dtype=np.float64).reshape(-1, 3)
    )
    theta = np.arange(n_rays) * (2 * np.pi / n_rays)
    u = np.column_stack([np.cos(theta), np.sin(theta)])
    t = np.arange(blind_radius_m, radius_m + 1e-9, 0.5 * grid.cell_m)
    occ = np.asarray(occluders, bool).ravel()
    out = np.zeros((len(pos), grid.nx * grid.ny), dtype=bool)
    for a in range(0, len(pos), chunk):
        p = pos[a : a + chunk]
        near = (
            stems[
                (
                    np.hypot(stems[:, 0:1] - p[None, :, 0], stems[:, 1:2] - p[None, :, 1]).min(
                        axis=1
                    )
                    <= radius_m + stems[:, 2]
                )
            ]
            if len(stems)
            else stems
        )
        t_stem = _ray_circle_t(p, u, near)  # (n, m)
        kernels.walk_rays(p, u, t, t_stem, occ, float(grid.x0), float(grid.y0), float(grid.cell_m),
                          int(grid.nx), int(grid.ny), out, a)
    return out


def visible_stems(
    positions: np.ndarray,
    stems: np.ndarray,
    *,
    range_m: float = 15.0,
    min_share: float = 0.5,
    min_width_rad: float = 0.0,
    n_sub: int = 7,
) -> np.ndarray:
    """Which stems (``x, y, r`` rows) a scan at each position sees (n, s): within ``range_m``,
    at least ``min_width_rad`` wide as seen from there (enough pixels across the stem for the
    scan-line segments, see :func:`stem_visibility`), and at least ``min_share`` of its angular
    width not hidden by nearer stems (sampled with ``n_sub`` rays across the width; inferred)."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    stems = np.asarray(stems, dtype=np.float64).reshape(-1, 3)
    if not len(stems) or not len(pos):
        return np.zeros((len(pos), len(stems)), dtype=bool)
    if len(pos) > 8:  # chunks of positions, each with only the stems within range of it
        out = np.zeros((len(pos), len(stems)), dtype=bool)
        for a in range(0, len(pos), 8):
            p = pos[a : a + 8]
            dmin = np.hypot(
                stems[:, None, 0] - p[None, :, 0], stems[:, None, 1] - p[None, :, 1]
            ).min(axis=1)
            near = np.flatnonzero(dmin <= range_m + stems[:, 2])
            if len(near):
                out[a : a + 8, near] = visible_stems(
                    p,
                    stems[near],
                    range_m=range_m,
                    min_share=min_share,
                    min_width_rad=min_width_rad,
                    n_sub=n_sub,
                )
        return out
    d = pos[:, None, :] - stems[None, :, :2]
    dist = np.hypot(d[..., 0], d[..., 1])  # (n, s)
    bearing = np.arctan2(-d[..., 1], -d[..., 0])
    half = np.arcsin(np.clip(stems[None, :, 2] / np.maximum(dist, 1e-9), 0, 1))
    frac = (np.arange(n_sub) + 0.5) / n_sub * 2 - 1  # (-1, 1)
    ang = bearing[..., None] + 0.98 * half[..., None] * frac  # (n, s, k)
    u = np.stack([np.cos(ang), np.sin(ang)], -1)  # (n, s, k, 2)
    # distance along each sub-ray to every stem (n, s, k, s')
    rel = pos[:, None, None, None, :] - stems[None, None, None, :, :2]
    b = (rel * u[:, :, :, None, :]).sum(-1)
    c = (rel**2).sum(-1) - stems[None, None, None, :, 2] ** 2
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    t = np.where((disc >= 0) & (t > 0), t, np.inf)
    own = np.arange(len(stems))
    t_own = t[:, own, :, own].transpose(1, 0, 2)  # (n, s, k)
    t[:, own, :, own] = np.inf
    clear = t.min(axis=3) >= t_own - 1e-9
    share = clear.mean(axis=2)
    wide = 2 * half >= min_width_rad
    return (dist <= range_m) & wide & (share >= min_share) & (dist > stems[None, :, 2])


def stem_visibility(config: ExplorationConfig) -> dict:
    """Keyword arguments of :func:`visible_stems` from the configuration: a stem counts when it
    spans at least ``stem_min_pixels`` columns of ``angular_step_deg`` (the scanner's azimuth
    step; no limit when None), so that the pipeline can find it (inferred: on simulated
    quarter-resolution scans stems about 3 columns wide or more got a cylinder, narrower ones
    mostly not)."""
    step = config.angular_step_deg
    return {
        "range_m": config.stem_range_m,
        "min_share": config.stem_visible_share,
        "min_width_rad": 0.0 if step is None else np.radians(step) * config.stem_min_pixels,
    }
