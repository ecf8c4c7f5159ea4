"""Pose covariance when observations sharing a scan are correlated (optimal_map.shared_scan_covariance)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.mapping.link_selection import select_links
from forestmap_assets.core.mapping.optimal_map import (
    RHO_COLUMNS,
    shared_scan_covariance,
    solve_network,
)

SCANS = list("ABCDE")
TRUE = np.array([[0.0, 0.0, 0.0, 0.0], [6.0, 1.0, 0.2, 0.0], [3.0, 7.0, -0.1, 0.0],
                 [-4.0, 5.0, 0.3, 0.0], [-5.0, -3.0, 0.1, 0.0]])
PAIRS = [(1, 0), (2, 0), (3, 0), (4, 0), (2, 1), (3, 2), (4, 3), (3, 1), (4, 1)]


def _draw(rng: np.random.Generator, sd: np.ndarray, rho) -> pd.DataFrame:
    """Observations with errors ``sqrt(1 - 2 rho) v + u_i - u_j`` (the model of the docstring;
    all true headings 0, so local and global frames agree); ``rho`` one value or one per
    observation row, observations with the same rho forming one type with its own ``u``."""
    i = np.array([p[0] for p in PAIRS])
    j = np.array([p[1] for p in PAIRS])
    rho = np.broadcast_to(np.asarray(rho, dtype=float).reshape(-1, 1), (len(PAIRS), 1))
    e = np.sqrt(1 - 2 * rho) * rng.normal(size=sd.shape) * sd
    for value in np.unique(rho):
        k = np.flatnonzero(rho[:, 0] == value)
        s_var = np.zeros((len(SCANS), 4))
        n = np.zeros(len(SCANS))
        for ends in (i[k], j[k]):
            np.add.at(s_var, ends, value * sd[k] ** 2)
            np.add.at(n, ends, 1)
        u = rng.normal(size=(len(SCANS), 4)) * np.sqrt(s_var / np.maximum(n, 1)[:, None])
        e[k] += u[i[k]] - u[j[k]]
    d = TRUE[i] - TRUE[j] + e
    return pd.DataFrame({"scan": [SCANS[k] for k in i], "reference": [SCANS[k] for k in j],
                         "dx": d[:, 0], "dy": d[:, 1], "dz": d[:, 2], "dheading_deg": d[:, 3],
                         "sd_x": sd[:, 0], "sd_y": sd[:, 1], "sd_z": sd[:, 2],
                         "sd_heading_deg": sd[:, 3]})


def _normalised(sol) -> np.ndarray:
    p = sol.poses.iloc[1:]
    err = p[["x", "y", "z", "heading_deg"]].to_numpy(float) - TRUE[1:]
    return err / p[["sd_x", "sd_y", "sd_z", "sd_heading_deg"]].to_numpy(float)


@pytest.mark.slow
def test_correlated_observations_get_calibrated_pose_sigmas():
    rng = np.random.default_rng(5)
    rho = 0.35
    sd = np.array([0.01, 0.015, 0.004, 0.02]) * rng.uniform(0.6, 1.6, size=(len(PAIRS), 1))
    plain, modelled = [], []
    for _ in range(300):
        obs = _draw(rng, sd, rho)
        a = solve_network(obs, SCANS, iterate=True)
        b = solve_network(obs, SCANS, iterate=True, scan_correlation=rho)
        # the estimate and the residuals of the thesis's solve do not change
        np.testing.assert_allclose(a.poses[["x", "y", "z", "heading_deg"]],
                                   b.poses[["x", "y", "z", "heading_deg"]], atol=1e-12)
        np.testing.assert_allclose(a.residuals[["rx", "ry", "rz", "rheading"]],
                                   b.residuals[["rx", "ry", "rz", "rheading"]], atol=1e-12)
        plain.append(_normalised(a))
        modelled.append(_normalised(b))
    rms_plain = np.sqrt(np.mean(np.concatenate(plain) ** 2, axis=0))
    rms = np.sqrt(np.mean(np.concatenate(modelled) ** 2, axis=0))
    assert np.all(rms_plain > 1.25)  # independent-observation sigmas are over-confident
    assert np.all(np.abs(rms - 1.0) < 0.08), rms


def test_per_component_correlation_and_limits():
    rng = np.random.default_rng(1)
    sd = np.tile([0.01, 0.01, 0.005, 0.02], (len(PAIRS), 1))
    obs = _draw(rng, sd, 0.0)
    base = solve_network(obs, SCANS)
    only_xy = solve_network(obs, SCANS, scan_correlation=[0.3, 0.3, 0.0, 0.0])
    cols = ["sd_x", "sd_y", "sd_z", "sd_heading_deg"]
    np.testing.assert_allclose(only_xy.poses[cols[2:]], base.poses[cols[2:]], rtol=1e-12)
    assert (only_xy.poses[cols[:2]].iloc[1:].to_numpy() > base.poses[cols[:2]].iloc[1:].to_numpy()).all()
    # a scan reached by a single link keeps that link's marginal sigma (no averaging to undo)
    chain = obs.iloc[[0]]
    one = solve_network(chain, SCANS[:2], scan_correlation=0.4)
    np.testing.assert_allclose(one.poses[cols].iloc[1].to_numpy(float), sd[0], rtol=1e-9)
    with pytest.raises(ValueError):
        shared_scan_covariance(base.covariance, 5, 0, np.array([1]), np.array([0]),
                               np.eye(4)[None], np.ones(5, bool), 0.6)


def test_link_selection_verdicts_do_not_depend_on_correlation():
    rng = np.random.default_rng(2)
    sd = np.tile([0.01, 0.01, 0.005, 0.02], (len(PAIRS), 1))
    obs = _draw(rng, sd, 0.3)
    obs.loc[len(obs) - 1, "dx"] += 0.2  # one wrong loop link
    obs["confidence"] = np.arange(len(obs))[::-1].astype(float)
    a = select_links(obs, "A", scans=SCANS)
    b = select_links(obs, "A", scans=SCANS, scan_correlation=0.3)
    pd.testing.assert_series_equal(a.links["status"], b.links["status"])
    assert (a.links["status"] == "rejected").sum() == 1
    assert (b.solution.poses["sd_x"].iloc[1:] > a.solution.poses["sd_x"].iloc[1:]).all()


@pytest.mark.slow
def test_each_observation_type_keeps_its_own_correlation():
    """Refined links are barely correlated, branch-and-bound links are: per-observation rho
    (``RHO_COLUMNS``) gives calibrated sigmas where any single rho is off."""
    rng = np.random.default_rng(11)
    rho = np.where(np.arange(len(PAIRS)) % 2 == 0, 0.45, 0.0)  # two observation types
    sd = np.array([0.01, 0.015, 0.004, 0.02]) * rng.uniform(0.6, 1.6, size=(len(PAIRS), 1))
    own, low, high = [], [], []
    for _ in range(300):
        obs = _draw(rng, sd, rho)
        typed = obs.assign(**{c: rho for c in RHO_COLUMNS})
        a = solve_network(typed, SCANS, iterate=True)
        b = solve_network(obs, SCANS, iterate=True, scan_correlation=0.0)
        np.testing.assert_allclose(a.poses[["x", "y", "z", "heading_deg"]],
                                   b.poses[["x", "y", "z", "heading_deg"]], atol=1e-12)
        own.append(_normalised(a))
        low.append(_normalised(b))
        high.append(_normalised(solve_network(obs, SCANS, iterate=True, scan_correlation=0.45)))
    rms = {k: np.sqrt(np.mean(np.concatenate(v) ** 2, axis=0))
           for k, v in (("own", own), ("low", low), ("high", high))}
    assert np.all(np.abs(rms["own"] - 1.0) < 0.08), rms
    assert np.all(rms["low"] > rms["own"] + 0.05) and np.all(rms["high"] < rms["own"] - 0.05), rms
    # the same rho in every row is the scalar argument; a row without its own rho takes it
    obs = _draw(rng, sd, 0.2)
    same = solve_network(obs.assign(**{c: 0.2 for c in RHO_COLUMNS}), SCANS)
    np.testing.assert_allclose(same.covariance, solve_network(obs, SCANS, scan_correlation=0.2)
                               .covariance, rtol=1e-9, atol=1e-15)
    part = obs.assign(**{c: np.where(np.arange(len(obs)) < 3, 0.2, np.nan) for c in RHO_COLUMNS})
    np.testing.assert_allclose(solve_network(part, SCANS, scan_correlation=0.2).covariance,
                               same.covariance, rtol=1e-9, atol=1e-15)
