"""The event log with open connections (orchestration/event_log.py): Dagster's own files and
schema, readable by Dagster's default storage, a run's file current at each step, no WAL files
left behind, and homes of the earlier configuration upgraded (issue 16)."""

from __future__ import annotations

import shutil
import sqlite3

from dagster import AssetKey, DagsterEventType, EventRecordsFilter, asset, materialize
from dagster._core.storage.event_log.sqlite.sqlite_event_log import SqliteEventLogStorage
from helpers.orchestration import environ

from forestmap_assets.orchestration import event_log
from forestmap_assets.orchestration.event_log import PooledSqliteEventLogStorage
from forestmap_assets.orchestration.instance import _OLD_CONFIG, get_instance, home_config


def _count_in_file_alone(db, run_id: str, kind: str, tmp) -> int:
    """Events of ``kind`` in a run's database file read without its WAL (what a watcher of the
    file sees)."""
    copy = tmp / f"copy-{kind}.db"
    shutil.copyfile(db, copy)
    with sqlite3.connect(copy) as con:
        return con.execute(
            "select count(*) from event_logs where run_id = ? and dagster_event_type = ?", (run_id, kind)
        ).fetchone()[0]


def test_new_home_keeps_dagster_files_and_each_step_reaches_the_run_file(tmp_path):
    home = tmp_path / "dagster"
    seen: dict[str, int] = {}

    @asset
    def leaf(context) -> int:
        db = home / "history" / "runs" / f"{context.run.run_id}.db"
        seen["steps started"] = _count_in_file_alone(db, context.run.run_id, "STEP_START", tmp_path)
        return 1

    with environ(DAGSTER_HOME=str(home)):
        instance = get_instance()
        assert (home / "dagster.yaml").read_text() == home_config(home)
        storage = instance.event_log_storage
        assert isinstance(storage, PooledSqliteEventLogStorage)
        result = materialize([leaf], instance=instance)
        assert result.success
        assert seen == {"steps started": 1}  # the step's start was in the file while it ran

        # Dagster's default storage reads the same files
        plain = SqliteEventLogStorage(str(home / "history" / "runs"))
        records = plain.get_event_records(
            EventRecordsFilter(DagsterEventType.ASSET_MATERIALIZATION, asset_key=AssetKey("leaf"))
        )
        assert [r.run_id for r in records] == [result.run_id]
        run_events = plain.get_logs_for_run(result.run_id)
        assert len(run_events) == len(storage.get_logs_for_run(result.run_id)) > 5
        # the run's file was made from the template: the schema Dagster checks is at its head
        assert plain.alembic_version() == storage.alembic_version()

        # a finished run's file holds all its events without its WAL; closing leaves no WAL
        db = home / "history" / "runs" / f"{result.run_id}.db"
        assert _count_in_file_alone(db, result.run_id, DagsterEventType.RUN_SUCCESS.value, tmp_path) == 1
        event_log.close_all()
        assert not [p.name for p in (home / "history" / "runs").iterdir() if "-wal" in p.name or "-shm" in p.name]


def test_every_process_opens_the_home_event_log_whatever_its_dagster_home(tmp_path):
    """A worker started for another campaign (another $DAGSTER_HOME) rebuilds the instance from
    its reference: it must write to the reference's event log, not its own home's."""
    from dagster import DagsterInstance

    home = tmp_path / "home"
    with environ(DAGSTER_HOME=str(home)):
        ref = get_instance().get_ref()
    with environ(DAGSTER_HOME=str(tmp_path / "elsewhere")):
        storage = DagsterInstance.from_ref(ref).event_log_storage
    assert storage._base_dir == str(home.resolve() / "history" / "runs")


