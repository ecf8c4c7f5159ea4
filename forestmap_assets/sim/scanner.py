"""A virtual Riegl LMS-Z210 (spec 1.1, 1.2): true ray casting with a first-return wide beam.

Image geometry (spec 1.2): ``rows x cols`` = 720 x 3000 at full resolution over 79 deg x
330 deg (JP §II-A), elevation symmetric about the horizon, row 0 at the top, azimuth
increasing with the column; "half"/"quarter" divide both counts by 2/4 over the same field of
view. "fine" is a modern scanner's grid instead (inferred, issue 18 "big scans"):
``FINE_GRID``, 0.028 deg over 360 x 100 deg (12857 x 3571 pixels, about 30 M returns in the
simulated forest; Riegl VZ-400i / FARO Focus class steps are 0.02-0.04 deg), with the same
beam. Range noise is Gaussian with sigma 0.025 m (Table 6.1).

First-return beam (spec 1.1 "Consequences"): the beam leaves the housing 0.042 m wide and
diverges by 3 mrad, i.e. its footprint diameter at range r is ``0.042 + 0.003 r``. A pixel whose
footprint touches a nearer object returns the nearer range, so thin objects appear wider. The
footprint is sampled efficiently (inferred): the centre rays are cast first; pixels within one
footprint radius of an object boundary (neighbouring pixels hitting different objects) get
``sub_rays`` extra rays on the footprint's edge circle (exit offset 0.021 m, half-angle
1.5 mrad), and the nearest of the centre and sub-ray returns is the pixel's range when it is
nearer than the centre return by more than ``mix_min_step_m`` (a different, nearer surface; the
small range spread of one oblique surface across its own footprint is not modelled).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from forestmap_assets.core.features.range_image import RangeImage, levelling_rotation
from forestmap_assets.sim.scene_mesh import (
    KIND_BRANCH,
    KIND_FOLIAGE,
    KIND_GROUND,
    KIND_STEM,
    KIND_UNDERSTOREY,
    NO_RETURN,
)

# Riegl LMS-Z210 pixel counts divided by these; "fine" (None) has its own grid, FINE_GRID
RESOLUTION_DIVISOR: dict[str, int | None] = {"fine": None, "full": 1, "half": 2, "quarter": 4}
# (inferred) a modern scanner's step and field of view: about 30 M returns per forest scan
FINE_GRID = {"step_deg": 0.028, "hfov_deg": 360.0, "vfov_deg": 100.0}

# Relative reflectance per kind for the (inferred) intensity channel.
_REFLECTANCE = np.zeros(256, dtype=np.float32)
_REFLECTANCE[[KIND_GROUND, KIND_STEM, KIND_BRANCH, KIND_FOLIAGE, KIND_UNDERSTOREY]] = (
    0.30, 0.50, 0.45, 0.60, 0.40)
# structured sites (sim/sites.py): wall, ceiling, pillar, pole, car, person
_REFLECTANCE[5:11] = (0.55, 0.60, 0.50, 0.40, 0.35, 0.30)


def rot_z(deg: float) -> np.ndarray:
    """Rotation by ``deg`` counter-clockwise about +z (spec 6.1 / Eq. 6.1)."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class ScanPose:
    """Scanner pose in the world: sensor origin, heading of the levelled frame, and the
    scanner's tilt (roll, pitch) so that ``p_world = R_z(heading) R_y(pitch) R_x(roll) p_s + t``."""

    x: float
    y: float
    z: float
    heading_deg: float = 0.0
    tilt_deg: tuple[float, float] = (0.0, 0.0)

    @property
    def origin(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z], dtype=np.float64)

    def rotation(self) -> np.ndarray:
        """Scanner frame -> world rotation."""
        return rot_z(self.heading_deg) @ levelling_rotation(*self.tilt_deg)


@dataclass
class ScanResult:
    """A simulated scan: the range image (scanner frame, tilt recorded) and per-pixel truth.

    ``true_range_m`` is the noise-free first-return range, ``kind`` the KIND_* label of the
    returning object (NO_RETURN where none), ``tree_id`` its tree (-1 where none), ``part`` the
    object id (-1 where none), ``mixed`` True where the first return came from a sub-ray of the
    beam edge rather than the centre ray (the "mixed" pixels that widen objects).
    """

    image: RangeImage
    pose: ScanPose
    true_range_m: np.ndarray
    kind: np.ndarray
    tree_id: np.ndarray
    part: np.ndarray
    mixed: np.ndarray
    n_rays: int

    def world_points(self, noisy: bool = True) -> np.ndarray:
        """Returned points (rows, cols, 3) in the world frame (NaN where no return)."""
        img = self.image
        if not noisy:
            img = RangeImage(self.true_range_m, img.azimuth_deg, img.elevation_deg, img.tilt_deg)
        lev = img.xyz
        return lev @ rot_z(self.pose.heading_deg).T + self.pose.origin


