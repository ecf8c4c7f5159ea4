"""Shared parts of the scan-file readers (spec 1.2, DESIGN section 2): the one-line
:class:`ScanReadError`, colour scaling to uint8, file signature checks and the spherical
projection of unorganised clouds to a :class:`RangeImage`
(:func:`forestmap_assets.io.projection.project_to_range_image`) with the
:class:`ProjectionSettings` of params section ``range_images``."""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io._place_kernels import bridge_rows
from forestmap_assets.io.projection import (
    fill_ratio,
    project_angles,
    project_to_range_image,
    spherical_angles,
)
from forestmap_assets.params import RangeImageParams

_DEFAULTS = RangeImageParams()


@dataclass(frozen=True)
class ProjectionSettings:
    """How a reader projects an unorganised cloud (params section ``range_images``):
    ``angular_step_deg`` the sensor's step (campaign.yaml ``sensor``; None: estimated from the
    data), ``min_step_deg`` the finest step of the image, ``min_fill`` the least fill of an
    estimated step (:func:`forestmap_assets.io.projection.project_angles`), ``bridge`` whether
    short row gaps are bridged (:func:`bridge_row_gaps`). The readers take it
    where they take a plain step (``read_scan(angular_step_deg=...)``); a plain step (or None)
    gets the section's defaults."""

    angular_step_deg: float | tuple[float, float] | None = None
    min_step_deg: float = _DEFAULTS.min_step_deg
    min_fill: float = _DEFAULTS.min_fill
    bridge: bool = _DEFAULTS.bridge_gaps

    @classmethod
    def of(cls, step) -> ProjectionSettings:
        return step if isinstance(step, cls) else cls(angular_step_deg=step)

    def kwargs(self) -> dict:
        return {"angular_step_deg": self.angular_step_deg, "min_step_deg": self.min_step_deg,
                "min_fill": self.min_fill}


class ScanReadError(ValueError):
    """A scan file that cannot be read; the message is one line naming the file and reason."""


class BadScan(Exception):
    """Internal: reason a file is rejected (the file name is added by :func:`read_scan`)."""


def one_line(text: object) -> str:
    return re.sub(r"\s+", " ", str(text)).strip()


def to_rgb8(values: np.ndarray, *, full_scale: float | None = None) -> np.ndarray:
    """Colours to uint8: 0-1 floats scaled by 255, 16-bit values by 1/257, 0-255 kept.

    ``full_scale`` (e.g. a LAS/E57 colour limit) overrides the guess from the values. Guess
    (inferred): non-integer values all <= 1 are 0-1; any value > 255 means 16-bit.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.size and (not np.all(np.isfinite(v)) or v.min() < 0):
        raise BadScan("colour values must be finite and non-negative")
    if full_scale is None:
        vmax = float(v.max()) if v.size else 0.0
        if vmax <= 1.0 and np.any(v != np.rint(v)):
            full_scale = 1.0
        elif vmax > 255.0:
            full_scale = 65535.0
        else:
            full_scale = 255.0
    return np.clip(np.rint(v * (255.0 / full_scale)), 0, 255).astype(np.uint8)


def count_damage(header_count: int, held: int | str) -> str:
    """The one-line damage of a file whose header's point count is not what it holds:
    ``truncated: header says 5000 points, file holds 3012`` (``damaged: ...`` when it holds
    more)."""
    fewer = not isinstance(held, int) or held < header_count
    kind = "truncated" if fewer else "damaged"
    return f"{kind}: header says {header_count} points, file holds {held}"


def count_words(path: Path, start: int) -> int:
    """Whitespace-separated words of a text file from byte ``start`` on, read in blocks."""
    words, inside = 0, False
    with open(path, "rb") as f:
        f.seek(start)
        while block := f.read(1 << 22):
            words += len(block.split())
            if inside and not block[:1].isspace():
                words -= 1  # one word split across two blocks
            inside = not block[-1:].isspace()
    return words


def check_signature(path: Path, accepted: tuple[bytes, ...], what: str) -> None:
    with open(path, "rb") as f:
        head = f.read(max(len(s) for s in accepted))
    if not any(head.startswith(s) for s in accepted):
        raise BadScan(f"not {what} (bad signature)")


def _project(
    xyz: np.ndarray,
    rgb: np.ndarray | None,
    intensity: np.ndarray | None,
    angular_step_deg,
    to_scanner=None,
    own: bool = False,
) -> RangeImage:
    """Spherical projection of a cloud about its scanner; ``to_scanner`` (4x4) first moves points
    of a project-frame file into the scanner's frame, in float64 (map coordinates keep their mm).
    ``angular_step_deg``: a step, None, or :class:`ProjectionSettings`. ``own``: ``xyz`` is the
    caller's to give up (the projection may overwrite it, :func:`spherical_angles`)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if to_scanner is not None:
        m = np.asarray(to_scanner, dtype=np.float64)
        xyz = xyz @ m[:3, :3].T + m[:3, 3]
    if xyz.shape[0] == 0:
        raise BadScan("no points")
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    good = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)  # (.all(1) is 5 times slower)
    if not good.any():
        raise BadScan("no finite points")
    settings = ProjectionSettings.of(angular_step_deg)
    try:
        image = project_to_range_image(xyz, rgb, intensity, **settings.kwargs(), overwrite=own)
    except ValueError as exc:
        raise BadScan(f"spherical projection failed: {one_line(exc)}") from exc
    return _bridged(image, int(good.sum()), settings)


