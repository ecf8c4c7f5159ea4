"""Coarse registration without a prior (men spec 4): EGI, SO(3) and heading correlation,
occupancy-grid translation and the H-EGI pipeline against V7-V10 of spec 12."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.colour_scenes import mesh_samples, random_rotation, room_mesh
from scipy import special

from forestmap_assets.core.registration.fourier_coarse import (
    coarse_register,
    prepare_cloud,
    registration_error,
)
from forestmap_assets.core.registration.fourier_rotation import (
    brute_force_rotation,
    cell_solid_angles,
    egi,
    euler_zyz,
    heading_correlation,
    heading_peaks,
    normal_angles,
    peak_rotation,
    quadrature_weights,
    rotation_angle_deg,
    rotation_by_correlation,
    sh_coefficients,
    sh_evaluate,
    sh_synthesis,
    so3_correlation,
    so3_grid,
    sphere_grid,
    wigner_d,
)
from forestmap_assets.core.registration.fourier_translation import translation_by_correlation
from forestmap_assets.core.registration.hicp import pose4_to_matrix


@pytest.fixture(scope="module")
def room_normals():
    mesh = room_mesh()
    _, n, _ = mesh_samples(mesh, 8000, (3.0, 3.0, 1.5), seed=0)
    return n


def test_wigner_d_and_spherical_harmonics_match_closed_forms():
    b = 0.7
    d1 = wigner_d(1, b)[0]
    np.testing.assert_allclose(d1[1, 1], np.cos(b), atol=1e-14)
    np.testing.assert_allclose([d1[2, 1], d1[1, 2]], [-np.sin(b) / np.sqrt(2), np.sin(b) / np.sqrt(2)], atol=1e-14)
    d5 = wigner_d(5, [0.3, 1.9])
    np.testing.assert_allclose(d5 @ d5.transpose(0, 2, 1), np.broadcast_to(np.eye(11), (2, 11, 11)), atol=1e-12)
    assert quadrature_weights(8).sum() == pytest.approx(2.0, abs=1e-12)
    L = 8
    theta, phi = sphere_grid(L)
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    for ell, m in ((3, 2), (5, -3), (7, 0)):
        y = special.sph_harm_y(ell, m, tt, pp)
        coeffs = sh_coefficients(y.real, L) + 1j * sh_coefficients(y.imag, L)
        expected = np.zeros_like(coeffs)
        expected[ell, m + L - 1] = 1.0
        np.testing.assert_allclose(coeffs, expected, atol=1e-12)
        np.testing.assert_allclose(sh_synthesis(sh_coefficients(y.real, L), L), y.real, atol=1e-12)


def test_v7_egi_counts_density_and_rotation(room_normals):
    n = np.vstack([room_normals, [[np.nan, 0, 0], [0, 0, 0]]])
    counts = egi(n, 16, density=False)
    assert counts.shape == (32, 32) and counts.sum() == len(room_normals)
    dens = egi(room_normals, 16)
    assert (dens * cell_solid_angles(16)[:, None]).sum() == pytest.approx(1.0)
    # rotating the normals rotates the EGI up to binning error: the (band-limited) EGI of the
    # rotated normals equals the original EGI evaluated at R^T w, and the degree power spectrum
    # is unchanged; normals with a PCA-like spread (about 6 deg)
    rng = np.random.default_rng(5)
    L = 16
    theta, phi = sphere_grid(L)
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1).reshape(-1, 3)
    w = np.repeat(quadrature_weights(L) * (2 * np.pi / (2 * L)), 2 * L)
    for _ in range(3):
        r = random_rotation(rng)
        noisy = room_normals + rng.normal(0, 0.1, room_normals.shape)
        noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
        fa = sh_coefficients(egi(noisy, L), L)
        fb = sh_coefficients(egi(noisy @ r.T, L), L)
        rotated_a = sh_evaluate(fa, *normal_angles(dirs @ r))
        b = sh_synthesis(fb, L).reshape(-1)
        assert np.sqrt((w * (rotated_a - b) ** 2).sum() / (w * b**2).sum()) < 0.12
        pa, pb = (np.sum(np.abs(f) ** 2, axis=1) for f in (fa, fb))
        assert np.abs(pb - pa).max() < 0.03 * pa.sum()


def test_soft_correlation_equals_brute_force_on_the_rotation_grid(room_normals):
    """The SO(3) Fourier correlation equals the brute-force band-limited objective at every
    rotation of the ZYZ grid (so both pick the same rotation); the true rotation is found."""
    rng = np.random.default_rng(2)
    r_true = random_rotation(rng)
    data = room_normals @ r_true  # R_true rotates the data normals onto the model normals
    for L, subset in ((4, None), (8, 150)):
        corr = so3_correlation(sh_coefficients(egi(room_normals, L), L), sh_coefficients(egi(data, L), L), L)
        a, b, g = np.meshgrid(*so3_grid(L), indexing="ij")
        rots = euler_zyz(a.ravel(), b.ravel(), g.ravel())
        best = int(np.argmax(corr.ravel()))
        sel = np.arange(len(rots)) if subset is None else np.r_[rng.choice(len(rots), subset, replace=False), best]
        brute = brute_force_rotation(room_normals, data, rots[sel], L)
        np.testing.assert_allclose(brute, corr.ravel()[sel], rtol=0, atol=1e-8 * np.abs(brute).max())
        if subset is None:
            assert int(np.argmax(brute)) == best
    assert rotation_angle_deg(rots[best], r_true) <= 1.5 * 180.0 / (2 * 8)
    with pytest.raises(ValueError, match="method"):
        brute_force_rotation(room_normals, data, rots[:1], 8, method="fast")


def test_v8_rotation_recovery_asymmetric_and_symmetric_rooms(room_normals):
    L = 24
    tol = 1.5 * 180.0 / (2 * L)
    rng = np.random.default_rng(0)
    errors = []
    for _ in range(20):
        r = random_rotation(rng)
        peaks = rotation_by_correlation(room_normals, room_normals @ r, L, top_k=1)
        errors.append(rotation_angle_deg(peak_rotation(peaks.iloc[0]), r))
    assert np.mean(np.array(errors) <= tol) >= 0.95, np.round(errors, 1)
    # a box room has the 180-degree symmetries of a rectangle: several equal peaks, the truth
    # among the top four
    _, n, _ = mesh_samples(room_mesh(symmetric=True), 8000, (3.0, 2.0, 1.2), seed=1)
    L = 16
    for _ in range(4):
        r = random_rotation(rng)
        peaks = rotation_by_correlation(n, n @ r, L, top_k=4)
        errs = [rotation_angle_deg(peak_rotation(p), r) for _, p in peaks.iterrows()]
        assert len(errs) == 4 and min(errs) <= 1.5 * 180.0 / (2 * L), errs
        assert peaks["score"].iloc[3] > 0.9 * peaks["score"].iloc[0]


def test_heading_correlation_recovers_yaw_finer_than_the_grid(room_normals):
    L = 16
    r = euler_zyz(np.radians(-123.4), 0.0, 0.0)
    heads, g = heading_correlation(sh_coefficients(egi(room_normals, L), L),
                                   sh_coefficients(egi(room_normals @ r, L), L), L, n_heading=1440)
    best = heading_peaks(heads, g, top_k=3)
    assert abs((best["heading_deg"].iloc[0] + 123.4 + 180) % 360 - 180) < 2.0


def test_v9_translation_by_occupancy_correlation():
    rng = np.random.default_rng(3)
    cell = 0.2
    model = (rng.integers(0, 40, (3000, 3)) + 0.5) * cell
    for shift in ([3, -5, 2], [-7, 0, 11]):
        t, score, info = translation_by_correlation(model, model - np.array(shift) * cell, cell)
        np.testing.assert_allclose(t, np.array(shift) * cell, atol=1e-9)  # exact for integer shifts
        assert info["padded"][0] >= 2 * info["shape"][0]
    cloud = rng.uniform(0, 8, (6000, 3))
    for _ in range(5):
        true = rng.uniform(-2, 2, 3)
        t, _, _ = translation_by_correlation(cloud, cloud - true, cell)
        assert np.all(np.abs(t - true) <= 0.5 * cell + 1e-9)
    # 50 % overlap: the data sees only half of the model
    half = cloud[cloud[:, 0] > 4.0]
    true = np.array([1.3, -0.7, 0.45])
    t, _, _ = translation_by_correlation(cloud[cloud[:, 0] < 6.0], half - true, cell)
    assert np.all(np.abs(t - true) <= cell + 1e-9)


def _room_scans(rng, scanner):
    from forestmap_assets.sim import ScanPose

    pa = ScanPose(2.0, 2.5, 1.5, float(rng.uniform(-180, 180)))
    while True:  # a second position 2-4 m away, inside the L and clear of the furniture
        ang, dist = rng.uniform(0, 2 * np.pi), rng.uniform(2, 4)
        c = np.array([2.0 + dist * np.cos(ang), 2.5 + dist * np.sin(ang)])
        inside = (0.5 < c[0] < 7.3 and 0.5 < c[1] < 3.5) or (0.5 < c[0] < 4.5 and 0.5 < c[1] < 8.5)
        if inside and np.hypot(*(c - [2.0, 2.0])) > 1.2 and np.hypot(*(c - [2.5, 6.5])) > 1.2:
            break
    pb = ScanPose(float(c[0]), float(c[1]), 1.5, float(rng.uniform(-180, 180)))
    a, b = scanner.scan(pa, 0), scanner.scan(pb, 1)
    ra, ta = pose4_to_matrix((pa.x, pa.y, pa.z, pa.heading_deg))
    rb, tb = pose4_to_matrix((pb.x, pb.y, pb.z, pb.heading_deg))
    return a, b, ra.T @ rb, ra.T @ (tb - ta)


@pytest.fixture(scope="module")
def room_pair():
    from forestmap_assets.sim import VirtualScanner

    scanner = VirtualScanner(room_mesh(), resolution="quarter", sub_rays=0, intensity=False)
    return _room_scans(np.random.default_rng(3), scanner)


@pytest.mark.slow
def test_v10_coarse_pipeline_on_simulated_room_scans(room_pair):
    a, b, r_true, t_true = room_pair
    xa, xb = a.image.xyz[a.image.valid], b.image.xyz[b.image.valid]
    prep = dict(voxel_m=0.08, normal_k=15)
    prepared = (prepare_cloud(xa, **prep), prepare_cloud(xb, **prep))
    kw = dict(cell_m=0.1, ground_weight=1.0, bandwidth=24, prepared=prepared)
    full = coarse_register(None, None, mode="so3", **kw)
    assert rotation_angle_deg(full.rotation, r_true) <= 360.0 / (2 * 24)  # SOFT grid step
    assert np.all(np.abs(full.translation - t_true) <= 2 * 0.1 + 1e-9)
    lev = coarse_register(None, None, mode="heading", **kw)
    assert rotation_angle_deg(lev.rotation, r_true) <= 2.0
    assert np.all(np.abs(lev.translation - t_true) <= 2 * 0.1 + 1e-9)

    # hue filter (spec 4.5): ceiling and two walls painted blue (hue 0.6) are removed by h <= 0.5
    hue_of_part = np.full(32, 0.12)
    hue_of_part[[1, 2, 3]] = 0.6
    ha, hb = hue_of_part[a.part[a.image.valid]], hue_of_part[b.part[b.image.valid]]
    filt = coarse_register(xa, xb, ha, hb, mode="heading", hue_max=0.5, cell_m=0.1, ground_weight=1.0,
                           bandwidth=24, **prep)
    removed = 1 - (np.mean(ha <= 0.5) + np.mean(hb <= 0.5)) / 2
    assert 0.25 < removed < 0.6
    assert filt.n_model < 0.8 * lev.n_model and filt.n_data < 0.8 * lev.n_data
    assert rotation_angle_deg(filt.rotation, r_true) <= 2.0
    eps = [registration_error(xa, xb @ res.rotation.T + res.translation, 0.2) for res in (lev, filt)]
    assert eps[1] <= 1.1 * eps[0]  # the filter does not make the coarse alignment worse


def test_occupancy_scan_heading_mode_and_argument_checks(room_pair):
    a, b, r_true, t_true = room_pair
    xa, xb = a.image.xyz[a.image.valid], b.image.xyz[b.image.valid]
    res = coarse_register(xa, xb, mode="heading", rotation="occupancy_scan", bandwidth=16, top_k=2,
                          voxel_m=0.08, cell_m=0.1, scan_cell_m=0.2, ground_weight=1.0)
    assert rotation_angle_deg(res.rotation, r_true) <= 360.0 / 32 / 4 + 0.5
    assert np.all(np.abs(res.translation - t_true) <= 0.2 + 1e-9)
    assert len(res.candidates) == 2 and np.isfinite(res.error)
    with pytest.raises(ValueError, match="rotation"):
        coarse_register(xa, xb, mode="so3", rotation="occupancy_scan")
    with pytest.raises(ValueError, match="mode"):
        coarse_register(xa, xb, mode="yaw")


def test_coarse_candidates_centre_no_prior_pairs_on_the_fourier_pose(room_pair):
    import pandas as pd

    from forestmap_assets.core.registration.candidates import candidate_pairs
    from forestmap_assets.core.registration.fourier_coarse import coarse_candidates

    a, b, r_true, t_true = room_pair
    clouds = {"T": a.image.xyz[a.image.valid], "S": b.image.xyz[b.image.valid]}
    table = candidate_pairs(["T", "S"], reach={"T": 8.0, "S": 8.0})
    assert table["source"].tolist() == ["no_prior"] and table["scan"].iloc[0] == "S"
    with_prior = pd.concat([table, table.assign(source="pairs", scan="T", reference="S")], ignore_index=True)
    out = coarse_candidates(with_prior, clouds, search=(5.0, 1.25, 60.0), max_range_m=None, z_band_m=None,
                            voxel_m=0.08, cell_m=0.1, scan_cell_m=0.2, ground_weight=1.0, bandwidth=16, top_k=2)
    row = out.iloc[0]
    assert row["source"] == "fourier" and (row["hx"], row["hz"], row["hheading_deg"]) == (5.0, 1.25, 60.0)
    heading = np.degrees(np.arctan2(r_true[1, 0], r_true[0, 0]))
    assert abs((row["cheading_deg"] - heading + 180) % 360 - 180) < 2.0
    assert np.hypot(row["cx"] - t_true[0], row["cy"] - t_true[1]) < 0.3
    pd.testing.assert_series_equal(out.iloc[1], with_prior.iloc[1])  # other sources untouched
