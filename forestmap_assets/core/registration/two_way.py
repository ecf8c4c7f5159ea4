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
   (relative; at the noise floor the two differ by a few hundredths of a millimetre).

The pose used is the mean of the two directions; its sigma combines the Gauss-Newton Hessian
(inflated for correlated neighbours, times ``sd_inflation``) with half the disagreement of the two
directions, scaled per axis by ``two_way_sd_scale`` (fitted on simulated surveys with realistic
stems, where bark relief and one-sided views bias both directions alike), then floors. Per-scan clouds (voxel-thinned data and model, model normals and k-d
tree) are prepared once and shared by all pairs of the scan (:class:`RefineCloud`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import pyarrow as pa
from scipy.spatial import cKDTree

from forestmap_assets.core.cloud import voxel_subsample, z_order
from forestmap_assets.core.geometry import wrap_deg
from forestmap_assets.core.registration.hicp import matrix_to_pose4, pose4_to_matrix
from forestmap_assets.core.registration.icp_uncertainty import icp_covariance, pose_sd
from forestmap_assets.core.registration.point_to_plane import plane_residuals, point_to_plane_4dof
from forestmap_assets.params.men import RefineSettings


@dataclass
class RefineCloud:
    """One scan's points for the refinement: ``data`` (voxel ``data_voxel_m``, at most
    ``max_data_points``), ``model`` (voxel ``two_way_model_voxel_m``) with normals (oriented to
    the sensor) and its k-d ``tree`` (built on first use: the per-scan asset only stores the
    points)."""

    data: np.ndarray
    model: np.ndarray
    normals: np.ndarray
    _tree: cKDTree | None = field(default=None, repr=False, compare=False)

    @property
    def tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.model)
        return self._tree

    @classmethod
    def from_points(cls, xyz: np.ndarray, s: RefineSettings) -> RefineCloud:
        p = np.asarray(xyz, dtype=np.float64)
        p = p[crop_mask(p, s)]
        model = p[voxel_subsample(p, s.two_way_model_voxel_m)] if s.two_way_model_voxel_m and len(p) else p
        data = p[voxel_subsample(p, s.data_voxel_m)] if s.data_voxel_m and len(p) else p
        if s.max_data_points and len(data) > s.max_data_points:  # a fixed, seeded thinning
            data = data[np.sort(np.random.default_rng(0).choice(len(data), s.max_data_points, replace=False))]
        return cls(data=data, model=model, normals=sensor_normals(model, s.normal_k))

    def to_table(self, colour: bool = False) -> pd.DataFrame:
        """One row per point: ``x, y, z`` (and ``nx, ny, nz`` for the model), ``role`` ``data``
        or ``model``; ``colour``: whether the scan has colour (the pair's method depends on it)."""
        n = np.full((len(self.data), 3), np.nan)
        xyz = np.vstack([self.data, self.model])
        normals = np.vstack([n, self.normals])
        return pd.DataFrame({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "nx": normals[:, 0],
                             "ny": normals[:, 1], "nz": normals[:, 2],
                             "role": _roles(len(self.data), len(self.model)), "colour": bool(colour)})

    @classmethod
    def from_table(cls, table: pd.DataFrame) -> RefineCloud:
        model = table["role"].to_numpy() == "model"
        xyz = table[["x", "y", "z"]].to_numpy(np.float64)
        return cls(data=xyz[~model], model=xyz[model], normals=table.loc[model, ["nx", "ny", "nz"]].to_numpy(np.float64))


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


def _overlap(data: np.ndarray, model: np.ndarray, pose, margin: float) -> np.ndarray:
    """Data points that, moved by ``pose``, fall in the model's bounding box grown by ``margin``."""
    r, t = pose4_to_matrix(pose)
    moved = data @ r.T + t
    return np.all((moved >= model.min(axis=0) - margin) & (moved <= model.max(axis=0) + margin), axis=1)


@dataclass
class _Way:
    pose: np.ndarray
    sd: np.ndarray
    fit_start: float
    fit_end: float
    pairs_start: int
    pairs_end: int
    iterations: int


