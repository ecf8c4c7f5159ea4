"""Thin Dagster wrappers around the core, one module per stage group (ingest, features,
registration, map, exploration). May import: ``core``, ``io``, ``outputs``, ``access``,
``params``; never ``orchestration``.

:func:`campaign_assets` is an asset factory: every campaign gets its own assets under the key
prefix ``<campaign>/`` with per-scan partitions, so each campaign's parameter overrides enter
its own code versions (README, "How the asset graph is organised"). :func:`campaign_jobs` gives
each campaign three asset jobs: its per-scan assets (one run per scan partition), its per-pair
assets (one run per pair partition) and its campaign-level assets.
"""

from __future__ import annotations

import warnings

from dagster import (
    AssetSelection,
    AutomationCondition,
    BetaWarning,
    PreviewWarning,
    define_asset_job,
)

from forestmap_assets.assets.common import CAMPAIGN_STAGES, asset_key, job_name, pair_partitions
from forestmap_assets.assets.exploration import exploration_assets
from forestmap_assets.assets.features import feature_assets
from forestmap_assets.assets.ingest import ingest_assets
from forestmap_assets.assets.mapping import mapping_assets
from forestmap_assets.assets.registration import registration_assets
from forestmap_assets.io.campaign import Campaign

warnings.filterwarnings("ignore", category=BetaWarning)
warnings.filterwarnings("ignore", category=PreviewWarning)

STAGE_BUILDERS = [ingest_assets, feature_assets, registration_assets, mapping_assets, exploration_assets]


def follows_its_inputs(per_scan: AssetSelection | None = None) -> AutomationCondition:
    """Declarative automation of the campaign-level assets (inferred).

    A campaign-level asset is requested when its code version (stage version, parameters,
    manifest entries) changed or when an input's *data version* changed, once nothing upstream
    is in progress, no campaign-level input is missing (unless requested in the same tick) and
    upstream blocking checks passed. Keying on data versions rather than on new materialisations
    means a re-run that reproduces the same table does not ripple downstream. Missing ``per_scan``
    inputs do not hold it back (a scan whose file is corrupt is left out, as in ``forestmap
    run``). Per-scan assets carry no condition: the scan-file sensor requests their runs.
    """
    ac = AutomationCondition
    trigger = ac.code_version_changed() | ac.any_deps_match(ac.data_version_changed())
    missing = ac.any_deps_match(ac.missing() & ~ac.will_be_requested())
    if per_scan is not None:
        missing = missing.ignore(per_scan)
    return (
        trigger.since_last_handled()
        & ~missing
        & ~ac.any_deps_in_progress()
        & ~ac.in_progress()
        & ac.all_deps_blocking_checks_passed()
    ).with_label("follows_its_inputs")


def campaign_assets(campaign: Campaign) -> list:
    """All asset (and asset check) definitions of one campaign."""
    out: list = []
    for build in STAGE_BUILDERS:
        out.extend(build(campaign))
    per_scan = [k for a in out if getattr(a, "partitions_def", None) is not None for k in getattr(a, "keys", [a.key])]
    condition = follows_its_inputs(AssetSelection.assets(*per_scan))
    level = {asset_key(campaign, s) for s in CAMPAIGN_STAGES}

    def with_condition(spec):
        return spec.replace_attributes(automation_condition=condition) if spec.key in level else spec

    return [
        a.map_asset_specs(with_condition) if hasattr(a, "map_asset_specs") and level & set(a.keys) else a
        for a in out
    ]


def campaign_jobs(campaign: Campaign, assets: list | None = None) -> list:
    """The campaign's per-scan job (its scan-partitioned assets), per-pair job (its
    pair-partitioned assets, issue 17) and campaign-level job (the others); ``assets`` defaults
    to :func:`campaign_assets`."""
    keys: dict[str, list] = {"scan": [], "pair": [], "campaign": []}
    pairs = pair_partitions(campaign).name
    for a in assets if assets is not None else campaign_assets(campaign):
        if getattr(a, "is_materializable", False):
            part = a.partitions_def
            kind = "campaign" if part is None else "pair" if getattr(part, "name", None) == pairs else "scan"
            keys[kind].extend(a.keys)
    return [
        define_asset_job(
            job_name(campaign, "scan"),
            selection=AssetSelection.assets(*keys["scan"]),  # partitioned by scan, as its assets
            description=f"Per-scan feature extraction of campaign {campaign.name!r}: one run per scan.",
            tags={"forestmap/campaign": campaign.key},
        ),
        define_asset_job(
            job_name(campaign, "pair"),
            selection=AssetSelection.assets(*keys["pair"]),  # partitioned by pair
            description=f"Registration of one pair of scans of campaign {campaign.name!r}: one run per pair.",
            tags={"forestmap/campaign": campaign.key},
        ),
        define_asset_job(
            job_name(campaign, "campaign"),
            selection=AssetSelection.assets(*keys["campaign"]),
            description=f"Candidate pairs, optimal map and tree list of campaign {campaign.name!r}.",
            tags={"forestmap/campaign": campaign.key},
        ),
    ]
