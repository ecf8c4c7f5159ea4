"""Batched 2-D circle fitting (spec 3.3-3.4; Eq. 4.10 / JP (3)): the linear least-squares circle
a (x^2 + z^2) + b z + c x = 1 without re-centring, inside the robust 3-sigma refit loop, for all
circles at once
(moment sums by ``np.add.reduceat``, one stacked solve); optional ``geometric`` (Gauss-Newton) and
``ray`` refinements."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from forestmap_assets.core.features._circle_kernels import (
    FIT_CODES,
    _nb_fit_groups,
    resolve_engine,
)


def _reduce(values: np.ndarray, ptr: np.ndarray) -> np.ndarray:
    """Sums of ``values`` (n, ...) over contiguous groups ``ptr`` (empty groups give 0)."""
    counts = np.diff(ptr)
    if values.shape[0] == 0:
        return np.zeros((counts.size,) + values.shape[1:])
    start = np.minimum(ptr[:-1], values.shape[0] - 1)
    out = np.add.reduceat(values, start, axis=0)
    out[counts == 0] = 0.0
    return out


def _solve_stacked(
    m: np.ndarray, rhs: np.ndarray, ridge: float = 0.0
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
    m = np.stack(
        [
            np.stack([d4, d2z, d2x, d2], -1),
            np.stack([d2z, zz, zx, z], -1),
            np.stack([d2x, zx, xx, x], -1),
            np.stack([d2, z, x, n], -1),
        ],
        -2,
    )
    ell = np.stack(
        [
            (ref[:, 0] ** 2 + ref[:, 1] ** 2) / sigma**2,
            -ref[:, 1] / sigma,
            -ref[:, 0] / sigma,
            np.ones(sigma.size),
        ],
        -1,
    )
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
        sums = _reduce(
            np.stack([jx * jx, jx * jz, -jx, jz * jz, -jz, wf, jx * e, jz * e, -e], -1), ptr
        )
        m = np.stack(
            [
                np.stack([sums[:, 0], sums[:, 1], sums[:, 2]], -1),
                np.stack([sums[:, 1], sums[:, 3], sums[:, 4]], -1),
                np.stack([sums[:, 2], sums[:, 4], sums[:, 5]], -1),
            ],
            -2,
        )
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
    j1 = np.stack(
        [
            -(ux + np.where(hit, mx / sc, 0.0)),
            -(uz + np.where(hit, mz / sc, 0.0)),
            np.where(hit, r / sc, 0.0),
        ],
        -1,
    )
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
        jtj = _reduce(
            (j1[:, :, None] * j1[:, None, :] + j2[:, :, None] * j2[:, None, :]).reshape(-1, 9), ptr
        ).reshape(-1, 3, 3)
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


def fit_groups_numpy(
    x: np.ndarray,
    z: np.ndarray,
    ptr: np.ndarray,
    *,
    h: np.ndarray | None = None,
    fit: str = "linear",
    robust_sigmas: float = 3.0,
    max_rounds: int = 10,
    min_points: int = 4,
    gn_iterations: int = 6,
    ray_iterations: int = 20,
) -> CircleFitResult:
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
                gx, gz, gr = _gauss_newton(
                    lx[pd_],
                    lz[pd_],
                    w[pd_],
                    dptr,
                    np.where(okd, x0[done], 0.0),
                    np.where(okd, z0[done], 0.0),
                    np.where(okd, r[done], 1.0),
                    gn_iterations,
                )
                if fit == "ray":
                    gx, gz, gr = _ray_refine(
                        lx[pd_],
                        lz[pd_],
                        w[pd_],
                        dptr,
                        -ref[done, 0] / sc,
                        -ref[done, 1] / sc,
                        gx,
                        gz,
                        gr,
                        ray_iterations,
                    )
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
        sub = np.concatenate(
            [_products(lx[ridx], lz[ridx]), np.stack([lh[ridx], dist[ridx]], -1)], -1
        )
        delta = np.zeros_like(sums)
        np.add.at(delta, grp, sub)
        sums = sums - delta
        w = w & ~rem
        # compact to the continuing groups
        pk = np.repeat(keep_g, cnt)
        gid, sums, ref, sigma = gid[keep_g], sums[keep_g], ref[keep_g], sigma[keep_g]
        lptr = np.concatenate([[0], np.cumsum(cnt[keep_g])])
        pidx, lx, lz, lh, w, dist = (a[pk] for a in (pidx, lx, lz, lh, w, dist))
    return CircleFitResult(
        out["x0"],
        out["z0"],
        out["r"],
        ok_out,
        n_inl,
        out["me"],
        out["rms"],
        out["mh"],
        out["md"],
        inlier,
    )


def fit_circles_2d(
    x: np.ndarray,
    z: np.ndarray,
    ptr: np.ndarray,
    *,
    h: np.ndarray | None = None,
    fit: str = "linear",
    robust_sigmas: float = 3.0,
    max_rounds: int = 10,
    min_points: int = 4,
    gn_iterations: int = 6,
    engine: str = "auto",
) -> CircleFitResult:
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
    if fit not in FIT_CODES:
        raise ValueError(f"fit: unknown {fit!r} (expected one of {sorted(FIT_CODES)})")
    if resolve_engine(engine) == "numpy":
        return fit_groups_numpy(
            x,
            z,
            ptr,
            h=h,
            fit=fit,
            robust_sigmas=robust_sigmas,
            max_rounds=max_rounds,
            min_points=min_points,
            gn_iterations=gn_iterations,
        )
    x = np.ascontiguousarray(x, np.float64)
    z = np.ascontiguousarray(z, np.float64)
    hh = np.zeros_like(x) if h is None else np.ascontiguousarray(h, np.float64)
    res, ok, inlier = _nb_fit_groups(
        x,
        z,
        hh,
        np.asarray(ptr, np.int64),
        FIT_CODES[fit],
        float(robust_sigmas),
        int(max_rounds),
        int(min_points),
        int(gn_iterations),
    )
    ne = np.nan_to_num(res[:, 7]).astype(np.int64)
    return CircleFitResult(
        res[:, 0], res[:, 1], res[:, 2], ok, ne, res[:, 3], res[:, 4], res[:, 5], res[:, 6], inlier
    )
