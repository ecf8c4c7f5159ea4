"""2-D pictures of every stage (matplotlib), shared by the exports, the report and the notebooks.

Each function returns a :class:`matplotlib.figure.Figure` built without pyplot (no global state,
safe in worker processes); :func:`save_png` writes one atomically and :func:`png_bytes` gives
its bytes for inline HTML. The pictures follow the theses' figures:

* :func:`range_image_panels`: JP Fig. 7 (a)-(d) / thesis Fig. 4.15: range image, segment mask,
  valid-circle mask (each row's mark as wide as the circle), cylinders over the range image.
* :func:`circle_convergence`: circle parameters over the iterations (thesis 4.6.3, Fig. 4.14;
  App. B Figs B.12-B.16: the initial phase and the converged circles).
* :func:`score_cloud_evolution`: JP Fig. 9 / thesis Fig. 5.7: the connected score cloud of one
  pair accumulated onto the xy plane at each cell size, peak and cloud centre +- sigma;
  :func:`submap_overlay`: two sub-maps before and after registration.
* :func:`network_figure`, :func:`residual_figure`: the registration network with pose sigmas
  and the residual verdicts of eq. (11) (thesis 6.4, 7.1).
* :func:`elevation_figure`: JP Fig. 11 / thesis Fig. 6.11: the merged lowest-hit elevation map
  with scan frames (larger axis symbol at the reference scan) and trees.
* :func:`dbh_histogram`: the tree list's DBH distribution.
"""

from __future__ import annotations

import io
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from forestmap_assets.core.features.range_image import RangeImage, levelling_rotation

STATUS_COLOURS = {
    "accepted": "#1b7837",
    "rejected": "#d95f02",
    "failed": "#7f7f7f",
    "admitted": "#1f4e9c",
    "ok": "#1b7837",
    "inconsistent": "#c51b1b",
}
BARK = "#8c5a2b"
NO_RETURN = "#cfe3f5"
NO_VALUE = "#a0a0a0"
ELEVATION_CMAP = "YlGn_r"  # lighter = higher (thesis Fig. 6.11); the same scale as map.png


def new_figure(width: float, height: float, layout: str | None = "constrained") -> Figure:
    """A pyplot-free figure with an Agg canvas."""
    fig = Figure(figsize=(width, height), layout=layout)
    FigureCanvasAgg(fig)
    return fig


def png_bytes(fig: Figure, dpi: int = 110) -> bytes:
    """The figure as PNG bytes."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def save_png(fig: Figure, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Write the figure as PNG atomically (temporary file + ``os.replace``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_bytes(png_bytes(fig, dpi))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


# ------------------------------------------------------------------------------------------
# range-image pictures (JP Fig. 7, thesis Fig. 4.15)


def _angles_extent(image: RangeImage) -> tuple[float, float, float, float]:
    """imshow extent in degrees: columns = azimuth, rows = elevation (row 0 at the top)."""
    az, el = image.azimuth_deg, image.elevation_deg
    da = image.azimuth_step_deg / 2 or 0.5
    de = image.elevation_step_deg / 2 or 0.5
    return (float(az[0] - da), float(az[-1] + da), float(el[-1] - de), float(el[0] + de))


def range_limits(
    image: RangeImage, percentiles: tuple[float, float] = (2.0, 80.0)
) -> tuple[float, float]:
    """Grey-scale limits of a range image: the given percentiles of the valid ranges, rounded
    to 0.5 m (JP Fig. 7 (a) shows 3.5-10 m; inferred: the near trunks, not the far field)."""
    r = image.range_m[image.valid]
    if r.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(r, percentiles)
    lo, hi = np.floor(lo * 2) / 2, np.ceil(hi * 2) / 2
    return float(lo), float(max(hi, lo + 0.5))


def _to_sensor(image: RangeImage, xyz: np.ndarray) -> np.ndarray:
    """Levelled points back into the scanner's own frame (inverse of the levelling, spec 1.2)."""
    if any(image.tilt_deg):
        return xyz @ levelling_rotation(*image.tilt_deg)
    return xyz


def _azimuth_in_image(image: RangeImage, az_deg: np.ndarray) -> np.ndarray:
    """Azimuths unwrapped into the image's azimuth interval."""
    a0 = image.azimuth_deg[0] - image.azimuth_step_deg / 2
    return a0 + np.mod(az_deg - a0, 360.0)


