"""Scan-file readers: every supported format to an organised :class:`RangeImage` (spec 1.2).

DESIGN section 2: one file per scan position, points in that scanner's own frame (origin at the
sensor), format chosen by extension. Organised sources (``.npz`` range images, structured E57
scans with row/column indices) are read as they are; unorganised clouds (LAS/LAZ, PLY, PCD,
text, unstructured E57) are turned into a range image by spherical projection
(:func:`forestmap_assets.io.projection.project_to_range_image`). Any failure is a
:class:`ScanReadError` whose message is one line ``<file>: <reason>``.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io.projection import nearest_per_pixel, project_to_range_image

__all__ = ["SCAN_EXTENSIONS", "ScanReadError", "read_scan"]


class ScanReadError(ValueError):
    """A scan file that cannot be read; the message is one line naming the file and reason."""


class _Bad(Exception):
    """Internal: reason a file is rejected (the file name is added by :func:`read_scan`)."""


def _one_line(text: object) -> str:
    return re.sub(r"\s+", " ", str(text)).strip()


# ---- colours and shared helpers ---------------------------------------------------------------


def _to_rgb8(values: np.ndarray, *, full_scale: float | None = None) -> np.ndarray:
    """Colours to uint8: 0-1 floats scaled by 255, 16-bit values by 1/257, 0-255 kept.

    ``full_scale`` (e.g. a LAS/E57 colour limit) overrides the guess from the values. Guess
    (inferred): non-integer values all <= 1 are 0-1; any value > 255 means 16-bit.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.size and (not np.all(np.isfinite(v)) or v.min() < 0):
        raise _Bad("colour values must be finite and non-negative")
    if full_scale is None:
        vmax = float(v.max()) if v.size else 0.0
        if vmax <= 1.0 and np.any(v != np.rint(v)):
            full_scale = 1.0
        elif vmax > 255.0:
            full_scale = 65535.0
        else:
            full_scale = 255.0
    return np.clip(np.rint(v * (255.0 / full_scale)), 0, 255).astype(np.uint8)


def _check_signature(path: Path, accepted: tuple[bytes, ...], what: str) -> None:
    with open(path, "rb") as f:
        head = f.read(max(len(s) for s in accepted))
    if not any(head.startswith(s) for s in accepted):
        raise _Bad(f"not {what} (bad signature)")


def _project(
    xyz: np.ndarray,
    rgb: np.ndarray | None,
    intensity: np.ndarray | None,
    angular_step_deg,
) -> RangeImage:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.shape[0] == 0:
        raise _Bad("no points")
    good = np.isfinite(xyz).all(1)
    if not good.any():
        raise _Bad("no finite points")
    try:
        return project_to_range_image(xyz, rgb, intensity, angular_step_deg=angular_step_deg)
    except ValueError as exc:
        raise _Bad(f"spherical projection failed: {_one_line(exc)}") from exc


# ---- .npz organised range image ---------------------------------------------------------------


def _npz_array(z, key: str, *, required: bool = True) -> np.ndarray | None:
    if key not in z.files:
        if required:
            raise _Bad(f"missing array '{key}'")
        return None
    arr = z[key]
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise _Bad(f"array '{key}' is not numeric (dtype {arr.dtype})")
    return arr


