"""Range-image pictures of one scan (JP Fig. 7 (a)-(d) / thesis Fig. 4.15): range image, segment
mask, valid-circle mask (each row's mark as wide as the circle, thesis 3.8) and cylinders over the
range image, and the azimuth of a chain for zooming (the Dagster UI's small pictures:
:mod:`.range_pictures`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from forestmap_assets.core.features.range_image import RangeImage, levelling_rotation
from forestmap_assets.outputs.figures.common import NO_RETURN, colour_map, new_figure

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def angles_extent(image: RangeImage) -> tuple[float, float, float, float]:
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
    if r.size > 200_000:  # a regular sample: the same limits once rounded, a tenth of the time
        r = r[:: r.size // 100_000]
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

    extent = angles_extent(image)
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
    cmap = colour_map("gray").with_extremes(bad=NO_RETURN)
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
