"""The merged lowest-hit elevation map (JP Fig. 11 / thesis Fig. 6.11) with scan frames (larger axis
symbol
at the reference scan) and trees, and its crop / spike-removal / colour-limit helpers shared with
the 3-D render."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from forestmap_assets.outputs.figures.common import (
    ELEVATION_CMAP,
    NO_VALUE,
    _registered,
    new_figure,
    scan_frames,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def crop_box(
    grid,
    poses: pd.DataFrame | None = None,
    trees: pd.DataFrame | None = None,
    margin_m: float = 6.0,
) -> tuple[float, float, float, float]:
    """xy box of the scan positions and trees plus ``margin_m`` (inferred: the map around the
    surveyed plot; the far field holds only sparse ground rings), within the grid's extent."""
    xs, ys = [], []
    for df in (poses, trees):
        if df is not None and len(df):
            xs.append(df["x"].to_numpy(float))
            ys.append(df["y"].to_numpy(float))
    ext = grid.extent
    if not xs:
        return ext
    x, y = np.concatenate(xs), np.concatenate(ys)
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        return ext
    x, y = x[ok], y[ok]
    return (
        max(ext[0], x.min() - margin_m),
        min(ext[1], x.max() + margin_m),
        max(ext[2], y.min() - margin_m),
        min(ext[3], y.max() + margin_m),
    )


def crop_grid(grid, box: tuple[float, float, float, float]):
    """The part of an :class:`~forestmap_assets.core.features.elevation.ElevationGrid` inside ``box``."""
    from forestmap_assets.core.features.elevation import ElevationGrid

    ny, nx = grid.z.shape
    i0 = int(np.clip(np.floor((box[0] - grid.x0) / grid.cell_m), 0, nx))
    i1 = int(np.clip(np.ceil((box[1] - grid.x0) / grid.cell_m), i0, nx))
    j0 = int(np.clip(np.floor((box[2] - grid.y0) / grid.cell_m), 0, ny))
    j1 = int(np.clip(np.ceil((box[3] - grid.y0) / grid.cell_m), j0, ny))
    return ElevationGrid(
        grid.z[j0:j1, i0:i1],
        grid.x0 + i0 * grid.cell_m,
        grid.y0 + j0 * grid.cell_m,
        grid.cell_m,
        grid.mode,
    )


