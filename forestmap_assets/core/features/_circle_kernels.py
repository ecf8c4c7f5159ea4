"""Numba engine of the circle models (spec 3; Th. 4.6.2-4.6.4): the batched circle fit with its
robust 3-sigma loop and refinements, one iteration of circle models (segments on the numba
threads) and the concatenation-method axes (spec 3.7), one circle per compiled loop iteration
(cached); ``HAVE_NUMBA`` and the engine choice (``auto``/``numpy``/``numba``)."""

from __future__ import annotations

import numpy as np

try:  # optional accelerator: same maths as the numpy engine, fused per circle
    from numba import njit, prange

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba missing: the numpy engine is used
    HAVE_NUMBA = False


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
            if not (ok and np.isfinite(step[0]) and np.isfinite(step[1]) and np.isfinite(step[2])):
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
    def _nb_robust_fit(
        x, z, h, geometric, sigmas, max_rounds, min_points, gn_iterations, inlier
    ):  # pragma: no cover - compiled
        """Robust fit of one group, mirrors :func:`_fit_groups_numpy`; fills ``inlier``."""
        out = np.empty(8)
        return out, _nb_robust_fit_into(x, z, h, geometric, sigmas, max_rounds, min_points, gn_iterations, inlier,
                                        np.empty((4, x.size)), np.empty(x.size, dtype=np.bool_), np.empty(12), out)

    @njit(cache=True)
    def _nb_robust_fit_into(
        x, z, h, geometric, sigmas, max_rounds, min_points, gn_iterations, inlier, work, wbuf, sm, out
    ):  # pragma: no cover - compiled
        """:func:`_nb_robust_fit` into given buffers: ``work`` (4, >= n) and ``w`` (>= n) for the
        scaled points, distances, residuals and weights, ``sm`` (12) the moments, ``out`` (8)
        the result (x0, z0, r, me, rms, mh, md, ne); returns whether the fit holds. The same
        arithmetic, without a dozen small arrays a circle (a phase fits 20-40 k of them)."""
        n = x.size
        out[:] = np.nan
        if n == 0:
            out[7] = 0
            return False
        rx, rz = np.mean(x), np.mean(z)
        sp = 0.0
        for i in range(n):
            sp += (x[i] - rx) ** 2 + (z[i] - rz) ** 2
        sigma = np.sqrt(sp / n)
        if not sigma > 0:
            sigma = 1.0
        lx = work[0, :n]
        lz = work[1, :n]
        dist = work[2, :n]
        e = work[3, :n]
        w = wbuf[:n]
        for i in range(n):
            lx[i] = (x[i] - rx) / sigma
            lz[i] = (z[i] - rz) / sigma
            dist[i] = np.sqrt(x[i] * x[i] + z[i] * z[i])
            w[i] = True
        sm[:] = 0.0
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
                    e[i] = (
                        np.sqrt(
                            (lx[i] - (cx if ok else 0.0)) ** 2 + (lz[i] - (cz if ok else 0.0)) ** 2
                        )
                        - r0
                    )
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
                        gx, gz, gr = _nb_ray_refine(
                            lx, lz, w, -rx / sigma, -rz / sigma, gx, gz, gr, 20
                        )
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
                return ok
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
        return ok

    @njit(cache=True)
    def _nb_fit_groups(
        x, z, h, ptr, geometric, sigmas, max_rounds, min_points, gn_iterations
    ):  # pragma: no cover - compiled
        g = ptr.size - 1
        res = np.full((g, 8), np.nan)
        oks = np.zeros(g, dtype=np.bool_)
        inlier = np.zeros(x.size, dtype=np.bool_)
        for k in range(g):
            a, b = ptr[k], ptr[k + 1]
            o, ok = _nb_robust_fit(
                x[a:b],
                z[a:b],
                h[a:b],
                geometric,
                sigmas,
                max_rounds,
                min_points,
                gn_iterations,
                inlier[a:b],
            )
            res[k] = o
            oks[k] = ok
        return res, oks, inlier

    @njit(cache=True, parallel=True)
    def _nb_phase(
        px,
        py,
        pz,
        pptr,
        circ,
        pair_ptr,
        pair_t,
        nrm,
        e1,
        e2,
        hbar,
        height,
        geometric,
        sigmas,
        max_rounds,
        min_points,
        gn_iterations,
        max_points,
    ):  # pragma: no cover - compiled
        """Gather (height filter along n), project and fit the circle of every segment in
        ``circ``; mirrors the gathering of :func:`_circle_phase`. Segments in parallel (each
        writes only its own row: the same results on any number of threads). With
        ``max_points`` > 0 a segment whose neighbours hold more points takes every
        ``ceil(points / max_points)``-th point of each neighbour, starting one point later on
        each next neighbour (the whole arc, not the same columns of every scan line)."""
        g = circ.size
        res = np.full((g, 8), np.nan)
        oks = np.zeros(g, dtype=np.bool_)
        npts = np.zeros(g, dtype=np.int64)
        chunk = 256  # segments a task: each task's buffers serve all its circles
        for c in prange((g + chunk - 1) // chunk):
            k0, k1 = c * chunk, min(g, (c + 1) * chunk)
            big = 0
            for k in range(k0, k1):
                cap = 0
                for j in range(pair_ptr[k], pair_ptr[k + 1]):
                    t = pair_t[j]
                    cap += pptr[t + 1] - pptr[t]
                big = max(big, cap)
            xs = np.empty(big)
            zs = np.empty(big)
            hs = np.empty(big)
            inl = np.empty(big, dtype=np.bool_)
            work = np.empty((4, big))
            wts = np.empty(big, dtype=np.bool_)
            sm = np.empty(12)
            for k in range(k0, k1):
                s = circ[k]
                cap = 0
                for j in range(pair_ptr[k], pair_ptr[k + 1]):
                    t = pair_t[j]
                    cap += pptr[t + 1] - pptr[t]
                stride = 1
                if max_points > 0 and cap > max_points:
                    stride = (cap + max_points - 1) // max_points
                m = 0
                for j in range(pair_ptr[k], pair_ptr[k + 1]):
                    t = pair_t[j]
                    first = pptr[t] + (stride - (j - pair_ptr[k]) % stride) % stride
                    for i in range(first, pptr[t + 1], stride):
                        hh = px[i] * nrm[s, 0] + py[i] * nrm[s, 1] + pz[i] * nrm[s, 2]
                        if abs(hh - hbar[s]) <= height:
                            xs[m] = px[i] * e1[s, 0] + py[i] * e1[s, 1] + pz[i] * e1[s, 2]
                            zs[m] = px[i] * e2[s, 0] + py[i] * e2[s, 1] + pz[i] * e2[s, 2]
                            hs[m] = hh
                            m += 1
                npts[k] = m
                oks[k] = _nb_robust_fit_into(
                    xs[:m], zs[:m], hs[:m], geometric, sigmas, max_rounds, min_points,
                    gn_iterations, inl[:m], work, wts, sm, res[k],
                )
        return res, oks, npts


if HAVE_NUMBA:

    @njit(cache=True, parallel=True)
    def _nb_axes(c, radius, q, qcell, vkey, vz, sv, n_x, n_y, span, tan_max, n):  # pragma: no cover
        """Concatenation sums of :func:`estimate_axes` (same filters as the numpy engine).

        The valid circles ``sv`` are sorted by (chain, x cell, y cell) key ``vkey``, then by z
        ``vz``; cells are ``span`` wide, so the circles within ``span`` of a query lie in its
        own and the 8 neighbouring cells of its chain, each a run found by binary search, and
        within a run a z interval. (One window per chain and z range was quadratic in a chain's
        size: a rendered scan's ground chain of 17,600 circles made 98 % of the work.) Queries
        in parallel: ``q`` holds distinct circles and each writes only its own row."""
        sa = np.zeros((n, 3))
        sb = np.zeros((n, 3))
        na = np.zeros(n)
        nb = np.zeros(n)
        for k in prange(q.size):
            a = q[k]
            ch, cx, cy = qcell[k, 0], qcell[k, 1], qcell[k, 2]
            for ox in range(-1, 2):
                x = cx + ox
                if x < 0 or x >= n_x:
                    continue
                for oy in range(-1, 2):
                    y = cy + oy
                    if y < 0 or y >= n_y:
                        continue
                    key = (ch * n_x + x) * n_y + y
                    r0 = np.searchsorted(vkey, key, side="left")
                    r1 = np.searchsorted(vkey, key, side="right")
                    if r0 == r1:
                        continue
                    j0 = r0 + np.searchsorted(vz[r0:r1], c[a, 2] - span, side="left")
                    j1 = r0 + np.searchsorted(vz[r0:r1], c[a, 2] + span, side="right")
                    for j in range(j0, j1):
                        b = sv[j]
                        if b == a:
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


FIT_CODES = {"linear": 0, "geometric": 1, "ray": 2}


if not HAVE_NUMBA:  # pragma: no cover - the numpy engine runs; the names exist for importers
    _nb_fit_groups = _nb_phase = _nb_axes = None


def resolve_engine(engine: str) -> str:
    if engine == "auto":
        return "numba" if HAVE_NUMBA else "numpy"
    if engine == "numba" and not HAVE_NUMBA:
        raise ValueError("engine 'numba' requested but numba is not installed")
    if engine not in ("numpy", "numba"):
        raise ValueError(f"engine: unknown {engine!r} (expected 'auto', 'numpy' or 'numba')")
    return engine
