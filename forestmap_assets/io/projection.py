"""Spherical projection of an unorganised cloud into an organised range image (spec 1.2).

Spec 1.2 (inferred model): pixel (row v, column u) looks along elevation
``theta_v = theta_max - v * d_theta`` and azimuth ``alpha_u = alpha_0 + u * d_alpha``; the sensor
frame point is ``x = r cos(theta) cos(alpha), y = r cos(theta) sin(alpha), z = r sin(theta)``.
A scanner-frame cloud is mapped back onto such a grid: ``alpha = atan2(y, x)``,
``theta = atan2(z, hypot(x, y))``, rows top-down, the azimuth origin in the largest empty azimuth
gap (a 330 deg scan is not split); per pixel the nearest point (first return, spec 1.1) is kept.

The angular step is either given or the scanner's grid estimated from the data
(:mod:`forestmap_assets.io.angular_grid`). Points anywhere inside their beam's cell, jittered,
thinned or sampled from a point-cloud scene (Sylva's simulator) have no such grid and nearer
neighbours than their density (issue 18: 7 % filled), so (inferred) the estimated step is
coarsened to the finest one at which ``min_fill`` of the pixels inside the scanned region hold a
return and its returns' neighbours are mostly filled too (:func:`fill_ratio`,
:func:`neighbour_fill`, :func:`_filling_steps`). No step is finer than ``min_step_deg``
(params ``range_images``). Each pixel keeps one point with its own xyz
(``RangeImage.points``): a point re-synthesised at its pixel's centre is up to half a pixel
off, which at a coarse step widens every stem by a pixel and moves its circle centre away from
the scanner (issue 18: scans registered 0.45 % too far apart).
"""

from __future__ import annotations

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io._place_kernels import fill, place, write_image
from forestmap_assets.io._projection_kernels import (
    Scratch,
    count_valid,
    mark,
    neighbour_shares,
    occupancy,
    region_counts,
    start_threads,
)
from forestmap_assets.io.angular_grid import (
    _estimate_steps,
    _fit_axis,
    _fit_sample,
    _unwrapped_azimuth,
    _window_subset,
    _xyz,
    estimate_angular_step,
    spherical_angles,
)
from forestmap_assets.params import RangeImageParams

__all__ = [
    "estimate_angular_step",
    "fill_ratio",
    "nearest_per_pixel",
    "neighbour_fill",
    "project_angles",
    "project_to_range_image",
    "spherical_angles",
]

_DEFAULTS = RangeImageParams()
_FILL_POINTS = 600_000  # (inferred) above this, the fill of a trial step is measured on windows
_FILL_TOL = 0.05  # (inferred) relative step precision of the fill search
_NEIGHBOUR_FILL = 0.7  # (inferred) least neighbour_fill of an estimated step (:func:`_filled`)
_MOVE_PX = 0.85  # (inferred) farthest a point's direction from the centre of a pixel it may fill
_FRONT_M = 0.11  # (inferred) a pixel's front surface: ranges this near its nearest (Table 4.1)


