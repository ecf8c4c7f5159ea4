"""State of a campaign's assets as ``forestmap status`` prints it (DESIGN.md section 3) and as
:func:`~forestmap_assets.orchestration.runner.run_campaign` decides what to run: Dagster's
stale-status resolver per (stage, scan) -- ``missing``, ``stale`` (a cause of its own: a new code
version, i.e. stage version + parameter hash, or an input with a new data version) or ``fresh`` --
propagated downstream, and the content hashes of changed scan files (runless observations of
``scan_files``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from dagster import AssetObservation, AssetRecordsFilter, DagsterInstance, Definitions
from dagster._core.asset_graph_view.asset_graph_view import AssetGraphView, TemporalContext
from dagster._core.definitions.data_version import (
    DATA_VERSION_TAG,
    CachingStaleStatusResolver,
    StaleStatus,
)
from dagster._time import get_current_datetime

from forestmap_assets.assets.common import PIPELINE, asset_key
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.orchestration.workspace import build_definitions


@dataclass
class StageState:
    stage: str
    granularity: str
    built: bool
    state: str  # missing | stale | fresh
    per_partition: dict[str, str] = field(default_factory=dict)


def campaign_stages(defs: Definitions, campaign: Campaign) -> list[tuple[str, str]]:
    """Every materialisable asset of the campaign as (stage, ``scan`` | ``campaign``): the
    stages of DESIGN.md section 5 in that order, then any further stage in graph order."""
    graph = defs.resolve_asset_graph()
    order = {s: i for i, (s, _) in enumerate(PIPELINE)}
    found = [
        (k.path[-1], "scan" if graph.get(k).is_partitioned else "campaign")
        for k in graph.toposorted_asset_keys
        if len(k.path) == 2 and k.path[0] == campaign.key and graph.get(k).is_materializable
    ]
    rank = {s: (order.get(s, len(order)), i) for i, (s, _) in enumerate(found)}
    return sorted(found, key=lambda sg: rank[sg[0]])


def stage_parents(defs: Definitions, campaign: Campaign) -> dict[str, list[str]]:
    """For every stage of the campaign, the stages it reads (from the Dagster asset graph)."""
    graph = defs.resolve_asset_graph()
    names = {asset_key(campaign, s): s for s, _ in campaign_stages(defs, campaign)}
    return {
        stage: sorted(names[k] for k in graph.get(key).parent_keys if k in names)
        for key, stage in names.items()
    }


def _resolver(defs: Definitions, instance: DagsterInstance) -> CachingStaleStatusResolver:
    return resolver_for_graph(defs.resolve_asset_graph(), instance)


def resolver_for_graph(graph, instance: DagsterInstance) -> CachingStaleStatusResolver:
    """Dagster's stale-status resolver on an asset graph (as the UI computes staleness)."""
    view = AssetGraphView(
        temporal_context=TemporalContext(effective_dt=get_current_datetime(), last_event_id=None),
        instance=instance,
        asset_graph=graph,
    )
    return CachingStaleStatusResolver(instance=instance, asset_graph=graph, loading_context=view)


def changed_scan_files(
    campaign: Campaign, instance: DagsterInstance, resolver=None, defs=None
) -> dict[str, str]:
    """Scans whose file content (or tilt) differs from the last observed ``scan_files`` version:
    ``{scan id: new fingerprint}``."""
    resolver = resolver or _resolver(defs or build_definitions([campaign]), instance)
    key = asset_key(campaign, "scan_files")
    out = {}
    for sid in campaign.scan_ids:
        try:
            fp = campaign.scan_fingerprint(sid)
        except OSError:
            fp = "missing"
        if resolver.get_current_data_version(key, sid).value != fp:
            out[sid] = fp
    return out


def observe_scan_files(
    instance: DagsterInstance, campaign: Campaign, changed: dict[str, str]
) -> None:
    """Record the new content hashes of changed scan files (runless observations of the
    ``scan_files`` source asset), which makes exactly those scans' range images stale."""
    key = asset_key(campaign, "scan_files")
    for sid, fp in changed.items():
        instance.report_runless_asset_event(
            AssetObservation(asset_key=key, partition=sid, tags={DATA_VERSION_TAG: fp})
        )


