"""Pictures of one pair registration: the connected score cloud accumulated onto the xy plane at
each cell
size with peak and cloud centre +- sigma (JP Fig. 9, eq. (6) / thesis Fig. 5.7, spec 6.5), and the
two
sub-maps before and after registration."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from forestmap_assets.outputs.figures.common import colour_map, new_figure

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def _level_components(cells: pd.DataFrame) -> np.ndarray:
    """Labels of the 80-connected components of one level's surviving cells (spec 6.5)."""
    from forestmap_assets.core.registration.cell_clouds import lattice_components

    size = cells[["cell_x_m", "cell_y_m", "cell_z_m", "cell_heading_deg"]].iloc[0].to_numpy(float)
    pose = cells[["dx", "dy", "dz", "dh_deg"]].to_numpy(float).copy()
    pose[:, 3] = np.mod(pose[:, 3] - pose[0, 3] + 180.0, 360.0) - 180.0
    idx = np.rint((pose - pose.min(axis=0)) / np.where(size > 0, size, 1.0)).astype(np.int64)
    n = idx.max(axis=0) + 1
    wrap = size[3] * n[3] >= 360.0 - 1e-6
    _, labels = lattice_components(idx, n, wrap)
    return labels


def score_snapshots(levels: pd.DataFrame, n: int = 6) -> list[int]:
    """Levels to show: for each xy cell size, the last level at that size; the ``n`` finest."""
    if len(levels) == 0:
        return []
    per = (
        levels.groupby("level").agg(xy=("cell_x_m", "first"), y=("cell_y_m", "first")).reset_index()
    )
    per["xy"] = np.maximum(per["xy"], per["y"])
    last = per.groupby("xy")["level"].max().sort_index(ascending=False)
    return [int(v) for v in last.to_numpy()[-n:]]


def cloud_weights(scores: np.ndarray, floor: float | None, weight: str = "linear") -> np.ndarray:
    """Cell weights of JP eq. (6): ``score - floor`` (linear, floor = n ln k1) or
    ``exp(score - max)`` (spec 6.5, inferred options). Cells of coarse levels that were only
    bounded (NaN score) get a token weight so that the cloud's extent stays visible."""
    s = np.asarray(scores, dtype=float)
    ok = np.isfinite(s)
    if not ok.any():
        return np.ones_like(s)
    if weight == "exp":
        w = np.exp(s - s[ok].max())
    else:
        base = floor if floor is not None and np.isfinite(floor) else s[ok].min() - 1.0
        w = np.maximum(s - base, 0.0)
    # a surviving cell whose score was not evaluated (bounded only) keeps a token weight
    return np.where(ok, w, 1e-3 * np.nanmax(w[ok]) if np.nanmax(w[ok]) > 0 else 1.0)