def circle_mask(image: RangeImage, circles: pd.DataFrame) -> np.ndarray:
    """Boolean (rows, cols) mask of valid circle models (thesis 3.8 output artefact, Fig. 4.15c):
    in each circle's row, the columns its circle covers as seen from the sensor, i.e. the
    azimuth of the centre +- asin(radius / horizontal distance)."""
    mask = np.zeros(image.shape, dtype=bool)
    if circles is None or len(circles) == 0:
        return mask
    if "iteration" in circles:
        circles = circles[circles["iteration"] == circles["iteration"].max()]
    if "valid" in circles:
        circles = circles[circles["valid"].astype(bool)]
    if len(circles) == 0:
        return mask
    c = _to_sensor(image, circles[["cx", "cy", "cz"]].to_numpy(float))
    rho = np.hypot(c[:, 0], c[:, 1])
    half = np.degrees(
        np.arcsin(np.clip(circles["radius_m"].to_numpy(float) / np.maximum(rho, 1e-6), 0, 1))
    )
    az = _azimuth_in_image(image, np.degrees(np.arctan2(c[:, 1], c[:, 0])))
    c0 = np.clip(np.searchsorted(image.azimuth_deg, az - half, side="left"), 0, image.shape[1] - 1)
    c1 = np.clip(
        np.searchsorted(image.azimuth_deg, az + half, side="right") - 1, 0, image.shape[1] - 1
    )
    c1 = np.maximum(c0, c1)
    rows = np.clip(circles["row"].to_numpy(int), 0, image.shape[0] - 1)
    diff = np.zeros((image.shape[0], image.shape[1] + 1), dtype=np.int32)
    np.add.at(diff, (rows, c0), 1)
    np.add.at(diff, (rows, c1 + 1), -1)
    return np.cumsum(diff[:, :-1], axis=1) > 0


def cylinder_outlines(
    image: RangeImage, cylinders: pd.DataFrame, samples: int = 12
) -> list[np.ndarray]:
    """Outline polygons (azimuth_deg, elevation_deg) of cylinder segments as seen from the sensor:
    along the axis, the azimuth of each axis point +- the azimuth span ``asin(r / rho)`` of the
    horizontal cross-section at horizontal distance ``rho``."""
    out: list[np.ndarray] = []
    if cylinders is None or len(cylinders) == 0:
        return out
    t = np.linspace(0.0, 1.0, samples)
    p0 = cylinders[["x0", "y0", "z0"]].to_numpy(float)
    p1 = cylinders[["x1", "y1", "z1"]].to_numpy(float)
    r0 = cylinders["r0_m" if "r0_m" in cylinders else "radius_m"].to_numpy(float)
    r1 = cylinders["r1_m" if "r1_m" in cylinders else "radius_m"].to_numpy(float)
    pts = p0[:, None, :] + t[None, :, None] * (p1 - p0)[:, None, :]  # (n, samples, 3)
    rad = r0[:, None] + t[None, :] * (r1 - r0)[:, None]
    s = _to_sensor(image, pts.reshape(-1, 3)).reshape(pts.shape)
    rho = np.hypot(s[..., 0], s[..., 1])
    az = np.degrees(np.arctan2(s[..., 1], s[..., 0]))
    az = _azimuth_in_image(image, az[:, :1]) + (az - az[:, :1] + 180.0) % 360.0 - 180.0
    el = np.degrees(np.arctan2(s[..., 2], rho))
    half = np.degrees(
        np.arcsin(np.clip(rad / np.maximum(rho, 1e-6), 0, 1))
    )  # azimuth span of a cross-section
    for k in range(len(cylinders)):
        left = np.stack([az[k] - half[k], el[k]], 1)
        right = np.stack([az[k] + half[k], el[k]], 1)[::-1]
        out.append(np.vstack([left, right, left[:1]]))
    return out


