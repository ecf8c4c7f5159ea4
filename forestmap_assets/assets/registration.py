"""Registration assets (thesis ch. 5; spec 6-7; men spec 4-5): ``candidate_pairs`` (which
sub-map pairs to search, and their boxes), then per pair (partitions ``<scan>__<reference>``,
:mod:`.pairs`) ``pairwise_registrations`` (branch and bound over Olson's score) and
``refined_registrations`` (fine registration on the raw points, hue-assisted ICP or
point-to-plane, used where it fits better; :mod:`forestmap_assets.core.registration.refine`),
and ``retry_pairs`` (partners for the scans left unplaced or held by a link on no loop).
"""

from __future__ import annotations

import contextlib

import numpy as np
import pandas as pd
from dagster import (
    AssetIn,
    DataVersion,
    DataVersionsByPartition,
    Output,
    asset,
    observable_source_asset,
)

from forestmap_assets.assets.common import (
    all_scans,
    asset_key,
    code_version,
    data_version,
    md_table,
    pair_partitions,
    scan_partitions,
    screened,
    timed,
)
from forestmap_assets.assets.pairs import (
    candidate_row,
    combine_pairs,
    pair_fingerprints,
    pair_rows,
    read_stored,
    scans_of,
)
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.outputs.progress import report


def _prepared_cloud(table: pd.DataFrame):
    """(whether the scan has colour, its RefineCloud) from its stored ``refine_clouds`` table
    (an empty table does not veto colour)."""
    from forestmap_assets.core.registration.two_way import RefineCloud

    return (bool(table["colour"].iloc[0]) if len(table) else True), RefineCloud.from_table(table)


def refine_settings(campaign: Campaign):
    """The campaign's ``refine`` parameter section as :class:`~forestmap_assets.params.men.RefineSettings`."""
    from forestmap_assets.params.men import RefineSettings

    values = campaign.params.refine.model_dump()
    return RefineSettings(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in values.items()})


def _has_colour(table) -> bool:
    """Whether a stored ``range_images`` table has the points' colour (``r, g, b``)."""
    return {"r", "g", "b"} <= set(table.column_names)


def _cloud(table) -> tuple[np.ndarray, np.ndarray | None]:
    """Levelled points and hue (None without colour) of a stored ``range_images`` table."""
    from forestmap_assets.core.features.range_image import table_points
    from forestmap_assets.core.registration.colour import rgb_to_hue

    xyz = table_points(table)
    hue = None
    if _has_colour(table):
        rgb = np.column_stack([table.column(c).to_numpy() for c in "rgb"]).astype(np.uint8)
        hue = rgb_to_hue(rgb)  # computed once per scan, carried unchanged through the ICP
    return xyz, hue


