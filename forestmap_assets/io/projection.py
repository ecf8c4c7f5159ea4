"""Spherical projection of an unorganised cloud into an organised range image (spec 1.2).

Spec 1.2 (inferred model): pixel (row v, column u) looks along elevation
``theta_v = theta_max - v * d_theta`` and azimuth ``alpha_u = alpha_0 + u * d_alpha``; the sensor
frame point is ``x = r cos(theta) cos(alpha), y = r cos(theta) sin(alpha), z = r sin(theta)``.
An unorganised cloud in the scanner's own frame (origin at the sensor) is mapped back onto such
a grid: ``alpha = atan2(y, x)``, ``theta = atan2(z, hypot(x, y))``; rows top-down by elevation,
columns by increasing azimuth, the azimuth origin placed in the largest empty azimuth gap so that
a 330 deg scan is not split. When several points fall in one pixel the nearest one (first
return, spec 1.1) is kept.

The angular step is either given or estimated from the data's own angular density: the median
spacing between angular nearest neighbours along each axis, refined by fitting the regular grid
``x = offset + k * step`` to the angles over growing spans (so a step error never accumulates
into empty columns across a 3000-column image).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from forestmap_assets.core.features.range_image import RangeImage

__all__ = [
    "estimate_angular_step",
    "nearest_per_pixel",
    "project_to_range_image",
    "spherical_angles",
]

_TINY_DEG = 1e-9  # angular differences below this are duplicates, not neighbours
_CONE = np.tan(np.radians(30.0))  # half-angle of the "along one axis" neighbour cone (inferred)


def spherical_angles(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range (m), azimuth ``atan2(y, x)`` and elevation ``atan2(z, hypot(x, y))`` in degrees."""
    xyz = np.asarray(xyz, dtype=np.float64)
    h = np.hypot(xyz[:, 0], xyz[:, 1])
    r = np.hypot(h, xyz[:, 2])
    az = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    el = np.degrees(np.arctan2(xyz[:, 2], h))
    return r, az, el


def _azimuth_origin(az_deg: np.ndarray) -> float:
    """Azimuth (deg) just after the largest empty azimuth gap, wrap-around included."""
    s = np.sort(az_deg)
    gaps = np.diff(s)
    wrap = s[0] + 360.0 - s[-1]
    if gaps.size == 0 or wrap >= gaps.max():
        return float(s[0])
    return float(s[int(np.argmax(gaps)) + 1])


def _unwrapped_azimuth(az_deg: np.ndarray) -> tuple[np.ndarray, float]:
    """Azimuths shifted to ``[0, 360)`` from the origin in the largest gap, and that origin."""
    origin = _azimuth_origin(az_deg)
    return np.mod(az_deg - origin, 360.0), origin


def _window_subset(a: np.ndarray, max_points: int, n_windows: int, rng) -> np.ndarray:
    """Indices of points inside a few random azimuth windows (full local density kept)."""
    n = a.size
    if n <= max_points:
        return np.arange(n)
    lo, hi = float(a.min()), float(a.max())
    width = (hi - lo) * max_points / n / n_windows
    starts = rng.uniform(lo, max(lo, hi - width), size=n_windows)
    mask = np.zeros(n, dtype=bool)
    for s in starts:  # a handful of windows, not a per-point loop
        mask |= (a >= s) & (a < s + width)
    idx = np.flatnonzero(mask)
    return idx if idx.size >= 10 else rng.choice(n, size=max_points, replace=False)


