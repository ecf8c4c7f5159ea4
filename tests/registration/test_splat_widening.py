"""Splat widening of rendered scans, found and taken back in a pair's refinement
(core/registration/splat_widening.py, issue 19)."""

from __future__ import annotations

import numpy as np
import pytest

from forestmap_assets.core.registration.refine import refine_pair_two_way
from forestmap_assets.core.registration.splat_widening import (
    choose_splat,
    corrected,
    lateral,
    widening,
)
from forestmap_assets.core.registration.two_way import RefineCloud
from forestmap_assets.params.men import RefineSettings
from forestmap_assets.sim.cloud_render import render_scan

STEP_DEG = 0.1
CANDIDATES = (0.005, 0.008, 0.012, 0.016)


def test_the_widening_is_a_whole_number_of_pixels():
    step = np.radians(0.1)  # a pixel is 17.45 mm at 10 m
    w = widening(np.array([2.0, 10.0, 20.0]), 0.012, step)
    assert np.allclose(w, [3 * 2.0 * step, 10.0 * step, 0.0])
    assert not widening(np.array([5.0]), 0.0, step).any()


def test_a_point_moves_back_across_its_ray_only():
    p = np.array([[10.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    n = np.array([[-1.0, 0.0, 0.0], [-0.6, 0.8, 0.0]])  # facing the sensor; turned 53 deg
    rng, u = lateral(p, n)
    assert np.allclose(rng, 10.0)
    assert np.allclose(u[0], 0.0) and np.allclose(u[1], [0.0, 1.0, 0.0])


def _stand(rng: np.random.Generator) -> np.ndarray:
    """A source cloud: ground at z = -1.5 (4 cm grid) and 20 stems of 10-25 cm radius (1 cm apart)."""
    g = np.mgrid[-12:12:0.04, -12:12:0.04].reshape(2, -1).T
    parts = [np.column_stack([g, np.full(len(g), -1.5)])]
    z = np.arange(-1.5, 1.5, 0.01)
    for cx, cy, radius in np.column_stack([rng.uniform(-9, 9, (20, 2)), rng.uniform(0.1, 0.25, 20)]):
        a, h = (v.ravel() for v in np.meshgrid(np.arange(0, 2 * np.pi, 0.01 / radius), z))
        parts.append(np.column_stack([cx + radius * np.cos(a), cy + radius * np.sin(a), h]))
    return np.vstack(parts)


@pytest.fixture(scope="module")
def renders():
    rng = np.random.default_rng(3)
    cloud = _stand(rng)
    a, b = np.array([-3.0, -2.0, 0.0]), np.array([4.0, 3.0, 0.0])
    s = RefineSettings()
    out = {}
    for splat in (0.001, 0.012):
        pa = render_scan(cloud, a, step_deg=STEP_DEG, splat_m=splat, max_range_m=25.0)
        pb = render_scan(cloud, b, step_deg=STEP_DEG, splat_m=splat, max_range_m=25.0)
        out[splat] = tuple(RefineCloud.from_points(p, s, np.radians(STEP_DEG)) for p in (pa, pb))
    return out, b - a, s


def test_a_pair_chooses_the_splat_it_was_rendered_with(renders):
    clouds, baseline, s = renders
    truth = np.r_[baseline[:2], 0.0, 0.0]  # scan b in scan a's frame (same heading)
    b, a = clouds[0.012][1], clouds[0.012][0]
    splat, gain = choose_splat(b, a, truth, CANDIDATES, radius_m=0.05, normal_k=s.normal_k, min_gain=0.1)
    assert splat == 0.012 and gain > 0.3
    # splats below half a pixel widen nothing: none is chosen
    b0, a0 = clouds[0.001][1], clouds[0.001][0]
    assert choose_splat(b0, a0, truth, CANDIDATES, radius_m=0.05, normal_k=s.normal_k, min_gain=0.1)[0] == 0.0
    # without the scans' angular step nothing is tried
    bare = [RefineCloud(data=c.data, model=c.model, normals=c.normals) for c in (b, a)]
    assert choose_splat(*bare, truth, CANDIDATES, radius_m=0.05, normal_k=s.normal_k, min_gain=0.1) == (0.0, 0.0)


def test_the_pair_is_refined_again_on_the_corrected_points(renders):
    clouds, baseline, s = renders
    truth = np.r_[baseline[:2], 0.0, 0.0]
    start = truth + np.array([0.01, -0.01, 0.0, 0.02])
    sd = np.array([0.01, 0.01, 0.005, 0.03])
    b, a = clouds[0.012][1], clouds[0.012][0]
    plain = refine_pair_two_way(b, a, start, sd, s)
    taken = refine_pair_two_way(b, a, start, sd, RefineSettings(splat_candidates_m=CANDIDATES))
    assert plain["used"] == taken["used"] == "refined"
    assert plain["splat_m"] == 0.0 and np.isnan(plain["splat_fit_gain"])  # none tried
    assert taken["splat_m"] == 0.012 and taken["splat_fit_gain"] > 0.3
    # the corrected surfaces lie closer: the refined fit falls by a third or more
    assert taken["fit_refined_m"] < 0.67 * plain["fit_refined_m"]
    # its z no longer rests on the raised ground: the z floor is 5 / m x (12 mm)^2, not 1 mm
    assert plain["ref_sd_z"] == 0.001 and abs(taken["ref_sd_z"] - 5.0 * 0.012**2) < 5e-5
    assert corrected(b, 0.012) is corrected(b, 0.012)  # kept on the cloud for the scan's next pair
