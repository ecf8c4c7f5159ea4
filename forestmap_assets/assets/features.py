"""Per-scan feature assets (thesis ch. 4, spec 2-5, 9): thin wrappers around ``core``."""

from __future__ import annotations

import numpy as np
import pandas as pd
from dagster import AssetIn, MetadataValue, Output, asset

from forestmap_assets.assets.common import (
    asset_key,
    circle_check_specs,
    circle_checks,
    code_version,
    cylinder_check_specs,
    cylinder_checks,
    data_version,
    picture_metadata,
    scan_check_thresholds,
    scan_partitions,
    timed,
)
from forestmap_assets.core.features.range_image import RangeImage, table_points
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.outputs.figures.range_images import (
    circle_mask,
    cylinder_outlines,
)
from forestmap_assets.outputs.figures.range_pictures import range_mask_picture


def _image(table) -> RangeImage:
    return RangeImage.from_table(table)


def _feature_image(table, params) -> RangeImage:
    """The stored range image on the scan lines of the segments and circle models
    (``segmentation.min_line_step_deg``)."""
    from forestmap_assets.core.features.segments import feature_scan_lines

    return feature_scan_lines(_image(table), params.segmentation.min_line_step_deg)


def _counts(series: pd.Series) -> dict[str, int]:
    return {str(k) if k else "valid": int(v) for k, v in series.value_counts().items()}


