"""Readers of unorganised point-cloud files (spec 1.2, DESIGN section 2): LAS/LAZ (laspy) and
PLY/PCD (open3d), turned into a range image by spherical projection."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io.readers_common import BadScan, _project, check_signature, to_rgb8


def read_las(path: Path, angular_step_deg) -> RangeImage:
    import laspy

    check_signature(path, (b"LASF",), "a LAS file")
    try:
        las = laspy.read(str(path))
    except Exception as exc:  # laspy's errors on damaged files are cryptic: say what happened
        first = (str(exc).splitlines() or [""])[0]
        raise BadScan(f"corrupt or truncated LAS/LAZ data ({type(exc).__name__}: {first})") from exc
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    dims = set(las.point_format.dimension_names)
    rgb = None
    if {"red", "green", "blue"} <= dims:
        raw = np.column_stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)])
        # 16-bit colour per the LAS spec; files holding 8-bit values (max <= 255) are kept as is
        rgb = to_rgb8(raw, full_scale=65535.0 if raw.size and raw.max() > 255 else 255.0)
    intensity = np.asarray(las.intensity, dtype=np.float32) if "intensity" in dims else None
    return _project(xyz, rgb, intensity, angular_step_deg)


def _check_pcd_header(path: Path) -> None:
    with open(path, "rb") as f:
        head = f.read(4096)
    text = head.split(b"\nDATA", 1)[0].decode("ascii", errors="replace")
    keys = {
        ln.split()[0].upper() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")
    }
    if b"\nDATA" not in head or "FIELDS" not in keys:
        raise BadScan("not a PCD file (no FIELDS/DATA header)")


def read_open3d(path: Path, angular_step_deg) -> RangeImage:
    import open3d as o3d

    if path.suffix.lower() == ".ply":
        check_signature(path, (b"ply\n", b"ply\r\n", b"ply\r"), "a PLY file")
    else:
        _check_pcd_header(path)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        pc = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in pc.point or pc.point.positions.shape[0] == 0:
        raise BadScan("no points (unreadable or empty point cloud)")
    xyz = pc.point.positions.numpy().astype(np.float64)
    rgb = intensity = None
    if "colors" in pc.point:
        c = pc.point.colors.numpy()
        rgb = c.astype(np.uint8) if c.dtype == np.uint8 else to_rgb8(c)
    if "intensity" in pc.point:
        intensity = pc.point.intensity.numpy().reshape(-1).astype(np.float32)
    return _project(xyz, rgb, intensity, angular_step_deg)
