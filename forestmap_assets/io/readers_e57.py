"""Reader of E57 scans (spec 1.2, DESIGN section 2): structured scans with row/column indices are
read as organised range images; unstructured ones are projected spherically."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io.projection import nearest_per_pixel
from forestmap_assets.io.readers_common import BadScan, _project, check_signature, to_rgb8


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
        raise BadScan(f"short read of point data ({got} of {n} points)")
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
        raise BadScan("structured scan has a single populated row/column")
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


@dataclass(frozen=True)
class E57Scan:
    """One ``data3D`` entry of an E57 file: its index, name, point count, and its stored pose as
    the 4x4 scanner-to-file transform (``None`` when the file stores none)."""

    index: int
    name: str
    points: int
    pose: np.ndarray | None
    structured: bool


def _pose(node) -> np.ndarray | None:
    from forestmap_assets.core.geometry import quaternion_matrix

    if not node.isDefined("pose"):
        return None
    pose = node["pose"]
    m = np.eye(4)
    if pose.isDefined("rotation"):
        rot = pose["rotation"]
        m[:3, :3] = quaternion_matrix(*(float(rot[k].value()) for k in "wxyz"))
    if pose.isDefined("translation"):
        tr = pose["translation"]
        m[:3, 3] = [float(tr[k].value()) for k in "xyz"]
    return m


def e57_scans(path: str | Path) -> list[E57Scan]:
    """The scans of an E57 file with their names and stored poses (header only, no points)."""
    import pye57

    path = Path(path)
    check_signature(path, (b"ASTM-E57",), "an E57 file")
    out = []
    with pye57.E57(str(path)) as e57:
        for i in range(e57.scan_count):
            header = e57.get_header(i)
            node = header.node
            name = str(node["name"].value()) if node.isDefined("name") else f"scan {i}"
            fields = set(header.point_fields)
            out.append(E57Scan(i, name, int(header.point_count), _pose(node),
                               {"rowIndex", "columnIndex"} <= fields))
    return out


def read_e57(path: Path, angular_step_deg, scan_index: int | None = None) -> RangeImage:
    import pye57

    check_signature(path, (b"ASTM-E57",), "an E57 file")
    with pye57.E57(str(path)) as e57:
        count = e57.scan_count
        if count == 0:
            raise BadScan("no scans in data3D")
        if scan_index is None:
            if count > 1:
                raise BadScan(f"holds {count} scans; give e57_scan: 0..{count - 1} in campaign.yaml "
                              "(forestmap init writes one entry per scan)")
            scan_index = 0
        if not 0 <= scan_index < count:
            raise BadScan(f"e57_scan {scan_index} out of range (file holds {count} scans)")
        header = e57.get_header(scan_index)
        fields = set(header.point_fields)
        n_points = header.point_count
        if n_points == 0:
            raise BadScan("scan has no points")
        cart = {"cartesianX", "cartesianY", "cartesianZ"}
        sph = {"sphericalRange", "sphericalAzimuth", "sphericalElevation"}
        use_sph = sph <= fields
        if not use_sph and not cart <= fields:
            raise BadScan("no cartesianX/Y/Z or sphericalRange/Azimuth/Elevation fields")
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
        rgb = to_rgb8(np.column_stack([data[c] for c in colours]), full_scale=full_scale)
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
        raise BadScan("no valid points")
    return _project(
        xyz[has_range],
        None if rgb is None else rgb[has_range],
        None if intensity is None else intensity[has_range],
        angular_step_deg,
    )
