"""Materialising a campaign through Dagster (``forestmap run``). :func:`run_campaign` works in
waves: it asks the stale-status resolver (:mod:`.status`) which partitions are missing or stale by
their own cause, launches exactly those, and asks again (a re-run that reproduced the same content
hash leaves its downstream fresh). Per-scan assets run as one Dagster run per scan partition (a
corrupt scan fails only its own partitions), then ``candidate_pairs``, then one run per pair
partition (issue 17; the pair set kept equal to the stored pair lists), then the campaign-level
assets that read the pairs. Every run is a real Dagster run in the persistent instance, launched
with ``execute_job`` machinery on a reconstructable job (:func:`campaign_job`) so that Dagster's
multiprocess and Dask executors run the same code; a per-campaign lock in the instance folder
makes a second run of one campaign wait, after which it finds everything fresh."""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pyarrow as pa
from dagster import DagsterInstance
from dagster._core.storage.defs_state.base import set_defs_state_storage

from forestmap_assets.assets.pairs import PAIR_LISTS, PAIR_SCAN_INPUTS
from forestmap_assets.io.campaign import load_campaign
from forestmap_assets.io.store import default_store_url
from forestmap_assets.orchestration.cluster import dask_cluster
from forestmap_assets.orchestration.instance import (
    campaign_lock,
    get_instance,
    is_settled,
    mark_settled,
    settled_key,
    sync_partitions,
)
from forestmap_assets.orchestration.levelling import level_campaign, tilts_to_level
from forestmap_assets.orchestration.namespace import claim_campaign_name
from forestmap_assets.orchestration.session import (  # noqa: F401  (re-exported)
    CAMPAIGN_TAG,
    PAIR_TAG,
    QUIET,
    SCAN_TAG,
    SESSION_TAG,
    RunSummary,
    Session,
    campaign_job,
)
from forestmap_assets.orchestration.status import (
    campaign_stages,
    changed_scan_files,
    count_attempts,
    direct_states,
    materialised_before,
    observe_scan_files,
    partition_work,
    partitions_of,
    safe_subset,
    stage_parents,
)
from forestmap_assets.orchestration.workspace import EXECUTORS, build_definitions

Progress = Callable[[str], None]


