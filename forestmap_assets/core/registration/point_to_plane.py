"""Point-to-plane ICP for clouds without colour (inferred): 4-DoF (x, y, z, heading) Gauss-Newton
with optional Tukey IRLS and box clamp, and Open3D's point-to-plane ICP from a 4-DoF start."""

from __future__ import annotations

import numba
import numpy as np
from scipy.spatial import cKDTree

from forestmap_assets.core.radius_grid import RadiusGrid, nearest
from forestmap_assets.core.registration.hicp import matrix_to_pose4, pose4_to_matrix, project_box
from forestmap_assets.core.registration.icp_uncertainty import pose_jacobian

MIN_NORMAL_DOT = 0.5  # symmetric pairs: the two normals within 60 deg (the same side of a surface)


def _threads() -> int:
    """Threads of the k-d queries: this process's share of the cores, as its numba kernels have
    (one in each worker of a 2-core ``forestmap run``). All cores in every worker (scipy's
    ``workers=-1``) put four query threads on two cores: a rendered survey's refinements took
    9.4 s, 8.5 s with one thread each (issue 16)."""
    return max(1, numba.get_num_threads())


class Reach:
    """Which data points can still find a model point, so that an ICP queries only those
    (inferred, issue 16): the distance to a point set is 1-Lipschitz, so a point whose nearest
    model point was ``d0`` away at the positions ``base`` has none within ``r`` after moving by
    ``delta`` unless ``d0 <= r + delta``. Exact: the pairs are those of a full query. Most of a
    scan's thinned points have no partner in the other scan (on a Sylva survey 85 % within 5 cm,
    62 % within 10 cm), so each step queries 2.5-6 times fewer points (a refinement 1.04 ->
    0.72 s with the other changes of 747c212)."""

    def __init__(self, tree: cKDTree | RadiusGrid, base: np.ndarray, bound_m: float):
        self.base = np.asarray(base, dtype=np.float64)
        self.bound = float(bound_m)
        self.d0 = nearest(tree, self.base, self.bound, workers=_threads())[0]

    def candidates(self, moved: np.ndarray, radius_m: float) -> np.ndarray | None:
        """Indices of the points that may pair within ``radius_m`` at ``moved`` (None: any may,
        the points moved beyond what ``d0`` was measured for)."""
        delta = np.sqrt(((moved - self.base) ** 2).sum(axis=1))
        if radius_m + float(delta.max(initial=0.0)) >= self.bound:
            return None
        return np.flatnonzero(self.d0 <= radius_m + delta + 1e-9)