def colour_limits(
    values: np.ndarray, percentiles: tuple[float, float] = (1.0, 99.0)
) -> tuple[float, float]:
    """Robust colour limits (inferred): branch hits make a few cells metres too high (JP Fig. 12
    caption), so the scale spans the given percentiles; the colour bar is extended."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(v, percentiles)
    return float(lo), float(hi if hi > lo else lo + 0.1)


def remove_spikes(grid, spike_m: float | None = 1.0, window: int = 7, percentile: float = 25.0):
    """A copy of ``grid`` without spikes (inferred; the thesis draws them, JP Fig. 12 caption):
    where the ground is occluded the lowest hit is a branch, metres above the ground. A cell
    more than ``spike_m`` above the ``percentile`` of its ``window`` x ``window`` neighbourhood
    loses its value. ``spike_m=None`` keeps every cell."""
    from numpy.lib.stride_tricks import sliding_window_view

    from forestmap_assets.core.features.elevation import ElevationGrid

    z = grid.z
    if spike_m is None or z.size == 0:
        return grid
    h = window // 2
    padded = np.pad(z, h, constant_values=np.nan)
    windows = np.sort(sliding_window_view(padded, (window, window)).reshape(z.shape + (-1,)), axis=-1)
    # np.nanpercentile (linear) on every window at once: NaNs sort last, n finite values each
    n = np.isfinite(windows).sum(axis=-1)
    pos = np.maximum(n - 1, 0) * (percentile / 100.0)
    below = np.floor(pos).astype(int)
    above = np.minimum(below + 1, np.maximum(n - 1, 0))
    v0 = np.take_along_axis(windows, below[..., None], -1)[..., 0]
    v1 = np.take_along_axis(windows, above[..., None], -1)[..., 0]
    low = np.where(n > 0, v0 + (v1 - v0) * (pos - below), np.nan)
    with np.errstate(invalid="ignore"):
        spikes = np.isfinite(z) & (z > low + spike_m)
    return ElevationGrid(np.where(spikes, np.nan, z), grid.x0, grid.y0, grid.cell_m, grid.mode)


def ground_limits(
    grid,
    percentiles: tuple[float, float] = (1.0, 99.0),
    render_cell_m: float = 0.6,
    n_lowest: int = 5,
    spike_m: float | None = 1.0,
) -> tuple[float, float]:
    """Colour limits of the ground (inferred): percentiles of the 0.6 m rendering grid
    (mean of the 5 lowest 0.1 m cells, spec 9) without spikes (:func:`remove_spikes`), which
    leaves out the branch hits that make some cells metres too high (JP Fig. 12 caption)."""
    from forestmap_assets.core.features.elevation import render_grid

    coarse = (
        remove_spikes(render_grid(grid, render_cell_m, n_lowest), spike_m) if grid.z.size else grid
    )
    return colour_limits(
        coarse.z if coarse.z.size and np.isfinite(coarse.z).any() else grid.z, percentiles
    )


def elevation_figure(
    grid,
    poses: pd.DataFrame | None = None,
    trees: pd.DataFrame | None = None,
    *,
    title: str = "",
    crop: bool = True,
    margin_m: float = 6.0,
    percentiles: tuple[float, float] = (1.0, 99.0),
    reference: str | None = None,
) -> Figure:
    """JP Fig. 11 / thesis Fig. 6.11: the merged elevation grid (lowest hit per cell), no-value
    cells grey (black in the thesis, but the darkest ground is nearly black here), the colour
    scale labelled in metres over robust limits (:func:`ground_limits`), scan positions as xy
    axis symbols (larger at the reference scan), trees as circles sized by DBH (x 5). With
    ``crop`` the map is cut to the scans and trees plus ``margin_m``."""
    fig = new_figure(7.6, 6.6)
    ax = fig.subplots()
    placed = _registered(poses) if poses is not None and len(poses) else None
    g = crop_grid(grid, crop_box(grid, placed, trees, margin_m)) if crop and grid.z.size else grid
    ax.set_facecolor(NO_VALUE)
    if g.z.size and np.isfinite(g.z).any():
        lo, hi = ground_limits(g, percentiles)
        im = ax.imshow(
            np.ma.masked_invalid(g.z),
            origin="lower",
            extent=g.extent,
            cmap=ELEVATION_CMAP,
            vmin=lo,
            vmax=hi,
            interpolation="nearest",
        )
        cb = fig.colorbar(im, ax=ax, shrink=0.9, extend="both")
        cb.set_label(f"ground elevation z (m), {g.mode} hit per {g.cell_m:g} m cell")
    if trees is not None and len(trees):
        from matplotlib.collections import EllipseCollection

        d = (
            trees["dbh_m"]
            .fillna(trees["dbh_m"].median() if trees["dbh_m"].notna().any() else 0.2)
            .to_numpy(float)
        )
        ax.add_collection(
            EllipseCollection(
                5 * d,
                5 * d,
                0,
                units="xy",
                offsets=trees[["x", "y"]].to_numpy(float),
                offset_transform=ax.transData,
                facecolors="none",
                edgecolors="#ff7f0e",
                linewidths=1.2,
                label="trees (DBH x 5)",
            )
        )
    if placed is not None and len(placed):
        span = max(g.extent[1] - g.extent[0], g.extent[3] - g.extent[2], 1.0)
        ref = reference if reference is not None else str(poses["scan"].iloc[0])
        scan_frames(ax, placed, 0.035 * span, ref)
    ax.set_xlim(g.extent[0], g.extent[1])
    ax.set_ylim(g.extent[2], g.extent[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    from matplotlib.lines import Line2D

    handles = [
        Line2D([], [], color="#d62728", lw=2, label="scan x axis"),
        Line2D([], [], color="#2ca02c", lw=2, label="scan y axis"),
    ]
    if trees is not None and len(trees):
        handles.append(
            Line2D([], [], marker="o", ls="none", mfc="none", mec="#ff7f0e", label="tree (DBH x 5)")
        )
    handles.append(
        Line2D([], [], marker="s", ls="none", mfc=NO_VALUE, mec="black", label="no elevation value")
    )
    ax.legend(handles=handles, fontsize=8, loc="upper right", framealpha=0.85)
    ax.set_title(title or "merged ground elevation map")
    return fig
