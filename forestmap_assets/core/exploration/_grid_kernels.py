"""Numba kernels of the exploration grid (men_spec 3.5 update, :mod:`.grid`) and the 2-D
visibility model (men_spec 7.5, :mod:`.visibility`), one pass over the points or rays without the
full temporaries of the numpy they replace (issue 16/17: on a 51-scan campaign the grid's update
took 6.5 s of numpy and the candidates' rays 4.4 s).

The grid update sums in the points' order into zeroed arrays, as ``np.bincount`` does, so the
histograms are the same bit for bit; the ray walk makes the same float64 operations as the numpy
and stops each ray at its first occluder or stem."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, inline="always")
def _add(x, y, z, w, m, x0, y0, cell_m, nx, ny, z_min, dz, nz, ground, has_ground, counts, measured,
         above, points):  # pragma: no cover - compiled
    """One point's weights into the grid's flat sums (:func:`accumulate`)."""
    fx = np.floor((x - x0) / cell_m)
    fy = np.floor((y - y0) / cell_m)
    if not (fx >= 0 and fx < nx and fy >= 0 and fy < ny):  # NaN too
        return
    ix, iy = int(fx), int(fy)
    c = ix * ny + iy
    points[c] += m
    h = z - ground[ix, iy] if has_ground else z
    if h >= z_min + nz * dz:
        above[c] += w
    fz = np.floor((h - z_min) / dz)
    if fz >= 0 and fz < nz:
        k = c * nz + int(fz)
        counts[k] += w
        measured[k] += m


@nb.njit(cache=True)
def accumulate(x, y, z, w, m, x0, y0, cell_m, nx, ny, z_min, dz, nz, ground, has_ground, counts,
               measured, above, points):  # pragma: no cover - compiled
    """Add every point to the grid's sums (flat arrays): ``counts`` and ``measured`` per (cell,
    level) with weights ``w`` and ``m``, ``above`` (``w``) above the top level, ``points``
    (``m``) per cell at any height; points outside the cells are left out
    (:meth:`.grid.ExplorationGrid.add_points`)."""
    for i in range(x.size):
        _add(x[i], y[i], z[i], w[i], m[i], x0, y0, cell_m, nx, ny, z_min, dz, nz, ground, has_ground,
             counts, measured, above, points)


@nb.njit(cache=True)
def accumulate_surface(ix, iy, iz, n_points, n_filled, voxel_m, pose, max_range_m, x0, y0, cell_m,
                       nx, ny, z_min, dz, nz, ground, has_ground, counts, measured, above,
                       points):  # pragma: no cover - compiled
    """One scan's observed-surface voxels (centres in the global frame, within ``max_range_m``
    horizontally of the scanner, ``inf``: all; ``pose`` x, y, z, heading in degrees) into the
    grid's sums with weights ``n_points + n_filled`` and ``n_points`` (measured): the numpy
    :func:`.surface.surface_points` then :meth:`.grid.ExplorationGrid.add_points` in one pass."""
    h = np.radians(pose[3])
    c, s = np.cos(h), np.sin(h)
    for j in range(ix.size):
        lx = (np.float64(ix[j]) + 0.5) * voxel_m  # the voxel's centre, levelled scan frame
        ly = (np.float64(iy[j]) + 0.5) * voxel_m
        if np.hypot(lx, ly) <= max_range_m:
            m = np.float64(n_points[j])
            _add(lx * c - ly * s + pose[0], lx * s + ly * c + pose[1],
                 (np.float64(iz[j]) + 0.5) * voxel_m + pose[2], m + np.float64(n_filled[j]), m, x0,
                 y0, cell_m, nx, ny, z_min, dz, nz, ground, has_ground, counts, measured, above,
                 points)


@nb.njit(cache=True)
def walk_rays(pos, u, t, t_stem, occ, x0, y0, cell_m, nx, ny, out, row0):  # pragma: no cover - compiled
    """Mark the cells each ray sees in ``out[row0 + n]``: samples at ``t`` along direction ``u[m]``
    from ``pos[n]`` inside the grid, before the first stem (``t < t_stem[n, m]``), up to and
    including the first ``occ`` cell (:func:`.visibility.visible_cells`)."""
    for a in range(pos.shape[0]):
        for b in range(u.shape[0]):
            ts = t_stem[a, b]
            for k in range(t.size):
                if not (t[k] < ts):
                    break
                fx = np.floor((pos[a, 0] + t[k] * u[b, 0] - x0) / cell_m)
                fy = np.floor((pos[a, 1] + t[k] * u[b, 1] - y0) / cell_m)
                if not (fx >= 0 and fx < nx and fy >= 0 and fy < ny):
                    continue
                f = int(fx) * ny + int(fy)
                out[row0 + a, f] = True
                if occ[f]:
                    break
