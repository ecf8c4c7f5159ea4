"""Readers of unorganised point-cloud files (spec 1.2, DESIGN section 2): LAS/LAZ (laspy) and
PLY/PCD (open3d), turned into a range image by spherical projection.

LAS/LAZ is read in chunks of ``_CHUNK_POINTS`` (laspy, LAZ decompressed by lazrs on every core):
each chunk's points go to float64 scanner-frame coordinates and straight to their range,
azimuth and elevation, so a 30 M-point scan never holds its whole cloud as float64 xyz
(issue 18, big scans; numba kernels on every core, :mod:`forestmap_assets.io._cloud_kernels`).

A damaged file is refused, not read in part (issue 18): the header's point count is compared
with what the file holds (its size for binary data, its words for ASCII data) before the
backend reads it, and with the points the backend returned after (Open3D stops at the damage
and returns what it read, or a full-size array padded with zeros)."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io._cloud_kernels import fast_hypot, fix_rare, las_xyz, rgb8
from forestmap_assets.io._projection_kernels import small_pages
from forestmap_assets.io.readers_common import (
    BadScan,
    _project,
    _project_angles,
    check_signature,
    count_damage,
    count_words,
    to_rgb8,
)

_LAS_DAMAGE = "corrupt or truncated LAS/LAZ data"
_CHUNK_POINTS = 1_000_000  # (inferred) points per LAS/LAZ read: ~30 MB of decompressed records
_BLOCK = 1 << 17  # points converted at a time (their float64 x, y, z stay in the cache)


def _las_layout(path: Path) -> dict:
    """The fields of a LAS/LAZ public header block that say where the points are and how many
    (LAS 1.0-1.4; little endian, fixed offsets)."""
    with open(path, "rb") as f:
        head = f.read(375)
    if len(head) < 227:
        raise BadScan(f"{_LAS_DAMAGE} (truncated: the header is {len(head)} of at least 227 bytes)")
    minor = head[25]
    (encoding,) = struct.unpack_from("<H", head, 6)
    offset, _n_vlrs, fmt, rec_len, count = struct.unpack_from("<IIBHI", head, 96)
    out = {"offset": offset, "rec_len": rec_len, "count": count, "compressed": bool(fmt & 0xC0)}
    ends = []  # data stored after the points (waveform packets, extended VLRs)
    if minor >= 3 and len(head) >= 235 and encoding & 2:
        ends.append(struct.unpack_from("<Q", head, 227)[0])
    if minor >= 4 and len(head) >= 255:
        evlr_start, n_evlrs, count64 = struct.unpack_from("<QIQ", head, 235)
        out["count"] = count64 or count
        if n_evlrs:
            ends.append(evlr_start)
    out["data_end"] = min((e for e in ends if e >= offset), default=None)
    return out


def _check_las_size(path: Path) -> dict:
    """Refuse a LAS file smaller (truncated) or larger (wrong point count) than its header's
    ``offset_to_point_data + count * point_size``; for LAZ, one whose chunk table lies beyond
    the end of the file."""
    las = _las_layout(path)
    size = path.stat().st_size
    n, offset, rec = las["count"], las["offset"], las["rec_len"]
    if offset > size:
        raise BadScan(f"{_LAS_DAMAGE} ({count_damage(n, 0)}: it ends before its point data)")
    if las["compressed"]:
        with open(path, "rb") as f:
            f.seek(offset)
            raw = f.read(8)
        if len(raw) < 8:
            raise BadScan(f"{_LAS_DAMAGE} ({count_damage(n, 0)})")
        (table,) = struct.unpack("<q", raw)  # LAZ: the chunk table follows the compressed points
        if table > size and n:
            about = int(n * max(size - offset - 8, 0) / max(table - offset - 8, 1))
            held = f"about {about}, compressed data cut at byte {size} of {table}"
            raise BadScan(f"{_LAS_DAMAGE} ({count_damage(n, held)})")
        return las
    if rec <= 0:
        raise BadScan(f"{_LAS_DAMAGE} (header gives a point size of {rec} bytes)")
    end = size if las["data_end"] is None else min(las["data_end"], size)
    held = (end - offset) // rec
    if held < n or (held > n and las["data_end"] is None):
        raise BadScan(f"{_LAS_DAMAGE} ({count_damage(n, held)})")
    return las


def _check_laz_chunks(path: Path, header, n: int) -> None:
    """A LAZ file's chunk table against the header's point count (exact for variable-size
    chunks; for fixed-size ones the count must fall in the last chunk)."""
    try:
        import lazrs

        vlr = next(v for v in header.vlrs if getattr(v, "record_id", None) == 22204)
        laz = lazrs.LazVlr(vlr.record_data_bytes())
        with open(path, "rb") as f:
            f.seek(header.offset_to_point_data)
            chunks = lazrs.read_chunk_table(f, laz)
    except Exception:  # no lazrs, no LASzip VLR, no readable table: the header count stands
        return
    if not chunks:
        return
    if laz.uses_variable_size_chunks():
        held = sum(int(c[0]) for c in chunks)
        if held != n:
            raise BadScan(f"{_LAS_DAMAGE} ({count_damage(n, held)})")
        return
    size = laz.chunk_size()
    lo, hi = (len(chunks) - 1) * size + 1, len(chunks) * size
    if not lo <= n <= hi:
        held = f"{lo} to {hi} ({len(chunks)} compressed chunks of {size})"
        raise BadScan(f"{_LAS_DAMAGE} ({count_damage(n, held)})")


def read_las(path: Path, angular_step_deg, to_scanner=None) -> RangeImage:
    import laspy

    check_signature(path, (b"LASF",), "a LAS file")
    layout = _check_las_size(path)
    try:
        with laspy.open(str(path)) as reader:
            header = reader.header
            n = int(header.point_count)
            dims = set(header.point_format.dimension_names)
            points = _LasPoints(n, {"red", "green", "blue"} <= dims, "intensity" in dims)
            for chunk in reader.chunk_iterator(_CHUNK_POINTS):
                if points.held + len(chunk) > n:
                    raise BadScan(f"{_LAS_DAMAGE} ({count_damage(n, points.held + len(chunk))})")
                points.add(chunk, to_scanner)
    except BadScan:
        raise
    except Exception as exc:  # laspy's errors on damaged files are cryptic: say what happened
        first = (str(exc).splitlines() or [""])[0]
        said = f"header says {layout['count']} points; " if layout["count"] else ""
        raise BadScan(f"{_LAS_DAMAGE} ({said}{type(exc).__name__}: {first})") from exc
    if points.held != n:
        raise BadScan(f"{_LAS_DAMAGE} ({count_damage(n, points.held)})")
    if layout["compressed"]:
        _check_laz_chunks(path, header, n)
    rgb, points.rgb = points.rgb8(), None
    return _project_angles(points.range_m, points.azimuth_deg, points.elevation_deg, rgb,
                           points.intensity, angular_step_deg)


class _LasPoints:
    """A LAS/LAZ file's points gathered chunk by chunk as range (float32: what the range image
    keeps), azimuth and elevation (float64) in the scanner frame, raw colour and intensity.
    A chunk goes through in blocks of ``_BLOCK`` points (their z and hypot(x, y) in the
    cache): the coordinates and hypots by :func:`~forestmap_assets.io._cloud_kernels.las_xyz`
    on every core (x and y straight into the azimuth and elevation arrays: their pages are
    first touched in parallel), then numpy's arctan2 and degrees in place: the values of
    ``spherical_angles(chunk.x, chunk.y, chunk.z)``."""

    def __init__(self, n: int, has_rgb: bool, has_intensity: bool) -> None:
        self.held = 0
        self.range_m = small_pages(n, np.float32)
        self.azimuth_deg = small_pages(n, np.float64)
        self.elevation_deg = small_pages(n, np.float64)
        self.rgb = small_pages(n, np.uint16, 3) if has_rgb else None
        self.rgb_max = 0
        self.intensity = small_pages(n, np.uint16) if has_intensity else None
        self._z, self._h = np.empty(_BLOCK), np.empty(_BLOCK)
        self._fast = fast_hypot()

    def add(self, chunk, to_scanner) -> None:
        a, b = self.held, self.held + len(chunk)
        moved = to_scanner is not None  # project-frame file: to the scanner's frame in float64
        m = np.asarray(to_scanner if moved else np.eye(4), dtype=np.float64)
        scale = np.asarray(chunk.scales, dtype=np.float64)
        offset = np.asarray(chunk.offsets, dtype=np.float64)
        xyz = [np.asarray(chunk.array[name]) for name in ("X", "Y", "Z")]
        for s in range(0, b - a, _BLOCK):
            e = min(s + _BLOCK, b - a)
            x, y = self.azimuth_deg[a + s:a + e], self.elevation_deg[a + s:a + e]
            z, h, r = self._z[:e - s], self._h[:e - s], self.range_m[a + s:a + e]
            if las_xyz(*(c[s:e] for c in xyz), scale, offset, m, moved, x, y, z, h, r,
                       self._fast) and self._fast:
                fix_rare(x, y, z, h, r)
            np.degrees(np.arctan2(y, x, out=x), out=x)  # the azimuth, in place of x
            np.degrees(np.arctan2(z, h, out=y), out=y)  # the elevation, in place of y
        if self.rgb is not None:
            for i, name in enumerate(("red", "green", "blue")):
                self.rgb[a:b, i] = np.asarray(chunk[name])
            if b > a:
                self.rgb_max = max(self.rgb_max, int(self.rgb[a:b].max()))
        if self.intensity is not None:
            self.intensity[a:b] = np.asarray(chunk["intensity"])
        self.held = b

    def rgb8(self) -> np.ndarray | None:
        """Colour as uint8 (``to_rgb8``, in one parallel pass): 16-bit per the LAS spec; files
        holding 8-bit values (max <= 255) are kept as they are."""
        if self.rgb is None:
            return None
        out = np.empty(self.rgb.shape, dtype=np.uint8)
        rgb8(self.rgb, 65535.0 if self.rgb_max > 255 else 255.0, out)
        return out


_PLY_SIZES = {
    **dict.fromkeys(("char", "uchar", "int8", "uint8"), 1),
    **dict.fromkeys(("short", "ushort", "int16", "uint16"), 2),
    **dict.fromkeys(("int", "uint", "int32", "uint32", "float", "float32"), 4),
    **dict.fromkeys(("double", "float64"), 8),
}
_PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")


def _ply_header(path: Path) -> tuple[str, list[list], int]:
    """PLY header: format, elements ``[name, count, bytes per row (None: has a list
    property), properties, (name, type) of the scalar properties]`` and the header's length in
    bytes."""
    with open(path, "rb") as f:
        head = f.read(1 << 20)
    end = re.search(rb"end_header[ \t]*\r?\n", head)
    if end is None:
        raise BadScan("damaged PLY header (no end_header line)")
    fmt, elements = None, []
    for ln in head[: end.start()].decode("ascii", errors="replace").splitlines()[1:]:
        tok = ln.split()
        if not tok:
            continue
        if tok[0] == "format" and len(tok) >= 2:
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise BadScan(f"damaged PLY header (line {ln.strip()!r})")
            elements.append([tok[1], int(tok[2]), 0, 0, []])
        elif tok[0] == "property" and elements:
            el = elements[-1]
            if len(tok) == 5 and tok[1] == "list":
                el[2] = None
            elif len(tok) == 3 and tok[1] in _PLY_SIZES:
                el[2] = None if el[2] is None else el[2] + _PLY_SIZES[tok[1]]
                el[4].append((tok[2], tok[1]))
            else:
                raise BadScan(f"damaged PLY header (line {ln.strip()!r})")
            el[3] += 1
    if fmt not in _PLY_FORMATS:
        raise BadScan(f"damaged PLY header (format {fmt!r}, expected one of {', '.join(_PLY_FORMATS)})")
    return fmt, elements, end.end()


def _vertex_index(elements: list[list]) -> int | None:
    """The position of the ``vertex`` element among a PLY header's elements (None: none)."""
    return next((i for i, e in enumerate(elements) if e[0] == "vertex"), None)