def run_campaign(
    folder: str | Path,
    *,
    executor: str = "in_process",
    store_url: str | None = None,
    progress: Progress = print,
    instance: DagsterInstance | None = None,
    workers: int | None = None,
    dask_address: str | None = None,
    stages: list[str] | None = None,
    share_namespace: bool = False,
    idle: Callable[[], None] | None = None,
    map_ready: Callable[[RunSummary], None] | None = None,
) -> RunSummary:
    """Materialise every missing or stale asset of a campaign, and nothing else.

    ``stages`` limits the work to those stages and what they read (default: all).
    ``share_namespace``: run a variant folder of a campaign in the original's store namespace on
    purpose (notebook 4); otherwise another folder with the same name is a one-line error.
    ``idle``: work for a background thread of this process while it waits for the pairs in
    worker processes, joined before anything runs here again (the CLI imports the libraries of
    its exports); not run when nothing waits so.
    ``map_ready``: called once, in this thread, when this session has changed the map (a pair or
    a campaign-level stage ran) and only the where-to-scan-next stages are left (issue 16: they
    never delay the map; the CLI writes the map's files here). Those stages then run beside it
    in a worker when their per-scan inputs are done, else after it.

    ``executor``: ``in_process`` (each run computes its steps in its own process; the scans' and
    then the pairs' runs side by side in ``workers`` worker processes, one after another in this
    process with ``workers=1``), ``multiprocess`` (Dagster's multiprocess executor, the runs side
    by side, ``workers`` processes in all) or
    ``dask`` (dagster-dask on the cluster at ``dask_address`` / ``$FORESTMAP_DASK_ADDRESS``, else a
    local cluster; put the store on a path every worker sees: ``$FORESTMAP_STORE``).
    """
    if executor not in EXECUTORS:
        raise ValueError(f"--executor: {executor!r} is not one of {', '.join(EXECUTORS)}")
    start = time.perf_counter()
    campaign = load_campaign(folder)
    instance = instance or get_instance()
    store_url = store_url or default_store_url()
    # no more workers than scans: a one-scan campaign runs in this process, its reading not
    # slowed by idle workers starting up (a 30 M-point LAZ: 4.6 s instead of 3.2 s)
    workers = max(1, min(workers or os.cpu_count() or 2, len(campaign.scan_ids)))
    if not share_namespace:
        claim_campaign_name(campaign, store_url, record=False)  # fail before any work
    defs = build_definitions([campaign], store_url, executor=executor)
    full = stages is None
    checked: list = []  # the stored scan_tilts' verdict, read once when the map is final

    def due():
        if not checked:
            checked.append(tilts_to_level(campaign, store_url) if full else None)
        return checked[0]

    def ready(summary: RunSummary) -> None:  # not for a map whose scans are levelled next
        if map_ready is not None and due() is None:
            map_ready(summary)

    # resolve definitions against this instance (not a stale one a caller left in the context)
    with set_defs_state_storage(instance.defs_state_storage):
        summary = _run(campaign, defs, instance, executor, store_url, progress, workers, dask_address,
                       stages, start, share_namespace, idle, ready if map_ready is not None else None,
                       levelling_next=lambda: due() is not None)
        tilts = due() if summary.level_next or not summary.failures else None
        if tilts is None:
            return summary
        try:
            progress(level_campaign(campaign, tilts))  # the scans tilted: levelled, and again
        except OSError as exc:  # a read-only campaign folder: the map as it is, said so
            progress(f"scans tilted, but {exc.filename or 'levelling.yaml'} cannot be written "
                     f"({exc.strerror or exc}); the map keeps their tilt")
            if map_ready is not None:
                map_ready(summary)
            if not summary.level_next:
                return summary
            rest = _run(campaign, defs, instance, executor, store_url, progress, workers, dask_address,
                        stages, start, share_namespace)  # where to scan next, left for the levelled map
            rest.ran[:0] = summary.ran
            return rest
        campaign = load_campaign(folder)
        defs = build_definitions([campaign], store_url, executor=executor)
        again = _run(campaign, defs, instance, executor, store_url, progress, workers, dask_address,
                     stages, start, share_namespace, None, map_ready)
        again.ran[:0] = summary.ran
        return again


