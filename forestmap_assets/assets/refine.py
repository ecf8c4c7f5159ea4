"""Campaign asset ``refined_registrations``: every accepted branch-and-bound registration refined
on the raw points by hue-assisted ICP (men spec 5) where both scans have colour, else by Open3D
point-to-plane ICP, kept inside the branch-and-bound cloud's 3-sigma box, with its own
uncertainty; used instead of the branch-and-bound pose only when it improves the fit
(:mod:`forestmap_assets.core.refine`)."""

from __future__ import annotations

import numpy as np
from dagster import AssetIn, MetadataValue, Output, asset

from forestmap_assets.assets.common import asset_key, code_version, data_version
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.outputs.progress import report


def refine_settings(campaign: Campaign):
    """The campaign's ``refine`` parameter section as :class:`~..core.refine.RefineSettings`."""
    from forestmap_assets.core.registration_.refine import RefineSettings

    values = campaign.params.refine.model_dump()
    return RefineSettings(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in values.items()})


def _cloud(table) -> tuple[np.ndarray, np.ndarray | None]:
    """Levelled points and hue (None without colour) of a stored ``range_images`` table."""
    from forestmap_assets.core.registration_.colour import rgb_to_hue

    names = set(table.column_names)
    xyz = np.column_stack([table.column(c).to_numpy() for c in "xyz"]).astype(np.float64)
    hue = None
    if {"r", "g", "b"} <= names:
        rgb = np.column_stack([table.column(c).to_numpy() for c in "rgb"]).astype(np.uint8)
        hue = rgb_to_hue(rgb)  # computed once per scan, carried unchanged through the ICP
    return xyz, hue


def refine_assets(campaign: Campaign) -> list:
    from forestmap_assets.core.registration_.refine import refine_registrations

    def key(stage: str):
        return asset_key(campaign, stage)

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
        "have colour, else Open3D point-to-plane ICP; kept inside the branch-and-bound cloud's "
        "3-sigma box; sigmas from the ICP Hessian; used when it improves the fit.",
    )
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
            "not_used": MetadataValue.json({f"{r.scan}{r.reference}": r.reason for r in ref.itertuples()
                                           if r.used != "refined"}),
        }
        return Output(bundle, metadata=meta, data_version=data_version(bundle))

    return [refined_registrations]
