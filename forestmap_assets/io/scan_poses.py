"""Where a scanner stood, as the campaign and its files say (DESIGN section 2): a scan entry's
``pose`` (files in a project or map frame), and the pose each scan of a multi-scan E57 stores.

A pose is the 4x4 scanner-to-file transform ``[R t; 0 1]`` with ``R = R_z(heading) R_y(pitch)
R_x(roll)`` (:func:`~forestmap_assets.core.geometry.rotation_zyx`): its roll and pitch level the
scan (the ``tilt_deg`` of the entry) and ``(x, y, z, heading)`` is an a priori pose of the scan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from forestmap_assets.core.geometry import roll_pitch_heading, rotation_zyx

POSE_KEYS = ("x", "y", "z", "roll_deg", "pitch_deg", "heading_deg")


class PoseError(ValueError):
    """A malformed ``pose``: ``key`` names the offending key ('' for the whole value)."""

    def __init__(self, key: str, message: str):
        super().__init__(message)
        self.key = key


@dataclass(frozen=True)
class ScanPose:
    """What a pose gives a scan entry: tilt (roll, pitch), a priori (x, y, z, heading) and the
    4x4 matrix itself."""

    matrix: np.ndarray
    tilt_deg: tuple[float, float]
    a_priori: tuple[float, float, float, float]


def pose_from_matrix(matrix) -> ScanPose:
    m = np.asarray(matrix, dtype=np.float64)
    roll, pitch, heading = roll_pitch_heading(m[:3, :3])
    x, y, z = (float(v) for v in m[:3, 3])
    return ScanPose(m, (roll, pitch), (x, y, z, heading))


def parse_pose(value: Any) -> ScanPose:
    """``{x, y, z, roll_deg, pitch_deg, heading_deg}`` (roll, pitch, heading default 0) or a 4x4
    matrix (rows); raises :class:`PoseError` naming what is wrong."""
    if isinstance(value, dict):
        extra = sorted(set(value) - set(POSE_KEYS))
        if extra:
            raise PoseError(extra[0], f"unknown key (allowed: {', '.join(POSE_KEYS)})")
        for key in ("x", "y", "z"):
            if key not in value:
                raise PoseError(key, "missing (the scanner's position in the file's frame)")
        vals = {}
        for key in POSE_KEYS:
            v = value.get(key, 0.0)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise PoseError(key, f"expected a number, got {v!r}")
            vals[key] = float(v)
        m = np.eye(4)
        m[:3, :3] = rotation_zyx(vals["roll_deg"], vals["pitch_deg"], vals["heading_deg"])
        m[:3, 3] = vals["x"], vals["y"], vals["z"]
        return pose_from_matrix(m)
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape != (4, 4) or not np.isfinite(m).all():
        raise PoseError("", "expected {x, y, z, roll_deg, pitch_deg, heading_deg} or a 4x4 matrix")
    if not np.allclose(m[3], [0, 0, 0, 1]):
        raise PoseError("", "the last row of a 4x4 pose must be 0 0 0 1")
    r = m[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise PoseError("", "the 3x3 part of the matrix is not a rotation (scaled or mirrored)")
    return pose_from_matrix(m)


def e57_poses(path: Path) -> list[tuple[str, ScanPose | None]] | None:
    """Name and stored pose of each scan of an E57 file; None when the header cannot be read
    (the reader reports the damage when the scan is read, and the other scans go on)."""
    from forestmap_assets.io.readers_e57 import e57_scans

    try:
        scans = e57_scans(path)
    except Exception:  # a damaged file: reported by the reader, one scan at a time
        return None
    return [(s.name, None if s.pose is None else pose_from_matrix(s.pose)) for s in scans]
