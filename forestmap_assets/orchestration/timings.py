"""Seconds per pipeline stage, read from the Dagster instance's run history.

For each stage: the compute seconds of the steps that materialised its current outputs, as each
materialisation records them (``seconds`` metadata, :func:`~forestmap_assets.assets.common.timed`;
else the step's duration in the run history), and the CPU seconds of the step's own thread
(``cpu_seconds``, where recorded: a stage far below its seconds waited for a core, the machine
busy with other steps; Open3D's own threads are not counted); per-scan and per-pair stages:
the latest materialisation of each partition, summed. The report shows this table.
"""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np
import pandas as pd

from forestmap_assets.assets.common import PIPELINE
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.orchestration.instance import get_instance

TIMING_COLUMNS = [
    "stage",
    "granularity",
    "outputs",
    "seconds",
    "cpu_seconds",
    "slowest_seconds",
    "last_materialised",
]


def stage_timings(campaign: Campaign, instance=None) -> pd.DataFrame:
    """Seconds per pipeline stage from the Dagster instance (see the module docstring)."""
    from dagster import AssetKey
    from dagster._core.event_api import AssetRecordsFilter

    if instance is None:
        instance = get_instance()
    step_cache: dict[str, dict[str, float]] = {}

    def durations(run_id: str) -> dict[str, float]:
        if run_id not in step_cache:
            stats = instance.get_run_step_stats(run_id)
            step_cache[run_id] = {
                s.step_key: float(s.end_time - s.start_time)
                for s in stats
                if s.start_time is not None and s.end_time is not None
            }
        return step_cache[run_id]

    rows = []
    for stage, granularity in PIPELINE:
        key = AssetKey([campaign.key, stage])
        records = instance.fetch_materializations(
            AssetRecordsFilter(asset_key=key), limit=max(200, 8 * len(campaign.scans))
        ).records
        latest: dict[str | None, object] = {}
        for rec in records:  # newest first
            part = rec.asset_materialization.partition if rec.asset_materialization else None
            if granularity == "scan" and part not in campaign.scan_ids:
                continue
            latest.setdefault(part, rec)
        if not latest:
            rows.append(
                dict(
                    stage=stage,
                    granularity=granularity,
                    outputs=0,
                    seconds=np.nan,
                    cpu_seconds=np.nan,
                    slowest_seconds=np.nan,
                    last_materialised="",
                )
            )
            continue
        secs, cpu = [], []
        for rec in latest.values():
            entry = rec.event_log_entry
            meta = rec.asset_materialization.metadata or {}
            recorded = meta.get("seconds")
            secs.append(float(recorded.value) if recorded is not None
                        else durations(entry.run_id).get(entry.step_key or "", np.nan))
            cpu.append(float(meta["cpu_seconds"].value) if "cpu_seconds" in meta else np.nan)
        newest = max(rec.event_log_entry.timestamp for rec in latest.values())
        rows.append(
            dict(
                stage=stage,
                granularity=granularity,
                outputs=len(latest),
                seconds=float(np.nansum(secs)),
                cpu_seconds=float(np.nansum(cpu)) if np.isfinite(cpu).any() else np.nan,
                slowest_seconds=float(np.nanmax(secs)) if np.isfinite(secs).any() else np.nan,
                last_materialised=datetime.fromtimestamp(newest, UTC).strftime(
                    "%Y-%m-%d %H:%M:%S UTC"
                ),
            )
        )
    return pd.DataFrame(rows, columns=TIMING_COLUMNS)


def stage_timings_or_note(campaign: Campaign, instance=None) -> pd.DataFrame:
    """:func:`stage_timings`, or a one-row note when the run history cannot be read (the
    report must not fail on it)."""
    try:
        return stage_timings(campaign, instance)
    except Exception as exc:
        return pd.DataFrame({"stage": [f"timings unavailable: {exc}"]})
