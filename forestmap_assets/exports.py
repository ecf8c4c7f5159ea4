"""The files ``forestmap run`` writes (DESIGN.md section 4), read from the asset store.

Every file is written under a temporary name and renamed into place.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from .access import load_asset
from .campaign import Campaign

POSES_COLUMNS = ["scan", "x", "y", "z", "heading_deg", "sd_x", "sd_y", "sd_z", "sd_heading_deg", "registered"]
REGISTRATION_COLUMNS = [
    "scan", "reference", "dx", "dy", "dz", "dheading_deg", "sd_x", "sd_y", "sd_z", "sd_heading_deg",
    "peak_dx", "peak_dy", "peak_dz", "peak_dheading_deg", "log_score", "n_points", "seconds", "status", "reason",
]
RESIDUAL_COLUMNS = ["scan", "reference", "ex", "ey", "ez", "eheading_deg", "rx", "ry", "rz", "rheading", "verdict"]
TREE_COLUMNS = ["tree_id", "x", "y", "z", "dbh_m", "n_scans", "n_cylinders", "visible_length_m"]
CYLINDER_COLUMNS = ["scan", "cylinder_id", "x0", "y0", "z0", "x1", "y1", "z1", "radius_m", "n_circles"]


def atomic_path(path: Path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` then rename ``tmp`` to ``path``; remove ``tmp`` on failure."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def write_csv(df: pd.DataFrame, path: Path, columns: list[str]) -> Path:
    """CSV with exactly ``columns``; booleans as true/false, NaN as empty."""
    out = df.reindex(columns=columns).copy()
    for c in out.columns:
        if out[c].dtype == bool:
            out[c] = out[c].map({True: "true", False: "false"})
    return atomic_path(path, lambda tmp: out.to_csv(tmp, index=False, float_format="%.6g", na_rep=""))


def write_exports(campaign: Campaign, out: str | Path) -> list[Path]:
    """Write every export of DESIGN.md section 4 that the stored assets allow; return paths."""
    from .core.elevation import elevation_png, save_elevation_npz

    out = Path(out)
    written: list[Path] = []
    omap = load_asset("optimal_map", campaign=campaign)
    poses = omap["poses"]
    written.append(write_csv(poses, out / "poses.csv", POSES_COLUMNS))
    regs = load_asset("pairwise_registrations", campaign=campaign)["registrations"]
    written.append(write_csv(regs, out / "registrations.csv", REGISTRATION_COLUMNS))
    residuals = load_asset("residual_checks", campaign=campaign)
    written.append(write_csv(residuals, out / "residuals.csv", RESIDUAL_COLUMNS))
    trees = load_asset("tree_list", campaign=campaign)
    written.append(write_csv(trees, out / "trees.csv", TREE_COLUMNS))
    integrated = load_asset("integrated_map", campaign=campaign)
    cylinders = integrated["cylinders"].reindex(columns=CYLINDER_COLUMNS)
    written.append(atomic_path(out / "cylinders.parquet", lambda tmp: cylinders.to_parquet(tmp, index=False)))
    grid = elevation_from_table(integrated["elevation"])
    written.append(atomic_path(out / "elevation.npz", lambda tmp: save_elevation_npz(tmp, grid)))
    placed = poses[poses["registered"].astype(bool)]
    scan_xy = placed[["x", "y"]].to_numpy(float) if len(placed) else None
    tree_xy = trees[["x", "y"]].to_numpy(float) if len(trees) else None
    written.append(
        atomic_path(
            out / "elevation.png",
            lambda tmp: elevation_png(tmp, grid, f"{campaign.name}: ground elevation (lowest hit)", scan_positions=scan_xy, trees=tree_xy),
        )
    )
    return written


def elevation_to_table(grid) -> pd.DataFrame:
    """A merged elevation grid as a sparse table (ix, iy, z) plus its origin columns."""
    iy, ix = np.nonzero(np.isfinite(grid.z))
    df = pd.DataFrame({"ix": ix.astype(np.int32), "iy": iy.astype(np.int32), "z": grid.z[iy, ix].astype(np.float32)})
    meta = pd.DataFrame({"x0": [grid.x0], "y0": [grid.y0], "cell_m": [grid.cell_m], "nx": [grid.z.shape[1]], "ny": [grid.z.shape[0]]})
    return df.assign(**{k: np.repeat(meta[k].to_numpy(), len(df)) for k in meta}) if len(df) else df.assign(**{k: pd.Series(dtype=meta[k].dtype) for k in meta})


def elevation_from_table(df: pd.DataFrame):
    """Inverse of :func:`elevation_to_table`."""
    from .core.elevation import ElevationGrid

    if df.empty:
        return ElevationGrid(z=np.full((1, 1), np.nan), x0=0.0, y0=0.0, cell_m=0.1)
    nx, ny = int(df["nx"].iloc[0]), int(df["ny"].iloc[0])
    z = np.full((ny, nx), np.nan)
    z[df["iy"].to_numpy(), df["ix"].to_numpy()] = df["z"].to_numpy()
    return ElevationGrid(z=z, x0=float(df["x0"].iloc[0]), y0=float(df["y0"].iloc[0]), cell_m=float(df["cell_m"].iloc[0]))
