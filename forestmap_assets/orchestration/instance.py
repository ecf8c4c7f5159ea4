"""The persistent Dagster instance of ``forestmap run`` / ``status`` / the UI (``$DAGSTER_HOME``,
else ``<forestmap home>/dagster``) and a campaign's dynamic scan partitions in it (matched to its
manifest)."""

from __future__ import annotations

import os
from pathlib import Path

from dagster import DagsterInstance

from forestmap_assets.assets.common import scan_partitions
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.io.store import forestmap_home

_INSTANCES: dict[str, DagsterInstance] = {}


def get_instance() -> DagsterInstance:
    """Persistent instance: ``$DAGSTER_HOME`` if set, else ``<forestmap home>/dagster``; one per
    home and process (opening its storage costs ~0.4 s).

    A new home gets a ``dagster.yaml`` with telemetry and the UI's welcome dialog off and the
    engine's console chatter at WARNING (embedded SQLite storage; run logs are kept in full).
    """
    if not os.environ.get("DAGSTER_HOME"):
        os.environ["DAGSTER_HOME"] = str(forestmap_home() / "dagster")
    home = Path(os.environ["DAGSTER_HOME"])
    home.mkdir(parents=True, exist_ok=True)
    config = home / "dagster.yaml"
    if not config.exists():
        # engine chatter of step subprocesses at WARNING; run logs are kept in full regardless
        config.write_text(
            "telemetry:\n  enabled: false\nnux:\n  enabled: false\n"
            "python_logs:\n  python_log_level: WARNING\n"
        )
    st = config.stat()
    key = f"{home.resolve()}:{st.st_ino}:{st.st_mtime_ns}"  # a home made anew is opened anew
    if key not in _INSTANCES:
        _INSTANCES[key] = DagsterInstance.get()
    return _INSTANCES[key]


def sync_partitions(instance: DagsterInstance, campaign: Campaign) -> None:
    """Make the campaign's dynamic scan partitions match its manifest."""
    name = scan_partitions(campaign).name
    existing = set(instance.get_dynamic_partitions(name))
    new = [s for s in campaign.scan_ids if s not in existing]
    if new:
        instance.add_dynamic_partitions(name, new)
    for gone in existing - set(campaign.scan_ids):
        instance.delete_dynamic_partition(name, gone)
