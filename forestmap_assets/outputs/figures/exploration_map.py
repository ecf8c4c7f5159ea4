"""Picture of a next-vantage plan (Men 2012 ch. 6; men_spec 7): elevation map, unmapped / obstacle
cells, stems,
scan positions, frontier, the ranked proposals and the walking paths to them (a matplotlib
Figure)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.exploration.candidates import VantagePlan
from forestmap_assets.core.exploration.frontier import OBSTACLE, UNMAPPED
from forestmap_assets.core.features.elevation import ElevationGrid


# ---- picture ---------------------------------------------------------------------------------
def exploration_figure(
    plan: VantagePlan,
    elevation: ElevationGrid | None = None,
    stems: np.ndarray | None = None,
    scans: pd.DataFrame | None = None,
    *,
    title: str = "next vantage positions",
    n_show: int = 5,
):
    """Picture: elevation map, unmapped / obstacle cells, stems, scan positions, frontier,
    proposals (numbered by rank) and the walking paths to them (a matplotlib Figure)."""
    from matplotlib.collections import PatchCollection
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    grid = plan.grid
    fig = Figure(figsize=(8.0, 7.0))
    ax = fig.add_subplot(1, 1, 1)
    if elevation is not None and elevation.z.size and np.isfinite(elevation.z).any():
        # colours span the local ground of the plot (lowest hits in the canopy are clipped)
        if grid.ground_z is not None:
            lo, hi = (
                np.nanpercentile(grid.ground_z[grid.in_plot], [0.5, 99.5])
                if grid.in_plot.any()
                else (0, 1)
            )
            hi += max(0.5, 0.2 * (hi - lo))
        else:
            lo, hi = np.nanpercentile(elevation.z, [1, 90])
        im = ax.imshow(
            np.ma.masked_invalid(elevation.z),
            origin="lower",
            extent=elevation.extent,
            cmap="terrain",
            interpolation="nearest",
            alpha=0.9,
            vmin=lo,
            vmax=hi,
        )
        fig.colorbar(im, ax=ax, shrink=0.8, label="lowest hit (m)", extend="max")
    cls = np.where(grid.in_plot, plan.classes, 255).T
    overlay = np.ma.masked_where((cls != UNMAPPED) & (cls != OBSTACLE), cls)
    ax.imshow(
        overlay,
        origin="lower",
        extent=grid.extent,
        interpolation="nearest",
        cmap=ListedColormap(["#d9d9d9", "#d9d9d9", "#404040"]),
        vmin=0,
        vmax=2,
        alpha=0.75,
    )
    x0, x1, y0, y1 = grid.extent
    if grid.polygon is not None:
        poly = np.vstack([grid.polygon, grid.polygon[:1]])
        ax.plot(poly[:, 0], poly[:, 1], color="black", lw=0.8, label="plot")
    fr = np.argwhere(plan.frontier)
    if len(fr):
        fxy = grid.cell_xy(fr[:, 0], fr[:, 1])
        ax.scatter(
            fxy[:, 0], fxy[:, 1], s=1.5, c="orange", marker="s", linewidths=0, label="frontier"
        )
    if stems is not None and len(stems):
        st = np.asarray(stems, dtype=np.float64).reshape(-1, 3)
        discs = [Circle((x, y), r) for x, y, r in st]  # one collection: a patch each took 0.7 s
        ax.add_collection(PatchCollection(discs, facecolor="saddlebrown", edgecolor="none"))
        ax.scatter(
            st[:, 0],
            st[:, 1],
            s=14,
            marker="o",
            facecolors="none",
            edgecolors="saddlebrown",
            linewidths=0.9,
            label="stems",
        )
    for rank, path in sorted(plan.paths.items())[:n_show]:
        ax.plot(
            path[:, 0],
            path[:, 1],
            color="blue" if rank == 1 else "steelblue",
            lw=1.6 if rank == 1 else 0.8,
            alpha=0.9 if rank == 1 else 0.6,
        )
    top = plan.proposals.head(n_show)
    if len(top):
        ax.scatter(
            top["x"],
            top["y"],
            s=90,
            marker="*",
            c=np.where(top["feasible"], "blue", "red"),
            edgecolors="white",
            linewidths=0.6,
            zorder=5,
            label="proposals",
        )
        for r in top.itertuples():
            ax.annotate(
                str(r.rank),
                (r.x, r.y),
                xytext=(5, 5),
                textcoords="offset points",
                fontsize=8,
                color="navy",
                weight="bold",
            )
    if scans is not None and len(scans):
        ax.scatter(
            scans["x"], scans["y"], s=45, c="red", edgecolors="black", zorder=6, label="scans"
        )
        if "scan" in scans:
            for r in scans.itertuples():
                ax.annotate(
                    str(r.scan),
                    (r.x, r.y),
                    xytext=(5, -11),
                    textcoords="offset points",
                    fontsize=8,
                    weight="bold",
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.7},
                )
    cov = plan.coverage
    ax.set_title(
        f"{title}\ncoverage {100 * cov['coverage']:.1f} % of the plot, "
        f"{int(plan.frontier.sum())} frontier cells",
        fontsize=10,
    )
    ax.set_xlim(x0 - 1, x1 + 1)
    ax.set_ylim(y0 - 1, y1 + 1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="upper right", fontsize=7, markerscale=1.0)
    fig.tight_layout()
    return fig
