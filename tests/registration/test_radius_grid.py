"""core.radius_grid.RadiusGrid: the nearest point within a radius, as a k-d tree's bounded query
gives it (issue 16: the fine registration's point pairs)."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from forestmap_assets.core.radius_grid import RadiusGrid
from forestmap_assets.core.registration.point_to_plane import Reach, plane_pairs


def _forest(rng, n_stems=40, per_stem=400):
    """Points on vertical stems (radius 0.1-0.3 m, up to 8 m) and a rough ground, like a
    levelled scan's thinned points."""
    centre = rng.uniform(-15, 15, (n_stems, 2))
    radius = rng.uniform(0.1, 0.3, n_stems)
    k = np.repeat(np.arange(n_stems), per_stem)
    a = rng.uniform(0, 2 * np.pi, len(k))
    stems = np.column_stack([centre[k, 0] + radius[k] * np.cos(a), centre[k, 1] + radius[k] * np.sin(a),
                             rng.uniform(-1, 8, len(k))])
    g = rng.uniform(-18, 18, (6000, 2))
    ground = np.column_stack([g, -1.5 + 0.05 * np.sin(g[:, 0]) + rng.normal(0, 0.02, len(g))])
    return np.vstack([stems, ground])


@pytest.mark.parametrize("cell", [0.05, 0.15, 0.4])
def test_the_nearest_point_within_a_radius_is_the_k_d_trees(cell):
    rng = np.random.default_rng(3)
    model = _forest(rng)
    near = model[::3] + rng.normal(0, 0.05, (len(model[::3]), 3))
    queries = np.vstack([near, rng.uniform(-30, 30, (500, 3))])
    tree, grid = cKDTree(model), RadiusGrid(model, cell)
    for radius in (0.02, 0.05, 0.1, 0.3):
        d0, i0 = tree.query(queries, distance_upper_bound=radius)
        d1, i1 = grid.query(queries, radius)
        np.testing.assert_array_equal(i1, i0)
        np.testing.assert_array_equal(d1, d0)
        assert 0.01 < np.isfinite(d1).mean() < 0.99
    rows = np.flatnonzero(rng.random(len(queries)) < 0.3)
    d2, i2 = grid.query(queries, 0.1, rows)
    d0, i0 = tree.query(queries, distance_upper_bound=0.1)
    np.testing.assert_array_equal(i2[rows], i0[rows])
    np.testing.assert_array_equal(d2[rows], d0[rows])
    others = np.setdiff1d(np.arange(len(queries)), rows)
    assert np.isinf(d2[others]).all() and (i2[others] == len(model)).all()


def test_ties_go_to_the_lower_row_and_the_radius_is_exclusive():
    ring = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    for order in ([0, 1, 2, 3], [3, 2, 1, 0], [2, 0, 3, 1]):
        grid = RadiusGrid(ring[order], 0.3)  # the four at 1 m of the origin, in other columns
        d, i = grid.query(np.zeros((1, 3)), 1.01)
        assert i[0] == 0 and d[0] == 1.0
    grid = RadiusGrid(np.array([[0.0, 0.0, 0.5]]), 0.3)
    d, i = grid.query(np.array([[0.0, 0.0, 0.25], [0.0, 0.0, 0.26]]), 0.25)  # exactly at it: none
    assert np.isinf(d[0]) and i[0] == 1 and d[1] == pytest.approx(0.24) and i[1] == 0


