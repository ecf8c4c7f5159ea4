"""Occlusion boundaries (per scan) and next vantage positions (per campaign): thin Dagster
wrappers around :mod:`..core.occlusion` and :mod:`..core.exploration` (men_spec 3.1, 3.5-3.6, 7).

Parameters come from the campaign's ``occlusion`` and ``exploration`` sections when the parameter
model has them, else from the defaults of :class:`~..core.occlusion.OcclusionConfig` and
:class:`~..core.exploration.ExplorationConfig`; their hash enters the code versions.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, replace

import numpy as np
import pandas as pd
from dagster import AssetIn, MetadataValue, Output, asset

from forestmap_assets.assets.common import asset_key, data_version, png_metadata, scan_partitions
from forestmap_assets.core.exploration import ExplorationConfig, VantagePlan
from forestmap_assets.figures import range_mask_figure
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.params_men import OcclusionConfig

CODE_VERSIONS = {"occlusion_boundaries": "1", "next_vantage_points": "1"}


def occlusion_config(campaign: Campaign) -> OcclusionConfig:
    return OcclusionConfig.from_params(getattr(campaign.params, "occlusion", None))


def exploration_config(campaign: Campaign) -> ExplorationConfig:
    return ExplorationConfig.from_params(getattr(campaign.params, "exploration", None))


def _version(stage: str, *configs) -> str:
    text = json.dumps([asdict(c) for c in configs], sort_keys=True, default=str)
    return f"v{CODE_VERSIONS[stage]}-{hashlib.sha256(text.encode()).hexdigest()[:16]}"


def stage_version(campaign: Campaign, stage: str) -> str:
    """Code version of ``occlusion_boundaries`` / ``next_vantage_points`` (stage version plus the
    hash of its settings), as :func:`~.common.code_version` gives for the other stages."""
    config = occlusion_config(campaign) if stage == "occlusion_boundaries" else exploration_config(campaign)
    return _version(stage, config)


def scan_surface(image, config: OcclusionConfig) -> dict[str, pd.DataFrame]:
    """The ``occlusion_boundaries`` bundle of one range image: ``boundaries`` (flagged pixels),
    ``surface`` (observed-surface voxels, levelled scan frame) and ``info`` (one row)."""
    from forestmap_assets.core.exploration import observed_surface
    from forestmap_assets.core.exploration_.occlusion import boundaries_table, detect_occlusions

    ob = detect_occlusions(image, **config.detector_kwargs())
    table = boundaries_table(image, ob)
    surface = observed_surface(
        image,
        ob.tilt_pair,
        ob.pan_pair,
        voxel_m=config.surface_voxel_m,
        fill_step_m=config.fill_step_m,
        max_fill_m=config.max_fill_m,
        wrap=ob.wrap,
    )
    rows, cols = image.shape
    info = pd.DataFrame(
        {
            "rows": [rows],
            "cols": [cols],
            "wrap": [ob.wrap],
            "voxel_m": [config.surface_voxel_m],
            "azimuth_step_deg": [image.azimuth_step_deg],
            "elevation_step_deg": [image.elevation_step_deg],
            "median_tilt_threshold": [
                float(np.median(ob.tilt_threshold)) if ob.tilt_threshold.size else np.nan
            ],
            "median_pan_threshold": [
                float(np.median(ob.pan_threshold)) if ob.pan_threshold.size else np.nan
            ],
            "valid_pixels": [int(image.valid.sum())],
            "boundary_pixels": [int(ob.boundary.sum())],
        }
    )
    return {"boundaries": table, "surface": surface, "info": info, "_mask": ob.boundary}


def stems_from_trees(trees: pd.DataFrame, default_radius_m: float = 0.1) -> np.ndarray:
    """Mapped stems as ``x, y, r`` rows (r = DBH / 2, ``default_radius_m`` where DBH is missing)."""
    if trees is None or not len(trees):
        return np.zeros((0, 3))
    r = (trees["dbh_m"].astype(float) / 2).fillna(default_radius_m).to_numpy()
    return np.column_stack([trees["x"].to_numpy(float), trees["y"].to_numpy(float), r])


def plan_from_map(
    surfaces: dict[str, pd.DataFrame | dict],
    integrated_map: dict[str, pd.DataFrame],
    trees: pd.DataFrame,
    config: ExplorationConfig,
    *,
    current_xy=None,
    default_voxel_m: float = 0.05,
) -> tuple[VantagePlan, object, np.ndarray]:
    """Exploration grid, classes, coverage and ranked next vantage positions of a mapped campaign.

    ``surfaces``: scan id -> ``occlusion_boundaries`` bundle (or its ``surface`` table);
    ``integrated_map``: the bundle with ``elevation`` and registered ``scans``. Returns the plan,
    the merged elevation grid and the stems (``x, y, r``)."""
    from forestmap_assets.core.exploration import build_grid, plan_next_vantage
    from forestmap_assets.core.features.elevation import elevation_from_table

    elevation = elevation_from_table(integrated_map["elevation"])
    scans = integrated_map["scans"]
    scans = scans[scans["registered"].astype(bool)] if "registered" in scans else scans
    poses = {r.scan: (r.x, r.y, r.z, r.heading_deg) for r in scans.itertuples()}
    items = []
    for sid, pose in poses.items():
        bundle = surfaces.get(sid)
        if bundle is None:
            continue
        if isinstance(bundle, dict):
            table = bundle["surface"]
            info = bundle.get("info")
            voxel = (
                float(info["voxel_m"].iloc[0])
                if info is not None and len(info)
                else default_voxel_m
            )
        else:
            table, voxel = bundle, default_voxel_m
        items.append((table, pose, voxel))
    scan_xy = scans[["x", "y"]].to_numpy(float)
    steps = [
        float(b["info"]["azimuth_step_deg"].iloc[0])
        for b in surfaces.values()
        if isinstance(b, dict) and "info" in b and "azimuth_step_deg" in b["info"]
    ]
    if config.angular_step_deg is None and steps:  # the scanner's step limits stem detection
        config = replace(config, angular_step_deg=float(np.median(steps)))
    ground_default = float(scans["z"].min()) - 1.5 if len(scans) else -1.5
    grid = build_grid(
        items,
        elevation,
        scan_xy if len(scan_xy) else np.zeros((1, 2)),
        config,
        default_ground_z=ground_default,
    )
    stems = stems_from_trees(trees)
    incomplete = trees["dbh_m"].isna().to_numpy() if trees is not None and len(trees) else None
    ids = scans["scan"].astype(str).tolist()
    plan = plan_next_vantage(
        grid, stems, scan_xy, ids, config, current_xy=current_xy, incomplete=incomplete
    )
    return plan, elevation, stems


def plan_tables(plan: VantagePlan) -> dict[str, pd.DataFrame]:
    """The ``next_vantage_points`` bundle: ``proposals``, ``paths`` (rank, step, x, y),
    ``coverage`` (one row) and ``cells`` (every plot cell: class, ground, density, frontier)."""
    from forestmap_assets.core.exploration import CLASS_NAMES

    grid = plan.grid
    paths = [
        pd.DataFrame({"rank": rank, "step": np.arange(len(p)), "x": p[:, 0], "y": p[:, 1]})
        for rank, p in sorted(plan.paths.items())
    ]
    paths_df = (
        pd.concat(paths, ignore_index=True)
        if paths
        else pd.DataFrame(
            {
                "rank": pd.Series(dtype="int64"),
                "step": pd.Series(dtype="int64"),
                "x": pd.Series(dtype="float64"),
                "y": pd.Series(dtype="float64"),
            }
        )
    )
    ix, iy = np.nonzero(grid.in_plot)
    xy = grid.cell_xy(ix, iy)
    cells = pd.DataFrame(
        {
            "ix": ix.astype(np.int32),
            "iy": iy.astype(np.int32),
            "x": xy[:, 0],
            "y": xy[:, 1],
            "cell_class": np.asarray(CLASS_NAMES, dtype=object)[plan.classes[ix, iy]],
            "ground_z": grid.ground_z[ix, iy] if grid.ground_z is not None else np.nan,
            "points_per_m2": grid.points[ix, iy] / grid.cell_m**2,
            "frontier": plan.frontier[ix, iy],
        }
    )
    coverage = pd.DataFrame(
        [
            {
                **plan.coverage,
                "cell_m": grid.cell_m,
                "current_ix": plan.current[0],
                "current_iy": plan.current[1],
            }
        ]
    )
    proposals = plan.proposals.copy()
    proposals["reference_scan"] = proposals["reference_scan"].fillna("").astype(str)
    return {"proposals": proposals, "paths": paths_df, "coverage": coverage, "cells": cells}


def exploration_assets(campaign: Campaign) -> list:
    parts = scan_partitions(campaign)
    occ_cfg = occlusion_config(campaign)
    exp_cfg = exploration_config(campaign)

    def key(stage: str):
        return asset_key(campaign, stage)

    @asset(
        key=key("occlusion_boundaries"),
        ins={"range_images": AssetIn(key=key("range_images"))},
        partitions_def=parts,
        group_name="exploration",
        code_version=stage_version(campaign, "occlusion_boundaries"),
        description="Occlusion-boundary pixels of the organised range image: range-normalised "
        "spacing test Delta_s/r >= sin(Delta)/sin(5 deg - Delta) in the tilt and pan directions, "
        "combined by union, plus the range-variance test (Men 2012 3.3; men_spec 3.1), and the "
        "observed surface between unflagged neighbours as voxels (for the exploration grid).",
    )
    def occlusion_boundaries(context, range_images):
        from forestmap_assets.core.features.range_image import RangeImage

        image = RangeImage.from_table(range_images)
        bundle = scan_surface(image, occ_cfg)
        mask = bundle.pop("_mask")
        table, info = bundle["boundaries"], bundle["info"].iloc[0]
        valid = max(int(info["valid_pixels"]), 1)
        meta = {
            "boundary_pixels": int(mask.sum()),
            "boundary_share": round(float(mask.sum()) / valid, 4),
            "tilt_pixels": int(table["tilt"].sum()),
            "pan_pixels": int(table["pan"].sum()),
            "variance_pixels": int(table["variance"].sum()),
            "tilt_threshold": round(float(info["median_tilt_threshold"]), 5),
            "pan_threshold": round(float(info["median_pan_threshold"]), 5),
            "surface_voxels": len(bundle["surface"]),
            "occlusion_boundaries": png_metadata(
                range_mask_figure(image, mask, f"occlusion boundaries, scan {context.partition_key}",
                                  label="occlusion boundaries")
            ),
        }
        return Output(bundle, metadata=meta, data_version=data_version(bundle))

    @asset(
        key=key("next_vantage_points"),
        ins={
            "occlusion_boundaries": AssetIn(
                key=key("occlusion_boundaries"), metadata={"allow_missing_partitions": True}
            ),
            "integrated_map": AssetIn(key=key("integrated_map")),
            "tree_list": AssetIn(key=key("tree_list")),
        },
        group_name="exploration",
        code_version=stage_version(campaign, "next_vantage_points"),
        description="Completeness and where to scan next: 2-D exploration grid (height histograms "
        "relative to the local ground; unmapped / ground / obstacle), coverage, frontier cells, "
        "and candidate positions reachable by shortest paths, ranked by the new area a 2-D "
        "visibility model with trunk occlusion expects, under the overlap constraint (common "
        "stems / 50 % overlap) and by walking distance (Men 2012 ch. 3.7-3.8, 6; men_spec 7).",
    )
    def next_vantage_points(context, occlusion_boundaries, integrated_map, tree_list):
        from forestmap_assets.core.exploration import exploration_figure

        surfaces = occlusion_boundaries or {}
        if "surface" in surfaces and isinstance(surfaces["surface"], pd.DataFrame):
            # Dagster hands a single upstream partition over as the object itself
            keys = context.asset_partition_keys_for_input("occlusion_boundaries")
            surfaces = {keys[0]: surfaces} if len(keys) == 1 else {}
        plan, elevation, stems = plan_from_map(surfaces, integrated_map, tree_list, exp_cfg)
        bundle = plan_tables(plan)
        props = bundle["proposals"]
        best = props.iloc[0] if len(props) else None
        fig = exploration_figure(
            plan,
            elevation,
            stems,
            integrated_map["scans"],
            title=f"{campaign.name}: next vantage positions",
        )
        show = props.head(exp_cfg.n_proposals)[
            [
                "rank",
                "x",
                "y",
                "expected_new_m2",
                "incomplete_stems",
                "overlap_share",
                "common_stems",
                "reference_scan",
                "path_m",
                "feasible",
            ]
        ]
        meta = {
            **{k: v for k, v in plan.coverage.items()},
            "frontier_cells": int(plan.frontier.sum()),
            "candidates": len(props),
            "feasible": int(props["feasible"].sum()) if len(props) else 0,
            "best": MetadataValue.json(
                {}
                if best is None
                else {
                    "x": round(float(best.x), 2),
                    "y": round(float(best.y), 2),
                    "expected_new_m2": round(float(best.expected_new_m2), 1),
                    "common_stems": int(best.common_stems),
                    "path_m": round(float(best.path_m), 1),
                }
            ),
            "proposals": MetadataValue.md(_md(show)),
            "picture": png_metadata(fig),
        }
        return Output(bundle, metadata=meta, data_version=data_version(bundle))

    return [occlusion_boundaries, next_vantage_points]


def _md(df: pd.DataFrame) -> str:
    if df.empty:
        return "_no candidate positions_"
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for row in df.itertuples(index=False):
        lines.append(
            "| " + " | ".join(f"{v:.2f}" if isinstance(v, float) else str(v) for v in row) + " |"
        )
    return "\n".join(lines)


def write_next_vantage_png(campaign: Campaign, path, *, store_url: str | None = None):
    """``next_vantage.png`` of a materialised campaign (for the exports and the report): the plan
    recomputed from the stored occlusion boundaries, integrated map and tree list."""
    from forestmap_assets.access import load_asset
    from forestmap_assets.core.exploration import exploration_figure
    from forestmap_assets.core.features.elevation import _atomic_write

    integrated = load_asset("integrated_map", campaign=campaign, store_url=store_url)
    trees = load_asset("tree_list", campaign=campaign, store_url=store_url)
    surfaces = {}
    for sid in integrated["scans"]["scan"].astype(str):
        try:
            surfaces[sid] = load_asset(
                "occlusion_boundaries", campaign=campaign, scan=sid, store_url=store_url
            )
        except FileNotFoundError:
            continue
    plan, elevation, stems = plan_from_map(
        surfaces, integrated, trees, exploration_config(campaign)
    )
    fig = exploration_figure(
        plan,
        elevation,
        stems,
        integrated["scans"],
        title=f"{campaign.name}: next vantage positions",
    )
    return _atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=100))
