"""A run's per-scan stages read its range image once (issue 18): the store hands the same Arrow
table over while the file is unchanged, and the image decoded from it is shared and read-only."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from upath import UPath

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io import store
from forestmap_assets.io.store import ParquetIOManager, forget_recent


def _image(seed: int) -> RangeImage:
    rng = np.random.default_rng(seed)
    r = rng.uniform(2.0, 25.0, (30, 60)).astype(np.float32)
    r[rng.random(r.shape) < 0.2] = np.nan
    pts = rng.normal(size=(30, 60, 3)).astype(np.float32)
    return RangeImage(r, np.arange(60.0), 15.0 - np.arange(30.0), (0.8, -1.2), points=pts)


def test_range_image_read_once_per_file_version(tmp_path):
    io = ParquetIOManager(base_path=UPath(tmp_path))
    path = UPath(tmp_path) / "range_images" / "A"
    first = _image(1).to_table()
    io.dump_to_path(None, first, path)
    assert io.read_stored(["range_images"], "A") is first  # just written: not read back
    forget_recent()
    read = io.read_stored(["range_images"], "A")
    assert read is not first and read.equals(first)
    assert io.read_stored(["range_images"], "A") is read

    image = RangeImage.from_table(read)
    assert RangeImage.from_table(read) is image
    assert not image.range_m.flags.writeable and not image.xyz.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        image.range_m[0, 0] = 1.0

    io.dump_to_path(None, _image(2).to_table(), path)  # a new version of the file
    forget_recent()
    again = io.read_stored(["range_images"], "A")
    assert again is not read and not again.equals(read)
    other = RangeImage.from_table(again)
    assert other is not image
    assert np.array_equal(other.range_m, _image(2).range_m, equal_nan=True)


def test_derived_objects_are_built_once_while_the_file_is_unchanged(tmp_path):
    """A pair step's prepared scan cloud (issue 16): built once per worker and stored file."""
    io = ParquetIOManager(base_path=UPath(tmp_path))
    store.write_table_atomic(pd.DataFrame({"a": [1.0, 2.0]}), tmp_path / "c" / "refine_clouds" / "s1.parquet")
    calls = []

    def build(table):
        calls.append(1)
        return float(table["a"].sum())

    assert io.derived_from_stored(["c", "refine_clouds"], "s1", build) == 3.0
    assert io.derived_from_stored(["c", "refine_clouds"], "s1", build) == 3.0
    assert len(calls) == 1
    store.write_table_atomic(pd.DataFrame({"a": [5.0]}), tmp_path / "c" / "refine_clouds" / "s1.parquet")
    assert io.derived_from_stored(["c", "refine_clouds"], "s1", build) == 5.0  # a new file: built again
    assert len(calls) == 2
    forget_recent()
    assert io.derived_from_stored(["c", "refine_clouds"], "s1", build) == 5.0
    assert len(calls) == 3
    with pytest.raises(FileNotFoundError):
        io.derived_from_stored(["c", "refine_clouds"], "s9", build)


def test_tables_read_ahead_are_taken_once_with_their_columns(tmp_path, monkeypatch):
    """The tree list's range image columns are read in a background thread while the stages
    before it run (issue 16): its input loading takes each table once, only with the same
    columns and while the file is unchanged; what no step took is dropped at the run's end."""
    io = ParquetIOManager(base_path=UPath(tmp_path))
    for sid, seed in (("A", 1), ("B", 2)):
        io.dump_to_path(None, _image(seed).to_table(), UPath(tmp_path) / "range_images" / sid)
    forget_recent()
    reads = []
    real = store.read_table
    monkeypatch.setattr(store, "read_table", lambda p, columns=None: reads.append(columns) or real(p, columns))

    class Context:  # the tree list's input: all scans, some columns
        definition_metadata = {"columns": ["x", "y", "z"]}

    io.read_ahead(["range_images"], ["A", "B", "missing"], ["x", "y", "z"])
    assert len(store._AHEAD) == 2  # no file, nothing to read
    for fut in list(store._AHEAD.values()):
        fut.result()
    assert reads == [["x", "y", "z"]] * 2
    got = io.load_from_path(Context(), UPath(tmp_path) / "range_images" / "A")
    assert len(reads) == 2  # taken from the read-ahead
    assert got.equals(real(UPath(tmp_path) / "range_images" / "A.parquet", ["x", "y", "z"]))
    io.load_from_path(Context(), UPath(tmp_path) / "range_images" / "A")  # taken once: read again
    assert len(reads) == 3
    # other columns, or a file changed since, are not taken from the read-ahead
    b = UPath(tmp_path) / "range_images" / "B.parquet"
    assert store._taken_ahead(b, ["x", "y"]) is None
    io.dump_to_path(None, _image(3).to_table(), UPath(tmp_path) / "range_images" / "B")
    assert store._taken_ahead(b, ["x", "y", "z"]) is None
    forget_recent()
    assert not store._AHEAD