def _neighbour_steps(
    a: np.ndarray,
    e: np.ndarray,
    *,
    max_points: int = 200_000,
    n_queries: int = 20_000,
    k: int = 12,
    seed: int = 0,
) -> tuple[float, float]:
    """Rough (az, el) steps: median angular nearest-neighbour spacing along each axis.

    Neighbours are taken in the (az, el) plane scaled by the current step estimates (start:
    isotropic); a neighbour counts for the azimuth axis when it lies within +-30 deg of that
    axis in the scaled plane (inferred), likewise for elevation. The rough step of an axis is
    the median spacing to the nearest such neighbour; it is then re-estimated as the median
    over all such neighbour pairs within [0.5, 1.5] x rough, which removes the downward bias
    of "nearest" under jitter. Re-scaling by the new steps repeats until they settle; a grid
    so anisotropic that the coarser axis has no neighbour among the k nearest is stretched.
    """
    rng = np.random.default_rng(seed)
    sub = _window_subset(a, max_points, 8, rng)
    a, e = a[sub], e[sub]
    if a.size < 2:
        raise ValueError("cannot estimate the angular step from fewer than 2 points")
    q = rng.choice(a.size, size=min(n_queries, a.size), replace=False)
    k_eff = min(k, a.size - 1)

    def axis_step(d: np.ndarray, along: np.ndarray) -> float:
        has = along.any(1)
        if has.sum() < 3:
            return float("nan")
        rough = float(np.median(np.where(along, d, np.inf).min(1)[has]))
        pairs = d[along]
        pairs = pairs[(pairs > 0.5 * rough) & (pairs < 1.5 * rough)]
        return float(np.median(pairs)) if pairs.size else rough

    scale = np.array([1.0, 1.0])
    steps = (float("nan"), float("nan"))
    for _ in range(8):
        tree = cKDTree(np.column_stack([a * scale[0], e * scale[1]]))
        _, nb = tree.query(np.column_stack([a[q] * scale[0], e[q] * scale[1]]), k_eff + 1)
        nb = nb[:, 1:]
        da = np.abs(a[nb] - a[q, None])
        de = np.abs(e[nb] - e[q, None])
        real = (da + de) > _TINY_DEG
        sa, se = da * scale[0], de * scale[1]
        along_a = real & (se <= _CONE * sa)
        along_e = real & (sa <= _CONE * se)
        frac_a, frac_e = along_a.any(1).mean(), along_e.any(1).mean()
        if frac_a < 0.05 and frac_e < 0.05:
            break
        if min(frac_a, frac_e) < 0.5 and max(frac_a, frac_e) >= 0.5:
            # one axis much coarser: stretch the other (finer) one and query again
            scale[0 if frac_e < 0.5 else 1] *= 4.0
            steps = (axis_step(da, along_a), axis_step(de, along_e))
            continue
        new = (axis_step(da, along_a), axis_step(de, along_e))
        if np.isnan(new[0]) or np.isnan(new[1]):
            steps = new
            break
        new_scale = 1.0 / np.asarray(new)
        new_scale /= new_scale.min()
        settled = np.allclose(new_scale / new_scale[0], scale / scale[0], rtol=0.05)
        steps, scale = new, new_scale
        if settled:
            break

    step_a, step_e = steps
    if np.isnan(step_a) and np.isnan(step_e):
        raise ValueError("cannot estimate the angular step: all points share one direction")
    # a single scan line (or column): use the other axis's step (inferred)
    step_a = step_e if np.isnan(step_a) else step_a
    step_e = step_a if np.isnan(step_e) else step_e
    return step_a, step_e


