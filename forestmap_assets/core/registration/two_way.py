"""Fine registration guarded by its own fit (forestmap's step beyond Men 2012 spec 5; inferred).

The branch-and-bound pose of a pair comes from stem centres, which the shapes of real stems
(out-of-round, rough, seen from one side) can bias by centimetres, and its sigma does not know
it. The raw points see the same bark from both scans, so the refinement is allowed to move as far
as the points say, inside a generous trust region (``max_shift_m``, ``max_turn_deg``: beyond it
the nearest-point pairs belong to other surfaces), and its result is accepted on evidence of its
own fit rather than because it stays within a box of the coarse sigma:

1. **both directions**: the scan is registered onto the reference and the reference onto the
   scan, each by 4-DoF point-to-plane Gauss-Newton (:func:`~.point_to_plane.point_to_plane_4dof`)
   from the branch-and-bound pose, coarse to fine (association radii ``two_way_radii_m``,
   ``two_way_iterations`` steps). Least squares, not Tukey: within 5 cm the far side of a stem
   has no partner, and on noisy clouds (2 cm, Sylva's simulator) the re-scaled Tukey weights
   kept the pose wandering (measured: errors grew from 11 to 53 mm on one pair). The two
   results must agree within ``agree_m`` / ``agree_deg`` or ``agree_sigmas`` of their own sigma,
   whichever is larger;
2. **overlap**: the number of point pairs within the fine radius must not fall below
   ``min_pairs`` nor below ``min_overlap_kept`` of its value at the branch-and-bound pose;
3. **residuals**: the mean point-to-plane distance of both directions together (within the fine
   radius) must not be worse than at the branch-and-bound pose by more than ``max_fit_loss``
   (relative; the least-squares step does not minimise that mean, so a refinement that moved
   the right way can end up slightly "worse": the measured margin is at the parameter).

Each pair's normal is the normalised sum of the two points' normals (``symmetric``; the
symmetric objective of Rusinkiewicz 2019, :func:`~.point_to_plane.plane_pairs`): with the model's
normal alone, bark seen from one side pulled every scan toward the other, about 0.1 mm a metre
of baseline on exact clouds and twice that at 2.5 cm range noise (issue 19). A wide first-return
beam's widened silhouettes, which the sum follows, are left out of the clouds first
(:mod:`~forestmap_assets.core.registration.mixed_pixels`).

The pose used is the mean of the two directions. Its sigma is
``two_way_sd_scale x sqrt(H^2 + (d / 2)^2 + beam^2)``, floored: ``H`` the larger Gauss-Newton
Hessian sd of the two directions (inflated for correlated neighbours), ``d`` their disagreement,
``beam`` what a wide first-return beam adds (:func:`beam_sd`; zero unless the campaign's sensor
names its beam). Per-scan clouds (voxel-thinned data with normals, model with normals and radius
grid) are prepared once and shared by all pairs of the scan (:class:`RefineCloud`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import pyarrow as pa
from scipy.spatial import cKDTree

from forestmap_assets.core._cloud_kernels import bounds
from forestmap_assets.core.cloud import pca_normals, voxel_subsample, z_order
from forestmap_assets.core.geometry import wrap_deg
from forestmap_assets.core.radius_grid import RadiusGrid
from forestmap_assets.core.registration.hicp import matrix_to_pose4, pose4_to_matrix
from forestmap_assets.core.registration.icp_uncertainty import icp_covariance, pose_sd
from forestmap_assets.core.registration.point_to_plane import (
    Reach,
    plane_pairs,
    plane_residuals,
    point_to_plane_4dof,
)
from forestmap_assets.params.men import RefineSettings

# how far (m) beyond the coarse radius the start pose's nearest distances are measured: the
# pruned queries (point_to_plane.Reach) hold while the points move less than this
REACH_MARGIN_M = 0.05
# the columns of the model's radius grid: about the largest radius it is queried with (Reach's,
# the coarse radius 0.1 m plus the margin); any radius gives the same pairs, this one is fastest
GRID_CELL_M = 0.15

@dataclass
class RefineCloud:
    """One scan's points for the refinement: ``data`` (voxel ``data_voxel_m``, at most
    ``max_data_points``), ``model`` (voxel ``two_way_model_voxel_m``) with normals (oriented to
    the sensor), its radius ``grid`` for the pairs and k-d ``tree`` for the neighbours of
    normals (each built on first use: the per-scan asset only stores the points)."""

    data: np.ndarray
    model: np.ndarray
    normals: np.ndarray
    data_normals: np.ndarray | None = None  # of the data points (symmetric objective)
    step_rad: float = float("nan")  # the scan's angular step (splat_widening); NaN: not known
    cache: dict = field(default_factory=dict, repr=False, compare=False)  # what a worker keeps for next pairs
    _tree: cKDTree | None = field(default=None, repr=False, compare=False)
    _grid: RadiusGrid | None = field(default=None, repr=False, compare=False)
    _box: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    @property
    def tree(self) -> cKDTree:
        if self._tree is None:  # sliding-midpoint, not compacted: built in half the time, queried as fast
            self._tree = cKDTree(self.model, balanced_tree=False, compact_nodes=False)
        return self._tree

    @property
    def grid(self) -> RadiusGrid:
        """The model points' :class:`~forestmap_assets.core.radius_grid.RadiusGrid` (the pairs'
        nearest points, 2-3.5 times faster than :attr:`tree`), built on first use."""
        if self._grid is None:
            self._grid = RadiusGrid(self.model, GRID_CELL_M)
        return self._grid

    @property
    def model_box(self) -> tuple[np.ndarray, np.ndarray]:
        """The model's bounding box (lower, upper corner), computed once."""
        if self._box is None:
            lo, hi, finite = bounds(self.model) if len(self.model) else (None, None, False)
            self._box = (lo, hi) if finite else (self.model.min(axis=0), self.model.max(axis=0))
        return self._box

    def with_data_normals(self, k: int) -> RefineCloud:
        """This cloud with :attr:`data_normals` (computed from the model if absent)."""
        if self.data_normals is None:
            self.data_normals = pca_normals(self.model, k, tree=self.tree, at=self.data)[0]
        return self

    @classmethod
    def from_points(cls, xyz: np.ndarray, s: RefineSettings, step_rad: float = float("nan")) -> RefineCloud:
        """The cloud of a scan's levelled points ``xyz`` (n, 3): cropped (:func:`crop_mask`),
        voxel-thinned to the model and data points, the model's normals (spec 3.2-3.3)."""
        p = np.asarray(xyz, dtype=np.float64)
        return cls._from_cropped(p[crop_mask(p, s)], s, step_rad)

    @classmethod
    def from_columns(cls, x: np.ndarray, y: np.ndarray, z: np.ndarray, s: RefineSettings,
                     step_rad: float = float("nan")) -> RefineCloud:
        """:meth:`from_points` of the columns of a stored range image (float32), cropped in one
        pass (:func:`~forestmap_assets.core._cloud_kernels.cropped_points`: the same points
        without the float64 copy of the whole scan, 0.05 s of a 2.3 M-point scan, issue 16)."""
        from forestmap_assets.core._cloud_kernels import cropped_points

        lo, hi = s.z_band_m
        p = cropped_points(np.ascontiguousarray(x), np.ascontiguousarray(y), np.ascontiguousarray(z),
                           float(s.max_range_m), float(lo), float(hi))
        return cls._from_cropped(p, s, step_rad)

    @classmethod
    def _from_cropped(cls, p: np.ndarray, s: RefineSettings, step_rad: float) -> RefineCloud:
        model = p[voxel_subsample(p, s.two_way_model_voxel_m)] if s.two_way_model_voxel_m and len(p) else p
        normals = sensor_normals(model, s.normal_k)
        # data voxels at least as coarse as the model's: thinned from the model, whose normals
        # they keep (each is its own nearest model point, so the same k neighbours): one voxel
        # pass over the full cloud and one normal estimate fewer (issue 16, 0.3 s a 2 M-point scan)
        nested = 0 < s.two_way_model_voxel_m <= s.data_voxel_m
        src, src_normals = (model, normals) if nested else (p, None)
        keep = voxel_subsample(src, s.data_voxel_m) if s.data_voxel_m and len(src) else np.arange(len(src))
        if s.max_data_points and len(keep) > s.max_data_points:  # a fixed, seeded thinning
            keep = keep[np.sort(np.random.default_rng(0).choice(len(keep), s.max_data_points, replace=False))]
        cloud = cls(data=src[keep], model=model, normals=normals, step_rad=float(step_rad),
                    data_normals=None if src_normals is None else src_normals[keep])
        return cloud.with_data_normals(s.normal_k) if s.symmetric else cloud

    def to_table(self, colour: bool = False) -> pd.DataFrame:
        """One row per point: ``x, y, z``, ``nx, ny, nz`` (NaN for data points without normals),
        ``role`` ``data`` or ``model``; ``colour``: whether the scan has colour (the pair's
        method depends on it); ``step_rad``: the scan's angular step."""
        n = np.full((len(self.data), 3), np.nan) if self.data_normals is None else self.data_normals
        xyz = np.vstack([self.data, self.model])
        normals = np.vstack([n, self.normals])
        return pd.DataFrame({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "nx": normals[:, 0],
                             "ny": normals[:, 1], "nz": normals[:, 2],
                             "role": _roles(len(self.data), len(self.model)), "colour": bool(colour),
                             "step_rad": float(self.step_rad)})

    @classmethod
    def from_table(cls, table: pd.DataFrame) -> RefineCloud:
        model = np.asarray(table["role"].array == "model", dtype=bool)  # Arrow's compare: 31 -> 3 ms
        xyz = table[["x", "y", "z"]].to_numpy(np.float64)
        normals = table[["nx", "ny", "nz"]].to_numpy(np.float64)
        data_normals = normals[~model] if np.isfinite(normals[~model]).any() else None
        step = float(table["step_rad"].iloc[0]) if "step_rad" in table and len(table) else float("nan")
        return cls(data=xyz[~model], model=xyz[model], normals=normals[model], data_normals=data_normals,
                   step_rad=step)


