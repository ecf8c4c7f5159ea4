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
from forestmap_assets.io.store import ParquetStore

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


def unique_campaigns(campaigns: Iterable[Campaign]) -> list[Campaign]:
    """Campaigns with distinct keys; a later campaign reusing a key is left out with a warning."""
    keys: dict[str, Path] = {}
    out = []
    for campaign in campaigns:
        if campaign.key in keys:
            warnings.warn(
                f"{campaign.root / MANIFEST}: name: campaign name {campaign.name!r} is already used "
                f"by {keys[campaign.key]}; this campaign is left out",
                stacklevel=2,
            )
            continue
        keys[campaign.key] = campaign.root
        out.append(campaign)
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
    campaigns = unique_campaigns(campaigns)
    assets: list = []
    jobs: list = []
    for campaign in campaigns:
        own = campaign_assets(campaign)
        assets.extend(own)
        jobs.extend(campaign_jobs(campaign, own))
    scan_jobs = jobs[0::2]
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

