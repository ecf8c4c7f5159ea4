"""Spherical projection of an unorganised cloud into an organised range image (spec 1.2).

Spec 1.2 (inferred model): pixel (row v, column u) looks along elevation
``theta_v = theta_max - v * d_theta`` and azimuth ``alpha_u = alpha_0 + u * d_alpha``; the sensor
frame point is ``x = r cos(theta) cos(alpha), y = r cos(theta) sin(alpha), z = r sin(theta)``.
A scanner-frame cloud is mapped back onto such a grid: ``alpha = atan2(y, x)``,
``theta = atan2(z, hypot(x, y))``, rows top-down, the azimuth origin in the largest empty azimuth
gap (a 330 deg scan is not split); per pixel the nearest point (first return, spec 1.1) is kept.

The angular step is either given or estimated from the data's own angular density: the median
spacing between angular nearest neighbours along each axis, refined by fitting the regular grid
``x = offset + k * step`` to the angles over growing spans (so a step error never accumulates
into empty columns across a 3000-column image). Points anywhere inside their beam's cell
(Sylva's simulator), jittered, thinned or sampled from a point-cloud scene have no such grid
and nearer neighbours than their density (issue 18: 7 % filled), so (inferred) while fewer than
``min_fill`` of the pixels inside the scanned region hold a return (:func:`fill_ratio`) both
steps grow by the factor a Poisson fill ``1 - exp(-lambda s^2)`` predicts. No step is finer
than ``min_step_deg`` (params ``range_images``), nearest return per pixel.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.params import RangeImageParams

__all__ = [
    "estimate_angular_step",
    "fill_ratio",
    "nearest_per_pixel",
    "project_angles",
    "project_to_range_image",
    "spherical_angles",
]

_DEFAULTS = RangeImageParams()
_TINY_DEG = 1e-9  # angular differences below this are duplicates, not neighbours
_CONE = np.tan(np.radians(30.0))  # half-angle of the "along one axis" neighbour cone (inferred)
_FILL_POINTS = 3_000_000  # (inferred) above this, the fill of a trial step is measured on windows
_MOVE_PX = 0.85  # (inferred) farthest a point's direction from the centre of a pixel it may fill
_FRONT_M = 0.11  # (inferred) a pixel's front surface: ranges this near its nearest (Table 4.1)


def _xyz(xyz) -> np.ndarray:
    if np.ndim(xyz) != 2 or np.shape(xyz)[1] != 3:
        raise ValueError(f"xyz: expected an (n, 3) array, got shape {np.shape(xyz)}")
    return np.asarray(xyz, dtype=np.float64)


def spherical_angles(xyz: np.ndarray, y=None, z=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range, azimuth ``atan2(y, x)``, elevation ``atan2(z, hypot(x, y))`` (deg) of (n, 3) or x, y, z."""
    if y is None:
        xyz = np.asarray(xyz, dtype=np.float64)
        xyz, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    h = np.hypot(xyz, y)
    az = np.degrees(np.arctan2(y, xyz))
    el = np.degrees(np.arctan2(z, h))
    return np.hypot(h, z, out=h), az, el


