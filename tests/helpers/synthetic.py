"""Analytic test scenes: exact ray casting of cylinders, planes and boxes into range images.

Used by the feature-extraction tests and ``benchmarks/bench_features.py``. Scenes are given in
the levelled sensor frame (origin at the sensor, z up). Every pixel's ray is intersected with
each object analytically (no meshes); Gaussian range noise is added afterwards. An optional
first-return beam-footprint model (spec 1.1: 0.042 m exit diameter + 3 mrad divergence) casts a
small bundle of sub-rays per pixel and keeps the shortest hit, which reproduces the "wide beam"
effects of spec 4.1 (segments wider than objects, radius biased low close up).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage, levelling_rotation

# Riegl LMS-Z210-like full-resolution grid (spec 1.1): 3000 x 720 pixels, 0.108 deg steps.
FULL_STEP_DEG = 0.108
FULL_COLS = 3000
FULL_ROWS = 720


@dataclass(frozen=True)
class Cylinder:
    """Finite cylinder: ``base`` (x, y, z) of the axis, unit ``axis``, ``radius``, ``length``."""

    base: tuple[float, float, float]
    axis: tuple[float, float, float]
    radius: float
    length: float

    @staticmethod
    def stem(x: float, y: float, radius: float, *, ground_z: float = -1.5, length: float = 12.0,
             lean_deg: float = 0.0, lean_azimuth_deg: float = 0.0) -> Cylinder:
        """A tree stem standing on the ground at (x, y), leaning ``lean_deg`` from vertical."""
        t, a = np.radians(lean_deg), np.radians(lean_azimuth_deg)
        axis = (np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t))
        return Cylinder((x, y, ground_z), tuple(float(v) for v in axis), radius, length)

    def point_at(self, s: float) -> np.ndarray:
        return np.asarray(self.base) + s * np.asarray(self.axis)


@dataclass(frozen=True)
class Wall:
    """Vertical rectangle from (x0, y0) to (x1, y1), between heights ``z0`` and ``z1``."""

    x0: float
    y0: float
    x1: float
    y1: float
    z0: float = -1.5
    z1: float = 3.0


@dataclass(frozen=True)
class Box:
    """Vertical square/rectangular post (doorframe-like): centre (x, y), half sizes, heights."""

    x: float
    y: float
    half_x: float
    half_y: float
    z0: float = -1.5
    z1: float = 3.0

    def walls(self) -> list[Wall]:
        x0, x1 = self.x - self.half_x, self.x + self.half_x
        y0, y1 = self.y - self.half_y, self.y + self.half_y
        return [Wall(x0, y0, x1, y0, self.z0, self.z1), Wall(x1, y0, x1, y1, self.z0, self.z1),
                Wall(x1, y1, x0, y1, self.z0, self.z1), Wall(x0, y1, x0, y0, self.z0, self.z1)]


@dataclass
class Scene:
    """Objects of an analytic scene; ``ground_z`` None means no ground plane."""

    cylinders: list[Cylinder] = field(default_factory=list)
    walls: list[Wall] = field(default_factory=list)
    boxes: list[Box] = field(default_factory=list)
    ground_z: float | None = -1.5
    ground_radius_m: float = 40.0


def grid(az_range_deg: tuple[float, float], el_range_deg: tuple[float, float],
         step_deg: float = FULL_STEP_DEG) -> tuple[np.ndarray, np.ndarray]:
    """Azimuths (increasing) and elevations (decreasing, row 0 at the top) covering the ranges."""
    az = np.arange(az_range_deg[0], az_range_deg[1] + 1e-9, step_deg)
    el = np.arange(el_range_deg[1], el_range_deg[0] - 1e-9, -step_deg)
    return az, el


def full_grid(step_deg: float = FULL_STEP_DEG) -> tuple[np.ndarray, np.ndarray]:
    """The 3000 x 720 LMS-Z210 grid (324 deg x 77.8 deg) scaled to ``step_deg``."""
    scale = FULL_STEP_DEG / step_deg
    cols, rows = int(round(FULL_COLS * scale)), int(round(FULL_ROWS * scale))
    az = -162.0 + step_deg * np.arange(cols)
    el = step_deg * (rows - 1) / 2.0 - step_deg * np.arange(rows)
    return az, el


def _ray_cylinder(o: np.ndarray, d: np.ndarray, c: Cylinder) -> np.ndarray:
    """Distance along rays (o + t d) to the outer surface of a finite open cylinder (inf = miss)."""
    a = np.asarray(c.axis, dtype=np.float64)
    w = o - np.asarray(c.base, dtype=np.float64)
    da, wa = d @ a, w @ a
    dp = d - da[:, None] * a
    wp = w - wa[:, None] * a
    qa = np.einsum("ij,ij->i", dp, dp)
    qb = 2.0 * np.einsum("ij,ij->i", dp, wp)
    qc = np.einsum("ij,ij->i", wp, wp) - c.radius**2
    disc = qb * qb - 4.0 * qa * qc
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-qb - np.sqrt(disc)) / (2.0 * qa)
        h = wa + t * da
        hit = (disc >= 0) & (qa > 0) & (t > 0) & (h >= 0) & (h <= c.length)
    return np.where(hit, t, np.inf)


def _ray_wall(o: np.ndarray, d: np.ndarray, w: Wall) -> np.ndarray:
    p0 = np.array([w.x0, w.y0])
    u = np.array([w.x1 - w.x0, w.y1 - w.y0])
    length = np.hypot(*u)
    u = u / length
    m = np.array([-u[1], u[0]])
    denom = d[:, :2] @ m
    with np.errstate(invalid="ignore", divide="ignore"):
        t = ((p0 - o[:, :2]) @ m) / denom
        p = o + t[:, None] * d
        s = (p[:, :2] - p0) @ u
        hit = (t > 0) & (s >= 0) & (s <= length) & (p[:, 2] >= w.z0) & (p[:, 2] <= w.z1)
    return np.where(hit, t, np.inf)


def _ray_ground(o: np.ndarray, d: np.ndarray, z: float, radius: float) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (z - o[:, 2]) / d[:, 2]
        p = o + t[:, None] * d
        hit = (t > 0) & (np.hypot(p[:, 0], p[:, 1]) <= radius)
    return np.where(hit, t, np.inf)


def _beam_bundle(n_sub: int) -> np.ndarray:
    """Unit-disc sample offsets (n_sub, 2): the centre plus rings (first-return footprint)."""
    if n_sub <= 1:
        return np.zeros((1, 2))
    k = n_sub - 1
    ang = 2 * np.pi * np.arange(k) / k
    rad = np.where(np.arange(k) % 2 == 0, 1.0, 0.55)
    return np.concatenate([np.zeros((1, 2)), np.stack([rad * np.cos(ang), rad * np.sin(ang)], 1)])


def _column_window(c: Cylinder, az: np.ndarray, margin_deg: float) -> np.ndarray:
    """Columns whose azimuth can see cylinder ``c`` (all columns when it is close)."""
    pts = np.asarray(c.base) + np.linspace(0, c.length, 17)[:, None] * np.asarray(c.axis)
    rho = np.hypot(pts[:, 0], pts[:, 1])
    if rho.min() < 3 * c.radius + 0.5:
        return np.arange(az.size)
    phi = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    half = np.degrees(np.arcsin(np.clip(c.radius / rho, 0, 1))).max() + margin_deg
    lo, hi = phi.min(), phi.max()
    if hi - lo > 180:  # straddles +-180: use everything
        return np.arange(az.size)
    return np.flatnonzero((az >= lo - half) & (az <= hi + half))


def render(scene: Scene, azimuth_deg: np.ndarray, elevation_deg: np.ndarray, *,
           noise_m: float = 0.025, seed: int = 0, tilt_deg: tuple[float, float] = (0.0, 0.0),
           beam: str | None = None, beam_exit_m: float = 0.042, beam_divergence_rad: float = 0.003,
           beam_rays: int = 13, echo_gate_m: float = 0.3, max_range_m: float = 80.0,
           labels: bool = False):
    """Exact range image of ``scene`` seen from the origin; returns (image, noise-free range).

    Rays follow the scanner's angular grid; with ``tilt_deg`` the scanner frame is tilted and
    the rays are rotated into the levelled scene frame by ``levelling_rotation``. ``beam``
    (inferred footprint models, spec 1.1 / 4.1): ``None`` one exact ray per pixel; ``"min"``
    ``beam_rays`` sub-rays spread over the footprint (diameter ``beam_exit_m +
    beam_divergence_rad * range``) and the shortest hit (any share of the pulse on a near object
    gives its range); ``"mean"`` the mean range of the sub-rays of the first echo (hits within
    ``echo_gate_m`` of the shortest), i.e. a footprint-averaged first echo. With ``labels``
    also returns an int image: index of the cylinder hit by the central ray, -1 otherwise.
    """
    az = np.radians(np.asarray(azimuth_deg, dtype=np.float64))
    el = np.radians(np.asarray(elevation_deg, dtype=np.float64))
    rows, cols = el.size, az.size
    d = np.stack(np.broadcast_arrays(np.cos(el)[:, None] * np.cos(az)[None, :],
                                     np.cos(el)[:, None] * np.sin(az)[None, :],
                                     np.sin(el)[:, None] + 0 * az[None, :]), -1)
    if any(tilt_deg):
        d = d @ levelling_rotation(*tilt_deg).T
    if beam not in (None, "min", "mean"):
        raise ValueError(f"beam: unknown {beam!r} (expected None, 'min' or 'mean')")
    offsets = _beam_bundle(beam_rays if beam else 1)
    # Orthonormal completion of each pixel direction for the beam footprint.
    up = np.where(np.abs(d[..., 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    e1 = np.cross(d, up)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(d, e1)

    # per sub-ray nearest hit over all objects: (n_sub, rows, cols)
    sub = np.full((len(offsets), rows, cols), np.inf)

    def cast(sel_r: np.ndarray, sel_c: np.ndarray, hit_fn) -> np.ndarray:
        dd = d[sel_r, sel_c]
        out = np.empty((len(offsets), dd.shape[0]))
        for k, (ox, oy) in enumerate(offsets):
            off = ox * e1[sel_r, sel_c] + oy * e2[sel_r, sel_c]
            o = 0.5 * beam_exit_m * off
            dirs = dd + 0.5 * beam_divergence_rad * off
            dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
            out[k] = hit_fn(o, dirs)
        return out

    all_r, all_c = np.divmod(np.arange(rows * cols), cols)
    if scene.ground_z is not None:
        sub = np.minimum(sub, cast(all_r, all_c, lambda o, dd: _ray_ground(
            o, dd, scene.ground_z, scene.ground_radius_m)).reshape(sub.shape))
    walls = list(scene.walls) + [w for b in scene.boxes for w in b.walls()]
    for w in walls:
        sub = np.minimum(sub, cast(all_r, all_c, lambda o, dd, w=w: _ray_wall(o, dd, w))
                         .reshape(sub.shape))
    margin = np.degrees(beam_divergence_rad) + 2 * abs(np.degrees(az[1] - az[0]) if cols > 1 else 0)
    label = np.full((rows, cols), -1, np.int64)
    for ci_obj, c in enumerate(scene.cylinders):
        cc = _column_window(c, np.degrees(az), margin)
        if cc.size == 0:
            continue
        rr, ci = np.divmod(np.arange(rows * cc.size), cc.size)
        hit = cast(rr, cc[ci], lambda o, dd, c=c: _ray_cylinder(o, dd, c))
        hit = hit.reshape(len(offsets), rows, cc.size)
        if labels:
            closer = hit[0] < sub[0][:, cc]
            lab_cc = label[:, cc]
            lab_cc[closer] = ci_obj
            label[:, cc] = lab_cc
        sub[:, :, cc] = np.minimum(sub[:, :, cc], hit)
    truth = sub.min(axis=0)
    if beam == "mean":
        echo = sub <= truth[None] + echo_gate_m
        with np.errstate(invalid="ignore"):
            truth = np.where(np.isfinite(truth), np.sum(np.where(echo, sub, 0.0), 0)
                             / np.maximum(echo.sum(0), 1), np.inf)
    truth[truth > max_range_m] = np.inf
    rng = np.random.default_rng(seed)
    noisy = truth + (rng.normal(0.0, noise_m, truth.shape) if noise_m > 0 else 0.0)
    noisy = np.where(np.isfinite(truth), noisy, np.nan)
    truth = np.where(np.isfinite(truth), truth, np.nan)
    image = RangeImage(noisy.astype(np.float32), np.degrees(az), np.degrees(el), tilt_deg)
    if labels:
        label[~np.isfinite(truth)] = -1
        return image, truth, label
    return image, truth


def visible_length_m(image: RangeImage, label: np.ndarray, index: int) -> float:
    """Visible trunk length of cylinder ``index``: rows hit at least 3 times, times the
    vertical pixel pitch at the hit range (an estimate for test selection)."""
    hits = label == index
    per_row = hits.sum(1)
    rows = np.flatnonzero(per_row >= 3)
    if rows.size == 0:
        return 0.0
    r = np.nanmedian(np.where(hits, image.range_m, np.nan)[rows], axis=1)
    return float(np.sum(r * np.radians(image.elevation_step_deg)))


def forest_scene(n_stems: int = 40, *, seed: int = 1, r_min_m: float = 2.0, r_max_m: float = 20.0,
                 radius_range_m: tuple[float, float] = (0.05, 0.3), max_lean_deg: float = 10.0,
                 ground_z: float = -1.5, stem_length_m: float = 14.0,
                 azimuth_range_deg: tuple[float, float] = (-160.0, 160.0),
                 min_separation_m: float = 1.0) -> Scene:
    """Random stems on flat ground at horizontal distances [r_min, r_max] from the sensor."""
    rng = np.random.default_rng(seed)
    stems: list[Cylinder] = []
    xy: list[tuple[float, float]] = []
    while len(stems) < n_stems:
        dist = np.sqrt(rng.uniform(r_min_m**2, r_max_m**2))
        phi = np.radians(rng.uniform(*azimuth_range_deg))
        x, y = dist * np.cos(phi), dist * np.sin(phi)
        if any(np.hypot(x - a, y - b) < min_separation_m for a, b in xy):
            continue
        radius = rng.uniform(*radius_range_m)
        lean = rng.uniform(0.0, max_lean_deg)
        stems.append(Cylinder.stem(x, y, radius, ground_z=ground_z, length=stem_length_m,
                                   lean_deg=lean, lean_azimuth_deg=rng.uniform(-180, 180)))
        xy.append((x, y))
    return Scene(cylinders=stems, ground_z=ground_z)


def stem_truth_at(c: Cylinder, z: float) -> np.ndarray:
    """Axis point of cylinder ``c`` at height ``z`` (levelled frame)."""
    s = (z - c.base[2]) / c.axis[2]
    return c.point_at(s)
