"""Numba kernel of one Gauss-Newton step of the least-squares 4-DoF point-to-plane ICP
(:func:`~.point_to_plane.point_to_plane_4dof`, issue 16): each data point moved by the pose,
paired with its nearest model point in the model's
:class:`~forestmap_assets.core.radius_grid.RadiusGrid`, and the normal equations summed, in one
pass and without the arrays of the numpy step (moved points, pairs, Jacobians). The pairs are
those of :func:`~.point_to_plane.plane_pairs` (the queries pruned by
:class:`~.point_to_plane.Reach` the same way), the equations those of the numpy step; the sums
are taken in fixed blocks, so the result does not depend on the number of threads."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from forestmap_assets.core._radius_grid_kernels import nearest_one

BLOCKS = 64  # partial sums, added in order


@nb.njit(cache=True, inline="always")
def _rotated(data, i, rot):
    x, y, z = data[i, 0], data[i, 1], data[i, 2]
    return (rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z,
            rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z,
            rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z)


@nb.njit(cache=True, inline="always")
def _moved(data, i, rot, t):
    x, y, z = _rotated(data, i, rot)
    return x + t[0], y + t[1], z + t[2]


@nb.njit(cache=True)
def _farthest(data, rot, t, base):
    """The largest distance of a data point moved by ``rot, t`` from its ``base`` position."""
    far = 0.0
    for i in range(data.shape[0]):
        mx, my, mz = _moved(data, i, rot, t)
        dx, dy, dz = mx - base[i, 0], my - base[i, 1], mz - base[i, 2]
        far = max(far, math.sqrt(dx * dx + dy * dy + dz * dz))
    return far


@nb.njit(cache=True, parallel=True)
def plane_step(data, rot, t, data_normals, min_dot, base, d0, bound, radius,
               points, order, start, lo, cell, nx, ny, model, normals, partner):
    """``A`` (4, 4), ``b`` (4) and the number of pairs of the step's normal equations
    ``A delta = b`` (``A = J^T J``, ``b = J^T r``; rows ``J = n^T dp/d(dx, dy, dz, dh)``,
    ``r = n . (m - p)``) of the data points moved by ``rot, t`` and their nearest model point
    within ``radius``, whose normal is finite; ``partner``: each data point's model row (-1
    none). ``data_normals`` (n, 3) or empty: the symmetric objective (pairs whose normals' dot
    is below ``min_dot`` left out, the normal the normalised sum). ``base``, ``d0`` (n) or empty:
    a point whose nearest model point was ``d0`` from ``base`` is not queried unless it moved
    enough to come within ``radius`` (all are, once a point moved ``bound - radius``)."""
    n = data.shape[0]
    symmetric = data_normals.shape[0] == n
    prune = d0.shape[0] == n and n > 0
    if prune and radius + _farthest(data, rot, t, base) >= bound:
        prune = False
    size = (n + BLOCKS - 1) // BLOCKS
    part = np.zeros((BLOCKS, 15))  # A's upper triangle (10), b (4), count
    for blk in nb.prange(BLOCKS):
        acc = np.zeros(15)
        for i in range(blk * size, min(n, (blk + 1) * size)):
            partner[i] = -1
            mx, my, mz = _moved(data, i, rot, t)
            if prune:
                dx, dy, dz = mx - base[i, 0], my - base[i, 1], mz - base[i, 2]
                if not d0[i] <= radius + math.sqrt(dx * dx + dy * dy + dz * dz) + 1e-9:
                    continue
            _, hit = nearest_one(mx, my, mz, radius, points, order, start, lo, cell, nx, ny)
            if hit < 0:
                continue
            row = order[hit]
            n0, n1, n2 = normals[row, 0], normals[row, 1], normals[row, 2]
            if not (math.isfinite(n0) and math.isfinite(n1) and math.isfinite(n2)):
                continue
            if symmetric:
                e0, e1, e2 = _rotated(data_normals, i, rot)
                if not n0 * e0 + n1 * e1 + n2 * e2 >= min_dot:
                    continue
                s0, s1, s2 = n0 + e0, n1 + e1, n2 + e2
                norm = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
                n0, n1, n2 = s0 / norm, s1 / norm, s2 / norm
            partner[i] = row
            r = n0 * (model[row, 0] - mx) + n1 * (model[row, 1] - my) + n2 * (model[row, 2] - mz)
            n3 = -n0 * (my - t[1]) + n1 * (mx - t[0])
            acc[0] += n0 * n0
            acc[1] += n0 * n1
            acc[2] += n0 * n2
            acc[3] += n0 * n3
            acc[4] += n1 * n1
            acc[5] += n1 * n2
            acc[6] += n1 * n3
            acc[7] += n2 * n2
            acc[8] += n2 * n3
            acc[9] += n3 * n3
            acc[10] += n0 * r
            acc[11] += n1 * r
            acc[12] += n2 * r
            acc[13] += n3 * r
            acc[14] += 1.0
        part[blk] = acc
    total = np.zeros(15)
    for blk in range(BLOCKS):
        total += part[blk]
    a_mat = np.empty((4, 4))
    k = 0
    for a in range(4):
        for b in range(a, 4):
            a_mat[a, b] = a_mat[b, a] = total[k]
            k += 1
    return a_mat, total[10:14].copy(), int(total[14])