class VirtualScanner:
    """Riegl LMS-Z210-like scanner casting rays into a labelled mesh (spec 1.1).

    ``target`` is a :class:`~forestmap_assets.sim.forest.Forest` or a
    :class:`~forestmap_assets.sim.scene_mesh.SceneMesh`. All beam and geometry numbers are those of
    spec 1.1 (JP §II-A field of view). (inferred): ``sub_rays`` per mixed-candidate pixel,
    ``footprint_fraction`` (share of the nominal footprint radius at which a first return still
    triggers), ``mix_min_step_m`` (how much nearer a sub-ray return must be to replace the
    centre return) and the ``intensity`` channel (reflectance per kind x |cos incidence|; the
    thesis uses range only). ``n_cols``/``n_rows`` are full-resolution counts (``resolution="fine"``
    replaces them and the field of view by ``FINE_GRID``). ``colour`` (True,
    or a :class:`~forestmap_assets.sim.colour.ColourModel`) adds 8-bit RGB per pixel from the
    surface's world-fixed albedo under the scan's own light (men spec 2.3; ``sim/colour.py``).
    ``mixed_range``: a mixed pixel returns the nearer surface (``"first"``, a first-return
    pulse scanner) or a range drawn uniformly between the two surfaces (``"blend"``: the one
    echo of both that phase and many pulse scanners report, the "ghost" points that trail
    trunks' silhouettes in real TLS clouds; inferred).
    """

    def __init__(
        self,
        target,
        *,
        resolution: str = "full",
        range_sigma_m: float = 0.025,
        beam_exit_m: float = 0.042,
        divergence_mrad: float = 3.0,
        max_range_m: float = 80.0,
        hfov_deg: float = 330.0,
        vfov_deg: float = 79.0,
        n_cols: int = 3000,
        n_rows: int = 720,
        azimuth_centre_deg: float = 0.0,
        elevation_centre_deg: float = 0.0,
        sub_rays: int = 8,
        footprint_fraction: float = 1.0,
        intensity: bool = True,
        chunk_rays: int = 1_000_000,
        mix_min_step_m: float = 0.05,
        colour=False,
        mixed_range: str = "first",
    ) -> None:
        if mixed_range not in ("first", "blend"):
            raise ValueError(f"mixed_range: {mixed_range!r} is not 'first' or 'blend'")
        if resolution not in RESOLUTION_DIVISOR:
            raise ValueError(f"resolution: {resolution!r} is not one of {list(RESOLUTION_DIVISOR)}")
        self.mesh = getattr(target, "mesh", target)
        div = RESOLUTION_DIVISOR[resolution]
        if div is None:  # a modern scanner's grid: its own step over its own field of view
            hfov_deg, vfov_deg = FINE_GRID["hfov_deg"], FINE_GRID["vfov_deg"]
            n_cols = int(round(hfov_deg / FINE_GRID["step_deg"]))
            n_rows = int(round(vfov_deg / FINE_GRID["step_deg"]))
            div = 1
        self.n_cols, self.n_rows = n_cols // div, n_rows // div
        self.d_az = hfov_deg / self.n_cols
        self.d_el = vfov_deg / self.n_rows
        # pixel centres, symmetric about the centre direction (spec 1.2)
        self.azimuth_deg = azimuth_centre_deg + (np.arange(self.n_cols) - (self.n_cols - 1) / 2) * (
            self.d_az)
        self.elevation_deg = elevation_centre_deg - (
            np.arange(self.n_rows) - (self.n_rows - 1) / 2) * self.d_el
        self.range_sigma_m = range_sigma_m
        self.exit_radius_m = footprint_fraction * beam_exit_m / 2
        self.half_angle_rad = footprint_fraction * divergence_mrad * 1e-3 / 2
        self.max_range_m = max_range_m
        self.sub_rays = sub_rays
        self.intensity = intensity
        self.chunk_rays = chunk_rays
        self.mix_min_step_m = mix_min_step_m
        self.mixed_range = mixed_range
        self._dirs: np.ndarray | None = None
        if colour is True:
            from forestmap_assets.sim.colour import ColourModel

            colour = ColourModel()
        self.colour = colour or None

    # ---- geometry ------------------------------------------------------------------------
    def footprint_radius_m(self, r: np.ndarray) -> np.ndarray:
        """Beam footprint radius at range r: (0.042 + 0.003 r) / 2 (spec 1.1)."""
        return self.exit_radius_m + self.half_angle_rad * np.asarray(r)

    def sensor_beam(self) -> dict[str, float]:
        """The beam as ``campaign.yaml`` names it (``sensor``): divergence (mrad) and exit
        diameter (mm) of the first-return footprint; none without sub-rays (one exact ray)."""
        wide = self.sub_rays > 0
        return {"beam_divergence_mrad": round(2e3 * self.half_angle_rad if wide else 0.0, 6),
                "beam_exit_mm": round(2e3 * self.exit_radius_m if wide else 0.0, 6)}

    def _directions(self, jitter=None) -> np.ndarray:
        """Unit beam directions, scanner frame, (rows*cols, 3) float32, built in row blocks so
        that a fine grid needs no float64 copy of the whole image; cached without ``jitter``
        (per-beam (d_az, d_el) in degrees, each (rows, cols))."""
        if jitter is None and self._dirs is not None:
            return self._dirs
        d = np.empty((self.n_rows, self.n_cols, 3), dtype=np.float32)
        block = max(1, 2_000_000 // self.n_cols)
        for a in range(0, self.n_rows, block):
            az, el = self._angles(slice(a, a + block), jitter)
            ce = np.cos(el)
            d[a:a + block, :, 0] = ce * np.cos(az)
            d[a:a + block, :, 1] = ce * np.sin(az)
            d[a:a + block, :, 2] = np.sin(el) * np.ones_like(az)
        if jitter is not None:
            return d.reshape(-1, 3)
        self._dirs = d.reshape(-1, 3)
        return self._dirs

    def _angles(self, rows, jitter=None, cols=slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """Beam azimuth and elevation (radians) of ``rows`` x ``cols`` (broadcastable), with
        the per-beam ``jitter`` (degrees) added; or of flat pixels (``rows`` an index array)."""
        if isinstance(rows, np.ndarray):  # flat pixel indices
            v, u = np.divmod(rows, self.n_cols)
            az, el = self.azimuth_deg[u], self.elevation_deg[v]
            if jitter is not None:
                az, el = az + jitter[0].reshape(-1)[rows], el + jitter[1].reshape(-1)[rows]
            return np.radians(az), np.radians(el)
        az = self.azimuth_deg[None, cols]
        el = self.elevation_deg[rows][:, None]
        if jitter is not None:
            az, el = az + jitter[0][rows, cols], el + jitter[1][rows, cols]
        return np.radians(az), np.radians(el)

    def _footprint_axes(self, pixels: np.ndarray, jitter=None) -> tuple[np.ndarray, np.ndarray]:
        """The two unit axes across the beam of flat ``pixels`` (scanner frame, float32):
        ``e1`` horizontal, ``e2`` towards increasing elevation."""
        az, el = self._angles(pixels, jitter)
        ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
        e1 = np.stack([-sa, ca, np.zeros_like(ca)], axis=-1).astype(np.float32)
        e2 = np.stack([-se * ca, -se * sa, ce], axis=-1).astype(np.float32)
        return e1, e2

    def _cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hit distance (inf: none or beyond max range) and triangle id (-1) of rays."""
        import open3d as o3d

        scene = self.mesh.raycasting_scene()
        n = len(dirs)
        t = np.empty(n, dtype=np.float32)
        prim = np.empty(n, dtype=np.int64)
        rays = np.empty((min(n, self.chunk_rays), 6), dtype=np.float32)
        for a in range(0, n, self.chunk_rays):
            b = min(a + self.chunk_rays, n)
            rays[: b - a, :3] = origins if origins.shape[0] == 1 else origins[a:b]
            rays[: b - a, 3:] = dirs[a:b]
            ans = scene.cast_rays(o3d.core.Tensor(rays[: b - a]))
            t[a:b] = ans["t_hit"].numpy()
            prim[a:b] = ans["primitive_ids"].numpy()
        miss = ~(t <= self.max_range_m)
        t[miss] = np.inf
        prim[miss] = -1
        return t, prim

    def _mixed_candidates(self, r: np.ndarray, part: np.ndarray) -> np.ndarray:
        """Pixels whose footprint may reach a nearer object (inferred criterion).

        Boundary pixels are pixels with a neighbour on a different object (or hit / no hit).
        A pixel is a candidate when a boundary pixel within the footprint radius (in pixels,
        at that boundary pixel's range) is nearer by more than ``mix_min_step_m``.
        """
        rows, cols = r.shape
        k = np.zeros((rows, cols), dtype=np.int32)
        finite = np.where(np.isfinite(r), r, np.float32(1e9))
        ang = self.exit_radius_m / finite + self.half_angle_rad
        kpix = np.minimum(np.ceil(np.degrees(ang) / self.d_el) + 1, 64).astype(np.int32)
        for axis in (0, 1):
            diff = part != np.roll(part, -1, axis=axis)
            if axis == 0:
                diff[-1, :] = False
            else:
                diff[:, -1] = False
            k = np.maximum(k, np.where(diff | np.roll(diff, 1, axis=axis), kpix, 0))
        cand = np.zeros((rows, cols), dtype=bool)
        cos_el = np.cos(np.radians(np.max(np.abs(self.elevation_deg))))
        for kv in np.unique(k[k > 0]):
            kc = int(np.ceil(kv * self.d_el / (self.d_az * cos_el)))
            near = np.where(k == kv, finite, np.float32(np.inf))
            nearest = ndimage.minimum_filter(near, size=(2 * kv + 1, 2 * kc + 1), mode="nearest")
            cand |= nearest < finite - self.mix_min_step_m
        return cand

    def _beam_edge(self, cand, d, rot, origin, best_r, best_prim, mixed, rng, jitter=None) -> int:
        """Sub-rays on the footprint's edge circle of the pixels ``cand``: where one returns
        nearer than the centre ray by more than ``mix_min_step_m`` it becomes the pixel's return
        (``best_r``, ``best_prim`` and ``mixed`` updated in place). Returns the rays cast."""
        k, a, b = self.sub_rays, self.exit_radius_m, self.half_angle_rad
        e1_s, e2_s = self._footprint_axes(cand, jitter)
        phi = (np.arange(k, dtype=np.float32)[None, :]
               + rng.random((cand.size, 1), dtype=np.float32)) * np.float32(2 * np.pi / k)
        off = (np.cos(phi)[..., None] * (e1_s @ rot.T)[:, None, :]
               + np.sin(phi)[..., None] * (e2_s @ rot.T)[:, None, :]).reshape(-1, 3)
        # sub-ray k: from the exit circle (radius a) at half-angle b to the beam axis; its
        # direction d + b*off has norm sqrt(1 + b^2) because off is perpendicular to d
        sub_o = (origin + a * off).astype(np.float32)
        sub_d = (np.repeat(d[cand], k, axis=0) + np.float32(b) * off) / np.float32(
            np.sqrt(1 + b * b))
        st, sp = self._cast(sub_o, sub_d)
        # distance from the sensor origin to the hit: |a off + t d_k|
        sr = np.sqrt(a * a + st * st + 2 * a * st * (b / np.sqrt(1 + b * b)))
        sr, sp = sr.reshape(-1, k), sp.reshape(-1, k)
        j = np.argmin(sr, axis=1)
        sub_best = sr[np.arange(cand.size), j]
        far = best_r[cand]
        closer = sub_best < far - self.mix_min_step_m
        sel = cand[closer]
        near = sub_best[closer]
        if self.mixed_range == "blend":  # an echo of both surfaces: a range between them
            behind = far[closer]
            both = np.isfinite(behind)
            w = rng.random(int(both.sum()), dtype=np.float32)
            near[both] += w * (behind[both] - near[both])
        best_r[sel] = near
        best_prim[sel] = sp[np.flatnonzero(closer), j[closer]]
        mixed[sel] = True
        return int(st.size)

    # ---- scanning ------------------------------------------------------------------------
    def scan(self, pose: ScanPose, seed: int | np.random.Generator = 0, *,
             jitter: tuple[np.ndarray, np.ndarray] | None = None) -> ScanResult:
        """Simulate one range image from ``pose`` (noise and sub-ray pattern from ``seed``).

        ``jitter``: per-beam (d_az, d_el) in degrees, (rows, cols) each, turning every beam off
        its grid direction (:meth:`scan_points`); the image then holds the ranges of the turned
        beams at their grid pixels."""
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        rot = pose.rotation().astype(np.float32)
        d = self._directions(jitter) @ rot.T
        origin = pose.origin
        t, prim = self._cast(origin[None], d)
        shape = (self.n_rows, self.n_cols)
        part_of = np.where(prim >= 0, self.mesh.part[np.maximum(prim, 0)], -1)
        n_rays = t.size
        best_r, best_prim = t, prim
        mixed = np.zeros(t.size, dtype=bool)
        if self.sub_rays > 0:
            cand = np.flatnonzero(self._mixed_candidates(t.reshape(shape), part_of.reshape(shape)))
            del part_of
            # candidates in blocks (a fine grid has millions); the same random stream as one block
            step = max(1, self.chunk_rays // self.sub_rays)
            for c0 in range(0, cand.size, step):
                n_rays += self._beam_edge(cand[c0:c0 + step], d, rot, origin, best_r, best_prim,
                                          mixed, rng, jitter)
        valid = np.isfinite(best_r)
        true_r = np.where(valid, best_r, np.float32(np.nan))
        noise = rng.standard_normal(true_r.size, dtype=np.float32) * np.float32(self.range_sigma_m)
        noisy = true_r + noise
        noisy[~(noisy > 0)] = np.nan
        pi = np.maximum(best_prim, 0)
        kind = np.where(valid, self.mesh.kind[pi], NO_RETURN).astype(np.uint8)
        tree = np.where(valid, self.mesh.tree[pi], -1).astype(np.int32)
        part = np.where(valid, self.mesh.part[pi], -1).astype(np.int32)
        intensity = rgb = None
        if self.intensity or self.colour is not None:
            cos_i = np.abs((self.mesh.normals[pi] * d).sum(axis=1))
        if self.intensity:
            intensity = np.where(valid, _REFLECTANCE[kind] * cos_i, np.nan).astype(np.float32)
            intensity = np.round(intensity, 3).reshape(shape)  # 1e-3 steps (compresses well)
        if self.colour is not None:
            # colour of the returning surface point (a mixed pixel takes the nearer surface's)
            hit = np.flatnonzero(valid)
            world = origin + best_r[hit, None].astype(np.float64) * d[hit]
            rgb = np.zeros((t.size, 3), dtype=np.uint8)
            rgb[hit] = self.colour.render(world, kind[hit], part[hit], cos_i[hit], rng)
            rgb = rgb.reshape(shape + (3,))
        image = RangeImage(noisy.reshape(shape), self.azimuth_deg, self.elevation_deg,
                           (float(pose.tilt_deg[0]), float(pose.tilt_deg[1])), intensity, rgb)
        return ScanResult(image, pose, true_r.reshape(shape), kind.reshape(shape),
                          tree.reshape(shape), part.reshape(shape), mixed.reshape(shape),
                          int(n_rays))

    def scan_points(self, pose: ScanPose, seed: int | np.random.Generator = 0, *,
                    jitter_steps: float = 0.3, dropout: float = 0.0
                    ) -> tuple[np.ndarray, np.ndarray | None]:
        """An unorganised scan as a scanner exports it (inferred, issue 18): each beam leaves
        along its grid direction turned by N(0, ``jitter_steps`` x step) in azimuth and in
        elevation (a real scanner's points do not sit on an exact grid), with the same wide
        first-return beam and range noise as :meth:`scan`, and a share ``dropout`` of the
        returns is lost at random. Returns the scanner-frame points (n, 3) float64 and their
        intensity (None without ``intensity``)."""
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        shape = (self.n_rows, self.n_cols)
        jitter = (rng.normal(0.0, jitter_steps * self.d_az, shape).astype(np.float32),
                  rng.normal(0.0, jitter_steps * self.d_el, shape).astype(np.float32))
        image = self.scan(pose, rng, jitter=jitter).image
        keep = np.flatnonzero((image.valid & (rng.random(shape) >= dropout)).ravel())
        az, el = self._angles(keep, jitter)
        r = image.range_m.reshape(-1)[keep].astype(np.float64)
        xyz = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                               r * np.sin(el)])
        inten = None if image.intensity is None else image.intensity.reshape(-1)[keep]
        return xyz, inten
