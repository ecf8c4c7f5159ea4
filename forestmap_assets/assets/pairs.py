"""Pair partitions (issue 17): one partition of ``pairwise_registrations`` and
``refined_registrations`` per searched pair, keys ``<scan>__<reference>``.

Which pairs exist is decided by the campaign-level ``candidate_pairs`` (and ``retry_pairs``),
as ``campaign.yaml`` decides which scans exist; the orchestration keeps the dynamic partition
set equal to their rows. A pair step reads only its own two scans' stored outputs and its own
candidate row. What it reads is summed up in a fingerprint, observed as the data version of
the pair partition of the ``pair_inputs`` source asset: a pair becomes stale exactly when its
own inputs change, so adding a scan runs only the pairs that involve it, and changing a
``registration`` parameter (a new code version) runs every pair and nothing upstream.
"""

from __future__ import annotations

import hashlib

import pandas as pd
from dagster import AssetKey, DagsterInstance

from forestmap_assets.assets.common import asset_key, pair_key, split_pair_key
from forestmap_assets.io.campaign import Campaign

# The per-scan outputs a pair step reads, for each of its two scans.
PAIR_SCAN_INPUTS: tuple[str, ...] = ("submaps", "elevation_maps", "range_images", "refine_clouds")

# The campaign-level tables that list pairs and their search boxes.
PAIR_LISTS: tuple[str, ...] = ("candidate_pairs", "retry_pairs")


def read_stored(io_manager, campaign: Campaign, stage: str, partition: str | None = None):
    """A stored asset output (one partition), ``None`` when it was never materialised."""
    try:
        return io_manager.read_stored(list(asset_key(campaign, stage).path), partition)
    except FileNotFoundError:
        return None


def pair_rows(io_manager, campaign: Campaign) -> pd.DataFrame:
    """Every pair to search with its box: the stored ``candidate_pairs`` rows, then the
    ``retry_pairs`` rows (column ``pair`` holds the partition key)."""
    tables = [t for t in (read_stored(io_manager, campaign, s) for s in PAIR_LISTS) if t is not None and len(t)]
    if not tables:
        return pd.DataFrame(columns=["scan", "reference", "pair"])
    rows = pd.concat(tables, ignore_index=True)
    rows["pair"] = [pair_key(a, b) for a, b in zip(rows["scan"], rows["reference"], strict=True)]
    return rows.drop_duplicates("pair", keep="first").reset_index(drop=True)


def candidate_row(io_manager, campaign: Campaign, key: str) -> pd.DataFrame:
    """The one-row candidate table of pair ``key`` (ValueError when no list holds it)."""
    rows = pair_rows(io_manager, campaign)
    row = rows[rows["pair"] == key].drop(columns="pair")
    if row.empty:
        raise ValueError(f"pair {key!r} is in neither candidate_pairs nor retry_pairs of {campaign.name!r}")
    return row.reset_index(drop=True)


def scans_of(campaign: Campaign, key: str) -> tuple[str, str]:
    return split_pair_key(key, campaign.scan_ids)


def _row_digest(row: pd.Series) -> str:
    values = [f"{c}={row[c]!r}" for c in sorted(row.index) if c != "pair"]
    return hashlib.sha256("|".join(values).encode()).hexdigest()[:16]


def latest_data_version(instance: DagsterInstance, key: AssetKey, partition: str | None,
                        source: bool = False) -> str:
    """Data version of the newest materialisation (``source``: observation) of one partition
    (``missing`` if none)."""
    from dagster._core.definitions.data_version import extract_data_version_from_entry

    record = instance.get_latest_data_version_record(key, source, partition)
    version = extract_data_version_from_entry(record.event_log_entry) if record else None
    return version.value if version is not None else "missing"


def pair_fingerprints(campaign: Campaign, instance: DagsterInstance, rows: pd.DataFrame) -> dict[str, str]:
    """``{pair key: fingerprint}``: the hash of the pair's candidate row and of the data
    versions of its two scans' :data:`PAIR_SCAN_INPUTS`."""
    versions: dict[tuple[str, str], str] = {}

    def version(stage: str, sid: str) -> str:
        if (stage, sid) not in versions:
            versions[(stage, sid)] = latest_data_version(instance, asset_key(campaign, stage), sid)
        return versions[(stage, sid)]

    out = {}
    for row in rows.itertuples(index=False):
        parts = [_row_digest(pd.Series(row._asdict()))]
        parts += [version(stage, sid) for sid in (row.scan, row.reference) for stage in PAIR_SCAN_INPUTS]
        out[row.pair] = hashlib.sha256("|".join(parts).encode()).hexdigest()[:24]
    return out


def combine_pairs(parts: dict[str, dict[str, pd.DataFrame]] | None) -> dict[str, pd.DataFrame]:
    """The per-pair bundles of a pair-partitioned asset as one bundle (tables concatenated in
    pair-key order), as the campaign-level stages, the exports and the notebooks read them."""
    out: dict[str, list[pd.DataFrame]] = {}
    for key in sorted(parts or {}):
        for name, table in parts[key].items():
            out.setdefault(name, []).append(table)
    return {name: pd.concat([t for t in tables if len(t)] or tables[:1], ignore_index=True)
            for name, tables in out.items()}
