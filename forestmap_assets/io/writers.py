"""Scan-file writers: a :class:`RangeImage` to any format :func:`read_scan` reads (DESIGN 2).

Points are written in the scanner's own (not levelled) frame, spec 1.2:
``x = r cos(el) cos(az), y = r cos(el) sin(az), z = r sin(el)`` for the pixels with a return.
``.npz`` and ``.e57`` keep the organised image exactly (E57: a structured scan with row/column
indices and spherical coordinates, pixels without a return stored as direction-only points,
``sphericalInvalidState = 1``); the other formats hold the unorganised cloud. Every file is
written atomically (temporary file in the same folder, then ``os.replace``).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage, spherical_to_xyz

__all__ = ["atomic_write", "scan_points", "write_e57_scans", "write_scan"]


@contextlib.contextmanager
def atomic_write(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` (same suffix); rename onto ``path`` on success.

    On an exception the temporary file is deleted and ``path`` is left untouched. Parent
    folders are created. The new file gets the old file's mode, else 0o644 (inferred).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        dir=path.parent, prefix=f".{path.name}.", suffix=f".tmp{path.suffix}"
    )
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        mode = path.stat().st_mode & 0o777 if path.exists() else 0o644
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def scan_points(image: RangeImage) -> tuple[np.ndarray, np.ndarray]:
    """Scanner-frame points (n, 3) of the pixels with a return, and their (row, col) (n, 2)."""
    v, u = np.nonzero(image.valid)
    if image.points is not None:  # a projected cloud's own points
        return image.points[v, u].astype(np.float64), np.column_stack([v, u])
    xyz = spherical_to_xyz(image.range_m, image.azimuth_deg, image.elevation_deg)[v, u]
    return xyz, np.column_stack([v, u])


# ---- formats ----------------------------------------------------------------------------------


def _write_npz(tmp: Path, image: RangeImage) -> None:
    arrays = {
        "range": image.range_m.astype(np.float32),
        "azimuth_deg": image.azimuth_deg.astype(np.float64),
        "elevation_deg": image.elevation_deg.astype(np.float64),
    }
    if image.intensity is not None:
        arrays["intensity"] = image.intensity.astype(np.float32)
    if image.rgb is not None:
        arrays["rgb"] = image.rgb.astype(np.uint8)
    with open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)


def _write_e57(tmp: Path, image: RangeImage) -> None:
    _write_e57_scans(tmp, [("forestmap scan", image, None)])


def _write_e57_scans(tmp: Path, scans) -> None:
    import pye57

    e57 = pye57.E57(str(tmp), mode="w")
    try:
        for name, image, pose in scans:
            _append_e57_scan(e57, image, name=name, pose=pose)
    finally:
        e57.close()


def _append_e57_scan(e57, image: RangeImage, *, name: str, pose) -> None:
    """Structured E57 scan: every pixel, row/column indices, spherical coordinates (radians).

    Pixels without a return carry their direction with ``sphericalInvalidState = 1`` and range
    0, so the reader recovers every row's and column's angle, hence the exact image. ``pose``: the
    4x4 scanner-to-file transform stored as the scan's E57 pose (None: identity).
    """
    from pye57 import libe57

    from forestmap_assets.core.geometry import matrix_quaternion

    rows, cols = image.shape
    v, u = np.divmod(np.arange(rows * cols), cols)
    rng = image.range_m.reshape(-1).astype(np.float64)
    valid = np.isfinite(rng)
    data = {
        "sphericalRange": np.where(valid, rng, 0.0),
        "sphericalAzimuth": np.radians(image.azimuth_deg)[u],
        "sphericalElevation": np.radians(image.elevation_deg)[v],
        "rowIndex": v.astype(np.float64),
        "columnIndex": u.astype(np.float64),
        "sphericalInvalidState": np.where(valid, 0.0, 1.0),
    }
    if image.intensity is not None:
        inten = image.intensity.reshape(-1).astype(np.float64)
        data["intensity"] = np.where(np.isfinite(inten), inten, 0.0)
    if image.rgb is not None:
        for i, key in enumerate(("colorRed", "colorGreen", "colorBlue")):
            data[key] = image.rgb[..., i].reshape(-1).astype(np.float64)
    n = rows * cols
    imf = e57.image_file
    scan = libe57.StructureNode(imf)
    scan.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
    scan.set("name", libe57.StringNode(imf, name))
    scan.set("description", libe57.StringNode(imf, "forestmap organised range image"))
    ib = libe57.StructureNode(imf)
    for key, val in [
        ("rowMinimum", 0),
        ("rowMaximum", rows - 1),
        ("columnMinimum", 0),
        ("columnMaximum", cols - 1),
        ("returnMinimum", 0),
        ("returnMaximum", 0),
    ]:
        ib.set(key, libe57.IntegerNode(imf, int(val)))
    scan.set("indexBounds", ib)
    rmax = float(np.nanmax(rng)) if valid.any() else 0.0
    az_r = data["sphericalAzimuth"]
    sb = libe57.StructureNode(imf)
    for key, val in [
        ("rangeMinimum", 0.0),
        ("rangeMaximum", rmax),
        ("elevationMinimum", float(data["sphericalElevation"].min())),
        ("elevationMaximum", float(data["sphericalElevation"].max())),
        ("azimuthStart", float(az_r.min())),
        ("azimuthEnd", float(az_r.max())),
    ]:
        sb.set(key, libe57.FloatNode(imf, val))
    scan.set("sphericalBounds", sb)
    m = np.eye(4) if pose is None else np.asarray(pose, dtype=np.float64)
    pose_node = libe57.StructureNode(imf)
    rot = libe57.StructureNode(imf)
    for key, val in zip("wxyz", matrix_quaternion(m[:3, :3]), strict=True):
        rot.set(key, libe57.FloatNode(imf, float(val)))
    tr = libe57.StructureNode(imf)
    for key, val in zip("xyz", m[:3, 3], strict=True):
        tr.set(key, libe57.FloatNode(imf, float(val)))
    pose_node.set("rotation", rot)
    pose_node.set("translation", tr)
    scan.set("pose", pose_node)
    proto = libe57.StructureNode(imf)
    dbl = libe57.E57_DOUBLE
    proto.set("sphericalRange", libe57.FloatNode(imf, 0.0, dbl, 0.0, max(rmax, 1.0)))
    proto.set(
        "sphericalAzimuth",
        libe57.FloatNode(imf, 0.0, dbl, float(az_r.min()), float(az_r.max())),
    )
    proto.set("sphericalElevation", libe57.FloatNode(imf, 0.0, dbl, -np.pi / 2, np.pi / 2))
    proto.set("rowIndex", libe57.IntegerNode(imf, 0, 0, max(rows - 1, 1)))
    proto.set("columnIndex", libe57.IntegerNode(imf, 0, 0, max(cols - 1, 1)))
    proto.set("sphericalInvalidState", libe57.IntegerNode(imf, 0, 0, 2))
    if "intensity" in data:
        lo, hi = float(data["intensity"].min()), float(data["intensity"].max())
        proto.set("intensity", libe57.FloatNode(imf, lo, libe57.E57_SINGLE, lo, max(hi, lo)))
        il = libe57.StructureNode(imf)
        il.set("intensityMinimum", libe57.FloatNode(imf, lo))
        il.set("intensityMaximum", libe57.FloatNode(imf, hi))
        scan.set("intensityLimits", il)
    if image.rgb is not None:
        cl = libe57.StructureNode(imf)
        for key in ("colorRed", "colorGreen", "colorBlue"):
            proto.set(key, libe57.IntegerNode(imf, 0, 0, 255))
            cl.set(f"{key}Minimum", libe57.IntegerNode(imf, 0))
            cl.set(f"{key}Maximum", libe57.IntegerNode(imf, 255))
        scan.set("colorLimits", cl)
    points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
    scan.set("points", points)
    e57.data3d.append(scan)
    bufs = libe57.VectorSourceDestBuffer()
    for key, arr in data.items():
        bufs.append(libe57.SourceDestBuffer(imf, key, arr, n, True, True))
    writer = points.writer(bufs)
    writer.write(n)
    writer.close()


def _in_frame(xyz: np.ndarray, to_file) -> np.ndarray:
    """Scanner-frame points moved into the file's frame by the 4x4 ``to_file`` (float64)."""
    if to_file is None:
        return xyz
    m = np.asarray(to_file, dtype=np.float64)
    return xyz @ m[:3, :3].T + m[:3, 3]


