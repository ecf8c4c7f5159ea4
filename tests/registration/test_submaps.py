"""Registration points along feature centre lines (spec 6.2, 13.1)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.registration.submaps import build_submap, sample_segments, submap_reach


def _cyl(rows):
    cols = ["cylinder_id", "x0", "y0", "z0", "x1", "y1", "z1"]
    return pd.DataFrame(rows, columns=cols)


def test_points_every_spacing_along_centre_lines():
    cyl = _cyl([[7, 1.0, 2.0, 0.0, 1.0, 2.0, 1.0], [9, 0.0, 0.0, 0.0, 0.3, 0.4, 0.0]])
    lines = pd.DataFrame([[3, 0.0, 0.0, 2.0, 2.0, 0.0, 2.0]],
                         columns=["line_id", "x0", "y0", "z0", "x1", "y1", "z1"])
    sm = build_submap(cyl, lines, spacing_m=0.05)
    assert list(sm.columns) == ["x", "y", "z", "feature", "feature_id"]
    c7 = sm[(sm.feature == "cylinder") & (sm.feature_id == 7)]
    assert len(c7) == 21  # 1 m at 0.05 m, both ends
    np.testing.assert_allclose(c7[["x", "y"]].to_numpy(), np.tile([1.0, 2.0], (21, 1)))
    np.testing.assert_allclose(np.diff(c7.z.to_numpy()), 0.05)
    c9 = sm[sm.feature_id == 9]
    assert len(c9) == 11  # 0.5 m long
    np.testing.assert_allclose(np.hypot(c9.x, c9.y), np.arange(11) * 0.05, atol=1e-12)
    np.testing.assert_allclose(c9.y * 0.3, c9.x * 0.4, atol=1e-12)
    ln = sm[sm.feature == "line"]
    assert len(ln) == 41 and (ln.feature_id == 3).all() and np.allclose(ln.z, 2.0)
    assert submap_reach(sm) == np.hypot(1.0, 2.0)


def test_cylinder_weight_samples_cylinders_more_densely_and_lines_unchanged():
    cyl = _cyl([[7, 1.0, 2.0, 0.0, 1.0, 2.0, 1.0]])
    lines = pd.DataFrame([[3, 0.0, 0.0, 2.0, 2.0, 0.0, 2.0]],
                         columns=["line_id", "x0", "y0", "z0", "x1", "y1", "z1"])
    base = build_submap(cyl, lines, spacing_m=0.05)
    sm = build_submap(cyl, lines, spacing_m=0.05, cylinder_weight=3)
    c7 = sm[sm.feature == "cylinder"]
    assert len(c7) == 61  # 1 m every 0.05/3 m, both ends: weight 3 per metre
    np.testing.assert_allclose(np.diff(c7.z.to_numpy()), 0.05 / 3)
    pd.testing.assert_frame_equal(sm[sm.feature == "line"].reset_index(drop=True),
                                  base[base.feature == "line"].reset_index(drop=True))
    for bad in (0, 1.5):
        with pytest.raises(ValueError):
            build_submap(cyl, lines, cylinder_weight=bad)


def test_empty_inputs_give_well_formed_table():
    empty = _cyl([])
    for sm in (build_submap(empty, None), build_submap(None, None)):
        assert len(sm) == 0
        assert list(sm.columns) == ["x", "y", "z", "feature", "feature_id"]
        assert sm["x"].dtype == np.float64 and sm["feature_id"].dtype == np.int64
    assert submap_reach(build_submap(None, None)) == 0.0


def test_sampling_mismatch_matches_eps_d():
    """Spec 13.1: two random-phase samplings of one line mismatch with sd Delta_d/sqrt(12)."""
    rng = np.random.default_rng(3)
    spacing = 0.05
    offsets = []
    for _ in range(200):
        a0, b0 = rng.uniform(0, spacing, 2)
        pa, _ = sample_segments(np.array([[0, 0, a0]]), np.array([[0, 0, 3.0]]), spacing)
        pb, _ = sample_segments(np.array([[0, 0, b0]]), np.array([[0, 0, 3.0]]), spacing)
        mid = pb[(pb[:, 2] > 0.5) & (pb[:, 2] < 2.5), 2]
        near = pa[np.abs(pa[:, 2][None, :] - mid[:, None]).argmin(1), 2]
        offsets.append((mid - near)[0])
    assert abs(np.std(offsets) / (spacing / np.sqrt(12)) - 1) < 0.12