def _run(
    campaign, defs, instance, executor, store_url, progress, workers, dask_address, stages, start,
    share_namespace=False, idle=None, map_ready=None, levelling_next: Callable[[], bool] | None = None,
) -> RunSummary:
    parents = stage_parents(defs, campaign)
    stages_all = campaign_stages(defs, campaign)
    if stages is not None:
        unknown = sorted(set(stages) - {s for s, _ in stages_all})
        if unknown:
            raise ValueError(
                f"unknown stage {unknown[0]!r} (stages: {', '.join(s for s, _ in stages_all)})"
            )
        wanted = set(stages)
        for stage, _ in reversed(stages_all):
            if stage in wanted:
                wanted |= set(parents[stage])
        stages_all = [(s, g) for s, g in stages_all if s in wanted]
    granularity = dict(stages_all)
    scan_stages = [s for s, g in stages_all if g == "scan"]
    pair_stages = [s for s, g in stages_all if g == "pair"]
    level_stages = [s for s, g in stages_all if g == "campaign"]
    # campaign-level stages that read a pair stage (directly or through another stage) wait
    # while any pair is due; the others (candidate_pairs) run before the pairs
    after_pairs: set[str] = set()
    for stage, _ in stages_all:
        if any(granularity.get(p) == "pair" or p in after_pairs for p in parents[stage]):
            after_pairs.add(stage)
    late_stages = _late_stages(scan_stages, parents, granularity)
    # the campaign-level where-to-scan-next stages (next_vantage_points) and what the map is
    explore = _readers_of(set(late_stages), parents, stages_all) & set(level_stages)
    map_stages = {*pair_stages, *(set(level_stages) - explore)}
    with contextlib.ExitStack() as stack:
        stack.enter_context(campaign_lock(instance, campaign, progress))
        if not share_namespace:
            claim_campaign_name(campaign, store_url)  # under the lock: one folder records itself
        if executor == "dask":
            dask_address = stack.enter_context(dask_cluster(dask_address, workers, progress))
        session = Session(
            campaign,
            instance,
            executor,
            store_url,
            progress,
            workers,
            dask_address,
            [s for s, _ in stages_all],
            defs,
        )
        stack.callback(session.close)
        summary = session.summary
        sync_partitions(instance, campaign)
        observe_scan_files(instance, campaign, changed_scan_files(campaign, instance, defs=defs))
        settle = stages is None  # a whole session may record that it left everything fresh
        if settle and is_settled(instance, campaign, settled_key(instance, campaign, defs, store_url)):
            n = len(campaign.scan_ids)
            progress(f"{campaign.name}: {n} scans, 0 to process, {n} up to date" + campaign.prior_note)
            summary.settled = True
            summary.seconds = time.perf_counter() - start
            return summary
        session.start_workers()  # likely work to do: the workers start while the states are read
        if session.can_run_late:
            # this process runs the campaign-level stages only, and its first read of the range
            # images (the tree list's) took mimalloc 1.2-1.4 s, the system allocator 0.4-0.5 s
            pa.set_memory_pool(pa.system_memory_pool())
        writer: _Writer | None = None
        attempts: dict[tuple[str, str | None], int] = {}
        first = True
        # the states read so far stand until something they depend on materialises (the campaign
        # is locked: only this session writes it); each wave reads again what ran and its readers
        states: dict[tuple[str, str | None], str] = {}
        read_pairs: list[str] | None = None
        accounted = 0
        depends = _dependencies(parents, granularity)
        while True:
            ran = {stage for stage, _ in summary.ran[accounted:]}
            accounted = len(summary.ran)
            # the pair partitions and their inputs' fingerprints change only with the pair lists
            # and the scans' stages the pairs read (about 200 queries on 50 scans: not each wave)
            changed_pairs = None
            if pair_stages and (not states or ran & {*PAIR_LISTS, *PAIR_SCAN_INPUTS}):
                changed_pairs = session.sync_pairs()
            pairs_now = partitions_of(instance, campaign, "pair")
            read = None if not states else ran | _readers_of(ran, depends, stages_all)
            if read is not None and pairs_now != read_pairs:  # pairs added or dropped
                states = {k: v for k, v in states.items() if granularity.get(k[0]) != "pair"}
                read |= set(pair_stages) | _readers_of(set(pair_stages), depends, stages_all)
            elif read is not None and changed_pairs == {} and not ran & set(pair_stages):
                # the pair lists ran (retry_pairs, usually listing nothing new) but no pair's
                # inputs changed: the pairs' states stand (about 300 statuses on 50 scans)
                read -= set(pair_stages)
            if read is None or read:
                states = {**states, **direct_states(defs, campaign, instance, check_files=False, only=read)}
            read_pairs = pairs_now
            # a stage that ran and is still not fresh gets one more chance (a stage that reads
            # its own downstream's partitions, retry_pairs, settles on the second run)
            due = {
                k
                for k, v in states.items()
                if v != "fresh" and attempts.get(k, 0) < 2 and k[0] in granularity
            }
            # never retry what failed, nor what reads something that failed in this session
            blocked = set(session.failed)
            for stage, g in stages_all:
                for part in campaign.scan_ids if g == "scan" else pairs_now if g == "pair" else [None]:
                    if any(
                        (p, part) in blocked for p in parents.get(stage, []) if granularity[p] == g
                    ):
                        blocked.add((stage, part))
            due -= blocked
            due -= set(session.pending)  # late scans' runs still going
            # where-to-scan-next stages wait for the pairs' runs, then run beside the campaign's
            # stages in the workers (``background``); without workers to leave them in (one
            # worker, another executor) after the map's stages, when nothing else is due
            late = partition_work(campaign.scan_ids, late_stages, due, parents, granularity)
            background = late if session.can_run_late else {}
            early = [s for s in scan_stages if s not in late_stages] if late else scan_stages
            scans = partition_work(campaign.scan_ids, early, due, parents, granularity)
            if first:
                todo = set(scans) | set(late)
                progress(
                    f"{campaign.name}: {len(campaign.scan_ids)} scans, {len(todo)} to process, "
                    f"{len(campaign.scan_ids) - len(todo)} up to date"
                    + campaign.prior_note
                )
                first = False
            if scans:
                count_attempts(attempts, scans)
                session.run_partitions("scan", scans)
                continue
            pairs = partition_work(pairs_now, pair_stages, due, parents, granularity)
            waiting = _readers_of({s for s, _ in session.pending} | set().union(*late.values()), parents, stages_all)
            level = safe_subset(
                {s for s in level_stages if (s, None) in due and s not in waiting},
                {s: [p for p in parents[s] if granularity[p] == "campaign"] for s in level_stages},
            )
            # candidate_pairs runs with what does not read pairs: its pairs come next. retry_pairs
            # runs with the stages after it: it usually lists nothing, and when it lists pairs,
            # they run and the stages after them run again
            if map_ready is not None and level - explore:
                # the map's stages first: where to scan next runs beside its files (a re-run
                # where only the campaign's stages changed had next_vantage_points before them)
                level -= explore
            if PAIR_LISTS[0] in level:
                level = (level - after_pairs) | {PAIR_LISTS[0]}
            if pairs:  # the pair lists first, then the pairs, then what reads them
                level -= after_pairs
                if not level:
                    progress(f"  {len(pairs)} pairs to register")
                    count_attempts(attempts, pairs)
                    count_attempts(attempts, background)
                    # the idle work only while this thread waits for the pairs' workers: a
                    # thread importing libraries beside steps that import them here can see a
                    # module half initialised (ImportError, matplotlib.colors)
                    warm = None
                    if idle is not None and session.runs_in_workers(pairs, background):
                        warm = threading.Thread(target=idle, daemon=True)
                        warm.start()
                        idle = None
                    session.run_partitions("pair", pairs, late=background)
                    if warm is not None:
                        warm.join()
                    continue
            if map_ready is not None and not pairs and level <= explore and any(
                s in map_stages for s, _ in summary.ran
            ):  # the map is final: its files first, the where-to-scan-next stages beside or after
                if levelling_next is not None and not summary.failures and levelling_next():
                    # its scans are levelled and the run goes again: where to scan next from
                    # this map would be thrown away (an unlevelled Sylva survey 2.8 s sooner)
                    session.cancel_late()
                    summary.level_next = True
                    break
                if session.pending and session.late_done():  # collected, then read again
                    session.wait_late()
                    continue
                # scans' where-to-scan-next runs still going: the map's files in a thread, and
                # the stages after those runs start in a worker as soon as they end
                threaded = bool(session.pending) and session.can_run_late and not late
                if level and session.can_run_late and not late and not session.pending:
                    _run_beside(session, attempts, [s for s in level_stages if s in level], progress)
                    level = set()
                if threaded:
                    writer = _Writer(map_ready, summary)
                else:
                    map_ready(summary)
                map_ready = None
            if writer is not None and writer.is_alive() and level and level <= explore:
                _run_beside(session, attempts, [s for s in level_stages if s in level], progress)
                continue
            if not level and (late or session.pending):
                if late:  # nothing else to do: the late stages run now
                    count_attempts(attempts, late)
                    session.run_partitions("scan", late)
                session.wait_late()
                continue
            if not level:
                if settle and not session.failed and all(
                    v == "fresh" for k, v in states.items() if k[0] in granularity
                ):
                    mark_settled(instance, campaign, settled_key(instance, campaign, defs, store_url))
                    summary.settled = True
                break
            stages = [s for s in level_stages if s in level]
            for s in stages:
                attempts[(s, None)] = attempts.get((s, None), 0) + 1
            progress(f"  campaign: {', '.join(stages)}")
            if background and PAIR_LISTS[0] not in stages:  # beside this run, in the workers
                count_attempts(attempts, background)
                session.run_partitions("scan", {}, late=background)
            session.read_ahead(stages[1:])  # beside the stages before them
            session.execute("campaign", stages, None, 1)
        if writer is not None:
            writer.finish()
    for stage, scan, _ in summary.failures:
        if scan is not None and materialised_before(instance, campaign, stage, scan):
            summary.kept_earlier.add(scan)
    summary.seconds = time.perf_counter() - start
    return summary


