"""Dagster's run-sharded SQLite event log (the same files and schema as its default
``SqliteEventLogStorage``) with its connections kept open.

Dagster's SQLite event log makes a new SQLAlchemy engine, opens the database, commits and
disposes the engine for every event it stores or query it makes, and checks (with Alembic) the
schema of every run's database it opens. A scan's run of eight stages stores about a hundred
events, so on a 6-scan survey this bookkeeping took about 9 s of the workers' time (issue 16).
Here, per process:

- one engine per database file, kept open (the last :data:`OPEN_SHARDS` files);
- a new run's database is a copy of an empty one that Dagster's own initialisation made once
  for the home (same tables, same Alembic stamp, WAL journal; kept beside ``runs/``), written
  under a temporary name and linked into place, so no process ever sees half a file;
- ``PRAGMA synchronous=NORMAL``: in WAL mode a power cut can lose the last events, never
  corrupt the file (a lost materialisation only means a stage is run again);
- the existence of a table, and of the asset table's columns, once seen, is remembered; so
  are the dynamic partition keys a worker of ``forestmap run`` has seen;
- a run's file takes in its WAL at each step's start and end (the UI's live view of a run
  watches that file) and when the run ends (its database is then closed).

A home's ``dagster.yaml`` names this class (:func:`forestmap_assets.orchestration.instance.get_instance`);
the UI, ``forestmap status`` and the workers open it through the same configuration.
"""

from __future__ import annotations

import contextlib
import multiprocessing.util
import os
import tempfile
import threading
import weakref
from collections import OrderedDict
from collections.abc import Iterator
from pathlib import Path

import sqlalchemy
from dagster import DagsterEventType, StringSource
from dagster._core.storage.event_log.sqlite.sqlite_event_log import (
    INDEX_SHARD_NAME,
    SqliteEventLogStorage,
)
from dagster._core.storage.sqlite import SQLITE_BUSY_TIMEOUT_SECONDS
from dagster.version import __version__ as dagster_version
from sqlalchemy import create_engine, event
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.pool import NullPool

from forestmap_assets.io.writers import atomic_write

OPEN_SHARDS = 8  # databases kept open per process (the index and the runs in progress)
_RUN_END = {DagsterEventType.RUN_SUCCESS, DagsterEventType.RUN_FAILURE, DagsterEventType.RUN_CANCELED}
# events after which a run's WAL is folded into its file: the UI's live log view of a run
# watches that file, so it follows the run step by step
_CHECKPOINT = {
    DagsterEventType.RUN_START,
    DagsterEventType.STEP_START,
    DagsterEventType.STEP_SUCCESS,
    DagsterEventType.STEP_FAILURE,
}


_SQLITE_MAGIC = b"SQLite format 3\x00"
# set in the worker processes of ``forestmap run`` (orchestration/session.py): dynamic partition
# keys once seen are remembered there (PooledSqliteEventLogStorage.has_dynamic_partition)
REMEMBER_PARTITIONS = False
_STORAGES: weakref.WeakSet = weakref.WeakSet()


def close_all() -> None:
    """Close every open database of this process (no -wal / -shm files left behind): at exit,
    also of multiprocessing workers, and by a command that leaves with ``os._exit``."""
    for storage in list(_STORAGES):
        storage._close_all()


_EXIT_HOOK: list[int] = []  # the process that registered close_all (a child starts afresh)


def track(storage) -> None:
    """Close ``storage`` (its ``_close_all``) with this process's other open databases at exit
    (:func:`close_all`)."""
    _STORAGES.add(storage)
    if _EXIT_HOOK != [os.getpid()]:  # a multiprocessing child clears its parent's finalizers
        multiprocessing.util.Finalize(None, close_all, exitpriority=10)
        _EXIT_HOOK[:] = [os.getpid()]


def _normal_sync(dbapi_connection, _record) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.close()


def open_engine(conn_string: str, **connect_args) -> Engine:
    """A pooled SQLAlchemy engine of a SQLite file that this process keeps open: usable from
    any thread, every connection with ``PRAGMA synchronous=NORMAL`` (WAL: a power cut may lose
    the last transactions, never corrupt the file)."""
    engine = create_engine(conn_string, connect_args={**connect_args, "check_same_thread": False})
    event.listen(engine, "connect", _normal_sync)
    return engine


