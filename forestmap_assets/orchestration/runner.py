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
import multiprocessing
import os
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from dagster import DagsterEventType, DagsterInstance, Definitions
from dagster._core.definitions.reconstruct import ReconstructableJob, build_reconstructable_job
from dagster._core.execution.api import (
    _check_execute_job_args,
    _job_with_repository_load_data,
    execute_run_iterator,
)
from dagster._core.storage.defs_state.base import set_defs_state_storage

from forestmap_assets.assets.common import asset_key, job_name
from forestmap_assets.assets.pairs import PAIR_LISTS
from forestmap_assets.io.campaign import Campaign, load_campaign
from forestmap_assets.io.store import default_store_url
from forestmap_assets.orchestration.cluster import dask_cluster
from forestmap_assets.orchestration.events import step_failure_reason
from forestmap_assets.orchestration.instance import (
    campaign_lock,
    get_instance,
    sync_pair_partitions,
    sync_partitions,
)
from forestmap_assets.orchestration.namespace import claim_campaign_name
from forestmap_assets.orchestration.status import (
    campaign_stages,
    changed_pair_inputs,
    changed_scan_files,
    count_attempts,
    direct_states,
    materialised_before,
    observe_pair_inputs,
    observe_scan_files,
    partition_work,
    partitions_of,
    safe_subset,
    stage_parents,
)
from forestmap_assets.orchestration.workspace import EXECUTORS, build_definitions

Progress = Callable[[str], None]


CAMPAIGN_TAG = "forestmap/campaign"
SCAN_TAG = "forestmap/scan"
PAIR_TAG = "forestmap/pair"
SESSION_TAG = "forestmap/session"
QUIET = {"loggers": {"console": {"config": {"log_level": "CRITICAL"}}}}


def campaign_job(folder: str, store_url: str, executor: str, kind: str):
    """Reconstructor of a campaign's asset job (``kind`` ``scan`` or ``campaign``): every
    process that executes a step (multiprocess children, Dask workers) rebuilds it from the
    campaign folder, so the same code runs wherever the step lands."""
    campaign = load_campaign(folder)
    defs = build_definitions([campaign], store_url, executor=executor)
    return defs.resolve_job_def(job_name(campaign, kind))


@dataclass
class RunSummary:
    campaign: Campaign
    ran: list[tuple[str, str | None]] = field(default_factory=list)  # (stage, partition)
    failures: list[tuple[str, str | None, str]] = field(default_factory=list)  # stage, scan, reason
    check_failures: list[tuple[str, str | None, str, str]] = field(default_factory=list)
    run_ids: list[str] = field(default_factory=list)
    not_built: list[str] = field(default_factory=list)
    seconds: float = 0.0
    kept_earlier: set[str] = field(default_factory=set)  # failed scans whose older results stand

    @property
    def left_out(self) -> dict[str, str]:
        """Scans this run could not process (unreadable or damaged file, or a failed per-scan
        stage), each with its first failure: the campaign-level stages ran without them, or,
        for those in ``kept_earlier``, with their results from an earlier run."""
        out: dict[str, str] = {}
        for stage, scan, reason in self.failures:
            if scan in self.campaign.scan_ids and scan not in out:
                out[scan] = reason if stage == "range_images" else f"{stage} failed: {reason}"
        return out


