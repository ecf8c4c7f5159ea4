"""4-DoF pose helpers shared by the stages (spec 6.1 conventions).

A pose ``(x, y, z, heading_deg)`` maps a point of a levelled sub-map into the frame it is
expressed in: ``p' = R_z(heading) p + (x, y, z)``.
"""

from __future__ import annotations

import numpy as np


def wrap_deg(angle):
    """Angles wrapped to (-180, 180]."""
    a = np.mod(np.asarray(angle, dtype=float) + 180.0, 360.0) - 180.0
    a = np.where(a == -180.0, 180.0, a)
    return a if a.ndim else float(a)


def rot_z(heading_deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(heading_deg)), np.sin(np.radians(heading_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def transform_points(points: np.ndarray, pose) -> np.ndarray:
    """Points (n, 3) of a sub-map expressed in the frame where the sub-map has ``pose``."""
    x, y, z, h = (float(v) for v in pose)
    return np.asarray(points, dtype=float) @ rot_z(h).T + np.array([x, y, z])


def compose(outer, inner) -> tuple[float, float, float, float]:
    """Pose of ``inner`` (given in the frame of a sub-map with pose ``outer``) in outer's frame."""
    p = transform_points(np.array([inner[:3]], dtype=float), outer)[0]
    return (float(p[0]), float(p[1]), float(p[2]), float(wrap_deg(outer[3] + inner[3])))


def relative_pose(scan_pose, reference_pose) -> tuple[float, float, float, float]:
    """Location of ``scan`` in the levelled frame of ``reference`` from two global poses."""
    d = np.asarray(scan_pose[:3], dtype=float) - np.asarray(reference_pose[:3], dtype=float)
    local = rot_z(-reference_pose[3]) @ d
    return (float(local[0]), float(local[1]), float(local[2]), float(wrap_deg(scan_pose[3] - reference_pose[3])))