class PooledSqliteEventLogStorage(SqliteEventLogStorage):
    """:class:`SqliteEventLogStorage` with open connections and new run databases from a
    template (module docstring). ``base_dir``: an absolute path, as it must reach every process
    through the instance's reference, whatever that process's ``$DAGSTER_HOME``."""

    def __init__(self, base_dir: str, inst_data=None):
        self._engines: OrderedDict[str, Engine] = OrderedDict()
        self._engines_lock = threading.Lock()
        self._pid = os.getpid()
        self._tables: set[str] = set()
        self._asset_columns: set[str] = set()
        self._partitions: set[tuple[str, str]] = set()
        self._template: bytes | None = None
        super().__init__(base_dir, inst_data)
        track(self)  # closed at exit (close_all)

    @classmethod
    def config_type(cls):
        return {"base_dir": StringSource}

    @classmethod
    def from_config_value(cls, inst_data, config_value):  # ty: ignore[invalid-method-override]
        return cls(inst_data=inst_data, **config_value)

    def _engine(self, shard: str) -> Engine:
        with self._engines_lock:
            if self._pid != os.getpid():  # a forked child never uses its parent's connections
                for engine in self._engines.values():
                    engine.dispose(close=False)
                self._engines.clear()
                self._pid = os.getpid()
            engine = self._engines.pop(shard, None)
            if engine is None:
                engine = open_engine(self.conn_string_for_shard(shard), timeout=SQLITE_BUSY_TIMEOUT_SECONDS)
            self._engines[shard] = engine
            while len(self._engines) > OPEN_SHARDS:
                self._engines.popitem(last=False)[1].dispose()
            return engine

    def _close(self, shard: str) -> None:
        with self._engines_lock:
            engine = self._engines.pop(shard, None) if self._pid == os.getpid() else None
        if engine is not None:
            engine.dispose()

    def _close_all(self) -> None:
        with self._engines_lock:
            engines = list(self._engines.values()) if self._pid == os.getpid() else []
            self._engines.clear()
        for engine in engines:
            engine.dispose()

    def _template_file(self) -> Path:
        """Where the home keeps its empty run database, beside ``runs/`` (named for the Dagster
        and SQLAlchemy versions that made it)."""
        return Path(self._base_dir).parent / f".run-template-{dagster_version}-{sqlalchemy.__version__}.db"

    def _template_bytes(self) -> bytes:
        """An empty run database as Dagster's own initialisation makes it: made once per home
        (0.06-0.1 s a process, which every process of a run paid) and kept beside ``runs/``,
        written atomically; a file that is not a whole SQLite database is made again."""
        if self._template is None:
            kept = self._template_file()
            with contextlib.suppress(OSError):
                data = kept.read_bytes()
                if data.startswith(_SQLITE_MAGIC) and len(data) % 512 == 0:
                    self._template = data
        if self._template is None:
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / "template.db"
                engine = create_engine(
                    f"sqlite:///{path}",
                    poolclass=NullPool,
                    connect_args={"timeout": SQLITE_BUSY_TIMEOUT_SECONDS},
                )
                self._initdb(engine)
                engine.dispose()
                self._template = path.read_bytes()
            with contextlib.suppress(OSError), atomic_write(kept) as tmp:
                tmp.write_bytes(self._template)
        return self._template

    def _new_run_shard(self, shard: str) -> bool:
        """Create a run's database from the template; False if another process made it first."""
        path = self.path_for_shard(shard)
        if os.path.exists(path):
            return False
        tmp = f"{path}.{os.getpid()}.{threading.get_ident()}.tmp"
        try:
            Path(tmp).write_bytes(self._template_bytes())
            os.link(tmp, path)  # atomic: fails if the file appeared meanwhile
            return True
        except FileExistsError:
            return False
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)

    @contextlib.contextmanager
    def _connect(self, shard: str) -> Iterator[Connection]:
        with self._db_lock:
            engine = self._engine(shard)
            if shard not in self._initialized_dbs:
                if shard == INDEX_SHARD_NAME or not self._new_run_shard(shard):
                    self._initdb(engine)
                self._initialized_dbs.add(shard)
            with engine.connect() as conn, conn.begin():
                yield conn

    def store_event(self, event) -> None:
        super().store_event(event)
        kind = event.dagster_event_type if event.is_dagster_event else None
        if kind in _RUN_END:
            with self._db_lock:  # a finished run's database is closed (and its WAL folded in)
                self._close(event.run_id)
        elif kind in _CHECKPOINT:
            with self._connect(event.run_id) as conn:
                conn.exec_driver_sql("PRAGMA wal_checkpoint(PASSIVE)")

    def has_table(self, table_name: str) -> bool:
        if table_name in self._tables:
            return True
        engine = self._engine(INDEX_SHARD_NAME)
        with engine.connect() as conn:
            found = bool(engine.dialect.has_table(conn, table_name))
        if found:
            self._tables.add(table_name)
        return found

    def _has_asset_key_col_on_connection(self, conn: Connection, column_name: str) -> bool:
        """Dagster asks SQLAlchemy to reflect the asset table's columns at every asset event
        (about 0.1 ms of SQL, 1-2 ms of reflection); a column once seen is remembered (a
        migration only adds columns)."""
        if column_name in self._asset_columns:
            return True
        found = super()._has_asset_key_col_on_connection(conn, column_name)
        if found:
            self._asset_columns.add(column_name)
        return found

    def has_dynamic_partition(self, partitions_def_name: str, partition_key: str) -> bool:
        """Dagster checks a step's partition key several times a step. In a worker of
        ``forestmap run`` (:data:`REMEMBER_PARTITIONS`, a process that lives for one run and
        deletes no partition) a key once seen is remembered."""
        key = (partitions_def_name, partition_key)
        if REMEMBER_PARTITIONS and key in self._partitions:
            return True
        found = super().has_dynamic_partition(partitions_def_name, partition_key)
        if found and REMEMBER_PARTITIONS:
            self._partitions.add(key)
        return found

    def delete_dynamic_partition(self, partitions_def_name: str, partition_key: str) -> None:
        self._partitions.discard((partitions_def_name, partition_key))
        super().delete_dynamic_partition(partitions_def_name, partition_key)

    def dispose(self) -> None:
        self._close_all()
        super().dispose()
