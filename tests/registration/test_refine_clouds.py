"""A scan prepared once for the refinement (the per-scan ``refine_clouds`` asset, issues 16-17)
gives the pair the same refinement as preparing it from the raw points."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.registration.refine import POSE, SD, refine_registrations
from forestmap_assets.core.registration.two_way import RefineCloud
from forestmap_assets.params.men import RefineSettings


def _stems(rng, centres, n=20000):
    """Points on vertical cylinders (r 0.15 m) and a ground plane, seen from the origin."""
    k = rng.integers(0, len(centres), n)
    a = rng.uniform(0, 2 * np.pi, n)
    z = rng.uniform(-1.0, 3.0, n)
    pts = np.column_stack([centres[k, 0] + 0.15 * np.cos(a), centres[k, 1] + 0.15 * np.sin(a), z])
    ground = np.column_stack([rng.uniform(-8, 8, n // 2), rng.uniform(-8, 8, n // 2), np.full(n // 2, -1.5)])
    return np.vstack([pts, ground + rng.normal(0, 0.005, ground.shape)])


def test_prepared_clouds_round_trip_and_refine_alike():
    rng = np.random.default_rng(4)
    centres = rng.uniform(-7, 7, (12, 2))
    ref_pts = _stems(rng, centres)
    true = np.array([0.8, -0.4, 0.0, 12.0])  # scan pose in the reference frame
    c, s = np.cos(np.radians(true[3])), np.sin(np.radians(true[3]))
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    scan_pts = (_stems(rng, centres) - true[:3]) @ rot  # the same stems in the scan's frame
    settings = RefineSettings()
    prepared = {sid: RefineCloud.from_points(p, settings) for sid, p in (("S", scan_pts), ("T", ref_pts))}
    back = {sid: RefineCloud.from_table(c.to_table()) for sid, c in prepared.items()}
    for sid in prepared:
        np.testing.assert_array_equal(back[sid].data, prepared[sid].data)
        np.testing.assert_array_equal(back[sid].model, prepared[sid].model)
        np.testing.assert_array_equal(back[sid].normals, prepared[sid].normals)
    assert not prepared["S"].to_table()["colour"].any()

    row = dict(scan="S", reference="T", status="accepted", **dict(zip(POSE, true + [0.03, -0.02, 0.0, 0.05], strict=True)),
               **dict(zip(SD, [0.02, 0.02, 0.01, 0.05], strict=True)))
    regs = pd.DataFrame([row])
    raw = refine_registrations(regs, {"S": (scan_pts, None), "T": (ref_pts, None)}, settings)
    fast = refine_registrations(regs, {"S": (None, None), "T": (None, None)}, settings, prepared=back)
    a, b = raw["refinements"], fast["refinements"]
    assert a["used"].iloc[0] == b["used"].iloc[0]
    cols = [c for c in a.columns if c not in ("seconds", "reason", "used", "method", "scan", "reference")]
    np.testing.assert_allclose(a[cols].to_numpy(float), b[cols].to_numpy(float), rtol=1e-9, atol=1e-12, equal_nan=True)
