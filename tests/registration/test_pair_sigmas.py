"""Observation sigmas of a registration: the tempered-likelihood cell cloud (issue 5)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.registration.pair_registrations import (
    observation_sigmas,
    tempered_cloud_sigma,
)

SIGMA = np.array([0.01, 0.02, 0.05, 0.1])  # dx, dy, dz m, heading deg
STEP = np.array([0.004, 0.004, 0.01, 0.02])
PEAK = np.array([1.0, -2.0, 0.3, 179.9])  # heading near the wrap


def _levels(temperature: float, rival_gap: float | None = None) -> pd.DataFrame:
    """Final-level cells on a lattice around PEAK scoring ``-T/2 sum((p - PEAK)/SIGMA)^2``: the
    tempered likelihood is then a Gaussian of width SIGMA. A coarser level and (optionally) a
    rival cloud 2 m away, ``rival_gap`` below the peak, are added."""
    k = np.arange(-12, 13)
    grid = np.array(np.meshgrid(k, k, k, k, indexing="ij")).reshape(4, -1).T * STEP * 3.0
    p = PEAK + grid
    score = -0.5 * temperature * ((grid / SIGMA) ** 2).sum(1) - 5000.0
    p[:, 3] = (p[:, 3] + 180.0) % 360.0 - 180.0
    frame = pd.DataFrame(p, columns=["dx", "dy", "dz", "dh_deg"]).assign(level=7, score=score)
    parts = [frame, frame.iloc[::50].assign(level=6, score=score[::50] + 1.0)]
    if rival_gap is not None:
        rival = frame.copy()
        rival["dx"] += 2.0
        rival["score"] -= rival_gap
        parts.append(rival)
    return pd.concat(parts, ignore_index=True)


@pytest.mark.parametrize("temperature", [1.0, 10.0])
def test_tempered_cloud_recovers_the_gaussian_width(temperature):
    sd = tempered_cloud_sigma(_levels(temperature), PEAK, 10.0, temperature)
    np.testing.assert_allclose(sd, SIGMA, rtol=0.03)
    # at a higher temperature the same scores spread wider, by sqrt(T'/T)
    wide = tempered_cloud_sigma(_levels(temperature), PEAK, 10.0, 4 * temperature)
    np.testing.assert_allclose(wide[:2], 2 * SIGMA[:2], rtol=0.1)


def test_tempered_cloud_leaves_out_other_hypotheses():
    levels = _levels(10.0, rival_gap=1.0)  # a near-equal rival 2 m away
    sd = tempered_cloud_sigma(levels, PEAK, 10.0, 10.0, separation_m=0.3)
    np.testing.assert_allclose(sd, SIGMA, rtol=0.03)
    merged = tempered_cloud_sigma(levels, PEAK, 10.0, 10.0, separation_m=5.0)
    assert merged[0] > 0.5  # both clouds: metres
    assert np.isnan(tempered_cloud_sigma(levels.iloc[:0], PEAK, 10.0, 10.0)).all()


def test_observation_sigmas_tempered_axes_and_fallbacks():
    jp = np.array([0.03, 0.04, 0.2, 0.3])
    res = SimpleNamespace(sigma=tuple(jp), final_step=tuple(STEP), peak=tuple(PEAK), d_bar_m=10.0,
                          levels=_levels(10.0))
    got = observation_sigmas(res, likelihood_temperature=10.0, heading_temperature=None)
    want = np.sqrt(np.r_[SIGMA[:2], jp[2], SIGMA[3]] ** 2 + STEP**2 / 12)
    np.testing.assert_allclose(got, want, rtol=0.03)
    # a heading temperature 4x lower halves the heading sigma only
    sharp = observation_sigmas(res, likelihood_temperature=10.0, heading_temperature=2.5)
    np.testing.assert_allclose(sharp[:3], got[:3])
    assert sharp[3] == pytest.approx(np.hypot(SIGMA[3] / 2, STEP[3] / np.sqrt(12)), rel=0.05)
    # the JP eq. 6 cloud sigma without a temperature or without levels, scaled by sigma_scale
    old = 2.0 * np.sqrt(jp**2 + STEP**2 / 12)
    np.testing.assert_allclose(observation_sigmas(res, 2.0, None), old)
    res.levels = pd.DataFrame(columns=["level", "dx", "dy", "dz", "dh_deg", "score"])
    np.testing.assert_allclose(observation_sigmas(res, 2.0, 10.0), old)


def test_ground_dz_gate_uses_the_feature_dz_sd(monkeypatch):
    """The ground dz replaces the feature dz when they agree within ``3 sd + 0.1 m`` with the
    feature dz's own sd (its cloud sd combined with ``feature_z_sd_m``): a tight cell cloud
    (lattice bound) no longer refuses a ground dz 0.3 m from a feature dz that near-vertical
    stems barely fix; a ground dz 1 m away is still refused."""
    from forestmap_assets.core.registration import pair_registrations as pr
    from forestmap_assets.core.registration.register import RegistrationResult
    from forestmap_assets.core.registration.score import ScoreModel
    from forestmap_assets.params import RegistrationParams

    params = RegistrationParams(min_support_m=0.0, max_rival_ratio=None)
    n = 200
    result = RegistrationResult(
        status="ok", peak=(0.0, 0.0, 0.0, 0.0), peak_score=n * ScoreModel().ln_p0,
        centre=(0.0, 0.0, 0.0, 0.0), sigma=(0.005, 0.005, 0.004, 0.02), cloud_cells=3,
        peak_mass_share=1.0, n_points=n, final_step=(0.02, 0.02, 0.02, 0.1), d_bar_m=5.0,
        matched_stems=10)
    monkeypatch.setattr(pr, "_register_one", lambda job: result)
    k = np.arange(-50, 50)
    ix, iy = (a.ravel() for a in np.meshgrid(k, k, indexing="ij"))
    ref_grid = pd.DataFrame({"ix": ix, "iy": iy, "z": np.zeros(len(ix))})
    cand = pd.DataFrame([dict(scan="B", reference="A", cx=0.0, cy=0.0, cz=0.0, cheading_deg=0.0,
                              hx=5.0, hy=5.0, hz=1.25, hheading_deg=60.0, box_heading_deg=0.0)])
    sub = {s: pd.DataFrame({"x": [0.0], "y": [0.0], "z": [0.0]}) for s in "AB"}
    for offset, source in ((0.3, "ground"), (1.0, "features")):
        scan_grid = ref_grid.assign(z=-offset)  # the scan's ground sits `offset` lower
        out = pr.register_candidates(cand, sub, params,
                                     elevation={"A": ref_grid, "B": scan_grid})
        row = out["registrations"].iloc[0]
        assert row["status"] == "accepted" and row["z_source"].startswith(source)
        want = offset if source == "ground" else 0.0
        assert row["dz"] == pytest.approx(want, abs=1e-9)


def test_a_peak_on_the_dz_edge_is_searched_again_at_the_grounds_dz(monkeypatch):
    """A no-prior pair whose scan stands 1.6 m above its reference (a slope) peaks on the edge of
    the thesis' dz range (+-1.25 m about 0) and was rejected; the ground grids put the dz at
    1.6 m, so the pair is searched again there, about the peak's x, y and heading in the
    screening box, and accepted. Where the range would not change, nothing is searched again."""
    from forestmap_assets.core.registration import pair_registrations as pr
    from forestmap_assets.core.registration.register import RegistrationResult
    from forestmap_assets.core.registration.score import ScoreModel
    from forestmap_assets.params import RegistrationParams

    params = RegistrationParams(min_support_m=0.0, max_rival_ratio=None)
    n, jobs = 200, []

    def search(job):
        jobs.append(job)
        z = min(job[2][2] + job[3][2] - 0.01, 1.6)  # the features' peak: 1.6, or the range's edge
        return RegistrationResult(
            status="ok", peak=(3.0, -4.0, z, 120.0), peak_score=n * ScoreModel().ln_p0,
            centre=(3.0, -4.0, z, 120.0), sigma=(0.005, 0.005, 0.05, 0.02), cloud_cells=3,
            peak_mass_share=1.0, n_points=n, final_step=(0.02, 0.02, 0.02, 0.1), d_bar_m=5.0,
            matched_stems=10)

    monkeypatch.setattr(pr, "_register_one", search)
    k = np.arange(-60, 60)
    ix, iy = (a.ravel() for a in np.meshgrid(k, k, indexing="ij"))
    flat = pd.DataFrame({"ix": ix, "iy": iy, "z": np.zeros(len(ix))})
    cand = pd.DataFrame([dict(scan="B", reference="A", cx=0.0, cy=0.0, cz=0.0, cheading_deg=0.0,
                              hx=15.0, hy=15.0, hz=1.25, hheading_deg=180.0, box_heading_deg=0.0,
                              source="no_prior")])
    sub = {s: pd.DataFrame({"x": [0.0], "y": [0.0], "z": [0.0]}) for s in "AB"}
    # the scan 1.6 m higher: its ground 1.6 m below it, the reference's level with it
    out = pr.register_candidates(cand, sub, params, elevation={"A": flat, "B": flat.assign(z=-1.6)})
    row = out["registrations"].iloc[0]
    assert len(jobs) == 2 and row["status"] == "accepted"
    assert jobs[1][2] == pytest.approx((3.0, -4.0, 1.6, 120.0), abs=0.01)
    assert jobs[1][3] == (1.0, 1.0, 1.25, 10.0)
    assert row["dz"] == pytest.approx(1.6, abs=0.01) and row["z_source"].startswith("ground")
    # a screened pair's narrow range about the ground's dz (1.2 +- 0.3 m) too narrow for the
    # features' 1.6 m: searched again about the ground's dz at least z_m wide
    jobs.clear()
    out = pr.register_candidates(cand.assign(cz=1.2, hz=0.3), sub, params,
                                 elevation={"A": flat, "B": flat.assign(z=-1.2)})
    assert len(jobs) == 2 and jobs[1][2][2] == pytest.approx(1.2, abs=0.01) and jobs[1][3][2] == params.z_m
    # the range would not change (the ground's dz at its centre, already z_m wide): no second
    # search, the edge stays
    jobs.clear()
    out = pr.register_candidates(cand.assign(hz=1.25), sub, params,
                                 elevation={"A": flat, "B": flat})
    assert len(jobs) == 1 and out["registrations"].iloc[0]["status"] == "rejected"
