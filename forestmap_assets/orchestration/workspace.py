"""Building Dagster ``Definitions`` for a set of campaigns (used by ``definitions.py``, the
runner and the automation), without loading any campaign at import time.

Campaigns are found under ``$FORESTMAP_DATA_ROOT`` (default: the bundled ``data/`` folder of the
repository), plus the folders listed in ``$FORESTMAP_CAMPAIGNS`` (separated by ``os.pathsep``).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path

from dagster import Definitions, in_process_executor, multiprocess_executor

from forestmap_assets.assets import campaign_assets, campaign_jobs
from forestmap_assets.io.campaign import MANIFEST, Campaign, CampaignError, load_campaign
from forestmap_assets.io.store import ParquetStore, default_store_url, read_campaign_root

REPO_DATA = Path(__file__).resolve().parents[2] / "data"
EXECUTORS = ("in_process", "multiprocess", "dask")


def data_root() -> Path:
    return Path(os.environ.get("FORESTMAP_DATA_ROOT", REPO_DATA)).expanduser()


def discover_campaign_folders(root: Path | None = None) -> list[Path]:
    """Campaign folders under the data root (any depth) and in ``$FORESTMAP_CAMPAIGNS``."""
    root = data_root() if root is None else root
    found = sorted(p.parent for p in root.rglob(MANIFEST)) if root.is_dir() else []
    extra = [Path(p).expanduser() for p in os.environ.get("FORESTMAP_CAMPAIGNS", "").split(os.pathsep) if p]
    seen, out = set(), []
    for folder in [*found, *extra]:
        key = folder.resolve()
        if key not in seen:
            seen.add(key)
            out.append(folder)
    return out


def executor_def(name: str | None):
    """Dagster executor for ``forestmap run --executor``: ``in_process``, ``multiprocess``
    (one process per step) or ``dask`` (dagster-dask; cluster given by run config)."""
    if name in (None, "in_process"):
        return in_process_executor
    if name == "multiprocess":
        return multiprocess_executor
    if name == "dask":
        try:
            from forestmap_assets.orchestration.executors import packed_dask_executor
        except ImportError:
            raise ValueError("--executor dask needs the dagster-dask package (pip install dagster-dask)") from None
        return packed_dask_executor
    raise ValueError(f"--executor: {name!r} is not one of {', '.join(EXECUTORS)}")


def unique_campaigns(campaigns: Iterable[Campaign], store_url: str | None = None) -> list[Campaign]:
    """Campaigns with distinct keys (a key is a namespace of the asset store and of the run
    history): of two folders with the same key, the one the store records as its owner
    (:func:`forestmap_assets.orchestration.runner.claim_campaign_name`), else the first, is
    kept; the other is left out with a one-line warning naming both folders."""
    campaigns = list(campaigns)
    groups: dict[str, list[Campaign]] = {}
    for campaign in campaigns:
        groups.setdefault(campaign.key, []).append(campaign)
    kept: dict[str, Campaign] = {}
    for key, group in groups.items():
        kept[key] = group[0]
        if len(group) > 1:
            try:
                found = read_campaign_root(store_url or default_store_url(), key)
            except Exception:  # an unreachable store: keep the first
                found = None
            owner = [c for c in group if found and str(c.root.resolve()) == found[0]]
            kept[key] = owner[0] if owner else group[0]
    out = []
    for campaign in campaigns:
        keep = kept[campaign.key]
        if campaign is keep:
            out.append(campaign)
            continue
        same = "" if campaign.name == keep.name else f" (store key {campaign.key!r} of {keep.name!r})"
        warnings.warn(
            f"{campaign.root / MANIFEST}: name: campaign name {campaign.name!r}{same} is already used "
            f"by {keep.root}; this campaign is left out: give it another name: in its {MANIFEST}",
            stacklevel=2,
        )
    return out


def build_definitions(
    campaigns: Iterable[Campaign],
    store_url: str | None = None,
    *,
    executor: str | None = None,
    extras: Callable[[list[Campaign], list], dict[str, list]] | None = None,
) -> Definitions:
    """Definitions for the given campaigns with the Parquet asset store.

    ``executor`` fixes the jobs' executor (default: Dagster's, in-process or multiprocess by
    run config); ``extras(campaigns, scan_jobs)`` adds jobs, sensors and schedules (the
    automation: :func:`forestmap_assets.orchestration.automation.automated_definitions`).
    """
    campaigns = unique_campaigns(campaigns, store_url)
    assets: list = []
    jobs: list = []
    for campaign in campaigns:
        own = campaign_assets(campaign)
        assets.extend(own)
        jobs.extend(campaign_jobs(campaign, own))
    scan_jobs = [j for j in jobs if j.name.endswith("__scan_assets")]
    sensors: list = []
    schedules: list = []
    if extras is not None:
        extra = extras(campaigns, scan_jobs)
        jobs.extend(extra["jobs"])
        sensors.extend(extra["sensors"])
        schedules.extend(extra["schedules"])
    return Definitions(
        assets=assets,
        jobs=jobs,
        sensors=sensors,
        schedules=schedules,
        resources={"io_manager": ParquetStore(base_url=store_url or "")},
        executor=executor_def(executor) if executor else None,
    )


def load_campaigns(folders: Iterable[Path]) -> list[Campaign]:
    campaigns = []
    for folder in folders:
        try:
            campaigns.append(load_campaign(folder))
        except CampaignError as exc:
            warnings.warn(str(exc), stacklevel=2)
    return campaigns