def _azimuth_origin(az_deg: np.ndarray) -> float:
    """Azimuth (deg) just after the largest empty azimuth gap, wrap-around included: the gap
    is found on a 0.01 deg histogram of (at most ~2 M of) the azimuths, the origin is the
    smallest azimuth in the first occupied bin after it; with no empty bin (a dense full circle)
    the largest spacing between sorted azimuths in the least occupied bins is the gap."""
    az = np.asarray(az_deg, dtype=np.float64)
    n_bins, width = 36_000, 0.01

    def bins(x):
        return np.floor((x + 180.0) / width).astype(np.int64) % n_bins

    counts = np.bincount(bins(az[:: max(1, az.size // 2_000_000)]), minlength=n_bins)
    occ = np.flatnonzero(counts)
    gaps = np.diff(np.append(occ, occ[0] + n_bins))  # bins from an occupied bin to the next
    i = int(np.argmax(gaps))
    j = occ[(i + 1) % occ.size] if gaps[i] > 1 else int(np.argmin(counts))
    lo = j * width - 180.0 - width  # the bin, and the one before it (a sample may miss points)
    d = az - lo
    near = d[(d >= 0) & (d < 2 * width) | (d >= 360) & (d < 360 + 2 * width)
             | (d >= -360) & (d < 2 * width - 360)] % 360.0
    if gaps[i] > 1:
        return float(lo + near.min())
    s = np.sort(near)
    return float(lo + s[int(np.argmax(np.diff(s))) + 1 if s.size > 1 else 0])


def _unwrapped_azimuth(az_deg: np.ndarray) -> tuple[np.ndarray, float]:
    """Azimuths shifted to ``[0, 360)`` from the origin in the largest gap, and that origin."""
    a = az_deg - (origin := _azimuth_origin(az_deg))  # (np.mod of 30 M floats takes seconds)
    np.add(a, 360.0, out=a, where=a < 0)
    if a.size and a.max() >= 360.0:  # azimuths past +180 (an organised image's columns)
        a %= 360.0
    return a, origin


def _window_subset(a: np.ndarray, max_points: int, n_windows: int, rng) -> np.ndarray:
    """Indices of points inside a few random azimuth windows (full local density kept)."""
    n = a.size
    if n <= max_points:
        return np.arange(n)
    lo, hi = float(a.min()), float(a.max())
    n_buckets = 64 * n_windows * max(1, n // max_points)  # windows of 64 buckets, one pass
    table = np.zeros(n_buckets + 1, dtype=bool)
    for s in rng.integers(0, max(1, n_buckets - 64), size=n_windows):
        table[s:s + 64] = True
    idx = np.flatnonzero(table[((a - lo) * (n_buckets / max(hi - lo, 1e-12))).astype(np.int64)])
    return idx if idx.size >= 10 else rng.choice(n, size=max_points, replace=False)


def _neighbour_steps(a: np.ndarray, e: np.ndarray, *, max_points: int = 200_000,
                     n_queries: int = 20_000, k: int = 12, seed: int = 0) -> tuple[float, float]:
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


def _fit_axis(x: np.ndarray, step: float, *, refine: bool, start_span: float = 16.0,
              min_start_points: int = 2_000, growth: float = 2.0,
              search: tuple[float, float] = (0.75, 1.33), min_coherence: float = 0.1,
              max_points: int = 200_000, coherence_points: int = 5_000,
              seed: int = 1) -> tuple[float, float]:
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
    # 2) least-squares refinement over growing spans of whole grid lines (a span cut at an
    # angle would drop the jittered points beyond it and tilt the fit)
    while True:
        near = xs[xs <= offset + (span + 2) * step]
        for _ in range(2):
            k = np.rint((near - offset) / step)
            sel, k = near[k <= span], k[k <= span]
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


def estimate_angular_step(xyz: np.ndarray) -> tuple[float, float]:
    """Scanner's angular step ``(az_step_deg, el_step_deg)`` estimated from an unorganised cloud.

    Spec 1.2: the range image is a regular (az, el) grid; its pitch is recovered from the
    points' own angular density (median nearest-neighbour spacing per axis, then a grid fit).
    """
    with np.errstate(invalid="ignore"):
        r, az, el = spherical_angles(_xyz(xyz))
    ok = np.isfinite(r) & (r > 0)
    if np.count_nonzero(ok) < 2:
        raise ValueError("cannot estimate the angular step from fewer than 2 points")
    _, step_a, _, step_e = _estimate_steps(_unwrapped_azimuth(az[ok])[0], el[ok])
    return step_a, step_e


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


def _dilated(m: np.ndarray) -> np.ndarray:  # 3 x 3 dilation of a boolean image
    rows = m.copy()
    rows[1:] |= m[:-1]
    rows[:-1] |= m[1:]
    out = rows.copy()
    out[:, 1:] |= rows[:, :-1]
    out[:, :-1] |= rows[:, 1:]
    return out


def _pixels(a, el, off_a, step_a, off_e, step_e) -> tuple[np.ndarray, np.ndarray, int, int, int, int]:
    """Fractional column and row of each point from 0, grid indices of column and row 0, rows
    and columns of the image (in place after one copy each: 30 M floats)."""
    fu, fv = a - off_a, np.negative(el)
    fu /= step_a
    fv -= off_e
    fv /= step_e
    u0, v0 = int(np.rint(fu.min())), int(np.rint(fv.min()))
    fu -= u0
    fv -= v0
    return fu, fv, u0, v0, int(np.rint(fv.max())) + 1, int(np.rint(fu.max())) + 1


def _filling_steps(a, el, steps, offsets, min_fill: float, max_pixels: int) -> tuple[float, float]:
    """``steps`` scaled (both axes alike) until the image fills ``min_fill`` of its scanned region
    (``offsets(step_a, step_e)``: the grid's offsets; above ``_FILL_POINTS`` on windows)."""
    sub = _window_subset(a, _FILL_POINTS, 8, np.random.default_rng(2))
    a, el = a[sub], el[sub]
    scale = 1.0
    for _ in range(16):
        sa, se = steps[0] * scale, steps[1] * scale
        off_a, off_e = offsets(sa, se)
        fu, fv, _, _, rows, cols = _pixels(a, el, off_a, sa, off_e, se)
        if rows * cols > max_pixels:
            scale *= min(np.sqrt(rows * cols / max_pixels) * 1.01, 4.0)
            continue
        mask = np.zeros(rows * cols, dtype=bool)
        mask[np.rint(fv).astype(np.int64) * cols + np.rint(fu).astype(np.int64)] = True
        f = fill_ratio(mask.reshape(rows, cols))
        if f >= min_fill or min(rows, cols) < 3:
            break
        # Poisson fill 1 - exp(-lambda s^2): the scale that reaches min_fill (inferred)
        grow = np.sqrt(np.log1p(-min_fill) / np.log1p(-f)) if f > 0 else 3.0
        scale *= float(np.clip(grow * 1.01, 1.05, 3.0))
    return steps[0] * scale, steps[1] * scale


def _place(fu, fv, r, rows, cols) -> np.ndarray:
    """Pixel (flat index; -1: none) of each point (fractional column ``fu``, row ``fv``). A
    pixel keeps its front point (within ``_FRONT_M`` of the nearest: first return, spec 1.1)
    nearest its centre (inferred: the nearest of k noisy ranges is ~1 sigma short). A point left
    out may fill an empty pixel of the three on its offset's side within ``_MOVE_PX`` of its
    direction (jitter pushed it over the border; a second return behind the first stays)."""
    u, v = np.rint(fu).astype(np.int32), np.rint(fv).astype(np.int32)
    flat = v * cols + u  # < max_pixels < 2**31
    pix = np.full(r.size, -1, dtype=np.int32)
    r32 = np.asarray(r, dtype=np.float32)
    best = np.full(rows * cols, np.inf, dtype=np.float32)
    np.minimum.at(best, flat, r32)
    off2 = ((fu - u) ** 2 + (fv - v) ** 2 + 1e-6 * r32).astype(np.float32)  # ties: nearest
    keep = nearest_per_pixel(flat, np.where(r32 <= best[flat] + _FRONT_M, off2, np.inf))
    pix[keep] = flat[keep]
    taken = np.zeros((rows, cols), dtype=bool).reshape(-1)
    taken[flat[keep]] = True
    near = _dilated(~taken.reshape(rows, cols))  # pixels next to an empty one
    lose = np.flatnonzero(pix < 0)
    lose = lose[near.reshape(-1)[flat[lose]]]
    du, dv = (fu[lose] - u[lose]).astype(np.float32), (fv[lose] - v[lose]).astype(np.float32)
    su, sv = np.where(du >= 0, 1, -1).astype(np.int8), np.where(dv >= 0, 1, -1).astype(np.int8)
    dist = np.stack([np.hypot(1 - abs(du), dv), np.hypot(du, 1 - abs(dv)),
                     np.hypot(1 - abs(du), 1 - abs(dv))])  # beside, above/below, diagonal
    order = np.argsort(dist, axis=0).astype(np.int8)
    for rank in range(3):
        c = order[rank]
        tu = u[lose] + np.where(c == 1, 0, su)
        tv = v[lose] + np.where(c == 0, 0, sv)
        ok = np.take_along_axis(dist, c[None].astype(np.int64), 0)[0] <= _MOVE_PX
        ok &= (tu >= 0) & (tu < cols) & (tv >= 0) & (tv < rows)
        tf = np.where(ok, tv * cols + tu, 0)
        idx = np.flatnonzero(ok & ~taken[tf])
        won = idx[nearest_per_pixel(tf[idx], r[lose[idx]])]
        pix[lose[won]] = tf[won]
        taken[tf[won]] = True
        rest = np.ones(lose.size, dtype=bool)
        rest[won] = False
        lose, du, dv, su, sv = lose[rest], du[rest], dv[rest], su[rest], sv[rest]
        dist, order = dist[:, rest], order[:, rest]
    return pix


def _grid(a, el, given, min_step_deg, min_fill, max_pixels) -> tuple[float, float, float, float]:
    """(az_offset, az_step, el_offset, el_step) of the image: the ``given`` step, or the fitted
    grid coarsened to ``min_fill``; no step finer than ``min_step_deg``."""
    floor = max(float(min_step_deg or 0.0), 0.0)

    def offsets(sa: float, se: float) -> tuple[float, float]:
        if fitted is not None and (sa, se) == fitted[1::2]:
            return fitted[0], fitted[2]
        return _fit_axis(a, sa, refine=False)[0], _fit_axis(-el, se, refine=False)[0]

    fitted = None
    if given is None:
        fitted = _estimate_steps(a, el)
        step_a, step_e = max(fitted[1], floor), max(fitted[3], floor)
        if min_fill > 0:
            step_a, step_e = _filling_steps(a, el, (step_a, step_e), offsets, min_fill, max_pixels)
    else:
        step_a, step_e = (max(s, floor) for s in _step_pair(given))
    off_a, off_e = offsets(step_a, step_e)
    return off_a, step_a, off_e, step_e


def project_angles(range_m: np.ndarray, azimuth_deg: np.ndarray, elevation_deg: np.ndarray,
                   rgb: np.ndarray | None = None, intensity: np.ndarray | None = None, *,
                   angular_step_deg: float | tuple[float, float] | None = None,
                   min_step_deg: float = 0.0, min_fill: float = _DEFAULTS.min_fill,
                   max_pixels: int = 100_000_000) -> RangeImage:
    """Organised range image (spec 1.2) from per-point range, azimuth and elevation (scanner
    frame, :func:`spherical_angles`; a reader of a big file computes them chunk by chunk).

    ``angular_step_deg`` (scalar or (az, el)) is used as given; None estimates the scanner's
    grid (:func:`estimate_angular_step`), coarsened until ``min_fill`` of the scanned region
    is filled (:func:`fill_ratio`; 0: never); no axis finer than ``min_step_deg``. The first
    column's azimuth lies in [-180, 180), later ones increase past it; one point per pixel
    (:func:`_place`), NaN where none. ``max_pixels`` (inferred) guards against a step far too
    fine.
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
    ok = np.isfinite(r) & (r > 0) & np.isfinite(az) & np.isfinite(el)
    if not ok.all():
        r, az, el = r[ok], az[ok], el[ok]
        rgb = None if rgb is None else np.asarray(rgb)[ok]
        intensity = None if intensity is None else np.asarray(intensity).reshape(-1)[ok]
    if r.size == 0:
        raise ValueError("no valid points to project")
    a, origin = _unwrapped_azimuth(az)
    del az
    if angular_step_deg is None and r.size < 2:
        raise ValueError("cannot estimate the angular step from fewer than 2 points")
    off_a, step_a, off_e, step_e = _grid(a, el, angular_step_deg, min_step_deg, min_fill,
                                         max_pixels)
    fu, fv, u0, v0, rows, cols = _pixels(a, el, off_a, step_a, off_e, step_e)
    del a, el
    if rows * cols > max_pixels:
        raise ValueError(
            f"projection would need {rows} x {cols} pixels (angular step {step_a:.4g} x "
            f"{step_e:.4g} deg); give angular_step_deg"
        )
    azimuth = origin + off_a + (u0 + np.arange(cols)) * step_a
    azimuth -= 360.0 * np.floor((azimuth[0] + 180.0) / 360.0)
    elevation = -(off_e + (v0 + np.arange(rows)) * step_e)
    pix = _place(fu, fv, r, rows, cols)
    del fu, fv
    keep = np.flatnonzero(pix >= 0)
    at = pix[keep]
    del pix

    def image(values, empty, dtype, *shape):
        out = np.full((rows * cols, *shape), empty, dtype=dtype)
        out[at] = values
        return out.reshape(rows, cols, *shape)

    rgb_img = None if rgb is None else image(
        np.clip(np.rint(np.asarray(rgb)[keep]), 0, 255), 0, np.uint8, 3)
    int_img = None if intensity is None else image(
        np.asarray(intensity, dtype=np.float32).reshape(-1)[keep], np.nan, np.float32)
    return RangeImage(image(r[keep], np.nan, np.float32), azimuth, elevation,
                      intensity=int_img, rgb=rgb_img)


def project_to_range_image(
    xyz: np.ndarray,
    rgb: np.ndarray | None = None,
    intensity: np.ndarray | None = None,
    *,
    angular_step_deg: float | tuple[float, float] | None = None,
    min_step_deg: float = 0.0,
    min_fill: float = _DEFAULTS.min_fill,
    max_pixels: int = 100_000_000,
) -> RangeImage:
    """Organised range image (spec 1.2) from an unorganised scanner-frame cloud: the points'
    :func:`spherical_angles` projected by :func:`project_angles` (same keywords); points at
    the origin or not finite are dropped."""
    with np.errstate(invalid="ignore"):
        r, az, el = spherical_angles(_xyz(xyz))
    return project_angles(r, az, el, rgb, intensity, angular_step_deg=angular_step_deg,
                          min_step_deg=min_step_deg, min_fill=min_fill, max_pixels=max_pixels)
