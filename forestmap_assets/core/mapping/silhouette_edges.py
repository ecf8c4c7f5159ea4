"""Silhouette edges of the stems in the scans' range images (issue 19, inferred): steps 1 and 2
of :mod:`.stem_calipers`.

Per scan, stem and scan line (rows of the range image within ``caliper_half_height_m`` of
breast height, inside :mod:`.stem_slices`' gate), the stem's outermost pixel on each side is a
silhouette edge when the first return beyond it in that line (within ``look_m`` across) is
farther by more than ``edge_step_m``, or there is none; a nearer return (an occluder), or the
end of an image short of the full circle, voids it. The tangent's distance from the axis is
``D sin(|beta| + step / 2) - f(r)`` (:func:`silhouette_edges`). The tree list's passes about
moving anchors keep each scan's edges of the stems whose radius stayed (:func:`tree_edges`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from forestmap_assets.core.features.range_image import table_azimuth_step
from forestmap_assets.core.geometry import rot_z, transform_points
from forestmap_assets.core.mapping.cylinder_radii import MAX_SLOPE
from forestmap_assets.core.mapping.stem_slices import StemCells, slice_members

if TYPE_CHECKING:
    import pyarrow as pa

EDGE_COLUMNS = ["tree", "scan", "side", "row", "h_m", "range_m", "quantum_m", "phi"]
EDGE_COLUMNS_NEEDED = ["row", "col", "range_m", "x", "y", "z"]
MAX_LOOK_PIXELS = 64


def silhouette_edges(tbl: pa.Table, pose: np.ndarray, stems: pd.DataFrame, *, half_height_m: float,
                     reach_m: np.ndarray, beam_exit_m: float, beam_divergence_rad: float,
                     edge_step_m: float = 0.3, look_m: float = 0.3, min_pixels: int = 3,
                     candidates: np.ndarray | None = None, only: np.ndarray | None = None) -> pd.DataFrame:
    """Silhouette edges (``EDGE_COLUMNS`` less ``scan``) of the ``stems`` (``x, y, zbh,
    slope_x, slope_y``, global frame) in one scan's range image ``tbl`` (``EDGE_COLUMNS_NEEDED``
    and the image's azimuths) placed with ``pose`` (x, y, z, heading_deg): per stem, scan line
    and side (+1: larger bearing) the tangent's distance ``h_m`` from the axis, for the edges
    that pass step 1 of the module docstring, ordered by side, stem and line. ``candidates``:
    the only rows of ``tbl`` that may lie in a slice (:class:`~.stem_slices.StemCells`); None:
    all. ``only`` (a mask over the stems): the edges of those stems alone, the same rows as
    among all stems' (a point belongs to its nearest stem whatever the others' reach)."""
    empty = pd.DataFrame({c: pd.Series(dtype="float64") for c in EDGE_COLUMNS if c != "scan"})
    step, n_cols, col_dir = table_azimuth_step(tbl)
    if not len(stems) or tbl.num_rows == 0 or not np.isfinite(step) or step <= 0:
        return empty
    row, col = tbl.column("row").to_numpy(), tbl.column("col").to_numpy()
    rng = tbl.column("range_m").to_numpy()
    zbh = stems["zbh"].to_numpy(float)
    if candidates is None:
        z = tbl.column("z").to_numpy().astype(np.float64) + pose[2]
        candidates = np.flatnonzero((z >= zbh.min() - half_height_m) & (z <= zbh.max() + half_height_m))
    idx = np.asarray(candidates, np.int64)
    if only is not None and idx.size:
        idx = _near_asked(tbl, idx, pose, stems, reach_m, half_height_m, only)
    if not idx.size:
        return empty
    xyz = np.column_stack([tbl.column(a).to_numpy()[idx] for a in "xyz"]).astype(np.float64)
    p = transform_points(xyz, pose)
    centre = stems[["x", "y"]].to_numpy(float)
    slope = stems[["slope_x", "slope_y"]].to_numpy(float)
    i, k, dz = slice_members(p, cKDTree(centre), zbh, slope, reach_m, half_height_m)
    if only is not None:
        asked = only[k]
        i, k, dz = i[asked], k[asked], dz[asked]
    idx, p = idx[i], p[i]
    axis = centre[k] + slope[k] * dz[:, None]
    if not idx.size:
        return empty
    sensor = np.asarray(pose[:2], np.float64)
    to_axis = axis - sensor
    dist = np.hypot(*to_axis.T)
    bearing = np.angle(np.exp(1j * (np.arctan2(p[:, 1] - sensor[1], p[:, 0] - sensor[0])
                                    - np.arctan2(to_axis[:, 1], to_axis[:, 0]))))
    # per (stem, line): the pixels in bearing order; its first and last are the two edges
    n_rows = int(row.max()) + 1
    group = k * n_rows + row[idx]
    order = np.lexsort((bearing, group))
    g = group[order]
    start = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    count = np.diff(np.r_[start, g.size])
    start, count = start[count >= min_pixels], count[count >= min_pixels]
    if not start.size:
        return empty
    ends = np.concatenate([order[start], order[start + count - 1]])
    side = np.repeat([-1, 1], start.size)
    # the returns beyond each edge along its line: the first one decides (step 1)
    e_row, e_col = row[idx[ends]].astype(np.int64), col[idx[ends]].astype(np.int64)
    e_rng = rng[idx[ends]].astype(np.float64)
    span = np.clip(np.ceil(look_m / np.maximum(e_rng * step, 1e-6)), 1, MAX_LOOK_PIXELS).astype(int)
    ahead = np.arange(1, MAX_LOOK_PIXELS + 1)
    cols = e_col[:, None] + (side * col_dir)[:, None] * ahead[None]
    # an image short of the full circle ends at its first and last column: nothing is known
    # beyond them, so an edge there (a stem cut by the field of view) is no silhouette
    full_circle = abs(n_cols * step - 2 * np.pi) < 1.5 * step
    outside = ((cols < 0) | (cols >= n_cols)) & (ahead[None] <= span[:, None])
    cols %= n_cols
    beyond = np.where(ahead[None] <= span[:, None], _pixel_ranges(row, col, rng, e_row, cols), np.inf)
    first = np.where(np.isfinite(beyond).any(1), beyond[np.arange(len(ends)), np.argmax(np.isfinite(beyond), 1)], np.inf)
    clear = (first > e_rng + edge_step_m) & (full_circle | ~outside.any(1))
    footprint = 0.5 * (beam_exit_m + beam_divergence_rad * e_rng)
    h = dist[ends] * np.sin(np.abs(bearing[ends]) + 0.5 * step) - footprint
    # the tangent's outward normal: the axis's bearing from the scanner turned by 90 deg plus
    # the edge's angle, towards the edge's side
    normal = (np.arctan2(to_axis[ends, 1], to_axis[ends, 0])
              + side * (0.5 * np.pi + np.abs(bearing[ends]) + 0.5 * step))
    return pd.DataFrame({"tree": k[ends][clear], "side": side[clear], "row": e_row[clear],
                         "h_m": h[clear], "range_m": e_rng[clear], "quantum_m": (dist[ends] * step)[clear],
                         "phi": normal[clear]})


def _near_asked(tbl: pa.Table, idx: np.ndarray, pose: np.ndarray, stems: pd.DataFrame, reach_m: np.ndarray,
                half_height_m: float, only: np.ndarray) -> np.ndarray:
    """The rows ``idx`` of ``tbl`` that may lie in the slice of a stem in ``only``: within its
    reach of its axis, leaning over the half height, in the scan's frame (:class:`StemCells`,
    a micrometre wider than the slice, so a superset: :func:`slice_members` decides, with every
    stem, as without ``only``). A pass that changed a few stems' radii looks at their points alone."""
    if not only.any():
        return idx[:0]
    slope = stems[["slope_x", "slope_y"]].to_numpy(float)[only]
    reach = np.asarray(reach_m, float)[only] + np.hypot(*slope.T) * half_height_m + 1e-6
    cells = _scan_cells(stems[["x", "y"]].to_numpy(float)[only], stems["zbh"].to_numpy(float)[only], pose, reach,
                        half_height_m + 1e-6)
    return idx[cells.near(*(tbl.column(a).to_numpy()[idx] for a in "xyz"))]


