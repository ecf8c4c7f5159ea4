"""Scans rendered inside a point cloud (sim/cloud_render.py): depth buffer, splats, own points."""

import numpy as np

from forestmap_assets.sim.cloud_render import _disc_offsets, render_scan, write_ply_xyz


def _cloud(spacing: float = 0.01) -> tuple[np.ndarray, float]:
    """A trunk (radius 0.2 m at x = 5 m, sampled on its whole circumference) 5 m in front of a
    wall (x = 10 m), both 2 m tall, points every ``spacing`` metres."""
    r = 0.2
    a = np.arange(0, 2 * np.pi, spacing / r)
    z = np.arange(-1.0, 1.0, spacing)
    A, Z = np.meshgrid(a, z)
    trunk = np.column_stack([5 + r * np.cos(A).ravel(), r * np.sin(A).ravel(), Z.ravel()])
    y = np.arange(-2.0, 2.0, spacing)
    Y, Z = np.meshgrid(y, z)
    wall = np.column_stack([np.full(Y.size, 10.0), Y.ravel(), Z.ravel()])
    return np.vstack([trunk, wall]), r


def test_disc_offsets_centre_first_and_round():
    off = _disc_offsets(2)
    assert tuple(off[0]) == (0, 0)
    assert len(off) == 13  # the pixels within 2 of the centre
    assert (np.hypot(*off.T) <= 2.01).all()


def test_render_sees_the_near_side_only_and_nothing_through_it():
    cloud, r = _cloud()
    pts = render_scan(cloud, (0.0, 0.0, 0.0), step_deg=0.1, splat_m=0.007)
    d_trunk = np.hypot(pts[:, 0] - 5.0, pts[:, 1])
    on_trunk = (np.abs(d_trunk - r) < 0.02) & (np.abs(pts[:, 2]) < 0.8)  # (not into the open tube)
    # the side facing the scanner is seen (x below the trunk's centre); a sparse cloud lets a
    # little of the back through where the splats of the front leave a diagonal gap
    assert on_trunk.sum() > 500
    assert (pts[on_trunk, 0] > 5.0 + 0.01).mean() < 0.02
    # nothing of the wall inside the trunk's silhouette (half-angle asin(0.2 / 5))
    wall = pts[:, 0] > 9.9
    half = np.arcsin(r / 5.0)
    az = np.abs(np.arctan2(pts[wall, 1], pts[wall, 0]))
    assert (az > half - np.radians(0.1)).all()
    # the depth-buffer points near the trunk's axis lie on its surface (own points or splats)
    centre = on_trunk & (np.abs(pts[:, 1]) < 0.1)
    assert np.abs(d_trunk[centre] - r).max() < 0.006


def test_render_range_noise_and_ply(tmp_path):
    cloud, _ = _cloud(0.02)
    a = render_scan(cloud, (0.0, 0.0, 0.5), step_deg=0.2, splat_m=0.02)
    b = render_scan(cloud, (0.0, 0.0, 0.5), step_deg=0.2, splat_m=0.02, range_sigma_m=0.01,
                    rng=np.random.default_rng(1))
    assert a.shape == b.shape
    dr = np.linalg.norm(b, axis=1) - np.linalg.norm(a, axis=1)
    assert 0.007 < dr.std() < 0.013
    write_ply_xyz(tmp_path / "s.ply", a)
    import open3d as o3d

    back = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "s.ply")).points)
    assert np.allclose(back, a, atol=1e-5)
    # each return's source point: the same depth (its own point, or its splat on the pixel's ray)
    c, src = render_scan(cloud, (0.0, 0.0, 0.5), step_deg=0.2, splat_m=0.02, source=True)
    assert np.array_equal(c, a)
    assert np.allclose(np.linalg.norm(a, axis=1), np.linalg.norm(cloud[src] - (0.0, 0.0, 0.5), axis=1))
    rgb = (np.arange(len(cloud))[:, None] * [1, 7, 13] % 256).astype(np.uint8)
    write_ply_xyz(tmp_path / "c.ply", a, rgb[src])
    pc = o3d.t.io.read_point_cloud(str(tmp_path / "c.ply"))
    assert np.allclose(pc.point.positions.numpy(), a, atol=1e-5)
    assert np.array_equal(pc.point.colors.numpy(), rgb[src])
