"""Scan-file reading: every supported format to an organised :class:`RangeImage` (spec 1.2).

DESIGN section 2: one file per scan position, points in that scanner's own frame (origin at the
sensor), format chosen by extension. Organised sources (``.npz`` range images, structured E57
scans with row/column indices) are read as they are; unorganised clouds (LAS/LAZ, PLY, PCD,
text, unstructured E57) are turned into a range image by spherical projection
(:func:`forestmap_assets.io.projection.project_to_range_image`). Any failure is a
:class:`ScanReadError` whose message is one line ``<file>: <reason>``."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io.readers_clouds import read_las, read_open3d
from forestmap_assets.io.readers_common import BadScan, ScanReadError, one_line
from forestmap_assets.io.readers_e57 import read_e57
from forestmap_assets.io.readers_npz import read_npz
from forestmap_assets.io.readers_text import read_text

__all__ = ["SCAN_EXTENSIONS", "ScanReadError", "read_scan"]


_READERS: dict[str, Callable[..., RangeImage]] = {
    ".npz": read_npz,
    ".e57": read_e57,
    ".las": read_las,
    ".laz": read_las,
    ".ply": read_open3d,
    ".pcd": read_open3d,
    ".xyz": read_text,
    ".txt": read_text,
    ".csv": read_text,
}


SCAN_EXTENSIONS = tuple(_READERS)


def read_scan(
    path: str | Path,
    *,
    angular_step_deg: float | tuple[float, float] | None = None,
    tilt_deg: tuple[float, float] = (0.0, 0.0),
    scan_index: int | None = None,
    to_scanner=None,
) -> RangeImage:
    """Read one scan file (DESIGN section 2) as an organised range image (spec 1.2).

    Dispatches on the extension (``.npz .e57 .las .laz .ply .pcd .xyz .txt .csv``). Points are
    in the scanner's own frame; unorganised clouds are projected at ``angular_step_deg``
    (scalar or (az, el); None = estimated from the data). ``tilt_deg`` = measured (roll,
    pitch) attached to the image for levelling. ``scan_index`` picks a scan of a multi-scan
    E57 (default: the file must hold exactly one). ``to_scanner``: the 4x4 transform that moves
    a point-cloud file's points from its project frame to the scanner's own frame before the
    projection (a scan entry's ``pose``, inverted). rgb is kept where present; NaN marks
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
    kwargs: dict = {"scan_index": scan_index} if ext == ".e57" else {}
    if to_scanner is not None:
        if ext in (".npz", ".e57"):
            raise ScanReadError(f"{name}: a pose is only for point-cloud files; {ext} scans are "
                                "in the scanner's frame")
        kwargs["to_scanner"] = np.asarray(to_scanner, dtype=np.float64)
    try:
        image = _READERS[ext](p, angular_step_deg, **kwargs)
    except BadScan as exc:
        raise ScanReadError(f"{name}: {one_line(exc)}") from exc
    except MemoryError:
        raise
    except Exception as exc:  # any backend failure becomes one clear line
        lines = [ln for ln in str(exc).splitlines() if ln.strip()]
        reason = one_line(lines[0]) if lines else "unreadable"
        raise ScanReadError(f"{name}: {type(exc).__name__}: {reason}"[: len(name) + 300]) from exc
    return replace(image, tilt_deg=(tilt[0], tilt[1]), _xyz=None)
