"""The registered point cloud of a campaign (exports beyond DESIGN.md section 4).

Every registered scan's levelled points are placed in the global frame with the scan's optimal
map pose (spec 6.1 convention ``p' = R_z(heading) p + t``) and thinned on one voxel grid of the
user's spacing. Each voxel keeps one measured point, the one nearest the centroid of the voxel's
points (men spec 3.2: a real return, not an average, so intensity and colour stay those of a
measurement), with the index of the scan it came from.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pandas as pd

from forestmap_assets.core._cloud_kernels import placed_points

CLOUD_COLUMNS = ["x", "y", "z", "scan"]
EXTRA_COLUMNS = ("intensity", "r", "g", "b")  # kept where every scan has them
MAX_THREADS = 4  # scans thinned at once by default (about 0.15 GB of temporaries each, 2.4 M points)


def voxel_keep(xyz: np.ndarray, spacing_m: float) -> np.ndarray:
    """Indices (sorted) of one measured point per occupied ``spacing_m`` voxel of the grid
    anchored at the origin of the frame (so that thinning scan by scan and then the union use
    the same voxels): :func:`~forestmap_assets.core.cloud.voxel_subsample`, the point nearest the
    centroid of its voxel (men spec 3.2). ``spacing_m <= 0`` keeps every finite point."""
    from forestmap_assets.core._cloud_kernels import finite_rows
    from forestmap_assets.core.cloud import voxel_subsample

    xyz = np.ascontiguousarray(xyz, dtype=np.float64).reshape(-1, 3)
    finite = finite_rows(xyz)
    if spacing_m <= 0 or finite.size == 0:
        return finite
    if finite.size < len(xyz):
        return finite[voxel_subsample(xyz[finite], spacing_m, origin=(0.0, 0.0, 0.0))]
    return voxel_subsample(xyz, spacing_m, origin=(0.0, 0.0, 0.0))


def registered_cloud(
    scans: Mapping[str, pd.DataFrame],
    poses: pd.DataFrame,
    spacing_m: float,
    scan_ids: list[str] | None = None,
    threads: int | None = None,
) -> pd.DataFrame:
    """Points of every registered scan in the global frame, thinned to ``spacing_m``.

    ``scans`` maps scan id to a table with levelled ``x, y, z`` and optional ``intensity``,
    ``r, g, b``; ``poses`` is the optimal map's pose table (``scan, x, y, z, heading_deg,
    registered``). Returns ``x, y, z, scan`` (index into ``scan_ids``, default the order of
    ``scans``) plus whichever of ``intensity, r, g, b`` every scan has. Each scan is thinned
    on the global grid first (bounded memory), then the union once more. The scans are thinned
    in ``threads`` threads (default: one a core, at most ``MAX_THREADS`` and one a scan, each
    holding one scan's temporary arrays; the kernels release the GIL): the same cloud, a rendered
    survey's 14 M points 3.6 -> 1.2-1.3 s on 2 cores."""
    scan_ids = list(scan_ids) if scan_ids is not None else list(scans)
    reg = poses["registered"]
    if reg.dtype != bool:
        reg = reg.astype(str).str.lower().isin(["true", "1"])
    placed = poses[reg.to_numpy(bool)].set_index("scan")
    todo = [(sid, t) for sid, t in scans.items() if sid in placed.index and t is not None and len(t)]
    extras = None
    for _, table in todo:
        cols = [c for c in EXTRA_COLUMNS if c in table]
        extras = cols if extras is None else [c for c in extras if c in cols]

    def thin(item: tuple[str, pd.DataFrame]) -> pd.DataFrame:
        sid, table = item
        pose = placed.loc[sid, ["x", "y", "z", "heading_deg"]].to_numpy(float)
        xyz = placed_points(*(table[c].to_numpy() for c in "xyz"), pose)
        keep = voxel_keep(xyz, spacing_m)
        part = {"x": xyz[keep, 0], "y": xyz[keep, 1], "z": xyz[keep, 2],
                "scan": np.full(len(keep), scan_ids.index(sid), dtype=np.uint16)}
        part.update({c: table[c].to_numpy()[keep] for c in extras})
        return pd.DataFrame(part)

    n = max(1, min(len(todo), threads or min(os.cpu_count() or 1, MAX_THREADS)))
    if n > 1:
        with ThreadPoolExecutor(n) as pool:
            parts = list(pool.map(thin, todo))
    else:
        parts = [thin(item) for item in todo]
    if not parts:
        return pd.DataFrame(
            {c: pd.Series(dtype="float64" if c != "scan" else "uint16") for c in CLOUD_COLUMNS}
        )
    cloud = pd.concat(parts, ignore_index=True)
    if len(parts) > 1:
        cloud = cloud.iloc[voxel_keep(cloud[["x", "y", "z"]].to_numpy(), spacing_m)].reset_index(
            drop=True
        )
    return cloud
