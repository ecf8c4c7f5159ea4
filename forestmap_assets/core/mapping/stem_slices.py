"""DBH from the merged, registered points of a thin slice at breast height (issue 19, inferred).

The cylinder DBH of :func:`~forestmap_assets.core.mapping.trees.merge_trees` averages the radii
of circles fitted to one scan's arc at a time. An out-of-round stem seen from one side shows the
local curvature of its section, not its mean radius (an ellipse of flattening 10 % has radii of
curvature 15 % above and below the mean), so per-scan arcs are biased one way or the other.
Here the points of every registered scan in a thin horizontal slice about breast height are
gathered in the global frame (:func:`gather_slices`) and one outline is fitted to the merged
slice (:func:`slice_dbh`):

1. points beyond ``max_incidence_deg`` from the surface normal, or within ``edge_footprints``
   beam footprint radii (``beam_exit_m + beam_divergence_rad r`` across: the campaign's
   scanner, spec 1.1's ``0.042 + 0.003 r`` m on the own simulator) of a scan's silhouette
   edge, are left out: there the footprint overhangs the stem (mixed pixels, +3 cm outside the
   bark in simulation) and grazing bark reads high (+0.5-1 cm);
2. each point is binned where its ray met the current circle, at the angle of the outward
   normal there, and measures the outline by its distance from the centre along that normal
   (:func:`_along_ray_hits`: range noise moves a point along its ray, so this is linear in the
   noise and the bin does not depend on it); each bin gives a trimmed mean, and a second-order
   Fourier outline ``r(psi) = a0 + dx cos psi + dy sin psi +
   a2 cos 2psi + b2 sin 2psi`` is fitted to the bins by weighted least squares (a bin's
   variance: its mean's noise plus ``outline_sd_m`` of bark relief, so well-filled bins weigh
   alike and ``a0`` is the mean radius over angle, not over points), with a ridge prior on the
   ellipse terms (sd ``ellipse_prior`` x ``a0``: an arc seen from one or two sides cannot tell
   an ellipse from a shifted circle) and, with ``radius_prior_sd_m``, the cylinders' radius as
   a prior of ``a0``; ``(dx, dy)`` moves the centre and the fit is repeated; points farther
   than ``trim_sigmas`` robust sigmas from the outline (branch stubs, understorey) are dropped,
   and so is a bin whose leave-one-out residual exceeds ``loo_sigmas`` of its own sd (a few
   stray points alone on the side no scan saw: there the outline is free, and the fit follows
   them unless they are left out);
3. DBH = ``2 a0`` (the simulator's truth: twice the mean radius at 1.3 m of the section,
   ``sim/stem_shapes.py``). Without the scanners' positions the points are binned by their own
   angle and the DBH loses the outward bias ``sigma^2 / (4 r)`` that range noise ``sigma`` adds
   to a point's distance from the centre (at incidence ``i``, ``sigma^2 sin^2(i) / (2 r)``).

Binned by its own angle, a point whose ray passed near the limb and whose range the noise made
longer lands beyond the arc's other points and inside the outline: with 2.5 cm noise the arc's
end bins read 1.4-2 cm inside, which pulled the centre towards the scans and the DBH 1 cm small
from two sides (own realistic seed 123: a 47.9 cm stem seen from four scans read 44.9 cm; by
the rays 46.6 cm). Twelve own realistic surveys at full resolution: the outline's DBH error
1.15 -> 1.18 cm RMSE but its bias +0.06 -> -0.05 cm, 46 trees better by 3 mm or more and 17 worse.

A slice with fewer than ``min_points`` points or less than ``min_coverage_deg`` of the
circumference seen (180 deg: a one-sided arc of about 120 deg with 2.5 cm range noise fits
mean radii centimetres off, worse than the cylinders), or whose outline leaves the plausible
range around the cylinder radius, gives no estimate and the caller keeps the cylinder DBH
(:func:`slice_dbhs` says why in ``dbh_note``). Simulated 40 m plots: ``benchmarks/results.md``,
section "DBH from the merged breast-height slice".
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from forestmap_assets.core.geometry import rot_z, transform_points
from forestmap_assets.core.mapping.cylinder_radii import MAX_SLOPE, axis_slopes
from forestmap_assets.core.mapping.slice_splats import splat_back
from forestmap_assets.core.memo import content_memo

if TYPE_CHECKING:
    import pyarrow as pa

SLICE_COLUMNS = ["tree", "x", "y", "z", "scan"]


@dataclass(frozen=True)
class SliceFit:
    """Result of :func:`slice_dbh`: ``dbh_m`` NaN when the slice gave no estimate (``reason``)."""

    dbh_m: float
    x: float
    y: float
    n_points: int
    coverage_deg: float
    rms_m: float
    reason: str = ""
    sd_m: float = float("nan")
    sigma_m: float = float("nan")  # robust scatter of the points about the outline


def _in_band(z: np.ndarray, zbh: np.ndarray, half_height_m: float) -> np.ndarray:
    """Global heights ``z`` within ``half_height_m`` of any breast height ``zbh`` range."""
    return (z >= zbh.min() - half_height_m) & (z <= zbh.max() + half_height_m)


class StemCells:
    """A 2-D grid of ``cell_m`` cells over the stems: each cell near a stem (within its reach
    ``reach`` of the axis ``centre``) holds the height band ``zbh`` +- ``half_height_m`` of the
    stems near it, so a point far from every slice is dropped by one lookup before the k-d tree
    (a point that a stem's slice keeps always lies in a cell that stem marked)."""

    def __init__(self, centre: np.ndarray, zbh: np.ndarray, reach: np.ndarray, half_height_m: float,
                 cell_m: float = 0.5):
        self.cell = cell_m
        self.lo = centre.min(axis=0) - reach.max() - cell_m
        self.shape = np.floor((centre.max(axis=0) + reach.max() + cell_m - self.lo) / cell_m).astype(int) + 1
        span = np.arange(-int(np.ceil(reach.max() / cell_m)) - 1, int(np.ceil(reach.max() / cell_m)) + 2)
        ox, oy = (a.ravel() for a in np.meshgrid(span, span, indexing="ij"))
        home = np.floor((centre - self.lo) / cell_m).astype(int)
        ix, iy = home[:, :1] + ox, home[:, 1:] + oy  # (stems, offsets)
        dist = np.hypot(self.lo[0] + (ix + 0.5) * cell_m - centre[:, :1], self.lo[1] + (iy + 0.5) * cell_m - centre[:, 1:])
        ok = (dist <= reach[:, None] + cell_m * 0.7072) & (ix >= 0) & (iy >= 0) & (ix < self.shape[0]) & (iy < self.shape[1])
        z = np.broadcast_to(zbh[:, None], ix.shape)[ok]
        self.z_lo = np.full(tuple(self.shape), np.inf)
        self.z_hi = np.full(tuple(self.shape), -np.inf)
        np.minimum.at(self.z_lo, (ix[ok], iy[ok]), z - half_height_m)
        np.maximum.at(self.z_hi, (ix[ok], iy[ok]), z + half_height_m)

    def near(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Indices of the points (``x, y, z``, any float dtype) that lie in a marked cell within
        its height band."""
        from forestmap_assets.core.mapping._slice_kernels import cells_near

        z_lo, z_hi = self.z_lo.ravel(), self.z_hi.ravel()
        return cells_near(x, y, z, float(self.lo[0]), float(self.lo[1]), float(self.cell), int(self.shape[0]),
                          int(self.shape[1]), z_lo, z_hi, float(z_lo.min()), float(z_hi.max()))


def slice_members(p: np.ndarray, tree: cKDTree, zbh: np.ndarray, slope: np.ndarray, reach: np.ndarray,
                  half_height_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which of the global points ``p`` (n, 3) lie in a stem's slice: within ``half_height_m``
    of its breast height ``zbh`` and within ``reach`` of its axis (through the k-d ``tree`` of
    the axes at breast height, leaning by ``slope``) at the point's height, the nearest stem
    deciding. Returns the points' indices, their stems' rows and their heights above breast
    height."""
    reach_max = float(np.max(reach + np.hypot(*slope.T) * half_height_m))
    _, k = tree.query(p[:, :2], distance_upper_bound=reach_max)
    hit = np.flatnonzero(k < len(zbh))
    k = k[hit]
    dz = p[hit, 2] - zbh[k]
    xy = p[hit, :2] - slope[k] * dz[:, None]
    keep = (np.abs(dz) <= half_height_m) & (np.hypot(*(xy - tree.data[k]).T) <= reach[k])
    return hit[keep], k[keep], dz[keep]


def gather_slices(clouds: Mapping[str, np.ndarray], poses: pd.DataFrame, stems: pd.DataFrame, *,
                  half_height_m: float = 0.1, gate_factor: float = 1.5, gate_margin_m: float = 0.05,
                  splats: Mapping[str, tuple[float, float]] | None = None) -> tuple[pd.DataFrame, np.ndarray]:
    """Points of every registered scan in each stem's breast-height slice, global frame.

    ``clouds`` maps scan id to its levelled points (n, 3) in the scanner frame; ``poses`` has
    ``scan, x, y, z, heading_deg`` of the placed scans (spec 6.1: ``p' = R_z(heading) p + t``);
    ``stems`` has ``x, y`` (axis at breast height), ``zbh`` (breast height, global z),
    ``radius_m`` (approximate) and optionally ``slope_x, slope_y`` (lean). A point belongs to
    the slice of the nearest stem when it lies within ``half_height_m`` of its breast height and
    within ``gate_factor`` x radius + ``gate_margin_m`` of its axis at the point's height.

    Returns ``SLICE_COLUMNS`` (``tree`` the 0-based row of ``stems``, ``x, y`` moved along the
    axis to breast height, ``z`` the original height, ``scan`` the index into ``clouds``) and the
    sensor position (scans, 2) of each scan index. One k-d tree query per scan. ``splats``:
    scan id -> (splat radius, angular step) of scans whose splat widening is taken back
    (:func:`~.slice_splats.splat_back`)."""
    scan_ids = list(clouds)
    sensors = np.full((len(scan_ids), 2), np.nan)
    empty = pd.DataFrame({c: pd.Series(dtype="int64" if c in ("tree", "scan") else "float64")
                          for c in SLICE_COLUMNS})
    if len(stems) == 0:
        return empty, sensors
    centre = stems[["x", "y"]].to_numpy(float)
    zbh = stems["zbh"].to_numpy(float)
    slope = (stems[["slope_x", "slope_y"]].to_numpy(float) if {"slope_x", "slope_y"} <= set(stems)
             else np.zeros((len(stems), 2)))
    reach = gate_factor * stems["radius_m"].to_numpy(float) + gate_margin_m
    tree = cKDTree(centre)
    placed = poses.set_index("scan")
    parts = []
    for index, sid in enumerate(scan_ids):
        xyz = clouds[sid]
        if sid not in placed.index or xyz is None or len(xyz) == 0:
            continue
        pose = placed.loc[sid, ["x", "y", "z", "heading_deg"]].to_numpy(float)
        sensors[index] = pose[:2]
        near = _in_band(np.asarray(xyz[:, 2], np.float64) + pose[2], zbh, half_height_m)
        p = transform_points(np.asarray(xyz[near], np.float64), pose)
        i, k, dz = slice_members(p, tree, zbh, slope, reach, half_height_m)
        xy = p[i, :2] - slope[k] * dz[:, None]
        if splats and sid in splats:
            rng = np.linalg.norm(np.asarray(xyz[near][i], np.float64), axis=1)
            xy = splat_back(xy, pose[:2], centre[k], rng, *splats[sid])
        parts.append(pd.DataFrame({"tree": k, "x": xy[:, 0], "y": xy[:, 1],
                                   "z": p[i, 2], "scan": np.full(i.size, index)}))
    if not parts:
        return empty, sensors
    return pd.concat(parts, ignore_index=True)[SLICE_COLUMNS], sensors


def _bin_means(bins: np.ndarray, values: np.ndarray, n_bins: int,
               trim: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Per-bin trimmed mean of ``values`` (the central ``1 - 2 trim`` share) and the count of
    points per bin (vectorised: one sort by bin then value)."""
    order = np.lexsort((values, bins))
    b, v = bins[order], values[order]
    count = np.bincount(b, minlength=n_bins)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    rank = np.arange(b.size) - start[b]
    cut = np.floor(trim * count).astype(int)
    keep = (rank >= cut[b]) & (rank < (count - cut)[b])
    total = np.bincount(b[keep], v[keep], minlength=n_bins)
    kept = np.bincount(b[keep], minlength=n_bins)
    return np.where(kept > 0, total / np.maximum(kept, 1), np.nan), count


@content_memo(4096)  # the anchor passes fit most trees again with the same arguments
def slice_dbh(xy: np.ndarray, sensor_xy: np.ndarray | None, centre: tuple[float, float],
              radius_m: float, *, max_incidence_deg: float = 65.0, bin_deg: float = 10.0,
              min_points: int = 30, min_coverage_deg: float = 180.0, ellipse_prior: float = 0.05,
              trim_sigmas: float = 3.0, range_sigma_m: float = 0.025, outline_sd_m: float = 0.005,
              radius_prior_sd_m: float | None = None, edge_footprints: float = 1.5,
              beam_exit_m: float = 0.042, beam_divergence_rad: float = 0.003,
              radius_range: tuple[float, float] = (0.5, 1.6), iterations: int = 6,
              loo_sigmas: float | None = None, sides: tuple | None = None,
              side_reject_m: float = 0.02) -> SliceFit:
    """DBH of one stem from its merged slice points ``xy`` (n, 2), seen from ``sensor_xy``
    (n, 2; None: no incidence test), starting from the axis ``centre`` and ``radius_m`` (the
    cylinders'); the method is in the module docstring. ``radius_range`` (shares of
    ``radius_m``) bounds a plausible mean radius; outside it the slice gives no estimate.
    ``sides``: silhouette sides ``(phi, h, w)`` (outward normals, distances from ``centre``,
    inverse variances; :mod:`.stem_outline`) fitted with the bins, less those farther than
    ``side_reject_m`` from the outline after the first round."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    c = np.asarray(centre, np.float64).copy()
    c_start = c.copy()
    n_bins = max(4, int(round(360.0 / bin_deg)))
    none = SliceFit(np.nan, c[0], c[1], len(xy), 0.0, np.nan)
    if len(xy) < min_points or not np.isfinite(radius_m) or radius_m <= 0:
        return _with(none, reason=f"{len(xy)} points")
    sin_max = np.sin(np.radians(max_incidence_deg))
    keep = np.ones(len(xy), bool)
    a0, theta, sigma, sd = float(radius_m), np.zeros(5), max(0.5 * radius_m, 0.02), np.nan
    coverage, rms = 0.0, np.nan
    for it in range(iterations):
        if sensor_xy is not None:
            d, psi, lateral = _along_ray_hits(xy, sensor_xy, c, a0)
        else:
            v = xy - c
            d, psi = np.hypot(*v.T), np.arctan2(v[:, 1], v[:, 0])
        model = a0 + theta[3] * np.cos(2 * psi) + theta[4] * np.sin(2 * psi)
        keep = np.abs(d - model) <= max(trim_sigmas * sigma, 0.01) if it else (
            (d > 0.5 * radius_m) & (d < radius_range[1] * radius_m + 0.05))
        if sensor_xy is not None:  # off the silhouette's edges (mixed pixels, grazing bark)
            footprint = 0.5 * (beam_exit_m + beam_divergence_rad * np.hypot(*(c - sensor_xy).T))
            keep &= lateral <= np.minimum(a0 * sin_max, a0 - edge_footprints * footprint)
        if keep.sum() < min_points:
            return _with(none, n_points=int(keep.sum()), reason=f"{int(keep.sum())} points")
        resid_pts = d[keep] - (a0 + theta[3] * np.cos(2 * psi[keep]) + theta[4] * np.sin(2 * psi[keep]))
        sigma = max(1.4826 * float(np.median(np.abs(resid_pts - np.median(resid_pts)))), 0.003)
        b = np.minimum(((psi[keep] + np.pi) / (2 * np.pi) * n_bins).astype(int), n_bins - 1)
        mean_d, count = _bin_means(b, d[keep], n_bins)
        filled = count >= 2
        coverage = float(filled.sum() * 360.0 / n_bins)
        if coverage < min_coverage_deg:
            return _with(none, n_points=int(keep.sum()), coverage_deg=coverage, sigma_m=sigma,
                         reason=f"{coverage:.0f} deg of the circumference seen")
        ang = np.angle(np.bincount(b, np.exp(1j * psi[keep]).real, minlength=n_bins)
                       + 1j * np.bincount(b, np.exp(1j * psi[keep]).imag, minlength=n_bins))[filled]
        A = np.column_stack([np.ones(ang.size), np.cos(ang), np.sin(ang), np.cos(2 * ang), np.sin(2 * ang)])
        # bin variance: the trimmed mean's noise plus the outline's own relief (bark, flutes)
        W = 1.0 / (sigma**2 / np.maximum(count[filled] * 0.6, 1.0) + outline_sd_m**2)
        lam, prior = np.zeros(5), np.zeros(5)
        lam[3:] = 1.0 / (ellipse_prior * a0) ** 2
        if radius_prior_sd_m:  # the cylinders' radius as a prior of the mean radius
            lam[0], prior[0] = 1.0 / radius_prior_sd_m**2, radius_m / radius_prior_sd_m**2
        y = mean_d[filled]
        n_binned = y.size
        if sides is not None:  # a side's tangent is the outline's support: the same terms
            A, W, y = _with_sides(A, W, y, sides, c - c_start, a0, theta, side_reject_m if it else None,
                                  radius_range)
        while True:
            normal = A.T @ (A * W[:, None]) + np.diag(lam)
            if np.linalg.cond(normal) > 1e12:  # too few bins and sides to place the outline
                return _with(none, n_points=int(keep.sum()), coverage_deg=coverage, reason="outline undetermined")
            inv = np.linalg.inv(normal)
            a = inv @ (A.T @ (W * y) + prior)
            # a bin the others do not predict (a branch or a neighbour's bark on the side not
            # seen): its residual left out of the fit, in its own sd (leave-one-out)
            hat = np.clip(W * np.einsum("ij,jk,ik->i", A, inv, A), 0.0, 1.0 - 1e-9)
            t = np.abs(y - A @ a) * np.sqrt(W / (1.0 - hat))
            t[n_binned:] = 0.0  # the sides are judged by side_reject_m
            worst = int(np.argmax(t))
            if not loo_sigmas or t[worst] <= loo_sigmas:
                break
            A, W, y = (np.delete(v, worst, axis=0) for v in (A, W, y))
            n_binned -= 1
            coverage -= 360.0 / n_bins
            if coverage < min_coverage_deg:
                return _with(none, n_points=int(keep.sum()), coverage_deg=coverage, sigma_m=sigma,
                             reason=f"{coverage:.0f} deg of the circumference seen")
        sd = float(np.sqrt(inv[0, 0]))
        c = c + a[1:3]
        a0, theta = float(a[0]), a
        rms = float(np.sqrt(np.average((y - A @ a) ** 2, weights=W)))
        if not (radius_range[0] * radius_m <= a0 <= radius_range[1] * radius_m) or (
                np.hypot(*(c - centre)) > radius_m):
            return _with(none, n_points=int(keep.sum()), coverage_deg=coverage,
                         reason=f"outline radius {a0 * 100:.1f} cm off the cylinders' {radius_m * 100:.1f} cm")
        if np.hypot(*a[1:3]) < 2e-4:
            break
    # without rays, the outward bias of a noisy point's distance from the centre (incidence
    # unknown: sin^2 i = 1/2): E[d] - r = sigma^2 sin^2(i) / 2r
    bias = 0.0 if sensor_xy is not None else range_sigma_m**2 / (4.0 * a0)
    return SliceFit(2.0 * (a0 - bias), float(c[0]), float(c[1]), int(keep.sum()), coverage, rms,
                    sd_m=2.0 * sd, sigma_m=sigma)


def _along_ray_hits(xy: np.ndarray, sensor_xy: np.ndarray, c: np.ndarray,
                    a0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's distance from the centre ``c`` along the outward normal ``n`` where its ray
    meets the circle of radius ``a0`` (the limb for a ray that misses it), the normal's angle
    ``psi``, and the ray's lateral distance from ``c``. Range noise moves a point along its ray
    and so leaves ``n`` alone: ``(p - c) . n`` is linear in it, and a point is binned where its
    ray looked (module docstring, step 2)."""
    ray = xy - sensor_xy
    u = ray / np.maximum(np.hypot(*ray.T), 1e-12)[:, None]
    to_c = c - sensor_xy
    lateral = np.abs(u[:, 0] * to_c[:, 1] - u[:, 1] * to_c[:, 0])
    t_hit = (u * to_c).sum(1) - np.sqrt(np.clip(a0**2 - lateral**2, 0.0, None))
    n = sensor_xy + t_hit[:, None] * u - c
    n /= np.maximum(np.hypot(*n.T), 1e-12)[:, None]
    return ((xy - c) * n).sum(1), np.arctan2(n[:, 1], n[:, 0]), lateral


def _with_sides(A, W, y, sides, moved, a0, theta, reject_m, radius_range):
    """The bins' rows ``A, W, y`` with the sides' (``sides = (phi, h, w)``, ``h`` from the
    start centre, so less ``moved`` along each normal), kept while within ``radius_range`` of
    ``a0`` and, with ``reject_m``, that close to the current outline."""
    phi, h, w = (np.asarray(v, np.float64) for v in sides)
    h = h - (moved[0] * np.cos(phi) + moved[1] * np.sin(phi))
    keep = (h >= radius_range[0] * a0) & (h <= radius_range[1] * a0)
    if reject_m is not None:
        keep &= np.abs(h - (a0 + theta[3] * np.cos(2 * phi) + theta[4] * np.sin(2 * phi))) <= reject_m
    phi = phi[keep]
    rows = np.column_stack([np.ones(phi.size), np.cos(phi), np.sin(phi), np.cos(2 * phi), np.sin(2 * phi)])
    return np.vstack([A, rows]), np.concatenate([W, w[keep]]), np.concatenate([y, h[keep]])


def _with(fit: SliceFit, **changes) -> SliceFit:
    return SliceFit(**{**fit.__dict__, **changes})


def slice_dbhs(trees: pd.DataFrame, slices: pd.DataFrame, sensors: np.ndarray, *,
               max_change: float = 0.5, **fit_kw) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``trees`` (``TREE_COLUMNS``, rows in the order of the slices' ``tree`` index) with the DBH
    from each stem's slice (:func:`slice_dbh`, keywords ``fit_kw``) where it gives one within
    ``max_change`` (share) of the cylinder DBH; elsewhere the cylinder DBH stays and
    ``dbh_note`` says why. Also a table of the fits (``tree_id, dbh_slice_m, dbh_cylinders_m,
    n_points, coverage_deg, rms_m, reason``)."""
    out = trees.copy()
    order = np.argsort(slices["tree"].to_numpy(), kind="stable")
    s = slices.iloc[order]
    k = s["tree"].to_numpy()
    bounds = np.searchsorted(k, np.arange(len(trees) + 1))
    xy = s[["x", "y"]].to_numpy(float)
    sens = sensors[s["scan"].to_numpy()] if len(s) else np.zeros((0, 2))
    rows, dbh, notes = [], out["dbh_m"].to_numpy(float).copy(), out["dbh_note"].astype(str).tolist()
    for i in range(len(trees)):
        old = dbh[i]
        lo, hi = bounds[i], bounds[i + 1]
        if not np.isfinite(old):
            fit = SliceFit(np.nan, np.nan, np.nan, hi - lo, 0.0, np.nan, "no cylinder DBH to start from")
        else:
            fit = slice_dbh(xy[lo:hi], sens[lo:hi], (out["x"].iat[i], out["y"].iat[i]), old / 2, **fit_kw)
        reason = fit.reason
        if not reason and abs(fit.dbh_m - old) > max_change * old:
            reason = f"slice DBH {fit.dbh_m * 100:.1f} cm too far from the cylinders'"
        rows.append((out["tree_id"].iat[i], fit.dbh_m, old, fit.sd_m, fit.n_points, fit.coverage_deg, fit.rms_m,
                     fit.sigma_m, reason))
        if not np.isfinite(old):
            continue
        ground = [p for p in notes[i].split("; ") if p.startswith("ground under the stem not seen")]
        if reason:
            notes[i] = "; ".join(filter(None, [notes[i], f"DBH from the cylinders: breast-height slice {reason}"]))
        else:
            dbh[i] = fit.dbh_m
            notes[i] = "; ".join(ground)
    out["dbh_m"] = dbh
    out["dbh_note"] = notes
    fits = pd.DataFrame(rows, columns=["tree_id", "dbh_slice_m", "dbh_cylinders_m", "sd_m", "n_points",
                                       "coverage_deg", "rms_m", "sigma_m", "reason"])
    return out, fits


def slice_clouds(tables: Mapping[str, pa.Table], poses: pd.DataFrame, trees: pd.DataFrame, tp,
                 breast_height_m: float = 1.3) -> dict[str, np.ndarray]:
    """The levelled points (n, 3) of each placed scan's table (columns ``x, y, z``, scanner
    frame) that may lie in a breast-height slice of ``trees``: within the slice's height band
    and gate (:func:`gather_slices`, any lean up to ``MAX_SLOPE``) of a stem, found with the
    stems' cells (:class:`StemCells`) in the scan's own frame, so that :func:`gather_slices`
    keeps the same points: a scan's full cloud is several times larger than the slices. The
    gate is that of the widest anchor ``tp.anchor_max_share`` (:func:`~.tree_dbh.tree_dbh`)."""
    zbh = trees["z"].to_numpy(float) + breast_height_m
    if not len(zbh):
        return {}
    half = gather_half_height(tp)
    centre = trees[["x", "y"]].to_numpy(float)
    radius = widest_anchor(tp) * np.nan_to_num(trees["dbh_m"].to_numpy(float) / 2, nan=0.0)
    reach = tp.slice_gate_factor * radius + tp.slice_gate_margin_m + MAX_SLOPE * half
    placed = poses.assign(scan=poses["scan"].astype(str)).set_index("scan")
    out = {}
    for sid, tbl in tables.items():
        if sid not in placed.index:
            continue
        x, y, z, h = placed.loc[sid, ["x", "y", "z", "heading_deg"]].to_numpy(float)
        local = (centre - (x, y)) @ rot_z(h)[:2, :2]  # the stems in the scan's frame: R^T (p - t)
        cells = StemCells(local, zbh - z, reach, half)
        cols = [tbl.column(a).to_numpy() for a in "xyz"]
        near = cells.near(*cols)
        out[sid] = np.column_stack([a[near] for a in cols])
    return out


def widest_anchor(tp) -> float:
    """The widest radius a tree's gates may take, as a share of the cylinders' (the anchors of
    :func:`~.tree_dbh.tree_dbh`, ``tp.anchor_max_share``; 1 without them)."""
    return max(1.0, tp.anchor_max_share) if tp.anchor_passes > 0 else 1.0


def slice_stems(trees: pd.DataFrame, cyl: pd.DataFrame, tree_of_cyl: np.ndarray,
                breast_height_m: float = 1.3) -> pd.DataFrame:
    """The stems' slices of the tree list ``trees`` (``tree_of_cyl`` over the global cylinders
    ``cyl``): ``x, y`` (axis at breast height), ``zbh`` (global z of breast height),
    ``radius_m`` (the cylinders', 0 where none) and the axis's lean ``slope_x, slope_y``."""
    zbh = trees["z"].to_numpy(float) + breast_height_m
    slopes = axis_slopes(cyl, tree_of_cyl, len(trees), z_max=zbh + 2.0)
    return pd.DataFrame({"x": trees["x"].to_numpy(float), "y": trees["y"].to_numpy(float), "zbh": zbh,
                         "radius_m": np.nan_to_num(trees["dbh_m"].to_numpy(float) / 2, nan=0.0),
                         "slope_x": slopes[:, 0], "slope_y": slopes[:, 1]})


def gather_half_height(tp) -> float:
    """Half the height band the tree list gathers: the slice's, or :mod:`.stem_outline`'s where
    the silhouettes run and it is wider."""
    outline = tp.outline_half_height_m if tp.calipers and tp.outline_ref_sd_m > 0 else 0.0
    return max(tp.slice_half_height_m, outline)


def slice_points(clouds: Mapping[str, np.ndarray], poses: pd.DataFrame, stems: pd.DataFrame, tp,
                 half_height_m: float | None = None,
                 splats: Mapping[str, tuple[float, float]] | None = None) -> tuple[pd.DataFrame, np.ndarray]:
    """:func:`gather_slices` with the tree parameters ``tp``' gate, within ``half_height_m``
    (default the slice's) of breast height."""
    half = tp.slice_half_height_m if half_height_m is None else half_height_m
    return gather_slices(clouds, poses, stems, half_height_m=half, gate_factor=tp.slice_gate_factor,
                         gate_margin_m=tp.slice_gate_margin_m, splats=splats)


def within_band(slices: pd.DataFrame, stems: pd.DataFrame, half_height_m: float) -> pd.DataFrame:
    """The points of :func:`gather_slices`' ``slices`` within ``half_height_m`` of their stem's
    breast height: the same points a gather with that band keeps (its reach and nearest stem do
    not depend on the band), so one gather serves two bands."""
    dz = slices["z"].to_numpy(float) - stems["zbh"].to_numpy(float)[slices["tree"].to_numpy(int)]
    return slices[np.abs(dz) <= half_height_m]


def merged_slice_dbh(trees: pd.DataFrame, cyl: pd.DataFrame, tree_of_cyl: np.ndarray,
                     clouds: Mapping[str, np.ndarray], poses: pd.DataFrame, tp,
                     breast_height_m: float = 1.3, stems: pd.DataFrame | None = None,
                     gathered: tuple[pd.DataFrame, np.ndarray] | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The tree list of :func:`~forestmap_assets.core.mapping.trees.merge_trees` (``trees``,
    ``tree_of_cyl`` over the global cylinders ``cyl``) with DBH from the breast-height slices of
    the registered scans' levelled points ``clouds`` placed with ``poses``; ``tp`` is the tree
    parameter section (``params.TreeParams``). Returns the trees and the per-tree fits of
    :func:`slice_dbhs`. ``stems``: the trees' :func:`slice_stems`, ``gathered`` their
    :func:`slice_points`, if the caller has them."""
    stems = slice_stems(trees, cyl, tree_of_cyl, breast_height_m) if stems is None else stems
    slices, sensors = slice_points(clouds, poses, stems, tp) if gathered is None else gathered
    return slice_dbhs(trees, slices, sensors, max_change=tp.slice_max_change,
                      max_incidence_deg=tp.slice_max_incidence_deg, bin_deg=tp.slice_bin_deg,
                      min_points=tp.slice_min_points, min_coverage_deg=tp.slice_min_coverage_deg,
                      ellipse_prior=tp.slice_ellipse_prior, trim_sigmas=tp.slice_trim_sigmas,
                      range_sigma_m=tp.range_sigma_m, outline_sd_m=tp.slice_outline_sd_m,
                      radius_prior_sd_m=tp.slice_cylinder_sd_m or None,
                      edge_footprints=tp.slice_edge_footprints, beam_exit_m=tp.beam_exit_m,
                      beam_divergence_rad=1e-3 * tp.beam_divergence_mrad, loo_sigmas=tp.slice_loo_sigmas or None)