def _scan_cells(centre: np.ndarray, zbh: np.ndarray, pose: np.ndarray, reach: np.ndarray,
                half_height_m: float) -> StemCells:
    """:class:`StemCells` of stems (global ``centre``, breast heights ``zbh``) in the frame of
    the scan placed with ``pose`` (x, y, z, heading_deg), where its image's points are."""
    local = (centre - pose[:2]) @ rot_z(pose[3])[:2, :2]
    return StemCells(local, zbh - pose[2], reach, half_height_m)


def _pixel_ranges(row: np.ndarray, col: np.ndarray, rng: np.ndarray, rows: np.ndarray,
                  cols: np.ndarray) -> np.ndarray:
    """The image's range (float32, ``inf`` where no return) at pixels ``(rows[e], cols[e, j])``,
    looked up in the table's own pixels instead of a dense image (81 of the 233 ms of a
    rendered survey's silhouette pass, three passes in a tree list); a table that is not in
    row-major order is sorted first."""
    from forestmap_assets.core.mapping._slice_kernels import pixel_ranges, row_major

    if not row_major(row, col):
        order = np.lexsort((col, row))
        row, col, rng = row[order], col[order], rng[order]
    return pixel_ranges(row, col, np.asarray(rng, np.float32), rows, cols)


def edge_candidates(tables: Mapping[str, pa.Table], poses: pd.DataFrame, stems: pd.DataFrame,
                    tp) -> dict[str, np.ndarray]:
    """Per placed scan of ``tables`` with the edge columns, the rows of its range image that may
    lie in a silhouette's gate about ``stems`` (:class:`~.stem_slices.StemCells`): the same
    rows serve any gates no wider, as :func:`silhouette_edges` tests each row's reach."""
    radius = np.nan_to_num(stems["radius_m"].to_numpy(float), nan=0.0)
    reach = tp.slice_gate_factor * radius + tp.slice_gate_margin_m
    half = tp.caliper_half_height_m
    centre, zbh = stems[["x", "y"]].to_numpy(float), stems["zbh"].to_numpy(float)
    placed = poses.assign(scan=poses["scan"].astype(str)).set_index("scan")
    out = {}
    for sid, tbl in tables.items():
        if not len(stems) or sid not in placed.index or not set(EDGE_COLUMNS_NEEDED) <= set(tbl.column_names):
            continue
        pose = placed.loc[sid, ["x", "y", "z", "heading_deg"]].to_numpy(float)
        cells = _scan_cells(centre, zbh, pose, reach + MAX_SLOPE * half, half)
        out[sid] = cells.near(*(tbl.column(a).to_numpy() for a in "xyz"))
    return out