def test_a_run_file_is_made_once(tmp_path):
    storage = PooledSqliteEventLogStorage(str(tmp_path / "runs"))
    assert storage._new_run_shard("r1") is True
    assert storage._new_run_shard("r1") is False  # made by someone else: Dagster's check instead
    with sqlite3.connect(tmp_path / "runs" / "r1.db") as con:
        tables = {r[0] for r in con.execute("select name from sqlite_master where type = 'table'")}
    assert {"event_logs", "alembic_version"} <= tables
    assert not [p.name for p in (tmp_path / "runs").iterdir() if p.name.endswith(".tmp")]


def test_the_run_template_is_made_once_per_home_and_remade_when_damaged(tmp_path):
    first = PooledSqliteEventLogStorage(str(tmp_path / "history" / "runs"))
    made = first._template_bytes()
    kept = first._template_file()
    assert kept.parent == tmp_path / "history" and kept.read_bytes() == made
    assert not [p.name for p in kept.parent.iterdir() if p.name.endswith(".tmp")]

    kept.write_bytes(b"not a database")  # a second process reads the kept file, else remakes it
    second = PooledSqliteEventLogStorage(str(tmp_path / "history" / "runs"))
    assert second._template_bytes() == made
    assert kept.read_bytes() == made
    kept.write_bytes(made[:1000])  # cut short: not a whole number of pages
    assert PooledSqliteEventLogStorage(str(tmp_path / "history" / "runs"))._template_bytes() == made


def test_schema_checks_and_partition_keys_are_remembered_only_once_seen(tmp_path, monkeypatch):
    storage = PooledSqliteEventLogStorage(str(tmp_path / "runs"))
    with storage.index_connection() as conn:
        assert storage._has_asset_key_col_on_connection(conn, "last_materialization_timestamp")
        assert not storage._has_asset_key_col_on_connection(conn, "no_such_column")
    assert storage._asset_columns == {"last_materialization_timestamp"}

    storage.add_dynamic_partitions("scans", ["s1"])
    assert storage.has_dynamic_partition("scans", "s1")
    assert storage._partitions == set()  # the main process asks the database every time
    monkeypatch.setattr(event_log, "REMEMBER_PARTITIONS", True)  # as in a run's worker
    assert storage.has_dynamic_partition("scans", "s1")
    assert not storage.has_dynamic_partition("scans", "s2")
    assert storage._partitions == {("scans", "s1")}
    storage.delete_dynamic_partition("scans", "s1")
    assert not storage.has_dynamic_partition("scans", "s1")


def test_earlier_home_configuration_is_upgraded_custom_kept(tmp_path):
    old = tmp_path / "old"
    old.mkdir()
    (old / "dagster.yaml").write_text(_OLD_CONFIG)
    with environ(DAGSTER_HOME=str(old)):
        assert isinstance(get_instance().event_log_storage, PooledSqliteEventLogStorage)
    assert (old / "dagster.yaml").read_text() == home_config(old)

    # the configuration before steps' stdout and stderr stopped being captured (tail -F per step)
    from dagster._core.storage.noop_compute_log_manager import NoOpComputeLogManager

    from forestmap_assets.orchestration.instance import _COMPUTE_LOGS

    before = tmp_path / "before"
    before.mkdir()
    (before / "dagster.yaml").write_text(home_config(before).replace(_COMPUTE_LOGS, ""))
    with environ(DAGSTER_HOME=str(before)):
        assert isinstance(get_instance().compute_log_manager, NoOpComputeLogManager)
    assert (before / "dagster.yaml").read_text() == home_config(before)

    moved = tmp_path / "moved"
    old.rename(moved)
    with environ(DAGSTER_HOME=str(moved)):
        storage = get_instance().event_log_storage
    assert storage._base_dir == str(moved / "history" / "runs")
    assert (moved / "dagster.yaml").read_text() == home_config(moved)

    custom = tmp_path / "custom"
    custom.mkdir()
    text = _OLD_CONFIG + "run_monitoring:\n  enabled: false\n"
    (custom / "dagster.yaml").write_text(text)
    with environ(DAGSTER_HOME=str(custom)):
        assert type(get_instance().event_log_storage) is SqliteEventLogStorage
    assert (custom / "dagster.yaml").read_text() == text