def _roles(n_data: int, n_model: int) -> pd.Series:
    """The ``role`` column, ``n_data`` times ``data`` then ``n_model`` times ``model``; built in
    Arrow where pandas keeps its strings there (its conversion of a numpy string array took
    20 ms a scan), with pandas' dtype and buffers (no validity bitmap), so the table and its
    data version are unchanged."""
    dtype = pd.Series(["data"]).dtype
    if not (isinstance(dtype, pd.StringDtype) and dtype.storage == "pyarrow"):
        return pd.Series(np.repeat(["data", "model"], [n_data, n_model]))
    arr = pa.array(["data", "model"], pa.large_string()).take(np.repeat(np.int8([0, 1]), [n_data, n_model]))
    return pd.Series(pa.LargeStringArray.from_buffers(len(arr), arr.buffers()[1], arr.buffers()[2]), dtype=dtype)


def crop_mask(points: np.ndarray, s: RefineSettings) -> np.ndarray:
    """Points within ``max_range_m`` of the sensor and in its height band ``z_band_m`` (drops
    the noisy, porous canopy, spec 10)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    return (np.sqrt(x * x + y * y) <= s.max_range_m) & (z >= s.z_band_m[0]) & (z <= s.z_band_m[1])


def sensor_normals(points: np.ndarray, k: int) -> np.ndarray:
    """Unit normals of the ``k`` nearest neighbours' plane (spec 3.3), oriented toward the sensor
    at the origin; Open3D's multi-threaded estimate (the numpy PCA of
    :func:`~forestmap_assets.core.cloud.pca_normals` took 7 s on a 355 k-point model), fed the
    points in :func:`~forestmap_assets.core.cloud.z_order`, so that successive searches walk the
    same k-d tree nodes (up to a quarter less CPU than in scan order; the same neighbours, so the
    same normals)."""
    import open3d as o3d

    p = np.asarray(points, dtype=np.float64)
    if len(p) < 3:
        return np.full((len(p), 3), np.nan)
    order = z_order(p)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p[order]))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(int(k)))
    n = np.empty_like(p)
    n[order] = np.asarray(pc.normals)
    flip = (n * p).sum(axis=1) > 0  # n . (0 - p) < 0: facing away from the sensor
    n[flip] *= -1.0
    return n


def invert_pose(pose) -> np.ndarray:
    """The 4-DoF pose of the reference in the scan's frame, from the scan's in the reference's."""
    r, t = pose4_to_matrix(pose)
    return matrix_to_pose4(r.T, -r.T @ t)