def feature_assets(campaign: Campaign) -> list:
    from forestmap_assets.core.features.circle_models import fit_circle_models
    from forestmap_assets.core.features.cylinders import assemble_cylinders
    from forestmap_assets.core.features.elevation import elevation_grid
    from forestmap_assets.core.features.segments import segment_mask, segment_scan_lines
    from forestmap_assets.core.registration.submaps import build_submap

    parts = scan_partitions(campaign)
    params = campaign.params
    limits = scan_check_thresholds(campaign)  # per-scan asset checks (assets/common.py)

    def key(stage: str):
        return asset_key(campaign, stage)

    def ins(*stages: str) -> dict[str, AssetIn]:
        return {s: AssetIn(key=key(s)) for s in stages}

    @asset(
        key=key("segments"),
        ins=ins("range_images"),
        partitions_def=parts,
        group_name="features",
        code_version=code_version(campaign, "segments"),
        description="Scan-line segments: blocking-object max filter, range-step runs, width "
        "window, T_out outlier gate, vertical chains (thesis 4.6.1; spec 2).",
    )
    @timed
    def segments(context, range_images):
        image = _feature_image(range_images, params)
        table = segment_scan_lines(image, params.segmentation, max_window_px=params.segmentation.max_window_px)
        meta = {
            "segments": len(table),
            "chains": int(table["chain_id"].nunique()) if len(table) else 0,
            "inlier_points": int(table["n_inliers"].sum()) if len(table) else 0,
            "segment_mask": picture_metadata(
                range_mask_picture(image, segment_mask(image, table), f"segments, scan {context.partition_key}",
                                  label="segments")
            ),
        }
        return Output(table, metadata=meta, data_version=data_version(table))

    @asset(
        key=key("circle_models"),
        ins=ins("range_images", "segments"),
        partitions_def=parts,
        group_name="features",
        code_version=code_version(campaign, "circle_models"),
        description="Circle models of every iteration's final state: projection plane through "
        "the sensor, linear least-squares circle (JP eqs. 1-4), robust refit, symmetry test, "
        "axis re-estimation (thesis 4.6.2-4.6.3; spec 3).",
        check_specs=circle_check_specs(key("circle_models")),
    )
    @timed
    def circle_models(context, range_images, segments):
        image = _feature_image(range_images, params)
        cp = params.circles
        options = ("fit", "symmetry_statistic", "stable_centre_m", "stable_radius_m", "stable_normal_deg",
                   "stable_share", "stable_gain", "max_batch_points", "engine")
        table = fit_circle_models(image, segments, cp, params.segmentation, **{k: getattr(cp, k) for k in options})
        meta: dict = {"circles": len(table)}
        if len(table):
            last = table[table["iteration"] == table["iteration"].max()]
            meta.update(
                iterations=int(table["iteration"].max()) + 1,
                valid_circles=int(last["valid"].sum()),
                rejected_circles=int((~last["valid"]).sum()),
                rejected_by=MetadataValue.json(_counts(last.loc[~last["valid"], "reject_reason"])),
                rejected_share=round(float((~last["valid"]).mean()), 4),
            )
            meta["circle_mask"] = picture_metadata(  # each row's mark as wide as its circle (Fig. 4.15c)
                range_mask_picture(image, circle_mask(image, last), f"valid circles, scan {context.partition_key}",
                                  label="valid circle models")
            )
        else:
            meta.update(valid_circles=0, rejected_circles=0, rejected_share=0.0)
        yield Output(table, metadata=meta, data_version=data_version(table))
        yield from circle_checks(table, limits)

    @asset(
        key=key("cylinder_segments"),
        ins=ins("range_images", "circle_models"),
        partitions_def=parts,
        group_name="features",
        code_version=code_version(campaign, "cylinder_segments"),
        description="Cylinder (truncated-cone) segments chained from valid circles, broken at "
        "the curvature threshold and gaps, filtered by length (thesis 4.6.3; spec 4).",
        check_specs=cylinder_check_specs(key("cylinder_segments")),
    )
    @timed
    def cylinder_segments(context, range_images, circle_models):
        final = circle_models[circle_models["iteration"] == circle_models["iteration"].max()] if len(circle_models) else circle_models
        table = assemble_cylinders(final, params.cylinders, reference=params.cylinders.curvature_reference)
        meta = {
            "cylinders": len(table),
            "total_length_m": round(float(table["length_m"].sum()), 2) if len(table) else 0.0,
            "median_radius_m": round(float(table["radius_m"].median()), 4) if len(table) else 0.0,
        }
        image = _feature_image(range_images, params)  # JP Fig. 7d: the cylinders over the range image
        meta["cylinders_picture"] = picture_metadata(
            range_mask_picture(image, None, f"cylinder segments, scan {context.partition_key}",
                              outlines=cylinder_outlines(image, table))
        )
        yield Output(table, metadata=meta, data_version=data_version(table))
        yield from cylinder_checks(table, limits)

    @asset(
        key=key("line_segments"),
        ins=ins("range_images"),
        partitions_def=parts,
        group_name="features",
        code_version=code_version(campaign, "line_segments"),
        description="Horizontal wall/ceiling border lines from the free/unknown-occupied "
        "border of a 3-D occupancy grid (thesis 4.7; spec 5). Empty in forests by default.",
    )
    @timed
    def line_segments(context, range_images):
        # Imported here: its scipy.ndimage/sparse imports cost 0.3 s on every run's start (issue 16).
        from forestmap_assets.core.features.wall_lines import extract_line_segments

        lp = params.lines
        extra = ("max_beams", "step_fraction", "hit_margin_m", "min_wall_extent_m", "top_tolerance_m",
                 "wall_depth_cells", "border_xy", "link_cells", "split_at_outliers")
        table = extract_line_segments(_image(range_images), lp, **{k: getattr(lp, k) for k in extra})
        meta = {"lines": len(table), "total_length_m": round(float(table["length_m"].sum()), 2) if len(table) else 0.0}
        return Output(table, metadata=meta, data_version=data_version(table))

    @asset(
        key=key("elevation_maps"),
        ins=ins("range_images"),
        partitions_def=parts,
        group_name="features",
        code_version=code_version(campaign, "elevation_maps"),
        description="Lowest (or highest) beam hit per 0.1 m cell in the levelled scan frame "
        "(thesis 6.x; spec 9).",
    )
    @timed
    def elevation_maps(context, range_images):
        # the stored points, not the organised image's (its float64 point image: 95 MB, 0.1 s
        # on a 2.3 M-point scan); the same points in the same order
        table = elevation_grid(table_points(range_images), params.elevation,
                               max_distance_m=params.elevation.max_distance_m)
        meta = {"cells": len(table)}
        if len(table):
            meta.update(z_min=float(np.min(table["z"])), z_max=float(np.max(table["z"])))
        return Output(table, metadata=meta, data_version=data_version(table))

    @asset(
        key=key("submaps"),
        ins=ins("cylinder_segments", "line_segments"),
        partitions_def=parts,
        group_name="registration",
        code_version=code_version(campaign, "submaps"),
        description="Registration points sampled every 0.05 m along cylinder centre lines and "
        "wall lines, levelled scan frame (thesis 5.4; spec 6.2).",
    )
    @timed
    def submaps(context, cylinder_segments, line_segments):
        table = build_submap(cylinder_segments, line_segments, params.submaps.spacing_m,
                             params.submaps.cylinder_weight)
        meta = {"points": len(table)}
        if len(table):
            meta["mean_horizontal_distance_m"] = round(float(np.hypot(table["x"], table["y"]).mean()), 2)
        return Output(table, metadata=meta, data_version=data_version(table))

    return [segments, circle_models, cylinder_segments, line_segments, elevation_maps, submaps]
