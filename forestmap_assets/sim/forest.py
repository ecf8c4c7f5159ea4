"""A virtual forest plot as one triangle mesh (synthetic data for spec 10.1 / 10.6 / 13).

The plot imitates the thesis's forest site (spec 10.1: natural forest, about 40 m square, six
tripod positions T, S, R, Q, O, N, trunks only): uneven ground, leaning and tapering stems with
slightly non-circular cross-sections, crowns of branches and foliage blobs above a few metres,
and understorey clutter near the ground. Everything is one triangle mesh whose triangles carry
labels (kind, tree, part), so that a ray cast with open3d's ``RaycastingScene`` tells which
object it hit.

Stem model (world frame, ``h`` = vertical height above ``z_base``, the ground under the stem)::

    axis(h)   = (x_base + lean_x h, y_base + lean_y h, z_base + h)
    r(h)      = r_base_m - taper_m_per_m h                   (mean radius, perpendicular to axis)
    r(h, psi) = r(h) + a2_m cos(2 (psi - phase2)) + a3_m cos(3 (psi - phase3))

``psi`` is the angle about the axis measured from the x axis projected perpendicular to the axis.
Breast height is ``h = 1.3`` m and the diameter at breast height is ``dbh_m = 2 r(1.3)``.
All numeric choices of the virtual forest are (inferred): the thesis describes its site only in
words; they are keyword arguments of :func:`make_forest`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

KIND_GROUND, KIND_STEM, KIND_BRANCH, KIND_FOLIAGE, KIND_UNDERSTOREY = 0, 1, 2, 3, 4
KIND_NAMES = ("ground", "stem", "branch", "foliage", "understorey")
NO_RETURN = 255  # kind label of a pixel without a return
BREAST_HEIGHT_M = 1.3

STEM_COLUMNS = [
    "tree_id", "x_base", "y_base", "z_base", "lean_x", "lean_y", "r_base_m", "taper_m_per_m",
    "height_m", "crown_base_m", "a2_m", "phase2_deg", "a3_m", "phase3_deg",
]


# ---- ground ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Ground:
    """Smooth random height field: a plane plus a few long-wave cosines (inferred)."""

    slope: tuple[float, float]
    amplitude: np.ndarray
    wavevector: np.ndarray  # (K, 2) rad/m
    phase: np.ndarray

    def height(self, x, y) -> np.ndarray:
        """Ground elevation z(x, y) (vectorised)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        arg = x[..., None] * self.wavevector[:, 0] + y[..., None] * self.wavevector[:, 1]
        waves = (self.amplitude * np.cos(arg + self.phase)).sum(axis=-1)
        base = (self.amplitude * np.cos(self.phase)).sum()  # so that z(0, 0) = 0
        return self.slope[0] * x + self.slope[1] * y + waves - base


def make_ground(
    rng: np.random.Generator,
    *,
    relief_m: float = 0.15,
    slope_range: tuple[float, float] = (0.02, 0.06),
    wavelength_range_m: tuple[float, float] = (8.0, 30.0),
    n_waves: int = 6,
) -> Ground:
    """Random ground: gradient ``slope_range`` (m/m), relief std ``relief_m`` (inferred)."""
    s = rng.uniform(*slope_range)
    a = rng.uniform(-np.pi, np.pi)
    lam = rng.uniform(*wavelength_range_m, n_waves)
    direction = rng.uniform(-np.pi, np.pi, n_waves)
    k = (2 * np.pi / lam)[:, None] * np.stack([np.cos(direction), np.sin(direction)], axis=1)
    amp = relief_m / np.sqrt(n_waves / 2) * rng.uniform(0.6, 1.4, n_waves)
    return Ground((s * np.cos(a), s * np.sin(a)), amp, k, rng.uniform(-np.pi, np.pi, n_waves))


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


def _concat(pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]):
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


def _unit_icosphere() -> tuple[np.ndarray, np.ndarray]:
    """Icosahedron subdivided once (42 vertices, 80 faces) on the unit sphere."""
    t = (1 + 5**0.5) / 2
    v = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
         [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64,
    )
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]],
    )
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    mid = len(v) + inv.reshape(3, -1).T  # midpoints of edges (01, 12, 20) per face
    v = np.concatenate([v, (v[uniq[:, 0]] + v[uniq[:, 1]]) / 2])
    a, b, c = f.T
    m01, m12, m20 = mid.T
    f = np.concatenate([np.stack(x, axis=1) for x in (
        (a, m01, m20), (b, m12, m01), (c, m20, m12), (m01, m12, m20))])
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


