"""The angular grid of a scanner-frame cloud (spec 1.2), for :mod:`forestmap_assets.io.projection`:
spherical angles, the azimuth origin in the largest empty azimuth gap, and the scanner's angular
step estimated from the data's own angular density: the median spacing between angular nearest
neighbours along each axis, refined by fitting the regular grid ``x = offset + k * step`` to the
angles over growing spans (so a step error never accumulates into empty columns across a
3000-column image).
"""

from __future__ import annotations

import numpy as np

from forestmap_assets.io._cloud_kernels import hypots
from forestmap_assets.io._projection_kernels import (
    azimuth_bins,
    azimuths_after,
    in_buckets,
    knn,
    min_after,
    min_max,
    unwrap,
)

__all__ = ["estimate_angular_step", "spherical_angles"]

_TINY_DEG = 1e-9  # angular differences below this are duplicates, not neighbours
_CONE = np.tan(np.radians(30.0))  # half-angle of the "along one axis" neighbour cone (inferred)


def _xyz(xyz) -> np.ndarray:
    if np.ndim(xyz) != 2 or np.shape(xyz)[1] != 3:
        raise ValueError(f"xyz: expected an (n, 3) array, got shape {np.shape(xyz)}")
    return np.asarray(xyz, dtype=np.float64)


