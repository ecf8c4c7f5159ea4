"""One ``forestmap run`` session's Dagster runs (:class:`Session`): each run of a scan, a pair or
the campaign-level stages launched with ``execute_job`` machinery on a reconstructable job
(:func:`campaign_job`), its events followed and summed up in a :class:`RunSummary`; the runs of
many scans or pairs side by side in worker processes (Dagster's run machinery is not
thread-safe, so no threads)."""

from __future__ import annotations

import multiprocessing
import os
import threading
import uuid
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

from dagster import DagsterEventType, DagsterInstance, Definitions
from dagster._core.definitions.reconstruct import ReconstructableJob, build_reconstructable_job
from dagster._core.execution.api import (
    _check_execute_job_args,
    _job_with_repository_load_data,
    execute_run_iterator,
)

from forestmap_assets.assets.common import asset_key, job_name
from forestmap_assets.io.campaign import Campaign, load_campaign
from forestmap_assets.io.store import forget_recent
from forestmap_assets.orchestration import forkserver as fork_server
from forestmap_assets.orchestration.events import step_failure_reason
from forestmap_assets.orchestration.instance import (
    pair_store,
    sync_pair_partitions,
)
from forestmap_assets.orchestration.priority import background
from forestmap_assets.orchestration.status import (
    changed_pair_inputs,
    observe_pair_inputs,
)
from forestmap_assets.orchestration.workspace import build_definitions

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
    settled: bool = False  # the session ended with every stage fresh (recorded as settled)
    level_next: bool = False  # it stopped after the map's stages: the scans are levelled next

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


