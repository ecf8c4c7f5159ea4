"""Circle models of scan-line segments (spec 3; Th. 4.6.2-4.6.4, Table 4.2; JP II-A eqs (1)-(4)).

For every segment the inlier points of the segment and of its chain neighbours above and below
(spec 3.2) are projected on a plane through the sensor origin perpendicular to the current axis
estimate ``n`` (spec 3.1) and fitted with the linear least-squares circle

    a (x_pr^2 + z_pr^2) + b z_pr + c x_pr = 1                   (Eq. 4.10 / JP (3))

without re-centring (spec 3.3), inside the robust 3-sigma refit loop (spec 3.4). The circle is
tested (symmetry of the signed residuals, size, convexity, inlier count; spec 3.5),
back-projected along ``n`` by the mean projection distance (spec 3.6), and the axis of the next
iteration is estimated from neighbouring valid circle centres by the concatenation method
(spec 3.7). The initial phase uses a vertical axis, +-2 neighbour segments and a relaxed
symmetry test; then iterations follow until the circles are stable (spec 3.8).

Two engines compute the same thing. ``engine="numpy"``: all circles of an iteration are fitted
together; the points of every circle are gathered into one flat array grouped by circle, the
moment sums of all circles are accumulated with ``np.add.reduceat`` and solved as one stacked
system, and the robust loop only subtracts removed points and keeps the still-changing circles.
``engine="numba"`` (default when numba is installed): the same maths fused into one compiled
loop over circles (single thread), about 8x faster on a full 3000 x 720 image. Both are tested to
agree. No Python loop runs per segment or per point.

Optional refinements (``fit``, applied to the final circles): ``"geometric"``
(orthogonal-distance Gauss-Newton after the linear fit) and ``"ray"`` (inferred: maximum
likelihood under range noise along ideal, infinitely thin beams). With 2.5 cm range noise and
ideal beams the thesis' linear fit underestimates trunk radii by 2-3 cm on a half-visible
contour and ``"ray"`` removes most of that; with a wide first-return beam (mixed pixels widen
objects, spec 1.1) the two effects largely cancel for the linear fit while ``"ray"``
overestimates, so the thesis' linear fit stays the default (numbers in benchmarks/results.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.core.features.segments import pixel_xyz, segment_pixels
from forestmap_assets.params import CircleParams, SegmentationParams

try:  # optional accelerator: same maths as the numpy engine, fused per circle
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba missing: the numpy engine is used
    HAVE_NUMBA = False

CIRCLE_COLUMNS: dict[str, str] = {
    "iteration": "int64",
    "segment_id": "int64",
    "row": "int64",
    "chain_id": "int64",
    "cx": "float64",
    "cy": "float64",
    "cz": "float64",
    "radius_m": "float64",
    "nx": "float64",
    "ny": "float64",
    "nz": "float64",
    "n_points": "int64",
    "n_inliers": "int64",
    "mean_residual_m": "float64",
    "rms_residual_m": "float64",
    "valid": "bool",
    "reject_reason": "str",
}

REJECT_REASONS = ("", "fit", "too_few_points", "size", "convexity", "symmetry", "no_axis")


def empty_circles() -> pd.DataFrame:
    """A well-formed circle-model table with no rows."""
    return pd.DataFrame({k: pd.Series([], dtype=v) for k, v in CIRCLE_COLUMNS.items()})


# ------------------------------------------------------------------------------------------
# Batched 2-D circle fitting
# ------------------------------------------------------------------------------------------

def _reduce(values: np.ndarray, ptr: np.ndarray) -> np.ndarray:
    """Sums of ``values`` (n, ...) over contiguous groups ``ptr`` (empty groups give 0)."""
    counts = np.diff(ptr)
    if values.shape[0] == 0:
        return np.zeros((counts.size,) + values.shape[1:])
    start = np.minimum(ptr[:-1], values.shape[0] - 1)
    out = np.add.reduceat(values, start, axis=0)
    out[counts == 0] = 0.0
    return out


def _solve_stacked(m: np.ndarray, rhs: np.ndarray, ridge: float = 0.0
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Solve stacked symmetric k x k systems with diagonal equilibration; (solution, ok).

    ``ridge`` is added to the equilibrated diagonal (unit diagonal), so that an exactly
    singular moment matrix still yields its null direction (see :func:`_linear_circle`).
    """
    k = m.shape[-1]
    d = np.sqrt(np.abs(np.einsum("nii->ni", m)))
    ok = np.all(d > 0, axis=1) & np.all(np.isfinite(m), axis=(1, 2))
    d = np.where(ok[:, None], d, 1.0)
    ms = m / d[:, :, None] / d[:, None, :]
    ms[~ok] = np.eye(k)
    if ridge:
        ms = ms + ridge * np.eye(k)
    rs = np.where(ok[:, None], rhs / d, 0.0)
    with np.errstate(invalid="ignore", over="ignore"):
        cond_ok = np.abs(np.linalg.det(ms)) > 1e-15
    ms[~cond_ok] = np.eye(k)
    ok &= cond_ok
    try:
        y = np.linalg.solve(ms, rs[..., None])[..., 0]
    except np.linalg.LinAlgError:  # pragma: no cover - guarded by the determinant test
        y = np.einsum("nij,nj->ni", np.linalg.pinv(ms), rs)
    return y / d, ok


def _linear_circle(sums: np.ndarray, ref: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, ...]:
    """Least-squares circle of Eq. 4.10, a (x^2 + z^2) + b z + c x = 1, from local moments.

    The points are written q = ref + sigma * d (ref, sigma per group: a computational frame
    only). Eq. 4.10 becomes A |d|^2 + B d_z + C d_x + D = 0 with (A, B, C, D) linear in (a, b, c)
    and the normalisation "= 1" turning into the linear constraint l . (A, B, C, D) = -1,
    l = (|ref|^2 / sigma^2, -z_ref / sigma, -x_ref / sigma, 1). Minimising the same sum of
    squared residuals under that constraint gives phi = -S^-1 l / (l' S^-1 l) with
    S = sum m m', m = (|d|^2, d_z, d_x, 1): exactly the least-squares solution of Eq. 4.10
    (no re-centring of the model), computed from well-conditioned moments. Returns local
    centre (dx0, dz0), local radius and ok (a < 0, i.e. the sensor is outside the circle).

    ``sums`` columns: d4, d2z, d2x, d2, zz, zx, z, xx, x, n.
    """
    d4, d2z, d2x, d2, zz, zx, z, xx, x, n = (sums[:, i] for i in range(10))
    m = np.stack([np.stack([d4, d2z, d2x, d2], -1), np.stack([d2z, zz, zx, z], -1),
                  np.stack([d2x, zx, xx, x], -1), np.stack([d2, z, x, n], -1)], -2)
    ell = np.stack([(ref[:, 0] ** 2 + ref[:, 1] ** 2) / sigma**2, -ref[:, 1] / sigma,
                    -ref[:, 0] / sigma, np.ones(sigma.size)], -1)
    ell /= np.linalg.norm(ell, axis=1, keepdims=True)
    # S is singular for noise-free points on a circle (its null vector is the solution); the
    # tiny ridge keeps the solve finite and returns that null direction in the limit.
    y, ok = _solve_stacked(m, ell, ridge=1e-13)
    with np.errstate(invalid="ignore", divide="ignore"):
        phi = -y / np.sum(ell * y, axis=1, keepdims=True)
        a_, b_, c_, d_ = phi[:, 0], phi[:, 1], phi[:, 2], phi[:, 3]
        cx = -c_ / (2 * a_)
        cz = -b_ / (2 * a_)
        r2 = cx * cx + cz * cz - d_ / a_
        ok &= np.isfinite(r2) & (r2 > 0) & (a_ < 0) & (n >= 3)
        r = np.sqrt(np.where(ok, r2, np.nan))
    return cx, cz, r, ok


