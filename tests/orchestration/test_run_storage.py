"""The run storage with its engine kept open (orchestration/run_storage.py): Dagster's own
runs.db, readable by its default storage, one engine per process, no WAL files left behind, and
homes of the earlier configuration upgraded (issue 16)."""

from __future__ import annotations

import os

from dagster import DagsterRunStatus, asset, materialize
from dagster._core.storage.runs.sqlite.sqlite_run_storage import SqliteRunStorage
from helpers.orchestration import environ

from forestmap_assets.orchestration import event_log
from forestmap_assets.orchestration.instance import _RUN_STORAGE, get_instance, home_config
from forestmap_assets.orchestration.run_storage import PooledSqliteRunStorage


@asset
def leaf() -> int:
    return 1


def test_runs_are_in_dagster_file_and_closing_leaves_no_wal(tmp_path):
    home = tmp_path / "dagster"
    with environ(DAGSTER_HOME=str(home)):
        instance = get_instance()
        assert isinstance(instance.run_storage, PooledSqliteRunStorage)
        result = materialize([leaf], instance=instance)
        assert result.success
        engine = instance.run_storage._pooled
        materialize([leaf], instance=instance)
        assert instance.run_storage._pooled is engine  # one engine for both runs
    plain = SqliteRunStorage.from_local(str(home / "history"))  # Dagster's default, same file
    run = plain.get_run_records()[-1].dagster_run
    assert run.run_id == result.run_id and run.status == DagsterRunStatus.SUCCESS
    event_log.close_all()
    assert instance.run_storage._pooled is None
    assert not [p.name for p in (home / "history").iterdir() if "-wal" in p.name or "-shm" in p.name]


def test_the_run_columns_check_is_remembered_once_true(tmp_path, monkeypatch):
    storage = PooledSqliteRunStorage.from_local(str(tmp_path / "history"))
    calls = []
    real = SqliteRunStorage.has_run_stats_index_cols

    def counted(self):
        calls.append(1)
        return real(self)

    monkeypatch.setattr(SqliteRunStorage, "has_run_stats_index_cols", counted)
    storage._run_stats_cols = False  # as before its first check (its opening made one)
    assert storage.has_run_stats_index_cols() and storage.has_run_stats_index_cols()
    assert len(calls) == 1


def test_a_forked_child_opens_its_own_engine(tmp_path):
    storage = PooledSqliteRunStorage.from_local(str(tmp_path / "history"))
    parent = storage._engine()
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: a new engine that works, the parent's left alone
        ok = storage._engine() is not parent and storage.get_run_records() == []
        os.write(write, b"1" if ok else b"0")
        os._exit(0)
    os.waitpid(pid, 0)
    assert os.read(read, 1) == b"1"
    assert storage._engine() is parent and storage.get_run_records() == []
    storage.dispose()


def test_configuration_before_the_pooled_run_storage_is_upgraded(tmp_path):
    home = tmp_path / "before"
    home.mkdir()
    earlier = home_config(home).split(_RUN_STORAGE)[0]
    (home / "dagster.yaml").write_text(earlier)
    with environ(DAGSTER_HOME=str(home)):
        assert isinstance(get_instance().run_storage, PooledSqliteRunStorage)
    assert (home / "dagster.yaml").read_text() == home_config(home)
