"""Rotation of the Fourier coarse registration (men spec 4.2-4.3, checklist 8-11): EGI of the
normals on the 2L x 2L SOFT grid, spherical-harmonic expansion (Driscoll-Healy, exact Wigner d),
SO(3) correlation G(a, b, g) by inverse 2-D FFTs on the ZYZ Euler grid and its peaks, the
brute-force reference (V8), and the heading-only correlation for levelled scans (forsman spec
6.1)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pandas as pd


def sphere_grid(bandwidth: int) -> tuple[np.ndarray, np.ndarray]:
    """Polar angles ``theta_j = pi (2j+1)/(4L)`` and azimuths ``phi_k = 2 pi k/(2L)`` (spec 4.2)."""
    b = int(bandwidth)
    j = np.arange(2 * b)
    return np.pi * (2 * j + 1) / (4 * b), 2 * np.pi * j / (2 * b)


def cell_solid_angles(bandwidth: int) -> np.ndarray:
    """Solid angle (2L,) of the cells of one theta row (cells span ``pi/(2L)`` in theta)."""
    b = int(bandwidth)
    edges = np.pi * np.arange(2 * b + 1) / (2 * b)
    return (np.cos(edges[:-1]) - np.cos(edges[1:])) * (2 * np.pi / (2 * b))


def normal_angles(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Polar angle theta (from +z) and azimuth phi in [0, 2 pi) of unit vectors (spec 4.2)."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    theta = np.arccos(np.clip(n[:, 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(n[:, 1], n[:, 0]), 2 * np.pi)
    return theta, phi


def egi(normals: np.ndarray, bandwidth: int = 32, weights=None, density: bool = True) -> np.ndarray:
    """Orientation histogram (EGI) on the ``2L x 2L`` grid (rows theta, columns phi; spec 4.2).

    Counts by direct index computation (equivalent to the thesis's double loop); invalid
    normals are skipped. With ``density`` the counts are divided by their total and by each
    cell's solid angle (a density on the sphere, inferred); else the raw counts (their sum is the
    number of valid normals, V7).
    """
    b = int(bandwidth)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    ok = np.isfinite(n).all(axis=1) & (np.linalg.norm(n, axis=1) > 0)
    theta, phi = normal_angles(n[ok] / np.linalg.norm(n[ok], axis=1, keepdims=True))
    j = np.minimum((theta / (np.pi / (2 * b))).astype(np.int64), 2 * b - 1)
    k = np.mod(np.rint(phi / (2 * np.pi / (2 * b))).astype(np.int64), 2 * b)
    w = None if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)[ok]
    h = np.bincount(j * 2 * b + k, weights=w, minlength=4 * b * b).reshape(2 * b, 2 * b)
    if density:
        total = h.sum()
        h = h / max(total, 1e-300) / cell_solid_angles(b)[:, None]
    return h


@lru_cache(maxsize=256)
def _jy_eigen(ell: int) -> tuple[np.ndarray, np.ndarray]:
    m = np.arange(-ell, ell)
    c = np.sqrt(ell * (ell + 1) - m * (m + 1.0))
    jp = np.zeros((2 * ell + 1, 2 * ell + 1))
    jp[np.arange(1, 2 * ell + 1), np.arange(2 * ell)] = c  # J+ |m> = c |m+1>
    jy = (jp - jp.T) / 2j
    return np.linalg.eigh(jy)


def wigner_d(ell: int, beta) -> np.ndarray:
    """Wigner small-d matrices ``d^l_{m'm}(beta) = <l m'| exp(-i beta J_y) |l m>`` for every
    beta: shape (n_beta, 2l+1, 2l+1), index ``[.., m' + l, m + l]`` (Condon-Shortley phase)."""
    lam, v = _jy_eigen(int(ell))
    b = np.atleast_1d(np.asarray(beta, dtype=np.float64))
    ph = np.exp(-1j * b[:, None] * lam[None, :])
    d = np.einsum("ik,bk,jk->bij", v, ph, v.conj())
    return d.real


@lru_cache(maxsize=16)
def _betas_d(bandwidth: int) -> tuple[np.ndarray, ...]:
    """Wigner d^l at the grid betas ``pi (2k+1)/(4L)`` for l < L (cached per bandwidth)."""
    beta = sphere_grid(bandwidth)[0]
    return tuple(wigner_d(ell, beta) for ell in range(bandwidth))


def quadrature_weights(bandwidth: int) -> np.ndarray:
    """Driscoll-Healy weights ``w_j`` so that ``sum_j w_j f(theta_j) ~ int_0^pi f sin(theta)
    d theta`` (exact for polynomials in cos theta of degree < 2L; SOFT, Kostelec-Rockmore)."""
    b = int(bandwidth)
    theta = sphere_grid(b)[0]
    k = np.arange(b)
    s = (np.sin((2 * k[None, :] + 1) * theta[:, None]) / (2 * k[None, :] + 1)).sum(axis=1)
    return (4.0 / (2 * b)) * np.sin(theta) * s


def sh_coefficients(grid: np.ndarray, bandwidth: int | None = None) -> np.ndarray:
    """Spherical-harmonic coefficients ``F[l, m + L - 1] = int f conj(Y_lm) dw`` (zero for
    |m| > l) of a function sampled on the ``2L x 2L`` grid (spec 4.3, Eqs. 4.2-4.3)."""
    g = np.asarray(grid, dtype=np.float64)
    b = int(bandwidth or g.shape[0] // 2)
    if g.shape != (2 * b, 2 * b):
        raise ValueError(f"grid: expected shape {(2 * b, 2 * b)}, got {g.shape}")
    w = quadrature_weights(b) * (2 * np.pi / (2 * b))
    gm = np.fft.fft(g, axis=1)  # sum_k f e^{-i m phi_k}, m mod 2L
    out = np.zeros((b, 2 * b - 1), dtype=np.complex128)
    dl = _betas_d(b)
    for ell in range(b):
        m = np.arange(-ell, ell + 1)
        norm = np.sqrt((2 * ell + 1) / (4 * np.pi))
        d_m0 = dl[ell][:, :, ell]  # (2L beta=theta, 2l+1) = d^l_{m0}(theta_j)
        out[ell, m + b - 1] = norm * ((w[:, None] * d_m0) * gm[:, np.mod(m, 2 * b)]).sum(axis=0)
    return out


def sh_synthesis(coeffs: np.ndarray, bandwidth: int) -> np.ndarray:
    """Function on the ``2L x 2L`` grid from coefficients (inverse of :func:`sh_coefficients`
    for band-limited functions; real part)."""
    b = int(bandwidth)
    gm = np.zeros((2 * b, 2 * b), dtype=np.complex128)
    dl = _betas_d(b)
    for ell in range(b):
        m = np.arange(-ell, ell + 1)
        norm = np.sqrt((2 * ell + 1) / (4 * np.pi))
        gm[:, np.mod(m, 2 * b)] += norm * dl[ell][:, :, ell] * coeffs[ell, m + b - 1][None, :]
    return (np.fft.ifft(gm, axis=1) * (2 * b)).real


def so3_correlation(f_model: np.ndarray, f_data: np.ndarray, bandwidth: int) -> np.ndarray:
    """``G`` on the ZYZ Euler grid, shape (2L alpha, 2L beta, 2L gamma), from the SH coefficients
    of the model and data EGIs (spec 4.3; ``G(R) = int H_m(w) H_d(R^T w) dw``)."""
    b = int(bandwidth)
    dl = _betas_d(b)
    out = np.empty((2 * b, 2 * b, 2 * b))
    s = np.zeros((2 * b, 2 * b, 2 * b), dtype=np.complex128)  # [beta, m mod 2L, n mod 2L]
    for ell in range(b):
        m = np.arange(-ell, ell + 1)
        fm = f_model[ell, m + b - 1]
        fd = np.conj(f_data[ell, m + b - 1])
        prod = fm[:, None] * fd[None, :]  # (m, n)
        idx = np.mod(m, 2 * b)
        s[:, idx[:, None], idx[None, :]] += dl[ell] * prod[None]
    # sum_{m,n} S[m, n] e^{i m alpha} e^{i n gamma} = (2L)^2 ifft2
    for k in range(2 * b):
        out[:, k, :] = (np.fft.ifft2(s[k]) * (2 * b) ** 2).real
    return out


def euler_zyz(alpha, beta, gamma) -> np.ndarray:
    """Rotation ``R_z(alpha) R_y(beta) R_z(gamma)`` (radians; arrays broadcast to (..., 3, 3))."""
    a, b, g = (np.asarray(v, dtype=np.float64) for v in (alpha, beta, gamma))

    def rz(t):
        c, s = np.cos(t), np.sin(t)
        z, o = np.zeros_like(t), np.ones_like(t)
        return np.stack(
            [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
        )

    c, s = np.cos(b), np.sin(b)
    z, o = np.zeros_like(b), np.ones_like(b)
    ry = np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)
    return rz(a) @ ry @ rz(g)


def so3_grid(bandwidth: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Euler angles of the ``(2L)^3`` correlation grid: alpha, beta, gamma (radians)."""
    b = int(bandwidth)
    ag = 2 * np.pi * np.arange(2 * b) / (2 * b)
    return ag, sphere_grid(b)[0], ag


def rotation_angle_deg(r_a: np.ndarray, r_b: np.ndarray) -> float:
    """Angle of the rotation ``R_a^T R_b`` in degrees."""
    c = (np.trace(np.asarray(r_a).T @ np.asarray(r_b)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def so3_peaks(
    corr: np.ndarray, bandwidth: int, top_k: int = 4, min_separation_deg: float | None = None
) -> pd.DataFrame:
    """The ``top_k`` largest local maxima of an SO(3) correlation grid, at least
    ``min_separation_deg`` apart (default two grid steps); columns ``alpha, beta, gamma`` (rad),
    ``score`` and the rotation matrix entries ``r00 .. r22``."""
    b = int(bandwidth)
    sep = 2 * 180.0 / (2 * b) if min_separation_deg is None else float(min_separation_deg)
    from scipy.ndimage import maximum_filter

    mx = maximum_filter(corr, size=3, mode=("wrap", "nearest", "wrap"))
    cand = np.argwhere(corr >= mx)
    vals = corr[tuple(cand.T)]
    order = np.argsort(-vals)
    ag, bg, gg = so3_grid(b)
    chosen: list[tuple[int, np.ndarray]] = []
    for i in order:
        a, bb, g = cand[i]
        r = euler_zyz(ag[a], bg[bb], gg[g])
        if all(rotation_angle_deg(r, rc) >= sep for _, rc in chosen):
            chosen.append((i, r))
        if len(chosen) >= top_k:
            break
    rows = []
    for i, r in chosen:
        a, bb, g = cand[i]
        rows.append(
            {
                "alpha": ag[a],
                "beta": bg[bb],
                "gamma": gg[g],
                "score": float(vals[i]),
                **{f"r{p}{q}": float(r[p, q]) for p in range(3) for q in range(3)},
            }
        )
    return pd.DataFrame(rows)


def peak_rotation(row) -> np.ndarray:
    return np.array([[row[f"r{p}{q}"] for q in range(3)] for p in range(3)], dtype=np.float64)


def rotation_by_correlation(
    model_normals: np.ndarray, data_normals: np.ndarray, bandwidth: int = 32, top_k: int = 1
) -> pd.DataFrame:
    """Best rotation(s) of the data normals onto the model normals by SO(3) correlation of their
    EGIs (spec 4.3): :func:`so3_peaks` of :func:`so3_correlation`."""
    fm = sh_coefficients(egi(model_normals, bandwidth), bandwidth)
    fd = sh_coefficients(egi(data_normals, bandwidth), bandwidth)
    return so3_peaks(so3_correlation(fm, fd, bandwidth), bandwidth, top_k=top_k)


def sh_evaluate(coeffs: np.ndarray, theta, phi) -> np.ndarray:
    """Band-limited function ``sum_lm F_lm Y_lm(theta, phi)`` at arbitrary directions (real
    part), with ``d^l_m0`` from the same Wigner construction."""
    b = coeffs.shape[0]
    th = np.asarray(theta, dtype=np.float64).reshape(-1)
    ph = np.asarray(phi, dtype=np.float64).reshape(-1)
    out = np.zeros(th.size, dtype=np.complex128)
    for ell in range(b):
        lam, v = _jy_eigen(ell)
        d_m0 = (
            (
                v[None, :, :]
                * np.exp(-1j * th[:, None, None] * lam[None, None, :])
                * np.conj(v[ell][None, None, :])
            )
            .sum(axis=2)
            .real
        )  # (n, 2l+1) = d^l_{m0}(theta)
        m = np.arange(-ell, ell + 1)
        norm = np.sqrt((2 * ell + 1) / (4 * np.pi))
        out += norm * (
            d_m0 * np.exp(1j * m[None, :] * ph[:, None]) * coeffs[ell, m + b - 1][None, :]
        ).sum(axis=1)
    return out.real


def brute_force_rotation(
    model_normals: np.ndarray,
    data_normals: np.ndarray,
    rotations: np.ndarray,
    bandwidth: int = 32,
    method: str = "bandlimited",
) -> np.ndarray:
    """Reference objective for every rotation R of a list (k, 3, 3) (spec 4.3, V8), without the
    SO(3) Fourier transform.

    ``bandlimited``: ``sum_jk w_j H_m(w_jk) H_d(R^T w_jk)`` with both EGIs band-limited to L and
    ``H_d`` evaluated at the rotated grid directions by spherical-harmonic synthesis; equals the
    SOFT correlation at the same R up to rounding. ``binned``: the naive form, the data normals
    rotated by R and re-binned, ``sum H_m H_{R d} dw`` (noisy for peaky histograms).
    """
    b = int(bandwidth)
    hm = egi(model_normals, b)
    d = np.asarray(data_normals, dtype=np.float64).reshape(-1, 3)
    d = d[np.isfinite(d).all(axis=1)]
    rots = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    out = np.empty(len(rots))
    if method == "binned":
        area = cell_solid_angles(b)[:, None]
        for i, r in enumerate(rots):
            out[i] = float((hm * egi(d @ r.T, b) * area).sum())
        return out
    if method != "bandlimited":
        raise ValueError(f"method: expected 'bandlimited' or 'binned', got {method!r}")
    fd = sh_coefficients(egi(d, b), b)
    hm_bl = sh_synthesis(sh_coefficients(hm, b), b)
    theta, phi = sphere_grid(b)
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    w = (quadrature_weights(b) * (2 * np.pi / (2 * b)))[:, None] * np.ones_like(tt)
    dirs = np.stack(
        [np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], axis=-1
    ).reshape(-1, 3)
    for i, r in enumerate(rots):
        rt = dirs @ r  # R^T w for every grid direction
        th, ph = normal_angles(rt)
        out[i] = float((w.reshape(-1) * hm_bl.reshape(-1) * sh_evaluate(fd, th, ph)).sum())
    return out


def heading_correlation(
    f_model: np.ndarray, f_data: np.ndarray, bandwidth: int, n_heading: int = 720
) -> tuple[np.ndarray, np.ndarray]:
    """``G(R_z(a))`` for headings ``a = 2 pi k / n_heading`` (levelled scans): ``sum_m e^{i m a}
    sum_l H_m^lm conj(H_d^lm)``; returns (headings_rad, G)."""
    b = int(bandwidth)
    n = max(int(n_heading), 2 * b)
    a = np.zeros(n, dtype=np.complex128)
    for ell in range(b):
        m = np.arange(-ell, ell + 1)
        a[np.mod(m, n)] += f_model[ell, m + b - 1] * np.conj(f_data[ell, m + b - 1])
    return 2 * np.pi * np.arange(n) / n, (np.fft.ifft(a) * n).real


def heading_peaks(
    headings: np.ndarray, g: np.ndarray, top_k: int = 4, min_separation_deg: float = 10.0
) -> pd.DataFrame:
    """Largest circular local maxima of a heading correlation, ``min_separation_deg`` apart,
    each refined by a parabola through its neighbours (beyond the thesis, inferred)."""
    left, right = np.roll(g, 1), np.roll(g, -1)
    cand = np.flatnonzero((g >= left) & (g >= right))
    cand = cand[np.argsort(-g[cand])]
    step = headings[1] - headings[0]
    rows: list[dict] = []
    for i in cand:
        den = left[i] - 2 * g[i] + right[i]
        off = 0.5 * (left[i] - right[i]) / den if den < 0 else 0.0
        h = np.degrees(headings[i] + off * step)
        h = (h + 180.0) % 360.0 - 180.0
        if all(
            abs((h - r["heading_deg"] + 180.0) % 360.0 - 180.0) >= min_separation_deg for r in rows
        ):
            rows.append({"heading_deg": h, "score": float(g[i])})
        if len(rows) >= top_k:
            break
    return pd.DataFrame(rows, columns=["heading_deg", "score"])