def tree_edges(tables: Mapping[str, pa.Table], poses: pd.DataFrame, stems: pd.DataFrame, tp,
               candidates: Mapping[str, np.ndarray] | None = None, reuse: dict | None = None) -> pd.DataFrame:
    """:func:`silhouette_edges` (``EDGE_COLUMNS``) of ``stems`` in every placed scan's range
    image in ``tables``; ``candidates``: :func:`edge_candidates` of gates at least as wide.
    ``reuse``: a dict the caller keeps between calls about the same stems, their radii alone
    changing (:func:`~.tree_dbh.tree_dbh`'s passes): each scan's edges of the stems whose
    radius stayed are kept, the others' found again (:func:`_respliced`; the same table)."""
    radius = np.nan_to_num(stems["radius_m"].to_numpy(float), nan=0.0)
    reach = tp.slice_gate_factor * radius + tp.slice_gate_margin_m
    half = tp.caliper_half_height_m
    placed = poses.assign(scan=poses["scan"].astype(str)).set_index("scan")
    candidates = edge_candidates(tables, poses, stems, tp) if candidates is None else candidates
    parts = []
    for sid, tbl in tables.items():
        if sid not in candidates:
            continue
        pose = placed.loc[sid, ["x", "y", "z", "heading_deg"]].to_numpy(float)
        kw = dict(half_height_m=half, reach_m=reach, candidates=candidates[sid], beam_exit_m=tp.beam_exit_m,
                  beam_divergence_rad=1e-3 * tp.beam_divergence_mrad, edge_step_m=tp.caliper_edge_step_m)
        before, e = (reuse or {}).get(sid), None
        if before is not None:
            moved = radius != before[0]
            e = before[1] if not moved.any() else _respliced(
                before[1], moved, silhouette_edges(tbl, pose, stems, only=moved, **kw))
        if e is None:
            e = silhouette_edges(tbl, pose, stems, **kw)
        if reuse is not None:
            reuse[sid] = (radius, e)
        parts.append(e.assign(scan=sid))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=EDGE_COLUMNS)


def _respliced(before: pd.DataFrame, moved: np.ndarray, fresh: pd.DataFrame) -> pd.DataFrame | None:
    """One scan's edges after only the stems ``moved`` changed radius: ``before``'s rows of the
    others and ``fresh`` (the moved stems' own), in :func:`silhouette_edges`' order (side, stem,
    line: one edge each). None where neither has a row (an empty table's column types differ:
    the caller finds them all)."""
    kept = before[~moved[before["tree"].to_numpy(int)]] if len(before) else before
    if len(kept) and len(fresh):
        both = pd.concat([kept, fresh], ignore_index=True)
        return both.sort_values(["side", "tree", "row"], kind="stable", ignore_index=True)
    if len(fresh):
        return fresh
    return kept.reset_index(drop=True) if len(kept) else None
