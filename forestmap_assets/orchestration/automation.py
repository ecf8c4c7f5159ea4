"""Automation: the scan-file sensor, the nightly schedule, declarative automation of the
campaign-level assets, and the ``process_campaign`` job.

- ``scan_files_sensor`` looks at every campaign folder under the data root. For a campaign
  whose definitions are loaded and whose manifest is unchanged it adds missing scan partitions
  (``SensorResult.dynamic_partitions_requests``), records changed scan files as observations of
  the ``scan_files`` source asset, and requests one per-scan run for each new or changed scan
  (run key = scan + content hash, so a scan is processed once per content, and a corrupt file is
  not retried until it changes). A new campaign folder, or one whose ``campaign.yaml`` changed
  since the code location was loaded, has no (or outdated) asset definitions in the running code
  location: for it the sensor requests one ``process_campaign`` run, which materialises the
  campaign with fresh definitions through the same runner as ``forestmap run``.
- ``campaign_automation`` evaluates the campaign-level assets' automation condition
  (:func:`~forestmap_assets.assets.follows_its_inputs`): once a scan's runs have produced new
  submaps, registration, optimal map, residual checks, integrated map and tree list follow,
  each only when an input's data version actually changed.
- ``nightly_reprocessing`` (03:00) requests a ``process_campaign`` run for every campaign with
  anything missing or stale, and skips when everything is fresh.

The sensors and the schedule start stopped (turn them on in the UI's Automation page), or
running when ``$FORESTMAP_AUTOMATION`` is ``on``.
"""

# (no ``from __future__ import annotations``: Dagster reads the op's config annotation at runtime)


import hashlib
import json
import os
from collections.abc import Iterable
from pathlib import Path

from dagster import (
    AssetObservation,
    AssetSelection,
    AutomationConditionSensorDefinition,
    Config,
    DefaultScheduleStatus,
    DefaultSensorStatus,
    Definitions,
    Failure,
    OpExecutionContext,
    RunRequest,
    SensorResult,
    SkipReason,
    in_process_executor,
    job,
    op,
    schedule,
    sensor,
)
from dagster._core.definitions.data_version import DATA_VERSION_TAG, StaleStatus

from forestmap_assets.assets.common import (
    CAMPAIGN_STAGES,
    asset_key,
    job_name,
    pair_partitions,
    scan_partitions,
    screened,
)
from forestmap_assets.io.campaign import MANIFEST, Campaign, CampaignError, load_campaign

PROCESS_JOB = "process_campaign"
CAMPAIGN_TAG = "forestmap/campaign"
NIGHTLY_CRON = "0 3 * * *"


def _running() -> bool:
    return os.environ.get("FORESTMAP_AUTOMATION", "").lower() in ("on", "1", "true", "running")


# --- the process_campaign job ---------------------------------------------------------------


class ProcessCampaignConfig(Config):
    folder: str
    exports: bool = True


@op(name="materialise_campaign", description="Materialise every missing or stale asset of one "
    "campaign through the forestmap runner (fresh definitions from its folder), then write its "
    "exports to CAMPAIGN/outputs.")
def process_campaign_op(context: OpExecutionContext, config: ProcessCampaignConfig) -> None:
    from forestmap_assets.orchestration.runner import run_campaign

    summary = run_campaign(config.folder, instance=context.instance, progress=context.log.info)
    if summary.failures:
        stage, scan, reason = summary.failures[0]
        where = f"{stage}[{scan}]" if scan else stage
        raise Failure(description=f"{where} failed: {reason}",
                      metadata={"failures": len(summary.failures), "runs": len(summary.run_ids)})
    context.log.info(f"{summary.campaign.name}: {len(summary.ran)} asset partitions materialised "
                     f"in {len(summary.run_ids)} runs ({summary.seconds:.1f} s)")
    if config.exports and summary.ran:
        from forestmap_assets.orchestration.timings import stage_timings_or_note
        from forestmap_assets.outputs.exports import write_exports

        timings = stage_timings_or_note(summary.campaign, context.instance)
        written = write_exports(summary.campaign, summary.campaign.root / "outputs", timings=timings)
        context.log.info("outputs written: " + ", ".join(str(p) for p in written))