def plane_pairs(tree: cKDTree | RadiusGrid, normals: np.ndarray, moved: np.ndarray, radius_m: float,
                moved_normals: np.ndarray | None = None,
                reach: Reach | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Data points paired with their nearest model point within ``radius_m``: (mask of the
    paired data points, their model indices, the pairs' normals). Pairs without a model normal
    are left out.

    With ``moved_normals`` (the data points' normals, rotated with them) the pair's normal is
    the normalised sum of the two (the symmetric objective, Rusinkiewicz 2019): a pair of points
    of one circle has ``(m - p) . (n_p + n_m) = 0``, where the model's tangent plane alone puts
    the data point behind it by ``t^2 / 2R`` (t: their offset, R: the stem's radius), pulling
    the data toward the model's sensor, both ways: a contraction of every baseline by about
    0.1 mm a metre on exact clouds (issue 19, inferred). Pairs whose normals differ by more
    than 60 deg are left out. ``reach``: query only the points that may pair (:class:`Reach`)."""
    rows = None if reach is None else reach.candidates(moved, radius_m)
    d, idx = nearest(tree, moved, radius_m, rows, workers=_threads())
    ok = np.isfinite(d)
    ok[ok] &= np.isfinite(normals[idx[ok]]).all(axis=1)
    if moved_normals is not None:
        sel = np.flatnonzero(ok)
        ok[sel] = (normals[idx[sel]] * moved_normals[sel]).sum(axis=1) >= MIN_NORMAL_DOT
    nv = normals[idx[ok]]
    if moved_normals is not None:
        nv = nv + moved_normals[ok]
        nv /= np.linalg.norm(nv, axis=1, keepdims=True)
    return ok, idx[ok], nv


def plane_residuals(tree: cKDTree | RadiusGrid, normals: np.ndarray, moved: np.ndarray, radius_m: float,
                    moved_normals: np.ndarray | None = None, reach: Reach | None = None) -> np.ndarray:
    """Signed point-to-plane distances ``n . (m - p)`` of the moved data points to their nearest
    model point within ``radius_m`` (pairs and normals as :func:`plane_pairs`)."""
    ok, idx, nv = plane_pairs(tree, normals, moved, radius_m, moved_normals, reach)
    return (nv * (tree.data[idx] - moved[ok])).sum(axis=1)


def point_to_plane_4dof(
    model_xyz: np.ndarray,
    model_normals: np.ndarray,
    data_xyz: np.ndarray,
    init_pose,
    *,
    max_distance_m: float,
    iterations: int = 5,
    tree: cKDTree | RadiusGrid | None = None,
    box=None,
    tol: float = 1e-7,
    robust_k: float | None = None,
    data_normals: np.ndarray | None = None,
    reach: Reach | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """4-DoF point-to-plane Gauss-Newton ICP (x, y, z, heading): pose, final partner indices
    (-1 none) and iterations (inferred). With ``robust_k``, iteratively re-weighted least squares with Tukey's biweight at
    ``robust_k`` times the residuals' robust spread (1.4826 MAD), so that pairs of different
    surfaces within ``max_distance_m`` do not bias the pose (inferred). ``data_normals``: the
    symmetric objective (:func:`plane_pairs`); ``reach``: the pruned queries of :class:`Reach`
    (its ``base``: ``data`` moved by ``init_pose`` or any other positions)."""
    model = np.asarray(model_xyz, dtype=np.float64)
    normals = np.asarray(model_normals, dtype=np.float64)
    data = np.asarray(data_xyz, dtype=np.float64)
    tree = tree or cKDTree(model)
    pose = np.asarray(init_pose, dtype=np.float64).copy()
    partner = np.full(len(data), -1)
    fused = robust_k is None and isinstance(tree, RadiusGrid)  # least squares: one kernel a step
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007
        r, t = pose4_to_matrix(pose)
        if fused:
            a, b, n_pairs = _normal_equations(tree, model, normals, data, r, t, max_distance_m, data_normals,
                                              reach, partner)
            if n_pairs < 4:
                break
            delta = np.linalg.lstsq(a, b, rcond=None)[0]
            pose, done = _stepped(pose, t, delta, box, tol)
            if done:
                break
            continue
        moved = data @ r.T + t
        moved_n = None if data_normals is None else data_normals @ r.T
        ok, idx, nv = plane_pairs(tree, normals, moved, max_distance_m, moved_n, reach)
        partner = np.full(len(data), -1)
        partner[ok] = idx
        if ok.sum() < 4:
            break
        jn = np.einsum("ni,nid->nd", nv, pose_jacobian(moved[ok] - t, 4))
        res = (nv * (model[idx] - moved[ok])).sum(axis=1)
        if robust_k is not None:
            c = robust_k * max(1.4826 * float(np.median(np.abs(res - np.median(res)))), 1e-6)
            w = np.clip(1.0 - (res / c) ** 2, 0.0, None) ** 2
            jw = jn * w[:, None]
            delta = np.linalg.lstsq(jw.T @ jn, jw.T @ res, rcond=None)[0]
        else:
            delta = np.linalg.lstsq(jn.T @ jn, jn.T @ res, rcond=None)[0]
        pose, done = _stepped(pose, t, delta, box, tol)
        if done:
            break
    return pose, partner, it


def _stepped(pose: np.ndarray, t: np.ndarray, delta: np.ndarray, box, tol: float) -> tuple[np.ndarray, bool]:
    """The pose after a Gauss-Newton step ``delta`` (clamped into ``box``), and whether the step
    was below ``tol``. ``p(delta) = R_z(h + dh) d + t + dt``: the increments add to the pose
    (see ``pose_jacobian``)."""
    pose = np.array([*(t + delta[:3]), pose[3] + np.degrees(delta[3])])
    if box is not None:
        r2, t2, _ = project_box(*pose4_to_matrix(pose), box)
        pose = matrix_to_pose4(r2, t2)
    return pose, bool(np.abs(delta[:3]).max() < tol and abs(delta[3]) < tol)


def _normal_equations(grid: RadiusGrid, model: np.ndarray, normals: np.ndarray, data: np.ndarray, r: np.ndarray,
                      t: np.ndarray, radius_m: float, data_normals: np.ndarray | None, reach: Reach | None,
                      partner: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The least-squares step's normal equations ``(J^T J, J^T r, pairs)`` of :func:`plane_pairs`'
    pairs at ``r, t`` in one kernel (:func:`~._plane_step_kernels.plane_step`, issue 16); fills
    ``partner``."""
    from forestmap_assets.core.registration._plane_step_kernels import plane_step

    none = np.zeros((0, 3))
    dn = none if data_normals is None else np.ascontiguousarray(data_normals, dtype=np.float64)
    base, d0, bound = (none, np.zeros(0), np.inf) if reach is None else (reach.base, reach.d0, reach.bound)
    return plane_step(np.ascontiguousarray(data), np.ascontiguousarray(r), np.asarray(t, dtype=np.float64), dn,
                      MIN_NORMAL_DOT, base, np.asarray(d0, dtype=np.float64), float(bound), float(radius_m),
                      *grid.columns, np.ascontiguousarray(model), np.ascontiguousarray(normals), partner)


def open3d_point_to_plane(
    model_xyz: np.ndarray,
    data_xyz: np.ndarray,
    init_pose,
    *,
    max_distance_m: float,
    model_normals: np.ndarray | None = None,
    normal_radius_m: float = 0.3,
    max_iterations: int = 50,
    tukey_k_m: float | None = None,
) -> tuple[np.ndarray, int, float]:
    """Open3D point-to-plane ICP from a 4-DoF start; returns the 6-DoF matrix, Open3D's
    iteration-independent fitness count (pairs) and its inlier RMSE. ``tukey_k_m``: Open3D's
    Tukey robust kernel with that cut-off (metres); None: least squares."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    tgt = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(np.asarray(model_xyz, dtype=np.float64))
    )
    if model_normals is None:
        tgt.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_m, max_nn=30)
        )
    else:
        tgt.normals = o3d.utility.Vector3dVector(
            np.nan_to_num(np.asarray(model_normals, dtype=np.float64))
        )
    src = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(np.asarray(data_xyz, dtype=np.float64))
    )
    r, t = pose4_to_matrix(init_pose)
    init = np.eye(4)
    init[:3, :3], init[:3, 3] = r, t
    estimation = (
        reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=tukey_k_m))
        if tukey_k_m
        else reg.TransformationEstimationPointToPlane()
    )
    res = reg.registration_icp(
        src,
        tgt,
        max_distance_m,
        init,
        estimation,
        reg.ICPConvergenceCriteria(max_iteration=max_iterations),
    )
    return np.asarray(res.transformation), len(res.correspondence_set), float(res.inlier_rmse)