def nearest_per_pixel(flat_index: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """Indices of the nearest point (smallest range, spec 1.1 first return; or smallest other
    key) in each pixel, in pixel order; linear time (``np.minimum.at``; a sort takes 10 s)."""
    flat = np.asarray(flat_index)
    r32 = np.asarray(range_m, dtype=np.float32)
    if flat.size == 0:
        return np.zeros(0, dtype=np.int64)
    n_pix = int(flat.max()) + 1
    best = np.full(n_pix, np.inf, dtype=np.float32)
    np.minimum.at(best, flat, r32)
    win = np.flatnonzero(r32 == best[flat])
    owner = np.full(n_pix, -1, dtype=np.int64)
    owner[flat[win]] = win  # ties: one of them
    return owner[owner >= 0]


def _step_pair(angular_step_deg) -> tuple[float, float]:
    steps = np.atleast_1d(np.asarray(angular_step_deg, dtype=np.float64)).ravel()
    if steps.size == 1:
        steps = np.repeat(steps, 2)
    if steps.size != 2 or not np.all(np.isfinite(steps)) or np.any(steps <= 0):
        raise ValueError(
            "angular_step_deg: expected a positive scalar or (az, el) pair, "
            f"got {angular_step_deg!r}"
        )
    return float(steps[0]), float(steps[1])


def fill_ratio(valid: np.ndarray) -> float:
    """Share of the pixels inside the scanned region that hold a return. The region: pixels
    with a return among themselves and their 8 neighbours (inferred: a hole narrower than 3
    pixels is a miss inside the scan, a wider one sky or out of range). About 1 on a scanner's
    own grid; ``p / (1 - (1 - p)^9)`` when a step too fine leaves a share ``p`` hit at random."""
    m = np.asarray(valid, dtype=bool)
    n = int(np.count_nonzero(_dilated(m)))
    return float(np.count_nonzero(m) / n) if n else 0.0


def neighbour_fill(valid: np.ndarray) -> float:
    """Mean share, over the pixels holding a return, of their 8 neighbours that hold one too
    (border pixels: of the neighbours inside the image). A cloud thinned at random leaves its
    surfaces as full of holes as its region (about the fill); one dense on its surfaces and
    sparse elsewhere (a sampled scene: stems dense, near ground sparse) scores higher."""
    m = np.asarray(valid, dtype=bool)
    if not m.any():
        return 0.0
    p = np.pad(m, 1).astype(np.uint8)
    ones = np.pad(np.ones(m.shape, dtype=np.uint8), 1)
    rows, cols = m.shape
    hits = np.zeros(m.shape, dtype=np.uint8)
    there = np.zeros(m.shape, dtype=np.uint8)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            if dv or du:
                hits += p[1 + dv:1 + dv + rows, 1 + du:1 + du + cols]
                there += ones[1 + dv:1 + dv + rows, 1 + du:1 + du + cols]
    return float(np.mean(hits[m] / there[m]))


def _filled(state: np.ndarray, rows: int, cols: int, min_fill: float) -> float:
    """The fill ratio of the pixels ``state != 0`` (flat, ``rows x cols``), lowered to
    ``min_fill * neighbour_fill / _NEIGHBOUR_FILL`` when that is less: a step reaches
    ``min_fill`` when both the region and the returns' neighbourhoods are filled enough
    (inferred: the scan-line segmentation, spec 2.2, breaks a run at every hole, and a thinned
    scanner grid at its own step, 50 % filled, loses half its stems). :func:`fill_ratio` and
    :func:`neighbour_fill` in two passes over the image."""
    n_filled, n_region = region_counts(state, rows, cols)
    f = n_filled / n_region if n_region else 0.0
    if f < min_fill:
        return f
    shares = neighbour_shares(state, rows, cols, n_filled)  # neighbour_fill's, in its order
    return min(f, min_fill * float(np.mean(shares)) / _NEIGHBOUR_FILL)


def _dilated(m: np.ndarray) -> np.ndarray:  # 3 x 3 dilation of a boolean image
    rows = m.copy()
    rows[1:] |= m[:-1]
    rows[:-1] |= m[1:]
    out = rows.copy()
    out[:, 1:] |= rows[:, :-1]
    out[:, :-1] |= rows[:, 1:]
    return out


def _dims(bounds, off_a, step_a, off_e, step_e) -> tuple[int, int, int, int]:
    """Grid indices of column and row 0, rows and columns of the image of angles within
    ``bounds`` (az min, az max, el min, el max) on the grid ``(off_a, step_a, off_e, step_e)``:
    the extreme fractional columns and rows of :func:`_place` (its maps are monotone)."""
    a_lo, a_hi, e_lo, e_hi = bounds
    u0, v0 = int(np.rint((a_lo - off_a) / step_a)), int(np.rint((-e_hi - off_e) / step_e))
    rows = int(np.rint((-e_lo - off_e) / step_e - v0)) + 1
    return u0, v0, rows, int(np.rint((a_hi - off_a) / step_a - u0)) + 1


def _filling_steps(a, el, steps, min_fill: float, max_pixels: int,
                   scratch: Scratch | None = None) -> tuple[float, float]:
    """``steps`` scaled (both axes alike) to the finest scale whose image fills ``min_fill`` of
    its scanned region (:func:`fill_ratio`; above ``_FILL_POINTS`` points on windows): grown by
    the factor a Poisson fill ``1 - exp(-lambda s^2)`` predicts until it fills, then bisected
    (geometrically, to ``_FILL_TOL``) between the last scale short of ``min_fill`` and the
    first that reaches it, so the step stays as fine as the fill allows (inferred: a coarser
    step keeps fewer points per stem)."""
    scratch = Scratch() if scratch is None else scratch
    sub = _window_subset(a, _FILL_POINTS, 8, np.random.default_rng(2))
    a, el = a[sub], el[sub]
    bounds = float(a.min()), float(a.max()), float(el.min()), float(el.max())

    def fill(scale: float) -> float:  # the fill does not depend on the grid's offsets
        sa, se = steps[0] * scale, steps[1] * scale
        u0, v0, rows, cols = _dims(bounds, 0.0, sa, 0.0, se)
        if rows * cols > max_pixels:
            return -float(rows * cols)
        if min(rows, cols) < 3:
            return 1.0
        state = occupancy(a, el, sa, se, u0, v0, rows, cols, _MOVE_PX, scratch)
        return _filled(state, rows, cols, min_fill)

    lo, hi = 1.0, None  # lo: a scale short of min_fill (or the fitted step); hi: one reaching it
    if fill(1.0) >= min_fill:  # the scanner's own grid
        return steps
    # first guess: the step of the points spread evenly over the occupied 1-degree cells
    cells = np.count_nonzero(np.bincount(np.floor(a).astype(np.int64) * 400
                                         + np.floor(el + 90.0).astype(np.int64)))
    scale = max(float(np.sqrt(cells / a.size / (steps[0] * steps[1]))), 1.25)
    for _ in range(16):
        f = fill(scale)
        if f >= min_fill:
            hi = scale
            if scale / 1.25 <= lo:
                break
            scale /= 1.25  # the guess may overshoot: step down until short of min_fill
            continue
        lo = scale
        if hi is not None:
            break
        if f < 0:  # too many pixels
            scale *= min(np.sqrt(-f / max_pixels) * 1.01, 4.0)
            continue
        grow = np.sqrt(np.log1p(-min_fill) / np.log1p(-f)) if f > 0 else 3.0
        scale *= float(np.clip(grow * 1.01, 1.25, 3.0))
    if hi is None:
        hi = scale
    else:
        while hi / lo > 1.0 + _FILL_TOL:
            mid = float(np.sqrt(lo * hi))
            if fill(mid) >= min_fill:
                hi = mid
            else:
                lo = mid
    return steps[0] * hi, steps[1] * hi


def _place(a, el, grid, r32, rows, cols, scratch: Scratch) -> np.ndarray:
    """Pixel (flat index; -1: none) of each point (unwrapped azimuth ``a``, elevation ``el``)
    on ``grid = (off_a, step_a, u0, off_e, step_e, v0)``: fractional column ``(a - off_a) /
    step_a - u0``, row ``(-el - off_e) / step_e - v0``. A pixel keeps its front point (within
    ``_FRONT_M`` of the nearest: first return, spec 1.1) nearest its centre (inferred: the
    nearest of k noisy ranges is ~1 sigma short). A point left out may fill an empty pixel of
    the three on its offset's side within ``_MOVE_PX`` of its direction (jitter pushed it over
    the border; a second return behind the first stays)."""
    return place(a, el, grid, r32, rows, cols, np.float32(_FRONT_M), np.float32(_MOVE_PX), scratch)


def _grid(a, el, given, min_step_deg, min_fill, max_pixels, scratch):
    """``(step_a, step_e, offsets)`` of the image: the ``given`` step, or the fitted grid
    coarsened to ``min_fill``; no step finer than ``min_step_deg``; ``offsets(step_a, step_e)``
    the grid's (az, el) offsets."""
    floor = max(float(min_step_deg or 0.0), 0.0)
    sample = _fit_sample(a, el)  # one draw for every fit

    def offsets(sa: float, se: float) -> tuple[float, float]:
        if fitted is not None and (sa, se) == fitted[1::2]:
            return fitted[0], fitted[2]
        return _fit_axis(sample[0], sa, refine=False)[0], _fit_axis(sample[1], se, refine=False)[0]

    fitted = None
    if given is None:
        fitted = _estimate_steps(a, el, sample)
        step_a, step_e = max(fitted[1], floor), max(fitted[3], floor)
        if min_fill > 0:
            step_a, step_e = _filling_steps(a, el, (step_a, step_e), min_fill, max_pixels,
                                            scratch)
    else:
        step_a, step_e = (max(s, floor) for s in _step_pair(given))
    return step_a, step_e, offsets


def project_angles(range_m: np.ndarray, azimuth_deg: np.ndarray, elevation_deg: np.ndarray,
                   rgb: np.ndarray | None = None, intensity: np.ndarray | None = None, *,
                   angular_step_deg: float | tuple[float, float] | None = None,
                   min_step_deg: float = 0.0, min_fill: float = _DEFAULTS.min_fill,
                   max_pixels: int = 100_000_000, overwrite: bool = False) -> RangeImage:
    """Organised range image (spec 1.2) from per-point range, azimuth and elevation (scanner
    frame, :func:`spherical_angles`; a reader of a big file computes them chunk by chunk).

    ``angular_step_deg`` (scalar or (az, el)) is used as given; None estimates the scanner's
    grid (:func:`estimate_angular_step`), coarsened until ``min_fill`` of the scanned region
    is filled (:func:`fill_ratio`; 0: never); no axis finer than ``min_step_deg``. The first
    column's azimuth lies in [-180, 180), later ones increase past it; one point per pixel
    (:func:`_place`), NaN where none, kept with its own xyz (``RangeImage.points``: never
    re-synthesised at the pixel's centre). ``max_pixels`` (inferred) guards against a step far too
    fine. ``overwrite``: the azimuths may be overwritten (the caller's own float64 array: it
    then holds the unwrapped azimuths; saves a copy of a big cloud's).
    """
    r = np.asarray(range_m).reshape(-1)
    az = np.asarray(azimuth_deg, dtype=np.float64).reshape(-1)
    el = np.asarray(elevation_deg, dtype=np.float64).reshape(-1)
    n_in = r.size
    if az.size != n_in or el.size != n_in:
        raise ValueError(f"angles: expected {n_in} azimuths and elevations, got {az.size}, {el.size}")
    if rgb is not None and np.shape(rgb) != (n_in, 3):
        raise ValueError(f"rgb: expected shape {(n_in, 3)}, got {np.shape(rgb)}")
    if intensity is not None and np.size(intensity) != n_in:
        raise ValueError(f"intensity: expected {n_in} values, got {np.shape(intensity)}")
    start_threads()
    if r.dtype not in (np.float32, np.float64) or count_valid(r, az, el) < n_in:
        ok = np.isfinite(r) & (r > 0) & np.isfinite(az) & np.isfinite(el)
        if not ok.all():
            r, az, el = r[ok], az[ok], el[ok]
            rgb = None if rgb is None else np.asarray(rgb)[ok]
            intensity = None if intensity is None else np.asarray(intensity).reshape(-1)[ok]
            overwrite = True
    if r.size == 0:
        raise ValueError("no valid points to project")
    a, origin, (a_lo, a_hi) = _unwrapped_azimuth(az, overwrite=overwrite)
    del az
    if angular_step_deg is None and r.size < 2:
        raise ValueError("cannot estimate the angular step from fewer than 2 points")
    scratch, filled = Scratch(), None
    step_a, step_e, offsets = _grid(a, el, angular_step_deg, min_step_deg, min_fill, max_pixels,
                                    scratch)
    r32 = np.asarray(r, dtype=np.float32)
    bounds = a_lo, a_hi, float(el.min()), float(el.max())
    tried: list[tuple[float, float]] = []  # (log step, fill) of the placements short of min_fill
    for _ in range(8):  # an estimated step: grown while short of min_fill (:func:`_growth`)
        off_a, off_e = offsets(step_a, step_e)
        u0, v0, rows, cols = _dims(bounds, off_a, step_a, off_e, step_e)
        if rows * cols > max_pixels:
            raise ValueError(
                f"projection would need {rows} x {cols} pixels (angular step {step_a:.4g} x "
                f"{step_e:.4g} deg); give angular_step_deg"
            )
        pix = _place(a, el, (off_a, step_a, u0, off_e, step_e, v0), r32, rows, cols, scratch)
        if angular_step_deg is not None or min_fill <= 0 or min(rows, cols) < 3:
            break
        filled = scratch.get("filled", rows * cols, np.uint8)
        mark(pix, filled)
        f = _filled(filled, rows, cols, min_fill)
        if f >= min_fill:
            break
        tried.append((float(np.log(step_a)), f))
        grow = _growth(tried, min_fill)
        step_a, step_e = step_a * grow, step_e * grow
    azimuth = origin + off_a + (u0 + np.arange(cols)) * step_a
    azimuth -= 360.0 * np.floor((azimuth[0] + 180.0) / 360.0)
    elevation = -(off_e + (v0 + np.arange(rows)) * step_e)
    del scratch, filled  # their pixel arrays' pages go to the image (a fresh page costs more)
    return _image(pix, r, a, el, origin, rgb, intensity, rows, cols, azimuth, elevation)


def _growth(tried: list[tuple[float, float]], min_fill: float) -> float:
    """Factor of the next step after placements ``tried`` (log step, fill) all short of
    ``min_fill`` (inferred): 5 % after the first; then the secant of the last two in log step,
    aimed 10 % past ``min_fill`` and kept within 5-50 %. The windows' fill that chose the step
    can miss the whole image's by a few points, and the fill rises slowly with the step
    (Sylva's scans: 0.45 -> 0.50 over 28 %), so the 5 % steps of before took up to 6 placements
    where this takes 3."""
    if len(tried) < 2:
        return 1.05
    (s0, f0), (s1, f1) = tried[-2:]
    slope = (f1 - f0) / (s1 - s0)
    if not slope > 0:
        return 1.05
    return float(np.clip(np.exp(1.1 * (min_fill - f1) / slope), 1.05, 1.5))


def _image(pix, r, a, el, origin, rgb, intensity, rows, cols, azimuth, elevation) -> RangeImage:
    """The range image of the points placed at ``pix`` (flat pixel; -1: none), each with its
    own xyz along its own direction (azimuth ``a + origin``); colour as uint8 (rounded and
    clipped), intensity as float32."""
    def new(dtype, empty, *shape):
        out = np.empty((rows * cols, *shape), dtype=dtype)
        fill(out.reshape(-1), empty)
        return out

    range_img, points = new(np.float32, np.nan), new(np.float32, np.nan, 3)
    int_img, int_in = np.empty(0, np.float32), np.empty(0, np.float32)
    if intensity is not None:
        int_img = new(np.float32, np.nan)
        int_in = np.asarray(intensity).reshape(-1)
        if int_in.dtype not in (np.float32, np.uint16, np.uint8):  # exact in float32
            int_in = int_in.astype(np.float32)
    rgb_img, rgb_in = np.empty((0, 3), np.uint8), np.empty((0, 3), np.uint8)
    if rgb is not None:
        rgb_img = new(np.uint8, 0, 3)
        rgb_in = np.asarray(rgb)
        if rgb_in.dtype != np.uint8:
            rgb_in = np.clip(np.rint(rgb_in), 0, 255).astype(np.uint8)
    write_image(pix, r, a, el, origin, int_in, rgb_in, range_img, int_img, rgb_img, points)
    return RangeImage(range_img.reshape(rows, cols), azimuth, elevation,
                      intensity=None if intensity is None else int_img.reshape(rows, cols),
                      rgb=None if rgb is None else rgb_img.reshape(rows, cols, 3),
                      points=points.reshape(rows, cols, 3))


def project_to_range_image(
    xyz: np.ndarray,
    rgb: np.ndarray | None = None,
    intensity: np.ndarray | None = None,
    *,
    angular_step_deg: float | tuple[float, float] | None = None,
    min_step_deg: float = 0.0,
    min_fill: float = _DEFAULTS.min_fill,
    max_pixels: int = 100_000_000,
    overwrite: bool = False,
) -> RangeImage:
    """Organised range image (spec 1.2) from an unorganised scanner-frame cloud: the points'
    :func:`spherical_angles` projected by :func:`project_angles` (same keywords); points at
    the origin or not finite are dropped. ``overwrite``: ``xyz`` may be used up
    (:func:`spherical_angles`)."""
    with np.errstate(invalid="ignore"):
        r, az, el = spherical_angles(_xyz(xyz), overwrite=overwrite)
    return project_angles(r, az, el, rgb, intensity, angular_step_deg=angular_step_deg,
                          min_step_deg=min_step_deg, min_fill=min_fill, max_pixels=max_pixels,
                          overwrite=True)