@job(name=PROCESS_JOB, executor_def=in_process_executor,
     description="One campaign, end to end, with exactly the work its caching leaves to do.")
def process_campaign_job():
    process_campaign_op()


def process_request(campaign: Campaign, run_key: str | None) -> RunRequest:
    return RunRequest(
        job_name=PROCESS_JOB,
        run_key=run_key,
        run_config={"ops": {"materialise_campaign": {"config": {"folder": str(campaign.root)}}}},
        tags={CAMPAIGN_TAG: campaign.key},
    )


# --- file fingerprints with a stat cache (the sensor's cursor) -----------------------------------


class FileCursor:
    """``{path: [size, mtime_ns, content hash]}``: a file is hashed again only when its size
    or modification time changed."""

    def __init__(self, text: str | None):
        self.files: dict[str, list] = json.loads(text) if text else {}

    def to_json(self) -> str:
        return json.dumps(self.files, sort_keys=True)

    def fingerprint(self, path: Path, extra: str = "") -> str:
        try:
            st = path.stat()
        except OSError:
            return "missing"
        key = str(path)
        cached = self.files.get(key)
        if cached and cached[0] == st.st_size and cached[1] == st.st_mtime_ns and cached[3] == extra:
            return cached[2]
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        h.update(extra.encode())
        self.files[key] = [st.st_size, st.st_mtime_ns, h.hexdigest()[:20], extra]
        return self.files[key][2]


def scan_fingerprint(campaign: Campaign, sid: str, cursor: FileCursor) -> str:
    """The scan's content hash as :meth:`Campaign.scan_fingerprint` computes it (file + tilt +
    angular step), through the stat cache."""
    entry = campaign.scan(sid)
    if not entry.path.is_file():
        return "missing"
    cached = cursor.files.get(str(entry.path))
    st = entry.path.stat()
    extra = repr((entry.tilt_deg, campaign.angular_step_deg))
    if cached and cached[0] == st.st_size and cached[1] == st.st_mtime_ns and cached[3] == extra:
        return cached[2]
    fp = campaign.scan_fingerprint(sid)
    cursor.files[str(entry.path)] = [st.st_size, st.st_mtime_ns, fp, extra]
    return fp


def manifest_fingerprint(root: Path) -> str:
    try:
        return hashlib.sha256((Path(root) / MANIFEST).read_bytes()).hexdigest()[:20]
    except OSError:
        return "missing"


# --- the sensor --------------------------------------------------------------------------------


def _campaign_status_fresh(campaign: Campaign, instance) -> bool:
    """Whether every asset of the campaign (fresh definitions) is fresh in the instance."""
    from forestmap_assets.orchestration.status import stage_states
    from forestmap_assets.orchestration.workspace import build_definitions

    defs = build_definitions([campaign])
    return all(s.state == "fresh" for s in stage_states(defs, campaign, instance))


