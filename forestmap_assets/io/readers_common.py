"""Shared parts of the scan-file readers (spec 1.2, DESIGN section 2): the one-line
:class:`ScanReadError`, colour scaling to uint8, file signature checks and the spherical
projection of unorganised clouds to a :class:`RangeImage`
(:func:`forestmap_assets.io.projection.project_to_range_image`)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io.projection import project_to_range_image


class ScanReadError(ValueError):
    """A scan file that cannot be read; the message is one line naming the file and reason."""


class BadScan(Exception):
    """Internal: reason a file is rejected (the file name is added by :func:`read_scan`)."""


def one_line(text: object) -> str:
    return re.sub(r"\s+", " ", str(text)).strip()


def to_rgb8(values: np.ndarray, *, full_scale: float | None = None) -> np.ndarray:
    """Colours to uint8: 0-1 floats scaled by 255, 16-bit values by 1/257, 0-255 kept.

    ``full_scale`` (e.g. a LAS/E57 colour limit) overrides the guess from the values. Guess
    (inferred): non-integer values all <= 1 are 0-1; any value > 255 means 16-bit.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.size and (not np.all(np.isfinite(v)) or v.min() < 0):
        raise BadScan("colour values must be finite and non-negative")
    if full_scale is None:
        vmax = float(v.max()) if v.size else 0.0
        if vmax <= 1.0 and np.any(v != np.rint(v)):
            full_scale = 1.0
        elif vmax > 255.0:
            full_scale = 65535.0
        else:
            full_scale = 255.0
    return np.clip(np.rint(v * (255.0 / full_scale)), 0, 255).astype(np.uint8)


def count_damage(header_count: int, held: int | str) -> str:
    """The one-line damage of a file whose header's point count is not what it holds:
    ``truncated: header says 5000 points, file holds 3012`` (``damaged: ...`` when it holds
    more)."""
    fewer = not isinstance(held, int) or held < header_count
    kind = "truncated" if fewer else "damaged"
    return f"{kind}: header says {header_count} points, file holds {held}"


def count_words(path: Path, start: int) -> int:
    """Whitespace-separated words of a text file from byte ``start`` on, read in blocks."""
    words, inside = 0, False
    with open(path, "rb") as f:
        f.seek(start)
        while block := f.read(1 << 22):
            words += len(block.split())
            if inside and not block[:1].isspace():
                words -= 1  # one word split across two blocks
            inside = not block[-1:].isspace()
    return words


def check_signature(path: Path, accepted: tuple[bytes, ...], what: str) -> None:
    with open(path, "rb") as f:
        head = f.read(max(len(s) for s in accepted))
    if not any(head.startswith(s) for s in accepted):
        raise BadScan(f"not {what} (bad signature)")


def _project(
    xyz: np.ndarray,
    rgb: np.ndarray | None,
    intensity: np.ndarray | None,
    angular_step_deg,
    to_scanner=None,
) -> RangeImage:
    """Spherical projection of a cloud about its scanner; ``to_scanner`` (4x4) first moves points
    of a project-frame file into the scanner's frame, in float64 (map coordinates keep their mm)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if to_scanner is not None:
        m = np.asarray(to_scanner, dtype=np.float64)
        xyz = xyz @ m[:3, :3].T + m[:3, 3]
    if xyz.shape[0] == 0:
        raise BadScan("no points")
    good = np.isfinite(xyz).all(1)
    if not good.any():
        raise BadScan("no finite points")
    try:
        return project_to_range_image(xyz, rgb, intensity, angular_step_deg=angular_step_deg)
    except ValueError as exc:
        raise BadScan(f"spherical projection failed: {one_line(exc)}") from exc