def _fit_axis(
    x: np.ndarray,
    step: float,
    *,
    refine: bool,
    start_span: float = 16.0,
    min_start_points: int = 500,
    growth: float = 4.0,
    search: tuple[float, float] = (0.75, 1.33),
    min_coherence: float = 0.1,
    max_points: int = 200_000,
    coherence_points: int = 5_000,
    seed: int = 1,
) -> tuple[float, float]:
    """Fit the regular grid ``x = offset + k * step`` to 1-D angles; returns (offset, step).

    The offset is the circular mean of ``x`` modulo the step (phase); when that mean's length
    is below ``min_coherence`` (inferred) the angles do not sit on this grid and the first
    pixel simply starts at the smallest angle. With ``refine`` the step is first searched in
    ``search`` x step for the largest phase coherence ``|mean exp(2 pi i x / step)|`` over the
    first ``start_span`` steps (robust to dropouts, which bias nearest-neighbour spacings),
    then re-fitted by least squares of ``x`` on the rounded grid index ``k`` over spans growing
    by ``growth``, so the index never slips while the span grows to the whole image (inferred
    refinement of spec 1.2's regular grid).
    """
    rng = np.random.default_rng(seed)
    if x.size > max_points:
        x = x[rng.choice(x.size, size=max_points, replace=False)]
    x0 = float(x.min())
    xs = x - x0
    extent = float(xs.max())

    def phase(vals: np.ndarray, s: float) -> float:
        z = np.exp(2j * np.pi * vals / s).mean()
        if abs(z) < min_coherence:  # angles not on this grid (e.g. a coarser step was given):
            return 0.5 * s * (1.0 - 1e-6)  # first pixel starts at the first angle
        return float(np.angle(z)) * s / (2 * np.pi)

    if not refine or extent <= 0:
        return x0 + phase(xs, step), step
    # 1) coarse step search by phase coherence over a short start window
    m = min(min_start_points, xs.size) - 1
    enough = float(np.partition(xs, m)[m])  # span holding min_start_points angles
    span = max(start_span, enough / step)
    win = xs[xs <= span * step]
    if win.size > coherence_points:
        win = win[rng.choice(win.size, size=coherence_points, replace=False)]
    cands = step * np.arange(search[0], search[1], 0.2 / span)
    coh = np.abs(np.exp(2j * np.pi * win[None, :] / cands[:, None]).mean(axis=1))
    if coh.max() < min_coherence:  # not a regular grid: keep the neighbour-spacing step
        return x0 + phase(xs, step), step
    step = float(cands[int(np.argmax(coh))])
    offset = phase(xs[xs <= span * step], step)
    # 2) least-squares refinement over growing spans
    while True:
        sel = xs[xs <= span * step]
        for _ in range(2):
            k = np.rint((sel - offset) / step)
            kc = k - k.mean()
            var = float(kc @ kc)
            if var <= 0:
                break
            step = float(kc @ (sel - sel.mean())) / var
            offset = float(sel.mean() - step * k.mean())
        if span * step >= extent:
            break
        span *= growth
    return x0 + offset, step


def _estimate_steps(a: np.ndarray, e: np.ndarray) -> tuple[float, float, float, float]:
    """(az_offset, az_step, el_offset, el_step) of the grid fitted to unwrapped az and -el."""
    step_a, step_e = _neighbour_steps(a, e)
    off_a, step_a = _fit_axis(a, step_a, refine=True)
    off_e, step_e = _fit_axis(-e, step_e, refine=True)
    return off_a, step_a, off_e, step_e