def build_scan_files_sensor(loaded: list[Campaign], scan_jobs: list):
    """The sensor for the campaigns whose definitions are ``loaded`` (see module docstring);
    ``scan_jobs`` are their per-scan jobs."""
    from forestmap_assets.orchestration.workspace import (
        build_definitions,
        discover_campaign_folders,
    )

    by_key = {c.key: c for c in loaded}
    manifests = {c.key: manifest_fingerprint(c.root) for c in loaded}

    @sensor(
        name="scan_files_sensor",
        minimum_interval_seconds=60,
        jobs=[process_campaign_job, *scan_jobs],
        default_status=DefaultSensorStatus.RUNNING if _running() else DefaultSensorStatus.STOPPED,
        description="New or changed scan files and new campaign folders under the data root: "
        "adds scan partitions and requests exactly the per-scan runs needed (one per new or "
        "changed scan); keeps the pair partitions and requests one run per pair whose inputs "
        "changed; a new or edited campaign gets one process_campaign run.",
    )
    def scan_files_sensor(context) -> SensorResult | SkipReason:
        state = json.loads(context.cursor) if context.cursor else {}
        cursor = FileCursor(json.dumps(state.get("files", {})))
        handled: dict[str, str] = state.get("handled", {})
        runs: list[RunRequest] = []
        partitions: list = []
        observations: list[AssetObservation] = []
        repo = context.repository_def
        graph = repo.asset_graph if repo is not None else build_definitions(loaded).resolve_asset_graph()
        for folder in discover_campaign_folders():
            try:
                campaign = load_campaign(folder)
            except CampaignError as exc:
                context.log.warning(str(exc))
                continue
            fps = {sid: scan_fingerprint(campaign, sid, cursor) for sid in campaign.scan_ids}
            known = by_key.get(campaign.key)
            if known is None or known.root != campaign.root or manifest_fingerprint(campaign.root) != manifests[campaign.key]:
                # no (or outdated) definitions in this code location: the runner, with fresh ones
                content = hashlib.sha256(
                    (manifest_fingerprint(campaign.root) + json.dumps(fps, sort_keys=True)).encode()
                ).hexdigest()[:16]
                token = f"{campaign.key}:{content}"
                if handled.get(str(campaign.root)) == token:
                    continue
                handled[str(campaign.root)] = token
                if _campaign_status_fresh(campaign, context.instance):
                    continue
                context.log.info(f"{campaign.root}: new or edited campaign; requesting {PROCESS_JOB}")
                runs.append(process_request(campaign, token))
                continue
            for runs_, parts_, obs_ in (_scan_requests(context.instance, graph, campaign, fps),
                                        _pair_requests(context.instance, campaign)):
                runs.extend(runs_)
                partitions.extend(parts_)
                observations.extend(obs_)
        cursor_text = json.dumps({"files": cursor.files, "handled": handled}, sort_keys=True)
        if not (runs or partitions or observations):
            return SensorResult(skip_reason=SkipReason("no new or changed scans"), cursor=cursor_text)
        return SensorResult(run_requests=runs, dynamic_partitions_requests=partitions,
                            asset_events=observations, cursor=cursor_text)

    return scan_files_sensor


def _scan_requests(instance, graph, campaign: Campaign, fps: dict[str, str]):
    """Partition requests, observations and per-scan run requests of one loaded campaign."""
    from forestmap_assets.orchestration.status import resolver_for_graph

    parts = scan_partitions(campaign)
    existing = set(instance.get_dynamic_partitions(parts.name))
    partitions = []
    new = [s for s in campaign.scan_ids if s not in existing]
    if new:
        partitions.append(parts.build_add_request(new))
    gone = sorted(existing - set(campaign.scan_ids))
    if gone:
        partitions.append(parts.build_delete_request(gone))
    resolver = resolver_for_graph(graph, instance)
    files_key = asset_key(campaign, "scan_files")
    images_key = asset_key(campaign, "range_images")
    runs, observations = [], []
    for sid in campaign.scan_ids:
        fp = fps[sid]
        changed = sid in new or resolver.get_current_data_version(files_key, sid).value != fp
        missing = sid in new or resolver.get_status(images_key, sid) == StaleStatus.MISSING
        if changed:
            observations.append(AssetObservation(asset_key=files_key, partition=sid,
                                                 tags={DATA_VERSION_TAG: fp}))
        if changed or missing:
            runs.append(RunRequest(
                job_name=job_name(campaign, "scan"), partition_key=sid,
                run_key=f"{campaign.key}:{sid}:{fp}",
                tags={CAMPAIGN_TAG: campaign.key, "forestmap/scan": sid},
            ))
    return runs, partitions, observations


