"""Ingest: scan files (observed) and levelled organised range images (spec 1.2)."""

from __future__ import annotations

import numpy as np
from dagster import (
    DataVersion,
    DataVersionsByPartition,
    Failure,
    MetadataValue,
    Output,
    asset,
    observable_source_asset,
)

from forestmap_assets.assets.common import (
    asset_key,
    code_version,
    data_version,
    picture_metadata,
    scan_partitions,
    timed,
)
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.io.projection import fill_ratio
from forestmap_assets.outputs.figures.range_pictures import range_mask_picture


def read_campaign_scan(campaign: Campaign, scan_id: str) -> RangeImage:
    """Read one scan of the campaign as a levelled organised range image, on the grid of params
    section ``range_images``: an unorganised cloud projected at the sensor's step (campaign.yaml
    ``sensor``) or one estimated to fill the image, an organised scan finer than
    ``min_step_deg`` thinned to it (issue 18, big scans)."""
    from forestmap_assets.io.readers import read_scan
    from forestmap_assets.io.readers_common import ProjectionSettings, coarsen_range_image

    try:
        entry = campaign.scan(scan_id)
    except KeyError:
        raise ValueError(f"scan {scan_id!r} is not listed in {campaign.root / 'campaign.yaml'}") from None
    p = campaign.params.range_images
    settings = ProjectionSettings(campaign.angular_step_deg, p.min_step_deg, p.min_fill,
                                  p.bridge_gaps)
    image = read_scan(entry.path, angular_step_deg=settings, tilt_deg=entry.tilt_deg,
                      scan_index=entry.e57_scan, to_scanner=entry.to_scanner)
    return coarsen_range_image(image, p.min_step_deg)


def ingest_assets(campaign: Campaign) -> list:
    parts = scan_partitions(campaign)

    @observable_source_asset(
        key=asset_key(campaign, "scan_files"),
        partitions_def=parts,
        group_name="ingest",
        description="The campaign's scan files; observed by content hash so a changed file "
        "makes its range image stale (DESIGN.md section 2).",
    )
    def scan_files(context) -> DataVersionsByPartition:
        keys = context.partition_keys if context.has_partition_key_range else campaign.scan_ids
        versions = {}
        for sid in keys:
            try:
                versions[sid] = DataVersion(campaign.scan_fingerprint(sid))
            except (KeyError, OSError):
                versions[sid] = DataVersion("missing")
        return DataVersionsByPartition(versions)

    @asset(
        key=asset_key(campaign, "range_images"),
        partitions_def=parts,
        deps=[scan_files],
        group_name="ingest",
        code_version=code_version(campaign, "range_images"),
        description="Organised range image of one scan, levelled by its measured roll/pitch "
        "(forsman spec 1.2): one row per valid pixel (row, col, range, levelled x y z, colour).",
    )
    @timed
    def range_images(context):
        sid = context.partition_key
        try:
            image = read_campaign_scan(campaign, sid)
        except (ValueError, OSError) as exc:
            raise Failure(description=str(exc).splitlines()[0]) from None
        table = image.to_table()
        rows, cols = image.shape
        valid = int(image.valid.sum())
        finite = image.range_m[image.valid]
        meta = {
            "rows": rows,
            "cols": cols,
            "valid_pixels": valid,
            "valid_share": round(valid / max(rows * cols, 1), 4),
            # share of the pixels inside the scanned region holding a return (io/projection.py)
            "fill_ratio": round(fill_ratio(image.valid), 4),
            "azimuth_step_deg": round(image.azimuth_step_deg, 5),
            "elevation_step_deg": round(image.elevation_step_deg, 5),
            "max_range_m": float(np.max(finite)) if valid else 0.0,
            "has_rgb": image.rgb is not None,
            "tilt_deg": MetadataValue.json(list(image.tilt_deg)),
            "range_image": picture_metadata(range_mask_picture(image, None, f"range image, scan {sid}")),
        }
        return Output(table, metadata=meta, data_version=data_version(table))

    return [scan_files, range_images]