def registration_assets(campaign: Campaign) -> list:
    from forestmap_assets.core.registration.candidates import candidate_pairs as make_candidates
    from forestmap_assets.core.registration.pair_registrations import register_candidates
    from forestmap_assets.core.registration.refine import refine_registrations
    from forestmap_assets.core.registration.submaps import submap_reach

    params = campaign.params

    def key(stage: str):
        return asset_key(campaign, stage)

    fourier = params.registration.no_prior_method == "fourier"  # raw points for the coarse step
    # stem-layout screening of the no-prior pairs reads the cylinder segments (inferred, issue 17)
    screen = screened(campaign)

    @asset(
        key=key("candidate_pairs"),
        ins={"submaps": all_scans(key("submaps")),
             **({"range_images": all_scans(key("range_images"))} if fourier else {}),
             **({"cylinder_segments": all_scans(key("cylinder_segments"))} if screen else {})},
        group_name="registration",
        code_version=code_version(campaign, "candidate_pairs"),
        description="Which sub-map pairs to register and their search boxes: the campaign's "
        "a priori pairs, else pairs of overlapping a priori poses, else every pair with a "
        "no-prior box (full heading circle, xy box of the scans' reach) (thesis 5.4; spec 6.4); "
        "with registration.no_prior_method 'fourier', no-prior boxes centred on the Fourier coarse "
        "registration of the raw points (men spec 4). Without priors, registration.screening "
        "keeps each scan's best registration.screen_keep partners (screen_keep_large beyond "
        "screen_large_scans scans) by a stem-layout comparison (column screen_score; inferred, "
        "issue 17).",
    )
    @timed
    def candidate_pairs(context, submaps, **raw):  # raw: range_images (fourier), cylinder_segments (screening)
        submaps = submaps or {}
        reg = params.registration
        pairs = [(p.scan, p.reference, p.a_priori, p.search) for p in campaign.pairs] or None
        priors = {s.id: s.a_priori for s in campaign.scans if s.a_priori is not None}
        a_priori = priors if len(priors) == len(campaign.scans) and not pairs else None
        reach = {sid: submap_reach(df) for sid, df in submaps.items()}
        stems = None
        if screen:
            from forestmap_assets.core.registration.screening import stems_from_cylinders

            cylinders = raw.get("cylinder_segments") or {}
            stems = {sid: stems_from_cylinders(cylinders.get(sid)) for sid in submaps}
        table = make_candidates(
            list(submaps), pairs=[p for p in pairs if p[0] in submaps and p[1] in submaps] if pairs else None,
            a_priori=a_priori, search=(reg.xy_m, reg.z_m, reg.heading_deg), reach=reach,
            k_nearest=reg.k_nearest, max_distance_m=reg.max_distance_m, max_xy_m=reg.max_xy_m,
            stems=stems, screen_keep=reg.keep_for(len(submaps)) if screen else 0,
            # no_prior_method fourier centres the no-prior boxes on its own result instead
            screen_centre_min=reg.screen_centre_min if screen and not fourier else 0, screen_box=tuple(reg.screen_box),
            progress=lambda m: (context.log.info(m), report(m)),
        )
        if fourier and len(table) and (table["source"] == "no_prior").any():
            from forestmap_assets.core.features.range_image import RangeImage
            from forestmap_assets.core.registration.fourier_coarse import coarse_candidates

            images = {sid: RangeImage.from_table(t) for sid, t in (raw.get("range_images") or {}).items()}
            clouds = {sid: im.xyz[im.valid] for sid, im in images.items()}
            table = coarse_candidates(table, clouds, search=(reg.xy_m, reg.z_m, reg.heading_deg),
                                      progress=lambda m: (context.log.info(m), report(m)))
        meta = {"pairs": len(table), "source": str(table["source"].iloc[0]) if len(table) else "none",
                "screened": bool(screen and len(submaps) > reg.keep_for(len(submaps)) + 1),
                "table": md_table(table)}
        return Output(table, metadata=meta, data_version=data_version(table))

    pairs = pair_partitions(campaign)

    @observable_source_asset(
        key=key("pair_inputs"),
        partitions_def=pairs,
        group_name="registration",
        required_resource_keys={"io_manager"},
        description="What one pair step reads, observed per pair (issue 17): the hash of the "
        "pair's candidate row (box, source) and of the data versions of its two scans' submaps, "
        "elevation maps and range images; a pair becomes stale when these change.",
    )
    def pair_inputs(context) -> DataVersionsByPartition:
        fps = pair_fingerprints(campaign, context.instance, pair_rows(context.resources.io_manager, campaign))
        keys = context.partition_keys if context.has_partition_key_range else list(fps)
        return DataVersionsByPartition({k: DataVersion(fps.get(k, "missing")) for k in keys})

    def register(table, submaps, elevation, progress):
        reg = params.registration
        return register_candidates(table, submaps, reg, elevation=elevation, elevation_cell_m=params.elevation.cell_m,
                                   likelihood_temperature=reg.likelihood_temperature,
                                   heading_temperature=reg.heading_temperature,
                                   ground_min_sd_m=reg.ground_min_sd_m,
                                   feature_z_sd_m=reg.feature_z_sd_m, progress=progress)

    @asset(
        key=key("pairwise_registrations"),
        partitions_def=pairs,
        deps=[pair_inputs],
        required_resource_keys={"io_manager"},
        group_name="registration",
        code_version=code_version(campaign, "pairwise_registrations"),
        description="Globally optimal 4-DoF registration of one candidate pair (partition "
        "<scan>__<reference>) by branch and bound over Olson's score: best cell, score-weighted "
        "cloud centre and sigma (JP eq. 6), every level's surviving cells, secondary hypotheses "
        "(thesis 5.3.3; spec 6.3-6.7); dz refined from the ground elevation maps (spec 9's "
        "proposed use). A pair centred on its screening motion that fails is searched again in "
        "the no-prior box (inferred, issue 17).",
    )
    @timed
    def pairwise_registrations(context):
        io = context.resources.io_manager
        scan, ref = scans_of(campaign, context.partition_key)
        row = candidate_row(io, campaign, context.partition_key)
        submaps = {sid: t for sid in (scan, ref) if (t := read_stored(io, campaign, "submaps", sid)) is not None}
        elevation = {sid: t for sid in (scan, ref) if (t := read_stored(io, campaign, "elevation_maps", sid)) is not None}
        progress = lambda m: (context.log.info(m), report(f"[{context.partition_key}] {m}"))  # noqa: E731
        bundle = register(row, submaps, elevation, progress)
        searched_again = False
        if row["source"].iloc[0] == "screened" and bundle["registrations"]["status"].iloc[0] != "accepted":
            from forestmap_assets.core.registration.candidates import widened

            reg = params.registration
            again = widened(row, reach={sid: submap_reach(df) for sid, df in submaps.items()},
                            z_m=reg.z_m, max_xy_m=reg.max_xy_m, xy_m=reg.xy_m)
            progress("searching the screened pair again in the no-prior box")
            bundle = register(again, submaps, elevation, progress)
            searched_again = True
        regs = bundle["registrations"]
        r = regs.iloc[0]
        meta = {
            "status": str(r["status"]),
            "reason": str(r["reason"]),
            "source": str(row["source"].iloc[0]),
            "searched_again_unscreened": searched_again,
            "search_seconds": float(regs["seconds"].sum()),
            "registration": md_table(regs[["scan", "reference", "dx", "dy", "dz", "dheading_deg", "sd_x",
                                           "sd_heading_deg", "status", "reason"]]),
        }
        return Output(bundle, metadata=meta, data_version=data_version(bundle))

    @asset(
        key=key("refine_clouds"),
        partitions_def=scan_partitions(campaign),
        ins={"range_images": AssetIn(key=key("range_images"))},
        group_name="registration",
        code_version=code_version(campaign, "refine_clouds"),
        description="One scan prepared once for the fine registration of all its pairs (issues "
        "16, 17): the levelled points cropped to the refinement's range and height band, the data "
        "points (voxel refine.data_voxel_m, at most refine.max_data_points) and the model points "
        "(voxel refine.two_way_model_voxel_m) with normals oriented to the sensor (spec 3.3); "
        "under a wide first-return beam without its mixed pixels (refine.mixed_pixel_jump_m).",
    )
    @timed
    def refine_clouds(context, range_images):
        from forestmap_assets.core.features.range_image import table_azimuth_step
        from forestmap_assets.core.registration.two_way import RefineCloud

        colour = _has_colour(range_images)  # the pair's method depends on it
        step_rad = table_azimuth_step(range_images)[0]
        s = refine_settings(campaign)
        xyz = [range_images.column(c).to_numpy() for c in "xyz"]
        mixed = np.zeros(range_images.num_rows, dtype=bool)
        if s.wide_beam and s.mixed_pixel_jump_m is not None:
            from forestmap_assets.core.registration.mixed_pixels import table_silhouette_band

            mixed = table_silhouette_band(range_images, s.beam_exit_m, 1e-3 * s.beam_divergence_mrad,
                                          s.mixed_pixel_jump_m)
            if mixed.any():
                xyz = [v[~mixed] for v in xyz]
        cloud = RefineCloud.from_columns(*xyz, s, step_rad)
        table = cloud.to_table(colour=colour)
        meta = {"data_points": int((table["role"] == "data").sum()),
                "model_points": int((table["role"] == "model").sum()), "colour": colour,
                "mixed_pixels_left_out": int(mixed.sum())}
        return Output(table, metadata=meta, data_version=data_version(table))

    @asset(
        key=key("refined_registrations"),
        partitions_def=pairs,
        ins={"pairwise_registrations": AssetIn(key=key("pairwise_registrations"))},
        deps=[pair_inputs],
        required_resource_keys={"io_manager"},
        group_name="registration",
        code_version=code_version(campaign, "refined_registrations"),
        description="One pair's accepted branch-and-bound registration refined on the raw "
        "levelled points: hue-assisted ICP (4-D association x, y, z, w*hue; men spec 5) where "
        "both scans have colour, else robust point-to-plane both ways (scan onto reference and "
        "back); free to move within a trust region and used when its own fit says so (the two "
        "directions agree, the overlap is kept, the residuals fall); sigmas from the ICP "
        "Hessian and the two directions' disagreement.",
    )
    @timed
    def refined_registrations(context, pairwise_registrations):
        settings = refine_settings(campaign)
        regs = pairwise_registrations["registrations"]
        io = context.resources.io_manager
        clouds, prepared = {}, {}
        if (regs["status"] == "accepted").any():
            from forestmap_assets.core.registration.refine import resolved_method

            ids = scans_of(campaign, context.partition_key)
            got = {}  # per scan: (colour, RefineCloud), kept by this worker for the scan's next pairs
            for sid in ids:
                with contextlib.suppress(FileNotFoundError):
                    got[sid] = io.derived_from_stored(list(asset_key(campaign, "refine_clouds").path), sid,
                                                      _prepared_cloud)
            colour = len(got) == 2 and all(c for c, _ in got.values())
            if len(got) == 2 and settings.guard == "fit" and resolved_method(settings, colour) == "point_to_plane":
                prepared = {sid: cloud for sid, (_, cloud) in got.items()}
                clouds = {sid: (None, None) for sid in got}  # the prepared clouds are enough
            else:  # HICP on colour, or the box guard: the raw points
                for sid in ids:
                    table = read_stored(io, campaign, "range_images", sid)
                    if table is not None:
                        clouds[sid] = _cloud(table)
        progress = lambda m: (context.log.info(m), report(f"[{context.partition_key}] {m}"))  # noqa: E731
        bundle = refine_registrations(regs, clouds, settings, progress=progress, prepared=prepared)
        ref = bundle["refinements"]
        meta = {
            "used": str(ref["used"].iloc[0]) if len(ref) else "not accepted",
            "method": str(ref["method"].iloc[0]) if len(ref) else "",
            "reason": str(ref["reason"].iloc[0]) if len(ref) else "",
        }
        if len(ref) and ref["used"].iloc[0] == "refined":
            # how far the refinement moved the coarse pose, and how well the two directions agree
            meta["moved_xy_mm"] = round(float(ref["moved_xy_m"].iloc[0] * 1000), 2)
            meta["disagree_xy_mm"] = round(float(ref["disagree_xy_m"].iloc[0] * 1000), 2)
        if len(ref):
            meta["fit_bnb_mm"] = round(float(ref["fit_bnb_m"].iloc[0] * 1000), 3)
            meta["fit_refined_mm"] = round(float(ref["fit_refined_m"].iloc[0] * 1000), 3)
        return Output(bundle, metadata=meta, data_version=data_version(bundle))

    out = [candidate_pairs, pair_inputs, pairwise_registrations, refine_clouds, refined_registrations]
    if not screen:
        return out

    @asset(
        key=key("retry_pairs"),
        ins={"candidate_pairs": AssetIn(key=key("candidate_pairs")),
             "pairwise_registrations": AssetIn(key=key("pairwise_registrations"),
                                               metadata={"allow_missing_partitions": True})},
        deps=[key("submaps"), key("cylinder_segments")],  # read only when a scan is weakly held
        required_resource_keys={"io_manager"},
        group_name="registration",
        code_version=code_version(campaign, "retry_pairs"),
        description="Pairs for the scans the candidate pairs left unplaced (inferred, issue 17): "
        "every scan outside the largest group the accepted candidate pairs link is screened "
        "against that group again and its best partners (as many as candidate_pairs keeps) not yet "
        "searched are added as pairs with the no-prior box; when every scan is placed, the best "
        "such pairs across each accepted link that lies on no loop (issue 16: a link no residual "
        "could check, left by a failed pair).",
    )
    @timed
    def retry_pairs(context, candidate_pairs, pairwise_registrations):
        from forestmap_assets.core.registration.candidates import (
            no_candidates,
            retry_candidates,
            weak_links,
        )
        from forestmap_assets.core.registration.screening import stems_from_cylinders

        reg = params.registration
        regs = combine_pairs(pairwise_registrations).get("registrations", pd.DataFrame(columns=["scan", "reference", "status"]))
        primary = set(zip(candidate_pairs["scan"], candidate_pairs["reference"], strict=True))
        regs = regs[np.array([(a, b) in primary for a, b in zip(regs["scan"], regs["reference"], strict=True)], dtype=bool)]
        extra = no_candidates()
        # the scans' sub-maps and cylinders are read only when a scan is left unplaced or held by
        # a link on no loop
        if weak_links(campaign.scan_ids, regs):
            io = context.resources.io_manager
            submaps = {sid: t for sid in campaign.scan_ids if (t := read_stored(io, campaign, "submaps", sid)) is not None}
            keep = reg.keep_for(len(submaps))
            if len(submaps) > keep + 1:
                cylinders = {sid: read_stored(io, campaign, "cylinder_segments", sid) for sid in submaps}
                extra = retry_candidates(
                    [s for s in campaign.scan_ids if s in submaps], candidate_pairs, regs,
                    {sid: stems_from_cylinders(cylinders[sid]) for sid in submaps},
                    keep=keep, search=(reg.xy_m, reg.z_m, reg.heading_deg),
                    reach={sid: submap_reach(df) for sid, df in submaps.items()}, max_xy_m=reg.max_xy_m)
                extra["source"] = "retry"
        if len(extra):
            context.log.info(f"retrying {len(extra)} pairs of unplaced scans or links on no loop")
        meta = {"pairs": len(extra), "table": md_table(extra)}
        return Output(extra, metadata=meta, data_version=data_version(extra))

    return [*out, retry_pairs]
