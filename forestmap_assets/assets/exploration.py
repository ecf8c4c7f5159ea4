"""Occlusion boundaries (per scan) and next vantage positions (per campaign): thin Dagster
wrappers around :mod:`forestmap_assets.core.exploration` (men_spec 3.1, 3.5-3.6, 7).

Parameters come from the campaign's ``occlusion`` and ``exploration`` sections when the parameter
model has them, else from the defaults of :class:`~forestmap_assets.params.men.OcclusionConfig`
and :class:`~forestmap_assets.params.men.ExplorationConfig`; their hash enters the code versions
(:func:`~forestmap_assets.assets.common.stage_version`).
"""

from __future__ import annotations

import pandas as pd
from dagster import AssetIn, MetadataValue, Output, asset

from forestmap_assets.assets.common import (
    asset_key,
    data_version,
    exploration_config,
    occlusion_config,
    picture_metadata,
    scan_partitions,
    stage_version,
    timed,
)
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.outputs.figures.common import Picture, png_bytes
from forestmap_assets.outputs.figures.range_pictures import range_mask_picture


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
    @timed
    def occlusion_boundaries(context, range_images):
        from forestmap_assets.core.exploration.surface import scan_surface
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
            "occlusion_boundaries": picture_metadata(
                range_mask_picture(image, mask, f"occlusion boundaries, scan {context.partition_key}",
                                  label="occlusion boundaries")
            ),
        }
        return Output(bundle, metadata=meta, data_version=data_version(bundle))

    @asset(
        key=key("next_vantage_points"),
        ins={
            "occlusion_boundaries": AssetIn(  # each scan's surface, not its boundary pixels
                key=key("occlusion_boundaries"),
                metadata={"allow_missing_partitions": True, "tables": ["surface", "info"]},
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
    @timed
    def next_vantage_points(context, occlusion_boundaries, integrated_map, tree_list):
        from forestmap_assets.core.exploration.mapped_plan import plan_from_map, plan_tables
        from forestmap_assets.outputs.figures.exploration_map import exploration_figure

        surfaces = occlusion_boundaries or {}
        if "surface" in surfaces and isinstance(surfaces["surface"], pd.DataFrame):
            # Dagster hands a single upstream partition over as the object itself
            keys = context.asset_partition_keys_for_input("occlusion_boundaries")
            surfaces = {keys[0]: surfaces} if len(keys) == 1 else {}
        plan, elevation, stems = plan_from_map(surfaces, integrated_map, tree_list, exp_cfg)
        bundle = plan_tables(plan)
        props = bundle["proposals"]
        title = f"{campaign.name}: next vantage positions"
        best = props.iloc[0] if len(props) else None
        fig = exploration_figure(
            plan,
            elevation,
            stems,
            integrated_map["scans"],
            title=title,
        )
        picture = Picture(png_bytes(fig, dpi=100), title)
        bundle["picture"] = pd.DataFrame({"png": [picture.png]})  # for the report
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
            "picture": picture_metadata(picture),
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