class _Session:
    """One ``run_campaign`` call: launches runs, follows their events, keeps the summary."""
    def __init__(
        self,
        campaign,
        instance,
        executor,
        store_url,
        progress,
        workers,
        dask_address,
        stage_names=(),
        defs: Definitions | None = None,
    ):
        self.campaign = campaign
        self.instance = instance
        self.executor = executor
        self.store_url = store_url
        self.progress = progress
        self.workers = workers
        self.dask_address = dask_address
        self.defs = defs
        self.session = uuid.uuid4().hex[:12]
        self.summary = RunSummary(campaign)
        self.failed: set[tuple[str, str | None]] = set()
        self._stage_of_step = {f"{campaign.key}__{s}": s for s in stage_names}

    def recon(self, kind: str):
        return build_reconstructable_job(
            "forestmap_assets.orchestration.runner",
            "campaign_job",
            reconstructable_args=(str(self.campaign.root), self.store_url, self.executor, kind),
        )

    def run_config(self, concurrent_runs: int) -> dict:
        config: dict = dict(QUIET)
        if self.executor == "multiprocess":
            per_run = max(1, self.workers // max(concurrent_runs, 1))
            config["execution"] = {
                "config": {
                    "max_concurrent": per_run,
                    # children fork from a server that has imported forestmap once
                    "start_method": {
                        "forkserver": {"preload_modules": ["forestmap_assets.orchestration.runner"]}
                    },
                }
            }
        elif self.executor == "dask":
            config["execution"] = {
                "config": {"cluster": {"existing": {"address": self.dask_address}}}
            }
        return config

    def execute(
        self, kind: str, stages: list[str], partition: str | None, concurrent_runs: int
    ) -> bool:
        """One Dagster run of the given stages (one scan partition, or campaign level)."""
        tags = {CAMPAIGN_TAG: self.campaign.key, SESSION_TAG: self.session}
        if partition is not None:
            tags.update({"dagster/partition": partition, (PAIR_TAG if kind == "pair" else SCAN_TAG): partition})
        if self.executor == "in_process" and self.defs is not None:
            # in this process: the job as already built (no reconstruction)
            job_arg, load_data = self.defs.resolve_job_def(job_name(self.campaign, kind)), None
        else:  # rebuilt from the campaign folder in every process that runs a step
            job_arg, load_data = _job_with_repository_load_data(self.recon(kind))
        job_arg, run_config, tags, resolved, op_selection = _check_execute_job_args(
            job_arg=job_arg,
            run_config=self.run_config(concurrent_runs),
            tags=tags,
            op_selection=None,
        )
        run = self.instance.create_run_for_job(
            job_def=job_arg.get_definition(),
            run_config=run_config,
            op_selection=op_selection,
            resolved_op_selection=resolved,
            tags=tags,
            job_code_origin=job_arg.get_python_origin()
            if isinstance(job_arg, ReconstructableJob)
            else None,
            repository_load_data=load_data,
            asset_selection=frozenset(asset_key(self.campaign, s) for s in stages),
        )
        self.summary.run_ids.append(run.run_id)
        where = f"[{partition}] " if partition else ""
        failed_steps: set[str] = set()
        run_failure = ""
        for event in execute_run_iterator(job_arg, run, self.instance):
            stage = self._stage_of_step.get(event.step_key or "")
            if event.event_type == DagsterEventType.ASSET_MATERIALIZATION:
                mat = event.step_materialization_data.materialization
                name = mat.asset_key.path[-1]
                self.summary.ran.append((name, mat.partition))
            elif event.event_type == DagsterEventType.STEP_SUCCESS and stage:
                seconds = event.event_specific_data.duration_ms / 1000.0
                self.progress(f"  {where}{stage} ({seconds:.1f} s)")
            elif event.event_type == DagsterEventType.STEP_FAILURE and stage:
                reason = step_failure_reason(event)
                failed_steps.add(stage)
                self.failed.add((stage, partition))
                self.summary.failures.append((stage, partition, reason))
                self.progress(f"  {where}{stage} FAILED: {reason}")
            elif event.event_type == DagsterEventType.ASSET_CHECK_EVALUATION:
                ev = event.event_specific_data
                if not ev.passed:
                    text = ", ".join(
                        f"{k}={v.value}"
                        for k, v in ev.metadata.items()
                        if not isinstance(v.value, dict)
                    )
                    owner = ev.asset_key.path[-1]
                    self.summary.check_failures.append(
                        (owner, partition, ev.check_name, ev.severity.value)
                    )
                    self.progress(
                        f"  {where}check {owner}.{ev.check_name} failed ({ev.severity.value}): {text}"
                    )
            elif event.event_type == DagsterEventType.RUN_FAILURE:
                err = getattr(event.event_specific_data, "error", None)
                text = err.message if err is not None and err.message else event.message
                run_failure = (text or "run failed").strip().splitlines()[0]
        done = self.instance.get_run_by_id(run.run_id)
        ok = bool(done and done.is_success)
        if not ok:
            # steps that never ran because something upstream failed
            for stage in stages:
                if stage not in failed_steps and (stage, partition) not in set(self.summary.ran):
                    self.failed.add((stage, partition))
            if not failed_steps:
                first = stages[0]
                self.summary.failures.append((first, partition, run_failure or "run failed"))
                self.progress(f"  {where}run FAILED: {run_failure or 'run failed'}")
        return ok

    def sync_pairs(self) -> None:
        """Pair partitions matched to the stored pair lists, their inputs' fingerprints observed
        (issue 17)."""
        sync_pair_partitions(self.instance, self.campaign, self.store_url)
        observe_pair_inputs(self.instance, self.campaign,
                            changed_pair_inputs(self.campaign, self.instance, self.store_url))

    def run_partitions(self, kind: str, todo: dict[str, list[str]]) -> None:
        """One run per scan (``kind`` ``scan``) or pair (``pair``): here one after another, or
        side by side in worker processes (Dagster's run machinery is not thread-safe, so no
        threads)."""
        if self.executor == "in_process" or len(todo) == 1:
            for part, stages in todo.items():
                self.execute(kind, stages, part, 1)
            return
        n = len(todo) if self.executor == "dask" else min(len(todo), self.workers)
        # forked workers start at once (this process has imported everything); they are all
        # forked at the first submit, before this process starts any thread of its own
        ctx = multiprocessing.get_context("fork")
        queue = ctx.Queue()
        base = (
            str(self.campaign.root),
            self.instance.get_ref(),
            self.executor,
            self.store_url,
            self.workers,
            self.dask_address,
            self.session,
        )
        drain = threading.Thread(target=_drain, args=(queue, self.progress), daemon=True)
        try:
            with ProcessPoolExecutor(
                max_workers=n, mp_context=ctx, initializer=_init_worker, initargs=(queue,)
            ) as pool:
                futures = [
                    pool.submit(_partition_worker, base, kind, part, stages, n)
                    for part, stages in todo.items()
                ]
                drain.start()
                for fut in futures:
                    ran, failures, checks, failed, run_ids = fut.result()
                    self.summary.ran.extend(ran)
                    self.summary.failures.extend(failures)
                    self.summary.check_failures.extend(checks)
                    self.summary.run_ids.extend(run_ids)
                    self.failed |= failed
        finally:
            queue.put(None)
            if drain.is_alive():
                drain.join(timeout=5)


_QUEUE = None


def _init_worker(queue) -> None:
    """A forked worker starts its own forkserver for Dagster's multiprocess executor: the one it
    inherits (started by an earlier campaign-level run) is its parent's child, not its own."""
    import multiprocessing.forkserver as forkserver

    global _QUEUE
    _QUEUE = queue
    server = forkserver._forkserver
    server._forkserver_address = server._forkserver_alive_fd = server._forkserver_pid = None
    server._inherited_fds = None
    server._lock = threading.Lock()


def _drain(queue, progress: Progress) -> None:
    while (line := queue.get()) is not None:
        progress(line)


def _partition_worker(base: tuple, kind: str, part: str, stages: list[str], concurrent_runs: int):
    """One scan's or pair's run in a worker process; returns what the parent session records."""
    folder, ref, executor, store_url, workers, dask_address, session_id = base
    with DagsterInstance.from_ref(ref) as instance:
        session = _Session(
            load_campaign(folder),
            instance,
            executor,
            store_url,
            _QUEUE.put if _QUEUE is not None else print,
            workers,
            dask_address,
            stages,
        )
        session.session = session_id
        session.execute(kind, stages, part, concurrent_runs)
        s = session.summary
        return s.ran, s.failures, s.check_failures, session.failed, s.run_ids


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
) -> RunSummary:
    """Materialise every missing or stale asset of a campaign, and nothing else.

    ``stages`` limits the work to those stages and what they read (default: all).
    ``share_namespace``: run a variant folder of a campaign in the original's store namespace on
    purpose (notebook 4); otherwise another folder with the same name is a one-line error.

    ``executor``: ``in_process`` (one run after another in this process), ``multiprocess``
    (Dagster's multiprocess executor, scans' runs side by side, ``workers`` processes in all) or
    ``dask`` (dagster-dask on the cluster at ``dask_address`` / ``$FORESTMAP_DASK_ADDRESS``, else a
    local cluster; put the store on a path every worker sees: ``$FORESTMAP_STORE``).
    """
    if executor not in EXECUTORS:
        raise ValueError(f"--executor: {executor!r} is not one of {', '.join(EXECUTORS)}")
    start = time.perf_counter()
    campaign = load_campaign(folder)
    instance = instance or get_instance()
    store_url = store_url or default_store_url()
    workers = workers or os.cpu_count() or 2
    if not share_namespace:
        claim_campaign_name(campaign, store_url, record=False)  # fail before any work
    defs = build_definitions([campaign], store_url, executor=executor)
    # resolve definitions against this instance (not a stale one a caller left in the context)
    with set_defs_state_storage(instance.defs_state_storage):
        return _run(
            campaign,
            defs,
            instance,
            executor,
            store_url,
            progress,
            workers,
            dask_address,
            stages,
            start,
            share_namespace,
        )


