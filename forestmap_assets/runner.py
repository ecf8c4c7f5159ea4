"""Materialising a campaign through Dagster (``forestmap run`` and ``forestmap status``).

Per-scan assets run as one Dagster run per scan partition (so a corrupt scan fails only its
own partitions), then the campaign-level assets run once. Only what is missing or stale
(Dagster's code-version and data-version lineage) is executed; everything else is reused.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

from dagster import AssetKey, DagsterInstance, Definitions, materialize
from dagster._core.asset_graph_view.asset_graph_view import AssetGraphView, TemporalContext
from dagster._core.definitions.data_version import CachingStaleStatusResolver, StaleStatus
from dagster._core.definitions.observe import observe
from dagster._time import get_current_datetime

from .assets.common import PIPELINE, asset_key, scan_partitions
from .campaign import Campaign, load_campaign
from .definitions import build_definitions
from .io.store import forestmap_home

Progress = Callable[[str], None]


QUIET = {"loggers": {"console": {"config": {"log_level": "CRITICAL"}}}}


def get_instance() -> DagsterInstance:
    """Persistent instance: ``$DAGSTER_HOME`` if set, else ``<forestmap home>/dagster``.

    A new home gets a ``dagster.yaml`` with telemetry off (embedded SQLite storage).
    """
    if not os.environ.get("DAGSTER_HOME"):
        os.environ["DAGSTER_HOME"] = str(forestmap_home() / "dagster")
    home = Path(os.environ["DAGSTER_HOME"])
    home.mkdir(parents=True, exist_ok=True)
    config = home / "dagster.yaml"
    if not config.exists():
        config.write_text("telemetry:\n  enabled: false\n")
    return DagsterInstance.get()


@dataclass
class StageState:
    stage: str
    granularity: str
    built: bool
    state: str  # missing | stale | fresh | not built
    per_partition: dict[str, str] = field(default_factory=dict)


@dataclass
class RunSummary:
    campaign: Campaign
    ran: list[tuple[str, str | None]] = field(default_factory=list)  # (stage, partition)
    failures: list[tuple[str, str | None, str]] = field(default_factory=list)
    not_built: list[str] = field(default_factory=list)
    seconds: float = 0.0


def _assets_by_stage(defs: Definitions, campaign: Campaign) -> dict[str, object]:
    graph = defs.resolve_asset_graph()
    out = {}
    for stage, _ in PIPELINE:
        key = asset_key(campaign, stage)
        if graph.has(key):
            out[stage] = key
    return out


def sync_partitions(instance: DagsterInstance, campaign: Campaign) -> None:
    """Make the campaign's dynamic scan partitions match its manifest."""
    name = scan_partitions(campaign).name
    existing = set(instance.get_dynamic_partitions(name))
    wanted = campaign.scan_ids
    new = [s for s in wanted if s not in existing]
    if new:
        instance.add_dynamic_partitions(name, new)
    for gone in existing - set(wanted):
        instance.delete_dynamic_partition(name, gone)


def observe_scan_files(defs: Definitions, campaign: Campaign, instance: DagsterInstance) -> None:
    """Record the content hash of every scan file, so changed files make their assets stale."""
    graph = defs.resolve_asset_graph()
    source = graph.get(AssetKey([campaign.key, "scan_files"]))
    assets = [a for a in defs.assets if getattr(a, "key", None) == source.key]
    observe(assets, instance=instance, resources=defs.resources, run_config=QUIET)


def stage_states(defs: Definitions, campaign: Campaign, instance: DagsterInstance) -> list[StageState]:
    """State of every pipeline stage (DESIGN.md section 3 rules for per-scan assets)."""
    graph = defs.resolve_asset_graph()
    view = AssetGraphView(
        temporal_context=TemporalContext(effective_dt=get_current_datetime(), last_event_id=None),
        instance=instance,
        asset_graph=graph,
    )
    resolver = CachingStaleStatusResolver(instance=instance, asset_graph=graph, loading_context=view)
    built = _assets_by_stage(defs, campaign)
    states = []
    for stage, granularity in PIPELINE:
        if stage not in built:
            states.append(StageState(stage, granularity, False, "not built"))
            continue
        key = built[stage]
        if granularity == "scan":
            per = {sid: _status(resolver, key, sid) for sid in campaign.scan_ids}
            values = set(per.values())
            state = "missing" if "missing" in values else "stale" if "stale" in values else "fresh"
            states.append(StageState(stage, granularity, True, state, per))
        else:
            states.append(StageState(stage, granularity, True, _status(resolver, key, None)))
    return states


def _status(resolver: CachingStaleStatusResolver, key, partition: str | None) -> str:
    status = resolver.get_status(key, partition)
    return {StaleStatus.MISSING: "missing", StaleStatus.STALE: "stale"}.get(status, "fresh")