def spherical_angles(xyz: np.ndarray, y=None, z=None, *, overwrite: bool = False
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range, azimuth ``atan2(y, x)``, elevation ``atan2(z, hypot(x, y))`` (deg) of (n, 3) or x, y, z.
    ``overwrite``: an (n, 3) float64 array stored column by column (Fortran order) may be used
    up: its x and y columns become the azimuth and elevation (no copy of the points)."""
    if y is None:
        xyz = np.asarray(xyz, dtype=np.float64)
        # the values of the code below in fewer passes: both hypots in one (on every core),
        # arctan2 on contiguous columns (3 times faster, same values), in place
        if overwrite and xyz.ndim == 2 and xyz.flags.f_contiguous:
            x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            h, r = np.empty(xyz.shape[0]), np.empty(xyz.shape[0])
        else:
            x, y, z, h, r = (np.empty(xyz.shape[0]) for _ in range(5))
            for i, c in enumerate((x, y, z)):
                c[:] = xyz[:, i]
        hypots(x, y, z, h, r)
        az = np.degrees(np.arctan2(y, x, out=x), out=x)
        return r, az, np.degrees(np.arctan2(z, h, out=y), out=y)
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
    counts = azimuth_bins(az, max(1, az.size // 2_000_000), n_bins, width)
    occ = np.flatnonzero(counts)
    gaps = np.diff(np.append(occ, occ[0] + n_bins))  # bins from an occupied bin to the next
    i = int(np.argmax(gaps))
    j = occ[(i + 1) % occ.size] if gaps[i] > 1 else int(np.argmin(counts))
    lo = j * width - 180.0 - width  # the bin, and the one before it (a sample may miss points)
    if gaps[i] > 1:  # the least (az - lo) % 360 in [0, 2 width)
        return float(lo + min_after(az, lo, 2 * width))
    s = np.sort(azimuths_after(az, lo, 2 * width))
    return float(lo + s[int(np.argmax(np.diff(s))) + 1 if s.size > 1 else 0])


def _unwrapped_azimuth(az_deg: np.ndarray, *, overwrite: bool = False
                       ) -> tuple[np.ndarray, float, tuple[float, float]]:
    """Azimuths shifted to ``[0, 360)`` from the origin in the largest gap (in place with
    ``overwrite``), that origin, and their least and greatest."""
    az = np.asarray(az_deg, dtype=np.float64)
    origin = _azimuth_origin(az)
    a = az if overwrite else np.empty(az.size)
    lo, hi = unwrap(az, origin, a)  # az - origin, + 360 where negative (np.mod: seconds)
    if hi >= 360.0:  # azimuths past +180 (an organised image's columns)
        a %= 360.0
        lo, hi = a.min(), a.max()
    return a, origin, (float(lo), float(hi))


def _window_subset(a: np.ndarray, max_points: int, n_windows: int, rng) -> np.ndarray:
    """Indices of points inside a few random azimuth windows (full local density kept)."""
    n = a.size
    if n <= max_points:
        return np.arange(n)
    lo, hi = (float(v) for v in min_max(a))
    n_buckets = 64 * n_windows * max(1, n // max_points)  # windows of 64 buckets, one pass
    table = np.zeros(n_buckets + 1, dtype=bool)
    for s in rng.integers(0, max(1, n_buckets - 64), size=n_windows):
        table[s:s + 64] = True
    idx = in_buckets(a, lo, n_buckets / max(hi - lo, 1e-12), table)
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
        x, y = a * scale[0], e * scale[1]
        nb = knn(x, y, q, k_eff + 1, _knn_cell(x, y))[:, 1:]  # (a k-d tree: 4 times slower)
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


def _knn_cell(x: np.ndarray, y: np.ndarray) -> float:
    """Cell side of :func:`~forestmap_assets.io._projection_kernels.knn` (only its speed
    depends on it): about 3 points in a typical point's cell, judged on a coarse grid."""
    w, h = float(np.ptp(x)), float(np.ptp(y))
    if max(w, h) <= 0:
        return 1.0
    c = max(float(np.sqrt(w * h * 64 / x.size)), max(w, h) / 1000)
    counts = np.bincount(((x - x.min()) / c).astype(np.int64) * (int(h / c) + 1)
                         + ((y - y.min()) / c).astype(np.int64))
    return c * float(np.sqrt(3 * x.size / (counts @ counts)))


def _coherence(x: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """``|mean exp(2 pi i x / s)|`` for each step ``s``: the phase reduced to half a cycle in
    float64, its cosine and sine in float32 (off by ~1e-7; complex exp is 30 times slower), in
    blocks of steps (small temporaries)."""
    out = np.empty(steps.size)
    block = max(1, 2**18 // max(x.size, 1))
    for b in range(0, steps.size, block):
        t = x[None, :] / steps[b:b + block, None]
        t -= np.rint(t)
        t *= 2 * np.pi
        t = t.astype(np.float32)
        out[b:b + block] = np.hypot(np.cos(t).mean(1, dtype=np.float64),
                                    np.sin(t).mean(1, dtype=np.float64))
    return out


def _fit_sample(a: np.ndarray, e: np.ndarray, *, max_points: int = 200_000,
                seed: int = 1) -> tuple[np.ndarray, np.ndarray, dict]:
    """The angles :func:`_fit_axis` fits: unwrapped az and -el of at most ``max_points``
    points drawn at random, with the state of the generator after the draw (one draw for both
    axes and every step tried)."""
    rng = np.random.default_rng(seed)
    if a.size > max_points:
        idx = rng.choice(a.size, size=max_points, replace=False)
        a, e = a[idx], e[idx]
    return a, -e, rng.bit_generator.state


def _fit_axis(x: np.ndarray, step: float, *, refine: bool, rng_state: dict | None = None,
              start_span: float = 16.0, min_start_points: int = 2_000, growth: float = 2.0,
              search: tuple[float, float] = (0.75, 1.33), min_coherence: float = 0.1,
              coherence_points: int = 5_000) -> tuple[float, float]:
    """Fit the regular grid ``x = offset + k * step`` to 1-D angles (of :func:`_fit_sample`,
    ``rng_state`` its generator's); returns (offset, step).

    The offset is the circular mean of ``x`` modulo the step (phase); when that mean's length
    is below ``min_coherence`` (inferred) the angles do not sit on this grid and the first
    pixel simply starts at the smallest angle. With ``refine`` the step is first searched in
    ``search`` x step for the largest phase coherence ``|mean exp(2 pi i x / step)|`` over the
    first ``start_span`` steps (robust to dropouts, which bias nearest-neighbour spacings),
    then re-fitted by least squares of ``x`` on the rounded grid index ``k`` over spans growing
    by ``growth``, so the index never slips while the span grows to the whole image (inferred
    refinement of spec 1.2's regular grid).
    """
    x0 = float(x.min())
    xs = x - x0
    extent = float(xs.max())

    def phase(vals: np.ndarray, s: float) -> float:
        # far below min_coherence (the float32 estimate is 1e-6 off) the exact mean is not needed
        far = _coherence(vals, np.array([s]))[0] < min_coherence - 1e-4
        z = 0.0 if far else np.exp(2j * np.pi * vals / s).mean()
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
        rng = np.random.default_rng(1)  # as _fit_sample's when it drew nothing
        if rng_state is not None:
            rng.bit_generator.state = rng_state
        win = win[rng.choice(win.size, size=coherence_points, replace=False)]
    cands = step * np.arange(search[0], search[1], 0.2 / span)
    coh = _coherence(win, cands)
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


def _estimate_steps(a: np.ndarray, e: np.ndarray,
                    sample: tuple | None = None) -> tuple[float, float, float, float]:
    """(az_offset, az_step, el_offset, el_step) of the grid fitted to unwrapped az and -el
    (``sample``: their :func:`_fit_sample`, if drawn already)."""
    step_a, step_e = _neighbour_steps(a, e)
    x_a, x_e, state = _fit_sample(a, e) if sample is None else sample
    off_a, step_a = _fit_axis(x_a, step_a, refine=True, rng_state=state)
    off_e, step_e = _fit_axis(x_e, step_e, refine=True, rng_state=state)
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
    _, step_a, _, step_e = _estimate_steps(_unwrapped_azimuth(az[ok], overwrite=True)[0],
                                            el[ok])
    return step_a, step_e