def _overlap(data: np.ndarray, box: tuple[np.ndarray, np.ndarray], pose, margin: float) -> np.ndarray:
    """Data points that, moved by ``pose``, fall in the model's bounding ``box`` grown by ``margin``."""
    r, t = pose4_to_matrix(pose)
    moved = data @ r.T + t
    return np.all((moved >= box[0] - margin) & (moved <= box[1] + margin), axis=1)


@dataclass
class _Way:
    pose: np.ndarray
    sd: np.ndarray
    fit_start: float
    fit_end: float
    pairs_start: int
    pairs_end: int
    iterations: int
    range_m: float  # median range of the paired data points from their own sensor
    centre: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))  # of the paired data points


def _one_way(data_cloud: RefineCloud, model_cloud: RefineCloud, pose, s: RefineSettings,
             pose_only: bool = False) -> _Way | None:
    """Robust 4-DoF point-to-plane of ``data_cloud``'s data onto ``model_cloud``'s model
    (``pose_only``: without the fits and the Hessian sigma)."""
    pose = np.asarray(pose, dtype=np.float64)
    if len(data_cloud.data) == 0 or len(model_cloud.model) == 0:
        return None
    keep = _overlap(data_cloud.data, model_cloud.model_box, pose, s.overlap_margin_m)
    data = data_cloud.data[keep]
    if len(data) < s.min_pairs:
        return None
    dn = data_cloud.with_data_normals(s.normal_k).data_normals[keep] if s.symmetric else None
    r0, t0 = pose4_to_matrix(pose)
    fine = s.two_way_radii_m[-1]
    tree, normals = model_cloud.grid, model_cloud.normals
    reach = Reach(tree, data @ r0.T + t0, max(s.two_way_radii_m) + REACH_MARGIN_M)
    start_res = plane_residuals(tree, normals, reach.base, fine, None if dn is None else dn @ r0.T, reach)
    if len(start_res) < s.min_pairs:
        return None
    box = (pose, np.array([s.max_shift_m, s.max_shift_m, s.max_shift_m, s.max_turn_deg]))
    new, its = pose, 0
    for radius, steps in zip(s.two_way_radii_m, s.two_way_iterations, strict=True):  # coarse to fine
        new, _, k = point_to_plane_4dof(model_cloud.model, normals, data, new, max_distance_m=radius,
                                        iterations=steps, tree=tree, box=box, tol=s.plane_tol,
                                        data_normals=dn, reach=reach)
        its += k
    new[3] = wrap_deg(new[3])
    if pose_only:
        return _Way(pose=new, sd=np.full(4, np.nan), fit_start=np.nan, fit_end=np.nan, pairs_start=len(start_res),
                    pairs_end=0, iterations=its, range_m=np.nan)
    r1, t1 = pose4_to_matrix(new)
    moved = data @ r1.T + t1
    ok, idx, nv = plane_pairs(tree, normals, moved, fine, None if dn is None else dn @ r1.T, reach)
    end_res = (nv * (model_cloud.model[idx] - moved[ok])).sum(axis=1)  # as plane_residuals
    fit_end = float(np.abs(end_res).mean()) if len(end_res) else np.nan
    cov = icp_covariance(moved[ok], model_cloud.model[idx], t1, normals=nv, dof=4,
                         correlation_m=s.correlation_m)
    rng = float(np.median(np.linalg.norm(data[ok], axis=1))) if ok.any() else np.nan
    centre = data[ok].mean(axis=0) if ok.any() else np.full(3, np.nan)
    return _Way(pose=new, sd=pose_sd(cov), fit_start=float(np.abs(start_res).mean()), fit_end=fit_end,
                pairs_start=len(start_res), pairs_end=len(end_res), iterations=its, range_m=rng, centre=centre)


