"""Lu-Milios minimum-variance optimal map with incremental re-solving (Th. 3.2.2, 6.4; JP II-C).

State: the global poses ``x_i = (x, y, z, heading)`` of the sub-maps, sub-map 0 (the reference)
fixing the global frame. Each observation, projected into the global frame with the current
global heading of its reference sub-map (Eq. 6.1), observes ``x_scan - x_reference``
(``d = H x + w``, Eq. 3.15-3.16 / JP (7)-(8)); with block-diagonal ``C`` the estimate is
``x = (H^T C^-1 H)^-1 H^T C^-1 d`` and ``C_x = (H^T C^-1 H)^-1`` (Eq. 3.20-3.21 / JP (9)-(10)).
The network is re-solved phase by phase as sub-maps are added in a given order, every phase
re-projecting all observations with the previous phase's headings (spec 8.4).

Observations that share a scan (beyond the thesis, inferred, :func:`shared_scan_covariance`):
the block-diagonal ``C`` treats every registration as independent, but two registrations of
the same scan share that scan's feature errors (stem centres, ground grid), so the poses came
out over-confident on simulated campaigns (error / sd RMS 1.3-1.7 while the pairs' was 0.6-0.9).
``scan_correlation`` = rho models each observation error as ``sqrt(1 - 2 rho) v + u_i - u_j``
with an error ``u_s`` per scan; its covariance is ``(1 - 2 rho) D + B S B^T`` (``B`` the
incidence matrix, ``S`` per-scan blocks). This keeps the poses and residuals of the thesis's
solve and inflates ``C_x`` to ``(1 - 2 rho) C_x + K``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pandas as pd
import scipy.linalg
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from forestmap_assets.core.mapping.chaining import (
    OBSERVATION_COLUMNS,
    POSE_COLUMNS,
    POSE_SD_COLUMNS,
    Covariance,
    observation_arrays,
    project_relative,
    wrap_deg,
)
from forestmap_assets.core.mapping.residuals import residual_arrays, residual_table

Linearisation = Literal["projection", "gauss_newton"]

# Pipeline default of ``scan_correlation`` (x, y, z, heading; the core functions default to 0,
# the thesis). Estimated (inferred) on simulated campaigns at quarter resolution, seeds 100-104
# (6 scans, 40 m plots, no prior), as the correlation of the normalised errors of two admitted
# links sharing one scan, rotated into the global frame and signed by the side the shared scan
# is on: x 0.28, y 0.25, z 0.15, heading 0.03 (+- 0.07-0.09, 147 link pairs), rounded to 0.05
# with one value for x and y (a per-scan error has no preferred horizontal direction). Checked,
# not fitted, on half resolution (benchmarks/results.md, mapping section).
PIPELINE_SCAN_CORRELATION: tuple[float, float, float, float] = (0.25, 0.25, 0.15, 0.05)
# Optional observation columns: that observation's own rho (x, y, z, heading), overriding the
# ``scan_correlation`` argument (:func:`observation_correlation`).
RHO_COLUMNS = ("rho_x", "rho_y", "rho_z", "rho_heading")


@dataclass
class MapSolution:
    """One solve of the optimal map (one phase of spec 8.4).

    ``poses``: ``scan, x, y, z, heading_deg`` (headings unwrapped, i.e. sums of the observed
    headings as printed in Table 6.8), ``sd_*`` (sqrt of the diagonal of ``C_x``) and
    ``registered``; ``covariance``: ``C_x`` (4N, 4N) in the scan order of ``poses``, block order
    (x, y, z, heading; with ``scan_correlation`` the covariance of the correlated-observation
    model, :func:`shared_scan_covariance`); ``projected``: the observations used, projected
    into the global frame (Table 6.7), with ``cov_xy``, ``projection_heading_deg`` and the
    input row ``observation``; ``residuals``: Eq. (11) per used observation (``residuals.csv``
    schema); ``iterations``: projection/solve rounds.
    """

    scans: list[str]
    reference: str
    poses: pd.DataFrame
    covariance: np.ndarray
    projected: pd.DataFrame
    residuals: pd.DataFrame
    iterations: int

    def headings(self) -> dict[str, float]:
        """Global heading (deg, unwrapped) of every registered sub-map."""
        p = self.poses[self.poses["registered"]]
        return dict(zip(p["scan"], p["heading_deg"].astype(float), strict=True))

    def heading_variances(self) -> dict[str, float]:
        """Variance (deg^2) of the global heading of every registered sub-map."""
        p = self.poses[self.poses["registered"]]
        return dict(zip(p["scan"], p["sd_heading_deg"].astype(float) ** 2, strict=True))


@dataclass
class OptimalMap:
    """Per-phase solutions of the incremental optimal map; ``final`` is the last phase."""

    order: list[str]
    phases: list[MapSolution]

    @property
    def final(self) -> MapSolution:
        return self.phases[-1]


def unwrap_headings(dheading_deg: np.ndarray, predicted_deg: np.ndarray) -> np.ndarray:
    """Observed heading differences moved by multiples of 360 deg to within +-180 deg of the
    difference ``phi_i - phi_j`` predicted by the current estimates (spec 8.4 item 4, inferred).
    Unknown predictions (NaN) leave the observation as given."""
    pred = np.asarray(predicted_deg, dtype=float)
    d = np.asarray(dheading_deg, dtype=float)
    return np.where(np.isnan(pred), d, pred + wrap_deg(d - pred))


def propagate_headings(
    n: int,
    i: np.ndarray,
    j: np.ndarray,
    dheading_deg: np.ndarray,
    sd_heading_deg: np.ndarray,
    heading: np.ndarray,
    heading_var: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Fill unknown (NaN) headings by chaining along links from known sub-maps (spec 8.3).

    A sub-map without an estimate (just added) gets ``phi_ref + dphi`` (or ``phi_scan - dphi``)
    from the link with the smallest chained heading variance; sweeps repeat until no link adds a
    sub-map. Used to project the new sub-map's links in its first phase (inferred: the thesis's
    forest links are all new -> older, so only the reference side is ever needed there).
    """
    h = np.array(heading, dtype=float, copy=True)
    v = np.array(heading_var, dtype=float, copy=True)
    dphi = np.asarray(dheading_deg, dtype=float)
    var_link = np.asarray(sd_heading_deg, dtype=float) ** 2
    for _ in range(n):
        ki, kj = ~np.isnan(h[i]), ~np.isnan(h[j])
        fwd, bwd = kj & ~ki, ki & ~kj
        m = np.flatnonzero(fwd | bwd)
        if m.size == 0:
            break
        target = np.where(fwd[m], i[m], j[m])
        value = np.where(fwd[m], h[j[m]] + dphi[m], h[i[m]] - dphi[m])
        vv = np.where(fwd[m], v[j[m]], v[i[m]]) + var_link[m]
        first = np.lexsort((vv, target))
        keep = first[np.r_[True, target[first][1:] != target[first][:-1]]]
        h[target[keep]], v[target[keep]] = value[keep], vv[keep]
    return h, v


