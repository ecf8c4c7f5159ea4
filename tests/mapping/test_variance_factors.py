"""The optimal map's a posteriori variance factor (core/mapping/residuals.variance_factors)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.mapping.residuals import variance_factors, with_variance_factors


def residuals(r: np.ndarray, verdict=None) -> pd.DataFrame:
    out = pd.DataFrame(r, columns=["rx", "ry", "rz", "rheading"])
    out["verdict"] = verdict if verdict is not None else "ok"
    return out


def test_variance_factor_is_the_residuals_rms_over_the_redundancy():
    """Six scans (five unknown poses) and eight consistent links: three redundant. A link the
    residual test rejected does not count."""
    r = np.tile([[1.0, 2.0, 0.5, 0.0]], (8, 1))
    res = pd.concat([residuals(r), residuals(np.full((1, 4), 9.0), ["inconsistent"])], ignore_index=True)
    f = variance_factors(res, n_placed=6)
    assert f == pytest.approx(np.sqrt(8 * np.array([1.0, 4.0, 0.25, 0.0]) / 3))
    # too little redundancy (a spanning tree and one loop), or switched off: ones
    assert variance_factors(residuals(r[:6]), n_placed=6).tolist() == [1.0] * 4
    assert variance_factors(res, n_placed=6, min_dof=0).tolist() == [1.0] * 4


def test_sigmas_grow_with_a_factor_above_one_and_never_shrink():
    poses = pd.DataFrame({"scan": ["a", "b"], "sd_x": [0.0, 0.002], "sd_y": [0.0, 0.003],
                          "sd_z": [0.0, 0.001], "sd_heading_deg": [0.0, 0.01]})
    out = with_variance_factors(poses, np.array([1.5, 0.5, np.nan, 2.0]))
    assert out["sd_x"].tolist() == pytest.approx([0.0, 0.003])
    assert out["sd_y"].tolist() == pytest.approx([0.0, 0.003])
    assert out["sd_z"].tolist() == pytest.approx([0.0, 0.001])
    assert out["sd_heading_deg"].tolist() == pytest.approx([0.0, 0.02])
    assert with_variance_factors(poses, np.array([0.9, 1.0, 0.2, 0.7])) is poses