def range_image_panels(
    image: RangeImage,
    segments: pd.DataFrame | None = None,
    circles: pd.DataFrame | None = None,
    cylinders: pd.DataFrame | None = None,
    *,
    title: str = "",
    limits: tuple[float, float] | None = None,
    width: float = 12.0,
    azimuth_range: tuple[float, float] | None = None,
    elevation_range: tuple[float, float] | None = None,
) -> Figure:
    """JP Fig. 7 / thesis Fig. 4.15 for one scan: (a) the range image in grey (near = dark,
    ``limits`` metres, default :func:`range_limits`), (b) the segment mask, (c) the valid circle
    models (each row's mark as wide as its circle), (d) the cylinder segments over the range
    image. Axes in degrees of azimuth and elevation; ``azimuth_range`` / ``elevation_range``
    (degrees) zoom in. Panels without data are left out."""
    from forestmap_assets.core.features.segments import segment_mask

    extent = _angles_extent(image)
    view = (*(azimuth_range or extent[:2]), *(elevation_range or extent[2:]))
    lo, hi = limits or range_limits(image)
    panels: list[tuple[str, str]] = [("a", "range image")]
    if segments is not None:
        panels.append(("b", "segments"))
    if circles is not None:
        panels.append(("c", "circles"))
    if cylinders is not None:
        panels.append(("d", "cylinders"))
    span_az = view[1] - view[0]
    span_el = view[3] - view[2]
    side_by_side = span_az < 2.0 * span_el  # a zoom: panels in a row, else stacked (inferred)
    if side_by_side:
        panel_w = (width - 0.8) / len(panels)
        fig = new_figure(width, panel_w * span_el / span_az + 1.2 + (0.4 if title else 0))
        axes = fig.subplots(1, len(panels), sharey=True, squeeze=False)[0]
    else:
        panel_h = (width - 1.6) * span_el / span_az + 0.45
        fig = new_figure(width, panel_h * len(panels) + (0.4 if title else 0) + 0.3)
        axes = fig.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
    grey = np.ma.masked_invalid(image.range_m)
    cmap = _cmap("gray").with_extremes(bad=NO_RETURN)
    for ax, (letter, kind) in zip(axes, panels, strict=True):
        ax.set_facecolor("white")
        if kind == "range image":
            im = ax.imshow(
                grey,
                cmap=cmap,
                vmin=lo,
                vmax=hi,
                extent=extent,
                interpolation="nearest",
                aspect="equal",
            )
            cb = fig.colorbar(im, ax=ax, fraction=0.025, pad=0.01, extend="both")
            cb.set_label("range (m)")
            text = (
                f"({letter}) range {lo:g}-{hi:g} m"
                if side_by_side
                else f"({letter}) range image, {lo:g}-{hi:g} m in shades of grey, "
                "pale blue = no return"
            )
        elif kind == "segments":
            mask = segment_mask(image, segments)
            ax.imshow(
                mask,
                cmap="gray_r",
                vmin=0,
                vmax=1,
                extent=extent,
                interpolation="nearest",
                aspect="equal",
            )
            text = (
                f"({letter}) segments"
                if side_by_side
                else f"({letter}) scan-line segments: {len(segments)} "
                "(black; ground and walls left out)"
            )
        elif kind == "circles":
            mask = circle_mask(image, circles)
            n_valid = _valid_final(circles)
            ax.imshow(
                mask,
                cmap="gray_r",
                vmin=0,
                vmax=1,
                extent=extent,
                interpolation="nearest",
                aspect="equal",
            )
            text = (
                f"({letter}) valid circles"
                if side_by_side
                else f"({letter}) valid circle models: {n_valid} (black, as wide as each circle)"
            )
        else:
            ax.imshow(
                grey,
                cmap=cmap,
                vmin=lo,
                vmax=hi,
                extent=extent,
                interpolation="nearest",
                aspect="equal",
                alpha=0.55,
            )
            from matplotlib.collections import PolyCollection

            outlines = cylinder_outlines(image, cylinders)
            if outlines:
                ax.add_collection(
                    PolyCollection(
                        outlines,
                        facecolors=(0.85, 0.1, 0.1, 0.45),
                        edgecolors=(0.7, 0.0, 0.0, 1.0),
                        linewidths=0.6,
                    )
                )
            text = (
                f"({letter}) cylinders"
                if side_by_side
                else f"({letter}) cylinder segments projected into the range image: "
                f"{len(cylinders)}"
            )
        ax.set_title(text, loc="left", fontsize=10)
        ax.set_xlim(view[0], view[1])
        ax.set_ylim(view[2], view[3])
        if side_by_side:
            ax.set_xlabel("azimuth (deg)")
    axes[0].set_ylabel("elevation (deg)")
    if not side_by_side:
        for ax in axes:
            ax.set_ylabel("elevation (deg)")
        axes[-1].set_xlabel("azimuth (deg)")
    if title:
        fig.suptitle(title)
    return fig


