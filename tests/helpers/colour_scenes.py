"""Small synthetic coloured clouds for the HICP and Fourier tests (men spec 12, V7-V15)."""

from __future__ import annotations

import numpy as np


def rotation_xyz(ax_deg: float, ay_deg: float, az_deg: float) -> np.ndarray:
    """R = R_z R_y R_x (the D6 test rotates 5 deg about each axis; order not stated)."""
    a, b, c = np.radians([ax_deg, ay_deg, az_deg])
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation (QR of a Gaussian matrix with sign fix)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def angle_deg(r_a: np.ndarray, r_b: np.ndarray) -> float:
    """Angle of the rotation between two rotation matrices."""
    c = (np.trace(r_a.T @ r_b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _rect(rng, origin, u, v, n):
    a, b = rng.random((2, n))
    return np.asarray(origin) + a[:, None] * np.asarray(u) + b[:, None] * np.asarray(v)


def building(n: int = 6000, seed: int = 0) -> np.ndarray:
    """Points on an asymmetric "building": ground, an L-shaped block with a slanted roof, a
    round tower and two boxes at odd angles (about 24 x 18 x 9 m; no 90-degree symmetry)."""
    rng = np.random.default_rng(seed)
    parts = []
    w = np.array([14.0, 10.0, 10.0, 8.0, 6.0, 6.0, 4.0, 3.0, 3.0, 2.0, 4.0, 2.0])
    counts = rng.multinomial(n, w / w.sum())
    parts.append(_rect(rng, (-4, -4, 0), (24, 0, 0), (0, 18, 0), counts[0]))            # ground
    parts.append(_rect(rng, (0, 0, 0), (12, 0, 0), (0, 0, 7), counts[1]))               # wall S
    parts.append(_rect(rng, (0, 0, 0), (0, 9, 0), (0, 0, 7), counts[2]))                # wall W
    parts.append(_rect(rng, (0, 9, 0), (6, 0, 0), (0, 0, 7), counts[3]))                # wall N
    parts.append(_rect(rng, (6, 4, 0), (0, 5, 0), (0, 0, 5), counts[4]))                # inner wall
    parts.append(_rect(rng, (6, 4, 0), (6, 0, 0), (0, 0, 5), counts[5]))                # inner wall 2
    parts.append(_rect(rng, (12, 0, 0), (0, 4, 0), (0, 0, 5), counts[6]))               # east wall
    parts.append(_rect(rng, (0, 0, 7), (6, 0, 0), (0, 9, 1.5), counts[7]))              # roof
    t = rng.uniform(0, 2 * np.pi, counts[8])
    z = rng.uniform(0, 9, counts[8])
    parts.append(np.column_stack([16 + 1.5 * np.cos(t), 10 + 1.5 * np.sin(t), z]))   # tower
    c, s = np.cos(0.5), np.sin(0.5)
    parts.append(_rect(rng, (15, 2, 0), (2 * c, 2 * s, 0), (0, 0, 1.2), counts[9]))     # box face
    c, s = np.cos(1.1), np.sin(1.1)
    parts.append(_rect(rng, (3, 12, 0), (3 * c, 3 * s, 0), (0, 0, 2.0), counts[10]))    # wall 2
    parts.append(_rect(rng, (3, 12, 2.0), (3 * c, 3 * s, 0), (-0.8 * s, 0.8 * c, 0), counts[11]))
    return np.vstack(parts)


def gradient_hue(points: np.ndarray, axis: int = 0) -> np.ndarray:
    """Continuous hue along one axis, 0..1 over the cloud (spec 5.10 second Eq. 5.10)."""
    x = points[:, axis]
    return (x - x.min()) / (x.max() - x.min())


def segment_hue(points: np.ndarray, axis: int = 2, segments: int = 7) -> np.ndarray:
    """Seven hue segments along one axis (Table 5.1: grey 0, yellow 1/6 ... red 1)."""
    x = points[:, axis]
    k = np.minimum(((x - x.min()) / (x.max() - x.min()) * segments).astype(int), segments - 1)
    return np.array([0.0, 1 / 6, 2 / 6, 3 / 6, 4 / 6, 5 / 6, 1.0])[k]


def blob(n: int = 4000, seed: int = 0, noise: float = 0.0) -> np.ndarray:
    """A bunny-sized irregular closed surface (radius about 0.1 m with bumps), uniformly sampled;
    two calls with different seeds sample the same surface differently."""
    rng = np.random.default_rng(seed)
    v = rng.standard_normal((n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    r = 0.1 * (1 + 0.25 * v[:, 0] * v[:, 1] + 0.2 * np.sin(3 * v[:, 2] + 1.0) + 0.15 * v[:, 0] ** 3)
    p = v * r[:, None] * np.array([1.0, 0.8, 1.2])
    return p + rng.normal(0, noise, p.shape)


def _quad(p0, p1, p2, p3):
    v = np.array([p0, p1, p2, p3], dtype=np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def room_mesh(symmetric: bool = False):
    """A closed room as a labelled :class:`SceneMesh` (part ids: 0 floor, 1 ceiling, 2.. walls,
    then furniture). ``symmetric``: a plain 10 x 4 x 2.5 m box. Otherwise an L-shaped room with a
    chamfered corner, two boxes at odd yaws and a slanted board (no 90-degree symmetry)."""
    from forestmap_assets.sim.scene_mesh import (
        KIND_GROUND,
        KIND_STEM,
        KIND_UNDERSTOREY,
        SceneMesh,
        box_mesh,
    )

    height = 2.5 if symmetric else 3.0
    if symmetric:
        outline = [(0, 0), (10, 0), (10, 4), (0, 4)]
    else:
        outline = [(0, 0), (8, 0), (8, 2.5), (6.5, 4), (5, 4), (5, 9), (0, 9)]
    pieces = []  # (vertices, faces, kind, part)
    xs, ys = zip(*outline, strict=True)
    lo, hi = (min(xs), min(ys)), (max(xs), max(ys))
    # floor and ceiling: the bounding rectangle (the L's missing corner lies outside the walls)
    pieces.append((*_quad((lo[0], lo[1], 0), (hi[0], lo[1], 0), (hi[0], hi[1], 0), (lo[0], hi[1], 0)), KIND_GROUND, 0))
    if symmetric:
        pieces.append((*_quad((lo[0], lo[1], height), (hi[0], lo[1], height), (hi[0], hi[1], height),
                              (lo[0], hi[1], height)), KIND_UNDERSTOREY, 1))
    else:  # flat ceiling over y < 4.5, a roof sloping down to 1.8 m over y > 4.5
        pieces.append((*_quad((lo[0], lo[1], height), (hi[0], lo[1], height), (hi[0], 4.5, height),
                              (lo[0], 4.5, height)), KIND_UNDERSTOREY, 1))
        pieces.append((*_quad((lo[0], 4.5, height), (hi[0], 4.5, height), (hi[0], hi[1], 1.8),
                              (lo[0], hi[1], 1.8)), KIND_UNDERSTOREY, 1))
    for i, (a, b) in enumerate(zip(outline, outline[1:] + outline[:1], strict=True)):
        pieces.append((*_quad((*a, 0), (*b, 0), (*b, height), (*a, height)), KIND_STEM, 2 + i))
    part = 2 + len(outline)
    if not symmetric:
        v, f = box_mesh(np.array([[2.0, 2.0, 0.0], [2.5, 6.5, 0.0]]), np.array([[1.6, 0.8, 0.75], [1.0, 1.0, 1.8]]),
                        np.array([0.45, 1.05]))
        pieces.append((v[:8], f[:12], KIND_UNDERSTOREY, part))
        pieces.append((v[8:] - 0, f[12:] - 8, KIND_UNDERSTOREY, part + 1))
        c, s = np.cos(0.3), np.sin(0.3)
        board = [(6.0, 0.6, 0.0), (6.0 + 1.2 * c, 0.6 + 1.2 * s, 0.0), (6.0 + 1.2 * c - 0.5, 0.6 + 1.2 * s + 0.3, 1.4),
                 (5.5, 0.9, 1.4)]
        pieces.append((*_quad(*board), KIND_UNDERSTOREY, part + 2))
    verts, faces, kinds, parts = [], [], [], []
    off = 0
    for v, f, k, p in pieces:
        verts.append(v)
        faces.append(f + off)
        kinds.append(np.full(len(f), k))
        parts.append(np.full(len(f), p))
        off += len(v)
    return SceneMesh(np.vstack(verts), np.vstack(faces), np.concatenate(kinds).astype(np.uint8),
                     np.full(sum(len(f) for f in faces), -1, np.int32), np.concatenate(parts).astype(np.int32))


def mesh_samples(mesh, n: int, eye, seed: int = 0):
    """Area-weighted random points on a mesh with their face normals oriented toward ``eye``."""
    rng = np.random.default_rng(seed)
    tri = mesh.vertices[mesh.triangles]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    f = rng.choice(len(tri), n, p=area / area.sum())
    u, v = rng.random((2, n))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    p = tri[f, 0] + u[:, None] * (tri[f, 1] - tri[f, 0]) + v[:, None] * (tri[f, 2] - tri[f, 0])
    nrm = mesh.normals[f].astype(np.float64)
    nrm[((np.asarray(eye) - p) * nrm).sum(1) < 0] *= -1
    return p, nrm, mesh.part[f]
