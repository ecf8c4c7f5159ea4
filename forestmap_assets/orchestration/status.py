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
from dagster._utils.caching_instance_queryer import CachingInstanceQueryer

from forestmap_assets.assets.common import PIPELINE, asset_key, pair_partitions, split_pair_key
from forestmap_assets.assets.pairs import PAIR_LISTS, PAIR_SCAN_INPUTS
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.orchestration.record_index import IndexedRecords
from forestmap_assets.orchestration.workspace import build_definitions


@dataclass
class StageState:
    stage: str
    granularity: str
    built: bool
    state: str  # missing | stale | fresh
    per_partition: dict[str, str] = field(default_factory=dict)

    def counts(self) -> str:
        """``12 pairs: 10 fresh, 2 missing`` for a partitioned stage, else ``""``."""
        if self.granularity == "campaign":
            return ""
        values = list(self.per_partition.values())
        parts = [f"{values.count(s)} {s}" for s in ("fresh", "stale", "missing") if values.count(s)]
        return f"{len(values)} {self.granularity}s" + (": " + ", ".join(parts) if parts else "")


def partitions_of(instance: DagsterInstance, campaign: Campaign, granularity: str) -> list[str | None]:
    """The partitions a stage of this granularity has now: the scans of the manifest, the pairs
    of the pair partition set (kept by the runner, issue 17), or ``[None]``."""
    if granularity == "scan":
        return list(campaign.scan_ids)
    if granularity == "pair":
        return sorted(instance.get_dynamic_partitions(pair_partitions(campaign).name))
    return [None]


def campaign_stages(defs: Definitions, campaign: Campaign) -> list[tuple[str, str]]:
    """Every materialisable asset of the campaign as (stage, ``scan`` | ``campaign``): the
    stages of DESIGN.md section 5 in that order, then any further stage in graph order."""
    graph = defs.resolve_asset_graph()
    order = {s: i for i, (s, _) in enumerate(PIPELINE)}
    pairs = pair_partitions(campaign).name

    def granularity(node) -> str:
        if not node.is_partitioned:
            return "campaign"
        return "pair" if getattr(node.partitions_def, "name", None) == pairs else "scan"

    found = [
        (k.path[-1], granularity(graph.get(k)))
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


def resolver_for_graph(graph, instance: DagsterInstance, records: IndexedRecords | None = None
                       ) -> CachingStaleStatusResolver:
    """Dagster's stale-status resolver on an asset graph (as the UI computes staleness); with
    ``records``, it reads the event log from them (:class:`.IndexedRecords`)."""
    view = AssetGraphView(
        temporal_context=TemporalContext(effective_dt=get_current_datetime(), last_event_id=None),
        instance=instance,
        asset_graph=graph,
    )
    if records is None:
        return CachingStaleStatusResolver(instance=instance, asset_graph=graph, loading_context=view)
    return CachingStaleStatusResolver(instance=records, asset_graph=graph, loading_context=view,
                                      instance_queryer=CachingInstanceQueryer(records, graph, view))


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


def changed_pair_inputs(campaign: Campaign, instance: DagsterInstance, store_url: str | None = None) -> dict[str, str]:
    """Pairs of the partition set whose inputs' fingerprint (:func:`.pairs.pair_fingerprints`)
    differs from the last observed ``pair_inputs`` version: ``{pair: new fingerprint}``."""
    from forestmap_assets.assets.pairs import latest_data_version, pair_fingerprints
    from forestmap_assets.orchestration.instance import wanted_pairs

    current = set(instance.get_dynamic_partitions(pair_partitions(campaign).name))
    rows = wanted_pairs(campaign, store_url)
    rows = rows[rows["pair"].isin(current)]
    key = asset_key(campaign, "pair_inputs")
    return {k: fp for k, fp in pair_fingerprints(campaign, instance, rows).items()
            if latest_data_version(instance, key, k, source=True) != fp}


def observe_pair_inputs(instance: DagsterInstance, campaign: Campaign, changed: dict[str, str]) -> None:
    """Record new pair fingerprints (runless observations of ``pair_inputs``): exactly those
    pairs' registrations become stale."""
    key = asset_key(campaign, "pair_inputs")
    for pair, fp in changed.items():
        instance.report_runless_asset_event(
            AssetObservation(asset_key=key, partition=pair, tags={DATA_VERSION_TAG: fp})
        )


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
    defs: Definitions, campaign: Campaign, instance: DagsterInstance, check_files: bool = True,
    store_url: str | None = None, only: set[str] | None = None,
) -> dict[tuple[str, str | None], str]:
    """Dagster's own status of every (stage, scan) and (stage, None): ``missing``, ``stale``
    (a cause of its own: new code version, or an input with a new data version) or ``fresh``;
    ``check_files`` also hashes the scan files (a changed, not yet observed file: stale).
    ``only``: just these stages (the runner's later waves, whose scans are done)."""
    graph = defs.resolve_asset_graph()  # the campaign's records read in bulk (issue 17)
    records = IndexedRecords(instance, [k for k in graph.get_all_asset_keys() if k.path[0] == campaign.key])
    resolver = resolver_for_graph(graph, instance, records)
    stages = [(s, g) for s, g in campaign_stages(defs, campaign) if only is None or s in only]
    resolver.instance_queryer.prefetch_asset_records([asset_key(campaign, s) for s, _ in stages])
    out: dict[tuple[str, str | None], str] = {}
    parts = {g: partitions_of(instance, campaign, g) for g in ("scan", "pair", "campaign")}
    for stage, granularity in stages:
        key = asset_key(campaign, stage)
        for part in parts[granularity]:
            status = resolver.get_status(key, part)
            out[(stage, part)] = {StaleStatus.MISSING: "missing", StaleStatus.STALE: "stale"}.get(
                status, "fresh"
            )
    _many_pairs(defs, campaign, records, stages, parts["pair"], out)
    changed = changed_scan_files(campaign, records, resolver) if check_files else {}
    for sid in changed:  # a changed file not yet observed: its range image is stale
        if out.get(("range_images", sid)) == "fresh":
            out[("range_images", sid)] = "stale"
    if check_files and parts["pair"]:  # a pair whose inputs changed since they were observed
        for pair in changed_pair_inputs(campaign, records, store_url):
            for stage, g in stages:
                if g == "pair" and out.get((stage, pair)) == "fresh":
                    out[(stage, pair)] = "stale"
    return out


