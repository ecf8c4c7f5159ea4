"""Reader of text point clouds ``.xyz .txt .csv`` (spec 1.2, DESIGN section 2): optional header
naming x y z [r g b] [intensity] columns, turned into a range image by spherical projection."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io.readers_common import BadScan, _project, one_line, to_rgb8

_NAME_ALIASES = {
    "x": "x",
    "y": "y",
    "z": "z",
    "r": "r",
    "red": "r",
    "g": "g",
    "green": "g",
    "b": "b",
    "blue": "b",
    "i": "intensity",
    "intensity": "intensity",
    "scalar_intensity": "intensity",
}


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def read_text(path: Path, angular_step_deg, to_scanner=None) -> RangeImage:
    import pandas as pd

    with open(path, "rb") as f:
        head = f.read(1 << 16)
    if b"\x00" in head:
        raise BadScan("binary data, not a text point list")
    lines = head.decode("utf-8", errors="replace").splitlines()
    skip = 0
    while skip < len(lines) and not lines[skip].strip():
        skip += 1
    if skip == len(lines):
        raise BadScan("no points (only blank lines)")
    first = lines[skip]
    sep = "," if "," in first else (";" if ";" in first else None)
    tokens = [t for t in re.split(sep if sep else r"\s+", first.strip()) if t != ""]
    names: list[str] | None = None
    if not all(_is_number(t) for t in tokens):
        names = [t.strip().strip("\"'").lstrip("/#").strip().lower() for t in tokens]
        skip += 1
    kwargs = dict(sep=sep or r"\s+", header=None, skiprows=skip, engine="c", skip_blank_lines=True)
    try:
        df = pd.read_csv(path, dtype=np.float64, **kwargs)
    except pd.errors.EmptyDataError as exc:
        raise BadScan("no points (header only)") from exc
    except pd.errors.ParserError as exc:
        raise BadScan(f"malformed text: {one_line(exc)}") from exc
    except ValueError as exc:
        raw = pd.read_csv(path, dtype=str, **kwargs)
        bad = raw.apply(pd.to_numeric, errors="coerce").isna() & raw.notna()
        r_i, c_i = np.argwhere(bad.to_numpy())[0] if bad.to_numpy().any() else (0, 0)
        value = raw.iat[int(r_i), int(c_i)] if bad.to_numpy().any() else "?"
        line = _data_line_number(path, skip, int(r_i))
        raise BadScan(f"line {line}: non-numeric value {str(value)[:40]!r}") from exc
    arr = df.to_numpy(dtype=np.float64)
    if arr.shape[0] == 0:
        raise BadScan("no points")
    ncol = arr.shape[1]
    if ncol < 3:
        raise BadScan(f"expected at least 3 columns (x y z), got {ncol}")
    cols: dict[str, int] = {}
    if names is not None and len(names) == ncol:
        for i, nm in enumerate(names):
            key = _NAME_ALIASES.get(nm)
            if key is not None and key not in cols:
                cols[key] = i
    if not {"x", "y", "z"} <= cols.keys():
        # by column count (inferred): 4 = x y z i, 6 = x y z r g b, 7 = x y z i r g b (PTS)
        cols = {"x": 0, "y": 1, "z": 2}
        if ncol in (4, 7):
            cols["intensity"] = 3
        if ncol == 6:
            cols.update(r=3, g=4, b=5)
        if ncol == 7:
            cols.update(r=4, g=5, b=6)
    held = _cut_last_line(path, sep)
    if held is not None and held < ncol:  # a cut file ends inside its last line
        line = _data_line_number(path, skip, arr.shape[0] - 1)
        raise BadScan(f"truncated: the last line ({line}) holds {held} of {ncol} values")
    xyz = arr[:, [cols["x"], cols["y"], cols["z"]]]
    missing = ~np.isfinite(xyz).all(1)
    if missing.any():
        line = _data_line_number(path, skip, int(np.argmax(missing)))
        raise BadScan(f"line {line}: missing or non-finite x/y/z")
    rgb = None
    if {"r", "g", "b"} <= cols.keys():
        raw = arr[:, [cols["r"], cols["g"], cols["b"]]]
        missing = ~np.isfinite(raw).all(1)
        if missing.any():
            line = _data_line_number(path, skip, int(np.argmax(missing)))
            raise BadScan(f"line {line}: missing or non-finite colour")
        rgb = to_rgb8(raw)
    intensity = arr[:, cols["intensity"]].astype(np.float32) if "intensity" in cols else None
    return _project(xyz, rgb, intensity, angular_step_deg, to_scanner)


def _cut_last_line(path: Path, sep: str | None) -> int | None:
    """The number of values on the last line of a file that does not end with a line break
    (where a cut file ends), else None."""
    with open(path, "rb") as f:
        size = f.seek(0, 2)
        f.seek(max(size - (1 << 16), 0))
        tail = f.read()
    if not tail or tail[-1:] in (b"\n", b"\r"):
        return None
    last = tail.splitlines()[-1].decode("utf-8", errors="replace").strip()
    return len([t for t in re.split(sep if sep else r"\s+", last) if t.strip()])


def _data_line_number(path: Path, skip: int, data_row: int) -> int:
    """1-based file line of the ``data_row``-th non-blank data line after ``skip`` lines."""
    with open(path, encoding="utf-8", errors="replace") as f:
        seen = -1
        for lineno, ln in enumerate(f, start=1):
            if lineno <= skip or not ln.strip():
                continue
            seen += 1
            if seen == data_row:
                return lineno
    return skip + data_row + 1