def score_cloud_evolution(
    levels: pd.DataFrame,
    registration: pd.Series | dict,
    *,
    floor: float | None = None,
    weight: str = "linear",
    a_priori: Sequence[float] | None = None,
    half_widths: Sequence[float] | None = None,
    truth: Sequence[float] | None = None,
    hypotheses: pd.DataFrame | None = None,
    n_panels: int = 8,
    connected: bool = True,
    title: str = "",
) -> Figure:
    """JP Fig. 9 / thesis Fig. 5.7: the score distribution of one pair at each search cell size,
    accumulated onto the (dx, dy) plane over z and heading. ``levels`` holds the surviving
    cells of every level of this pair (``pairwise_registrations["levels"]``); with ``connected``
    only the connected cloud around the best cell is drawn (as in JP Fig. 9). Marks: the best
    cell (plain cross), the cloud centre with its sample sigma (ended cross hair), the a priori
    (circle), the truth when given (star), secondary hypotheses (x). The last panel is a zoom
    on the final cloud. Axes: x to the right, y up (JP Fig. 9 has x up, y to the left)."""
    reg = dict(registration)
    snaps = score_snapshots(levels, n_panels)
    ncols = 3 if len(snaps) + 1 > 4 else max(len(snaps) + 1, 1)
    nrows = int(np.ceil((len(snaps) + 1) / ncols))
    fig = new_figure(4.2 * ncols, 3.9 * nrows + 0.4)
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False).ravel())
    centre = np.asarray(
        a_priori if a_priori is not None else (reg.get("dx"), reg.get("dy"), 0, 0), dtype=float
    )
    clouds = {}
    for lvl in snaps:
        cells = levels[levels["level"] == lvl].reset_index(drop=True)
        if connected and len(cells) > 1:
            labels = _level_components(cells)
            cells = cells[labels == labels[_best(cells)]].reset_index(drop=True)
        clouds[lvl] = cells
    window = _cloud_window(clouds[snaps[0]] if snaps else None, centre, truth, half_widths)
    cmap = colour_map("magma")
    final_cells = None
    for k, lvl in enumerate(snaps):
        ax = axes[k]
        cells = clouds[lvl]
        w = cloud_weights(cells["score"].to_numpy(), floor, weight)
        size_x, size_y = float(cells["cell_x_m"].iloc[0]), float(cells["cell_y_m"].iloc[0])
        img, ext = _accumulate(
            cells["dx"].to_numpy(), cells["dy"].to_numpy(), w, size_x, size_y, window
        )
        ax.set_facecolor("black")
        ax.imshow(
            np.ma.masked_less_equal(img, 0),
            origin="lower",
            extent=ext,
            cmap=cmap,
            interpolation="nearest",
            aspect="equal",
        )
        _marks(ax, cells, w, reg, centre, truth, show_cloud=True)
        ax.set_xlim(window[0], window[1])
        ax.set_ylim(window[2], window[3])
        ax.set_title(
            f"cell {size_x:.3g} x {size_y:.3g} m, "
            f"{float(cells['cell_heading_deg'].iloc[0]):.3g} deg: "
            f"{len(cells)} cells",
            fontsize=9,
        )
        final_cells = cells
    ax = axes[len(snaps)]
    if final_cells is not None and len(final_cells):
        w = cloud_weights(final_cells["score"].to_numpy(), floor, weight)
        size_x, size_y = (
            float(final_cells["cell_x_m"].iloc[0]),
            float(final_cells["cell_y_m"].iloc[0]),
        )
        sd = np.nan_to_num([float(reg.get("sd_x", 0) or 0), float(reg.get("sd_y", 0) or 0)])
        half = max(6 * size_x, 4 * float(np.max(sd)), 0.1)
        cx, cy = float(reg.get("dx", centre[0])), float(reg.get("dy", centre[1]))
        zoom = (cx - half, cx + half, cy - half, cy + half)
        img, ext = _accumulate(
            final_cells["dx"].to_numpy(), final_cells["dy"].to_numpy(), w, size_x, size_y, zoom
        )
        ax.set_facecolor("black")
        im = ax.imshow(
            np.ma.masked_less_equal(img, 0),
            origin="lower",
            extent=ext,
            cmap=cmap,
            interpolation="nearest",
            aspect="equal",
        )
        _marks(ax, final_cells, w, reg, centre, truth, show_cloud=True)
        if hypotheses is not None and len(hypotheses):
            ax.plot(
                hypotheses["peak_dx"],
                hypotheses["peak_dy"],
                "x",
                color="cyan",
                ms=8,
                label="other hypotheses",
            )
        ax.set_xlim(zoom[0], zoom[1])
        ax.set_ylim(zoom[2], zoom[3])
        cb = fig.colorbar(im, ax=ax, fraction=0.045, pad=0.02)
        cb.set_label(
            "accumulated weight (score - floor)"
            if weight == "linear"
            else "accumulated exp(score - best)",
            fontsize=8,
        )
        ax.set_title("final cloud, zoomed", fontsize=9)
        handles, labels = ax.get_legend_handles_labels()
        if handles:
            ax.legend(fontsize=7, loc="upper right", framealpha=0.8)
    for extra in axes[len(snaps) + 1 :]:
        extra.set_visible(False)
    for ax in axes[: len(snaps) + 1]:
        ax.set_xlabel("dx (m)")
        ax.set_ylabel("dy (m)")
    if hypotheses is not None and len(hypotheses) and len(snaps):
        for ax in axes[: len(snaps)]:
            ax.plot(hypotheses["peak_dx"], hypotheses["peak_dy"], "x", color="cyan", ms=7)
    fig.suptitle(
        title
        or f"score cloud of pair {reg.get('scan', '?')}{reg.get('reference', '?')} "
        "over the search levels"
    )
    return fig