class Session:
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
        self._pool: ProcessPoolExecutor | None = None
        self._closers: list = []
        self._pool_lock = threading.Lock()
        self._starter: threading.Thread | None = None
        self.pending: dict[tuple[str, str], object] = {}  # (stage, scan) -> future of a late run

    def recon(self, kind: str):
        return build_reconstructable_job(
            "forestmap_assets.orchestration.session",
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
                        "forkserver": {"preload_modules": ["forestmap_assets.orchestration.session"]}
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
        forget_recent()  # the run's range image, remembered by the store (io/store.py)
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

    def read_ahead(self, stages: list[str]) -> None:
        """Start reading the per-scan tables that ``stages`` read column by column (an input's
        metadata ``columns``: the tree list's range images) in a background thread, while the
        stages before them run in this process (in_process; :func:`~forestmap_assets.io.store.read_ahead`)."""
        if self.executor != "in_process" or self.defs is None:
            return
        store = pair_store(self.store_url)
        for stage in stages:
            assets_def = self.defs.get_assets_def(asset_key(self.campaign, stage))
            for d in assets_def.node_def.input_defs:
                key, columns = assets_def.keys_by_input_name.get(d.name), d.metadata.get("columns")
                if key is not None and columns:
                    store.read_ahead(list(key.path), self.campaign.scan_ids, list(columns))

    def sync_pairs(self) -> dict[str, str]:
        """Pair partitions matched to the stored pair lists, their inputs' fingerprints observed
        (issue 17); returns the pairs whose fingerprints changed."""
        sync_pair_partitions(self.instance, self.campaign, self.store_url)
        changed = changed_pair_inputs(self.campaign, self.instance, self.store_url)
        observe_pair_inputs(self.instance, self.campaign, changed)
        return changed

    @property
    def can_run_late(self) -> bool:
        """Whether scans' runs can be left running in the session's workers (in_process)."""
        return self.executor == "in_process" and self.workers > 1

    def runs_in_workers(self, todo: dict[str, list[str]], late: dict[str, list[str]] | None = None) -> bool:
        """Whether :meth:`run_partitions` runs all of ``todo`` in the session's fork-server
        workers, this thread only waiting (its first and third branches; never so with another
        executor: its workers fork from this process)."""
        return self.can_run_late and (bool(late) or len(todo) > 1)

    def run_partitions(
        self, kind: str, todo: dict[str, list[str]], late: dict[str, list[str]] | None = None
    ) -> None:
        """One run per scan (``kind`` ``scan``) or pair (``pair``): here one after another, or
        side by side in worker processes (Dagster's run machinery is not thread-safe, so no
        threads). ``late``: scans' runs queued behind these (:attr:`can_run_late`) and left
        running when they are done, their results collected by :meth:`wait_late`."""
        if self.can_run_late and late:
            self._collect(self._in_process_pool(), kind, todo, self.workers, late=late)
            return
        if len(todo) == 1 or (self.executor == "in_process" and self.workers <= 1):
            for part, stages in todo.items():
                self.execute(kind, stages, part, 1)
            return
        if self.executor == "in_process":
            self._collect(self._in_process_pool(), kind, todo, self.workers)
            return
        n = len(todo) if self.executor == "dask" else min(len(todo), self.workers)
        # forked workers start at once (this process has imported everything); they are all
        # forked at the first submit, before this process starts any thread of its own
        ctx = multiprocessing.get_context("fork")
        queue = ctx.Queue()
        drain = threading.Thread(target=_drain, args=(queue, self.progress), daemon=True)
        try:
            with ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_init_worker,
                                     initargs=(queue, 0, dict(os.environ))) as pool:
                self._collect(pool, kind, todo, n, start=drain.start)
        finally:
            queue.put(None)
            if drain.is_alive():
                drain.join(timeout=5)

    def _in_process_pool(self) -> ProcessPoolExecutor:
        """The session's workers for in_process runs, kept for all its waves: started from a fork
        server that has only imported libraries (:mod:`.forkserver`; this process may have used
        OpenMP, which a fork must not inherit), the cores shared out among them."""
        with self._pool_lock:
            return self._start_pool()

    def _start_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            ctx = fork_server.context()  # started early by `forestmap run`, else now
            queue = ctx.Queue()
            threads = max(1, (os.cpu_count() or 1) // self.workers)
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx, initializer=_init_worker,
                                             initargs=(queue, threads, dict(os.environ)))
            drain = threading.Thread(target=_drain, args=(queue, self.progress), daemon=True)
            drain.start()
            self._closers = [self._pool.shutdown, lambda: queue.put(None), lambda: drain.join(timeout=5)]
        return self._pool

    def close(self) -> None:
        """Stop the session's workers (if any)."""
        if self._starter is not None:
            self._starter.join()
            self._starter = None
        for close in self._closers:
            close()
        self._pool, self._closers = None, []

    def run_late_campaign(self, stages: list[str]) -> None:
        """One campaign-level run of ``stages`` left running in a worker (:attr:`can_run_late`),
        collected by :meth:`wait_late` (issue 16: next_vantage_points beside the map's files)."""
        fut = self._in_process_pool().submit(_partition_worker, self._base(), "campaign", None, stages, 1, late=True)
        self.pending.update({(stage, None): fut for stage in stages})

    def cancel_late(self) -> None:
        """Drop the late runs not started yet and stop following the others, which end on
        their own (the map is made again from levelled scans, and what they make with it)."""
        pending, self.pending = self.pending, {}
        for fut in dict.fromkeys(pending.values()):
            fut.cancel()

    def late_done(self) -> bool:
        """Whether every late run (:meth:`run_partitions`, :meth:`run_late_campaign`) has ended."""
        return all(fut.done() for fut in self.pending.values())

    def wait_late(self) -> None:
        """Collect the late runs (:meth:`run_partitions`)."""
        pending, self.pending = self.pending, {}
        for fut in dict.fromkeys(pending.values()):
            self._record(fut.result())

    def _record(self, result) -> None:
        ran, failures, checks, failed, run_ids = result
        self.summary.ran.extend(ran)
        self.summary.failures.extend(failures)
        self.summary.check_failures.extend(checks)
        self.summary.run_ids.extend(run_ids)
        self.failed |= failed

    def _base(self) -> tuple:
        return (
            str(self.campaign.root),
            self.instance.get_ref(),
            self.executor,
            self.store_url,
            self.workers,
            self.dask_address,
            self.session,
        )

    def start_workers(self) -> None:
        """Start the in_process workers now, in the background, and let each load the campaign's
        definitions and the per-scan libraries while this process works out what is due."""
        if not self.can_run_late:
            return

        def start() -> None:
            pool, base = self._in_process_pool(), self._base()
            for _ in range(self.workers):
                pool.submit(_warm_worker, base)

        self._starter = threading.Thread(target=start, daemon=True)
        self._starter.start()

    def _collect(
        self, pool, kind: str, todo: dict[str, list[str]], n: int, start=None, late=None
    ) -> None:
        base = self._base()
        futures = [pool.submit(_partition_worker, base, kind, part, stages, n) for part, stages in todo.items()]
        for part, stages in (late or {}).items():
            fut = pool.submit(_partition_worker, base, "scan", part, stages, n, late=True)
            self.pending.update({(stage, part): fut for stage in stages})
        if start is not None:
            start()
        for fut in futures:
            self._record(fut.result())