def beam_sd(ways: list[_Way], s: RefineSettings) -> np.ndarray:
    """The sigma (x, y, z m, heading deg) a wide beam adds (inferred, issue 19): a footprint
    that touches a nearer object returns its range, so each scan sees the stems' silhouettes
    widened by up to a footprint, differently from each side, and the raw points carry a
    view-dependent bias no residual shows. ``beam_sd_share`` of the footprint diameter
    ``beam_exit_m + beam_divergence_mrad * r`` at the pairs' median range r (the heading: that
    over r). Zero for a beam of no width (a campaign's ``sensor`` gives its beam)."""
    r = float(np.nanmax([w.range_m for w in ways]))
    foot = s.beam_exit_m + 1e-3 * s.beam_divergence_mrad * r
    if not foot > 0 or not np.isfinite(r) or r <= 0:
        return np.zeros(4)
    c = np.asarray(s.beam_sd_share, dtype=np.float64)
    return np.array([c[0] * foot, c[1] * foot, c[2] * foot, np.degrees(c[3] * foot / r)])


def objective_spread(scan: RefineCloud, ref: RefineCloud, pose, s: RefineSettings) -> float:
    """How much longer (m, signed) the pair's baseline is in a symmetric refinement's pose
    ``pose`` than with the model's normal alone (inferred, issue 19): the forward way refined
    again from ``pose`` with the objective of Men 2012 at the finest radius, the difference
    along the unit baseline ``u``. Where the points see the same surfaces from both sides the
    two objectives agree; where silhouettes are widened (a wide beam's mixed pixels, a rendered
    cloud's splats) the symmetric one lengthens the baseline and the model's normal shortens
    it (scans rendered inside a registered cloud: +4.3 and +0.7 mm over 14 links). Neither
    direction's agreement sees that, so with ``objective_sd_scope="link"`` it becomes the
    link's sigma along the baseline, ``|d| (|u_x|, |u_y|)``; with ``"campaign"`` the optimal
    map takes its systematic part over all links
    (:func:`~forestmap_assets.core.mapping.objective_scale.objective_scale`); NaN when the
    model-normal way finds too few pairs."""
    u = np.array(pose[:2], dtype=np.float64)  # a copy: pose stays
    length = float(np.hypot(*u))
    if length <= 0:
        return 0.0
    one = dataclasses.replace(s, symmetric=False, two_way_radii_m=(s.two_way_radii_m[-1],),
                              two_way_iterations=(s.two_way_iterations[-1],))
    alt = _one_way(scan, ref, pose, one, pose_only=True)
    if alt is None:
        return float("nan")
    u /= length
    return -float(np.dot(alt.pose[:2] - np.asarray(pose[:2], dtype=np.float64), u))