def _products(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    s = x * x + z * z
    return np.stack([s * s, s * z, s * x, s, z * z, z * x, z, x * x, x, np.ones_like(x)], -1)


@dataclass
class CircleFitResult:
    """Per-group result of :func:`fit_circles_2d` (in input units)."""

    x0: np.ndarray
    z0: np.ndarray
    r: np.ndarray
    ok: np.ndarray
    n_inliers: np.ndarray
    mean_residual: np.ndarray
    rms_residual: np.ndarray
    mean_h: np.ndarray
    mean_dist: np.ndarray
    inlier: np.ndarray  # per input point


def _gauss_newton(x, z, w, ptr, x0, z0, r, iterations):
    """Geometric (orthogonal-distance) refinement of circles, batched Gauss-Newton."""
    counts = np.diff(ptr)
    wf = w.astype(np.float64)
    for _ in range(iterations):
        X0, Z0, R = (np.repeat(v, counts) for v in (x0, z0, r))
        dx, dz = x - X0, z - Z0
        d = np.sqrt(dx * dx + dz * dz)
        d = np.where(d > 0, d, 1e-12)
        jx, jz = -dx / d * wf, -dz / d * wf
        e = (d - R) * wf
        sums = _reduce(np.stack([jx * jx, jx * jz, -jx, jz * jz, -jz, wf,
                                 jx * e, jz * e, -e], -1), ptr)
        m = np.stack([np.stack([sums[:, 0], sums[:, 1], sums[:, 2]], -1),
                      np.stack([sums[:, 1], sums[:, 3], sums[:, 4]], -1),
                      np.stack([sums[:, 2], sums[:, 4], sums[:, 5]], -1)], -2)
        step, ok = _solve_stacked(m, -sums[:, 6:9])
        step = np.where(ok[:, None] & np.isfinite(step), step, 0.0)
        x0, z0, r = x0 + step[:, 0], z0 + step[:, 1], r + step[:, 2]
    return x0, z0, np.abs(r)


def _ray_terms(x, z, ox, oz, cx, cz, r):
    """Residuals and Jacobian rows of the along-beam (range) circle model, per point.

    The beam of a point runs from the projected sensor origin o through the point; r1 is the
    measured range minus the range of the beam's first intersection with the circle, and for a
    beam missing the circle r2 is its miss distance (zero otherwise), which keeps the residual
    continuous at grazing incidence. Returns (r1, r2, J1 (n, 3), J2 (n, 3)) for (cx, cz, r).
    """
    vx, vz = x - ox, z - oz
    rho = np.sqrt(vx * vx + vz * vz)
    rho = np.where(rho > 0, rho, 1e-12)
    ux, uz = vx / rho, vz / rho
    px, pz = cx - ox, cz - oz
    along = ux * px + uz * pz
    mx, mz = px - along * ux, pz - along * uz  # centre minus its foot on the beam
    m = np.sqrt(mx * mx + mz * mz)
    hit = m < r
    s = np.sqrt(np.maximum(r * r - m * m, 0.0))
    sc = np.maximum(s, 1e-3 * r)
    r1 = rho - (along - s)
    j1 = np.stack([-(ux + np.where(hit, mx / sc, 0.0)), -(uz + np.where(hit, mz / sc, 0.0)),
                   np.where(hit, r / sc, 0.0)], -1)
    r2 = np.where(hit, 0.0, m - r)
    mm = np.where(m > 0, m, 1.0)
    j2 = np.where(hit[:, None], 0.0, np.stack([mx / mm, mz / mm, -np.ones_like(m)], -1))
    return r1, r2, j1, j2


def _ray_refine(x, z, w, ptr, ox, oz, x0, z0, r, iterations):
    """Damped Gauss-Newton (Levenberg-Marquardt) fit of the along-beam circle model (inferred:
    maximum likelihood for range noise along the beams), batched over groups."""
    counts = np.diff(ptr)
    wf = w.astype(np.float64)
    lam = np.full(x0.size, 1e-3)
    active = np.ones(x0.size, bool)

    def cost_terms(cx, cz, rr):
        args = [np.repeat(v, counts) for v in (ox, oz, cx, cz, rr)]
        r1, r2, j1, j2 = _ray_terms(x, z, *args)
        return r1 * wf, r2 * wf, j1 * wf[:, None], j2 * wf[:, None]

    r1, r2, j1, j2 = cost_terms(x0, z0, r)
    cost = _reduce(r1 * r1 + r2 * r2, ptr)
    for _ in range(iterations):
        jtj = _reduce((j1[:, :, None] * j1[:, None, :] + j2[:, :, None] * j2[:, None, :])
                      .reshape(-1, 9), ptr).reshape(-1, 3, 3)
        jtr = _reduce(j1 * r1[:, None] + j2 * r2[:, None], ptr)
        damped = jtj + lam[:, None, None] * np.einsum("nii->ni", jtj)[:, :, None] * np.eye(3)
        step, ok = _solve_stacked(damped, -jtr)
        step = np.where(ok[:, None] & np.isfinite(step), step, 0.0)
        nx0, nz0, nr = x0 + step[:, 0], z0 + step[:, 1], np.abs(r + step[:, 2])
        t1, t2, k1, k2 = cost_terms(nx0, nz0, nr)
        ncost = _reduce(t1 * t1 + t2 * t2, ptr)
        moved = np.abs(step).max(1) > 1e-12 * np.maximum(np.abs(r), 1.0)
        acc = active & ok & (ncost < cost)
        x0, z0, r = np.where(acc, nx0, x0), np.where(acc, nz0, z0), np.where(acc, nr, r)
        cost = np.where(acc, ncost, cost)
        lam = np.where(acc, lam / 3.0, lam * 4.0)
        active &= ~(acc & ~moved)  # an accepted negligible step: converged
        if not active.any():
            break
        pa = np.repeat(acc, counts)
        r1, r2 = np.where(pa, t1, r1), np.where(pa, t2, r2)
        j1, j2 = np.where(pa[:, None], k1, j1), np.where(pa[:, None], k2, j2)
    return x0, z0, r


def _fit_groups_numpy(x: np.ndarray, z: np.ndarray, ptr: np.ndarray, *,
                      h: np.ndarray | None = None, fit: str = "linear",
                      robust_sigmas: float = 3.0, max_rounds: int = 10, min_points: int = 4,
                      gn_iterations: int = 6, ray_iterations: int = 20) -> CircleFitResult:
    """Robust circle fits of many point groups at once (spec 3.3-3.4).

    ``x, z``: projected coordinates (x_pr, z_pr) grouped contiguously by ``ptr`` (n_groups+1);
    the origin is the projected sensor origin, which matters because the "= 1" normalisation
    of Eq. 4.10 is not translation invariant (the model is never re-centred; see
    :func:`_linear_circle` for the numerically stable evaluation). The numpy engine of
    :func:`fit_circles_2d` (which documents the parameters); ``mean_dist`` is the inliers'
    mean distance from the origin (for the convexity check).
    """
    ptr = np.asarray(ptr, np.int64)
    n_groups = ptr.size - 1
    counts = np.diff(ptr)
    x = np.asarray(x, np.float64)
    z = np.asarray(z, np.float64)
    hh = np.zeros_like(x) if h is None else np.asarray(h, np.float64)
    out = {k: np.full(n_groups, np.nan) for k in ("x0", "z0", "r", "me", "rms", "mh", "md")}
    n_inl = np.zeros(n_groups, np.int64)
    ok_out = np.zeros(n_groups, bool)
    inlier = np.zeros(x.size, bool)

    gid = np.flatnonzero(counts > 0)  # live groups (global ids)
    pidx = np.flatnonzero(np.repeat(counts > 0, counts))  # live points (global ids)
    cnt = counts[gid]
    lptr = np.concatenate([[0], np.cumsum(cnt)])
    # computational frame per group: mean point and spread (not a re-centring of the model)
    ref = _reduce(np.stack([x[pidx], z[pidx]], -1), lptr) / cnt[:, None]
    rx, rz = np.repeat(ref[:, 0], cnt), np.repeat(ref[:, 1], cnt)
    spread = np.sqrt(_reduce((x[pidx] - rx) ** 2 + (z[pidx] - rz) ** 2, lptr) / cnt)
    sigma = np.where(spread > 0, spread, 1.0)
    sg = np.repeat(sigma, cnt)
    lx, lz = (x[pidx] - rx) / sg, (z[pidx] - rz) / sg
    lh = hh[pidx]
    dist = np.hypot(x[pidx], z[pidx])
    w = np.ones(lx.size, bool)
    sums = _reduce(np.concatenate([_products(lx, lz), np.stack([lh, dist], -1)], -1), lptr)
    for rnd in range(max_rounds + 1):
        if gid.size == 0:
            break
        x0, z0, r, ok = _linear_circle(sums[:, :10], ref, sigma)
        cnt = np.diff(lptr)
        X0, Z0, R = (np.repeat(np.where(ok, v, 0.0), cnt) for v in (x0, z0, r))
        e = np.sqrt((lx - X0) ** 2 + (lz - Z0) ** 2) - R
        ew = np.where(w, e, 0.0)
        st = _reduce(np.stack([ew, ew * ew], -1), lptr)
        ne = sums[:, 9]
        with np.errstate(invalid="ignore", divide="ignore"):
            me = st[:, 0] / ne
            msq = st[:, 1] / ne
            sd = np.sqrt(np.maximum(msq - me * me, 0.0))
        remove = w & (np.abs(e) > robust_sigmas * np.repeat(sd, cnt)) & np.repeat(ok, cnt)
        nrem = _reduce(remove.astype(np.float64), lptr)
        done = (nrem == 0) | (ne - nrem < min_points) | ~ok | (rnd == max_rounds)
        if done.any():
            g = gid[done]
            sc = sigma[done]
            if fit in ("geometric", "ray"):  # algebraic-then-geometric, on the final inliers
                pd_ = np.repeat(done, cnt)
                dptr = np.concatenate([[0], np.cumsum(cnt[done])])
                okd = ok[done]
                gx, gz, gr = _gauss_newton(lx[pd_], lz[pd_], w[pd_], dptr,
                                           np.where(okd, x0[done], 0.0),
                                           np.where(okd, z0[done], 0.0),
                                           np.where(okd, r[done], 1.0), gn_iterations)
                if fit == "ray":
                    gx, gz, gr = _ray_refine(lx[pd_], lz[pd_], w[pd_], dptr, -ref[done, 0] / sc,
                                             -ref[done, 1] / sc, gx, gz, gr, ray_iterations)
                x0, z0, r = x0.copy(), z0.copy(), r.copy()
                x0[done] = np.where(okd, gx, x0[done])
                z0[done] = np.where(okd, gz, z0[done])
                r[done] = np.where(okd & np.isfinite(gr), gr, r[done])
            out["x0"][g] = ref[done, 0] + x0[done] * sc
            out["z0"][g] = ref[done, 1] + z0[done] * sc
            out["r"][g] = r[done] * sc
            out["me"][g] = me[done] * sc
            out["rms"][g] = np.sqrt(msq[done]) * sc
            with np.errstate(invalid="ignore", divide="ignore"):
                out["mh"][g] = sums[done, 10] / ne[done]
                out["md"][g] = sums[done, 11] / ne[done]
            n_inl[g] = ne[done].astype(np.int64)
            ok_out[g] = ok[done]
            inlier[pidx[np.repeat(done, cnt) & w]] = True
        if done.all():
            break
        # drop the outliers of the continuing groups and subtract their contributions
        keep_g = ~done
        rem = remove & np.repeat(keep_g, cnt)
        ridx = np.flatnonzero(rem)
        grp = np.repeat(np.arange(gid.size), cnt)[ridx]
        sub = np.concatenate([_products(lx[ridx], lz[ridx]),
                              np.stack([lh[ridx], dist[ridx]], -1)], -1)
        delta = np.zeros_like(sums)
        np.add.at(delta, grp, sub)
        sums = sums - delta
        w = w & ~rem
        # compact to the continuing groups
        pk = np.repeat(keep_g, cnt)
        gid, sums, ref, sigma = gid[keep_g], sums[keep_g], ref[keep_g], sigma[keep_g]
        lptr = np.concatenate([[0], np.cumsum(cnt[keep_g])])
        pidx, lx, lz, lh, w, dist = (a[pk] for a in (pidx, lx, lz, lh, w, dist))
    return CircleFitResult(out["x0"], out["z0"], out["r"], ok_out, n_inl, out["me"], out["rms"],
                           out["mh"], out["md"], inlier)


# ------------------------------------------------------------------------------------------
# numba engine: the same computation, one circle per loop iteration (compiled, cached)
# ------------------------------------------------------------------------------------------

if HAVE_NUMBA:

    @njit(cache=True)
    def _nb_solve(m, rhs, ridge):  # pragma: no cover - compiled
        """Equilibrated k x k solve with partial pivoting, mirrors :func:`_solve_stacked`."""
        k = rhs.size
        d = np.empty(k)
        ok = True
        for i in range(k):
            d[i] = np.sqrt(abs(m[i, i]))
            if not (d[i] > 0) or not np.isfinite(d[i]):
                ok = False
        y = np.zeros(k)
        if not ok:
            return y, False
        a = np.empty((k, k))
        b = np.empty(k)
        for i in range(k):
            for j in range(k):
                a[i, j] = m[i, j] / d[i] / d[j]
                if not np.isfinite(a[i, j]):
                    return y, False
            a[i, i] += ridge
            b[i] = rhs[i] / d[i]
        det = 1.0
        for c in range(k):
            piv = c
            for i in range(c + 1, k):
                if abs(a[i, c]) > abs(a[piv, c]):
                    piv = i
            if piv != c:
                det = -det
                for j in range(k):
                    a[c, j], a[piv, j] = a[piv, j], a[c, j]
                b[c], b[piv] = b[piv], b[c]
            det *= a[c, c]
            if a[c, c] == 0.0:
                return y, False
            for i in range(c + 1, k):
                f = a[i, c] / a[c, c]
                for j in range(c, k):
                    a[i, j] -= f * a[c, j]
                b[i] -= f * b[c]
        if not (abs(det) > 1e-15):
            return y, False
        for i in range(k - 1, -1, -1):
            acc = b[i]
            for j in range(i + 1, k):
                acc -= a[i, j] * y[j]
            y[i] = acc / a[i, i]
        for i in range(k):
            y[i] /= d[i]
        return y, True

    @njit(cache=True)
    def _nb_linear_circle(sm, rx, rz, sigma):  # pragma: no cover - compiled
        """Eq. 4.10 least-squares circle from local moments, mirrors :func:`_linear_circle`."""
        m = np.empty((4, 4))
        m[0, 0], m[0, 1], m[0, 2], m[0, 3] = sm[0], sm[1], sm[2], sm[3]
        m[1, 1], m[1, 2], m[1, 3] = sm[4], sm[5], sm[6]
        m[2, 2], m[2, 3] = sm[7], sm[8]
        m[3, 3] = sm[9]
        for i in range(4):
            for j in range(i):
                m[i, j] = m[j, i]
        ell = np.array([(rx * rx + rz * rz) / sigma**2, -rz / sigma, -rx / sigma, 1.0])
        ell /= np.sqrt(np.sum(ell * ell))
        y, ok = _nb_solve(m, ell, 1e-13)
        if not ok:
            return 0.0, 0.0, np.nan, False
        den = np.sum(ell * y)
        a_, b_, c_, d_ = -y[0] / den, -y[1] / den, -y[2] / den, -y[3] / den
        cx = -c_ / (2 * a_)
        cz = -b_ / (2 * a_)
        r2 = cx * cx + cz * cz - d_ / a_
        if not (np.isfinite(r2) and r2 > 0 and a_ < 0 and sm[9] >= 3):
            return cx, cz, np.nan, False
        return cx, cz, np.sqrt(r2), True

    @njit(cache=True)
    def _nb_gauss_newton(lx, lz, w, x0, z0, r, iterations):  # pragma: no cover - compiled
        m = np.empty((3, 3))
        g = np.empty(3)
        for _ in range(iterations):
            m[:] = 0.0
            g[:] = 0.0
            for i in range(lx.size):
                if not w[i]:
                    continue
                dx, dz = lx[i] - x0, lz[i] - z0
                d = np.sqrt(dx * dx + dz * dz)
                if not d > 0:
                    d = 1e-12
                jx, jz = -dx / d, -dz / d
                e = d - r
                m[0, 0] += jx * jx
                m[0, 1] += jx * jz
                m[0, 2] += -jx
                m[1, 1] += jz * jz
                m[1, 2] += -jz
                m[2, 2] += 1.0
                g[0] -= jx * e
                g[1] -= jz * e
                g[2] += e
            m[1, 0], m[2, 0], m[2, 1] = m[0, 1], m[0, 2], m[1, 2]
            step, ok = _nb_solve(m, g, 0.0)
            if ok and np.isfinite(step[0]) and np.isfinite(step[1]) and np.isfinite(step[2]):
                x0, z0, r = x0 + step[0], z0 + step[1], r + step[2]
        return x0, z0, abs(r)

    @njit(cache=True)
    def _nb_ray_cost(lx, lz, w, ox, oz, cx, cz, r, jtj, jtr):  # pragma: no cover - compiled
        """Cost of the along-beam model; fills J'J and J'r (mirrors :func:`_ray_terms`)."""
        jtj[:] = 0.0
        jtr[:] = 0.0
        cost = 0.0
        j = np.empty(3)
        for i in range(lx.size):
            if not w[i]:
                continue
            vx, vz = lx[i] - ox, lz[i] - oz
            rho = np.sqrt(vx * vx + vz * vz)
            if not rho > 0:
                rho = 1e-12
            ux, uz = vx / rho, vz / rho
            px, pz = cx - ox, cz - oz
            along = ux * px + uz * pz
            mx, mz = px - along * ux, pz - along * uz
            m = np.sqrt(mx * mx + mz * mz)
            if m < r:
                s = np.sqrt(max(r * r - m * m, 0.0))
                sc = max(s, 1e-3 * r)
                e = rho - (along - s)
                j[0], j[1], j[2] = -(ux + mx / sc), -(uz + mz / sc), r / sc
            else:
                e = rho - along
                j[0], j[1], j[2] = -ux, -uz, 0.0
                mm = m if m > 0 else 1.0
                e2 = m - r
                cost += e2 * e2
                j2x, j2z = mx / mm, mz / mm
                jtj[0, 0] += j2x * j2x
                jtj[0, 1] += j2x * j2z
                jtj[0, 2] -= j2x
                jtj[1, 1] += j2z * j2z
                jtj[1, 2] -= j2z
                jtj[2, 2] += 1.0
                jtr[0] += j2x * e2
                jtr[1] += j2z * e2
                jtr[2] -= e2
            cost += e * e
            for a in range(3):
                jtr[a] += j[a] * e
                for b in range(a, 3):
                    jtj[a, b] += j[a] * j[b]
        jtj[1, 0], jtj[2, 0], jtj[2, 1] = jtj[0, 1], jtj[0, 2], jtj[1, 2]
        return cost

    @njit(cache=True)
    def _nb_ray_refine(lx, lz, w, ox, oz, cx, cz, r, iterations):  # pragma: no cover
        """Levenberg-Marquardt fit of the along-beam model, mirrors :func:`_ray_refine`."""
        jtj = np.empty((3, 3))
        jtr = np.empty(3)
        njtj = np.empty((3, 3))
        njtr = np.empty(3)
        lam = 1e-3
        cost = _nb_ray_cost(lx, lz, w, ox, oz, cx, cz, r, jtj, jtr)
        damped = np.empty((3, 3))
        for _ in range(iterations):
            for a in range(3):
                for b in range(3):
                    damped[a, b] = jtj[a, b]
                damped[a, a] += lam * jtj[a, a]
            step, ok = _nb_solve(damped, -jtr, 0.0)
            if not (ok and np.isfinite(step[0]) and np.isfinite(step[1])
                    and np.isfinite(step[2])):
                step[:] = 0.0
            ncx, ncz, nr = cx + step[0], cz + step[1], abs(r + step[2])
            ncost = _nb_ray_cost(lx, lz, w, ox, oz, ncx, ncz, nr, njtj, njtr)
            moved = max(abs(step[0]), abs(step[1]), abs(step[2])) > 1e-12 * max(abs(r), 1.0)
            if ok and ncost < cost:
                cx, cz, r, cost = ncx, ncz, nr, ncost
                jtj[:] = njtj
                jtr[:] = njtr
                lam /= 3.0
                if not moved:
                    break
            else:
                lam *= 4.0
        return cx, cz, r

    @njit(cache=True)
    def _nb_robust_fit(x, z, h, geometric, sigmas, max_rounds, min_points, gn_iterations,
                       inlier):  # pragma: no cover - compiled
        """Robust fit of one group, mirrors :func:`_fit_groups_numpy`; fills ``inlier``."""
        n = x.size
        out = np.full(8, np.nan)  # x0, z0, r, me, rms, mh, md, ne
        if n == 0:
            out[7] = 0
            return out, False
        rx, rz = np.mean(x), np.mean(z)
        sp = 0.0
        for i in range(n):
            sp += (x[i] - rx) ** 2 + (z[i] - rz) ** 2
        sigma = np.sqrt(sp / n)
        if not sigma > 0:
            sigma = 1.0
        lx = (x - rx) / sigma
        lz = (z - rz) / sigma
        dist = np.sqrt(x * x + z * z)
        w = np.ones(n, dtype=np.bool_)
        sm = np.zeros(12)
        for i in range(n):
            q = lx[i] * lx[i] + lz[i] * lz[i]
            sm[0] += q * q
            sm[1] += q * lz[i]
            sm[2] += q * lx[i]
            sm[3] += q
            sm[4] += lz[i] * lz[i]
            sm[5] += lz[i] * lx[i]
            sm[6] += lz[i]
            sm[7] += lx[i] * lx[i]
            sm[8] += lx[i]
            sm[9] += 1.0
            sm[10] += h[i]
            sm[11] += dist[i]
        e = np.empty(n)
        ok = False
        for rnd in range(max_rounds + 1):
            cx, cz, r, ok = _nb_linear_circle(sm, rx, rz, sigma)
            if not ok:
                cx, cz, r0 = cx, cz, 0.0
            else:
                r0 = r
            se = 0.0
            se2 = 0.0
            for i in range(n):
                if w[i]:
                    e[i] = np.sqrt((lx[i] - (cx if ok else 0.0)) ** 2
                                   + (lz[i] - (cz if ok else 0.0)) ** 2) - r0
                    se += e[i]
                    se2 += e[i] * e[i]
            ne = sm[9]
            me = se / ne
            msq = se2 / ne
            sd = np.sqrt(max(msq - me * me, 0.0))
            nrem = 0
            if ok:
                for i in range(n):
                    if w[i] and abs(e[i]) > sigmas * sd:
                        nrem += 1
            if nrem == 0 or ne - nrem < min_points or not ok or rnd == max_rounds:
                if geometric > 0 and ok:  # algebraic-then-geometric refinement on the inliers
                    gx, gz, gr = _nb_gauss_newton(lx, lz, w, cx, cz, r, gn_iterations)
                    if geometric > 1:
                        gx, gz, gr = _nb_ray_refine(lx, lz, w, -rx / sigma, -rz / sigma,
                                                    gx, gz, gr, 20)
                    if np.isfinite(gr):
                        cx, cz, r = gx, gz, gr
                out[0] = rx + cx * sigma
                out[1] = rz + cz * sigma
                out[2] = r * sigma
                out[3] = me * sigma
                out[4] = np.sqrt(msq) * sigma
                out[5] = sm[10] / ne
                out[6] = sm[11] / ne
                out[7] = ne
                for i in range(n):
                    inlier[i] = w[i]
                return out, ok
            for i in range(n):
                if w[i] and abs(e[i]) > sigmas * sd:
                    w[i] = False
                    q = lx[i] * lx[i] + lz[i] * lz[i]
                    sm[0] -= q * q
                    sm[1] -= q * lz[i]
                    sm[2] -= q * lx[i]
                    sm[3] -= q
                    sm[4] -= lz[i] * lz[i]
                    sm[5] -= lz[i] * lx[i]
                    sm[6] -= lz[i]
                    sm[7] -= lx[i] * lx[i]
                    sm[8] -= lx[i]
                    sm[9] -= 1.0
                    sm[10] -= h[i]
                    sm[11] -= dist[i]
        return out, ok

    @njit(cache=True)
    def _nb_fit_groups(x, z, h, ptr, geometric, sigmas, max_rounds, min_points,
                       gn_iterations):  # pragma: no cover - compiled
        g = ptr.size - 1
        res = np.full((g, 8), np.nan)
        oks = np.zeros(g, dtype=np.bool_)
        inlier = np.zeros(x.size, dtype=np.bool_)
        for k in range(g):
            a, b = ptr[k], ptr[k + 1]
            o, ok = _nb_robust_fit(x[a:b], z[a:b], h[a:b], geometric, sigmas, max_rounds,
                                   min_points, gn_iterations, inlier[a:b])
            res[k] = o
            oks[k] = ok
        return res, oks, inlier

    @njit(cache=True)
    def _nb_phase(px, py, pz, pptr, circ, pair_ptr, pair_t, nrm, e1, e2, hbar, height,
                  geometric, sigmas, max_rounds, min_points,
                  gn_iterations):  # pragma: no cover - compiled
        """Gather (height filter along n), project and fit the circle of every segment in
        ``circ``; mirrors the gathering of :func:`_circle_phase`."""
        g = circ.size
        res = np.full((g, 8), np.nan)
        oks = np.zeros(g, dtype=np.bool_)
        npts = np.zeros(g, dtype=np.int64)
        for k in range(g):
            s = circ[k]
            cap = 0
            for j in range(pair_ptr[k], pair_ptr[k + 1]):
                t = pair_t[j]
                cap += pptr[t + 1] - pptr[t]
            xs = np.empty(cap)
            zs = np.empty(cap)
            hs = np.empty(cap)
            m = 0
            for j in range(pair_ptr[k], pair_ptr[k + 1]):
                t = pair_t[j]
                for i in range(pptr[t], pptr[t + 1]):
                    hh = px[i] * nrm[s, 0] + py[i] * nrm[s, 1] + pz[i] * nrm[s, 2]
                    if abs(hh - hbar[s]) <= height:
                        xs[m] = px[i] * e1[s, 0] + py[i] * e1[s, 1] + pz[i] * e1[s, 2]
                        zs[m] = px[i] * e2[s, 0] + py[i] * e2[s, 1] + pz[i] * e2[s, 2]
                        hs[m] = hh
                        m += 1
            npts[k] = m
            inl = np.empty(m, dtype=np.bool_)
            o, ok = _nb_robust_fit(xs[:m], zs[:m], hs[:m], geometric, sigmas, max_rounds,
                                   min_points, gn_iterations, inl)
            res[k] = o
            oks[k] = ok
        return res, oks, npts


if HAVE_NUMBA:

    @njit(cache=True)
    def _nb_axes(c, chain, radius, q, lo, hi, sv, span, tan_max, n):  # pragma: no cover
        """Concatenation sums of :func:`estimate_axes` (same filters as the numpy engine)."""
        sa = np.zeros((n, 3))
        sb = np.zeros((n, 3))
        na = np.zeros(n)
        nb = np.zeros(n)
        for k in range(q.size):
            a = q[k]
            for j in range(lo[k], hi[k]):
                b = sv[j]
                if b == a or chain[b] != chain[a]:
                    continue
                dx, dy, dz = c[b, 0] - c[a, 0], c[b, 1] - c[a, 1], c[b, 2] - c[a, 2]
                if dz == 0 or np.sqrt(dx * dx + dy * dy + dz * dz) > span:
                    continue
                if np.sqrt(dx * dx + dy * dy) > abs(dz) * tan_max + radius[a]:
                    continue
                if dz > 0:
                    sa[a, 0] += dx
                    sa[a, 1] += dy
                    sa[a, 2] += dz
                    na[a] += 1
                else:
                    sb[a, 0] -= dx
                    sb[a, 1] -= dy
                    sb[a, 2] -= dz
                    nb[a] += 1
        return sa, sb, na, nb


_FIT_CODES = {"linear": 0, "geometric": 1, "ray": 2}


def _resolve_engine(engine: str) -> str:
    if engine == "auto":
        return "numba" if HAVE_NUMBA else "numpy"
    if engine == "numba" and not HAVE_NUMBA:
        raise ValueError("engine 'numba' requested but numba is not installed")
    if engine not in ("numpy", "numba"):
        raise ValueError(f"engine: unknown {engine!r} (expected 'auto', 'numpy' or 'numba')")
    return engine


def fit_circles_2d(x: np.ndarray, z: np.ndarray, ptr: np.ndarray, *, h: np.ndarray | None = None,
                   fit: str = "linear", robust_sigmas: float = 3.0, max_rounds: int = 10,
                   min_points: int = 4, gn_iterations: int = 6,
                   engine: str = "auto") -> CircleFitResult:
    """Robust circle fits of many point groups at once (spec 3.3-3.4).

    ``x, z``: projected coordinates (x_pr, z_pr) grouped contiguously by ``ptr`` (n_groups+1);
    the origin is the projected sensor origin, which matters because the "= 1" normalisation
    of Eq. 4.10 is not translation invariant (the model is never re-centred; see
    :func:`_linear_circle`). Robust loop (always with the linear fit, Eq. 4.8-4.11):
    residuals e = |q - c| - r; points with ``|e| > robust_sigmas * std(e)`` are removed and the
    circle refitted until nothing is removed, ``max_rounds`` is reached or fewer than
    ``min_points`` would remain (inferred stop rule). ``fit="geometric"`` then refines centre
    and radius by ``gn_iterations`` Gauss-Newton steps on orthogonal distances of the final
    inliers (algebraic-then-geometric); the residual statistics (``mean_residual``, the
    symmetry statistic of spec 3.5, and ``rms_residual``) stay those of the linear fit, whose
    mean signed residual is what the thesis tests (a geometric fit forces it to zero).
    ``fit="ray"`` (inferred) continues from the geometric circle with a Levenberg-Marquardt
    fit of the along-beam model (:func:`_ray_terms`): the maximum-likelihood circle when the
    noise is in range, as for a laser scanner; it removes most of the low radius bias that
    range noise gives both other fits on a half-visible contour.
    ``h`` (per point) is averaged over the final inliers (mean projection distance, spec 3.6).
    ``engine``: ``"numpy"`` (batched arrays), ``"numba"`` (compiled loop, same results) or
    ``"auto"``.
    """
    if fit not in _FIT_CODES:
        raise ValueError(f"fit: unknown {fit!r} (expected one of {sorted(_FIT_CODES)})")
    if _resolve_engine(engine) == "numpy":
        return _fit_groups_numpy(x, z, ptr, h=h, fit=fit, robust_sigmas=robust_sigmas,
                                 max_rounds=max_rounds, min_points=min_points,
                                 gn_iterations=gn_iterations)
    x = np.ascontiguousarray(x, np.float64)
    z = np.ascontiguousarray(z, np.float64)
    hh = np.zeros_like(x) if h is None else np.ascontiguousarray(h, np.float64)
    res, ok, inlier = _nb_fit_groups(x, z, hh, np.asarray(ptr, np.int64), _FIT_CODES[fit],
                                     float(robust_sigmas), int(max_rounds), int(min_points),
                                     int(gn_iterations))
    ne = np.nan_to_num(res[:, 7]).astype(np.int64)
    return CircleFitResult(res[:, 0], res[:, 1], res[:, 2], ok, ne, res[:, 3], res[:, 4],
                           res[:, 5], res[:, 6], inlier)


# ------------------------------------------------------------------------------------------
# Projection frames, point collection, axis estimation
# ------------------------------------------------------------------------------------------

def plane_frames(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane orthonormal axes (e1, e2) for unit normals ``n`` (k, 3) (spec 3.1).

    e1 is the x axis made orthogonal to n, e2 = n x e1; for n = (0, 0, 1) this is (x, y).
    """
    ex = np.array([1.0, 0.0, 0.0])
    ey = np.array([0.0, 1.0, 0.0])
    ref = np.where(np.abs(n[:, :1]) < 0.9, ex, ey)
    e1 = ref - np.sum(ref * n, 1, keepdims=True) * n
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(n, e1)
    return e1, e2


@dataclass
class _SegData:
    row: np.ndarray
    chain: np.ndarray
    col0: np.ndarray
    col1: np.ndarray
    r_mid: np.ndarray
    width: np.ndarray
    pptr: np.ndarray  # CSR offsets into pts
    pts: np.ndarray  # (P, 3) levelled inlier points grouped by segment
    el_step: float


def _neighbour_pairs(sd: _SegData, k_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (s, t): t in the chain of s, |row_t - row_s| <= k_rows[s], column intervals overlap
    (spec 3.2, "overlapping segments above and below"). Sorted by s; includes (s, s)."""
    n = sd.row.size
    nrows = int(sd.row.max()) + 2
    key = sd.chain * nrows + sd.row
    order = np.argsort(key, kind="stable")
    skey = key[order]
    lo = np.searchsorted(skey, key - k_rows, "left")
    hi = np.searchsorted(skey, key + k_rows, "right")
    cnt = np.maximum(hi - lo, 0)
    s = np.repeat(np.arange(n), cnt)
    first = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    t = order[lo[s] + (np.arange(s.size) - first[s])]
    ok = (sd.chain[t] == sd.chain[s]) & (sd.col0[t] <= sd.col1[s]) & (sd.col1[t] >= sd.col0[s])
    return s[ok], t[ok]


def estimate_axes(centres: np.ndarray, valid: np.ndarray, normals: np.ndarray,
                  radius: np.ndarray, chain: np.ndarray, span_m: float,
                  max_tilt_deg: float, engine: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Axis (projection-plane normal) per circle by the concatenation method (spec 3.7).

    For circle c0, the vectors to valid circle centres of the same chain above (within
    ``span_m``) are summed, likewise the vectors from those below; both sums are normalised and
    averaged with weights proportional to their numbers of circles (inferred). Neighbours
    outside the +-``max_tilt_deg`` cone (with the circle radius as tolerance, inferred) are
    ignored. Normals farther than ``max_tilt_deg`` from vertical are clamped to the cone.
    Returns (normals, has_estimate); circles without valid neighbours keep their normal.
    """
    engine = _resolve_engine(engine)
    n = centres.shape[0]
    new = normals.copy()
    has = np.zeros(n, bool)
    fin = np.all(np.isfinite(centres), axis=1)
    vidx = np.flatnonzero(valid & fin)
    if vidx.size == 0:
        return new, has
    big = 1e5
    vkey = chain[vidx] * big + centres[vidx, 2]
    order = np.argsort(vkey, kind="stable")
    sv, skey = vidx[order], vkey[order]
    q = np.flatnonzero(fin)
    qkey = chain[q] * big + centres[q, 2]
    lo = np.searchsorted(skey, qkey - span_m, "left")
    hi = np.searchsorted(skey, qkey + span_m, "right")
    tan_max = float(np.tan(np.radians(max_tilt_deg)))
    if engine == "numba":
        sa, sb, na, nb = _nb_axes(np.ascontiguousarray(centres), chain, radius, q, lo, hi, sv,
                                  float(span_m), tan_max, n)
    else:
        cnt = hi - lo
        a = np.repeat(q, cnt)
        first = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        b = sv[lo[np.repeat(np.arange(q.size), cnt)] + (np.arange(a.size) - np.repeat(first, cnt))]
        d = centres[b] - centres[a]
        dz = d[:, 2]
        dh = np.hypot(d[:, 0], d[:, 1])
        ok = (b != a) & (chain[b] == chain[a]) & (np.linalg.norm(d, axis=1) <= span_m)
        ok &= (dz != 0) & (dh <= np.abs(dz) * tan_max + radius[a])
        a, d, dz = a[ok], d[ok], dz[ok]
        up = np.where((dz > 0)[:, None], d, -d)
        above = dz > 0
        sa = np.stack([np.bincount(a[above], up[above, i], n) for i in range(3)], 1)
        sb = np.stack([np.bincount(a[~above], up[~above, i], n) for i in range(3)], 1)
        na = np.bincount(a[above], minlength=n).astype(float)
        nb = np.bincount(a[~above], minlength=n).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        ua = sa / np.linalg.norm(sa, axis=1, keepdims=True)
        ub = sb / np.linalg.norm(sb, axis=1, keepdims=True)
    ua = np.where(na[:, None] > 0, ua, 0.0)
    ub = np.where(nb[:, None] > 0, ub, 0.0)
    m = na[:, None] * ua + nb[:, None] * ub
    norm = np.linalg.norm(m, axis=1)
    has = (na + nb > 0) & (norm > 0)
    new[has] = m[has] / norm[has, None]
    return clamp_tilt(new, max_tilt_deg), has


def clamp_tilt(n: np.ndarray, max_tilt_deg: float) -> np.ndarray:
    """Unit normals pointing up, tilted at most ``max_tilt_deg`` from vertical (spec 3.7)."""
    n = np.where(n[:, 2:3] < 0, -n, n)
    tilt = np.arccos(np.clip(n[:, 2], -1, 1))
    lim = np.radians(max_tilt_deg)
    over = tilt > lim
    if over.any():
        h = n[over, :2]
        hn = np.linalg.norm(h, axis=1, keepdims=True)
        n = n.copy()
        n[over, :2] = h / np.where(hn > 0, hn, 1.0) * np.sin(lim)
        n[over, 2] = np.cos(lim)
    return n


# ------------------------------------------------------------------------------------------
# One iteration of circle models for all segments
# ------------------------------------------------------------------------------------------

def _circle_phase(sd: _SegData, normals: np.ndarray, todo: np.ndarray, k_max: int,
                  collect_height_m: float, fit: str, robust_sigmas: float, max_rounds: int,
                  min_points: int, max_batch_points: int, engine: str
                  ) -> dict[str, np.ndarray]:
    """Fit the circles of segments ``todo`` with axes ``normals``; per-segment result arrays."""
    n_seg = sd.row.size
    res = {k: np.full(n_seg, np.nan) for k in ("cx", "cy", "cz", "r", "me", "rms", "md", "dc")}
    res["n_points"] = np.zeros(n_seg, np.int64)
    res["n_inliers"] = np.zeros(n_seg, np.int64)
    res["ok"] = np.zeros(n_seg, bool)
    if not todo.any():
        return res
    e1, e2 = plane_frames(normals)
    own = np.diff(sd.pptr)
    seg_of_pt = np.repeat(np.arange(n_seg), own)
    h_pts = np.einsum("ij,ij->i", sd.pts, normals[seg_of_pt])
    hbar = _reduce(h_pts, sd.pptr) / np.maximum(own, 1)
    # rows needed to cover +-collect_height along n (pruning only; the exact test is per point)
    tilt = np.arccos(np.clip(normals[:, 2], -1, 1))
    pitch_v = sd.r_mid * sd.el_step
    need = (collect_height_m + sd.width * np.sin(tilt)) / (pitch_v * np.cos(tilt))
    k_rows = np.minimum(k_max, np.ceil(need) + 1).astype(np.int64)
    k_rows = np.where(todo, k_rows, -1)
    ps, pt = _neighbour_pairs(sd, k_rows)
    keep = todo[ps]
    ps, pt = ps[keep], pt[keep]
    pair_n = own[pt]
    per_seg = np.bincount(ps, weights=pair_n, minlength=n_seg).astype(np.int64)
    segs = np.flatnonzero(todo)
    if engine == "numba":
        pair_ptr = np.searchsorted(ps, np.concatenate([segs, [n_seg]]))
        out, ok, npts = _nb_phase(
            np.ascontiguousarray(sd.pts[:, 0]), np.ascontiguousarray(sd.pts[:, 1]),
            np.ascontiguousarray(sd.pts[:, 2]), sd.pptr, segs, pair_ptr, pt,
            np.ascontiguousarray(normals), e1, e2, hbar, collect_height_m, _FIT_CODES[fit],
            float(robust_sigmas), int(max_rounds), int(min_points), 6)
        _store(res, segs, out[:, 0], out[:, 1], out[:, 2], ok,
               np.nan_to_num(out[:, 7]).astype(np.int64), out[:, 3], out[:, 4], out[:, 5],
               out[:, 6], npts, e1, e2, normals)
        return res
    # numpy engine: batches of circles bounded in gathered points (memory), in segment order
    csum = np.cumsum(per_seg[segs])
    cuts = np.searchsorted(csum, np.arange(max_batch_points, csum[-1] + max_batch_points,
                                           max_batch_points), "right")
    bounds = np.unique(np.concatenate([[0], cuts, [segs.size]]))
    pair_start = np.searchsorted(ps, segs)
    pair_end = np.searchsorted(ps, segs, "right")
    for b0, b1 in zip(bounds[:-1], bounds[1:], strict=True):
        bseg = segs[b0:b1]
        if bseg.size == 0:
            continue
        pa, pb = pair_start[b0], pair_end[b1 - 1]
        s, t, cnt = ps[pa:pb], pt[pa:pb], pair_n[pa:pb]
        g = np.repeat(s, cnt)
        first = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        pidx = np.repeat(sd.pptr[t], cnt) + (np.arange(g.size) - np.repeat(first, cnt))
        p = sd.pts[pidx]
        nn = normals[g]
        h = np.einsum("ij,ij->i", p, nn)
        inside = np.abs(h - hbar[g]) <= collect_height_m
        g, p, h = g[inside], p[inside], h[inside]
        x = np.einsum("ij,ij->i", p, e1[g])
        z = np.einsum("ij,ij->i", p, e2[g])
        gcount = np.bincount(g, minlength=n_seg)[bseg]
        ptr = np.concatenate([[0], np.cumsum(gcount)])
        fr = _fit_groups_numpy(x, z, ptr, h=h, fit=fit, robust_sigmas=robust_sigmas,
                               max_rounds=max_rounds, min_points=min_points)
        _store(res, bseg, fr.x0, fr.z0, fr.r, fr.ok, fr.n_inliers, fr.mean_residual,
               fr.rms_residual, fr.mean_h, fr.mean_dist, gcount, e1, e2, normals)
    return res


def _store(res, idx, x0, z0, r, ok, n_inl, me, rms, mean_h, mean_dist, n_points, e1, e2,
           normals) -> None:
    """Back-project circle centres to 3-D (spec 3.6) and store per-segment results."""
    c3 = x0[:, None] * e1[idx] + z0[:, None] * e2[idx] + mean_h[:, None] * normals[idx]
    res["cx"][idx], res["cy"][idx], res["cz"][idx] = c3[:, 0], c3[:, 1], c3[:, 2]
    res["r"][idx] = r
    res["me"][idx], res["rms"][idx] = me, rms
    res["md"][idx] = mean_dist
    res["dc"][idx] = np.hypot(x0, z0)
    res["n_points"][idx] = n_points
    res["n_inliers"][idx] = n_inl
    res["ok"][idx] = ok


def _validate(res: dict[str, np.ndarray], todo: np.ndarray, sym_limit: float,
              seg_params: SegmentationParams, min_points: int, statistic: str,
              range_sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Validity checks of spec 3.5; returns (valid, reject_reason) per segment."""
    n = todo.size
    reason = np.full(n, "", dtype=object)
    r = res["r"]
    with np.errstate(invalid="ignore"):
        stat = res["me"].copy()
        if statistic == "noise_corrected":
            # (inferred) remove the shift -sigma^2/(2r) that pure range noise gives the mean
            # signed residual of an algebraic circle fit, and test only a larger negative mean.
            stat = np.minimum(stat + range_sigma_m**2 / (2 * r), 0.0)
        elif statistic != "mean":
            raise ValueError(f"symmetry statistic: unknown {statistic!r}")
        checks = [
            ("fit", ~res["ok"] | ~np.isfinite(r)),
            ("too_few_points", res["n_inliers"] < min_points),
            ("size", (2 * r < seg_params.min_width_m) | (2 * r > seg_params.max_width_m)),
            ("convexity", ~(res["dc"] > res["md"])),
            ("symmetry", ~(np.abs(stat) <= sym_limit)),
        ]
    for name, fail in checks:
        reason[(reason == "") & fail & todo] = name
    reason[~todo] = "no_axis"
    return reason == "", reason


def fit_circle_models(image: RangeImage, segments: pd.DataFrame,
                      params: CircleParams | None = None,
                      seg_params: SegmentationParams | None = None, *,
                      fit: str | None = None, symmetry_statistic: str | None = None,
                      stable_centre_m: float = 0.001, stable_radius_m: float = 0.001,
                      stable_normal_deg: float = 0.5, stable_share: float = 0.8,
                      max_batch_points: int = 2_000_000, engine: str = "auto") -> pd.DataFrame:
    """Circle models of every segment, every iteration (spec 3.1-3.8).

    Iteration 0 (initial phase): vertical axis, +-``initial_neighbour_segments`` neighbours,
    symmetry threshold relaxed by ``initial_symmetry_factor`` (inferred x2). Iterations >= 1:
    axis from the previous iteration's valid circles (concatenation method, ``axis_span_m``),
    up to ``max_neighbour_segments`` neighbours within +-``collect_height_m`` along the axis.
    At least ``iterations`` iterations run; more follow, up to ``max_iterations``, until the
    circles are stable: a share ``stable_share`` of the circles valid in both iterations moved
    by less than ``stable_centre_m`` / ``stable_radius_m`` / ``stable_normal_deg`` and at most
    ``1 - stable_share`` of them changed validity (inferred; 0.8 gives the thesis' "usually two
    iterations" on clean and cluttered synthetic forests, where a few clutter circles never
    settle).
    In iterations >= 1 a segment is refitted when it was valid or received an axis estimate
    from valid neighbours; others keep their previous state with reason ``no_axis``.

    ``symmetry_statistic`` overrides ``params.symmetry_statistic``: ``"mean"`` (spec 3.5:
    |mean signed residual| <= T_sym) or ``"noise_corrected"`` (inferred alternative, see
    :func:`_validate`; with 2.5 cm range noise the linear fit's mean signed residual is biased
    by about -sigma^2/(2r), -4.2 mm on a 7.5 cm stem, so the "mean" test rejects thin trunks
    beyond ~10 m: the thesis' "a strict threshold misses distant trunks", spec 11).
    ``fit`` overrides ``params.fit``: ``"linear"`` (Eq. 4.10, default), ``"geometric"`` or
    ``"ray"`` (refinements, see :func:`fit_circles_2d`). The iterations always use the linear
    fit of the thesis; a refinement is applied to the final iteration's circles only (same
    points, same axes), so the axis estimation and the stopping rule do not depend on it.
    ``engine``:
    ``"numpy"`` (batched arrays), ``"numba"`` (compiled per-circle loop, same maths) or
    ``"auto"`` (numba when installed).

    Returns one row per segment and iteration with columns :data:`CIRCLE_COLUMNS`; ``cx, cy,
    cz`` is the back-projected 3-D centre (levelled frame), ``n*`` the projection normal,
    ``n_points`` the collected points and ``n_inliers`` the robust inliers.
    """
    cp = params or CircleParams()
    sp = seg_params or SegmentationParams()
    fit = fit or cp.fit
    symmetry_statistic = symmetry_statistic or cp.symmetry_statistic
    if len(segments) == 0:
        return empty_circles()
    seg_idx, pr, pc, _ = segment_pixels(image, segments)
    pts = pixel_xyz(image, pr, pc)
    n_seg = len(segments)
    pptr = np.concatenate([[0], np.cumsum(np.bincount(seg_idx, minlength=n_seg))])
    el_step = np.radians(image.elevation_step_deg or image.azimuth_step_deg or 0.108)
    sd = _SegData(segments["row"].to_numpy(np.int64), segments["chain_id"].to_numpy(np.int64),
                  segments["col0"].to_numpy(np.int64), segments["col1"].to_numpy(np.int64),
                  segments["r_mid"].to_numpy(np.float64), segments["width_m"].to_numpy(np.float64),
                  pptr, pts, el_step)
    min_points = sp.min_points
    common = dict(collect_height_m=cp.collect_height_m, robust_sigmas=cp.robust_sigmas,
                  max_rounds=cp.robust_max_rounds, min_points=min_points,
                  max_batch_points=max_batch_points, engine=_resolve_engine(engine))
    normals = np.tile([0.0, 0.0, 1.0], (n_seg, 1))
    todo = np.ones(n_seg, bool)
    tables = []
    prev: dict[str, np.ndarray] | None = None
    prev_valid = np.zeros(n_seg, bool)
    prev_reason = np.full(n_seg, "", dtype=object)
    prev_normals = normals.copy()
    for it in range(cp.max_iterations + 1):
        if prev is not None:
            centres = np.stack([prev["cx"], prev["cy"], prev["cz"]], 1)
            new_n, has = estimate_axes(centres, prev_valid, normals, prev["r"], sd.chain,
                                       cp.axis_span_m, cp.max_axis_tilt_deg, engine)
            todo = (has | prev_valid) & np.all(np.isfinite(centres), axis=1)
            normals = np.where(todo[:, None], new_n, normals)
        k_max = cp.initial_neighbour_segments if it == 0 else cp.max_neighbour_segments
        sym = cp.symmetry_threshold_m * (cp.initial_symmetry_factor if it == 0 else 1.0)

        def phase(fit_kind, prev=prev, prev_reason=prev_reason, todo=todo, normals=normals,
                  k_max=k_max, sym=sym):
            res = _circle_phase(sd, normals, todo, k_max, fit=fit_kind, **common)
            valid, reason = _validate(res, todo, sym, sp, min_points, symmetry_statistic,
                                      sp.range_sigma_m)
            if prev is not None:  # carry the previous state of segments not refitted
                for k in res:
                    res[k] = np.where(todo, res[k], prev[k])
                reason = np.where(todo, reason,
                                  np.where(prev_reason == "", "no_axis", prev_reason))
                valid = todo & valid
            return res, valid, reason

        res, valid, reason = phase("linear")
        last = it == cp.max_iterations or (
            prev is not None and it >= cp.iterations
            and _stable(prev, res, prev_valid, valid, prev_normals, normals, stable_centre_m,
                        stable_radius_m, stable_normal_deg, stable_share))
        if last and fit != "linear":  # refine the final circles (same points and axes)
            res, valid, reason = phase(fit)
        tables.append(_phase_table(it, segments, res, normals, valid, reason))
        if last:
            break
        prev, prev_valid, prev_reason, prev_normals = res, valid, reason, normals.copy()
    out = pd.concat(tables, ignore_index=True)
    return out.astype(CIRCLE_COLUMNS)


def _stable(a, b, va, vb, na, nb, dc, dr, dn_deg, share) -> bool:
    both = va & vb
    if not both.any():
        return True
    ca = np.stack([a["cx"], a["cy"], a["cz"]], 1)[both]
    cb = np.stack([b["cx"], b["cy"], b["cz"]], 1)[both]
    ang = np.degrees(np.arccos(np.clip(np.sum(na[both] * nb[both], 1), -1, 1)))
    small = (np.linalg.norm(ca - cb, axis=1) < dc) & (np.abs(a["r"][both] - b["r"][both]) < dr)
    small &= ang < dn_deg
    flips = np.count_nonzero(va != vb) / max(np.count_nonzero(va | vb), 1)
    return bool(small.mean() >= share and flips <= 1 - share)


def _phase_table(it, segments, res, normals, valid, reason) -> pd.DataFrame:
    return pd.DataFrame({
        "iteration": np.full(len(segments), it, np.int64),
        "segment_id": segments["segment_id"].to_numpy(np.int64),
        "row": segments["row"].to_numpy(np.int64),
        "chain_id": segments["chain_id"].to_numpy(np.int64),
        "cx": res["cx"], "cy": res["cy"], "cz": res["cz"], "radius_m": res["r"],
        "nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2],
        "n_points": res["n_points"], "n_inliers": res["n_inliers"],
        "mean_residual_m": res["me"], "rms_residual_m": res["rms"],
        "valid": valid, "reject_reason": reason.astype(object),
    })


def final_circles(circles: pd.DataFrame) -> pd.DataFrame:
    """Rows of the last iteration of a circle-model table."""
    if len(circles) == 0:
        return circles
    return circles[circles["iteration"] == circles["iteration"].max()].reset_index(drop=True)
