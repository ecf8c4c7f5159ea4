"""The asset store: every asset output as Parquet, written atomically, on any fsspec URL.

An asset output is either one table (``pandas.DataFrame`` or ``pyarrow.Table``), stored as
``<base>/<campaign>/<asset>/<partition>.parquet``, or a *bundle* (``dict`` of name -> table),
stored as a folder ``<...>.bundle/`` holding one ``<name>.parquet`` per table. Files are written
under a temporary name and renamed into place, so a failed or concurrent run never leaves a
partial file behind.
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable, Collection
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from dagster import ConfigurableIOManagerFactory, InputContext, OutputContext, UPathIOManager
from upath import UPath

from forestmap_assets.io.home import default_store_url, forestmap_home  # noqa: F401 (re-exported)


def _as_arrow(obj: pd.DataFrame | pa.Table) -> pa.Table:
    if isinstance(obj, pa.Table):
        return obj
    if isinstance(obj, pd.DataFrame):
        return pa.Table.from_pandas(obj, preserve_index=False)
    raise TypeError(f"expected a pandas DataFrame or pyarrow Table, got {type(obj).__name__}")


def _write_parquet(table: pa.Table, f) -> None:
    """LZ4-compressed Parquet (:func:`_encodings`). LZ4, not Zstandard: float coordinates
    hardly compress (a 2.3 M-point range image: 34.0 MB with Zstandard, 38.6 MB with LZ4, 40.5
    MB without), and LZ4 writes it in 0.10 s instead of 0.14 s and reads it in 0.03 s instead of
    0.06 s (issue 16)."""
    dictionary, encoding = _encodings(table.schema)
    pq.write_table(table, f, compression="lz4", use_dictionary=dictionary, column_encoding=encoding)


def _encodings(schema: pa.Schema) -> tuple[list[str], dict[str, str]]:
    """The columns to dictionary-encode and the others' encodings (issue 16). float32 / float64:
    byte stream split (each byte of the values in its own stream, so that the exponents' bytes
    compress); integers: delta; strings, booleans and the like: dictionary; float16: plain.
    Dictionary encoding of coordinates cost most of the write time and made the file larger.
    A 2.7 M-pixel range image: 45.1 -> 30.6 MB. The stored tables of a 6-scan survey of such
    scans (one thread, in memory): 488 -> 369 MB, writes 2.55 -> 2.08 s, reads 1.02 -> 0.94 s;
    every table read back equal."""
    dictionary, encoding = [], {}
    for fl in schema:
        if pa.types.is_float32(fl.type) or pa.types.is_float64(fl.type):
            encoding[fl.name] = "BYTE_STREAM_SPLIT"
        elif pa.types.is_integer(fl.type):
            encoding[fl.name] = "DELTA_BINARY_PACKED"
        elif not pa.types.is_floating(fl.type):
            dictionary.append(fl.name)
    return dictionary, encoding


MANIFEST = "_tables.json"  # bundle folder: its table names, written last


def _tmp_sibling(path: UPath) -> UPath:
    return path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:12]}")


def _being_swapped(path: UPath) -> bool:
    """Whether a writer is between moving ``path`` aside and moving its new version in: a
    temporary sibling of it exists (:func:`_tmp_sibling`)."""
    parent = path.parent
    if not parent.exists():
        return False
    return any(p.name.startswith(f".{path.name}.tmp-") for p in parent.iterdir())


def _move(src: UPath, dst: UPath) -> None:
    if src.protocol in ("", "file", "local"):
        os.replace(src.path, dst.path)
    else:
        src.fs.mv(src.path, dst.path, recursive=True)


def write_table_atomic(table: pd.DataFrame | pa.Table, path: str | os.PathLike | UPath) -> None:
    """Write one Parquet file under a temporary name, then rename it into place."""
    path = UPath(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_sibling(path)
    try:
        with tmp.open("wb") as f:
            _write_parquet(_as_arrow(table), f)
        _move(tmp, path)
    except BaseException:
        if tmp.exists():
            tmp.unlink()
        raise


SMALL_TABLE_BYTES = 1 << 20  # a table this small is read in the calling thread alone


def read_table(path: str | os.PathLike | UPath, columns: list[str] | None = None) -> pa.Table:
    """A stored table (``columns``: only these; see :func:`_read_parquet`), each column one
    chunk: a column read in many chunks (a rendered scan's range image: 18) is copied again at
    every ``to_numpy``, 5 ms a column of 2.3 M points, which the tree list did some 500 times
    on a rendered survey (issue 16); combined once, 20 ms a table, ``to_numpy`` is a view."""
    path = UPath(path)
    if _local(path):
        with open(path.path, "rb") as f:
            return _read_parquet(f, columns).combine_chunks()
    with path.open("rb") as f:
        return pq.read_table(f, columns=columns).combine_chunks()


def _read_parquet(f, columns: list[str] | None = None) -> pa.Table:
    """One local Parquet file; a whole one under :data:`SMALL_TABLE_BYTES` is read without
    Arrow's thread pool, whose start-up took 3 of the 4 ms a pair's one-row table cost."""
    if columns is None and os.fstat(f.fileno()).st_size < SMALL_TABLE_BYTES:
        return pq.ParquetFile(f).read(use_threads=False)
    return pq.read_table(f, columns=columns)


def _to_pandas(table: pa.Table) -> pd.DataFrame:
    """``table`` as a DataFrame, in the calling thread alone when it is small."""
    return table.to_pandas(use_threads=table.nbytes >= SMALL_TABLE_BYTES)


def _local(path: UPath) -> bool:
    return path.protocol in ("", "file", "local")


# The last tagged table (a range image) this process wrote or read, with the file's identity:
# the per-scan stages of one scan's run all read its range image, so a run in one process reads
# it once (issue 18: 0.3-0.6 s a read on a 14 M-pixel image, and its decoded image is reused by
# RangeImage.from_table). Cleared by forget_recent() when a run ends.
_RECENT: dict[str, Any] = {}


def _identity(path: UPath) -> tuple | None:
    if not _local(path):
        return None
    try:
        st = os.stat(path.path)
    except OSError:
        return None
    return (os.path.realpath(path.path), st.st_ino, st.st_mtime_ns, st.st_size)


def _remember(path: UPath, table: pa.Table) -> None:
    if (table.schema.metadata or {}).get(b"forestmap.kind") and (ident := _identity(path)) is not None:
        _RECENT.clear()
        _RECENT.update(identity=ident, table=table)


def _recalled(path: UPath) -> pa.Table | None:
    if _RECENT and (ident := _identity(path)) is not None and _RECENT["identity"] == ident:
        return _RECENT["table"]
    return None


def forget_recent() -> None:
    """Drop the remembered table and derived objects (the end of a run in a long-lived worker
    process), and the tables read ahead that no step took."""
    _RECENT.clear()
    _DERIVED.clear()
    for fut in _AHEAD.values():
        fut.cancel()
    _AHEAD.clear()


# Tables read ahead in a background thread (:func:`read_ahead`), by file identity and columns:
# the tree list reads every scan's range image columns (13.7 M rows of a rendered survey, 0.3-0.5
# s), which the map's earlier campaign-level stages leave time to read beside them in this
# process (Parquet decodes without the GIL; issue 16). A step's input loading takes a table once.
_AHEAD: dict[tuple, Future] = {}


def read_ahead(tables: list[tuple[UPath, list[str] | None]]) -> None:
    """Start reading the local stored ``tables`` (path, columns) one after another in a
    background thread; :meth:`ParquetIOManager.load_from_path` takes them from there."""
    todo = []
    for path, columns in tables:
        key = _ahead_key(path, columns)
        if key is not None and key not in _AHEAD:
            _AHEAD[key] = fut = Future()
            todo.append((path, columns, fut))

    def work() -> None:
        for path, columns, fut in todo:
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(read_table(path, columns))
                except BaseException as exc:  # noqa: BLE001 - the step reads it again itself
                    fut.set_exception(exc)

    if todo:
        threading.Thread(target=work, name="read ahead", daemon=True).start()


def _ahead_key(path: UPath, columns: list[str] | None) -> tuple | None:
    """A read-ahead's key: the file's identity (None: not a local file) and the columns."""
    ident = _identity(path)
    return None if ident is None else (ident, tuple(columns) if columns else None)


def _taken_ahead(path: UPath, columns: list[str] | None) -> pa.Table | None:
    """The table :func:`read_ahead` read (waiting for it), or None: not read ahead, or failed."""
    key = _ahead_key(path, columns) if _AHEAD else None
    fut = _AHEAD.pop(key, None) if key is not None else None
    if fut is None or fut.cancelled():
        return None
    try:
        return fut.result()
    except Exception:  # noqa: BLE001 - read again by the caller, which reports what is wrong
        return None


# Objects built from a stored table (a scan's refinement cloud with its k-d tree), per worker
# process, while the file is unchanged: every pair of a scan needs the same one (issue 16:
# reading and preparing two clouds took about half of a pair's refinement step).
_DERIVED: OrderedDict = OrderedDict()
DERIVED_MAX = 6


def _remove_tree(path: UPath) -> None:
    if _local(path):
        import shutil

        with contextlib.suppress(OSError):  # tables first, the manifest last (see read_bundle)
            for name in os.listdir(path.path):
                if name != MANIFEST:
                    os.unlink(os.path.join(path.path, name))
        shutil.rmtree(path.path, ignore_errors=True)
    else:
        path.fs.rm(path.path, recursive=True)


def _swap_in(tmp: UPath, path: UPath, attempts: int = 20) -> None:
    """Move the finished folder ``tmp`` to ``path``, replacing an older one. A folder cannot be
    renamed over another, so the old one is moved aside first; when a concurrent writer slips in
    between, try again (the last writer wins, no reader ever sees a partial folder)."""
    for k in range(attempts):
        old = None
        try:
            if path.exists():
                old = _tmp_sibling(path)
                _move(path, old)
            _move(tmp, path)
        except (FileNotFoundError, FileExistsError, OSError):
            if k == attempts - 1:
                raise
            time.sleep(0.01 * (k + 1))
            continue
        finally:
            if old is not None and old.exists():
                _remove_tree(old)
        return


def write_bundle_atomic(bundle: dict[str, Any], path: UPath) -> None:
    """Write a folder of Parquet tables; the folder appears complete or not at all."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_sibling(path)
    tmp.mkdir(parents=True, exist_ok=True)
    try:
        for name, table in bundle.items():
            with (tmp / f"{name}.parquet").open("wb") as f:
                _write_parquet(_as_arrow(table), f)
        (tmp / MANIFEST).write_text(json.dumps(list(bundle)))
        _swap_in(tmp, path)
    except BaseException:
        if tmp.exists():
            _remove_tree(tmp)
        raise


def read_bundle(
    path: UPath, attempts: int = 20, tables: Collection[str] | None = None
) -> dict[str, pd.DataFrame]:
    """The tables of a bundle folder (``tables``: only those of them that it holds). Locally
    the folder is read through one open directory handle, so a concurrent writer swapping a
    new folder in (:func:`_swap_in`) cannot mix two versions; a folder being deleted under the
    reader is read again from its new self."""
    path = UPath(path)
    if not _local(path):
        return {
            p.name.removesuffix(".parquet"): read_table(p).to_pandas()
            for p in sorted(path.iterdir())
            if p.name.endswith(".parquet")
            and (tables is None or p.name.removesuffix(".parquet") in tables)
        }
    for k in range(attempts):
        try:
            return _read_bundle_dir(path.path, tables)
        except FileNotFoundError:
            if k == attempts - 1:
                raise
            time.sleep(0.005 * (k + 1))
    raise AssertionError("unreachable")


def _read_bundle_dir(folder: str, tables: Collection[str] | None = None) -> dict[str, pd.DataFrame]:
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        names = sorted(n.removesuffix(".parquet") for n in os.listdir(fd) if n.endswith(".parquet"))
        try:
            with open(os.open(MANIFEST, os.O_RDONLY, dir_fd=fd)) as f:
                expected = json.load(f)
        except FileNotFoundError:
            expected = None  # a bundle written before manifests, or one being deleted
        if expected is None and not names:
            raise FileNotFoundError(f"{folder}: empty bundle folder (being replaced?)")
        out = {}
        for name in expected if expected is not None else names:
            if tables is not None and name not in tables:
                continue
            with open(os.open(f"{name}.parquet", os.O_RDONLY, dir_fd=fd), "rb") as f:
                out[name] = _to_pandas(_read_parquet(f))
        return out
    finally:
        os.close(fd)


CAMPAIGN_ROOT = "_campaign_root.txt"  # <store>/<campaign key>/: the folder owning the key


def _store_id(store_url: str) -> str:
    base = UPath(store_url)
    return str(Path(base.path).resolve()) if _local(base) else str(base)


def read_campaign_root(store_url: str, key: str) -> tuple[str, str] | None:
    """``(campaign folder, store)`` recorded in the namespace ``key`` of the store by
    :func:`write_campaign_root`, or None. The store differs from ``store_url`` when the store
    was copied or moved since (its namespaces are then no longer shared with the original's)."""
    try:
        text = (UPath(store_url) / key / CAMPAIGN_ROOT).read_text()
    except (FileNotFoundError, NotADirectoryError):
        return None
    root, store, *_ = [*text.splitlines(), "", ""]
    return root.strip(), store.strip()


def recorded_elsewhere(store_url: str, key: str, root: str | os.PathLike) -> str | None:
    """The other campaign folder recorded as the owner of namespace ``key`` of this store,
    or None (nothing recorded, this folder, or a record copied along with the store)."""
    found = read_campaign_root(store_url, key)
    if found is None or found[1] != _store_id(store_url):
        return None
    return None if found[0] == str(Path(root).resolve()) else found[0]


def write_campaign_root(store_url: str, key: str, root: str | os.PathLike) -> None:
    """Record ``root`` (a campaign folder) as the owner of namespace ``key`` of the store."""
    if read_campaign_root(store_url, key) == (str(Path(root).resolve()), _store_id(store_url)):
        return
    marker = UPath(store_url) / key / CAMPAIGN_ROOT
    marker.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_sibling(marker)
    try:
        tmp.write_text(f"{Path(root).resolve()}\n{_store_id(store_url)}\n")
        _move(tmp, marker)
    except BaseException:
        if tmp.exists():
            tmp.unlink()
        raise


class ParquetIOManager(UPathIOManager):
    """Stores tables as ``.parquet`` and bundles as ``.bundle/`` folders, atomically."""

    extension = None

    def _table_path(self, path: UPath) -> UPath:
        return path.with_name(path.name + ".parquet")

    def _bundle_path(self, path: UPath) -> UPath:
        return path.with_name(path.name + ".bundle")

    def dump_to_path(self, context: OutputContext, obj: Any, path: UPath) -> None:
        if obj is None:
            return
        if isinstance(obj, dict):
            write_bundle_atomic(obj, self._bundle_path(path))
        else:
            write_table_atomic(obj, self._table_path(path))
            if isinstance(obj, pa.Table):
                _remember(self._table_path(path), obj)

    def load_from_path(self, context: InputContext, path: UPath) -> Any:
        table_path = self._table_path(path)
        if (table := _recalled(table_path)) is not None:
            return table
        wanted = getattr(context, "definition_metadata", None) or {}
        if table_path.exists():
            # an input's metadata "columns": read only those (tree_list: x, y, z of the images)
            columns = wanted.get("columns")
            table = _taken_ahead(table_path, columns)
            if table is None:
                table = read_table(table_path, columns=columns)
            if (table.schema.metadata or {}).get(b"forestmap.kind"):
                if columns is None:
                    _remember(table_path, table)
                return table  # keep Arrow metadata (e.g. range images)
            return _to_pandas(table)
        bundle_path = self._bundle_path(path)
        for k in range(5):  # a concurrent writer swaps a bundle folder in (see _swap_in)
            if bundle_path.exists():  # an input's metadata "tables": read only those of a bundle
                return read_bundle(bundle_path, tables=wanted.get("tables"))
            if not _being_swapped(bundle_path):
                break
            time.sleep(0.02 * (k + 1))
        raise FileNotFoundError(f"no stored output at {table_path} (has the asset been materialised?)")

    def path_exists(self, path: UPath) -> bool:
        return self._table_path(path).exists() or self._bundle_path(path).exists()

    def read_stored(self, asset_path: list[str], partition: str | None = None) -> Any:
        """The stored output of another asset (one partition of it), read outside Dagster's
        input loading: a pair step reads its two scans' partitions this way (issue 17)."""
        path = self._base_path.joinpath(*asset_path)
        if partition is not None:
            path = path / partition
        return self.load_from_path(None, path)

    def read_ahead(self, asset_path: list[str], partitions: Collection[str], columns: list[str] | None) -> None:
        """Read these partitions of another asset ahead, in a background thread (:func:`read_ahead`)."""
        read_ahead([(self._table_path(self._base_path.joinpath(*asset_path) / p), columns) for p in partitions])

    def derived_from_stored(self, asset_path: list[str], partition: str, build: Callable[[Any], Any]) -> Any:
        """``build(stored output)`` of one partition of another asset, remembered in this
        process (the last :data:`DERIVED_MAX`) while the stored file is unchanged (local stores;
        elsewhere built each time). Raises ``FileNotFoundError`` when it was never materialised."""
        path = self._base_path.joinpath(*asset_path) / partition
        ident = _identity(self._table_path(path))
        key = (ident, getattr(build, "__qualname__", repr(build)))
        if ident is not None and key in _DERIVED:
            _DERIVED.move_to_end(key)
            return _DERIVED[key]
        value = build(self.load_from_path(None, path))
        if ident is not None:
            _DERIVED[key] = value
            while len(_DERIVED) > DERIVED_MAX:
                _DERIVED.popitem(last=False)
        return value

    def remove_stored(self, asset_path: list[str], partition: str) -> None:
        """Delete one stored partition (a pair no longer searched, issue 17)."""
        path = self._base_path.joinpath(*asset_path) / partition
        table, bundle = self._table_path(path), self._bundle_path(path)
        if table.exists():
            table.unlink()
        if bundle.exists():
            _remove_tree(bundle)

    def load_partitions(self, context: InputContext):
        """Per-scan partitions read by a campaign-level asset are always ``{scan: output}``,
        also for a campaign of one scan (Dagster's default hands one partition over bare)."""
        if context.has_partition_key:  # per-scan asset reading its own scan's partition
            return super().load_partitions(context)
        paths = self._get_paths_for_partitions(context)
        out = {}
        for key in context.asset_partition_keys:
            obj = self._load_partition_from_path(context, key, paths[key])
            if obj is not None:
                out[key] = obj
        return out


class ParquetStore(ConfigurableIOManagerFactory):
    """The forestmap asset store; ``base_url`` is a local folder or any fsspec URL."""

    base_url: str = ""

    def create_io_manager(self, context) -> ParquetIOManager:
        return ParquetIOManager(base_path=UPath(self.base_url or default_store_url()))
