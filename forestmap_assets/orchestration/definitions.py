"""The one Dagster ``Definitions`` object (``workspace.yaml`` loads this module).

Campaigns are found at load time: every folder with a ``campaign.yaml`` under
``$FORESTMAP_DATA_ROOT`` (default: the bundled ``data/`` folder of the repository), plus the
folders listed in ``$FORESTMAP_CAMPAIGNS`` (separated by ``os.pathsep``). A campaign whose
manifest is invalid is left out with a warning, so one bad folder does not hide the others.

Per campaign: its assets and asset checks (:func:`~forestmap_assets.assets.campaign_assets`),
a per-scan and a campaign-level asset job. For the whole workspace: the scan-file sensor, the
nightly schedule and the ``process_campaign`` job (:mod:`forestmap_assets.automation`).
"""

from __future__ import annotations

from forestmap_assets.orchestration.automation import automated_definitions
from forestmap_assets.orchestration.workspace import (  # noqa: F401  (re-exported: the public names of this module)
    EXECUTORS,
    REPO_DATA,
    build_definitions,
    data_root,
    discover_campaign_folders,
    executor_def,
    load_campaigns,
    unique_campaigns,
)

defs = automated_definitions(load_campaigns(discover_campaign_folders()))