def _check_ply(path: Path, header: tuple[str, list[list], int]) -> int:
    """The header's (:func:`_ply_header`) vertex count, after checking that the file holds that
    many vertices: binary data by the file size (when the vertex element and those before it
    have fixed-size rows), ASCII data by its words (when the vertex element comes first)."""
    fmt, elements, start = header
    index = _vertex_index(elements)
    if index is None:
        raise BadScan("damaged PLY header (no 'element vertex' line)")
    _, n, row, props, _ = elements[index]
    before, after = elements[:index], elements[index + 1 :]
    if fmt == "ascii":
        if index == 0 and row is not None and props:
            held = count_words(path, start) // props
            if held < n or (held > n and not after):
                raise BadScan(count_damage(n, held))
        return n
    if row and all(e[2] is not None for e in before):
        start += sum(e[1] * e[2] for e in before)
        held = max(path.stat().st_size - start, 0) // row
        if held < n or (held > n and not after):
            raise BadScan(count_damage(n, held))
    return n


_PLY_NUMPY = {
    **dict.fromkeys(("char", "int8"), "i1"), **dict.fromkeys(("uchar", "uint8"), "u1"),
    **dict.fromkeys(("short", "int16"), "i2"), **dict.fromkeys(("ushort", "uint16"), "u2"),
    **dict.fromkeys(("int", "int32"), "i4"), **dict.fromkeys(("uint", "uint32"), "u4"),
    **dict.fromkeys(("float", "float32"), "f4"), **dict.fromkeys(("double", "float64"), "f8"),
}


