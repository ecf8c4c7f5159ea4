"""Circle models over the iterations (thesis 4.6.3, Fig. 4.14; App. B Figs B.12-B.16: the initial
phase
and the converged circles): per-iteration changes of centre, radius and axis, and the best-seen
chain."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from forestmap_assets.outputs.figures.common import new_figure

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def circle_changes(circles: pd.DataFrame) -> pd.DataFrame:
    """Per iteration: valid circles, and the median / 90th percentile change of centre (m),
    radius (m) and axis (deg) of the circles valid in this and the previous iteration."""
    rows = []
    its = sorted(circles["iteration"].unique()) if len(circles) else []
    prev = None
    for it in its:
        cur = circles[circles["iteration"] == it].set_index("segment_id")
        row = {"iteration": int(it), "circles": len(cur), "valid": int(cur["valid"].sum())}
        if prev is not None:
            both = cur.index.intersection(prev.index)
            a, b = cur.loc[both], prev.loc[both]
            ok = (a["valid"].to_numpy(bool)) & (b["valid"].to_numpy(bool))
            a, b = a[ok], b[ok]
            dc = np.linalg.norm(
                a[["cx", "cy", "cz"]].to_numpy() - b[["cx", "cy", "cz"]].to_numpy(), axis=1
            )
            dr = np.abs(a["radius_m"].to_numpy() - b["radius_m"].to_numpy())
            cosang = np.abs(
                np.sum(a[["nx", "ny", "nz"]].to_numpy() * b[["nx", "ny", "nz"]].to_numpy(), axis=1)
            )
            dn = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
            for name, v in (("centre_m", dc), ("radius_m", dr), ("axis_deg", dn)):
                row[f"median_d{name}"] = float(np.median(v)) if len(v) else np.nan
                row[f"p90_d{name}"] = float(np.percentile(v, 90)) if len(v) else np.nan
            row["became_valid"] = int(
                (
                    cur.loc[both, "valid"].to_numpy(bool) & ~prev.loc[both, "valid"].to_numpy(bool)
                ).sum()
            )
            row["became_invalid"] = int(
                (
                    ~cur.loc[both, "valid"].to_numpy(bool) & prev.loc[both, "valid"].to_numpy(bool)
                ).sum()
            )
        rows.append(row)
        prev = cur
    return pd.DataFrame(rows)


def best_chain(circles: pd.DataFrame) -> int | None:
    """The chain with the most valid circles in the last iteration (a well-seen trunk)."""
    if len(circles) == 0:
        return None
    last = circles[
        (circles["iteration"] == circles["iteration"].max()) & circles["valid"].astype(bool)
    ]
    if last.empty:
        return None
    return int(last["chain_id"].value_counts().idxmax())


def circle_convergence(
    circles: pd.DataFrame, chain_id: int | None = None, *, title: str = ""
) -> Figure:
    """Circle models over the iterations (thesis 4.6.3, Fig. 4.14; App. B Figs B.12-B.16):
    (left) valid circles per iteration, (middle) median and 90th-percentile change of centre
    and radius to the previous iteration, (right) radius against height along one trunk
    (``chain_id``, default :func:`best_chain`) in every iteration."""
    fig = new_figure(13.0, 3.8)
    ax0, ax1, ax2 = fig.subplots(1, 3)
    ch = circle_changes(circles)
    if len(ch):
        ax0.bar(ch["iteration"], ch["valid"], color="#4c72b0", label="valid")
        ax0.bar(
            ch["iteration"],
            ch["circles"] - ch["valid"],
            bottom=ch["valid"],
            color="#dddddd",
            label="rejected",
        )
        ax0.set_xticks(ch["iteration"])
        ax0.legend(fontsize=8)
    ax0.set_xlabel("iteration (0 = initial phase)")
    ax0.set_ylabel("circle models")
    ax0.set_title("valid circles", fontsize=10)
    if "median_dcentre_m" in ch:
        sub = ch.dropna(subset=["median_dcentre_m"])
        for col, style, label, colour in (
            ("dcentre_m", "o-", "centre", "#1f77b4"),
            ("dradius_m", "s-", "radius", "#2ca02c"),
        ):
            ax1.plot(
                sub["iteration"],
                1000 * sub[f"median_{col}"],
                style,
                color=colour,
                label=f"median |d {label}|",
            )
            ax1.plot(
                sub["iteration"],
                1000 * sub[f"p90_{col}"],
                style,
                color=colour,
                alpha=0.35,
                mfc="none",
                label=f"90 % |d {label}|",
            )
        ax1.set_yscale("symlog", linthresh=0.1)
        ax1.set_xticks(sub["iteration"])
        ax1.legend(fontsize=8)
    else:
        ax1.text(0.5, 0.5, "one iteration only", ha="center", va="center", transform=ax1.transAxes)
    ax1.set_xlabel("iteration")
    ax1.set_ylabel("change to previous iteration (mm)")
    ax1.set_title("convergence", fontsize=10)
    chain_id = best_chain(circles) if chain_id is None else chain_id
    if chain_id is not None:
        one = circles[circles["chain_id"] == chain_id]
        its = sorted(one["iteration"].unique())
        for it in its:
            c = one[(one["iteration"] == it) & one["valid"].astype(bool)].sort_values("cz")
            if it == its[0]:
                ax2.plot(
                    100 * c["radius_m"],
                    c["cz"],
                    "o",
                    ms=4,
                    mfc="none",
                    mec="#999999",
                    label=f"initial phase ({len(c)} valid)",
                )
            elif it == its[-1]:
                ax2.plot(
                    100 * c["radius_m"],
                    c["cz"],
                    "o-",
                    ms=3,
                    lw=0.6,
                    color="#d62728",
                    label=f"iteration {it}, final ({len(c)} valid)",
                )
            else:
                ax2.plot(
                    100 * c["radius_m"],
                    c["cz"],
                    ".",
                    ms=2,
                    color="#1f77b4",
                    alpha=0.5,
                    label="intermediate iterations" if it == its[1] else None,
                )
        ax2.legend(fontsize=8)
        ax2.set_title(f"one trunk (chain {chain_id}): radius along the stem", fontsize=10)
    ax2.set_xlabel("circle radius (cm)")
    ax2.set_ylabel("circle centre z (m, levelled scan frame)")
    if title:
        fig.suptitle(title)
    return fig