def _pair_requests(instance, campaign: Campaign):
    """Pair partitions matched to the stored pair lists, observations of changed pair inputs and
    one per-pair run for each (issue 17), as :func:`_scan_requests` does for scans."""
    from forestmap_assets.assets.pairs import latest_data_version, pair_fingerprints
    from forestmap_assets.orchestration.instance import wanted_pairs

    parts = pair_partitions(campaign)
    existing = set(instance.get_dynamic_partitions(parts.name))
    rows = wanted_pairs(campaign)
    partitions = []
    new = sorted(set(rows["pair"]) - existing)
    gone = sorted(existing - set(rows["pair"]))
    if new:
        partitions.append(parts.build_add_request(new))
    if gone:
        partitions.append(parts.build_delete_request(gone))
    key = asset_key(campaign, "pair_inputs")
    runs, observations = [], []
    for pair, fp in pair_fingerprints(campaign, instance, rows).items():
        if latest_data_version(instance, key, pair, source=True) != fp:
            observations.append(AssetObservation(asset_key=key, partition=pair, tags={DATA_VERSION_TAG: fp}))
            runs.append(RunRequest(
                job_name=job_name(campaign, "pair"), partition_key=pair, run_key=f"{campaign.key}:{pair}:{fp}",
                tags={CAMPAIGN_TAG: campaign.key, "forestmap/pair": pair},
            ))
    return runs, partitions, observations


# --- the nightly schedule ----------------------------------------------------------------------


@schedule(
    name="nightly_reprocessing",
    cron_schedule=NIGHTLY_CRON,
    job=process_campaign_job,
    default_status=DefaultScheduleStatus.RUNNING if _running() else DefaultScheduleStatus.STOPPED,
    description="Every night, one process_campaign run per campaign with anything missing or "
    "stale (changed parameters, scans or code versions); nothing when all is fresh.",
)
def nightly_reprocessing(context):
    from forestmap_assets.orchestration.workspace import discover_campaign_folders

    requests = []
    stamp = context.scheduled_execution_time.strftime("%Y-%m-%d") if context.scheduled_execution_time else "now"
    for folder in discover_campaign_folders():
        try:
            campaign = load_campaign(folder)
        except CampaignError as exc:
            context.log.warning(str(exc))
            continue
        if not _campaign_status_fresh(campaign, context.instance):
            requests.append(process_request(campaign, f"nightly:{stamp}:{campaign.key}"))
    return requests or SkipReason("every campaign is up to date")


def automation_definitions(campaigns: list[Campaign], scan_jobs: list) -> dict[str, list]:
    """Jobs, sensors and schedules of the workspace for the loaded ``campaigns`` (whose per-scan
    jobs are ``scan_jobs``)."""
    level = AssetSelection.assets(*(asset_key(c, s) for c in campaigns for s in CAMPAIGN_STAGES
                                    if s != "retry_pairs" or screened(c)))
    sensors = [build_scan_files_sensor(campaigns, scan_jobs)]
    if campaigns:
        sensors.append(AutomationConditionSensorDefinition(
            "campaign_automation",
            target=level,
            minimum_interval_seconds=30,
            default_status=DefaultSensorStatus.RUNNING if _running() else DefaultSensorStatus.STOPPED,
            description="Campaign-level assets follow their scans: each runs when its code "
            "version or an input's data version changed.",
        ))
    return {"jobs": [process_campaign_job], "sensors": sensors, "schedules": [nightly_reprocessing]}


def automated_definitions(campaigns: Iterable[Campaign], store_url: str | None = None) -> Definitions:
    """The workspace's definitions with the automation: every campaign's assets and jobs, plus
    the scan-file sensor, the nightly schedule and ``process_campaign``."""
    from forestmap_assets.orchestration.workspace import build_definitions

    return build_definitions(campaigns, store_url, extras=automation_definitions)