def _one_way(data_cloud: RefineCloud, model_cloud: RefineCloud, pose, s: RefineSettings) -> _Way | None:
    """Robust 4-DoF point-to-plane of ``data_cloud``'s data onto ``model_cloud``'s model."""
    pose = np.asarray(pose, dtype=np.float64)
    if len(data_cloud.data) == 0 or len(model_cloud.model) == 0:
        return None
    data = data_cloud.data[_overlap(data_cloud.data, model_cloud.model, pose, s.overlap_margin_m)]
    if len(data) < s.min_pairs:
        return None
    r0, t0 = pose4_to_matrix(pose)
    fine = s.two_way_radii_m[-1]
    start_res = plane_residuals(model_cloud.tree, model_cloud.normals, data @ r0.T + t0, fine)
    if len(start_res) < s.min_pairs:
        return None
    fit_start = float(np.abs(start_res).mean())
    box = (pose, np.array([s.max_shift_m, s.max_shift_m, s.max_shift_m, s.max_turn_deg]))
    new, its = pose, 0
    for radius, steps in zip(s.two_way_radii_m, s.two_way_iterations, strict=True):  # coarse to fine
        new, _, k = point_to_plane_4dof(model_cloud.model, model_cloud.normals, data, new, max_distance_m=radius,
                                        iterations=steps, tree=model_cloud.tree, box=box, tol=s.plane_tol)
        its += k
    new[3] = wrap_deg(new[3])
    r1, t1 = pose4_to_matrix(new)
    moved = data @ r1.T + t1
    end_res = plane_residuals(model_cloud.tree, model_cloud.normals, moved, fine)
    fit_end = float(np.abs(end_res).mean()) if len(end_res) else np.nan
    dist, idx = model_cloud.tree.query(moved, distance_upper_bound=fine)
    ok = np.isfinite(dist)
    cov = icp_covariance(moved[ok], model_cloud.model[idx[ok]], t1, normals=model_cloud.normals[idx[ok]], dof=4,
                         correlation_m=s.correlation_m)
    return _Way(pose=new, sd=pose_sd(cov), fit_start=fit_start, fit_end=fit_end, pairs_start=len(start_res),
                pairs_end=len(end_res), iterations=its)


def two_way_refine(scan: RefineCloud, ref: RefineCloud, pose, s: RefineSettings) -> dict:
    """Refine the pose of ``scan`` in ``ref``'s frame both ways and test the result (module doc).
    Returns ``pose``, ``sd``, ``used`` (bool), ``reason``, the fits and pair counts, and the
    disagreement of the two directions ``disagree`` (x, y, z m, heading deg)."""
    pose = np.asarray(pose, dtype=np.float64)
    out = {"pose": pose, "sd": np.full(4, np.nan), "used": False, "reason": "", "fit_bnb_m": np.nan,
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
    hess = s.sd_inflation * np.nanmax([w.sd for w in ways], axis=0)
    sd = np.asarray(s.two_way_sd_scale) * np.sqrt(np.nan_to_num(hess, nan=np.inf) ** 2 + (diff / 2) ** 2)
    sd = np.maximum(sd, [s.sd_floor_m, s.sd_floor_m, s.sd_floor_z_m, s.two_way_sd_floor_deg])
    fit_b = float(np.mean([w.fit_start for w in ways]))
    fit_r = float(np.mean([w.fit_end for w in ways]))
    pairs_b, pairs_r = sum(w.pairs_start for w in ways), sum(w.pairs_end for w in ways)
    out.update(pose=mean, sd=sd, fit_bnb_m=fit_b, fit_refined_m=fit_r, pairs_bnb=pairs_b, pairs_refined=pairs_r,
               iterations=sum(w.iterations for w in ways), disagree=diff)
    moved = np.abs(np.r_[mean[:3] - pose[:3], wrap_deg(mean[3] - pose[3])])
    tol = np.maximum(np.r_[s.agree_m, s.agree_m, s.agree_m, s.agree_deg], s.agree_sigmas * hess)
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