def _valid_points(xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz: expected an (n, 3) array, got shape {xyz.shape}")
    return np.isfinite(xyz).all(1) & (np.abs(xyz).sum(1) > 0)


def estimate_angular_step(xyz: np.ndarray) -> tuple[float, float]:
    """Scanner's angular step ``(az_step_deg, el_step_deg)`` estimated from an unorganised cloud.

    Spec 1.2: the range image is a regular (az, el) grid; its pitch is recovered from the
    points' own angular density (median nearest-neighbour spacing per axis, then a grid fit),
    so a sparse or irregular cloud projects without holes.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    xyz = xyz[_valid_points(xyz)]
    if xyz.shape[0] < 2:
        raise ValueError("cannot estimate the angular step from fewer than 2 points")
    _, az, el = spherical_angles(xyz)
    a, _ = _unwrapped_azimuth(az)
    _, step_a, _, step_e = _estimate_steps(a, el)
    return step_a, step_e


def nearest_per_pixel(flat_index: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """Indices of the nearest point (smallest range, spec 1.1 first return) in each pixel.

    One sort on a 64-bit key (pixel index, float32 range bits; positive floats sort like their
    bit patterns), then the first point of each pixel run.
    """
    r32 = np.ascontiguousarray(range_m, dtype=np.float32)
    key = (np.asarray(flat_index).astype(np.uint64) << np.uint64(32)) | r32.view(np.uint32).astype(
        np.uint64
    )
    order = np.argsort(key)
    fs = np.asarray(flat_index)[order]
    first = np.ones(fs.size, dtype=bool)
    first[1:] = fs[1:] != fs[:-1]
    return order[first]


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


def project_to_range_image(
    xyz: np.ndarray,
    rgb: np.ndarray | None = None,
    intensity: np.ndarray | None = None,
    *,
    angular_step_deg: float | tuple[float, float] | None = None,
    max_pixels: int = 100_000_000,
) -> RangeImage:
    """Organised range image (spec 1.2) from an unorganised scanner-frame cloud.

    ``angular_step_deg`` is a scalar or ``(az_step, el_step)``; None estimates it from the data
    (:func:`estimate_angular_step`). The image spans the data's azimuth/elevation extent; its
    first column's azimuth lies in [-180, 180) and later ones increase past it (the origin sits
    in the largest empty azimuth gap). Per pixel the nearest point is kept (first return);
    empty pixels are NaN. ``max_pixels`` (inferred) guards against a step far too fine.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    ok = _valid_points(xyz)
    n_in = xyz.shape[0]
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.shape != (n_in, 3):
            raise ValueError(f"rgb: expected shape {(n_in, 3)}, got {rgb.shape}")
        rgb = rgb[ok]
    if intensity is not None:
        intensity = np.asarray(intensity, dtype=np.float32).reshape(-1)
        if intensity.shape != (n_in,):
            raise ValueError(f"intensity: expected {n_in} values, got {intensity.shape}")
        intensity = intensity[ok]
    xyz = xyz[ok]
    if xyz.shape[0] == 0:
        raise ValueError("no valid points to project")
    r, az, el = spherical_angles(xyz)
    a, origin = _unwrapped_azimuth(az)
    if angular_step_deg is None:
        if xyz.shape[0] < 2:
            raise ValueError("cannot estimate the angular step from fewer than 2 points")
        off_a, step_a, off_e, step_e = _estimate_steps(a, el)
    else:
        step_a, step_e = _step_pair(angular_step_deg)
        off_a, _ = _fit_axis(a, step_a, refine=False)
        off_e, _ = _fit_axis(-el, step_e, refine=False)
    u = np.rint((a - off_a) / step_a).astype(np.int64)
    v = np.rint((-el - off_e) / step_e).astype(np.int64)
    u0, v0 = int(u.min()), int(v.min())
    u -= u0
    v -= v0
    rows, cols = int(v.max()) + 1, int(u.max()) + 1
    if rows * cols > max_pixels:
        raise ValueError(
            f"projection would need {rows} x {cols} pixels (angular step {step_a:.4g} x "
            f"{step_e:.4g} deg); give angular_step_deg"
        )
    azimuth = origin + off_a + (u0 + np.arange(cols)) * step_a
    azimuth -= 360.0 * np.floor((azimuth[0] + 180.0) / 360.0)
    elevation = -(off_e + (v0 + np.arange(rows)) * step_e)
    flat = v * cols + u
    keep = nearest_per_pixel(flat, r)
    rng_img = np.full(rows * cols, np.nan, dtype=np.float32)
    rng_img[flat[keep]] = r[keep]
    rgb_img = int_img = None
    if rgb is not None:
        rgb_img = np.zeros((rows * cols, 3), dtype=np.uint8)
        rgb_img[flat[keep]] = np.clip(np.rint(rgb[keep]), 0, 255).astype(np.uint8)
        rgb_img = rgb_img.reshape(rows, cols, 3)
    if intensity is not None:
        int_img = np.full(rows * cols, np.nan, dtype=np.float32)
        int_img[flat[keep]] = intensity[keep]
        int_img = int_img.reshape(rows, cols)
    return RangeImage(
        rng_img.reshape(rows, cols), azimuth, elevation, intensity=int_img, rgb=rgb_img
    )
