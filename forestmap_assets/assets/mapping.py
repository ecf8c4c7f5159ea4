"""Map assets (thesis ch. 6-7; spec 8-10): ``optimal_map`` (links admitted one at a time,
Lu-Milios minimum-variance poses), ``residual_checks``, ``scan_tilts`` (the scans' tilts from
their shared stems), ``integrated_map`` (cylinders and elevation in the global frame) and
``tree_list``."""

from __future__ import annotations

import numpy as np
import pandas as pd
from dagster import (
    AssetCheckResult,
    AssetCheckSeverity,
    AssetCheckSpec,
    AssetIn,
    MetadataValue,
    Output,
    asset,
)

from forestmap_assets.assets.common import (
    all_scans,
    asset_key,
    code_version,
    data_version,
    md_table,
    picture_metadata,
    png_metadata,
    screened,
    timed,
)
from forestmap_assets.assets.pairs import combine_pairs
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.outputs.figures.elevation_pictures import elevation_picture
from forestmap_assets.outputs.figures.mapping import dbh_histogram, network_figure

POSE_COLUMNS = ["scan", "x", "y", "z", "heading_deg", "sd_x", "sd_y", "sd_z", "sd_heading_deg", "registered"]


def poses_table(campaign: Campaign, solution_poses: pd.DataFrame | None) -> pd.DataFrame:
    """``poses.csv`` rows for every scan of the campaign; unplaced scans have empty poses."""
    from forestmap_assets.core.geometry import wrap_deg

    out = pd.DataFrame({"scan": campaign.scan_ids})
    if solution_poses is not None and len(solution_poses):
        placed = solution_poses[solution_poses["registered"].astype(bool)].drop(columns=["registered"])
        out = out.merge(placed, on="scan", how="left")
    for c in POSE_COLUMNS[1:-1]:
        if c not in out:
            out[c] = np.nan
    out["registered"] = out["x"].notna()
    out["heading_deg"] = np.where(out["registered"], wrap_deg(out["heading_deg"].fillna(0.0).to_numpy(float)), np.nan)
    return out[POSE_COLUMNS]


