"""Feature accuracy against the virtual forest's truth (issue 3; spec 2-4, 10.6).

Three simulated forests (fixed seeds) scanned from two positions each at half resolution
(1500 x 360, 0.216 deg): segments -> circle models -> cylinder segments of every scan are scored
with :func:`forestmap_assets.sim.evaluate.scan_feature_accuracy`:

* target stems: within 15 m of the scanner with >= 1 m of visible trunk (the simulator's
  per-pixel stem labels); found when at least one cylinder's axis middle lies within
  max(r, 10 cm) of the true axis;
* false positives: cylinders on no stem at all (branches, saplings, foliage), share of all;
* radius: per found stem the length-weighted mean of (cylinder radius - true mean radius at the
  cylinder's middle height); RMSE over the stems.

Measured (2026-11-22): 75/78 stems (96.2 %; the three misses are stems visible only as 1-2 px
slivers beside nearer trunks, below the 4-point segment minimum), 0/404 false positives, radius
RMSE 0.67 cm, bias +0.17 cm (benchmarks/results.md, features section).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.features.cylinders import extract_features
from forestmap_assets.io.readers import read_scan
from forestmap_assets.params import resolve_params
from forestmap_assets.sim import simulate_campaign
from forestmap_assets.sim.evaluate import scan_feature_accuracy

SEEDS = (1, 2, 3)
# the forest preset with the noise-corrected symmetry statistic (inferred; proposed as the
# forest preset's default, as for indoor: the plain mean rejects thin trunks beyond ~10 m)
PARAMS = resolve_params("forest", {"circles": {"symmetry_statistic": "noise_corrected"}})


@pytest.fixture(scope="module")
def score_seed(tmp_path_factory):
    """Per scan of a seed's campaign: (campaign, scan, cylinders (levelled scan frame), accuracy
    dict); each seed simulated and scored once for the module."""
    root = tmp_path_factory.mktemp("feature_accuracy")
    done = {}

    def score(seed: int) -> list:
        if seed not in done:
            camp = simulate_campaign(root / f"s{seed}", scans=2, trees=40, seed=seed, resolution="half")
            done[seed] = []
            for path in sorted((camp / "scans").glob("*.npz")):
                cyl = extract_features(read_scan(path), PARAMS)["cylinder_segments"]
                done[seed].append((camp, path.stem, cyl, scan_feature_accuracy(camp, path.stem, cyl)))
        return done[seed]

    return score


def _totals(results) -> dict:
    stems = sum(a["stems"] for a in results)
    found = sum(a["found"] for a in results)
    ncyl = sum(a["n_cylinders"] for a in results)
    fp = sum(a["false_positives"] for a in results)
    err = pd.concat([a["per_stem"] for a in results])
    err = err.loc[err["target"], "radius_error_m"].dropna().to_numpy()
    return {"stems": stems, "found": found, "detection": found / stems, "n_cylinders": ncyl,
            "fp_rate": fp / ncyl, "rmse_m": float(np.sqrt(np.mean(err**2))),
            "bias_m": float(np.mean(err))}


@pytest.mark.slow
def test_detection_false_positives_and_radius(score_seed):
    t = _totals([a for seed in SEEDS for *_, a in score_seed(seed)])
    assert t["stems"] >= 60  # enough stems for the rates to mean something
    assert t["detection"] >= 0.95, t
    assert t["fp_rate"] <= 0.05, t
    assert t["rmse_m"] <= 0.010, t
    assert abs(t["bias_m"]) <= 0.005, t


def test_scorer_rejects_displaced_or_wrong_cylinders(score_seed):
    """The scoring can fail: cylinders moved 0.3 m sideways match no stem, and radii 2 cm too
    large break the RMSE bound (the first seed's two scans)."""
    moved, fat = [], []
    for camp, scan, cyl, _ in score_seed(SEEDS[0]):
        c = cyl.copy()
        c[["x0", "x1"]] += 0.3
        moved.append(scan_feature_accuracy(camp, scan, c))
        c = cyl.copy()
        c["radius_m"] += 0.02
        fat.append(scan_feature_accuracy(camp, scan, c))
    tm, tf = _totals(moved), _totals(fat)
    assert tm["detection"] < 0.2 and tm["fp_rate"] > 0.8
    assert tf["rmse_m"] > 0.015
