"""Labelled triangle meshes of the synthetic scenes (spec 10.1 / 10.6 / 13).

:class:`SceneMesh` is one triangle mesh whose triangles carry labels (kind, tree, part), so that
a ray cast with open3d's ``RaycastingScene`` tells which object it hit; plus its primitives:
open tapered tubes (radius harmonics ``a2 cos 2(psi - phase2) + a3 cos 3(psi - phase3)``),
open tubes through rings of any radius profile (the realistic stems of :mod:`.stem_shapes`),
irregular ellipsoid blobs (foliage, bushes) and boxes. Shapes are (inferred)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

KIND_GROUND, KIND_STEM, KIND_BRANCH, KIND_FOLIAGE, KIND_UNDERSTOREY = 0, 1, 2, 3, 4


KIND_NAMES = ("ground", "stem", "branch", "foliage", "understorey")


NO_RETURN = 255  # kind label of a pixel without a return


# ---- mesh ------------------------------------------------------------------------------------
@dataclass
class SceneMesh:
    """A labelled triangle mesh: per-triangle ``kind`` (KIND_*), ``tree`` (-1: none) and
    ``part`` (one id per object: a stem, a branch, a blob, a bush, the ground)."""

    vertices: np.ndarray  # (V, 3) float64
    triangles: np.ndarray  # (F, 3) int64
    kind: np.ndarray  # (F,) uint8
    tree: np.ndarray  # (F,) int32
    part: np.ndarray  # (F,) int32
    _scene: object = field(default=None, repr=False, compare=False)

    _normals: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    @property
    def normals(self) -> np.ndarray:
        """Unit triangle normals (F, 3) float32 (cached)."""
        if self._normals is None:
            v = self.vertices[self.triangles]
            n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            self._normals = n.astype(np.float32)
        return self._normals

    def raycasting_scene(self):
        """open3d ``RaycastingScene`` holding this mesh (built once, cached)."""
        if self._scene is None:
            import open3d as o3d

            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(self.vertices, dtype=np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(self.triangles, dtype=np.uint32)),
            )
            self._scene = scene
        return self._scene

    def to_open3d(self):
        """Legacy ``open3d.geometry.TriangleMesh`` (for viewing)."""
        import open3d as o3d

        return o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(self.triangles)
        )


def concat_meshes(pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]):
    """Join (vertices, faces, kind, tree, part) pieces into one :class:`SceneMesh`."""
    offsets = np.cumsum([0] + [p[0].shape[0] for p in pieces[:-1]])
    return SceneMesh(
        np.concatenate([p[0] for p in pieces]),
        np.concatenate([p[1] + o for p, o in zip(pieces, offsets, strict=True)]),
        np.concatenate([p[2] for p in pieces]).astype(np.uint8),
        np.concatenate([p[3] for p in pieces]).astype(np.int32),
        np.concatenate([p[4] for p in pieces]).astype(np.int32),
    )


def _perpendicular_frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors e1, e2 perpendicular to unit ``axis`` (N, 3); e1 = x projected (or y)."""
    ref = np.where(np.abs(axis[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = ref - (ref * axis).sum(axis=1, keepdims=True) * axis
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(axis, e1)


def tube_mesh(
    p0: np.ndarray,
    p1: np.ndarray,
    r0: np.ndarray,
    r1: np.ndarray,
    *,
    n_sides: int,
    n_rings: int,
    harmonics: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of N open tapered tubes from ``p0`` to ``p1`` (radii ``r0``, ``r1``).

    Rings are perpendicular to the axis; ``harmonics`` (N, 4) = (a2, phase2, a3, phase3) adds
    ``a2 cos 2(psi - phase2) + a3 cos 3(psi - phase3)`` to the radius (phases in radians).
    Returns ``(N * n_rings * n_sides, 3)`` vertices and ``(N * (n_rings-1) * n_sides * 2, 3)``
    faces.
    """
    p0, p1 = np.atleast_2d(p0).astype(np.float64), np.atleast_2d(p1).astype(np.float64)
    n = p0.shape[0]
    axis = p1 - p0
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    e1, e2 = _perpendicular_frame(axis)
    s = np.linspace(0.0, 1.0, n_rings)
    psi = np.arange(n_sides) * (2 * np.pi / n_sides)
    centre = p0[:, None, :] + s[None, :, None] * (p1 - p0)[:, None, :]  # (N, R, 3)
    radius = np.asarray(r0)[:, None] + s[None, :] * (np.asarray(r1) - np.asarray(r0))[:, None]
    radius = np.broadcast_to(radius[:, :, None], (n, n_rings, n_sides)).copy()
    if harmonics is not None:
        h = np.asarray(harmonics, dtype=np.float64)
        radius += (
            h[:, 0, None] * np.cos(2 * (psi[None, :] - h[:, 1, None]))
            + h[:, 2, None] * np.cos(3 * (psi[None, :] - h[:, 3, None]))
        )[:, None, :]
    ring = np.cos(psi)[None, :, None] * e1[:, None, :] + np.sin(psi)[None, :, None] * e2[:, None, :]
    verts = centre[:, :, None, :] + radius[..., None] * ring[:, None, :, :]
    j, k = np.meshgrid(np.arange(n_rings - 1), np.arange(n_sides), indexing="ij")
    a = j * n_sides + k
    b = j * n_sides + (k + 1) % n_sides
    quad = np.stack([a, b, b + n_sides, a + n_sides], axis=-1).reshape(-1, 4)
    tri = np.concatenate([quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]])
    faces = tri[None, :, :] + (np.arange(n) * n_rings * n_sides)[:, None, None]
    return verts.reshape(-1, 3), faces.reshape(-1, 3)


def ring_tube_mesh(
    centres: np.ndarray, tangents: np.ndarray, radius: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """One open tube through rings of varying radius (realistic stems, :mod:`.stem_shapes`).

    ``centres`` (R, 3) ring centres along a possibly curved axis, ``tangents`` (R, 3) the axis
    direction there, ``radius`` (R, S) the radius at ``psi_k = 2 pi k / S``, measured about the
    tangent from the x axis projected perpendicular to it (as :func:`tube_mesh`). Returns
    ``(R * S, 3)`` vertices and ``(2 (R - 1) S, 3)`` faces (ring-major, like :func:`tube_mesh`).
    """
    centres = np.asarray(centres, dtype=np.float64)
    t = np.asarray(tangents, dtype=np.float64)
    t = t / np.linalg.norm(t, axis=1, keepdims=True)
    e1, e2 = _perpendicular_frame(t)
    n_rings, n_sides = radius.shape
    psi = np.arange(n_sides) * (2 * np.pi / n_sides)
    ring = (np.cos(psi)[None, :, None] * e1[:, None, :]
            + np.sin(psi)[None, :, None] * e2[:, None, :])  # (R, S, 3)
    verts = centres[:, None, :] + radius[..., None] * ring
    j, k = np.meshgrid(np.arange(n_rings - 1), np.arange(n_sides), indexing="ij")
    a = j * n_sides + k
    b = j * n_sides + (k + 1) % n_sides
    quad = np.stack([a, b, b + n_sides, a + n_sides], axis=-1).reshape(-1, 4)
    faces = np.concatenate([quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]])
    return verts.reshape(-1, 3), faces


def _unit_icosphere() -> tuple[np.ndarray, np.ndarray]:
    """Icosahedron subdivided once (42 vertices, 80 faces) on the unit sphere."""
    t = (1 + 5**0.5) / 2
    v = np.array(
        [
            [-1, t, 0],
            [1, t, 0],
            [-1, -t, 0],
            [1, -t, 0],
            [0, -1, t],
            [0, 1, t],
            [0, -1, -t],
            [0, 1, -t],
            [t, 0, -1],
            [t, 0, 1],
            [-t, 0, -1],
            [-t, 0, 1],
        ],
        dtype=np.float64,
    )
    f = np.array(
        [
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ],
    )
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    mid = len(v) + inv.reshape(3, -1).T  # midpoints of edges (01, 12, 20) per face
    v = np.concatenate([v, (v[uniq[:, 0]] + v[uniq[:, 1]]) / 2])
    a, b, c = f.T
    m01, m12, m20 = mid.T
    f = np.concatenate(
        [
            np.stack(x, axis=1)
            for x in ((a, m01, m20), (b, m12, m01), (c, m20, m12), (m01, m12, m20))
        ]
    )
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


_SPHERE_V, _SPHERE_F = _unit_icosphere()


_BOX_V = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (0.0, 1.0)])


_BOX_F = np.array(
    [
        [0, 1, 3],
        [0, 3, 2],
        [4, 6, 7],
        [4, 7, 5],
        [0, 4, 5],
        [0, 5, 1],
        [2, 3, 7],
        [2, 7, 6],
        [0, 2, 6],
        [0, 6, 4],
        [1, 5, 7],
        [1, 7, 3],
    ]
)


def blob_mesh(
    centre: np.ndarray,
    radii: np.ndarray,
    rng: np.random.Generator,
    *,
    jitter: float = 0.2,
    porosity: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """N irregular ellipsoid blobs (foliage, bushes): returns vertices, faces, face->blob index.

    Each vertex's radius is scaled by U(1-jitter, 1+jitter); a share ``porosity`` of faces is
    dropped so that rays can pass through gaps (inferred model of foliage).
    """
    n = centre.shape[0]
    scale = rng.uniform(1 - jitter, 1 + jitter, (n, _SPHERE_V.shape[0], 1))
    verts = centre[:, None, :] + _SPHERE_V[None] * radii[:, None, :] * scale
    faces = _SPHERE_F[None] + (np.arange(n) * _SPHERE_V.shape[0])[:, None, None]
    owner = np.repeat(np.arange(n), _SPHERE_F.shape[0])
    keep = rng.random(owner.size) >= porosity
    return verts.reshape(-1, 3), faces.reshape(-1, 3)[keep], owner[keep]


def box_mesh(centre: np.ndarray, size: np.ndarray, yaw: np.ndarray):
    """N boxes standing on ``centre`` (bottom centre), ``size`` (N, 3), rotated by ``yaw``."""
    c, s = np.cos(yaw), np.sin(yaw)
    local = _BOX_V[None] * size[:, None, :]
    x = c[:, None] * local[..., 0] - s[:, None] * local[..., 1]
    y = s[:, None] * local[..., 0] + c[:, None] * local[..., 1]
    verts = np.stack([x, y, local[..., 2]], axis=-1) + centre[:, None, :]
    faces = _BOX_F[None] + (np.arange(len(centre)) * 8)[:, None, None]
    return verts.reshape(-1, 3), faces.reshape(-1, 3)