def _many_pairs(defs, campaign, instance, stages, pairs, out) -> None:
    """Dagster does not compare data versions across 100 or more upstream partitions
    (``SKIP_PARTITION_DATA_VERSION_DEPENDENCY_THRESHOLD``): then a campaign-level stage that
    reads a pair stage is stale when any pair was materialised after it."""
    from dagster._core.definitions.data_version import (
        SKIP_PARTITION_DATA_VERSION_DEPENDENCY_THRESHOLD,
    )

    if len(pairs) < SKIP_PARTITION_DATA_VERSION_DEPENDENCY_THRESHOLD:
        return
    granularity = dict(stages)
    parents = stage_parents(defs, campaign)

    def newest(stage: str) -> int:
        records = instance.fetch_materializations(
            AssetRecordsFilter(asset_key=asset_key(campaign, stage)), limit=1).records
        return int(records[0].storage_id) if records else 0

    for stage, g in stages:
        if g == "campaign" and out.get((stage, None)) == "fresh":
            pair_parents = [p for p in parents[stage] if granularity.get(p) == "pair"]
            if pair_parents and max(newest(p) for p in pair_parents) > newest(stage):
                out[(stage, None)] = "stale"


def stage_states(
    defs: Definitions, campaign: Campaign, instance: DagsterInstance, store_url: str | None = None
) -> list[StageState]:
    """State of every pipeline stage as ``forestmap status`` prints it (DESIGN.md section 3).

    A partition is ``stale`` if Dagster reports a cause of its own or if anything it reads is
    missing or stale (so the effect of a parameter change shows all the way down; a pair also
    reads its two scans' outputs and ``candidate_pairs``); a per-scan or per-pair asset is
    ``missing`` if any of its partitions is, else ``stale`` if any is.
    """
    direct = direct_states(defs, campaign, instance, store_url=store_url)
    parents = stage_parents(defs, campaign)
    stages = campaign_stages(defs, campaign)
    granularity = dict(stages)
    parts = {g: partitions_of(instance, campaign, g) for g in ("scan", "pair", "campaign")}

    def read_by(p: str, g: str, part: str | None) -> list[str | None]:
        """The partitions of stage ``p`` that partition ``part`` of a ``g`` stage reads."""
        if granularity[p] == g:
            return [part]
        if g == "pair" and granularity[p] == "scan":
            return list(split_pair_key(part, campaign.scan_ids))
        return parts[granularity[p]]

    # a pair step also reads its two scans' stored outputs and the pair lists (.pairs)
    # (not retry_pairs: it lies downstream of the pairs it reads)
    pair_reads = [s for s in (*PAIR_SCAN_INPUTS, PAIR_LISTS[0]) if s in granularity]
    effective: dict[tuple[str, str | None], str] = {}
    for stage, g in stages:
        for part in parts[g]:
            state = direct[(stage, part)]
            if state == "fresh":
                reads = parents[stage] + (pair_reads if g == "pair" else [])
                upstream = [effective[(p, q)] for p in reads for q in read_by(p, g, part)]
                state = "stale" if any(u != "fresh" for u in upstream) else "fresh"
            effective[(stage, part)] = state
    out = []
    for stage, g in stages:
        if g != "campaign":
            per = {q: effective[(stage, q)] for q in parts[g]}
            values = set(per.values()) or {"missing"}
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


def partition_work(parts, stages, due, parents, granularity) -> dict[str, list[str]]:
    """``{partition: stages}`` due now for the scans or pairs ``parts``: per partition the due
    stages that may run together (:func:`safe_subset` within the granularity)."""
    out: dict[str, list[str]] = {}
    same = {s: [p for p in parents[s] if granularity[p] == granularity[s]] for s in stages}
    for part in parts:
        chosen = safe_subset({s for s in stages if (s, part) in due}, same)
        if chosen:
            out[part] = [s for s in stages if s in chosen]
    return out


def count_attempts(attempts: dict, todo: dict[str, list[str]]) -> None:
    for part, stages in todo.items():
        for s in stages:
            attempts[(s, part)] = attempts.get((s, part), 0) + 1
