"""dz of a registration from two scans' lowest-hit ground grids (core/ground_z.py)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.features.elevation import elevation_grid
from forestmap_assets.core.geometry import transform_points
from forestmap_assets.core.registration.ground_z import ground_dz
from forestmap_assets.params import ElevationParams


def _ground_points(rng, n=60000, bushes=True):
    xy = rng.uniform(-20, 20, (n, 2))
    z = 0.03 * xy[:, 0] - 0.02 * xy[:, 1] + 0.1 * np.sin(xy[:, 0] / 3) + rng.normal(0, 0.01, n)
    if bushes:  # understorey blobs: hits above the ground in some cells
        k = rng.random(n) < 0.05
        z[k] += rng.uniform(0.2, 1.0, k.sum())
    return np.column_stack([xy, z])


def test_ground_dz_recovers_vertical_offset_despite_understorey():
    rng = np.random.default_rng(3)
    world = _ground_points(rng)
    pose_s = (4.0, -2.0, 0.37, 35.0)  # scan S in the reference frame
    ref_local = world
    s_local = (world - np.array(pose_s[:3])) @ np.array(
        [[np.cos(np.radians(35)), -np.sin(np.radians(35)), 0], [np.sin(np.radians(35)), np.cos(np.radians(35)), 0], [0, 0, 1]])
    back = transform_points(s_local, pose_s)
    np.testing.assert_allclose(back, world, atol=1e-9)
    p = ElevationParams()
    g_ref = elevation_grid(ref_local, p)
    g_s = elevation_grid(s_local, p)
    wrong_z = (pose_s[0], pose_s[1], pose_s[2] - 0.2, pose_s[3])  # the features' dz is 0.2 m off
    res = ground_dz(g_s, g_ref, wrong_z, p.cell_m)
    assert res.ok and res.n_cells > 1000
    assert abs(res.dz - pose_s[2]) < 0.01
    assert 0.0 < res.sd < 0.02


def test_ground_dz_fails_cleanly_without_overlap():
    rng = np.random.default_rng(4)
    p = ElevationParams()
    g = elevation_grid(_ground_points(rng, 5000, bushes=False), p)
    far = ground_dz(g, g, (200.0, 0.0, 0.0, 0.0), p.cell_m)
    assert not far.ok and far.n_cells == 0
    assert not ground_dz(pd.DataFrame(columns=["ix", "iy", "z"]), g, (0, 0, 0, 0), p.cell_m).ok


def test_screened_box_is_centred_on_the_ground_dz():
    """A screened pair's z range (issue 16, pair_registrations.ground_z_box): the ground's dz at
    the screening motion +- screen_ground_hz_m, from a screening motion 0.5 m and 2 deg off."""
    from forestmap_assets.core.registration.pair_registrations import ground_z_box
    from forestmap_assets.params import RegistrationParams

    rng = np.random.default_rng(5)
    world = _ground_points(rng)
    pose_s = (4.0, -2.0, 0.37, 35.0)
    c, s = np.cos(np.radians(35)), np.sin(np.radians(35))
    s_local = (world - np.array(pose_s[:3])) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    p = ElevationParams()
    grids = {"S": elevation_grid(s_local, p), "T": elevation_grid(world, p)}
    reg = RegistrationParams()
    centre, half = (4.5, -2.0, 0.0, 37.0), (1.0, 1.0, 1.25, 10.0)
    c2, h2 = ground_z_box(centre, half, reg, grids, "S", "T", p.cell_m)
    assert abs(c2[2] - pose_s[2]) < 0.05 and h2[2] == reg.screen_ground_hz_m
    assert (c2[0], c2[1], c2[3]) == (centre[0], centre[1], centre[3]) and h2[:2] + h2[3:] == (1.0, 1.0, 10.0)
    # no grids, or the option off: the box as it was
    assert ground_z_box(centre, half, reg, {}, "S", "T", p.cell_m) == (centre, half)
    off = reg.model_copy(update={"screen_ground_hz_m": None})
    assert ground_z_box(centre, half, off, grids, "S", "T", p.cell_m) == (centre, half)


def test_screened_box_moves_to_a_ground_dz_outside_the_z_range():
    """On a slope the ground's dz may lie outside the thesis' z range about 0 (Sylva's survey 3:
    1.41 m): the range moves there at its full width (the stems' features alone put such a
    pair's dz up to 0.25 m from the ground's), instead of staying about 0 and failing."""
    from forestmap_assets.core.registration.pair_registrations import ground_z_box
    from forestmap_assets.params import RegistrationParams

    rng = np.random.default_rng(6)
    world = _ground_points(rng)
    pose_s = (4.0, -2.0, 1.6, 35.0)  # 1.6 m above the reference, beyond z_m = 1.25
    c, s = np.cos(np.radians(35)), np.sin(np.radians(35))
    s_local = (world - np.array(pose_s[:3])) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    p = ElevationParams()
    grids = {"S": elevation_grid(s_local, p), "T": elevation_grid(world, p)}
    reg = RegistrationParams()
    centre, half = (4.5, -2.0, 0.0, 37.0), (1.0, 1.0, reg.z_m, 10.0)
    c2, h2 = ground_z_box(centre, half, reg, grids, "S", "T", p.cell_m)
    assert abs(c2[2] - pose_s[2]) < 0.05
    assert h2 == half and (c2[0], c2[1], c2[3]) == (centre[0], centre[1], centre[3])


def test_ground_cells_keep_the_ground_where_far_cells_see_trunks_and_branches():
    """Far from a scanner most cells' lowest hit is not the ground (Sylva's pairs 20-25 m apart:
    1-5 % of the compared cells agreed at the true pose, and the ground dz came out 12-40 cm
    off). Two scans of one sloping ground, each seeing it only near itself and clutter 0.3-6 m
    up in 90 % of its far cells: all cells give a chance mode, the ground-like cells the dz."""
    from forestmap_assets.core.registration.ground_z import ground_cells

    rng = np.random.default_rng(7)
    cell = 0.1
    ix, iy = (a.ravel() for a in np.meshgrid(np.arange(-150, 151), np.arange(-60, 61), indexing="ij"))
    x, y = (ix + 0.5) * cell, (iy + 0.5) * cell
    ground = 0.2 * x + 0.05 * np.sin(y)  # a 20 % slope
    dz = 0.4  # scan S stands 0.4 m higher than the reference (same cells: heading 0, no shift)

    def grid(near_x, z_frame, clutter_share):
        far = np.abs(x - near_x) > 6.0
        z = ground - z_frame + rng.normal(0, 0.005, x.size)
        clutter = far & (rng.random(x.size) < clutter_share)
        z[clutter] += rng.uniform(0.3, 6.0, clutter.sum()) * (1 + (x[clutter] > near_x))
        return pd.DataFrame({"ix": ix, "iy": iy, "z": z})

    g_ref = grid(-9.0, 0.0, 0.9)
    g_s = grid(9.0, dz, 0.9)
    pose = (0.0, 0.0, 0.0, 0.0)
    raw = ground_dz(g_s, g_ref, pose, cell, max_range_m=30.0)
    kept = ground_dz(ground_cells(g_s, cell, max_range_m=30.0), ground_cells(g_ref, cell, max_range_m=30.0),
                     pose, cell, max_range_m=30.0)
    assert kept.ok and abs(kept.dz - dz) < 0.01 and kept.sd < 0.01
    assert not raw.ok or abs(raw.dz - dz) > 0.1  # the clutter's chance mode
    # 0.7 m squares keep a 40 % slope; a block of 0 keeps every cell
    steep = pd.DataFrame({"ix": ix, "iy": iy, "z": 0.4 * x})
    assert len(ground_cells(steep, cell, max_range_m=30.0)) == len(steep)
    assert ground_cells(g_s, cell, block_m=0.0) is g_s
    # only cells the comparison can use (within max_range_m of the scanner) are filtered: a
    # return 2 km away does not make a dense array of 20000 x 20000 cells
    far = pd.concat([g_s, pd.DataFrame({"ix": [20000], "iy": [0], "z": [0.0]})], ignore_index=True)
    assert ground_cells(far, cell)["ix"].max() < 160
