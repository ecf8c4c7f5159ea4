"""Thin Dagster wrappers around the core, one module per stage group.

:func:`campaign_assets` is an asset factory: every campaign gets its own assets under the key
prefix ``<campaign>/`` with per-scan partitions, so each campaign's parameter overrides enter
its own code versions (README, "How the asset graph is organised").
"""

from __future__ import annotations

import warnings

from dagster import BetaWarning, PreviewWarning

from ..campaign import Campaign
from .features import feature_assets
from .ingest import ingest_assets
from .mapping import mapping_assets

warnings.filterwarnings("ignore", category=BetaWarning)
warnings.filterwarnings("ignore", category=PreviewWarning)

STAGE_BUILDERS = [ingest_assets, feature_assets, mapping_assets]


def campaign_assets(campaign: Campaign) -> list:
    """All asset (and asset check) definitions of one campaign."""
    out: list = []
    for build in STAGE_BUILDERS:
        out.extend(build(campaign))
    return out