def _project_angles(range_m, azimuth_deg, elevation_deg, rgb, intensity,
                    angular_step_deg) -> RangeImage:
    """:func:`_project` for a reader that computed the points' spherical angles itself (a big
    file read in chunks, :func:`forestmap_assets.io.projection.spherical_angles`); its
    azimuth array is used up (overwritten)."""
    if np.size(range_m) == 0:
        raise BadScan("no points")
    settings = ProjectionSettings.of(angular_step_deg)
    try:
        image = project_angles(range_m, azimuth_deg, elevation_deg, rgb, intensity,
                               **settings.kwargs(), overwrite=True)
    except ValueError as exc:
        raise BadScan(f"spherical projection failed: {one_line(exc)}") from exc
    return _bridged(image, int(np.count_nonzero(np.isfinite(range_m))), settings)


_LOST_SHARE = 0.01  # (inferred) share of points without a pixel above which gaps are bridged
_GRID_FILL = 0.75  # (inferred) fill below which an image is not a scanner's whole grid either
_GAP_PX, _GAP_RANGE_M = 2, 0.11  # (inferred) longest row gap bridged; range step (Table 4.1)


def _bridged(image: RangeImage, n_points: int, settings: ProjectionSettings) -> RangeImage:
    """``image`` with its short row gaps bridged (:func:`bridge_row_gaps`) when ``settings``
    say so and more than ``_LOST_SHARE`` of the ``n_points`` projected found no pixel, or less
    than ``_GRID_FILL`` of its scanned region holds a return (a thinned export at the scanner's
    own step): not a scanner's whole grid, whose misses are kept."""
    if settings.bridge and (image.valid.sum() < (1.0 - _LOST_SHARE) * n_points
                            or fill_ratio(image.valid) < _GRID_FILL):
        bridge_row_gaps(image.range_m, image.intensity, image.rgb, image.points)
    return image


def bridge_row_gaps(range_img, intensity=None, rgb=None, points=None) -> None:
    """Fill, in place, row gaps of 1 to ``_GAP_PX`` empty pixels between two returns less than
    ``_GAP_RANGE_M`` apart: range, intensity and the pixel's point (``RangeImage.points``, on
    the chord between its neighbours' points) interpolated linearly, colour of the nearer
    side (inferred: the holes a projection leaves in a surface split its scan lines, and the
    segmentation, spec 2.2, breaks a run at every empty pixel). A numba kernel, rows in
    parallel (:func:`forestmap_assets.io._place_kernels.bridge_rows`)."""
    r = np.asarray(range_img)
    bridge_rows(r, np.empty((0, 0), r.dtype) if intensity is None else intensity,
                np.empty((0, 0, 3), np.uint8) if rgb is None else rgb,
                np.empty((0, 0, 3), r.dtype) if points is None else points, _GAP_PX,
                r.dtype.type(_GAP_RANGE_M))  # numpy compares in the image's precision


def coarsen_range_image(image: RangeImage, min_step_deg: float) -> RangeImage:
    """``image`` on a grid no finer than ``min_step_deg`` per axis, per pixel the first-return
    pixel nearest its centre (an organised scan finer than the per-scan stages need, params
    ``range_images``; :func:`forestmap_assets.io.projection.project_angles`); the image itself
    when it is not finer."""
    sa, se = image.azimuth_step_deg, image.elevation_step_deg
    tol = 1.0 - 1e-9
    if min_step_deg <= 0 or (sa >= min_step_deg * tol and se >= min_step_deg * tol):
        return image
    v, u = np.nonzero(image.valid)
    if image.points is not None:  # the pixels' own points (a projected cloud)
        r, az, el = spherical_angles(image.points[v, u].astype(np.float64))
    else:
        r, az, el = image.range_m[v, u], image.azimuth_deg[u], image.elevation_deg[v]
    out = project_angles(
        r, az, el,
        None if image.rgb is None else image.rgb[v, u],
        None if image.intensity is None else image.intensity[v, u],
        angular_step_deg=(max(sa, min_step_deg), max(se, min_step_deg)), min_fill=0.0,
        overwrite=True,
    )
    return replace(out, tilt_deg=image.tilt_deg)