def _write_las(tmp: Path, image: RangeImage, to_file=None) -> None:
    """LAS 1.2 point format 2 (rgb, 16-bit = 8-bit x 257) or 0; 1 um coordinate scale about an
    offset at the points' lower corner (map coordinates keep their micrometres).

    Intensity (when present) is rounded and clipped to LAS's uint16 (inferred).
    """
    import laspy

    xyz, vu = scan_points(image)
    xyz = _in_frame(xyz, to_file)
    v, u = vu[:, 0], vu[:, 1]
    fmt = 2 if image.rgb is not None else 0
    header = laspy.LasHeader(point_format=fmt, version="1.2")
    offsets = np.floor(xyz.min(axis=0)) if to_file is not None and xyz.size else np.zeros(3)
    extent = float(np.abs(xyz - offsets).max()) if xyz.size else 1.0
    scale = max(1e-6, 10.0 ** np.ceil(np.log10(max(extent, 1e-9) / 2.0e9)))
    header.scales = np.array([scale] * 3)
    header.offsets = offsets
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if image.rgb is not None:
        rgb16 = image.rgb[v, u].astype(np.uint16) * np.uint16(257)
        las.red, las.green, las.blue = rgb16[:, 0], rgb16[:, 1], rgb16[:, 2]
    if image.intensity is not None:
        inten = np.nan_to_num(image.intensity[v, u].astype(np.float64))
        las.intensity = np.clip(np.rint(inten), 0, 65535).astype(np.uint16)
    las.write(str(tmp), do_compress=tmp.suffix.lower() == ".laz")