def direct_states(
    defs: Definitions, campaign: Campaign, instance: DagsterInstance, check_files: bool = True
) -> dict[tuple[str, str | None], str]:
    """Dagster's own status of every (stage, scan) and (stage, None): ``missing``, ``stale``
    (a cause of its own: new code version, or an input with a new data version) or ``fresh``;
    ``check_files`` also hashes the scan files (a changed, not yet observed file: stale)."""
    resolver = _resolver(defs, instance)
    stages = campaign_stages(defs, campaign)
    resolver.instance_queryer.prefetch_asset_records([asset_key(campaign, s) for s, _ in stages])
    out: dict[tuple[str, str | None], str] = {}
    for stage, granularity in stages:
        key = asset_key(campaign, stage)
        for part in campaign.scan_ids if granularity == "scan" else [None]:
            status = resolver.get_status(key, part)
            out[(stage, part)] = {StaleStatus.MISSING: "missing", StaleStatus.STALE: "stale"}.get(
                status, "fresh"
            )
    changed = changed_scan_files(campaign, instance, resolver) if check_files else {}
    for sid in changed:  # a changed file not yet observed: its range image is stale
        if out.get(("range_images", sid)) == "fresh":
            out[("range_images", sid)] = "stale"
    return out


def stage_states(
    defs: Definitions, campaign: Campaign, instance: DagsterInstance
) -> list[StageState]:
    """State of every pipeline stage as ``forestmap status`` prints it (DESIGN.md section 3).

    A partition is ``stale`` if Dagster reports a cause of its own or if anything it reads is
    missing or stale (so the effect of a parameter change shows all the way down); a per-scan
    asset is ``missing`` if any scan's partition is, else ``stale`` if any is.
    """
    direct = direct_states(defs, campaign, instance)
    parents = stage_parents(defs, campaign)
    stages = campaign_stages(defs, campaign)
    granularity = dict(stages)
    effective: dict[tuple[str, str | None], str] = {}
    for stage, g in stages:
        for part in campaign.scan_ids if g == "scan" else [None]:
            state = direct[(stage, part)]
            if state == "fresh":
                upstream = [
                    effective[(p, q)]
                    for p in parents[stage]
                    for q in (
                        [part] if granularity[p] == g or part is not None else campaign.scan_ids
                    )
                ]
                state = "stale" if any(u != "fresh" for u in upstream) else "fresh"
            effective[(stage, part)] = state
    out = []
    for stage, g in stages:
        if g == "scan":
            per = {sid: effective[(stage, sid)] for sid in campaign.scan_ids}
            values = set(per.values())
            state = "missing" if "missing" in values else "stale" if "stale" in values else "fresh"
            out.append(StageState(stage, g, True, state, per))
        else:
            out.append(StageState(stage, g, True, effective[(stage, None)]))
    return out


def materialised_before(instance: DagsterInstance, campaign: Campaign, stage: str, scan: str) -> bool:
    """Whether ``stage`` of ``scan`` was ever materialised (a failed scan's earlier results)."""
    records = instance.fetch_materializations(
        AssetRecordsFilter(asset_key=asset_key(campaign, stage), asset_partitions=[scan]), limit=1
    ).records
    return bool(records)


def safe_subset(candidates: set[str], parents: dict[str, list[str]]) -> set[str]:
    """Candidates that may run in one wave: drop a stage that reads a non-candidate stage which
    itself lies downstream of a candidate (it would read an input about to change)."""

    def downstream_of_candidate(stage: str, seen: set[str]) -> bool:
        for p in parents.get(stage, []):
            if p in chosen or (p not in seen and downstream_of_candidate(p, seen | {p})):
                return True
        return False

    chosen = set(candidates)
    changed = True
    while changed:
        changed = False
        for stage in sorted(chosen):
            if any(
                p not in chosen and downstream_of_candidate(p, {p}) for p in parents.get(stage, [])
            ):
                chosen.discard(stage)
                changed = True
    return chosen


def latest_materialization_id(instance: DagsterInstance, campaign: Campaign) -> int:
    """The newest materialisation of any of the campaign's stages, as the event log's storage
    id: unchanged since an export means the exports are still current."""
    newest = 0
    for stage, _ in PIPELINE:
        records = instance.fetch_materializations(
            AssetRecordsFilter(asset_key=asset_key(campaign, stage)), limit=1
        ).records
        if records:
            newest = max(newest, int(records[0].storage_id))
    return newest
