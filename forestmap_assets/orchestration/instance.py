"""The persistent Dagster instance of ``forestmap run`` / ``status`` / the UI (``$DAGSTER_HOME``,
else ``<forestmap home>/dagster``) and a campaign's dynamic scan partitions in it (matched to its
manifest)."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
from collections.abc import Callable, Iterator
from pathlib import Path

from dagster import DagsterInstance

from forestmap_assets.assets.common import PAIR_STAGES, asset_key, pair_partitions, scan_partitions
from forestmap_assets.io.campaign import Campaign
from forestmap_assets.io.home import dagster_home, settled_file
from forestmap_assets.io.writers import atomic_write

_INSTANCES: dict[str, DagsterInstance] = {}

# engine chatter of step subprocesses at WARNING (run logs are kept in full regardless); the
# event log with open connections (orchestration/event_log.py: same files as Dagster's default)
_OLD_CONFIG = (
    "telemetry:\n  enabled: false\nnux:\n  enabled: false\n"
    "python_logs:\n  python_log_level: WARNING\n"
)
_EVENT_LOG = (
    "event_log_storage:\n"
    "  module: forestmap_assets.orchestration.event_log\n"
    "  class: PooledSqliteEventLogStorage\n"
    "  config:\n"
    "    base_dir: "
)


# no capture of each step's stdout and stderr into files: Dagster's local manager starts two
# ``tail -F`` and two orphan watchers (Python) for every step, and a step's exit waits for the
# tails, which hung a Dask worker for good (CI rehearsal of ef6b978); forestmap reports through
# the event log, and its steps print nothing
_COMPUTE_LOGS = (
    "compute_logs:\n"
    "  module: dagster._core.storage.noop_compute_log_manager\n"
    "  class: NoOpComputeLogManager\n"
)


# the run storage with its engine kept open (orchestration/run_storage.py: Dagster's runs.db)
_RUN_STORAGE = (
    "run_storage:\n"
    "  module: forestmap_assets.orchestration.run_storage\n"
    "  class: PooledSqliteRunStorage\n"
    "  config:\n"
    "    base_dir: "
)


def home_config(home: Path) -> str:
    """The ``dagster.yaml`` of a forestmap home (the storages' folders are written out: every
    process, whatever its ``$DAGSTER_HOME``, must open the same ones)."""
    history = home.resolve() / "history"
    return (_OLD_CONFIG + _EVENT_LOG + json.dumps(str(history / "runs")) + "\n" + _COMPUTE_LOGS
            + _RUN_STORAGE + json.dumps(str(history)) + "\n")


def _outdated(text: str, home: Path) -> bool:
    """A configuration forestmap wrote, for an earlier version or for this home at another place."""
    return text == _OLD_CONFIG or (text.startswith(_OLD_CONFIG + _EVENT_LOG) and text != home_config(home))


def get_instance() -> DagsterInstance:
    """Persistent instance: ``$DAGSTER_HOME`` if set, else ``<forestmap home>/dagster``; one per
    home and process (opening its storage costs ~0.4 s).

    A new home gets a ``dagster.yaml`` with telemetry and the UI's welcome dialog off, the
    engine's console chatter at WARNING (run logs are kept in full) and Dagster's SQLite event
    log and run storage with their connections kept open
    (:mod:`~forestmap_assets.orchestration.event_log`, :mod:`~.run_storage`: the same files); a
    home made with an earlier configuration of forestmap's, or moved, gets the new one.
    """
    home = dagster_home()
    os.environ["DAGSTER_HOME"] = str(home)
    home.mkdir(parents=True, exist_ok=True)
    config = home / "dagster.yaml"
    if not config.exists() or _outdated(config.read_text(), home):
        with atomic_write(config) as tmp:
            tmp.write_text(home_config(home))
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


def pair_store(store_url: str | None = None):
    """The asset store's IO manager, to read and prune stored outputs outside a run."""
    from upath import UPath

    from forestmap_assets.io.store import ParquetIOManager, default_store_url

    return ParquetIOManager(base_path=UPath(store_url or default_store_url()))


def wanted_pairs(campaign: Campaign, store_url: str | None = None):
    """The stored pair lists (``candidate_pairs`` then ``retry_pairs``) of the campaign's scans,
    with their partition keys in column ``pair``."""
    from forestmap_assets.assets.pairs import pair_rows

    rows = pair_rows(pair_store(store_url), campaign)
    ids = set(campaign.scan_ids)
    keep = rows["scan"].isin(ids) & rows["reference"].isin(ids)
    return rows[keep].reset_index(drop=True)


def sync_pair_partitions(instance: DagsterInstance, campaign: Campaign, store_url: str | None = None) -> None:
    """Make the campaign's dynamic pair partitions match its stored pair lists (issue 17); a pair
    no longer listed loses its partition and its stored outputs."""
    name = pair_partitions(campaign).name
    existing = set(instance.get_dynamic_partitions(name))
    wanted = set(wanted_pairs(campaign, store_url)["pair"])
    new = sorted(wanted - existing)
    if new:
        instance.add_dynamic_partitions(name, new)
    store = pair_store(store_url)
    for gone in sorted(existing - wanted):
        instance.delete_dynamic_partition(name, gone)
        for stage in PAIR_STAGES:
            store.remove_stored(list(asset_key(campaign, stage).path), gone)


@contextlib.contextmanager
def campaign_lock(
    instance: DagsterInstance, campaign: Campaign, progress: Callable[[str], None]
) -> Iterator[None]:
    """Exclusive lock per campaign in the instance folder: a second ``forestmap run`` of the same
    campaign waits for the first, then finds its work done."""
    folder = Path(instance.root_directory) / "locks"
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / f"{campaign.key}.lock", "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            progress(
                f"{campaign.name}: another run of this campaign is in progress; waiting for it"
            )
            fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def settled_key(instance: DagsterInstance, campaign: Campaign, defs, store_url: str) -> str:
    """What a campaign's state depends on: the newest event of the instance, the code version of
    every stage (stage version plus parameter hash), the scan files' fingerprints and the store.
    Unchanged since a session that left every stage fresh means nothing to do (issue 16: a run
    with nothing to do asks Dagster's stale-status resolver nothing)."""
    import hashlib
    import json

    graph = defs.resolve_asset_graph()
    versions = sorted(
        (k.to_user_string(), graph.get(k).code_version or "")
        for k in graph.get_all_asset_keys()
        if len(k.path) == 2 and k.path[0] == campaign.key
    )
    doc = {
        "event": instance.event_log_storage.get_maximum_record_id(),
        "versions": versions,
        "files": {sid: campaign.scan_fingerprint(sid) for sid in campaign.scan_ids},
        "store": store_url,
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()[:24]


def _settled_path(instance: DagsterInstance, campaign: Campaign) -> Path:
    return settled_file(instance.root_directory, campaign.key)


def is_settled(instance: DagsterInstance, campaign: Campaign, key: str) -> bool:
    """Whether the last session of the campaign ended with every stage fresh, and nothing that
    :func:`settled_key` covers changed since."""
    try:
        return _settled_path(instance, campaign).read_text().strip() == key
    except OSError:
        return False


def mark_settled(instance: DagsterInstance, campaign: Campaign, key: str | None) -> None:
    """Record (``key``) or forget (``None``) that every stage of the campaign is fresh."""
    path = _settled_path(instance, campaign)
    if key is None:
        path.unlink(missing_ok=True)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(key)
    os.replace(tmp, path)
