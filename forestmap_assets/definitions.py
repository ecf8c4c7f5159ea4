"""The one Dagster ``Definitions`` object (``workspace.yaml`` loads this module).

Campaigns are found at load time: every folder with a ``campaign.yaml`` under
``$FORESTMAP_DATA_ROOT`` (default: the bundled ``data/`` folder of the repository), plus the
folders listed in ``$FORESTMAP_CAMPAIGNS`` (separated by ``os.pathsep``). A campaign whose
manifest is invalid is left out with a warning, so one bad folder does not hide the others.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterable
from pathlib import Path

from dagster import Definitions

from .assets import campaign_assets
from .campaign import MANIFEST, Campaign, CampaignError, load_campaign
from .io.store import ParquetStore

REPO_DATA = Path(__file__).resolve().parent.parent / "data"


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


def build_definitions(campaigns: Iterable[Campaign], store_url: str | None = None) -> Definitions:
    """Definitions for the given campaigns with the Parquet asset store."""
    assets: list = []
    keys: dict[str, Path] = {}
    for campaign in campaigns:
        if campaign.key in keys:
            warnings.warn(
                f"{campaign.root / MANIFEST}: name: campaign name {campaign.name!r} is already used "
                f"by {keys[campaign.key]}; this campaign is left out",
                stacklevel=2,
            )
            continue
        keys[campaign.key] = campaign.root
        assets.extend(campaign_assets(campaign))
    return Definitions(assets=assets, resources={"io_manager": ParquetStore(base_url=store_url or "")})


def load_campaigns(folders: Iterable[Path]) -> list[Campaign]:
    campaigns = []
    for folder in folders:
        try:
            campaigns.append(load_campaign(folder))
        except CampaignError as exc:
            warnings.warn(str(exc), stacklevel=2)
    return campaigns


defs = build_definitions(load_campaigns(discover_campaign_folders()))
