"""The parallel kernels of the spherical projection (issue 18, big scans) give numpy's values bit
for bit, and the same image on any number of threads."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from forestmap_assets.io._cloud_kernels import fix_rare, hypots, las_xyz, rgb8
from forestmap_assets.io.projection import project_to_range_image
from forestmap_assets.io.readers_common import to_rgb8


def _pairs(n: int = 20_000, seed: int = 0):
    """Scanner coordinates (0.1 mm integers), normals, near-equal pairs, one axis zero, and
    extremes (tiny, huge, zero, not finite)."""
    rng = np.random.default_rng(seed)
    ints = rng.integers(-500_000, 500_000, (2, n)) * 1e-4
    normal = rng.normal(0.0, 30.0, (2, n))
    near = np.stack([normal[0], normal[0] * (1.0 + rng.normal(0.0, 1e-9, n))])
    axis = np.stack([np.zeros(n // 10), rng.normal(0.0, 5.0, n // 10)])
    special = np.array([0.0, -0.0, 1.0, 1e-320, 2.0**-459, 2.0**-500, 2.0**511, 1e300, np.inf,
                        -np.inf, np.nan])
    extreme = np.stack([np.repeat(special, special.size), np.tile(special, special.size)])
    return np.concatenate([ints, normal, near, axis, extreme], axis=1)


def _same(a, b) -> bool:
    return a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)


def test_hypots_are_numpys():
    x, y = _pairs()
    z = np.random.default_rng(1).permutation(np.concatenate([x, y]))[:x.size]
    h, r = np.empty_like(x), np.empty_like(x)
    hypots(x, y, z, h, r)
    assert _same(h, np.hypot(x, y))
    assert _same(r, np.hypot(np.hypot(x, y), z))


@pytest.mark.parametrize("moved", [False, True])
def test_las_coordinates_and_ranges_are_laspys_and_numpys(moved):
    rng = np.random.default_rng(2)
    n = 50_000
    raw = rng.integers(-(2**31), 2**31, (n, 3)).astype(np.int32)
    raw[:100, :2] = 0  # straight up (unmoved): libm's hypot
    rec = np.zeros(n, dtype=[("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("intensity", "<u2")])
    rec["X"], rec["Y"], rec["Z"] = raw.T
    scale, offset = np.array([1e-4, 1e-3, 1e-4]), np.array([0.0, 0.0, -12.0])
    m = np.eye(4)
    if moved:
        c, s = np.cos(0.7), np.sin(0.7)
        m[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        m[:3, 3] = [-5e5, -6.5e6, 120.0]
        offset = np.array([5e5, 6.5e6, -12.0])
    xyz = [rec[k] * scale[i] + offset[i] for i, k in enumerate("XYZ")]  # laspy's
    if moved:
        xyz = [xyz[0] * m[i, 0] + xyz[1] * m[i, 1] + xyz[2] * m[i, 2] + m[i, 3] for i in range(3)]
    x, y, z, h = (np.empty(n) for _ in range(4))
    r = np.empty(n, np.float32)
    for fast in (True, False):
        if las_xyz(rec["X"], rec["Y"], rec["Z"], scale, offset, m, moved, x, y, z, h, r, fast):
            fix_rare(x, y, z, h, r)
        assert all(_same(a, b) for a, b in zip((x, y, z), xyz, strict=True))
        assert _same(h, np.hypot(xyz[0], xyz[1]))
        assert _same(r, np.hypot(np.hypot(xyz[0], xyz[1]), xyz[2]).astype(np.float32))


def test_las_colour_is_to_rgb8():
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 65536, (10_000, 3)).astype(np.uint16)
    for full in (65535.0, 255.0):
        out = np.empty(rgb.shape, np.uint8)
        rgb8(rgb, full, out)
        assert _same(out, to_rgb8(rgb, full_scale=full))


def _cloud(n_rows=120, n_cols=700, step=0.1, seed=4):
    rng = np.random.default_rng(seed)
    shape = (n_rows, n_cols)
    az = np.radians(-40.0 + step * (np.arange(n_cols) + rng.normal(0, 0.3, shape)))
    el = np.radians(30.0 - step * (np.arange(n_rows)[:, None] + rng.normal(0, 0.3, shape)))
    r = 5.0 + 20.0 * rng.random((n_rows, n_cols))
    keep = rng.random((n_rows, n_cols)) < 0.8
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], -1)
    return xyz[keep], rng.integers(0, 256, (int(keep.sum()), 3)).astype(np.uint8)


@pytest.mark.parametrize("shuffled", [False, True])
def test_same_image_on_any_number_of_threads(shuffled):
    xyz, rgb = _cloud()
    if shuffled:
        order = np.random.default_rng(5).permutation(len(xyz))
        xyz, rgb = xyz[order], rgb[order]
    inten = np.linalg.norm(xyz, axis=1).astype(np.float32)
    before = numba.get_num_threads()
    images = []
    try:
        for threads in sorted({1, before}):
            numba.set_num_threads(threads)
            images.append(project_to_range_image(xyz, rgb, inten))
    finally:
        numba.set_num_threads(before)
    first = images[0]
    assert first.valid.mean() > 0.5
    for img in images[1:]:
        for name in ("range_m", "points", "intensity", "rgb", "azimuth_deg", "elevation_deg"):
            assert _same(getattr(img, name), getattr(first, name)), name


def _bridged_by_numpy(range_img, intensity, rgb, points, max_gap=2, tol=0.11):
    """The vectorised passes ``bridge_row_gaps`` gave before its kernel."""
    rows, cols = range_img.shape
    empty = ~np.isfinite(range_img)
    for g in range(1, max_gap + 1):
        left, right = range_img[:, : cols - g - 1], range_img[:, g + 1:]
        ok = np.abs(left - right) <= tol
        for k in range(g):
            ok &= empty[:, 1 + k: cols - g + k]
        vv, uu = np.nonzero(ok)
        for k in range(g):
            w = np.float32((k + 1) / (g + 1))
            for img in (range_img, intensity, points):
                if img is not None:
                    img[vv, uu + 1 + k] = (1 - w) * img[vv, uu] + w * img[vv, uu + g + 1]
            if rgb is not None:
                rgb[vv, uu + 1 + k] = rgb[vv, uu + (0 if w <= 0.5 else g + 1)]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_row_gaps_bridged_as_by_numpy(dtype):
    from forestmap_assets.io.readers_common import bridge_row_gaps

    rng = np.random.default_rng(6)
    r = (10.0 + np.cumsum(rng.normal(0.0, 0.04, (60, 400)), axis=1)).astype(dtype)
    r[rng.random(r.shape) < 0.35] = np.nan
    r[:, 1::37] = np.nan
    r[:, 0::37], r[:, 2::37] = 10.0, 10.11  # ends at the range limit (0.11 in float64)
    parts = [r, (r * 3).astype(np.float32), rng.integers(0, 256, r.shape + (3,)).astype(np.uint8),
             np.stack([r, -r, 2 * r], -1).astype(np.float32)]
    for keep in ([0, 1, 2, 3], [0], [0, 2]):
        got = [p.copy() if i in keep else None for i, p in enumerate(parts)]
        want = [None if p is None else p.copy() for p in got]
        bridge_row_gaps(*got)
        _bridged_by_numpy(*want)
        assert all(a is None or _same(a, b) for a, b in zip(got, want, strict=True))
