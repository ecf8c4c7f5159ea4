"""The ground elevation model as files (spec 9): ``elevation.npz`` (``z, x0, y0, cell_m, mode``) and
a
quick ``elevation.png`` of the grid with scan positions and trees, both written atomically."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from forestmap_assets.core.features.elevation import ElevationGrid


def _atomic_write(path: str | os.PathLike, write) -> Path:
    """Call ``write(file)`` on a temporary file next to ``path``, then ``os.replace`` it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def save_elevation_npz(path: str | os.PathLike, grid: ElevationGrid) -> Path:
    """Write ``z, x0, y0, cell_m, mode`` to an ``.npz`` file atomically."""
    return _atomic_write(
        path,
        lambda fh: np.savez_compressed(
            fh,
            z=grid.z,
            x0=np.float64(grid.x0),
            y0=np.float64(grid.y0),
            cell_m=np.float64(grid.cell_m),
            mode=np.str_(grid.mode),
        ),
    )


def load_elevation_npz(path: str | os.PathLike) -> ElevationGrid:
    """Read a grid written by :func:`save_elevation_npz`."""
    with np.load(path, allow_pickle=False) as f:
        return ElevationGrid(
            z=f["z"].astype(np.float64),
            x0=float(f["x0"]),
            y0=float(f["y0"]),
            cell_m=float(f["cell_m"]),
            mode=str(f["mode"]),  # type: ignore[arg-type]
        )


def _xy(table) -> np.ndarray:
    if isinstance(table, pd.DataFrame):
        return table[["x", "y"]].to_numpy(dtype=np.float64)
    return np.asarray(table, dtype=np.float64).reshape(-1, np.shape(table)[-1])[:, :2]


def elevation_png(
    path: str | os.PathLike,
    grid: ElevationGrid,
    title: str,
    scan_positions: pd.DataFrame | np.ndarray | None = None,
    trees: pd.DataFrame | np.ndarray | None = None,
    *,
    dpi: int = 120,
) -> Path:
    """Picture of an elevation grid (spec 9, Figs 6.4, 6.7, 6.11): colour = elevation with a
    labelled colour bar in metres, axes in metres, equal aspect; optional scan positions
    (table with ``x, y`` and optional ``scan`` labels, or an (n, 2+) array) and tree markers
    (``x, y``). Written atomically (temporary file + ``os.replace``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.0, 6.0))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if grid.z.size:
        im = ax.imshow(
            np.ma.masked_invalid(grid.z),
            origin="lower",
            extent=grid.extent,
            cmap="terrain",
            interpolation="nearest",
        )
        cbar = fig.colorbar(im, ax=ax, shrink=0.85)
        cbar.set_label(f"elevation (m), {grid.mode} hit per {grid.cell_m:g} m cell")
    if trees is not None and len(trees):
        t = _xy(trees)
        ax.scatter(
            t[:, 0],
            t[:, 1],
            s=12,
            marker="^",
            facecolors="none",
            edgecolors="darkgreen",
            linewidths=0.8,
            label="trees",
        )
    if scan_positions is not None and len(scan_positions):
        s = _xy(scan_positions)
        ax.scatter(s[:, 0], s[:, 1], s=40, marker="o", c="red", edgecolors="black", label="scans")
        if isinstance(scan_positions, pd.DataFrame) and "scan" in scan_positions:
            for (x, y), name in zip(s, scan_positions["scan"].astype(str), strict=True):
                ax.annotate(name, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=8)
    if (trees is not None and len(trees)) or (scan_positions is not None and len(scan_positions)):
        ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    fig.tight_layout()
    return _atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=dpi, pil_kwargs={"compress_level": 2}))
