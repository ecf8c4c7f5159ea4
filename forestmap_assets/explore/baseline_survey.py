"""Surveys of fixed positions instead of planned ones (the grid and random baselines of
``benchmarks/bench_explore.py``, inferred): the same virtual plot as
:func:`~forestmap_assets.explore.planned_survey.explore` with the same seed, scanned at every
position, then the pipeline run once at the end."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from forestmap_assets.explore.priors import relative_pose_tuple
from forestmap_assets.explore.survey_map import Progress, SurfaceCache, read_map, run_pipeline
from forestmap_assets.explore.survey_record import (
    STEP_COLUMNS,
    ExploreResult,
    registration_check,
    save_plan,
    tree_counts,
)
from forestmap_assets.explore.survey_writer import SurveyWriter
from forestmap_assets.explore.virtual_plot import VirtualPlot, plot_and_streams
from forestmap_assets.params.men import ExplorationConfig


# ---- fixed positions (baselines) ------------------------------------------------------------
def grid_positions(n: int, plot_size: float) -> np.ndarray:
    """``n`` positions (world) of a regular grid over the plot (inferred baseline): ``k =
    ceil(sqrt(n))`` columns and ``ceil(n / k)`` rows, each position at the centre of its cell of
    the plot's partition (a short last row is spread over its own cells), serpentine order."""
    k = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / k))
    ys = -plot_size / 2 + (np.arange(rows) + 0.5) * plot_size / rows
    pts = []
    for j, y in enumerate(ys):
        m = min(k, n - j * k)
        xs = -plot_size / 2 + (np.arange(m) + 0.5) * plot_size / m
        pts.extend((x, y) for x in (xs if j % 2 == 0 else xs[::-1]))
    return np.array(pts)


def random_positions(
    vp: VirtualPlot,
    n: int,
    rng: np.random.Generator,
    margin_m: float = 2.0,
    clearance_m: float = 0.5,
) -> np.ndarray:
    """``n`` random positions (world) inside the plot that one can stand at (clear of stems and
    understorey); the first is the survey's start."""
    h = vp.plot_size / 2 - margin_m
    out = [np.array([vp.origin.x, vp.origin.y])]
    while len(out) < n:
        cand = rng.uniform(-h, h, (64, 2))
        ok = vp.is_free(cand, clearance_m)
        out.extend(cand[ok][: n - len(out)])
    return np.array(out[:n])


