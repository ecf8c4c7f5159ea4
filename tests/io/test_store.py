"""The Parquet asset store writes atomically and round-trips tables and bundles."""

from __future__ import annotations

import pandas as pd
import pytest
from upath import UPath

from forestmap_assets.io import store


def test_table_round_trip_and_no_temp_left(tmp_path):
    df = pd.DataFrame({"a": [1, 2, 3], "b": [0.5, 1.5, 2.5]})
    path = tmp_path / "x" / "t.parquet"
    store.write_table_atomic(df, path)
    assert store.read_table(path).to_pandas().equals(df)
    assert [p.name for p in path.parent.iterdir()] == ["t.parquet"]


def test_failed_write_leaves_old_file_intact(tmp_path):
    path = tmp_path / "t.parquet"
    store.write_table_atomic(pd.DataFrame({"a": [1]}), path)
    with pytest.raises(TypeError):
        store.write_table_atomic("not a table", path)  # type: ignore[arg-type]
    assert store.read_table(path).to_pandas()["a"].tolist() == [1]
    assert [p.name for p in tmp_path.iterdir()] == ["t.parquet"]


def test_bundle_round_trip_and_replace(tmp_path):
    path = UPath(tmp_path / "b.bundle")
    store.write_bundle_atomic({"x": pd.DataFrame({"a": [1]}), "y": pd.DataFrame({"b": [2.0]})}, path)
    store.write_bundle_atomic({"x": pd.DataFrame({"a": [7]})}, path)
    out = store.read_bundle(path)
    assert list(out) == ["x"] and out["x"]["a"].tolist() == [7]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.bundle"]


def test_bundle_tables_read_only_those_asked_for(tmp_path):
    """An input's metadata "tables" (next_vantage_points reads each scan's surface, not its
    boundary pixels): only those tables are read, locally and through fsspec."""
    bundle = {"boundaries": pd.DataFrame({"v": range(5)}), "surface": pd.DataFrame({"ix": [1, 2]}),
              "info": pd.DataFrame({"voxel_m": [0.05]})}
    for path in (UPath(tmp_path / "o.bundle"), UPath("memory://forestmap-test/o.bundle")):
        store.write_bundle_atomic(bundle, path)
        got = store.read_bundle(path, tables=["surface", "info", "absent"])
        assert sorted(got) == ["info", "surface"] and got["surface"]["ix"].tolist() == [1, 2]
        assert sorted(store.read_bundle(path)) == ["boundaries", "info", "surface"]

    class Context:  # what Dagster hands the IO manager for an input with that metadata
        definition_metadata = {"tables": ["surface"]}

    manager = store.ParquetIOManager(base_path=UPath(tmp_path))
    assert list(manager.load_from_path(Context(), UPath(tmp_path / "o"))) == ["surface"]


def test_fsspec_memory_url():
    path = UPath("memory://forestmap-test/t.parquet")
    store.write_table_atomic(pd.DataFrame({"a": [1, 2]}), path)
    assert store.read_table(path).num_rows == 2


def test_concurrent_bundle_writers_and_a_reader(tmp_path):
    """Two writers replacing one bundle folder while a reader reads it: every write succeeds,
    every read sees a whole bundle, and one complete bundle is left with no temporary folder."""
    import threading

    path = UPath(tmp_path / "x.bundle")
    store.write_bundle_atomic({"a": pd.DataFrame({"v": [0]})}, path)
    errors, seen = [], []

    def writer(w):
        try:
            for i in range(40):
                store.write_bundle_atomic(
                    {"a": pd.DataFrame({"v": [w * 1000 + i]}), "b": pd.DataFrame({"v": [w]})}, path)
        except Exception as exc:  # pragma: no cover - the assertion below reports it
            errors.append(exc)

    def reader():
        for _ in range(80):
            for _attempt in range(20):
                try:
                    seen.append(store.read_bundle(path))
                    break
                except (FileNotFoundError, OSError):
                    continue  # between the two renames of a swap

    threads = [threading.Thread(target=writer, args=(w,)) for w in (1, 2)]
    threads.append(threading.Thread(target=reader))
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    final = store.read_bundle(path)
    assert set(final) == {"a", "b"} and final["a"]["v"][0] // 1000 == final["b"]["v"][0]
    assert all(set(b) in ({"a"}, {"a", "b"}) for b in seen)
    assert [p.name for p in UPath(tmp_path).iterdir()] == ["x.bundle"]


def test_read_table_gives_one_chunk_a_column(tmp_path):
    """A table stored in many row groups reads back with each column in one chunk, so that
    ``to_numpy`` is a view and not a copy at every call (issue 16)."""
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.table({"x": np.arange(50_000, dtype=np.float32), "row": np.arange(50_000, dtype=np.int32)})
    path = tmp_path / "t.parquet"
    pq.write_table(table, path, row_group_size=5_000)
    assert pq.read_table(path).column("x").num_chunks > 1
    got = store.read_table(path, ["x", "row"])
    assert [got.column(c).num_chunks for c in got.column_names] == [1, 1]
    assert got.equals(table)
    assert np.shares_memory(got.column("x").to_numpy(), got.column("x").to_numpy())
