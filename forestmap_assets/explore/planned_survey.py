"""``forestmap explore``: a whole survey planned scan by scan in a virtual plot (men_spec 7.7; the
loop of thesis Fig. 6.3 with a surveyor instead of a robot): scan, run the pipeline, plan the next
vantage positions, walk to the best one (within ``walk_sigma_m``, tripod facing away from the
reference +-20 deg), scan there, and repeat until the budget is spent, coverage stops improving
(``min_gain``) or no position adds area while keeping enough overlap to register; the final map's
exports go to ``OUT/outputs`` (DESIGN.md 4)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from forestmap_assets.explore.priors import (
    ground_at,
    more_references,
    prior_pose,
    relative_pose_tuple,
)
from forestmap_assets.explore.survey_map import Progress, SurfaceCache, read_map, run_pipeline
from forestmap_assets.explore.survey_record import (
    STEP_COLUMNS,
    ExploreResult,
    registration_check,
    save_plan,
    tree_counts,
)
from forestmap_assets.explore.survey_writer import SurveyWriter
from forestmap_assets.explore.virtual_plot import plot_and_streams
from forestmap_assets.params.men import ExplorationConfig


def explore(
    out,
    *,
    plot_size: float = 40.0,
    trees: int = 40,
    seed: int = 0,
    budget: int = 8,
    resolution: str = "full",
    strategy: str = "coverage",
    config: ExplorationConfig | None = None,
    start_xy: Sequence[float] | None = None,
    min_gain: float = 0.01,
    min_expected_m2: float = 2.0,
    walk_sigma_m: float = 0.3,
    compass_sigma_deg: float = 5.0,
    use_prior: bool = True,
    max_pairs: int = 2,
    progress: Progress | None = None,
    forest_kwargs: dict | None = None,
    scanner_kwargs: dict | None = None,
    export_kwargs: dict | None = None,
    campaign_params: dict | None = None,
) -> ExploreResult:
    """Plan and simulate a survey of a virtual plot (module docstring); deterministic per seed.

    ``export_kwargs`` go to :func:`~forestmap_assets.outputs.exports.write_exports` (the final map's
    exports in ``OUT/outputs``); ``campaign_params``: the ``params`` section of the campaign's
    ``campaign.yaml`` (per-stage overrides, DESIGN.md 2.1)."""
    say = progress or (lambda _m: None)
    if budget < 1:
        raise ValueError("budget: need at least one scan")
    t_start = time.perf_counter()
    out = Path(out)
    vp, ss_noise, walk_rng, prior_rng = plot_and_streams(
        plot_size, trees, seed, resolution, start_xy, forest_kwargs, scanner_kwargs
    )
    config = replace(
        config or ExplorationConfig(),
        strategy=strategy,
        plot=tuple(map(tuple, vp.plot_polygon().tolist())),
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
    writer = SurveyWriter(
        out, vp, search=search, rng_noise=np.random.default_rng(ss_noise), params=campaign_params
    )
    cache = SurfaceCache()
    say(
        f"explore: {trees} trees in a {plot_size:g} m plot (seed {seed}), budget {budget} "
        f"scans, {resolution} resolution"
    )

    rows: list[dict] = []
    sid = writer.add_scan(vp.origin)
    writer.write_manifest()
    say(f"scan {sid} (1/{budget}) at the start")
    pipeline_s = run_pipeline(out, say)
    t0 = time.perf_counter()
    sm = read_map(out, config, cache, current=sid, fallback_xy=(0.0, 0.0))
    plan_s = time.perf_counter() - t0
    found, with_dbh, _ = tree_counts(out, sm.trees)
    cov = sm.plan.coverage["coverage"]
    rows.append(
        dict(
            step=0,
            scan=sid,
            reference="",
            planned_x=0.0,
            planned_y=0.0,
            true_x=0.0,
            true_y=0.0,
            true_heading_deg=0.0,
            expected_new_m2=np.nan,
            predicted_common_stems=np.nan,
            predicted_overlap=np.nan,
            path_m=0.0,
            registered=True,
            pose_error_m=0.0,
            heading_error_deg=0.0,
            coverage=cov,
            gain=cov,
            trees=found,
            trees_with_dbh=with_dbh,
            pipeline_seconds=pipeline_s,
            plan_seconds=plan_s,
        )
    )
    save_plan(out, 0, sm, f"after scan {sid}")
    say(f"  coverage {100 * cov:.1f} %, {found} trees ({with_dbh} with DBH)")
    stop = "budget reached"
    for k in range(1, budget):
        props = sm.plan.proposals
        feasible = props[props["feasible"]] if len(props) else props
        if feasible.empty:
            stop = "no position keeps enough overlap to register"
            break
        best = feasible.iloc[0]
        if best.expected_gain_m2 < min_expected_m2:
            stop = f"no position is expected to add {min_expected_m2:g} m2"
            break
        planned = np.array([best.x, best.y])
        ref = str(best.reference_scan)
        ref_row = sm.scans[sm.scans["scan"] == ref].iloc[0]
        # walk there (planning error), set the tripod up facing away from the reference
        target_w = vp.to_world(planned)[0]
        actual_w = vp.free_near(
            target_w
            + np.clip(walk_rng.normal(0, walk_sigma_m, 2), -3 * walk_sigma_m, 3 * walk_sigma_m),
            walk_rng,
        )
        ref_w = vp.to_world([ref_row.x, ref_row.y])[0]
        bearing = np.degrees(np.arctan2(*(actual_w - ref_w)[::-1]))
        pose = vp.pose_at(actual_w, bearing + walk_rng.uniform(-20, 20), walk_rng)
        sid = writer.add_scan(pose)
        truth_g = vp.global_pose(pose)
        if use_prior:
            heading_prior = truth_g[3] + prior_rng.normal(0, compass_sigma_deg)
            gz = ground_at(sm.plan.grid, planned)
            prior = prior_pose(planned, gz, heading_prior)
            refs = [ref] + more_references(sm, planned, ref, config, max_pairs - 1)
            for r in refs:
                rr = sm.scans[sm.scans["scan"] == r].iloc[0]
                writer.add_pair(
                    sid, r, relative_pose_tuple(prior, (rr.x, rr.y, rr.z, rr.heading_deg))
                )
        writer.write_manifest()
        say(
            f"scan {sid} ({k + 1}/{budget}) at ({planned[0]:.1f}, {planned[1]:.1f}): expected "
            f"+{best.expected_new_m2:.0f} m2, {int(best.common_stems)} common stems with {ref}, "
            f"walk {best.path_m:.1f} m"
        )
        pipeline_s = run_pipeline(out, say)
        t0 = time.perf_counter()
        sm = read_map(out, config, cache, current=sid, fallback_xy=planned)
        plan_s = time.perf_counter() - t0
        registered, exy, eh = registration_check(out, sm.poses, sid)
        found, with_dbh, _ = tree_counts(out, sm.trees)
        new_cov = sm.plan.coverage["coverage"]
        rows.append(
            dict(
                step=k,
                scan=sid,
                reference=ref,
                planned_x=planned[0],
                planned_y=planned[1],
                true_x=truth_g[0],
                true_y=truth_g[1],
                true_heading_deg=truth_g[3],
                expected_new_m2=best.expected_new_m2,
                predicted_common_stems=int(best.common_stems),
                predicted_overlap=best.overlap_share,
                path_m=best.path_m,
                registered=registered,
                pose_error_m=exy,
                heading_error_deg=eh,
                coverage=new_cov,
                gain=new_cov - cov,
                trees=found,
                trees_with_dbh=with_dbh,
                pipeline_seconds=pipeline_s,
                plan_seconds=plan_s,
            )
        )
        save_plan(out, k, sm, f"after scan {sid}")
        say(
            f"  {'registered' if registered else 'NOT registered'}"
            f"{f' (error {exy:.3f} m, {eh:.2f} deg)' if registered else ''}; "
            f"coverage {100 * new_cov:.1f} % "
            f"(+{100 * (new_cov - cov):.1f}), {found} trees ({with_dbh} with DBH)"
        )
        gain, cov = new_cov - cov, new_cov
        if gain < min_gain:
            stop = f"coverage stopped improving (+{100 * gain:.2f} % < {100 * min_gain:g} %)"
            break
    steps = pd.DataFrame(rows, columns=STEP_COLUMNS)
    steps.to_csv(out / "explore" / "steps.csv", index=False, float_format="%.4f")
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.outputs.exports import write_exports

    write_exports(load_campaign(out), out / "outputs", **(export_kwargs or {}))
    found, with_dbh, rmse = tree_counts(out, sm.trees)
    positions = np.array([[p.x, p.y] for p in writer.poses])
    say(
        f"explore: stopped after {len(steps)} scans ({stop}); coverage {100 * cov:.1f} %, "
        f"{found} trees "
        f"({with_dbh} with DBH), walked {steps['path_m'].sum():.0f} m"
    )
    return ExploreResult(
        out,
        steps,
        float(cov),
        stop,
        found,
        with_dbh,
        rmse,
        float(steps["path_m"].sum()),
        time.perf_counter() - t_start,
        positions,
    )