def _read_npz(path: Path, angular_step_deg) -> RangeImage:
    _check_signature(path, (b"PK\x03\x04", b"PK\x05\x06"), "an NPZ archive")
    with np.load(path, allow_pickle=False) as z:
        rng = _npz_array(z, "range")
        az = _npz_array(z, "azimuth_deg")
        el = _npz_array(z, "elevation_deg")
        intensity = _npz_array(z, "intensity", required=False)
        rgb = _npz_array(z, "rgb", required=False)
    if rng.ndim != 2 or 0 in rng.shape:
        raise _Bad(f"array 'range' must be 2-D (rows x cols), got shape {rng.shape}")
    rows, cols = rng.shape
    if az.shape != (cols,):
        raise _Bad(f"array 'azimuth_deg' has shape {az.shape}, expected ({cols},)")
    if el.shape != (rows,):
        raise _Bad(f"array 'elevation_deg' has shape {el.shape}, expected ({rows},)")
    if intensity is not None and intensity.shape != (rows, cols):
        raise _Bad(f"array 'intensity' has shape {intensity.shape}, expected {(rows, cols)}")
    if rgb is not None and rgb.shape != (rows, cols, 3):
        raise _Bad(f"array 'rgb' has shape {rgb.shape}, expected {(rows, cols, 3)}")
    az = az.astype(np.float64)
    el = el.astype(np.float64)
    rng = rng.astype(np.float32)
    if not (np.all(np.isfinite(az)) and np.all(np.isfinite(el))):
        raise _Bad("arrays 'azimuth_deg'/'elevation_deg' must be finite")
    if np.any(np.abs(el) > 90.0):
        raise _Bad("array 'elevation_deg' has values outside [-90, 90]")
    # RangeImage convention: azimuth increasing, elevation decreasing (row 0 on top)
    flip_c = cols > 1 and np.all(np.diff(az) < 0)
    flip_r = rows > 1 and np.all(np.diff(el) > 0)
    if cols > 1 and not (flip_c or np.all(np.diff(az) > 0)):
        raise _Bad("array 'azimuth_deg' is not strictly monotonic")
    if rows > 1 and not (flip_r or np.all(np.diff(el) < 0)):
        raise _Bad("array 'elevation_deg' is not strictly monotonic")
    sl = (slice(None, None, -1 if flip_r else 1), slice(None, None, -1 if flip_c else 1))
    if rgb is not None:
        rgb = _to_rgb8(rgb.reshape(-1, 3)).reshape(rows, cols, 3)[sl]
    if intensity is not None:
        intensity = intensity.astype(np.float32)[sl]
    return RangeImage(rng[sl], az[sl[1]], el[sl[0]], intensity=intensity, rgb=rgb)


# ---- .e57 -------------------------------------------------------------------------------------


def _e57_fields(e57, header, names: list[str]) -> dict[str, np.ndarray]:
    """Read per-point fields as float64 (libe57 converts integer nodes; exact below 2**53)."""
    from pye57 import libe57

    n = header.point_count
    out = {name: np.empty(n, dtype=np.float64) for name in names}
    bufs = libe57.VectorSourceDestBuffer()
    for name, arr in out.items():
        bufs.append(libe57.SourceDestBuffer(e57.image_file, name, arr, n, True, True))
    reader = header.points.reader(bufs)
    try:
        got = reader.read()
    finally:
        reader.close()
    if got != n:
        raise _Bad(f"short read of point data ({got} of {n} points)")
    return out


def _color_full_scale(header) -> float | None:
    node = header.node
    if not node.isDefined("colorLimits"):
        return None
    try:
        return float(node["colorLimits"]["colorRedMaximum"].value()) or None
    except Exception:  # malformed optional limits: fall back to guessing
        return None