def survey_positions(
    out,
    positions_world: np.ndarray,
    *,
    plot_size: float = 40.0,
    trees: int = 40,
    seed: int = 0,
    resolution: str = "full",
    config: ExplorationConfig | None = None,
    start_xy: Sequence[float] | None = None,
    walk_sigma_m: float = 0.3,
    compass_sigma_deg: float = 5.0,
    use_prior: bool = True,
    max_pairs: int = 2,
    pair_distance_m: float = 20.0,
    progress: Progress | None = None,
    forest_kwargs: dict | None = None,
    scanner_kwargs: dict | None = None,
    export_kwargs: dict | None = None,
    campaign_params: dict | None = None,
) -> ExploreResult:
    """Scan a fixed list of positions (world) of the same virtual plot as :func:`explore` with the
    same ``seed`` (the first position replaces the start), then run the pipeline once. Each scan is
    paired with its ``max_pairs`` nearest earlier positions within ``pair_distance_m``."""
    say = progress or (lambda _m: None)
    t_start = time.perf_counter()
    out = Path(out)
    vp, ss_noise, walk_rng, prior_rng = plot_and_streams(
        plot_size, trees, seed, resolution, start_xy, forest_kwargs, scanner_kwargs
    )
    config = replace(
        config or ExplorationConfig(), plot=tuple(map(tuple, vp.plot_polygon().tolist()))
    )
    search = (
        {
            "xy_m": round(max(1.0, 4 * walk_sigma_m), 3),
            "z_m": 1.25,
            "heading_deg": round(min(180.0, max(15.0, 4 * compass_sigma_deg)), 3),
        }
        if use_prior
        else {}
    )
    positions_world = np.asarray(positions_world, dtype=np.float64).reshape(-1, 2)
    first = vp.free_near(positions_world[0], walk_rng)
    vp.origin = vp.pose_at(first, vp.origin.heading_deg, walk_rng)
    writer = SurveyWriter(
        out, vp, search=search, rng_noise=np.random.default_rng(ss_noise), params=campaign_params
    )
    planned_g = vp.to_global(positions_world)
    priors: list[tuple] = []
    for k, p in enumerate(positions_world):
        if k == 0:
            pose = vp.origin
        else:
            actual = vp.free_near(
                p
                + np.clip(walk_rng.normal(0, walk_sigma_m, 2), -3 * walk_sigma_m, 3 * walk_sigma_m),
                walk_rng,
            )
            pose = vp.pose_at(actual, walk_rng.uniform(-180, 180), walk_rng)
        sid = writer.add_scan(pose)
        g = vp.global_pose(pose)
        heading_prior = g[3] + (prior_rng.normal(0, compass_sigma_deg) if k else 0.0)
        priors.append(
            (planned_g[k, 0], planned_g[k, 1], 0.0, heading_prior) if k else (0.0, 0.0, 0.0, 0.0)
        )
        if use_prior and k:
            d = np.hypot(*(planned_g[:k] - planned_g[k]).T)
            for j in [j for j in np.argsort(d, kind="stable") if d[j] <= pair_distance_m][
                :max_pairs
            ]:
                writer.add_pair(sid, writer.ids[j], relative_pose_tuple(priors[k], priors[j]))
        say(f"scan {sid} ({k + 1}/{len(positions_world)}) at world ({p[0]:.1f}, {p[1]:.1f})")
    writer.write_manifest()
    pipeline_s = run_pipeline(out, say)
    cache = SurfaceCache()
    sm = read_map(out, config, cache)
    rows = []
    for k, sid in enumerate(writer.ids):
        registered, exy, eh = registration_check(out, sm.poses, sid) if k else (True, 0.0, 0.0)
        g = vp.global_pose(writer.poses[k])
        rows.append(
            dict(
                step=k,
                scan=sid,
                reference="",
                planned_x=planned_g[k, 0],
                planned_y=planned_g[k, 1],
                true_x=g[0],
                true_y=g[1],
                true_heading_deg=g[3],
                expected_new_m2=np.nan,
                predicted_common_stems=np.nan,
                predicted_overlap=np.nan,
                path_m=float(np.hypot(*(planned_g[k] - planned_g[k - 1]))) if k else 0.0,
                registered=registered,
                pose_error_m=exy,
                heading_error_deg=eh,
                coverage=np.nan,
                gain=np.nan,
                trees=np.nan,
                trees_with_dbh=np.nan,
                pipeline_seconds=pipeline_s if k == 0 else 0.0,
                plan_seconds=0.0,
            )
        )
    steps = pd.DataFrame(rows, columns=STEP_COLUMNS)
    cov = sm.plan.coverage["coverage"]
    steps.loc[steps.index[-1], "coverage"] = cov
    steps.to_csv(out / "explore" / "steps.csv", index=False, float_format="%.4f")
    save_plan(out, len(steps) - 1, sm, f"fixed positions, after scan {writer.ids[-1]}")
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.outputs.exports import write_exports

    write_exports(load_campaign(out), out / "outputs", **(export_kwargs or {}))
    found, with_dbh, rmse = tree_counts(out, sm.trees)
    return ExploreResult(
        out,
        steps,
        float(cov),
        "fixed positions",
        found,
        with_dbh,
        rmse,
        float(steps["path_m"].sum()),
        time.perf_counter() - t_start,
        np.array([[p.x, p.y] for p in writer.poses]),
    )