def _binary_ply_vertices(path: Path, header: tuple[str, list[list], int] | None = None) -> np.ndarray | None:
    """The vertex rows of a binary PLY (a structured array mapped from the file) when the vertex
    element and those before it have fixed-size rows, else None (Open3D reads it); ``header``:
    the file's :func:`_ply_header`, if already read. Open3D's reader took 0.10-0.13 s a 2.3
    M-point cloud, this 2 ms, and the columns 0.03 s (issue 16)."""
    fmt, elements, start = header or _ply_header(path)
    index = _vertex_index(elements)
    if fmt == "ascii" or index is None or any(e[2] is None for e in elements[: index + 1]):
        return None
    _, n, row, _, props = elements[index]
    if not {"x", "y", "z"} <= {name for name, _ in props} or len({name for name, _ in props}) < len(props):
        return None
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(name, order + _PLY_NUMPY[kind]) for name, kind in props])
    offset = start + sum(e[1] * e[2] for e in elements[:index])
    if n == 0 or path.stat().st_size < offset + n * row:
        return None
    return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(n,))


def _ply_columns(v: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Points (float64), colour (uint8 RGB or None) and intensity (float32 or None) of PLY vertex
    rows, as Open3D's reader names them (``red, green, blue``; ``intensity``). The points are
    stored column by column, as the projection reads them (:func:`~forestmap_assets.io.
    angular_grid.spherical_angles` then needs no copy: 15-20 ms and 56 MB less on a 2.3 M-point
    scan, issue 16)."""
    names = set(v.dtype.names)
    xyz = np.empty((len(v), 3), order="F")
    for i, c in enumerate("xyz"):
        xyz[:, i] = v[c]
    rgb = intensity = None
    if {"red", "green", "blue"} <= names:
        c = np.column_stack([v[c] for c in ("red", "green", "blue")])
        rgb = c if c.dtype == np.uint8 else to_rgb8(c)
    if "intensity" in names:
        intensity = np.asarray(v["intensity"], dtype=np.float32)
    return xyz, rgb, intensity


def _pcd_header(path: Path) -> tuple[dict[str, list[str]], int]:
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    data = re.search(rb"(?m)^DATA[ \t]+\S+[ \t]*\r?\n", head)
    text = head[: data.start()] if data else head.split(b"\nDATA", 1)[0]
    fields: dict[str, list[str]] = {}
    for ln in text.decode("ascii", errors="replace").splitlines():
        if ln.strip() and not ln.startswith("#"):
            key, *values = ln.split()
            fields[key.upper()] = values
    if data is None or "FIELDS" not in fields:
        raise BadScan("not a PCD file (no FIELDS/DATA header)")
    fields["DATA"] = head[data.start() : data.end()].decode("ascii", errors="replace").split()[1:2]
    return fields, data.end()


def _check_pcd(path: Path) -> int:
    """The header's POINTS, after checking it against WIDTH x HEIGHT and what the file holds
    (``binary``: file size; ``binary_compressed``: its block sizes; ``ascii``: words)."""
    fields, start = _pcd_header(path)

    def numbers(key: str, default: list[int] | None = None) -> list[int]:
        values = fields.get(key)
        if values is None and default is not None:
            return default
        try:
            out = [int(v) for v in values or []]
        except ValueError:
            out = []
        if not out or min(out) < 0:
            raise BadScan(f"damaged PCD header ({key} {' '.join(values or [])!r})")
        return out

    names = fields["FIELDS"]
    sizes = numbers("SIZE")
    counts = numbers("COUNT", [1] * len(names))
    if not len(names) == len(sizes) == len(counts):
        raise BadScan("damaged PCD header (FIELDS, SIZE and COUNT differ in length)")
    if "WIDTH" not in fields and "POINTS" not in fields:
        raise BadScan("damaged PCD header (neither POINTS nor WIDTH)")
    n = numbers("POINTS")[0] if "POINTS" in fields else None
    if "WIDTH" in fields:
        width, height = numbers("WIDTH")[0], numbers("HEIGHT", [1])[0]
        if n is not None and n != width * height:
            raise BadScan(f"damaged PCD header (POINTS {n}, but WIDTH x HEIGHT = {width} x {height})")
        n = width * height
    kind = (fields["DATA"] or [""])[0].lower()
    row = sum(s * c for s, c in zip(sizes, counts, strict=True))
    if not row:
        raise BadScan("damaged PCD header (SIZE and COUNT give 0 bytes per point)")
    size = path.stat().st_size
    if kind == "ascii":
        held = count_words(path, start) // max(sum(counts), 1)
    elif kind == "binary":
        held = (size - start) // row
    elif kind == "binary_compressed":
        with open(path, "rb") as f:
            f.seek(start)
            raw = f.read(8)
        if len(raw) < 8:
            raise BadScan(count_damage(n, 0))
        packed, unpacked = struct.unpack("<II", raw)
        if unpacked != n * row:
            raise BadScan(f"{count_damage(n, unpacked // row)} (compressed block of {unpacked} bytes)")
        if start + 8 + packed > size:
            held = f"{size - start - 8} of their {packed} compressed bytes"
            raise BadScan(count_damage(n, held))
        return n
    else:
        raise BadScan(f"damaged PCD header (DATA {kind!r}, expected ascii, binary or binary_compressed)")
    if held != n:
        raise BadScan(count_damage(n, held))
    return n


def read_open3d(path: Path, angular_step_deg, to_scanner=None) -> RangeImage:
    import open3d as o3d

    if path.suffix.lower() == ".ply":
        check_signature(path, (b"ply\n", b"ply\r\n", b"ply\r"), "a PLY file")
        header = _ply_header(path)
        n = _check_ply(path, header)
        if (rows := _binary_ply_vertices(path, header)) is not None:
            xyz, rgb, intensity = _ply_columns(rows)
            del rows  # unmaps the file
            return _project(xyz, rgb, intensity, angular_step_deg, to_scanner, own=True)
    else:
        n = _check_pcd(path)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        pc = o3d.t.io.read_point_cloud(str(path))
    got = pc.point.positions.shape[0] if "positions" in pc.point else 0
    if got == 0:
        said = f"header says {n} points, " if n else ""
        raise BadScan(f"no points ({said}unreadable or empty point cloud)")
    if got != n:
        raise BadScan(count_damage(n, got))
    xyz = np.asarray(pc.point.positions.numpy(), dtype=np.float64)  # a view (it keeps the tensor)
    rgb = intensity = None
    if "colors" in pc.point:
        c = pc.point.colors.numpy()
        rgb = c.astype(np.uint8) if c.dtype == np.uint8 else to_rgb8(c)
    if "intensity" in pc.point:
        intensity = pc.point.intensity.numpy().reshape(-1).astype(np.float32)
    return _project(xyz, rgb, intensity, angular_step_deg, to_scanner)