_QUEUE = None


def _init_worker(queue, threads: int = 0, environ: dict | None = None) -> None:
    """A forked worker starts its own forkserver for Dagster's multiprocess executor: the one it
    inherits (started by an earlier campaign-level run) is its parent's child, not its own.
    ``threads``: the numba threads of a worker that computes its steps itself (in_process);
    ``environ``: the session's environment (a fork server keeps the one it started with). Each
    worker then loads the compiled kernels numba has cached (:mod:`.kernel_cache`), and
    remembers the dynamic partition keys it has seen (it lives for one run and deletes none:
    :data:`.event_log.REMEMBER_PARTITIONS`)."""
    import multiprocessing.forkserver as forkserver

    from forestmap_assets.orchestration import event_log
    from forestmap_assets.orchestration.kernel_cache import load_cached_kernels

    global _QUEUE
    _QUEUE = queue
    event_log.REMEMBER_PARTITIONS = True
    if environ is not None:
        os.environ.clear()
        os.environ.update(environ)
    if threads:  # starts numba's threads
        import numba

        from forestmap_assets.io._projection_kernels import without_tbb_warning

        with without_tbb_warning():
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        _limit_thread_pools(threads)
    server = forkserver._forkserver
    server._forkserver_address = server._forkserver_alive_fd = server._forkserver_pid = None
    server._inherited_fds = None
    server._lock = threading.Lock()
    load_cached_kernels()  # in every worker, before its first task (numba's threads may start)


def _limit_thread_pools(threads: int) -> None:
    """The libraries' own thread pools sized like numba's: OpenBLAS and OpenMP (threadpoolctl)
    and Arrow's (Parquet reads and writes). At one thread per core per worker their idle threads
    no longer spin beside the other workers' steps: a rendered survey's per-scan stages 3.2 ->
    2.9 s a scan on two workers (issue 16)."""
    import pyarrow as pa
    from threadpoolctl import threadpool_limits

    threadpool_limits(threads)
    pa.set_cpu_count(threads)


def _drain(queue, progress: Progress) -> None:
    while (line := queue.get()) is not None:
        progress(line)


_WORKER: dict = {}  # per worker process: instance, campaign and (in_process) definitions


def _load_worker(base: tuple) -> None:
    folder, ref, executor, store_url, *_ = base
    if _WORKER.get("base") != base:
        campaign = load_campaign(folder)
        defs = build_definitions([campaign], store_url, executor=executor) if executor == "in_process" else None
        _WORKER.update(base=base, instance=DagsterInstance.from_ref(ref), campaign=campaign, defs=defs)


def _warm_worker(base: tuple) -> None:
    """A worker's first task (:meth:`Session.start_workers`): the campaign, its definitions, the
    instance, and the libraries of the per-scan stages."""
    import open3d  # noqa: F401
    import scipy.spatial  # noqa: F401

    _load_worker(base)


def _partition_worker(
    base: tuple, kind: str, part: str | None, stages: list[str], concurrent_runs: int, late: bool = False
):
    """One scan's, pair's or (``part`` None) campaign-level run in a worker process; returns what
    the parent session records. ``late``: a where-to-scan-next run, at a lower priority than the
    map's stages beside it (:mod:`.priority`)."""
    folder, ref, executor, store_url, workers, dask_address, session_id = base
    _load_worker(base)
    session = Session(
        _WORKER["campaign"],
        _WORKER["instance"],
        executor,
        store_url,
        _QUEUE.put if _QUEUE is not None else print,
        workers,
        dask_address,
        stages,
        _WORKER["defs"],
    )
    session.session = session_id
    with background(late):
        session.execute(kind, stages, part, concurrent_runs)
    s = session.summary
    return s.ran, s.failures, s.check_failures, session.failed, s.run_ids