def _cloud_window(
    cells: pd.DataFrame | None, centre, truth, half_widths
) -> tuple[float, float, float, float]:
    """Square xy window holding the coarsest shown cloud, the a priori and the truth, within
    the search box when it is known (inferred: the thesis always shows the whole 10 m box, but
    an exact bound prunes most of it before the 0.64 m level, leaving a cloud too small to see)."""
    xs, ys = [centre[0]], [centre[1]]
    if cells is not None and len(cells):
        sx, sy = float(cells["cell_x_m"].iloc[0]), float(cells["cell_y_m"].iloc[0])
        xs += [cells["dx"].min() - sx, cells["dx"].max() + sx]
        ys += [cells["dy"].min() - sy, cells["dy"].max() + sy]
    if truth is not None:
        xs.append(truth[0])
        ys.append(truth[1])
    cx, cy = (min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2
    half = 0.55 * max(max(xs) - min(xs), max(ys) - min(ys), 0.2)
    if half_widths is not None:
        half = min(half, max(float(half_widths[0]), float(half_widths[1])))
    return (cx - half, cx + half, cy - half, cy + half)


def _accumulate(x, y, w, size_x, size_y, window):
    """Sum of weights per (dx, dy) cell of the level's grid over ``window`` (for imshow)."""
    nx = max(1, int(np.ceil((window[1] - window[0]) / size_x)))
    ny = max(1, int(np.ceil((window[3] - window[2]) / size_y)))
    nx, ny = min(nx, 2000), min(ny, 2000)
    img, xe, ye = np.histogram2d(
        x,
        y,
        bins=(nx, ny),
        range=((window[0], window[0] + nx * size_x), (window[2], window[2] + ny * size_y)),
        weights=w,
    )
    return img.T, (xe[0], xe[-1], ye[0], ye[-1])


def _best(cells: pd.DataFrame) -> int:
    s = cells["score"].to_numpy(float)
    return (
        int(np.nanargmax(s))
        if np.isfinite(s).any()
        else int(np.nanargmax(cells["bound"].to_numpy(float)))
    )


def _marks(ax, cells, w, reg, centre, truth, *, show_cloud: bool) -> None:
    best = cells.iloc[_best(cells)]
    ax.plot(best["dx"], best["dy"], "+", color="cyan", ms=11, mew=1.5, label="highest score")
    if show_cloud and w.sum() > 0:
        mx = float(np.average(cells["dx"], weights=w))
        my = float(np.average(cells["dy"], weights=w))
        sx = float(np.sqrt(np.average((cells["dx"] - mx) ** 2, weights=w)))
        sy = float(np.sqrt(np.average((cells["dy"] - my) ** 2, weights=w)))
        ax.errorbar(
            [mx],
            [my],
            xerr=[sx],
            yerr=[sy],
            fmt="none",
            ecolor="white",
            elinewidth=1.2,
            capsize=4,
            label="cloud centre +- sigma",
        )
    ax.plot(centre[0], centre[1], "o", mfc="none", mec="#66ccff", ms=8, label="a priori")
    if truth is not None:
        ax.plot(
            truth[0], truth[1], "*", color="#7CFC00", ms=10, mec="black", mew=0.5, label="truth"
        )


def submap_overlay(
    reference: pd.DataFrame,
    scan: pd.DataFrame,
    poses: dict[str, Sequence[float]],
    *,
    names: tuple[str, str] = ("scan", "reference"),
    title: str = "",
) -> Figure:
    """Top view of two sub-maps (registration points, spec 6.2): the reference in grey and the
    scan placed in the reference frame by each of ``poses`` (label -> dx, dy, dz, dheading_deg),
    one panel per pose (e.g. the a priori and the registration result)."""
    from forestmap_assets.core.geometry import transform_points

    fig = new_figure(5.2 * max(len(poses), 1), 5.0)
    axes = np.atleast_1d(
        fig.subplots(1, max(len(poses), 1), sharex=True, sharey=True, squeeze=False).ravel()
    )
    ref = reference[["x", "y"]].to_numpy(float)
    pts = scan[["x", "y", "z"]].to_numpy(float)
    for ax, (label, pose) in zip(axes, poses.items(), strict=False):
        moved = transform_points(pts, pose)
        ax.plot(ref[:, 0], ref[:, 1], ".", ms=2, color="0.55", label=f"{names[1]} (reference)")
        ax.plot(
            moved[:, 0],
            moved[:, 1],
            ".",
            ms=2,
            color="#d62728",
            label=f"{names[0]} placed by {label}",
        )
        ax.plot(0, 0, "k^", ms=8)
        ax.plot(pose[0], pose[1], "^", color="#d62728", mec="black", ms=8)
        ax.set_aspect("equal")
        ax.set_xlabel(f"x (m), frame of {names[1]}")
        ax.set_title(
            f"{label}: ({pose[0]:.2f}, {pose[1]:.2f}, {pose[2]:.2f} m, {pose[3]:.1f} deg)",
            fontsize=9,
        )
        ax.legend(fontsize=7, loc="upper right", markerscale=4)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("y (m)")
    if title:
        fig.suptitle(title)
    return fig