def reached_from(n: int, root: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Boolean mask of the sub-maps connected to ``root`` through the links (i, j)."""
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return labels == labels[root]


def solve_linear(
    n: int,
    root: int,
    i: np.ndarray,
    j: np.ndarray,
    d_g: np.ndarray,
    c_g: np.ndarray,
    a_i: np.ndarray | None = None,
    a_j: np.ndarray | None = None,
    want_covariance: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimum-variance estimate of Eq. 3.20-3.21 for projected observations of ``x_i - x_j``.

    ``d_g`` (M, 4), ``c_g`` (M, 4, 4) block-diagonal ``C``. The normal matrix
    ``H^T C^-1 H`` is assembled block-wise (each observation adds ``W`` at (i,i), (j,j) and
    ``-W`` at (i,j), (j,i)); the ``root`` sub-map is fixed at 0. Optional per-observation
    Jacobian blocks ``a_i``, ``a_j`` (M, 4, 4) replace ``+I`` / ``-I`` (model
    ``d ~ a_i x_i + a_j x_j``, used by the Gauss-Newton option). Returns poses (n, 4) (NaN where
    not connected to ``root``), ``C_x`` (4n, 4n; NaN unless ``want_covariance``) and the
    ``registered`` mask.
    """
    reg = reached_from(n, root, i, j) if len(i) else np.arange(n) == root
    use = reg[i] & reg[j]
    i, j, d_g, c_g = i[use], j[use], d_g[use], c_g[use]
    eye = np.broadcast_to(np.eye(4), (len(i), 4, 4))
    a_i = eye if a_i is None else a_i[use]
    a_j = -eye if a_j is None else a_j[use]
    w = np.linalg.inv(c_g)
    aiw = np.einsum("mba,mbc->mac", a_i, w)  # a_i^T W
    ajw = np.einsum("mba,mbc->mac", a_j, w)
    a = np.zeros((n, n, 4, 4))
    b = np.zeros((n, 4))
    np.add.at(a, (i, i), aiw @ a_i)
    np.add.at(a, (j, j), ajw @ a_j)
    np.add.at(a, (i, j), aiw @ a_j)
    np.add.at(a, (j, i), ajw @ a_i)
    np.add.at(b, i, np.einsum("mab,mb->ma", aiw, d_g))
    np.add.at(b, j, np.einsum("mab,mb->ma", ajw, d_g))
    free = np.flatnonzero(reg & (np.arange(n) != root))
    x = np.full((n, 4), np.nan)
    x[root] = 0.0
    idx_reg = (4 * np.flatnonzero(reg)[:, None] + np.arange(4)).reshape(-1)
    cov = np.full((4 * n, 4 * n), np.nan)
    cov[np.ix_(idx_reg, idx_reg)] = 0.0
    if free.size:
        af = a[np.ix_(free, free)].transpose(0, 2, 1, 3).reshape(4 * free.size, 4 * free.size)
        idx = (4 * free[:, None] + np.arange(4)).reshape(-1)
        if want_covariance:
            cf = np.linalg.inv(af)
            x[free] = (cf @ b[free].reshape(-1)).reshape(-1, 4)
            cov[np.ix_(idx, idx)] = cf
        else:
            x[free] = scipy.linalg.solve(af, b[free].reshape(-1), assume_a="pos").reshape(-1, 4)
            cov[np.ix_(idx, idx)] = np.nan
    return x, cov, reg


def observation_correlation(
    observations: pd.DataFrame, scan_correlation: float | Sequence[float] = 0.0
) -> np.ndarray:
    """rho per observation row (M, 4: x, y, z, heading): the ``RHO_COLUMNS`` of ``observations``
    where present and finite (each observation type has its own correlation, e.g. refined and
    branch-and-bound links, inferred), else ``scan_correlation``."""
    rho = np.tile(np.broadcast_to(np.asarray(scan_correlation, dtype=float), (4,)),
                  (len(observations), 1))
    if set(RHO_COLUMNS) <= set(observations.columns):
        own = observations.loc[:, list(RHO_COLUMNS)].to_numpy(dtype=float)
        rho = np.where(np.isfinite(own), own, rho)
    return rho


def shared_scan_covariance(
    cov: np.ndarray,
    n: int,
    root: int,
    i: np.ndarray,
    j: np.ndarray,
    c_g: np.ndarray,
    reg: np.ndarray,
    scan_correlation: float | Sequence[float] | np.ndarray,
) -> np.ndarray:
    """``C_x`` of the Lu-Milios estimate when observations sharing a scan are correlated.

    Model (beyond the thesis, inferred): the error of observation ``k = d_ij`` is
    ``sqrt(1 - 2 rho_k) v_k + u_i - u_j``, ``v_k ~ N(0, C_k)`` independent and ``u_s`` a per-scan
    error (the scan's own feature errors, shared by all its registrations) with covariance
    ``S_s = mean(rho_k C_k)`` over the used observations ``k`` touching scan ``s`` (projected
    blocks ``c_g``). With equal ``rho C`` an observation keeps its marginal covariance ``C`` and
    two observations sharing one scan have correlation ``rho`` (sign by the side the scan is on).
    Observations of different types (different rho rows, e.g. branch-and-bound links from the
    sub-maps' features and refined links fitted on the raw points) carry different errors of a
    scan: each type has its own ``u`` (``S`` averaged over that type only), uncorrelated across
    types. So ``C_full = D' + sum_t B_t S_t B_t^T`` with ``D' = diag((1 - 2 rho_k) C_k)`` and
    ``B_t`` the incidence matrix of the type-``t`` observations; the thesis's estimate ``A d``,
    ``A = (H^T D^-1 H)^-1 H^T D^-1`` (poses and residuals unchanged) has covariance
    ``A C_full A^T``: what this returns (``cov`` = ``(H^T D^-1 H)^-1``, 4n x 4n, root and
    unregistered rows as given). For one type this is ``(1 - 2 rho) C_x + K``
    (``K = S_free + 1 S_root 1^T``), the minimum-variance estimate's own covariance (Rao's
    condition ``A C Z = 0`` for ``H^T Z = 0``). ``rho = 0`` returns ``cov`` (the thesis); rho
    must lie in [0, 0.5]. rho is one value, one per component (x, y, z, heading; blocks scaled
    elementwise by ``sqrt(rho_a rho_b)`` and ``sqrt((1 - 2 rho_a) (1 - 2 rho_b))``, Schur
    products that keep them PSD) or one row per observation (M, 4;
    :func:`observation_correlation`).
    """
    rho = np.asarray(scan_correlation, dtype=float)
    rho = np.broadcast_to(rho if rho.ndim == 2 else np.broadcast_to(rho, (4,)), (len(i), 4))
    if not np.all((rho >= 0.0) & (rho <= 0.5)):
        raise ValueError(f"scan_correlation must lie in [0, 0.5], got {scan_correlation}")
    if not rho.any() or len(i) == 0:
        return cov
    use = reg[i] & reg[j]
    i, j, c_g, rho = i[use], j[use], c_g[use], rho[use]
    free = np.flatnonzero(reg & (np.arange(n) != root))
    out = cov.copy()
    if free.size == 0:
        return out
    m = len(i)
    share = np.sqrt(rho[:, :, None] * rho[:, None, :]) * c_g  # rho_k C_k, Schur form
    keep = np.sqrt((1.0 - 2.0 * rho)[:, :, None] * (1.0 - 2.0 * rho)[:, None, :])
    f = free.size
    pos = np.full(n, -1)
    pos[free] = np.arange(f)
    # A = C_x H^T D^-1 (H restricted to the free scans): observation k adds +D_k^-1 at its
    # scan's rows and -D_k^-1 at its reference's, so H^T D^-1 is built block by block
    inv = np.linalg.inv(c_g)
    htw = np.zeros((f, 4, m, 4))
    for ends, sign in ((i, 1.0), (j, -1.0)):
        ok = np.flatnonzero(pos[ends] >= 0)
        htw[pos[ends[ok]], :, ok, :] = sign * inv[ok]
    idx = (4 * free[:, None] + np.arange(4)).reshape(-1)
    a = (cov[np.ix_(idx, idx)] @ htw.reshape(4 * f, 4 * m)).reshape(4 * f, m, 4)
    # A C_full A^T with C_full = D' + sum_t B_t S_t B_t^T, never formed (4M x 4M): the
    # diagonal blocks D'_k = keep_k C_k, then per type sum_s (A B_t)_s S_t,s (A B_t)_s^T
    out_ff = np.einsum("fka,kab->fkb", a, keep * c_g).reshape(4 * f, 4 * m) @ a.reshape(4 * f, 4 * m).T
    _, kind = np.unique(rho, axis=0, return_inverse=True)
    a_t = a.transpose(0, 2, 1).reshape(4 * f * 4, m)
    for t in np.unique(kind):
        b = np.zeros((m, n))  # incidence of the type-t observations
        sel = np.flatnonzero(kind.ravel() == t)
        b[sel, i[sel]], b[sel, j[sel]] = 1.0, -1.0
        touching = np.abs(b).sum(0)
        s_t = ((np.abs(b).T @ share.reshape(m, 16)) / np.maximum(touching, 1.0)[:, None]).reshape(n, 4, 4)
        ab = (a_t @ b).reshape(4 * f, 4, n).transpose(0, 2, 1)  # (A B_t) per scan: (4F, N, 4)
        out_ff += np.einsum("fsa,sab->fsb", ab, s_t).reshape(4 * f, 4 * n) @ ab.reshape(4 * f, 4 * n).T
    out[np.ix_(idx, idx)] = out_ff
    return out


def _rot(phi_deg: np.ndarray) -> np.ndarray:
    """R_z(phi) (M, 2, 2) for headings in degrees."""
    p = np.radians(phi_deg)
    c, s = np.cos(p), np.sin(p)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def gauss_newton(
    n: int,
    i: np.ndarray,
    j: np.ndarray,
    d: np.ndarray,
    sd: np.ndarray,
    x0: np.ndarray,
    *,
    max_iterations: int = 50,
    tolerance: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Maximum-likelihood 4-DoF network by Gauss-Newton (beyond the thesis, inferred option).

    Minimises ``sum e^T W e`` with the residual in the reference's levelled frame,
    ``e_xy = R(-phi_j)(p_i - p_j) - (dx, dy)``, ``e_z = z_i - z_j - dz``,
    ``e_phi = phi_i - phi_j - dphi`` and ``W = diag(sd^-2)`` there, linearised in all poses
    including the reference's heading (the lever-arm term the thesis's projection leaves out),
    from ``x0`` (sub-map 0 fixed at 0). The fixed point is what a Pose2 factor graph (GTSAM)
    returns. Returns poses, ``C_x`` (4n, 4n), the registered mask and the iteration count.
    """
    x = np.array(x0, dtype=float, copy=True)
    w_cov = np.zeros((len(i), 4, 4))
    w_cov[:, np.arange(4), np.arange(4)] = np.asarray(sd, dtype=float) ** 2
    deg = np.radians(1.0)
    rounds, last_step = 0, np.inf
    while rounds < max_iterations:
        rounds += 1
        rt = _rot(-x[j, 3])  # R(-phi_j)
        dp = x[i, :2] - x[j, :2]
        e = np.empty((len(i), 4))
        e[:, :2] = np.einsum("mab,mb->ma", rt, dp) - d[:, :2]
        e[:, 2] = x[i, 2] - x[j, 2] - d[:, 2]
        e[:, 3] = wrap_deg(x[i, 3] - x[j, 3] - d[:, 3])
        a_i = np.zeros((len(i), 4, 4))
        a_i[:, :2, :2] = rt
        a_i[:, 2, 2] = a_i[:, 3, 3] = 1.0
        a_j = -a_i.copy()
        # d/dphi_j of R(-phi_j) dp = -R'(-phi_j) dp = R(-phi_j) [[0, 1], [-1, 0]] dp, per degree
        a_j[:, :2, 3] = deg * np.einsum("mab,mb->ma", rt, np.column_stack([dp[:, 1], -dp[:, 0]]))
        converged = rounds > 1 and last_step < tolerance
        step, cov, reg = solve_linear(n, 0, i, j, -e, w_cov, a_i, a_j,
                                      want_covariance=converged or rounds == max_iterations)
        x = np.where(reg[:, None], x + np.nan_to_num(step), np.nan)
        last_step = float(np.nanmax(np.abs(step)))
        if converged:
            break
    return x, cov, reg, rounds


def _as_array(values: Mapping[str, float] | None, scans: Sequence[str]) -> np.ndarray:
    values = values or {}
    return np.array([float(values.get(s, np.nan)) for s in scans])


def solve_network(
    observations: pd.DataFrame,
    scans: Sequence[str],
    *,
    headings: Mapping[str, float] | None = None,
    heading_variances: Mapping[str, float] | None = None,
    covariance: Covariance = "published",
    iterate: bool = False,
    max_iterations: int = 50,
    tolerance_deg: float = 1e-9,
    residual_sigmas: float = 3.0,
    z_residual_sigmas: float = 8.0,
    linearisation: Linearisation = "projection",
    scan_correlation: float | Sequence[float] = 0.0,
) -> MapSolution:
    """Optimal map of the sub-maps ``scans`` (``scans[0]`` = reference) from ``observations``.

    Observations are projected with ``headings`` (global headings of their reference sub-maps,
    e.g. the previous phase's solution; the reference is at 0; missing sub-maps are chained from
    known ones, see :func:`propagate_headings`), unwrapped (spec 8.4 item 4) and solved with
    Eq. 3.20-3.21. ``iterate=True`` repeats projection and solve until the headings change by
    less than ``tolerance_deg`` (spec 8.4 item 5, inferred; the thesis projects once per phase).
    ``heading_variances`` (deg^2) feed ``covariance="full"``. Rows whose scans are not all in
    ``scans`` are ignored; sub-maps not connected to the reference are not registered.
    ``scan_correlation`` (rho, default 0 = the thesis's independent observations; an
    observation's own ``RHO_COLUMNS`` take precedence) inflates ``C_x`` for errors shared by the
    observations of one scan (:func:`shared_scan_covariance`; poses and residuals do not change).
    """
    if linearisation not in ("projection", "gauss_newton"):
        raise ValueError(f"linearisation must be 'projection' or 'gauss_newton', "
                         f"got {linearisation!r}")
    scans = [str(s) for s in scans]
    n = len(scans)
    i, j, d, sd = observation_arrays(observations, scans)
    rows = np.flatnonzero((i >= 0) & (j >= 0) & (i != j))
    i, j, d, sd = i[rows], j[rows], d[rows].copy(), sd[rows]
    rho = observation_correlation(observations, scan_correlation)[rows]
    h = _as_array(headings, scans)
    hv = _as_array(heading_variances, scans)
    h[0], hv[0] = 0.0, 0.0
    hv = np.where(np.isnan(hv) & ~np.isnan(h), 0.0, hv)
    h, hv = propagate_headings(n, i, j, d[:, 3], sd[:, 3], h, hv)
    rounds = 0
    while True:
        rounds += 1
        d[:, 3] = unwrap_headings(d[:, 3], h[i] - h[j])
        dg, cg = project_relative(d, sd, h[j], hv[j], covariance)
        x, cov, reg = solve_linear(n, 0, i, j, dg, cg)
        cov = shared_scan_covariance(cov, n, 0, i, j, cg, reg, rho)
        if not iterate or rounds >= max_iterations:
            break
        change = np.nanmax(np.abs(x[reg, 3] - h[reg])) if reg.any() else 0.0
        h = np.where(reg, x[:, 3], h)
        hv = np.where(reg, np.diagonal(cov)[3::4], hv)
        if change < tolerance_deg:
            break
    if linearisation == "gauss_newton":
        x, cov, reg, gn_rounds = gauss_newton(n, i, j, d, sd, np.nan_to_num(x),
                                              max_iterations=max_iterations)
        rounds += gn_rounds
        h = np.where(reg, x[:, 3], h)
        hv = np.where(reg, np.diagonal(cov)[3::4], hv)
        d[:, 3] = unwrap_headings(d[:, 3], h[i] - h[j])
        dg, cg = project_relative(d, sd, h[j], hv[j], covariance)
        cov = shared_scan_covariance(cov, n, 0, i, j, cg, reg, rho)  # approx.
    var = np.diagonal(cov).reshape(n, 4)
    poses = pd.DataFrame(x, columns=list(POSE_COLUMNS))
    poses.insert(0, "scan", scans)
    poses[list(POSE_SD_COLUMNS)] = np.sqrt(np.clip(var, 0.0, None))
    poses["registered"] = reg
    used = reg[i] & reg[j]
    sd_g = np.sqrt(np.diagonal(cg, axis1=1, axis2=2))
    projected = pd.DataFrame({"scan": [scans[k] for k in i[used]],
                              "reference": [scans[k] for k in j[used]]})
    projected[list(OBSERVATION_COLUMNS[2:6])] = dg[used]
    projected[list(OBSERVATION_COLUMNS[6:])] = sd_g[used]
    projected["cov_xy"] = cg[used, 0, 1]
    projected["projection_heading_deg"] = h[j[used]]
    projected["observation"] = observations.index[rows[used]]
    e, r = residual_arrays(i[used], j[used], dg[used], sd_g[used], x)
    residuals = residual_table(projected["scan"], projected["reference"], e, r,
                               residual_sigmas, z_residual_sigmas)
    residuals.index = projected.index
    return MapSolution(scans, scans[0], poses, cov, projected, residuals, rounds)


def solve_incremental(
    observations: pd.DataFrame,
    order: Sequence[str],
    *,
    covariance: Covariance = "published",
    iterate: bool = False,
    max_iterations: int = 50,
    tolerance_deg: float = 1e-9,
    residual_sigmas: float = 3.0,
    z_residual_sigmas: float = 8.0,
    linearisation: Linearisation = "projection",
    scan_correlation: float | Sequence[float] = 0.0,
) -> OptimalMap:
    """Optimal map re-solved phase by phase as sub-maps are added in ``order`` (spec 8.4).

    Phase k holds ``order[:k+1]`` (phase 1 = {reference, second}) and all observations among
    them; every observation is re-projected with the headings (and, for ``covariance="full"``,
    heading variances) of the previous phase's solution, the new sub-map's heading chained from
    its links. Returns every phase (Table 6.8/6.9 rows); a single-scan order gives one phase.
    ``linearisation="gauss_newton"`` solves every phase to the maximum-likelihood map instead
    (beyond the thesis, see :func:`gauss_newton`); ``scan_correlation`` see
    :func:`solve_network`.
    """
    order = [str(s) for s in order]
    headings: dict[str, float] = {order[0]: 0.0}
    variances: dict[str, float] = {order[0]: 0.0}
    phases = []
    for k in range(min(2, len(order)), len(order) + 1):
        sol = solve_network(
            observations, order[:k], headings=headings, heading_variances=variances,
            covariance=covariance, iterate=iterate, max_iterations=max_iterations,
            tolerance_deg=tolerance_deg, residual_sigmas=residual_sigmas,
            z_residual_sigmas=z_residual_sigmas, linearisation=linearisation,
            scan_correlation=scan_correlation,
        )
        headings = {**headings, **sol.headings()}
        variances = {**variances, **sol.heading_variances()}
        phases.append(sol)
    return OptimalMap(order, phases)