def _fill_axis(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Fill angles of rows/columns without points: linear between, median step outside."""
    idx = np.flatnonzero(known)
    out = values.copy()
    if idx.size == values.size:
        return out
    if idx.size == 1:
        raise _Bad("structured scan has a single populated row/column")
    step = float(np.median(np.diff(values[idx]) / np.diff(idx)))
    allidx = np.arange(values.size)
    out = np.interp(allidx, idx, values[idx])
    out[: idx[0]] = values[idx[0]] - (idx[0] - allidx[: idx[0]]) * step
    out[idx[-1] + 1 :] = values[idx[-1]] + (allidx[idx[-1] + 1 :] - idx[-1]) * step
    return out


def _structured_image(
    row: np.ndarray,
    col: np.ndarray,
    r: np.ndarray,
    az: np.ndarray,
    el: np.ndarray,
    has_dir: np.ndarray,
    has_range: np.ndarray,
    rgb: np.ndarray | None,
    intensity: np.ndarray | None,
    max_pixels: int = 100_000_000,
) -> RangeImage | None:
    """Organised image straight from E57 row/column indices (None if the grid is not regular).

    Row angle = mean elevation of the row's points, column angle = circular-mean azimuth of the
    column's points (unwrapped), both filled where a row/column has no direction at all. Rows
    are flipped to put the highest elevation on top and columns to make azimuth increase; a
    file whose rows run along azimuth is transposed (inferred: some scanners index that way).
    """
    row = row[has_dir].astype(np.int64)
    col = col[has_dir].astype(np.int64)
    row -= row.min()
    col -= col.min()
    a, e = np.radians(az[has_dir]), el[has_dir]
    nr, nc = int(row.max()) + 1, int(col.max()) + 1
    if nr * nc > max_pixels:  # index bounds far beyond any image: project instead
        return None

    def within_var(group: np.ndarray, ng: int, vals: np.ndarray) -> float:
        cnt = np.bincount(group, minlength=ng)
        s1 = np.bincount(group, vals, ng)
        s2 = np.bincount(group, vals * vals, ng)
        m = cnt > 0
        return float(np.sum(s2[m] - s1[m] ** 2 / cnt[m]) / max(1, cnt.sum()))

    if within_var(col, nc, e) < within_var(row, nr, e):  # rows run vertically: transpose
        row, col, nr, nc = col, row, nc, nr
    cnt_r = np.bincount(row, minlength=nr)
    el_row = np.bincount(row, e, nr) / np.maximum(cnt_r, 1)
    cnt_c = np.bincount(col, minlength=nc)
    az_col = np.arctan2(np.bincount(col, np.sin(a), nc), np.bincount(col, np.cos(a), nc))
    known_c = cnt_c > 0
    az_col[known_c] = np.unwrap(az_col[known_c])
    el_row = _fill_axis(el_row, cnt_r > 0)
    az_col = _fill_axis(np.degrees(az_col), known_c)
    if nr > 1 and np.median(np.diff(el_row)) > 0:
        row, el_row = nr - 1 - row, el_row[::-1]
    if nc > 1 and np.median(np.diff(az_col)) < 0:
        col, az_col = nc - 1 - col, az_col[::-1]
    if (nr > 1 and not np.all(np.diff(el_row) < 0)) or (nc > 1 and not np.all(np.diff(az_col) > 0)):
        return None
    az_col -= 360.0 * np.floor((az_col[0] + 180.0) / 360.0)
    flat = row * nc + col
    ranged = has_range[has_dir]
    fr, rr = flat[ranged], r[has_dir][ranged]
    keep = nearest_per_pixel(fr, rr)
    img = np.full(nr * nc, np.nan, dtype=np.float32)
    img[fr[keep]] = rr[keep]
    rgb_img = int_img = None
    if rgb is not None:
        rgb_img = np.zeros((nr * nc, 3), dtype=np.uint8)
        rgb_img[fr[keep]] = rgb[has_dir][ranged][keep]
        rgb_img = rgb_img.reshape(nr, nc, 3)
    if intensity is not None:
        int_img = np.full(nr * nc, np.nan, dtype=np.float32)
        int_img[fr[keep]] = intensity[has_dir][ranged][keep]
        int_img = int_img.reshape(nr, nc)
    return RangeImage(img.reshape(nr, nc), az_col, el_row, intensity=int_img, rgb=rgb_img)


def _read_e57(path: Path, angular_step_deg, scan_index: int | None = None) -> RangeImage:
    import pye57

    _check_signature(path, (b"ASTM-E57",), "an E57 file")
    with pye57.E57(str(path)) as e57:
        count = e57.scan_count
        if count == 0:
            raise _Bad("no scans in data3D")
        if scan_index is None:
            if count > 1:
                raise _Bad(f"holds {count} scans; give scan_index (one scan per position)")
            scan_index = 0
        if not 0 <= scan_index < count:
            raise _Bad(f"scan_index {scan_index} out of range (file holds {count} scans)")
        header = e57.get_header(scan_index)
        fields = set(header.point_fields)
        n_points = header.point_count
        if n_points == 0:
            raise _Bad("scan has no points")
        cart = {"cartesianX", "cartesianY", "cartesianZ"}
        sph = {"sphericalRange", "sphericalAzimuth", "sphericalElevation"}
        use_sph = sph <= fields
        if not use_sph and not cart <= fields:
            raise _Bad("no cartesianX/Y/Z or sphericalRange/Azimuth/Elevation fields")
        names = sorted(sph if use_sph else cart)
        state = "sphericalInvalidState" if use_sph else "cartesianInvalidState"
        colours = ["colorRed", "colorGreen", "colorBlue"]
        has_rgb = set(colours) <= fields
        structured = {"rowIndex", "columnIndex"} <= fields
        extra = [f for f in [state, "intensity"] if f in fields]
        extra += colours if has_rgb else []
        extra += ["rowIndex", "columnIndex"] if structured else []
        data = _e57_fields(e57, header, names + extra)
        full_scale = _color_full_scale(header)
    inv = data[state] if state in data else np.zeros(n_points)
    if use_sph:
        r = data["sphericalRange"]
        az = np.degrees(data["sphericalAzimuth"])
        el = np.degrees(data["sphericalElevation"])
        xyz = np.column_stack(
            [
                r * np.cos(np.radians(el)) * np.cos(np.radians(az)),
                r * np.cos(np.radians(el)) * np.sin(np.radians(az)),
                r * np.sin(np.radians(el)),
            ]
        )
    else:
        xyz = np.column_stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]])
        h = np.hypot(xyz[:, 0], xyz[:, 1])
        r = np.hypot(h, xyz[:, 2])
        az = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
        el = np.degrees(np.arctan2(xyz[:, 2], h))
    finite = np.isfinite(xyz).all(1)
    has_range = (inv == 0) & finite & (r > 0)
    # E57 invalid state 1: direction meaningful, range not (a pixel without a return)
    dir_ok = np.isfinite(az) & np.isfinite(el) & (True if use_sph else r > 0)
    has_dir = has_range | ((inv == 1) & dir_ok)
    rgb = None
    if has_rgb:
        rgb = _to_rgb8(np.column_stack([data[c] for c in colours]), full_scale=full_scale)
    intensity = data["intensity"].astype(np.float32) if "intensity" in data else None
    if structured and has_dir.any():
        rows_u = np.unique(data["rowIndex"][has_dir])
        cols_u = np.unique(data["columnIndex"][has_dir])
        if rows_u.size > 1 and cols_u.size > 1:
            img = _structured_image(
                data["rowIndex"],
                data["columnIndex"],
                r,
                az,
                el,
                has_dir,
                has_range,
                rgb,
                intensity,
            )
            if img is not None:
                return img
    if not has_range.any():
        raise _Bad("no valid points")
    return _project(
        xyz[has_range],
        None if rgb is None else rgb[has_range],
        None if intensity is None else intensity[has_range],
        angular_step_deg,
    )


# ---- .las / .laz ------------------------------------------------------------------------------


def _read_las(path: Path, angular_step_deg) -> RangeImage:
    import laspy

    _check_signature(path, (b"LASF",), "a LAS file")
    try:
        las = laspy.read(str(path))
    except Exception as exc:  # laspy's errors on damaged files are cryptic: say what happened
        first = (str(exc).splitlines() or [""])[0]
        raise _Bad(f"corrupt or truncated LAS/LAZ data ({type(exc).__name__}: {first})") from exc
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    dims = set(las.point_format.dimension_names)
    rgb = None
    if {"red", "green", "blue"} <= dims:
        raw = np.column_stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)])
        # 16-bit colour per the LAS spec; files holding 8-bit values (max <= 255) are kept as is
        rgb = _to_rgb8(raw, full_scale=65535.0 if raw.size and raw.max() > 255 else 255.0)
    intensity = np.asarray(las.intensity, dtype=np.float32) if "intensity" in dims else None
    return _project(xyz, rgb, intensity, angular_step_deg)


# ---- .ply / .pcd (open3d) ---------------------------------------------------------------------


def _check_pcd_header(path: Path) -> None:
    with open(path, "rb") as f:
        head = f.read(4096)
    text = head.split(b"\nDATA", 1)[0].decode("ascii", errors="replace")
    keys = {
        ln.split()[0].upper() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")
    }
    if b"\nDATA" not in head or "FIELDS" not in keys:
        raise _Bad("not a PCD file (no FIELDS/DATA header)")


def _read_open3d(path: Path, angular_step_deg) -> RangeImage:
    import open3d as o3d

    if path.suffix.lower() == ".ply":
        _check_signature(path, (b"ply\n", b"ply\r\n", b"ply\r"), "a PLY file")
    else:
        _check_pcd_header(path)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        pc = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in pc.point or pc.point.positions.shape[0] == 0:
        raise _Bad("no points (unreadable or empty point cloud)")
    xyz = pc.point.positions.numpy().astype(np.float64)
    rgb = intensity = None
    if "colors" in pc.point:
        c = pc.point.colors.numpy()
        rgb = c.astype(np.uint8) if c.dtype == np.uint8 else _to_rgb8(c)
    if "intensity" in pc.point:
        intensity = pc.point.intensity.numpy().reshape(-1).astype(np.float32)
    return _project(xyz, rgb, intensity, angular_step_deg)


# ---- .xyz / .txt / .csv -----------------------------------------------------------------------

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


def _read_text(path: Path, angular_step_deg) -> RangeImage:
    import pandas as pd

    with open(path, "rb") as f:
        head = f.read(1 << 16)
    if b"\x00" in head:
        raise _Bad("binary data, not a text point list")
    lines = head.decode("utf-8", errors="replace").splitlines()
    skip = 0
    while skip < len(lines) and not lines[skip].strip():
        skip += 1
    if skip == len(lines):
        raise _Bad("no points (only blank lines)")
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
        raise _Bad("no points (header only)") from exc
    except pd.errors.ParserError as exc:
        raise _Bad(f"malformed text: {_one_line(exc)}") from exc
    except ValueError as exc:
        raw = pd.read_csv(path, dtype=str, **kwargs)
        bad = raw.apply(pd.to_numeric, errors="coerce").isna() & raw.notna()
        r_i, c_i = np.argwhere(bad.to_numpy())[0] if bad.to_numpy().any() else (0, 0)
        value = raw.iat[int(r_i), int(c_i)] if bad.to_numpy().any() else "?"
        line = _data_line_number(path, skip, int(r_i))
        raise _Bad(f"line {line}: non-numeric value {str(value)[:40]!r}") from exc
    arr = df.to_numpy(dtype=np.float64)
    if arr.shape[0] == 0:
        raise _Bad("no points")
    ncol = arr.shape[1]
    if ncol < 3:
        raise _Bad(f"expected at least 3 columns (x y z), got {ncol}")
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
    xyz = arr[:, [cols["x"], cols["y"], cols["z"]]]
    missing = ~np.isfinite(xyz).all(1)
    if missing.any():
        line = _data_line_number(path, skip, int(np.argmax(missing)))
        raise _Bad(f"line {line}: missing or non-finite x/y/z")
    rgb = None
    if {"r", "g", "b"} <= cols.keys():
        rgb = _to_rgb8(arr[:, [cols["r"], cols["g"], cols["b"]]])
    intensity = arr[:, cols["intensity"]].astype(np.float32) if "intensity" in cols else None
    return _project(xyz, rgb, intensity, angular_step_deg)


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


# ---- dispatch ---------------------------------------------------------------------------------

_READERS: dict[str, Callable[..., RangeImage]] = {
    ".npz": _read_npz,
    ".e57": _read_e57,
    ".las": _read_las,
    ".laz": _read_las,
    ".ply": _read_open3d,
    ".pcd": _read_open3d,
    ".xyz": _read_text,
    ".txt": _read_text,
    ".csv": _read_text,
}
SCAN_EXTENSIONS = tuple(_READERS)


def read_scan(
    path: str | Path,
    *,
    angular_step_deg: float | tuple[float, float] | None = None,
    tilt_deg: tuple[float, float] = (0.0, 0.0),
    scan_index: int | None = None,
) -> RangeImage:
    """Read one scan file (DESIGN section 2) as an organised range image (spec 1.2).

    Dispatches on the extension (``.npz .e57 .las .laz .ply .pcd .xyz .txt .csv``). Points are
    in the scanner's own frame; unorganised clouds are projected at ``angular_step_deg``
    (scalar or (az, el); None = estimated from the data). ``tilt_deg`` = measured (roll,
    pitch) attached to the image for levelling. ``scan_index`` picks a scan of a multi-scan
    E57 (default: the file must hold exactly one). rgb is kept where present; NaN marks
    pixels without a return. Raises :class:`ScanReadError` (one line: ``<file>: <reason>``).
    """
    name = str(path)
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in _READERS:
        reason = f"unsupported extension '{ext}'" if ext else "no file extension"
        raise ScanReadError(f"{name}: {reason} (supported: {' '.join(SCAN_EXTENSIONS)})")
    try:
        tilt = tuple(float(t) for t in tilt_deg)
    except (TypeError, ValueError):
        tilt = ()
    if len(tilt) != 2 or not np.all(np.isfinite(tilt)):
        raise ScanReadError(f"{name}: tilt_deg must be two finite numbers (roll, pitch)")
    if not p.exists():
        raise ScanReadError(f"{name}: file not found")
    if p.is_dir():
        raise ScanReadError(f"{name}: is a directory, not a scan file")
    if p.stat().st_size == 0:
        raise ScanReadError(f"{name}: empty file")
    kwargs = {"scan_index": scan_index} if ext == ".e57" else {}
    try:
        image = _READERS[ext](p, angular_step_deg, **kwargs)
    except _Bad as exc:
        raise ScanReadError(f"{name}: {_one_line(exc)}") from exc
    except MemoryError:
        raise
    except Exception as exc:  # any backend failure becomes one clear line
        lines = [ln for ln in str(exc).splitlines() if ln.strip()]
        reason = _one_line(lines[0]) if lines else "unreadable"
        raise ScanReadError(f"{name}: {type(exc).__name__}: {reason}"[: len(name) + 300]) from exc
    return replace(image, tilt_deg=(tilt[0], tilt[1]), _xyz=None)
