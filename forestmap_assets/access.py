"""Reading stored asset outputs outside Dagster (notebooks, exports)."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
from upath import UPath

from forestmap_assets.assets.common import PAIR_STAGES
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io.campaign import Campaign, load_campaign
from forestmap_assets.io.store import default_store_url, read_bundle, read_table


def _campaign_key(campaign: str | Path | Campaign) -> str:
    if isinstance(campaign, Campaign):
        return campaign.key
    path = Path(campaign).expanduser()
    if (path / "campaign.yaml").is_file():
        return load_campaign(path).key
    return str(campaign)


def load_asset(name: str, *, campaign: str | Path | Campaign, scan: str | None = None, store_url: str | None = None,
               columns: list[str] | None = None):
    """One stored asset output: a DataFrame, a dict of DataFrames (bundles) or a RangeImage.

    ``campaign`` is a campaign folder, a :class:`Campaign` or its key; ``scan`` selects the
    partition of a per-scan asset (or a pair, ``<scan>__<reference>``, of a per-pair asset;
    without it a per-pair asset's pairs come as one bundle). ``columns``: only those of these
    columns that a stored table has, as a DataFrame (a range image's: its valid pixels,
    row-major, e.g. the levelled ``x, y, z``, float32). Raises ``FileNotFoundError`` (one line) when the asset has
    not been materialised.
    """
    base = UPath(store_url or default_store_url()) / _campaign_key(campaign) / name
    stem = base / scan if scan is not None else base
    table_path = stem.with_name(stem.name + ".parquet")
    bundle_path = stem.with_name(stem.name + ".bundle")
    if table_path.exists():
        if columns is not None:
            with table_path.open("rb") as f:
                stored = set(pq.read_schema(f).names)
            return read_table(table_path, [c for c in columns if c in stored]).to_pandas()
        table: pa.Table = read_table(table_path)
        if (table.schema.metadata or {}).get(b"forestmap.kind") == b"range_image":
            return RangeImage.from_table(table)
        return table.to_pandas()
    if bundle_path.exists():
        return read_bundle(bundle_path)
    if scan is None and name in PAIR_STAGES:  # every pair partition (issue 17)
        from forestmap_assets.assets.pairs import combine_pairs

        parts = {p.name[: -len(".bundle")]: read_bundle(p) for p in base.iterdir()
                 if p.name.endswith(".bundle")} if base.is_dir() else {}
        if parts or (base.parent / "candidate_pairs.parquet").exists():  # none searched: {}
            return combine_pairs(parts)
    what = f"{name}[{scan}]" if scan is not None else name
    raise FileNotFoundError(f"{what} of campaign {_campaign_key(campaign)!r} is not in the store {base.parent} (run `forestmap run` first)")