def _run(
    campaign, defs, instance, executor, store_url, progress, workers, dask_address, stages, start,
    share_namespace=False,
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
    with contextlib.ExitStack() as stack:
        stack.enter_context(campaign_lock(instance, campaign, progress))
        if not share_namespace:
            claim_campaign_name(campaign, store_url)  # under the lock: one folder records itself
        if executor == "dask":
            dask_address = stack.enter_context(dask_cluster(dask_address, workers, progress))
        session = _Session(
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
        summary = session.summary
        sync_partitions(instance, campaign)
        observe_scan_files(instance, campaign, changed_scan_files(campaign, instance, defs=defs))
        attempts: dict[tuple[str, str | None], int] = {}
        first = True
        while True:
            if pair_stages:
                session.sync_pairs()
            pairs_now = partitions_of(instance, campaign, "pair")
            states = direct_states(defs, campaign, instance, check_files=False)
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
            scans = partition_work(campaign.scan_ids, scan_stages, due, parents, granularity)
            if first:
                fresh = sum(1 for sid in campaign.scan_ids if sid not in scans)
                progress(
                    f"{campaign.name}: {len(campaign.scan_ids)} scans, {len(scans)} to process, {fresh} up to date"
                    + campaign.prior_note
                )
                first = False
            if scans:
                count_attempts(attempts, scans)
                session.run_partitions("scan", scans)
                continue
            pairs = partition_work(pairs_now, pair_stages, due, parents, granularity)
            level = safe_subset(
                {s for s in level_stages if (s, None) in due},
                {s: [p for p in parents[s] if granularity[p] == "campaign"] for s in level_stages},
            )
            lists = [s for s in PAIR_LISTS if s in level]
            if lists:  # a pair list runs alone with what does not read pairs: its pairs come next
                level = (level - after_pairs) | {lists[0]}
            if pairs:  # the pair lists first, then the pairs, then what reads them
                level -= after_pairs
                if not level:
                    progress(f"  {len(pairs)} pairs to register")
                    count_attempts(attempts, pairs)
                    session.run_partitions("pair", pairs)
                    continue
            if not level:
                break
            stages = [s for s in level_stages if s in level]
            for s in stages:
                attempts[(s, None)] = attempts.get((s, None), 0) + 1
            progress(f"  campaign: {', '.join(stages)}")
            session.execute("campaign", stages, None, 1)
    for stage, scan, _ in summary.failures:
        if scan is not None and materialised_before(instance, campaign, stage, scan):
            summary.kept_earlier.add(scan)
    summary.seconds = time.perf_counter() - start
    return summary
