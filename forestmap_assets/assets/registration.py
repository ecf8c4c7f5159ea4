"""Registration assets (thesis ch. 5; spec 6-7; men spec 4-5): ``candidate_pairs`` (which
sub-map pairs to search, and their boxes), ``pairwise_registrations`` (branch and bound over
Olson's score) and ``refined_registrations`` (fine registration on the raw points, hue-assisted
ICP or point-to-plane, used where it fits better; :mod:`forestmap_assets.core.registration.refine`).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from dagster import AssetIn, MetadataValue, Output, asset

from forestmap_assets.assets.common import (
    all_scans,
    asset_key,
    code_version,
    data_version,
    md_table,
    timed,
)
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.outputs.progress import report


def refine_settings(campaign: Campaign):
    """The campaign's ``refine`` parameter section as :class:`~forestmap_assets.params.men.RefineSettings`."""
    from forestmap_assets.params.men import RefineSettings

    values = campaign.params.refine.model_dump()
    return RefineSettings(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in values.items()})


def _cloud(table) -> tuple[np.ndarray, np.ndarray | None]:
    """Levelled points and hue (None without colour) of a stored ``range_images`` table."""
    from forestmap_assets.core.registration.colour import rgb_to_hue

    names = set(table.column_names)
    xyz = np.column_stack([table.column(c).to_numpy() for c in "xyz"]).astype(np.float64)
    hue = None
    if {"r", "g", "b"} <= names:
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
    no_prior = not campaign.pairs and any(s.a_priori is None for s in campaign.scans)
    screen = no_prior and params.registration.screening and params.registration.screen_keep > 0

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
        "keeps each scan's best registration.screen_keep partners by a stem-layout comparison "
        "(column screen_score; inferred, issue 17).",
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
            stems=stems, screen_keep=reg.screen_keep if screen else 0,
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
                "screened": bool(screen and len(submaps) > reg.screen_keep + 1),
                "table": md_table(table)}
        return Output(table, metadata=meta, data_version=data_version(table))

    @asset(
        key=key("pairwise_registrations"),
        ins={
            "candidate_pairs": AssetIn(key=key("candidate_pairs")),
            "submaps": all_scans(key("submaps")),
            "elevation_maps": all_scans(key("elevation_maps")),
            **({"cylinder_segments": all_scans(key("cylinder_segments"))} if screen else {}),
        },
        group_name="registration",
        code_version=code_version(campaign, "pairwise_registrations"),
        description="Globally optimal 4-DoF registration of every candidate pair by branch and "
        "bound over Olson's score: best cell, score-weighted cloud centre and sigma (JP eq. 6), "
        "every level's surviving cells, secondary hypotheses (thesis 5.3.3; spec 6.3-6.7); dz "
        "refined from the ground elevation maps (spec 9's proposed use). With screening, scans "
        "the accepted pairs leave unplaced are retried against their next best screened partners "
        "(inferred, issue 17).",
    )
    @timed
    def pairwise_registrations(context, candidate_pairs, submaps, elevation_maps, **raw):
        reg = params.registration
        progress = lambda m: (context.log.info(m), report(m))  # noqa: E731

        def register(table):
            return register_candidates(table, submaps or {}, reg,
                                       elevation=elevation_maps or {}, elevation_cell_m=params.elevation.cell_m,
                                       likelihood_temperature=reg.likelihood_temperature,
                                       heading_temperature=reg.heading_temperature,
                                       ground_min_sd_m=reg.ground_min_sd_m,
                                       feature_z_sd_m=reg.feature_z_sd_m, progress=progress)

        bundle = register(candidate_pairs)
        regs = bundle["registrations"]
        # issue 17: a pair centred on its screening motion that failed is searched again in the
        # no-prior box (the motion may have been wrong)
        failed = set(zip(regs.loc[regs["status"] != "accepted", "scan"], regs.loc[regs["status"] != "accepted", "reference"],
                         strict=True))
        again_mask = np.array([(a, b) in failed for a, b in zip(candidate_pairs["scan"], candidate_pairs["reference"],
                                                                   strict=True)], dtype=bool)
        screened = candidate_pairs[(candidate_pairs["source"] == "screened").to_numpy() & again_mask] \
            if len(candidate_pairs) else candidate_pairs
        widened_pairs = 0
        if len(screened):
            from forestmap_assets.core.registration.candidates import widened

            again = widened(screened, reach={sid: submap_reach(df) for sid, df in (submaps or {}).items()},
                            z_m=reg.z_m, max_xy_m=reg.max_xy_m, xy_m=reg.xy_m)
            progress(f"searching {len(again)} screened pairs again in the no-prior box")
            more = register(again)
            drop = set(zip(again["scan"], again["reference"], strict=True))
            bundle = {k: pd.concat([v[np.array([(a, b) not in drop for a, b in zip(v["scan"], v["reference"], strict=True)],
                                               dtype=bool)] if len(v) else v, more[k]], ignore_index=True)
                      for k, v in bundle.items()}
            widened_pairs = len(again)
        retried = 0
        if screen and len(submaps or {}) > reg.screen_keep + 1:  # issue 17: retry unplaced scans
            from forestmap_assets.core.registration.candidates import retry_candidates
            from forestmap_assets.core.registration.screening import stems_from_cylinders

            cylinders = raw.get("cylinder_segments") or {}
            extra = retry_candidates(
                list(submaps), candidate_pairs, bundle["registrations"],
                {sid: stems_from_cylinders(cylinders.get(sid)) for sid in submaps},
                keep=reg.screen_keep, search=(reg.xy_m, reg.z_m, reg.heading_deg),
                reach={sid: submap_reach(df) for sid, df in submaps.items()}, max_xy_m=reg.max_xy_m)
            if len(extra):
                progress(f"retrying {len(extra)} pairs of unplaced scans")
                more = register(extra)
                bundle = {k: pd.concat([v, more[k]], ignore_index=True) for k, v in bundle.items()}
                retried = len(extra)
        regs = bundle["registrations"]
        counts = regs["status"].value_counts().to_dict()
        meta = {
            "pairs": len(regs),
            "retried": retried,
            "searched_again_unscreened": widened_pairs,
            "accepted": int(counts.get("accepted", 0)),
            "rejected": int(counts.get("rejected", 0)),
            "failed": int(counts.get("failed", 0)),
            "median_seconds": float(regs["seconds"].median()) if len(regs) else 0.0,
            "registrations": md_table(regs[["scan", "reference", "dx", "dy", "dz", "dheading_deg", "sd_x", "sd_heading_deg", "status", "reason"]]),
        }
        return Output(bundle, metadata=meta, data_version=data_version(bundle))

    @asset(
        key=key("refined_registrations"),
        ins={
            "pairwise_registrations": AssetIn(key=key("pairwise_registrations")),
            "range_images": AssetIn(key=key("range_images"), metadata={"allow_missing_partitions": True}),
        },
        group_name="registration",
        code_version=code_version(campaign, "refined_registrations"),
        description="Every accepted branch-and-bound registration refined on the raw levelled "
        "points: hue-assisted ICP (4-D association x, y, z, w*hue; men spec 5) where both scans "
        "have colour, else robust point-to-plane both ways (scan onto reference and back); "
        "free to move within a trust region and used when its own fit says so (the two "
        "directions agree, the overlap is kept, the residuals fall); sigmas from the ICP "
        "Hessian and the two directions' disagreement.",
    )
    @timed
    def refined_registrations(context, pairwise_registrations, range_images):
        settings = refine_settings(campaign)
        regs = pairwise_registrations["registrations"]
        needed = set(regs.loc[regs["status"] == "accepted", "scan"]) | set(
            regs.loc[regs["status"] == "accepted", "reference"])
        clouds = {sid: _cloud(tbl) for sid, tbl in (range_images or {}).items() if sid in needed}
        bundle = refine_registrations(regs, clouds, settings, progress=lambda m: (context.log.info(m), report(m)))
        ref = bundle["refinements"]
        used = ref[ref["used"] == "refined"] if len(ref) else ref
        meta = {
            "accepted_pairs": len(ref),
            "refined": len(used),
            "methods": MetadataValue.json(ref["method"].value_counts().to_dict() if len(ref) else {}),
            "median_fit_bnb_mm": round(float(ref["fit_bnb_m"].median() * 1000), 3) if len(ref) else 0.0,
            "median_fit_refined_mm": round(float(ref["fit_refined_m"].median() * 1000), 3) if len(ref) else 0.0,
            "median_seconds": round(float(ref["seconds"].median()), 2) if len(ref) else 0.0,
            # how far the used refinements moved the coarse pose, and how well the two directions agree
            "median_moved_xy_mm": round(float(used["moved_xy_m"].median() * 1000), 2) if len(used) else 0.0,
            "median_disagree_xy_mm": round(float(used["disagree_xy_m"].median() * 1000), 2) if len(used) else 0.0,
            "not_used": MetadataValue.json({f"{r.scan}{r.reference}": r.reason for r in ref.itertuples()
                                           if r.used != "refined"}),
        }
        return Output(bundle, metadata=meta, data_version=data_version(bundle))

    return [candidate_pairs, pairwise_registrations, refined_registrations]