def range_mask_figure(
    image: RangeImage,
    mask: np.ndarray | None,
    title: str,
    *,
    width: float = 9.0,
    label: str = "mask",
    outlines: list[np.ndarray] | None = None,
    outline_label: str = "cylinder segments",
) -> Figure:
    """A small picture for the Dagster UI: the range image in grey (robust limits, pale blue =
    no return, axes in degrees) with a boolean ``mask`` (segments, circles, occlusion
    boundaries) in red on top and optional ``outlines`` (:func:`cylinder_outlines`) in orange."""
    extent = _angles_extent(image)
    lo, hi = range_limits(image)
    span_az, span_el = extent[1] - extent[0], extent[3] - extent[2]
    fig = new_figure(width, (width - 1.4) * span_el / span_az + 0.8)
    ax = fig.subplots()
    im = ax.imshow(
        np.ma.masked_invalid(image.range_m),
        cmap=_cmap("gray").with_extremes(bad=NO_RETURN),
        vmin=lo,
        vmax=hi,
        extent=extent,
        interpolation="nearest",
        aspect="equal",
    )
    if mask is not None and mask.any():
        rgba = np.zeros(mask.shape + (4,))
        rgba[mask] = (0.9, 0.05, 0.05, 0.85)
        ax.imshow(rgba, extent=extent, interpolation="nearest", aspect="equal")
        title = f"{title} (red: {label}, {int(mask.sum())} pixels)"
    if outlines:
        for poly in outlines:
            ax.plot(poly[:, 0], poly[:, 1], color="#ff8c00", lw=0.9)
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        title = f"{title} (orange: {len(outlines)} {outline_label})"
    cb = fig.colorbar(im, ax=ax, fraction=0.025, pad=0.01, extend="both")
    cb.set_label("range (m)")
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("azimuth (deg)")
    ax.set_ylabel("elevation (deg)")
    return fig


def _valid_final(circles: pd.DataFrame) -> int:
    if circles is None or len(circles) == 0:
        return 0
    last = (
        circles[circles["iteration"] == circles["iteration"].max()]
        if "iteration" in circles
        else circles
    )
    return int(last["valid"].sum()) if "valid" in last else len(last)


def chain_azimuth(image: RangeImage, circles: pd.DataFrame, chain_id: int) -> float:
    """Azimuth (deg, in the image's interval) of a chain's valid circle centres, for zooming."""
    c = circles[(circles["chain_id"] == chain_id) & circles["valid"].astype(bool)]
    if c.empty:
        c = circles[circles["chain_id"] == chain_id]
    s = _to_sensor(image, c[["cx", "cy", "cz"]].to_numpy(float))
    az = _azimuth_in_image(image, np.degrees(np.arctan2(s[:, 1], s[:, 0])))
    return float(np.median(az))


# ------------------------------------------------------------------------------------------
# circle convergence (thesis 4.6.3, Fig. 4.14; App. B)


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


def _cmap(name: str):
    from matplotlib import colormaps

    return colormaps[name]


# ------------------------------------------------------------------------------------------
# score clouds of one registration (JP Fig. 9, thesis Fig. 5.7)


def _level_components(cells: pd.DataFrame) -> np.ndarray:
    """Labels of the 80-connected components of one level's surviving cells (spec 6.5)."""
    from forestmap_assets.core.registration import lattice_components

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
    cmap = _cmap("magma")
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


# ------------------------------------------------------------------------------------------
# network, poses and residuals (thesis 6.4, 7.1)


def _registered(poses: pd.DataFrame) -> pd.DataFrame:
    reg = poses["registered"]
    if reg.dtype != bool:
        reg = reg.astype(str).str.lower().isin(["true", "1"])
    return poses[reg.to_numpy(bool)]