def _write_open3d(tmp: Path, image: RangeImage, to_file=None) -> None:
    import open3d as o3d

    xyz, vu = scan_points(image)
    xyz = _in_frame(xyz, to_file)
    v, u = vu[:, 0], vu[:, 1]
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(np.ascontiguousarray(xyz))
    if image.rgb is not None:
        pc.point.colors = o3d.core.Tensor(np.ascontiguousarray(image.rgb[v, u]))
    if image.intensity is not None:
        inten = image.intensity[v, u].astype(np.float32).reshape(-1, 1)
        pc.point.intensity = o3d.core.Tensor(np.ascontiguousarray(inten))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        ok = o3d.t.io.write_point_cloud(str(tmp), pc)
    if not ok:
        raise OSError(f"open3d could not write {tmp.suffix} file")


def _write_text(tmp: Path, image: RangeImage, to_file=None) -> None:
    """``.csv``: header ``x,y,z[,r,g,b][,intensity]``; ``.xyz``/``.txt``: ``x y z [r g b]``.

    Coordinates use the shortest exact decimal form (round-trips float64 bit for bit).
    """
    import pyarrow as pa
    import pyarrow.csv as pcsv

    xyz, vu = scan_points(image)
    xyz = _in_frame(xyz, to_file)
    v, u = vu[:, 0], vu[:, 1]
    is_csv = tmp.suffix.lower() == ".csv"
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    if image.rgb is not None:
        for i, key in enumerate("rgb"):
            cols[key] = image.rgb[v, u, i]
    if is_csv and image.intensity is not None:
        cols["intensity"] = image.intensity[v, u].astype(np.float64)
    opts = pcsv.WriteOptions(
        include_header=is_csv,
        delimiter="," if is_csv else " ",
        quoting_style="none",
        quoting_header="none",
    )
    pcsv.write_csv(pa.table(cols), str(tmp), opts)


_WRITERS: dict[str, Callable[..., None]] = {
    ".npz": _write_npz,
    ".e57": _write_e57,
    ".las": _write_las,
    ".laz": _write_las,
    ".ply": _write_open3d,
    ".pcd": _write_open3d,
    ".xyz": _write_text,
    ".txt": _write_text,
    ".csv": _write_text,
}


def write_scan(path: str | Path, image: RangeImage, *, to_file=None) -> Path:
    """Write ``image`` to ``path`` in the format named by its extension (DESIGN section 2).

    Points go out in the scanner's own frame (spec 1.2; the tilt is not applied and not stored:
    it belongs in ``campaign.yaml``), or, for the point-cloud formats, moved into a project frame
    by the 4x4 scanner-to-file transform ``to_file`` (the scan entry's ``pose``). Atomic: a
    reader never sees a half-written file.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in _WRITERS:
        raise ValueError(f"{path}: unsupported extension '{ext}' (supported: {' '.join(_WRITERS)})")
    if to_file is not None and ext in (".npz", ".e57"):
        raise ValueError(f"{path}: organised {ext} scans stay in the scanner frame (E57: a pose)")
    with atomic_write(path) as tmp:
        if to_file is None:
            _WRITERS[ext](tmp, image)
        else:
            _WRITERS[ext](tmp, image, to_file)
    return path


def write_e57_scans(path: str | Path, scans) -> Path:
    """One E57 file holding several structured scans, as scanner software exports a day's work:
    ``scans`` are ``(name, RangeImage, pose)`` with ``pose`` the 4x4 scanner-to-file transform
    (None: identity) stored as each scan's E57 pose; the points stay in each scan's own frame."""
    path = Path(path)
    with atomic_write(path) as tmp:
        _write_e57_scans(tmp, scans)
    return path
