"""A scene for the own simulator's first-return beam (spec 1.1): a thin pole before a wall, and
the small image grid that sees it (tests/sim/test_simulator.py, tests/registration/test_mixed_pixels.py)."""

from __future__ import annotations

import numpy as np

from forestmap_assets.sim.scene_mesh import KIND_STEM, SceneMesh, box_mesh, tube_mesh

# a 50 x 20 pixel full-resolution window onto the pole, exact ranges
POLE_GRID = dict(resolution="full", hfov_deg=5.5, n_cols=50, vfov_deg=2.2, n_rows=20, range_sigma_m=0.0)


def pole_before_wall() -> SceneMesh:
    """A 0.2 m pole (stem, tree 1) at 5 m in front of a wall at 15 m (kind 0, no tree), both
    straight ahead of a sensor at the origin."""
    pv, pf = tube_mesh(np.array([[5.0, 0, -2]]), np.array([[5.0, 0, 2]]), np.array([0.1]),
                       np.array([0.1]), n_sides=64, n_rings=2)
    wv, wf = box_mesh(np.array([[15.5, 0, -5]]), np.array([[1.0, 20.0, 10.0]]), np.zeros(1))
    return SceneMesh(np.vstack([pv, wv]), np.vstack([pf, wf + len(pv)]),
                     np.r_[np.full(len(pf), KIND_STEM), np.zeros(len(wf))].astype(np.uint8),
                     np.r_[np.ones(len(pf)), -np.ones(len(wf))].astype(np.int32),
                     np.r_[np.ones(len(pf)), 2 * np.ones(len(wf))].astype(np.int32))
