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


def rotation_zyx(roll_deg: float, pitch_deg: float, heading_deg: float) -> np.ndarray:
    """Scanner-to-frame rotation ``R_z(heading) R_y(pitch) R_x(roll)``: the levelling rotation
    of :func:`~forestmap_assets.core.features.range_image.levelling_rotation`, then the heading."""
    r, p, h = np.radians([roll_deg, pitch_deg, heading_deg])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(h), -np.sin(h), 0], [np.sin(h), np.cos(h), 0], [0, 0, 1]])
    return rz @ ry @ rx


def roll_pitch_heading(rotation: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_zyx`: (roll, pitch, heading) in degrees of a rotation matrix."""
    m = np.asarray(rotation, dtype=np.float64)
    pitch = np.arcsin(np.clip(-m[2, 0], -1.0, 1.0))
    roll = np.arctan2(m[2, 1], m[2, 2])
    heading = np.arctan2(m[1, 0], m[0, 0])
    return float(np.degrees(roll)), float(np.degrees(pitch)), float(wrap_deg(np.degrees(heading)))


def quaternion_matrix(w: float, x: float, y: float, z: float) -> np.ndarray:
    """Rotation matrix of a (not necessarily unit) quaternion ``w + xi + yj + zk`` (E57 pose)."""
    q = np.array([w, x, y, z], dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n == 0:
        raise ValueError("zero or non-finite quaternion")
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix (inverse of
    :func:`quaternion_matrix`)."""
    m = np.asarray(rotation, dtype=np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 1e-300))
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q) / np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    return tuple(float(v) for v in q)  # type: ignore[return-value]
