"""Surfaces widened by a renderer's splats, found and taken back in a pair's refinement (issue 19,
inferred; benchmarks/results.md "splat_dilation").

Scans rendered inside a registered cloud splat each source point over the pixels within its
radius, and the nearest depth wins each pixel: every surface is widened across the rays by
``k r step``, ``k = round(s / (r step))`` pixels of the scan's angular step for a splat of radius
``s`` at range ``r`` (:func:`widening`). A stem's sides and grazing ground then lie outward of the
truth by that widening times the sine of the incidence, differently for each scan, and a pair's
raw-point refinement comes out long: +0.27 mm per metre of baseline with 7 mm splats, +0.96 with
12 mm (rendered 46). Moving each point back by the widening along the part of its normal across
its own ray (:func:`corrected`) brought those to -0.08 / +0.03 mm/m.

The splat is not known for data we did not make, so each refined pair chooses it
(:func:`choose_splat`): at the refined pose, the mean point-to-plane distance of both
directions (pairs found on the raw points, distances between the corrected ones) for every
candidate radius; the smallest wins when it is at least ``min_gain`` below the uncorrected one.
Rendered 46 chose 7 mm (7 mm splats) and 15 mm (15 mm) on every pair, 11-13 mm with 12 mm splats;
Sylva's and the own simulator's surveys chose none."""

from __future__ import annotations

import numpy as np

from forestmap_assets.core.registration.hicp import pose4_to_matrix
from forestmap_assets.core.registration.point_to_plane import plane_pairs
from forestmap_assets.core.registration.two_way import RefineCloud, invert_pose


def lateral(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's range from its sensor (at the origin) and the unit direction (n, 3) of its
    normal's part across its ray (zeros where the normal lies along the ray or is missing)."""
    p = np.asarray(points, dtype=np.float64)
    rng = np.linalg.norm(p, axis=1)
    ray = p / np.maximum(rng, 1e-12)[:, None]
    n = np.nan_to_num(np.asarray(normals, dtype=np.float64))
    across = n - (n * ray).sum(axis=1, keepdims=True) * ray
    size = np.linalg.norm(across, axis=1)
    return rng, np.where((size > 1e-6)[:, None], across / np.maximum(size, 1e-12)[:, None], 0.0)


def widening(rng: np.ndarray, splat_m: float, step_rad: float) -> np.ndarray:
    """How far (m) splats of radius ``splat_m`` widen a surface at range ``rng``: a whole number
    of pixels of ``step_rad``, ``round(s / (r step)) r step``."""
    rng = np.asarray(rng, dtype=np.float64)
    if not splat_m > 0 or not step_rad > 0:
        return np.zeros_like(rng)
    pixel = rng * step_rad
    return np.floor(splat_m / np.maximum(pixel, 1e-12) + 0.5) * pixel


class Widened:
    """A refinement cloud's points with what :func:`corrected` needs: ranges and across-ray
    directions of its data and model points, computed once."""

    def __init__(self, data, data_normals, model, normals, step_rad: float):
        self.data, self.model, self.step_rad = data, model, step_rad
        self.rd, self.ud = lateral(data, data_normals)
        self.rm, self.um = lateral(model, normals)

    def _back(self, p, rng, u, splat_m: float, idx) -> np.ndarray:
        return p[idx] - widening(rng[idx], splat_m, self.step_rad)[:, None] * u[idx]

    def data_at(self, splat_m: float, idx=slice(None)) -> np.ndarray:
        return self._back(self.data, self.rd, self.ud, splat_m, idx)

    def model_at(self, splat_m: float, idx=slice(None)) -> np.ndarray:
        return self._back(self.model, self.rm, self.um, splat_m, idx)


def _widened(cloud: RefineCloud) -> Widened:
    """The cloud's :class:`Widened`, made once and kept on it."""
    got = cloud.cache.get("widened")
    if got is None:
        got = cloud.cache["widened"] = Widened(cloud.data, cloud.data_normals, cloud.model, cloud.normals,
                                               cloud.step_rad)
    return got


def corrected(cloud: RefineCloud, splat_m: float) -> RefineCloud:
    """``cloud`` with its data and model points moved back by the widening of splats of radius
    ``splat_m`` along their normals' part across their rays (normals unchanged); kept on the
    cloud for the scan's next pairs."""
    key = ("corrected", round(float(splat_m), 6))
    got = cloud.cache.get(key)
    if got is None:
        w = _widened(cloud)
        got = cloud.cache[key] = RefineCloud(data=w.data_at(splat_m), model=w.model_at(splat_m),
                                             normals=cloud.normals, data_normals=cloud.data_normals,
                                             step_rad=cloud.step_rad)
    return got


def one_way_fit(data_cloud: RefineCloud, model_cloud: RefineCloud, pose, splats, radius_m: float,
                max_points: int) -> np.ndarray:
    """Mean |point-to-plane distance| (m) of (at most ``max_points``) data points of
    ``data_cloud`` moved by ``pose`` onto ``model_cloud``'s model, for each splat radius in
    ``splats``: pairs found on the raw points (symmetric normals), distances between the points
    corrected for that radius."""
    w_data, w_model = _widened(data_cloud), _widened(model_cloud)
    r, t = pose4_to_matrix(pose)
    n = len(data_cloud.data)
    idx = np.arange(n) if n <= max_points else np.sort(np.random.default_rng(0).choice(n, max_points, replace=False))
    ok, j, nv = plane_pairs(model_cloud.grid, model_cloud.normals, data_cloud.data[idx] @ r.T + t, radius_m,
                            data_cloud.data_normals[idx] @ r.T)
    if not ok.any():
        return np.full(len(splats), np.nan)
    sel = idx[ok]
    out = []
    for s in splats:
        moved = w_data.data_at(s, sel) @ r.T + t
        out.append(float(np.abs((nv * (w_model.model_at(s, j) - moved)).sum(axis=1)).mean()))
    return np.array(out)


def choose_splat(scan: RefineCloud, ref: RefineCloud, pose, candidates, *, radius_m: float, normal_k: int,
                 min_gain: float, max_points: int = 4000) -> tuple[float, float]:
    """``(splat_m, gain)``: the candidate splat radius whose correction fits the pair best at
    ``pose`` (mean of both directions, :func:`one_way_fit`) and its relative gain over none;
    0 when no candidate gains ``min_gain``, or a scan's angular step is not known."""
    if not (scan.step_rad > 0 and ref.step_rad > 0) or not len(candidates):
        return 0.0, 0.0
    splats = np.r_[0.0, np.asarray(candidates, dtype=np.float64)]
    scan, ref = scan.with_data_normals(normal_k), ref.with_data_normals(normal_k)
    fwd = one_way_fit(scan, ref, pose, splats, radius_m, max_points)
    bwd = one_way_fit(ref, scan, invert_pose(pose), splats, radius_m, max_points)
    fit = 0.5 * (fwd + bwd)
    if not np.isfinite(fit).all() or fit[0] <= 0:
        return 0.0, 0.0
    best = int(np.argmin(fit))
    gain = float(1.0 - fit[best] / fit[0])
    return (float(splats[best]), gain) if best and gain >= min_gain else (0.0, gain)
