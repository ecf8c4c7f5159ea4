"""Pictures of the optimal map: the registration network with pose sigmas, the residual verdicts of
eq. (11) (thesis 6.4, 7.1), and the tree list's DBH distribution."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from forestmap_assets.outputs.figures.common import (
    BARK,
    STATUS_COLOURS,
    _registered,
    new_figure,
    scan_frames,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure

MAX_LINK_LABELS = 40  # more links than this: their labels only hide each other


def network_figure(
    poses: pd.DataFrame,
    registrations: pd.DataFrame | None = None,
    links: pd.DataFrame | None = None,
    *,
    sigma_scale: float | None = None,
    title: str = "",
) -> Figure:
    """The registration network (thesis Fig. 6.10 style): scan frames at their optimal-map
    poses, one line per registered pair: admitted into the map (solid, blue), accepted but not
    admitted (dashed, red), rejected or failed registrations (dotted, grey). Pose sigmas are
    drawn as ellipses (diagonal covariance) magnified by ``sigma_scale`` (default: so that the
    largest is about 4 % of the plot). Each line is labelled with its pair up to
    :data:`MAX_LINK_LABELS` lines."""
    from matplotlib.collections import LineCollection, PatchCollection
    from matplotlib.lines import Line2D
    from matplotlib.patches import Ellipse

    fig = new_figure(9.5, 6.5)
    ax = fig.subplots()
    placed = _registered(poses)
    at = {r.scan: (r.x, r.y) for r in placed.itertuples(index=False)}
    admitted = set()
    if links is not None and len(links) and "status" in links:
        admitted = {
            (r.scan, r.reference) for r in links.itertuples(index=False) if r.status == "admitted"
        }
    if registrations is not None:
        styles = {  # one line collection per style: a line each took a second on 120 links
            "admitted": dict(color=STATUS_COLOURS["admitted"], lw=2.2, ls="-"),
            "accepted": dict(color=STATUS_COLOURS["inconsistent"], lw=1.5, ls="--"),
            "other": dict(color=STATUS_COLOURS["failed"], lw=1.0, ls=":"),
        }
        segments: dict[str, list] = {k: [] for k in styles}
        drawn = [r for r in registrations.itertuples(index=False) if r.scan in at and r.reference in at]
        for r in drawn:
            (x0, y0), (x1, y1) = at[r.scan], at[r.reference]
            kind = ("admitted" if (r.scan, r.reference) in admitted
                    else "accepted" if r.status == "accepted" else "other")
            segments[kind].append([(x0, y0), (x1, y1)])
            if len(drawn) <= MAX_LINK_LABELS:
                label = ax.annotate(
                    f"{r.scan}{r.reference}",
                    ((x0 + x1) / 2, (y0 + y1) / 2),
                    fontsize=7,
                    color=styles[kind]["color"],
                    ha="center",
                    va="center",
                    bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.8),
                )
                label.set_in_layout(False)
        for kind, style in styles.items():
            if segments[kind]:
                ax.add_collection(LineCollection(segments[kind], colors=style["color"],
                                                 linewidths=style["lw"], linestyles=style["ls"],
                                                 zorder=1))
    span = 1.0
    if len(placed):
        span = max(float(np.ptp(placed["x"])), float(np.ptp(placed["y"])), 1.0)
        sd = placed[["sd_x", "sd_y"]].to_numpy(float)
        top = float(np.nanmax(sd)) if np.isfinite(sd).any() else 0.0
        scale = sigma_scale or (0.04 * span / top if top > 0 else 1.0)
        scale = (
            float(10 ** np.floor(np.log10(scale))) if sigma_scale is None and scale > 0 else scale
        )
        ellipses = [
            Ellipse((r.x, r.y), 2 * scale * r.sd_x, 2 * scale * r.sd_y)
            for r in placed.itertuples(index=False)
            if np.isfinite(r.sd_x) and np.isfinite(r.sd_y) and (r.sd_x > 0 or r.sd_y > 0)
        ]
        if ellipses:
            ax.add_collection(PatchCollection(ellipses, facecolor=(0.2, 0.4, 0.9, 0.15),
                                              edgecolor="#1f4e9c", linewidths=1.0, zorder=2))
        reference = str(poses["scan"].iloc[0]) if len(poses) else None
        scan_frames(ax, placed, 0.06 * span, reference)
        handles = [
            Line2D(
                [], [], color=STATUS_COLOURS["admitted"], lw=2.2, label="link in the optimal map"
            ),
            Line2D(
                [],
                [],
                color=STATUS_COLOURS["inconsistent"],
                lw=1.5,
                ls="--",
                label="accepted, not admitted",
            ),
            Line2D(
                [],
                [],
                color=STATUS_COLOURS["failed"],
                lw=1.0,
                ls=":",
                label="rejected / failed registration",
            ),
            Line2D(
                [],
                [],
                color="#1f4e9c",
                marker="o",
                ls="none",
                mfc=(0.2, 0.4, 0.9, 0.15),
                label=f"1-sigma xy ellipse x {scale:g}",
            ),
        ]
        # beside the plot: it never hides a link, and "best" costs a search over every link
        # and ellipse (1.7 s of the report on 50 scans)
        ax.legend(handles=handles, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0),
                  borderaxespad=0.0)
        pad = 0.12 * span
        ax.set_xlim(placed["x"].min() - pad, placed["x"].max() + pad)
        ax.set_ylim(placed["y"].min() - pad, placed["y"].max() + pad)
    missing = [s for s in poses["scan"] if s not in at]
    if missing:
        ax.text(
            0.01,
            0.01,
            "not registered: " + ", ".join(map(str, missing)),
            transform=ax.transAxes,
            color=STATUS_COLOURS["inconsistent"],
            fontsize=9,
        )
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)
    ax.set_title(title or "registration network and pose sigmas")
    return fig


def residual_figure(
    residuals: pd.DataFrame,
    residual_sigmas: float = 3.0,
    z_residual_sigmas: float = 8.0,
    *,
    title: str = "",
) -> Figure:
    """Normalised residuals ``r = e / sigma`` of every admitted observation (eq. 11; thesis
    6.4, 7.1) per component, with the verdict limits (3 sigma x, y, heading; 8 sigma z)."""
    fig = new_figure(max(6.0, 0.55 * len(residuals) + 3), 3.8)
    ax = fig.subplots()
    names = [f"{r.scan}{r.reference}" for r in residuals.itertuples(index=False)]
    x = np.arange(len(residuals))
    comps = (("rx", "x", "o"), ("ry", "y", "s"), ("rz", "z", "^"), ("rheading", "heading", "D"))
    for k, (col, label, marker) in enumerate(comps):
        if col in residuals:
            ax.plot(
                x + (k - 1.5) * 0.12,
                residuals[col].to_numpy(float),
                marker,
                ls="none",
                ms=6,
                label=label,
            )
    for lim, style, label in (
        (residual_sigmas, "--", f"+-{residual_sigmas:g} sigma (x, y, heading)"),
        (z_residual_sigmas, ":", f"+-{z_residual_sigmas:g} sigma (z)"),
    ):
        ax.axhline(lim, color="#c51b1b", ls=style, lw=1, label=label)
        ax.axhline(-lim, color="#c51b1b", ls=style, lw=1)
    if "verdict" in residuals:
        for xi, v in zip(x, residuals["verdict"], strict=True):
            if v != "ok":
                ax.axvspan(xi - 0.45, xi + 0.45, color="#c51b1b", alpha=0.12)
    ax.set_xticks(x, names)
    ax.set_xlabel("observation (scan, reference)")
    ax.set_ylabel("residual / sigma")
    ax.legend(fontsize=8, ncol=3, loc="upper left")
    top = (
        np.nanmax(np.abs(residuals[[c for c, *_ in comps if c in residuals]].to_numpy(float)))
        if len(residuals)
        else 0
    )
    ax.set_ylim(-max(z_residual_sigmas, top) * 1.15, max(z_residual_sigmas, top) * 1.45)
    ax.grid(axis="y", alpha=0.3)
    ax.set_title(title or "residuals of the admitted observations (shaded: inconsistent)")
    return fig


def dbh_histogram(
    trees: pd.DataFrame, truth: pd.DataFrame | None = None, *, bin_cm: float = 2.0, title: str = ""
) -> Figure:
    """DBH distribution of the tree list (cm), optionally against the simulator's truth."""
    fig = new_figure(6.0, 3.6)
    ax = fig.subplots()
    d = 100 * trees["dbh_m"].dropna().to_numpy(float) if len(trees) else np.zeros(0)
    t = (
        100 * truth["dbh_m"].dropna().to_numpy(float)
        if truth is not None and len(truth)
        else np.zeros(0)
    )
    both = np.concatenate([d, t])
    if both.size:
        lo = np.floor(both.min() / bin_cm) * bin_cm
        hi = np.ceil(both.max() / bin_cm) * bin_cm + bin_cm
        bins = np.arange(lo, hi + 1e-9, bin_cm)
        ax.hist(d, bins=bins, color=BARK, alpha=0.85, label=f"measured ({len(d)} trees)")
        if t.size:
            ax.hist(
                t,
                bins=bins,
                histtype="step",
                color="black",
                lw=1.5,
                label=f"truth ({len(t)} trees)",
            )
        ax.legend(fontsize=8, loc="upper right")
    else:
        ax.text(0.5, 0.5, "no tree with a DBH", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("DBH (cm)")
    ax.set_ylabel("trees")
    ax.set_title(title or "diameter at breast height")
    return fig
