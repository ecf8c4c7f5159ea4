"""The bulk record index that ``forestmap status`` gives Dagster's stale-status resolver
(orchestration/record_index.py, issue 17): every per-partition query it serves from memory
answers as the event log does, and a stale partition is still stale through it."""

from __future__ import annotations

import itertools

from dagster import (
    AssetKey,
    AssetMaterialization,
    AssetObservation,
    AssetRecordsFilter,
    DagsterInstance,
    DataVersion,
    Definitions,
    StaticPartitionsDefinition,
    asset,
    materialize,
)
from dagster._core.definitions.data_version import (
    DATA_VERSION_TAG,
    CachingStaleStatusResolver,
    StaleStatus,
)

from forestmap_assets.orchestration.record_index import IndexedRecords
from forestmap_assets.orchestration.status import resolver_for_graph

PARTS = StaticPartitionsDefinition(["a", "b", "c"])


def _ids(result) -> list[int]:
    return [r.storage_id for r in result.records]


def test_index_answers_every_query_as_the_event_log():
    instance = DagsterInstance.ephemeral()
    key, source = AssetKey(["c", "x"]), AssetKey(["c", "src"])
    for i, part in itertools.product(range(3), ["a", "b", "c", "a"]):
        instance.report_runless_asset_event(AssetMaterialization(key, partition=part, tags={DATA_VERSION_TAG: f"v{i}"}))
        instance.report_runless_asset_event(AssetObservation(source, partition=part, tags={DATA_VERSION_TAG: f"o{i}"}))
    index = IndexedRecords(instance, [key, source])
    short = IndexedRecords(instance, [key, source], cap=4)  # the newest 4 records a key only
    all_ids = _ids(instance.fetch_materializations(AssetRecordsFilter(asset_key=key), limit=100))
    middle = sorted(all_ids)[len(all_ids) // 2]
    filters = [AssetRecordsFilter(asset_key=k, asset_partitions=parts, before_storage_id=before, after_storage_id=after)
               for k in (key, source) for parts in (None, ["a"], ["b", "c"], ["z"])
               for before in (None, middle) for after in (None, middle - 5)]
    for f, limit, ascending in itertools.product(filters, (1, 3, 100), (False, True)):
        for name, view in itertools.product(("fetch_materializations", "fetch_observations"), (index, short)):
            got = getattr(view, name)(f, limit=limit, ascending=ascending)
            want = getattr(instance, name)(f, limit=limit, ascending=ascending)
            assert _ids(got) == _ids(want), (name, f, limit, ascending)
    for k, source_flag, part, before, after in itertools.product(
            (key, source), (None, True, False), (None, "a", "c"), (None, middle), (None, middle - 5)):
        want = instance.get_latest_data_version_record(k, source_flag, part, before_cursor=before, after_cursor=after)
        for view in (index, short):
            got = view.get_latest_data_version_record(k, source_flag, part, before_cursor=before, after_cursor=after)
            assert (got and got.storage_id) == (want and want.storage_id)
    # a query it does not index goes to the event log
    other = AssetKey(["elsewhere"])
    instance.report_runless_asset_event(AssetMaterialization(other))
    assert len(index.fetch_materializations(AssetRecordsFilter(asset_key=other), limit=5).records) == 1


def test_resolver_reading_the_index_sees_a_stale_partition():
    @asset(key=["c", "up"], partitions_def=PARTS, code_version="1")
    def up(context):
        return 1

    @asset(key=["c", "down"], partitions_def=PARTS, deps=[up], code_version="1")
    def down(context):
        return 2

    instance = DagsterInstance.ephemeral()
    for p in ("a", "b", "c"):
        materialize([up, down], instance=instance, partition_key=p)
    instance.report_runless_asset_event(  # a new version of up/b: down/b is stale
        AssetMaterialization(AssetKey(["c", "up"]), partition="b", tags={DATA_VERSION_TAG: DataVersion("new").value}))
    graph = Definitions(assets=[up, down]).resolve_asset_graph()
    plain = resolver_for_graph(graph, instance)
    fast = resolver_for_graph(graph, instance, IndexedRecords(instance, graph.get_all_asset_keys()))
    assert isinstance(fast, CachingStaleStatusResolver)
    for p in ("a", "b", "c"):
        for k in (AssetKey(["c", "up"]), AssetKey(["c", "down"])):
            assert fast.get_status(k, p) == plain.get_status(k, p)
    assert fast.get_status(AssetKey(["c", "down"]), "b") == StaleStatus.STALE
    assert fast.get_status(AssetKey(["c", "down"]), "a") == StaleStatus.FRESH