def heading_gap_sigmas(refined, sd_refined, bnb, sd_bnb) -> float:
    """How many sigmas of their difference the refined and the branch-and-bound headings lie
    apart (NaN where a sigma is missing or not positive)."""
    sr, sb = float(np.asarray(sd_refined, dtype=np.float64)[3]), float(np.asarray(sd_bnb, dtype=np.float64)[3])
    if not (np.isfinite(sr) and np.isfinite(sb) and sr > 0 and sb > 0):
        return float("nan")
    return abs(wrap_deg(float(bnb[3]) - float(refined[3]))) / float(np.hypot(sr, sb))


def fuse_heading(refined, sd_refined, bnb, sd_bnb, centre,
                 agree_sigmas: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """The refined pose with the inverse-variance mean of its heading and the branch-and-bound
    one (inferred, issue 17, 19; ``RefineSettings.heading_from``), and its sigmas (heading
    ``(1/sd_r^2 + 1/sd_b^2)^-1/2``). The heading turns the scan about its sensor; the
    translation follows so that ``centre`` (the paired data points' mean, the scan's frame) stays
    where the refinement put it: the overlap fixes where those points are, not the lever arm to
    the sensor. Unchanged where a sigma is missing or the headings differ by more than
    ``agree_sigmas`` sigmas of their difference (:func:`heading_gap_sigmas`; the refinement is
    then not used at all, :func:`~.refine.refine_pair_two_way`)."""
    refined = np.asarray(refined, dtype=np.float64).copy()
    sd = np.asarray(sd_refined, dtype=np.float64).copy()
    if not (heading_gap_sigmas(refined, sd, bnb, sd_bnb) <= agree_sigmas and np.all(np.isfinite(centre))):
        return refined, sd
    sr, sb = sd[3], float(sd_bnb[3])
    gap = wrap_deg(float(bnb[3]) - refined[3])
    heading = refined[3] + sr**2 / (sr**2 + sb**2) * gap
    r0, t0 = pose4_to_matrix(refined)
    r1, _ = pose4_to_matrix(np.r_[refined[:3], heading])
    refined[:3] = t0 + (r0 - r1) @ np.asarray(centre, dtype=np.float64)
    refined[3] = wrap_deg(heading)
    sd[3] = (sr**-2 + sb**-2) ** -0.5
    return refined, sd


def two_way_refine(scan: RefineCloud, ref: RefineCloud, pose, s: RefineSettings, spread: bool = True) -> dict:
    """Refine the pose of ``scan`` in ``ref``'s frame both ways and test the result (module doc).
    Returns ``pose``, ``sd``, ``used`` (bool), ``reason``, the fits and pair counts, and the
    disagreement of the two directions ``disagree`` (x, y, z m, heading deg). ``spread=False``
    leaves out :func:`objective_spread` (one more refinement; nothing else depends on it) for
    :func:`with_objective_spread` to add once the result is known to be kept."""
    pose = np.asarray(pose, dtype=np.float64)
    out = {"pose": pose, "sd": np.full(4, np.nan), "used": False, "reason": "", "spread_along": np.nan,
           "centre": np.full(3, np.nan), "forward": None,
           "fit_bnb_m": np.nan,
           "fit_refined_m": np.nan, "pairs_bnb": 0, "pairs_refined": 0, "iterations": 0,
           "disagree": np.full(4, np.nan), "n_data": len(scan.data), "n_model": len(ref.model)}
    fwd = _one_way(scan, ref, pose, s)
    back = _one_way(ref, scan, invert_pose(pose), s) if s.two_way else None
    if fwd is None or (s.two_way and back is None):
        out["reason"] = "too little overlap of the raw points"
        return out
    ways = [fwd] + ([back] if back else [])
    poses = [fwd.pose] + ([invert_pose(back.pose)] if back else [])
    diff = np.r_[poses[0][:3] - poses[-1][:3], wrap_deg(poses[0][3] - poses[-1][3])]
    mean = np.r_[(poses[0][:3] + poses[-1][:3]) / 2, wrap_deg(poses[-1][3] + diff[3] / 2)]
    hess = np.nan_to_num(np.nanmax([w.sd for w in ways], axis=0), nan=np.inf)
    sd = np.asarray(s.two_way_sd_scale) * np.sqrt(hess**2 + (diff / 2) ** 2 + beam_sd(ways, s) ** 2)
    sd = np.maximum(sd, s.two_way_sd_floor)
    fit_b = float(np.mean([w.fit_start for w in ways]))
    fit_r = float(np.mean([w.fit_end for w in ways]))
    pairs_b, pairs_r = sum(w.pairs_start for w in ways), sum(w.pairs_end for w in ways)
    out.update(pose=mean, sd=sd, fit_bnb_m=fit_b, fit_refined_m=fit_r, pairs_bnb=pairs_b, pairs_refined=pairs_r,
               iterations=sum(w.iterations for w in ways), disagree=diff, centre=fwd.centre, forward=fwd.pose)
    if spread:
        with_objective_spread(out, scan, ref, s)
    moved = np.abs(np.r_[mean[:3] - pose[:3], wrap_deg(mean[3] - pose[3])])
    tol = np.maximum(np.r_[s.agree_m, s.agree_m, s.agree_m, s.agree_deg], s.agree_sigmas * s.sd_inflation * hess)
    if np.any(moved[:3] >= s.max_shift_m * (1 - 1e-6)) or moved[3] >= s.max_turn_deg * (1 - 1e-6):
        out["reason"] = (f"refinement moved to the edge of its trust region ({100 * s.max_shift_m:g} cm, "
                         f"{s.max_turn_deg:g} deg): another surface pulled it")
    elif min(w.pairs_end for w in ways) < s.min_pairs:
        out["reason"] = f"only {min(w.pairs_end for w in ways)} point pairs after refinement"
    elif pairs_r < s.min_overlap_kept * pairs_b:
        out["reason"] = f"overlap fell from {pairs_b} to {pairs_r} point pairs"
    elif not fit_r <= fit_b * (1.0 + s.max_fit_loss):
        out["reason"] = f"fit worse ({fit_r * 1000:.3f} mm vs {fit_b * 1000:.3f} mm)"
    elif np.any(np.abs(diff) > tol):
        out["reason"] = ("the two directions disagree by "
                         f"{100 * np.hypot(diff[0], diff[1]):.1f} cm xy, {100 * abs(diff[2]):.1f} cm z, "
                         f"{abs(diff[3]):.3f} deg")
    else:
        out["used"] = True
    return out


def with_objective_spread(out: dict, scan: RefineCloud, ref: RefineCloud, s: RefineSettings) -> dict:
    """``out`` of :func:`two_way_refine` with its ``spread_along`` (:func:`objective_spread` from
    the forward direction's pose) and, with ``objective_sd_scope="link"``, that spread in its x, y
    sigmas; unchanged where the refinement found too little overlap."""
    if out["forward"] is None:
        return out
    spread = objective_spread(scan, ref, out["forward"], s) if s.symmetric and s.objective_sd else np.nan
    if s.objective_sd_scope == "link" and np.isfinite(spread):
        sd, mean = out["sd"], out["pose"]
        sd[:2] = np.hypot(sd[:2], abs(spread) * np.abs(mean[:2]) / max(float(np.hypot(*mean[:2])), 1e-12))
    out["spread_along"] = spread
    return out