_SPHERE_V, _SPHERE_F = _unit_icosphere()
_BOX_V = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (0.0, 1.0)])
_BOX_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                   [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def blob_mesh(
    centre: np.ndarray, radii: np.ndarray, rng: np.random.Generator, *,
    jitter: float = 0.2, porosity: float = 0.0,
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


def ground_mesh(ground: Ground, half_extent: float, cell_m: float):
    """Regular triangulated grid of the ground over ``[-half_extent, half_extent]^2``."""
    n = int(np.ceil(2 * half_extent / cell_m)) + 1
    g = np.linspace(-half_extent, half_extent, n)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    verts = np.stack([xx, yy, ground.height(xx, yy)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    faces = np.concatenate([np.stack([a, a + n, a + n + 1], 1), np.stack([a, a + n + 1, a + 1], 1)])
    return verts, faces


# ---- placement -------------------------------------------------------------------------------
def scan_layout(
    n: int, plot_size: float, rng: np.random.Generator, *,
    spacing_m: float = 7.0, jitter_m: float = 0.75, edge_margin_m: float = 5.0,
) -> np.ndarray:
    """Scan positions (n, 2): a perturbed serpentine (zigzag) grid centred in the plot so that
    neighbours are about ``spacing_m`` apart (5-10 m, inferred from Fig. 6.10, spec 10.1)."""
    ncols = int(np.ceil(np.sqrt(n)))
    nrows = int(np.ceil(n / ncols))
    span = max(ncols, nrows) - 1
    step = spacing_m if span == 0 else min(spacing_m, (plot_size - 2 * edge_margin_m) / span)
    k = np.arange(n)
    row, col = k // ncols, k % ncols
    col = np.where(row % 2 == 1, ncols - 1 - col, col)  # serpentine order
    xy = np.stack([(col - (ncols - 1) / 2) * step, (row - (nrows - 1) / 2) * step], axis=1)
    return xy + rng.uniform(-jitter_m, jitter_m, (n, 2))


def sample_dbh(
    n: int, rng: np.random.Generator, *,
    median_m: float = 0.24, log_sigma: float = 0.35, bounds_m: tuple[float, float] = (0.07, 0.60),
) -> np.ndarray:
    """DBH from a lognormal truncated to ``bounds_m`` (inferred; mostly 0.15-0.35 m)."""
    out = np.empty(0)
    while out.size < n:
        d = median_m * np.exp(log_sigma * rng.standard_normal(2 * n + 16))
        out = np.concatenate([out, d[(d >= bounds_m[0]) & (d <= bounds_m[1])]])
    return out[:n]


def stem_height(dbh_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Tree height from DBH, ``1.3 + 30 (1 - exp(-0.045 d_cm))`` times U(0.9, 1.1) (inferred)."""
    return (1.3 + 30.0 * (1 - np.exp(-0.045 * dbh_m * 100))) * rng.uniform(0.9, 1.1, dbh_m.size)


def place_stems(
    radius: np.ndarray, scan_xy: np.ndarray, plot_size: float, rng: np.random.Generator, *,
    scan_clearance_m: float = 2.5, min_gap_m: float = 0.8, edge_m: float = 0.5,
    max_tries: int = 400,
) -> np.ndarray:
    """Stem positions (n, 2) inside the plot by rejection sampling: stems do not overlap each
    other (gap ``min_gap_m``) and stay ``scan_clearance_m`` from every scan position."""
    half = plot_size / 2 - edge_m
    placed = np.empty((0, 2))
    placed_r = np.empty(0)
    for r in radius:  # one iteration per tree, candidates tested vectorised
        cand = rng.uniform(-half, half, (max_tries, 2))
        ok = (np.linalg.norm(cand[:, None] - scan_xy[None], axis=2) >= scan_clearance_m + r).all(1)
        ok &= (np.linalg.norm(cand[:, None] - placed[None], axis=2)
               >= r + placed_r[None] + min_gap_m).all(1)
        if not ok.any():
            raise ValueError(
                f"cannot place {radius.size} non-overlapping trees in a {plot_size} m plot "
                f"around {len(scan_xy)} scan positions; use fewer trees or a larger plot"
            )
        placed = np.vstack([placed, cand[np.argmax(ok)]])
        placed_r = np.append(placed_r, r)
    return placed


# ---- the forest ------------------------------------------------------------------------------
@dataclass
class Forest:
    """A virtual plot: ground, stems (table, world frame), scan positions and the mesh."""

    plot_size: float
    ground: Ground
    stems: pd.DataFrame
    scan_xy: np.ndarray
    mesh: SceneMesh

    def trees_at_breast_height(self) -> pd.DataFrame:
        """Truth per tree (world frame): ``tree_id, x, y, z, dbh_m`` (axis at 1.3 m; z ground)."""
        return breast_height_table(self.stems)


def breast_height_table(stems: pd.DataFrame) -> pd.DataFrame:
    """``tree_id, x, y, z, dbh_m`` of a stem table (any frame): axis at 1.3 m, ground z."""
    h = BREAST_HEIGHT_M
    return pd.DataFrame({
        "tree_id": stems["tree_id"].to_numpy(),
        "x": stems["x_base"].to_numpy() + stems["lean_x"].to_numpy() * h,
        "y": stems["y_base"].to_numpy() + stems["lean_y"].to_numpy() * h,
        "z": stems["z_base"].to_numpy(),
        "dbh_m": 2 * (stems["r_base_m"].to_numpy() - stems["taper_m_per_m"].to_numpy() * h),
    })


def stems_in_frame(stems: pd.DataFrame, origin: np.ndarray, heading_deg: float) -> pd.DataFrame:
    """Stem table expressed in a levelled frame at ``origin`` with ``heading_deg`` (world)."""
    c, s = np.cos(np.radians(heading_deg)), np.sin(np.radians(heading_deg))
    out = stems.copy()
    dx = stems["x_base"].to_numpy() - origin[0]
    dy = stems["y_base"].to_numpy() - origin[1]
    out["x_base"], out["y_base"] = c * dx + s * dy, -s * dx + c * dy
    out["z_base"] = stems["z_base"].to_numpy() - origin[2]
    lx, ly = stems["lean_x"].to_numpy(), stems["lean_y"].to_numpy()
    out["lean_x"], out["lean_y"] = c * lx + s * ly, -s * lx + c * ly
    for col in ("phase2_deg", "phase3_deg"):  # psi is measured from the (rotated) x axis
        out[col] = np.mod(stems[col].to_numpy() - heading_deg + 180.0, 360.0) - 180.0
    return out


def make_forest(
    trees: int = 40,
    plot_size: float = 40.0,
    *,
    scan_xy: np.ndarray | None = None,
    n_scans: int = 6,
    seed: int | np.random.Generator = 0,
    scan_clearance_m: float = 2.5,
    min_tree_gap_m: float = 0.8,
    max_lean_deg: float = 8.0,
    lean_sigma_deg: float = 2.5,
    crown_base_range_m: tuple[float, float] = (3.0, 6.0),
    branches_per_m: float = 1.2,
    foliage_porosity: float = 0.3,
    understorey_per_m2: float = 0.04,
    understorey_clearance_m: float = 2.0,
    stem_sides: int = 48,
    stem_rings: int = 24,
    ground_margin_m: float = 20.0,
    ground_cell_m: float = 0.5,
    ground_kwargs: dict | None = None,
) -> Forest:
    """Build a virtual forest plot (square ``plot_size`` m centred at the origin).

    ``trees`` stems with DBH from :func:`sample_dbh`, leaning ``|N(0, lean_sigma_deg)|`` (at
    most ``max_lean_deg``), linear taper to ~1.5 cm at the top, elliptical/triangular
    cross-section perturbation of 1-4 mm and 0-2 mm, crowns of branches (tubes) and porous
    foliage blobs from 3-6 m up, understorey bushes/saplings/boxes below ~1 m. Stems keep
    ``scan_clearance_m`` from the scan positions (``scan_xy`` or :func:`scan_layout` of
    ``n_scans``), understorey ``understorey_clearance_m``. All values (inferred).
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    ground = make_ground(rng, **(ground_kwargs or {}))
    if scan_xy is None:
        scan_xy = scan_layout(n_scans, plot_size, rng)
    scan_xy = np.asarray(scan_xy, dtype=np.float64).reshape(-1, 2)

    # stems
    dbh = sample_dbh(trees, rng)
    height = stem_height(dbh, rng)
    r_bh = dbh / 2
    taper = (r_bh - 0.015) / (height - BREAST_HEIGHT_M)
    r_base = r_bh + taper * BREAST_HEIGHT_M
    xy = place_stems(r_base, scan_xy, plot_size, rng, scan_clearance_m=scan_clearance_m,
                     min_gap_m=min_tree_gap_m)
    lean = np.radians(np.minimum(np.abs(rng.normal(0, lean_sigma_deg, trees)), max_lean_deg))
    lean_dir = rng.uniform(-np.pi, np.pi, trees)
    harm = np.stack([rng.uniform(0.001, 0.004, trees), rng.uniform(-np.pi, np.pi, trees),
                     rng.uniform(0.0, 0.002, trees), rng.uniform(-np.pi, np.pi, trees)], axis=1)
    crown_base = np.minimum(rng.uniform(*crown_base_range_m, trees), 0.6 * height)
    stems = pd.DataFrame({
        "tree_id": np.arange(1, trees + 1),
        "x_base": xy[:, 0], "y_base": xy[:, 1], "z_base": ground.height(xy[:, 0], xy[:, 1]),
        "lean_x": np.tan(lean) * np.cos(lean_dir), "lean_y": np.tan(lean) * np.sin(lean_dir),
        "r_base_m": r_base, "taper_m_per_m": taper, "height_m": height,
        "crown_base_m": crown_base,
        "a2_m": harm[:, 0], "phase2_deg": np.degrees(harm[:, 1]),
        "a3_m": harm[:, 2], "phase3_deg": np.degrees(harm[:, 3]),
    })[STEM_COLUMNS]

    base = stems[["x_base", "y_base", "z_base"]].to_numpy()
    slope = np.column_stack([stems["lean_x"], stems["lean_y"], np.ones(trees)])

    def axis_at(idx, h):  # stem axis points of trees (row index) at heights h
        return base[idx] + np.asarray(h)[:, None] * slope[idx]

    idx = np.arange(trees)
    h0 = np.full(trees, -0.3)  # the tube starts below the ground
    sv, sf = tube_mesh(axis_at(idx, h0), axis_at(idx, height), r_base - taper * h0,
                       r_base - taper * height, n_sides=stem_sides, n_rings=stem_rings,
                       harmonics=harm)
    per_stem = 2 * (stem_rings - 1) * stem_sides
    stem_owner = np.repeat(idx, per_stem)
    part = 1  # 0 is the ground
    pieces = []
    gv, gf = ground_mesh(ground, plot_size / 2 + ground_margin_m, ground_cell_m)
    pieces.append((gv, gf, np.full(len(gf), KIND_GROUND), np.full(len(gf), -1),
                   np.zeros(len(gf))))
    pieces.append((sv, sf, np.full(len(sf), KIND_STEM), stem_owner + 1, part + stem_owner))
    part += trees

    # crowns: branches from the stem axis, foliage blobs at their ends and at the top
    crown_len = np.maximum(height * 0.95 - crown_base, 0.5)
    n_br = np.maximum(3, np.round(branches_per_m * crown_len)).astype(int)
    bt = np.repeat(idx, n_br)
    u = rng.random(bt.size)
    hb = crown_base[bt] + u * crown_len[bt]
    crown_r = 0.8 + 6.0 * dbh[bt]  # crown radius (inferred)
    length = crown_r * rng.uniform(0.5, 1.0, bt.size) * (1 - 0.6 * u)
    az = rng.uniform(-np.pi, np.pi, bt.size)
    up = np.radians(rng.uniform(10, 50, bt.size))
    direction = np.stack([np.cos(up) * np.cos(az), np.cos(up) * np.sin(az), np.sin(up)], axis=1)
    start = axis_at(bt, hb)
    end = start + length[:, None] * direction
    rb = np.minimum(0.4 * (r_base[bt] - taper[bt] * hb), rng.uniform(0.01, 0.04, bt.size))
    bv, bf = tube_mesh(start, end, rb, 0.3 * rb, n_sides=6, n_rings=2)
    br_owner = np.repeat(np.arange(bt.size), 2 * 6)
    pieces.append((bv, bf, np.full(len(bf), KIND_BRANCH), bt[br_owner] + 1, part + br_owner))
    part += bt.size

    top = axis_at(idx, height)
    blob_c = np.concatenate([end, top])
    blob_tree = np.concatenate([bt, idx])
    blob_size = np.concatenate([0.25 + 0.35 * crown_r / 2 * rng.uniform(0.5, 1.0, bt.size),
                                0.4 + 2.0 * dbh])
    radii = blob_size[:, None] * np.array([[1.0, 1.0, 0.7]])
    fv, ff, f_owner = blob_mesh(blob_c, radii, rng, porosity=foliage_porosity)
    pieces.append((fv, ff, np.full(len(ff), KIND_FOLIAGE), blob_tree[f_owner] + 1,
                   part + f_owner))
    part += blob_c.shape[0]

    # understorey: bushes, saplings and boxes (stumps, stones) away from scans and stems
    n_u = int(round(understorey_per_m2 * plot_size**2))
    if n_u:
        size = rng.uniform(0.2, 0.6, 8 * n_u + 64)
        cand = rng.uniform(-plot_size / 2, plot_size / 2, (size.size, 2))
        ok = (np.linalg.norm(cand[:, None] - scan_xy[None], axis=2)
              >= understorey_clearance_m + size[:, None]).all(1)
        ok &= (np.linalg.norm(cand[:, None] - xy[None], axis=2)
               >= r_base[None] + size[:, None] + 0.1).all(1)
        cand, size = cand[ok][:n_u], size[ok][:n_u]
        n_u = len(size)
        kind_u = rng.choice(3, n_u, p=[0.45, 0.35, 0.20])
        zc = ground.height(cand[:, 0], cand[:, 1])
        for k, gen in ((0, "bush"), (1, "sapling"), (2, "box")):
            m = np.flatnonzero(kind_u == k)
            if not m.size:
                continue
            if gen == "bush":
                rad = size[m, None] * np.array([[1.0, 1.0, 0.8]])
                c = np.column_stack([cand[m], zc[m] + 0.5 * rad[:, 2]])
                v, f, own = blob_mesh(c, rad, rng, jitter=0.25, porosity=0.2)
                own = m[own]
            elif gen == "sapling":
                hgt = rng.uniform(0.5, 1.3, m.size)
                lean_v = rng.normal(0, 0.08, (m.size, 2))
                p0 = np.column_stack([cand[m], zc[m] - 0.1])
                p1 = np.column_stack([cand[m] + lean_v * hgt[:, None], zc[m] + hgt])
                rs = rng.uniform(0.005, 0.02, m.size)
                v, f = tube_mesh(p0, p1, rs, 0.4 * rs, n_sides=6, n_rings=2)
                own = m[np.repeat(np.arange(m.size), 12)]
                cv, cf, cown = blob_mesh(p1, rng.uniform(0.1, 0.3, (m.size, 1)) * [[1, 1, 0.8]],
                                         rng, jitter=0.25, porosity=0.3)
                f = np.concatenate([f, cf + len(v)])
                v = np.concatenate([v, cv])
                own = np.concatenate([own, m[cown]])
            else:
                dims = np.column_stack([size[m], size[m] * rng.uniform(0.5, 1.0, m.size),
                                        rng.uniform(0.1, 0.4, m.size) + 0.1])
                v, f = box_mesh(np.column_stack([cand[m], zc[m] - 0.1]), dims,
                                rng.uniform(0, np.pi, m.size))
                own = m[np.repeat(np.arange(m.size), 12)]
            pieces.append((v, f, np.full(len(f), KIND_UNDERSTOREY), np.full(len(f), -1),
                           part + own))
        part += n_u
    return Forest(plot_size, ground, stems, scan_xy, _concat(pieces))
