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


def test_fsspec_memory_url():
    path = UPath("memory://forestmap-test/t.parquet")
    store.write_table_atomic(pd.DataFrame({"a": [1, 2]}), path)
    assert store.read_table(path).num_rows == 2