def _run_beside(session: Session, attempts: dict, run: list[str], progress: Callable[[str], None]) -> None:
    """The campaign-level where-to-scan-next stages ``run`` left running in a worker beside the
    map's files (issue 16)."""
    count_attempts(attempts, {None: run})
    progress(f"  campaign: {', '.join(run)} (beside the map's files)")
    session.run_late_campaign(run)


class _Writer(threading.Thread):
    """``map_ready(summary)`` (the map's files) in a thread of this process, its error raised
    where the session waits for it (:meth:`finish`)."""

    def __init__(self, map_ready: Callable, summary: RunSummary):
        super().__init__(name="map-files")
        self._call, self._error = (lambda: map_ready(summary)), None
        self.start()

    def run(self) -> None:
        try:
            self._call()
        except BaseException as exc:  # noqa: BLE001 - raised again in the session's thread
            self._error = exc

    def finish(self) -> None:
        self.join()
        if self._error is not None:
            raise self._error


def _late_stages(scan_stages: list[str], parents: dict[str, list[str]], granularity: dict[str, str]) -> list[str]:
    """Per-scan stages that neither the pairs' runs (:data:`.pairs.PAIR_SCAN_INPUTS`) nor the
    pair lists read, directly or through another stage: the where-to-scan-next stages
    (occlusion boundaries, issue 16), which run late, beside the campaign-level stages."""
    needed = {s for s in PAIR_SCAN_INPUTS if s in granularity}
    needed |= {p for s in PAIR_LISTS if s in granularity for p in parents[s]}
    frontier = list(needed)
    while frontier:
        for p in parents.get(frontier.pop(), []):
            if p not in needed:
                needed.add(p)
                frontier.append(p)
    return [s for s in scan_stages if s not in needed]


def _dependencies(parents: dict[str, list[str]], granularity: dict[str, str]) -> dict[str, list[str]]:
    """The stage graph plus what a pair's run reads outside it: the per-scan stages of its two
    scans (:data:`.pairs.PAIR_SCAN_INPUTS`) and the pair lists."""
    extra = [s for s in (*PAIR_SCAN_INPUTS, *PAIR_LISTS) if s in granularity]
    return {s: [*ps, *extra] if granularity.get(s) == "pair" else ps for s, ps in parents.items()}


def _readers_of(stages: set[str], parents: dict[str, list[str]], stages_all) -> set[str]:
    """Every stage that reads one of ``stages``, directly or through another stage."""
    out: set[str] = set()
    for stage, _ in stages_all:  # in graph order
        if any(p in stages or p in out for p in parents[stage]):
            out.add(stage)
    return out