def mapping_assets(campaign: Campaign) -> list:
    from forestmap_assets.core.features.elevation import (
        elevation_from_table,
        elevation_to_table,
        merge_elevation,
    )
    from forestmap_assets.core.mapping.levelling import widen_levelled_links
    from forestmap_assets.core.mapping.link_selection import select_links
    from forestmap_assets.core.mapping.objective_scale import (
        gap_scale,
        objective_scale,
        scale_floor,
        scale_sd,
        stem_gap,
        take_out,
        widen_links,
    )
    from forestmap_assets.core.mapping.optimal_map import RHO_COLUMNS
    from forestmap_assets.core.mapping.residuals import variance_factors, with_variance_factors
    from forestmap_assets.core.mapping.slice_splats import scan_splats, shared_scan_correlations
    from forestmap_assets.core.mapping.trees import beam_options, cylinders_to_global, merge_trees

    params = campaign.params
    reference = campaign.scan_ids[0]

    def key(stage: str):
        return asset_key(campaign, stage)

    @asset(
        key=key("optimal_map"),
        ins={"refined_registrations": AssetIn(key=key("refined_registrations"),
                                              metadata={"allow_missing_partitions": True})},
        # the pair lists decide which pair partitions exist (a pair dropped from them leaves the map)
        deps=[key("candidate_pairs"), *([key("retry_pairs")] if screened(campaign) else [])],
        group_name="map",
        code_version=code_version(campaign, "optimal_map"),
        description="Global poses and covariances: links admitted one at a time (most confident "
        "first, spanning tree then loop closures tested by the residual rule), Lu-Milios "
        "minimum-variance estimate (thesis 3.2.2, 6.4, 7.1; spec 8); with mapping.method "
        "'chain', the thesis's incremental chaining with summed variances (6.2; spec 8.3).",
    )
    @timed
    def optimal_map(context, refined_registrations):
        # every pair partition: branch and bound, refined where it fits better
        pairs = combine_pairs(refined_registrations)
        regs = pairs.get("registrations", pd.DataFrame(columns=["status"]))
        accepted = regs[regs["status"] == "accepted"].reset_index(drop=True)
        mp = params.mapping
        scale, scale_t, scale_n = objective_scale(accepted, mp.objective_scale_t)  # the objectives'
        accepted, sigma_scale = take_out(accepted, scale, scale_t, mp.objective_scale_correct_t)
        accepted = widen_links(accepted, sigma_scale)
        gap, gap_n = stem_gap(accepted, pairs.get("refinements"))
        levelled = {e.id: e.tilt_sd_deg for e in campaign.scans if e.levelled_from is not None}
        accepted = widen_levelled_links(accepted, levelled, mp.levelling_sd_floor_deg)
        if accepted.empty:  # only the reference scan is placed: it defines the frame
            ref_pose = pd.DataFrame([{c: 0.0 for c in POSE_COLUMNS[1:-1]}]).assign(scan=reference, registered=True)
            poses = poses_table(campaign, ref_pose)
            links = accepted.assign(status=pd.Series(dtype=object), role=pd.Series(dtype=object), step=pd.Series(dtype=int))
            residuals = pd.DataFrame(columns=["scan", "reference", "ex", "ey", "ez", "eheading_deg", "rx", "ry", "rz", "rheading", "verdict"])
        elif mp.method == "chain":  # the thesis's parking lot / corridor maps (spec 8.3)
            from forestmap_assets.core.mapping.chained_map import chained_map

            chained = chained_map(accepted, campaign.scan_ids, link_choice=mp.chain_link_choice,
                                  covariance=mp.covariance, residual_sigmas=mp.residual_sigmas,
                                  z_residual_sigmas=mp.z_residual_sigmas)
            poses = poses_table(campaign, chained.poses)
            links, residuals = chained.links, chained.residuals
        else:
            wide = params.refine.beam_divergence_mrad > params.refine.wide_beam_min_divergence_mrad
            accepted[list(RHO_COLUMNS)] = shared_scan_correlations(
                accepted, pairs.get("refinements"), mp.scan_correlation, mp.refined_scan_correlation,
                mp.footprint_free_z_correlation, wide)
            sel = select_links(accepted, reference, scans=campaign.scan_ids, confidence="confidence",
                               covariance=mp.covariance, iterate=mp.iterate,
                               residual_sigmas=mp.residual_sigmas, z_residual_sigmas=mp.z_residual_sigmas,
                               scan_correlation=mp.scan_correlation)
            poses = poses_table(campaign, sel.solution.poses)
            links = sel.links
            residuals = sel.solution.residuals
        factors = variance_factors(residuals, int(poses["registered"].sum()), mp.variance_factor_min_dof)
        rp = params.refine
        floor = scale_floor(mp.scale_sd_floor, mp.wide_beam_scale_sd_floor, rp.beam_divergence_mrad,
                            rp.wide_beam_min_divergence_mrad)
        poses = scale_sd(with_variance_factors(poses, factors), max(abs(sigma_scale), gap_scale(gap, mp.stem_gap_share, mp.stem_gap_free)), floor)
        splats = scan_splats(pairs.get("refinements"))  # the tree list takes them back from the slices
        poses["splat_m"] = poses["scan"].astype(str).map(splats).fillna(0.0).astype(float)
        bundle = {"poses": poses, "links": links, "residuals": residuals}
        meta = {
            "objective_scale_mm_per_m": round(1000 * scale, 4),
            "objective_scale_t": round(float(scale_t), 2) if np.isfinite(scale_t) else str(scale_t),
            "objective_scale_links": scale_n,
            "objective_scale_taken_out": bool(scale) and not sigma_scale,
            "stem_gap_mm_per_m": round(1000 * gap, 4),
            "stem_gap_links": gap_n,
            "variance_factors": MetadataValue.json([round(float(f), 3) for f in factors]),
            "registered": int(poses["registered"].sum()),
            "unregistered": MetadataValue.json(poses.loc[~poses["registered"], "scan"].tolist()),
            "admitted_links": int((links["status"] == "admitted").sum()) if len(links) else 0,
            "rejected_links": int((links["status"] == "rejected").sum()) if len(links) else 0,
            "poses": md_table(poses),
            "network": png_metadata(network_figure(poses, regs, links, title=f"{campaign.name}: registration network")),
        }
        return Output(bundle, metadata=meta, data_version=data_version(bundle))

    @asset(
        key=key("residual_checks"),
        ins={"optimal_map": AssetIn(key=key("optimal_map"))},
        group_name="map",
        code_version=code_version(campaign, "residual_checks"),
        description="Residuals of eq. (11) of every admitted observation, normalised by its "
        "sigma, with verdicts ok / inconsistent (thesis 6.4, 7.1; spec 8.5).",
        check_specs=[
            AssetCheckSpec("admitted_links_consistent", asset=key("residual_checks"), blocking=True,
                           description="Every admitted observation passes the residual test (3 sigma x/y/heading, 8 sigma z)."),
            AssetCheckSpec("every_scan_registered", asset=key("residual_checks"),
                           description="Every scan is placed by an admitted link, or explicitly reported as not registered."),
        ],
    )
    @timed
    def residual_checks(context, optimal_map):
        residuals = optimal_map["residuals"].reset_index(drop=True)
        poses = optimal_map["poses"]
        bad = residuals[residuals["verdict"] != "ok"] if len(residuals) else residuals
        unplaced = poses.loc[~poses["registered"].astype(bool), "scan"].tolist()
        yield Output(residuals, metadata={"observations": len(residuals), "inconsistent": len(bad),
                                          "residuals": md_table(residuals)},
                     data_version=data_version(residuals))
        yield AssetCheckResult(
            check_name="admitted_links_consistent", passed=bad.empty, severity=AssetCheckSeverity.ERROR,
            metadata={"inconsistent": MetadataValue.json([f"{r.scan}{r.reference}" for r in bad.itertuples()])},
        )
        yield AssetCheckResult(
            check_name="every_scan_registered", passed=not unplaced, severity=AssetCheckSeverity.WARN,
            metadata={"not_registered": MetadataValue.json(unplaced)},
        )

    mp = params.mapping

    @asset(
        key=key("scan_tilts"),
        ins={"optimal_map": AssetIn(key=key("optimal_map")),
             "cylinder_segments": all_scans(key("cylinder_segments"),
                                           ["x0", "y0", "z0", "x1", "y1", "z1", "radius_m", "n_circles"])},
        group_name="map",
        code_version=code_version(campaign, "scan_tilts"),
        description="Each scan's roll and pitch against the reference scan, from the lean of the "
        "stems it shares with the scans registered to it (beyond the thesis, which levels scans by "
        "their measured tilt; core/mapping/levelling.py): level is true where a scan is tilted by "
        "mapping.levelling_min_tilt_deg and levelling_sigmas sd or more; forestmap run then writes "
        "the estimates to the campaign's levelling.yaml and runs again with the scans levelled.",
    )
    @timed
    def scan_tilts(context, optimal_map, cylinder_segments):
        from forestmap_assets.core.mapping.levelling import link_tilt, needs_levelling, solve_tilts
        from forestmap_assets.core.mapping.stem_groups import group_stems

        links = optimal_map["links"]
        cyl = cylinder_segments or {}
        stems: dict[str, np.ndarray] = {}  # each reference scan's stems, grouped once
        rows = []
        for r in links.itertuples():
            if r.scan in cyl and r.reference in cyl:
                if r.reference not in stems:
                    stems[r.reference] = group_stems(cyl[r.reference])
                rows.append({"scan": r.scan, "reference": r.reference, "dheading_deg": r.dheading_deg,
                             **link_tilt(cyl[r.scan], cyl[r.reference], (r.dx, r.dy, r.dz, r.dheading_deg),
                                         ref_stems=stems[r.reference])})
        measured = pd.DataFrame(rows, columns=["scan", "reference", "dheading_deg", "tilt_x_deg", "tilt_y_deg",
                                               "sd_tilt_deg", "n_tilt"])
        tilts = solve_tilts(measured, campaign.scan_ids, reference)
        tilted = needs_levelling(tilts, mp.levelling_min_tilt_deg, mp.levelling_sigmas) if mp.levelling else tilts.iloc[:0]
        tilts["level"] = tilts["scan"].isin(tilted["scan"])
        size = np.hypot(tilts["roll_deg"], tilts["pitch_deg"])
        meta = {"largest_tilt_deg": round(float(size.max()), 4) if size.notna().any() else 0.0,
                "to_level": MetadataValue.json(tilted["scan"].tolist()),
                "tilts": md_table(tilts, ".4f"), "pairs": md_table(measured, ".4f")}
        return Output(tilts, metadata=meta, data_version=data_version(tilts))

    @asset(
        key=key("integrated_map"),
        ins={
            "optimal_map": AssetIn(key=key("optimal_map")),
            "cylinder_segments": all_scans(key("cylinder_segments")),
            "elevation_maps": all_scans(key("elevation_maps")),
        },
        deps=[key("residual_checks")],  # built only from a map that passed the residual test
        group_name="map",
        code_version=code_version(campaign, "integrated_map"),
        description="All cylinder segments in the global frame and the merged lowest-hit "
        "elevation map of the registered scans (thesis 6.4, Figs 6.11-6.13; spec 9).",
    )
    @timed
    def integrated_map(context, optimal_map, cylinder_segments, elevation_maps):
        poses = optimal_map["poses"]
        placed = poses[poses["registered"].astype(bool)]
        pose = {r.scan: (r.x, r.y, r.z, r.heading_deg) for r in placed.itertuples()}
        cylinders = cylinders_to_global(cylinder_segments or {}, pose)
        grids = [(tbl, pose[sid]) for sid, tbl in (elevation_maps or {}).items() if sid in pose and len(tbl)]
        ep = params.elevation
        grid = merge_elevation(grids, ep.cell_m, ep.mode, supersample=ep.supersample) if grids else None
        elevation = elevation_to_table(grid) if grid is not None else elevation_to_table(elevation_from_table(pd.DataFrame()))
        bundle = {"cylinders": cylinders, "elevation": elevation, "scans": placed.reset_index(drop=True)}
        meta = {"cylinders": len(cylinders), "elevation_cells": len(elevation), "scans": len(placed)}
        if grid is not None:
            meta["elevation_map"] = picture_metadata(elevation_picture(grid, placed, f"{campaign.name}: merged elevation map"))
        return Output(bundle, metadata=meta, data_version=data_version(bundle))

    tp = params.trees
    by_slice = tp.dbh_method == "slice"
    image_cols = ["row", "col", "range_m"] if tp.calipers else []  # the silhouettes' edges

    @asset(
        key=key("tree_list"),
        ins={"integrated_map": AssetIn(key=key("integrated_map")),
             **({"range_images": all_scans(key("range_images"), ["x", "y", "z"] + image_cols)} if by_slice else {})},
        group_name="map",
        code_version=code_version(campaign, "tree_list"),
        description="One row per physical tree, cylinders of all scans merged: stem position at "
        "breast height (1.3 m above the ground under the stem), ground z, DBH, and dbh_note: how "
        "a DBH not measured at breast height was obtained or why there is none (forestmap's step "
        "beyond the thesis; core/mapping/trees.py). With trees.dbh_method 'slice' the DBH is the "
        "mean diameter of an outline fitted to the registered points of every scan in a slice "
        "at breast height, the cylinders' where the slice has too few points "
        "(core/mapping/stem_slices.py); where the campaign names its beam, blended with the "
        "silhouettes' widths (stem_calipers.py) and with one outline fitted to the slice and "
        "the silhouette sides together (stem_outline.py).",
    )
    @timed
    def tree_list(context, integrated_map, **raw):  # raw: {"range_images": ...} with the slice DBH
        grid = elevation_from_table(integrated_map["elevation"])
        trees, tree_of_cyl = merge_trees(integrated_map["cylinders"], grid, min_top_m=tp.understorey_top_m or None,
                                         **beam_options(tp.beam_exit_m, 1e-3 * tp.beam_divergence_mrad))
        from_slice = from_calipers = from_outline = 0
        widening = None
        if by_slice:
            from forestmap_assets.core.mapping.slice_splats import splat_steps
            from forestmap_assets.core.mapping.stem_slices import slice_clouds
            from forestmap_assets.core.mapping.tree_dbh import tree_dbh

            clouds = slice_clouds(raw.get("range_images") or {}, integrated_map["scans"], trees, tp)
            splats = splat_steps(integrated_map["scans"], raw.get("range_images") or {})
            trees, fits = tree_dbh(trees, integrated_map["cylinders"], tree_of_cyl, clouds, integrated_map["scans"],
                                   tp, images=raw.get("range_images") if tp.calipers else None, splats=splats)
            from_calipers = int((fits["caliper_scans"] > 0).sum()) if tp.calipers else 0
            from_outline = int(fits["outline_dbh_m"].notna().sum()) if "outline_dbh_m" in fits else 0
            from_slice = int((fits["reason"] == "").sum())
            if "caliper_widening_m" in fits and len(fits):
                widening = {"silhouette_widening_m": round(float(fits["caliper_widening_m"].iat[0]), 4)}
                if np.isfinite(far := float(fits["caliper_widening_far_m"].iat[0])):
                    widening["silhouette_widening_far_m"] = round(far, 4)
        dbh = trees["dbh_m"].dropna()
        noted = trees["dbh_note"].astype(bool)
        meta = {"trees": len(trees), "with_dbh": int(len(dbh)), "dbh_from_slice": from_slice,
                "dbh_with_silhouette_widths": from_calipers, "dbh_with_outline": from_outline,
                "dbh_with_note": int((noted & trees["dbh_m"].notna()).sum()),
                **(widening or {}),
                "median_dbh_m": round(float(dbh.median()), 3) if len(dbh) else 0.0,
                "seen_from_2_or_more_scans": int((trees["n_scans"] >= 2).sum()),
                "dbh_histogram": png_metadata(dbh_histogram(trees, title=f"{campaign.name}: DBH of {len(dbh)} trees"))}
        return Output(trees, metadata=meta, data_version=data_version(trees))

    return [optimal_map, residual_checks, scan_tilts, integrated_map, tree_list]