def test_edge_cases():
    empty = RadiusGrid(np.zeros((0, 3)), 0.1)
    d, i = empty.query(np.ones((4, 3)), 1.0)
    assert np.isinf(d).all() and (i == 0).all()
    grid = RadiusGrid(np.array([[0.0, 0.0, 0.0]]), 0.1)
    assert grid.query(np.zeros((0, 3)), 1.0)[0].shape == (0,)
    d, i = grid.query(np.array([[np.nan, 0.0, 0.0], [0.05, 0.0, 0.0]]), 0.1)
    assert np.isinf(d[0]) and i[0] == 1 and d[1] == pytest.approx(0.05) and i[1] == 0
    wide = RadiusGrid(np.array([[0.0, 0.0, 0.0], [5e4, 5e4, 1.0]]), 0.01)  # columns widened
    assert wide.cell > 0.01 and wide.nx * wide.ny <= 1 << 24
    assert wide.query(np.array([[5e4, 5e4, 1.02]]), 0.05)[1][0] == 1
    with pytest.raises(ValueError, match="finite"):
        RadiusGrid(np.array([[0.0, np.inf, 0.0]]), 0.1)
    with pytest.raises(ValueError, match="cell_m"):
        RadiusGrid(np.zeros((1, 3)), 0.0)


def test_the_pairs_are_the_same_from_the_grid_and_the_tree():
    """point_to_plane.plane_pairs and Reach give the same pairs whichever index they query."""
    from forestmap_assets.core.cloud import pca_normals

    rng = np.random.default_rng(11)
    model = _forest(rng, 20, 300)
    normals = pca_normals(model, 12)[0]
    data = model[::2] + rng.normal(0, 0.02, (len(model[::2]), 3))
    tree, grid = cKDTree(model), RadiusGrid(model, 0.15)
    reach_t, reach_g = Reach(tree, data, 0.15), Reach(grid, data, 0.15)
    np.testing.assert_array_equal(reach_t.d0, reach_g.d0)
    for radius in (0.05, 0.1):
        for reach in (None, reach_g):
            a = plane_pairs(tree, normals, data + 0.01, radius, normals[::2], reach)
            b = plane_pairs(grid, normals, data + 0.01, radius, normals[::2], reach)
            for x, y in zip(a, b, strict=True):
                np.testing.assert_array_equal(x, y)
            assert a[0].sum() > 100


@pytest.mark.parametrize("symmetric", [False, True])
@pytest.mark.parametrize("pruned", [False, True])
def test_the_fused_gauss_newton_step_follows_the_numpy_one(symmetric, pruned):
    """point_to_plane_4dof on a grid (one kernel a step, _plane_step_kernels.plane_step) walks
    the poses of its numpy step on a k-d tree: the same partners and iterations, the pose to
    rounding; some model normals missing, some data normals facing away."""
    from forestmap_assets.core.cloud import pca_normals
    from forestmap_assets.core.registration.hicp import pose4_to_matrix
    from forestmap_assets.core.registration.point_to_plane import point_to_plane_4dof

    rng = np.random.default_rng(5)
    model = _forest(rng, 25, 300)
    normals = pca_normals(model, 12)[0]
    normals[rng.random(len(model)) < 0.05] = np.nan
    truth = np.array([0.03, -0.02, 0.01, 0.4])
    r, t = pose4_to_matrix(truth)
    data = (model[::2] - t) @ r + rng.normal(0, 0.005, (len(model[::2]), 3))  # model = R data + t
    dn = normals[::2] @ r
    dn[rng.random(len(dn)) < 0.05] *= -1.0
    start = np.zeros(4)
    tree, grid = cKDTree(model), RadiusGrid(model, 0.15)
    runs = []
    for index in (tree, grid):
        reach = Reach(index, data, 0.2) if pruned else None
        box = (start, np.array([0.05, 0.05, 0.05, 2.0]))
        runs.append(point_to_plane_4dof(model, normals, data, start, max_distance_m=0.1, iterations=8, tree=index,
                                        box=box, tol=1e-9, data_normals=dn if symmetric else None, reach=reach))
    (p0, partner0, it0), (p1, partner1, it1) = runs
    assert it1 == it0 and it0 > 2
    np.testing.assert_array_equal(partner1, partner0)
    np.testing.assert_allclose(p1, p0, rtol=0, atol=1e-10)
    np.testing.assert_allclose(p1, truth, atol=2e-3)
    assert (partner1 >= 0).sum() > 1000