def _materialize_scan(folder: str, scan_id: str, stages: list[str], store_url: str | None) -> tuple[bool, str]:
    """Run the given per-scan stages for one scan partition (also used in worker processes)."""
    campaign = load_campaign(folder)
    defs = build_definitions([campaign], store_url)
    instance = get_instance()
    selection = [asset_key(campaign, s) for s in stages]
    result = materialize(
        list(defs.assets),
        instance=instance,
        partition_key=scan_id,
        selection=selection,
        resources=defs.resources,
        run_config=QUIET,
        raise_on_error=False,
        tags={"forestmap/campaign": campaign.key, "forestmap/scan": scan_id},
    )
    if result.success:
        return True, ""
    return False, _failure_reason(result)


def _materialize_campaign_stage(defs: Definitions, campaign: Campaign, instance: DagsterInstance, stage: str) -> tuple[bool, str]:
    result = materialize(
        list(defs.assets),
        instance=instance,
        selection=[asset_key(campaign, stage)],
        resources=defs.resources,
        run_config=QUIET,
        raise_on_error=False,
        tags={"forestmap/campaign": campaign.key},
    )
    return (True, "") if result.success else (False, _failure_reason(result))


def _failure_reason(result) -> str:
    for event in result.all_events:
        if event.is_step_failure:
            data = event.step_failure_data
            err = data.error
            text = (data.user_failure_data.description if data.user_failure_data else None) or (
                err.message if err else "failed"
            )
            return f"{event.step_key}: {text.strip().splitlines()[0]}"
    return "run failed"


def run_campaign(
    folder: str | Path,
    *,
    executor: str = "in_process",
    store_url: str | None = None,
    progress: Progress = print,
) -> RunSummary:
    """Materialise every missing or stale asset of a campaign."""
    start = time.perf_counter()
    campaign = load_campaign(folder)
    defs = build_definitions([campaign], store_url)
    instance = get_instance()
    sync_partitions(instance, campaign)
    observe_scan_files(defs, campaign, instance)
    summary = RunSummary(campaign)
    states = stage_states(defs, campaign, instance)
    summary.not_built = [s.stage for s in states if not s.built]

    scan_stages = [s for s in states if s.built and s.granularity == "scan"]
    todo: dict[str, list[str]] = {}
    for sid in campaign.scan_ids:
        stale = [s.stage for s in scan_stages if s.per_partition.get(sid) != "fresh"]
        if stale:
            todo[sid] = stale
    fresh = len(campaign.scan_ids) - len(todo)
    progress(f"{campaign.name}: {len(campaign.scan_ids)} scans, {len(todo)} to process, {fresh} up to date")

    def done(sid: str, ok: bool, reason: str, seconds: float) -> None:
        if ok:
            summary.ran.extend((s, sid) for s in todo[sid])
            progress(f"  scan {sid}: {', '.join(todo[sid])} ({seconds:.1f} s)")
        else:
            summary.failures.append((reason.split(":")[0], sid, reason))
            progress(f"  scan {sid}: FAILED {reason}")

    if executor == "multiprocess" and len(todo) > 1:
        with ProcessPoolExecutor(max_workers=min(len(todo), os.cpu_count() or 2)) as pool:
            t0 = time.perf_counter()
            futures = {
                pool.submit(_materialize_scan, str(campaign.root), sid, stages, store_url): sid
                for sid, stages in todo.items()
            }
            for fut in as_completed(futures):
                ok, reason = fut.result()
                done(futures[fut], ok, reason, time.perf_counter() - t0)
    elif executor in ("in_process", "multiprocess"):
        for sid, stages in todo.items():
            t0 = time.perf_counter()
            ok, reason = _materialize_scan(str(campaign.root), sid, stages, store_url)
            done(sid, ok, reason, time.perf_counter() - t0)
    else:
        raise ValueError(f"--executor: {executor!r} is not available (in_process, multiprocess)")

    # campaign-level stages, in pipeline order, each only if it is missing or stale now
    for stage, granularity in PIPELINE:
        if granularity != "campaign" or stage in summary.not_built:
            continue
        state = {s.stage: s for s in stage_states(defs, campaign, instance)}[stage]
        if state.state == "fresh":
            continue
        t0 = time.perf_counter()
        progress(f"  {stage} ...")
        ok, reason = _materialize_campaign_stage(defs, campaign, instance, stage)
        if not ok:
            summary.failures.append((stage, None, reason))
            progress(f"  {stage}: FAILED {reason}")
            break
        summary.ran.append((stage, None))
        progress(f"  {stage} ({time.perf_counter() - t0:.1f} s)")

    summary.seconds = time.perf_counter() - start
    return summary
