"""One turn of the survey loop (thesis Fig. 6.3) after a scan: run the pipeline on the campaign as
it stands (:func:`~forestmap_assets.orchestration.runner.run_campaign`: features, registration,
optimal map, integrated map, trees) and read the stored map back with the exploration grid and the
ranked next vantage positions planned from it (:mod:`forestmap_assets.core.exploration`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from forestmap_assets.params.men import ExplorationConfig, OcclusionConfig

Progress = Callable[[str], None]


@dataclass
class SurveyMap:
    """What the pipeline knows after a run, with the plan made from it."""

    plan: object
    elevation: object
    stems: np.ndarray
    scans: pd.DataFrame  # registered scans, global estimated poses
    poses: pd.DataFrame  # poses.csv rows
    trees: pd.DataFrame


class SurfaceCache:
    """Observed-surface voxels per scan (range images do not change once scanned)."""

    def __init__(self, config: OcclusionConfig | None = None):
        self.config = config or OcclusionConfig()
        self._cache: dict[tuple[str, str], dict] = {}

    def get(self, campaign, sid: str) -> dict:
        from forestmap_assets.access import load_asset
        from forestmap_assets.core.exploration.surface import scan_surface

        key = (campaign.key, sid)
        if key not in self._cache:
            bundle = scan_surface(
                load_asset("range_images", campaign=campaign, scan=sid), self.config
            )
            bundle.pop("_mask", None)
            self._cache[key] = bundle
        return self._cache[key]


def read_map(
    folder: Path,
    config: ExplorationConfig,
    cache: SurfaceCache,
    *,
    current: str | None = None,
    fallback_xy=None,
) -> SurveyMap:
    """Load the stored map of the campaign and plan from it; the surveyor stands at scan
    ``current`` (its estimated position), or at ``fallback_xy`` when it is not registered."""
    from forestmap_assets.access import load_asset
    from forestmap_assets.core.exploration.mapped_plan import plan_from_map
    from forestmap_assets.io.campaign import load_campaign

    campaign = load_campaign(folder)
    poses = load_asset("optimal_map", campaign=campaign)["poses"]
    integrated = load_asset("integrated_map", campaign=campaign)
    trees = load_asset("tree_list", campaign=campaign)
    scans = integrated["scans"]
    surfaces = {sid: cache.get(campaign, sid) for sid in scans["scan"].astype(str)}
    here = scans[scans["scan"].astype(str) == current] if current is not None else scans.iloc[:0]
    current_xy = here[["x", "y"]].to_numpy(float)[0] if len(here) else fallback_xy
    plan, elevation, stems = plan_from_map(
        surfaces, integrated, trees, config, current_xy=current_xy
    )
    return SurveyMap(plan, elevation, stems, scans, poses, trees)


class ExploreError(ValueError):
    """The pipeline failed during a survey (one line: stage and reason)."""


def run_pipeline(folder: Path, progress: Progress) -> float:
    """Run the pipeline on the campaign as it stands; raise :class:`ExploreError` on a failure."""
    from forestmap_assets.orchestration.runner import run_campaign

    t0 = time.perf_counter()
    summary = run_campaign(folder, progress=lambda m: progress(f"    {m.strip()}"))
    if summary.failures:
        stage, scan, reason = summary.failures[0]
        raise ExploreError(f"pipeline failed in {stage}{f'[{scan}]' if scan else ''}: {reason}")
    return time.perf_counter() - t0
