"""A wide first-return beam's mixed pixels are found beside the range jumps and left out of the
refinement clouds (core/registration/mixed_pixels.py, issue 16)."""

from __future__ import annotations

import numpy as np
from helpers.beam_scenes import POLE_GRID, pole_before_wall

from forestmap_assets.core.registration.mixed_pixels import silhouette_band, table_silhouette_band
from forestmap_assets.params.men import RefineSettings
from forestmap_assets.sim import ScanPose, VirtualScanner
from forestmap_assets.sim.scene_mesh import KIND_STEM

STEP = np.radians(0.1)  # rad a pixel, both ways


def test_the_band_is_the_near_side_of_a_jump_one_footprint_wide():
    """A 40-pixel wide object at 5 m before a wall at 15 m; a footprint of 3 pixels' radius at
    5 m (exit 0, divergence 6 pixels): the object's 3 outer columns on each side, nothing of
    the wall, nothing inside the object, and no row or column beyond its top and bottom."""
    r = np.full((30, 100), 15.0, dtype=np.float32)
    r[10:20, 30:70] = 5.0
    band = silhouette_band(r, STEP, STEP, np.zeros(30), 0.0, 6 * STEP, jump_m=0.3)
    near = np.zeros_like(band)
    near[10:20, 30:33] = near[10:20, 67:70] = True  # the sides
    near[10:13, 30:70] = near[17:20, 30:70] = True  # the top and bottom
    np.testing.assert_array_equal(band, near)
    # a smaller jump than the threshold, or no footprint at all, finds nothing
    r2 = np.where(r == 15.0, 5.2, r).astype(np.float32)
    assert not silhouette_band(r2, STEP, STEP, np.zeros(30), 0.0, 6 * STEP, jump_m=0.3).any()
    assert not silhouette_band(r, STEP, STEP, np.zeros(30), 0.0, 0.0, jump_m=0.3).any()


def test_pixels_without_a_return_are_no_jump():
    """Holes (an unorganised cloud's projection, the sky) never mark their neighbours."""
    r = np.full((20, 20), 8.0, dtype=np.float32)
    r[::3, ::2] = np.nan
    assert not silhouette_band(r, STEP, STEP, np.zeros(20), 0.04, 3e-3, jump_m=0.3).any()


def test_the_simulated_beams_mixed_pixels_are_in_the_band():
    """The own simulator's 42 mm + 3 mrad beam (spec 1.1) on a 0.2 m pole at 5 m before a wall
    at 15 m: every mixed pixel is found, and the band is at most the mixed pixels and one
    footprint of the pole's own edge beside them."""
    scanner = VirtualScanner(pole_before_wall(), **POLE_GRID)
    res = scanner.scan(ScanPose(0.0, 0.0, 0.0), seed=1)
    beam = scanner.sensor_beam()
    exit_m, div = 1e-3 * beam["beam_exit_mm"], 1e-3 * beam["beam_divergence_mrad"]
    table = res.image.to_table()
    band = np.zeros(res.mixed.shape, dtype=bool)
    rows, cols = table.column("row").to_numpy(), table.column("col").to_numpy()
    band[rows, cols] = table_silhouette_band(table, exit_m, div, jump_m=0.3)
    assert res.mixed.sum() >= 40
    assert band[res.mixed].all()
    assert band.sum() <= 2 * res.mixed.sum()
    assert not band[res.kind != KIND_STEM].any()  # never the wall


def test_only_a_wide_beam_leaves_pixels_out():
    assert not RefineSettings().wide_beam
    assert not RefineSettings(beam_exit_m=0.005, beam_divergence_mrad=0.3).wide_beam
    assert RefineSettings(beam_exit_m=0.042, beam_divergence_mrad=3.0).wide_beam
