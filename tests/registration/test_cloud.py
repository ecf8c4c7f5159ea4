"""Point-cloud pre-processing of Men ch. 3: voxel sub-sampling (V5), PCA normals (V6), outlier
filter and radius normals."""

from __future__ import annotations

import numpy as np

from forestmap_assets.core.cloud import (
    pca_normals,
    radius_normals,
    radius_outlier_mask,
    voxel_keys,
    voxel_subsample,
)


def test_v5_voxel_subsample_one_point_per_voxel_order_invariant():
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 3, (5000, 3))
    keep = voxel_subsample(p, 0.25)
    keys, origin = voxel_keys(p, 0.25)
    occupied = np.unique(keys, axis=0)
    kept_keys = voxel_keys(p[keep], 0.25, origin)[0]
    assert len(keep) == len(occupied) == len(np.unique(kept_keys, axis=0))
    perm = rng.permutation(len(p))
    keep2 = perm[voxel_subsample(p[perm], 0.25)]
    assert np.array_equal(np.sort(keep2), keep)  # same voxels, same representatives
    # the representative is the point nearest its voxel's centroid
    k0 = kept_keys[0]
    members = p[(keys == k0).all(axis=1)]
    centroid = members.mean(0)
    assert np.allclose(p[keep[0]], members[np.argmin(((members - centroid) ** 2).sum(1))])


def test_v5_density_evened_out_on_a_scanned_floor():
    """A floor seen from 1.6 m with a fixed angular step: the density falls roughly as 1/r^2;
    after sub-sampling it varies by at most 2x across 2-15 m (more than 10x before)."""
    az = np.radians(np.arange(0, 360, 0.2))
    el = np.radians(np.arange(-45, -5, 0.1))
    a, e = np.meshgrid(az, el)
    r = 1.6 / np.sin(-e)
    p = np.column_stack([(r * np.cos(e) * np.cos(a)).ravel(), (r * np.cos(e) * np.sin(a)).ravel(),
                         np.full(a.size, -1.6)])
    dist = np.hypot(p[:, 0], p[:, 1])

    def density(points, d):
        rings = [(2, 3), (14, 15)]
        return [np.sum((d >= lo) & (d < hi)) / (np.pi * (hi**2 - lo**2)) for lo, hi in rings]

    before = density(p, dist)
    assert before[0] / before[1] > 10
    kept = p[voxel_subsample(p, 0.1)]
    after = density(kept, np.hypot(kept[:, 0], kept[:, 1]))
    assert after[0] / after[1] < 2


def test_v6_pca_normals_on_a_plane_and_oriented_to_the_scanner():
    rng = np.random.default_rng(1)
    p = np.column_stack([rng.uniform(-2, 2, 3000), rng.uniform(-2, 2, 3000), np.zeros(3000)])
    tilt = np.radians(20)
    rot = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    p = p @ rot.T + [0, 0, -1.5]
    true = rot @ [0, 0, 1.0]
    n, variation = pca_normals(p, k=10, origin=(0, 0, 0))
    ang = np.degrees(np.arccos(np.clip(n @ true, -1, 1)))
    assert ang.max() < 0.1
    assert np.all(((0 - p) * n).sum(axis=1) >= 0)  # n . (o - p) >= 0
    assert np.nanmax(variation) < 1e-10
    nr = radius_normals(p, 0.3, origin=(0, 0, 0))
    assert np.degrees(np.arccos(np.clip(nr @ true, -1, 1))).max() < 0.1
    # duplicating the points does not change radius normals
    nd = radius_normals(np.vstack([p, p]), 0.3, origin=(0, 0, 0), at=p[:50])
    np.testing.assert_allclose(nd, nr[:50], atol=1e-9)


def test_radius_outlier_filter_removes_isolated_points():
    rng = np.random.default_rng(2)
    dense = rng.uniform(0, 1, (2000, 3))
    lonely = rng.uniform(5, 50, (20, 3))
    keep = radius_outlier_mask(np.vstack([dense, lonely]), 0.15, 3)
    assert keep[:2000].mean() > 0.99 and not keep[2000:].any()


def test_one_pass_bounds_and_occupied_voxels_are_numpys():
    """_cloud_kernels.bounds and icp_uncertainty._occupied_voxels (issue 16) give what numpy's
    reductions and np.unique(axis=0) give, with negative coordinates and a non-finite value."""
    from forestmap_assets.core._cloud_kernels import bounds
    from forestmap_assets.core.registration.icp_uncertainty import _occupied_voxels

    rng = np.random.default_rng(2)
    p = rng.normal(0, 20, (5000, 3)) * [1, 3, 0.2]
    lo, hi, finite = bounds(p)
    np.testing.assert_array_equal(lo, p.min(axis=0))
    np.testing.assert_array_equal(hi, p.max(axis=0))
    assert finite and not bounds(np.vstack([p, [[0.0, np.inf, 0.0]]]))[2]
    for voxel in (0.05, 0.5, 7.0):
        want = len(np.unique(np.floor(p / voxel).astype(np.int64), axis=0))
        assert _occupied_voxels(p, voxel) == want
    assert _occupied_voxels(np.zeros((0, 3)), 0.5) == 0
    wide = np.array([[4e18, 0, 0], [-4e18, 0, 0], [4e18, 0, 0]])  # too wide for one key: by rows
    assert _occupied_voxels(wide, 1.0) == 2


def test_voxel_subsample_two_point_voxels_favour_no_direction():
    """The two points of a two-point voxel tie on their distance to the centroid; the tie must
    not go to the smaller x (that moved every thinned scan along its own x axis, about 0.3-1.9 mm
    of link error on the benchmarks)."""
    rng = np.random.default_rng(5)
    centres = rng.uniform(0, 100, (4000, 3))
    a = centres + rng.uniform(-0.01, 0.01, (4000, 3))
    b = centres + rng.uniform(-0.01, 0.01, (4000, 3))
    p = np.vstack([a, b])
    keep = voxel_subsample(p, 0.05, origin=np.zeros(3))
    keys = voxel_keys(p, 0.05, np.zeros(3))[0]
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    centroid = np.stack([np.bincount(inverse, weights=p[:, k]) for k in range(3)], axis=1) / counts[:, None]
    two = counts[inverse[keep]] == 2
    assert two.sum() > 1000
    shift = (p[keep] - centroid[inverse[keep]])[two].mean(axis=0)
    assert np.all(np.abs(shift) < 3e-4), shift  # the lexicographic tie gave x -3.1 mm here


def test_radix_argsort_is_numpys_stable_argsort():
    """The voxel subsample's and the Z-order's radix sort gives ``np.argsort(kind="stable")``:
    ties in input order, digits every key shares skipped, 63-bit keys, no keys."""
    from forestmap_assets.core._cloud_kernels import stable_argsort, stable_sort

    rng = np.random.default_rng(5)
    for keys in (
        rng.integers(0, 50, 20_000),  # many ties, one digit
        rng.integers(0, 2**40, 20_000) // 2**22 * 2**22,  # low digits all zero: skipped
        rng.integers(0, 2**63 - 1, 5_000, dtype=np.int64),  # Morton codes' width
        np.full(7, 3, np.int64),
        np.zeros(0, np.int64),
    ):
        keys = keys.astype(np.int64)
        top = int(keys.max()) if len(keys) else 0
        want = np.argsort(keys, kind="stable")
        assert np.array_equal(stable_argsort(keys, top), want)
        # the sort in the keys' own buffer (voxel_subsample): the sorted keys beside the order
        got_keys, got = stable_sort(keys.copy(), top)
        assert np.array_equal(got, want) and np.array_equal(got_keys, keys[want])