def _scan_frames(ax, poses: pd.DataFrame, length_m: float, reference: str | None = None) -> None:
    """Scan positions as xy axis symbols rotated by the heading (JP Fig. 11): x red, y green;
    the reference scan's symbol is twice as large."""
    for r in poses.itertuples(index=False):
        size = 2 * length_m if r.scan == reference else length_m
        h = np.radians(float(r.heading_deg))
        for (ux, uy), colour in (
            ((np.cos(h), np.sin(h)), "#d62728"),
            ((-np.sin(h), np.cos(h)), "#2ca02c"),
        ):
            ax.annotate(
                "",
                xy=(r.x + size * ux, r.y + size * uy),
                xytext=(r.x, r.y),
                arrowprops=dict(arrowstyle="-|>", color=colour, lw=1.6, mutation_scale=9),
            )
        ax.plot(r.x, r.y, "o", ms=4, color="black")
        ax.annotate(
            str(r.scan),
            (r.x, r.y),
            xytext=(-10, -12),
            textcoords="offset points",
            fontsize=10,
            fontweight="bold",
            color="black",
            bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.7),
        )


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
    largest is about 4 % of the plot)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Ellipse

    fig = new_figure(7.5, 6.5)
    ax = fig.subplots()
    placed = _registered(poses)
    at = {r.scan: (r.x, r.y) for r in placed.itertuples(index=False)}
    admitted = set()
    if links is not None and len(links) and "status" in links:
        admitted = {
            (r.scan, r.reference) for r in links.itertuples(index=False) if r.status == "admitted"
        }
    if registrations is not None:
        for r in registrations.itertuples(index=False):
            if r.scan not in at or r.reference not in at:
                continue
            (x0, y0), (x1, y1) = at[r.scan], at[r.reference]
            if (r.scan, r.reference) in admitted:
                style = dict(color=STATUS_COLOURS["admitted"], lw=2.2, ls="-")
            elif r.status == "accepted":
                style = dict(color=STATUS_COLOURS["inconsistent"], lw=1.5, ls="--")
            else:
                style = dict(color=STATUS_COLOURS["failed"], lw=1.0, ls=":")
            ax.plot([x0, x1], [y0, y1], zorder=1, **style)
            ax.annotate(
                f"{r.scan}{r.reference}",
                ((x0 + x1) / 2, (y0 + y1) / 2),
                fontsize=7,
                color=style["color"],
                ha="center",
                va="center",
                bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.8),
            )
    span = 1.0
    if len(placed):
        span = max(float(np.ptp(placed["x"])), float(np.ptp(placed["y"])), 1.0)
        sd = placed[["sd_x", "sd_y"]].to_numpy(float)
        top = float(np.nanmax(sd)) if np.isfinite(sd).any() else 0.0
        scale = sigma_scale or (0.04 * span / top if top > 0 else 1.0)
        scale = (
            float(10 ** np.floor(np.log10(scale))) if sigma_scale is None and scale > 0 else scale
        )
        for r in placed.itertuples(index=False):
            if np.isfinite(r.sd_x) and np.isfinite(r.sd_y) and (r.sd_x > 0 or r.sd_y > 0):
                ax.add_patch(
                    Ellipse(
                        (r.x, r.y),
                        2 * scale * r.sd_x,
                        2 * scale * r.sd_y,
                        fc=(0.2, 0.4, 0.9, 0.15),
                        ec="#1f4e9c",
                        lw=1.0,
                        zorder=2,
                    )
                )
        reference = str(poses["scan"].iloc[0]) if len(poses) else None
        _scan_frames(ax, placed, 0.06 * span, reference)
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
        ax.legend(handles=handles, fontsize=8, loc="best")
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


# ------------------------------------------------------------------------------------------
# elevation map (JP Fig. 11, thesis Fig. 6.11)


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
    """The part of an :class:`~forestmap_assets.core.elevation.ElevationGrid` inside ``box``."""
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
    windows = sliding_window_view(padded, (window, window)).reshape(z.shape + (-1,))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows
        low = np.nanpercentile(windows, percentile, axis=-1)
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
        _scan_frames(ax, placed, 0.035 * span, ref)
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


# ------------------------------------------------------------------------------------------
# tree list


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
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no tree with a DBH", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("DBH (cm)")
    ax.set_ylabel("trees")
    ax.set_title(title or "diameter at breast height")
    return fig
