"""Hue-assisted ICP (HICP) and plain 3-D ICP as one algorithm (men spec 5, checklist 13-17).

Data cloud D (moved) is registered to model cloud M (fixed) by point-to-point ICP (Eq. 5.1)
whose nearest-neighbour association runs in a 4-D space (spec 5.2-5.3)::

    e(p, h) = ((p - o) / s, w * h)          o, s: one shared offset and scale for both clouds

* **Shared scale** (spec 5.2, "faithful-but-sound"): the thesis's three descriptions conflict;
  one offset ``o`` and one scale ``s`` come from the model's bounding box (or the union of both
  boxes) and are applied to both clouds, only for the association metric. ``scale="per_axis"``
  (s = box extents, thesis 5.8) or ``"isotropic"`` (s = the largest extent); which one was used
  is recorded in :class:`Embedding`.
* **Association** (spec 5.3): a k-d tree over the model's embedded points, built **once** (hue
  does not change under the rigid transform, so only x, y, z of D are moved); each moved data
  point takes its nearest model point within the fixed radius ``r`` (1-NN with an upper bound),
  else stays unassociated. The radius gate is the only rejection; many-to-one is allowed.
  Default ``r``: median distance to the 50th-nearest 4-D neighbour over a model sample (spec
  5.3, inferred rule).
* **Transform** (spec 5.4, corrected convention of Appendix A): ``K = sum d' m'^T = U S V^T``,
  ``R = V diag(1, 1, det(V U^T)) U^T`` (reflection guard), ``T = m_bar - R d_bar``, solved in
  metric coordinates from the original data points to their current partners (equivalent to
  composing increments). ``dof=4`` restricts R to a rotation about z (levelled scans, forsman
  spec 6.1): closed form ``theta = atan2(sum (d'_x m'_y - d'_y m'_x), sum (d'_x m'_x + d'_y m'_y))``.
* **Convergence** (spec 5.5): per iteration the mean association distance ``eps`` (Eq. 5.5, in
  normalised units), the number of pairs ``N`` and the association stability ``S`` (data points
  whose partner changed, gained or lost). Stop when ``|d eps| < tol_error``, ``|d N| <=
  tol_pairs N`` and ``S <= tol_changed N`` hold for ``stable_iterations`` consecutive iterations
  (inferred defaults 1e-6, 0.1 %, 0.1 %, 2), or after ``max_iterations`` (200).
* **Plain ICP** is the same code with ``w = 0`` and a 3-D tree (spec 5.6, V13).

Uncertainty (forestmap's step beyond the thesis, inferred): :func:`icp_covariance` is the
Gauss-Newton inverse Hessian of the final residuals (point-to-point, or point-to-plane when model
normals are given) times the residual variance, inflated by ``N / N_eff`` where ``N_eff`` counts
the voxels of edge ``correlation_m`` holding paired points, because neighbouring residuals are not
independent.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from forestmap_assets.core.registration_.colour import hue_features

HISTORY_COLUMNS = ["iteration", "error", "error_m", "n_pairs", "changed"]


# --------------------------------------------------------------------------------------------
# rigid transforms


def rot_z(theta_rad: float) -> np.ndarray:
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rigid_transform(data: np.ndarray, model: np.ndarray, dof: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares ``R, T`` with ``model ~ R data + T`` from paired points (spec 5.4, Eqs.
    5.6-5.9 in the corrected Arun/Horn form with the reflection guard, Appendix A).

    ``dof=6``: any rotation, ``det R = +1`` even for planar or collinear sets. ``dof=4``: rotation
    about z only (levelled scans).
    """
    d = np.asarray(data, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(model, dtype=np.float64).reshape(-1, 3)
    if len(d) != len(m) or len(d) == 0:
        raise ValueError(f"rigid_transform: need equal, non-zero numbers of points ({len(d)}, {len(m)})")
    d_bar, m_bar = d.mean(axis=0), m.mean(axis=0)
    dc, mc = d - d_bar, m - m_bar
    if dof == 4:
        theta = np.arctan2((dc[:, 0] * mc[:, 1] - dc[:, 1] * mc[:, 0]).sum(),
                           (dc[:, 0] * mc[:, 0] + dc[:, 1] * mc[:, 1]).sum())
        r = rot_z(theta)
    elif dof == 6:
        k = dc.T @ mc  # K = sum d' m'^T
        u, _, vt = np.linalg.svd(k)
        v = vt.T
        guard = np.diag([1.0, 1.0, np.sign(np.linalg.det(v @ u.T)) or 1.0])
        r = v @ guard @ u.T
    else:
        raise ValueError(f"dof: expected 4 or 6, got {dof!r}")
    return r, m_bar - r @ d_bar


def matrix_to_pose4(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(x, y, z, heading_deg) of a rigid transform (heading of R's x axis; roll/pitch dropped)."""
    return np.array([t[0], t[1], t[2], np.degrees(np.arctan2(r[1, 0], r[0, 0]))])


def pose4_to_matrix(pose) -> tuple[np.ndarray, np.ndarray]:
    """``R, T`` of a 4-DoF pose (x, y, z, heading_deg): ``p' = R_z(h) p + t`` (forsman 6.1)."""
    x, y, z, h = (float(v) for v in pose)
    return rot_z(np.radians(h)), np.array([x, y, z])


def _project_box(r: np.ndarray, t: np.ndarray, box) -> tuple[np.ndarray, np.ndarray, bool]:
    """Clamp a 4-DoF transform into ``box = (centre(4), half_widths(4))`` (heading deg)."""
    centre, half = (np.asarray(v, dtype=np.float64) for v in box)
    pose = matrix_to_pose4(r, t)
    dh = (pose[3] - centre[3] + 180.0) % 360.0 - 180.0
    rel = np.array([*(pose[:3] - centre[:3]), dh])
    clamped = np.clip(rel, -half, half)
    hit = bool(np.any(np.abs(rel) > half))
    new = centre + clamped
    r2, t2 = pose4_to_matrix(new)
    return r2, t2, hit


# --------------------------------------------------------------------------------------------
# embedding


@dataclass(frozen=True)
class Embedding:
    """The shared association metric: ``((p - offset) / scale, weight * hue)`` (spec 5.2)."""

    offset: np.ndarray
    scale: np.ndarray
    weight: float
    hue_mode: str = "linear"
    scale_mode: str = "per_axis"
    scale_box: str = "model"

    @classmethod
    def from_clouds(cls, model_xyz, data_xyz=None, *, weight: float = 0.2, scale: str = "per_axis",
                    box: str = "model", hue_mode: str = "linear") -> Embedding:
        """Offset and scale from the model's bounding box (``box="model"``) or the union of both
        boxes (``"union"``); ``scale`` 'per_axis' (thesis 5.8) or 'isotropic'."""
        pts = np.asarray(model_xyz, dtype=np.float64).reshape(-1, 3)
        if box == "union" and data_xyz is not None:
            pts = np.vstack([pts, np.asarray(data_xyz, dtype=np.float64).reshape(-1, 3)])
        elif box not in ("model", "union"):
            raise ValueError(f"box: expected 'model' or 'union', got {box!r}")
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        ext = hi - lo
        # a flat axis (a planar cloud) would blow up noise: it takes the largest extent (inferred)
        ext = np.where(ext > 1e-6 * max(ext.max(), 1e-9), ext, max(ext.max(), 1e-9))
        if scale == "isotropic":
            ext = np.full(3, ext.max())
        elif scale != "per_axis":
            raise ValueError(f"scale: expected 'per_axis' or 'isotropic', got {scale!r}")
        hue_features(np.zeros(1), hue_mode)  # validates the mode
        return cls(lo, ext, float(weight), hue_mode, scale, box)

    def spatial(self, xyz: np.ndarray) -> np.ndarray:
        return (np.asarray(xyz, dtype=np.float64) - self.offset) / self.scale

    def hue_part(self, hue, n: int) -> np.ndarray:
        """``w * hue`` coordinates (n, 1 or 2); empty (n, 0) for plain ICP (w = 0)."""
        if self.weight == 0.0:
            return np.zeros((n, 0))
        if hue is None:
            raise ValueError("hue: HICP with a non-zero weight needs the hue of both clouds")
        return self.weight * hue_features(hue, self.hue_mode)

    def embed(self, xyz: np.ndarray, hue=None) -> np.ndarray:
        s = self.spatial(xyz)
        return np.hstack([s, self.hue_part(hue, len(s))])


def default_radius(embedded_model: np.ndarray, k: int = 50, sample: int = 2000, seed: int = 0) -> float:
    """Association radius with about ``k`` model points inside: median distance to the k-th
    nearest embedded neighbour over a random model sample (spec 5.3 rule of thumb, inferred)."""
    pts = np.asarray(embedded_model, dtype=np.float64)
    if len(pts) <= k:
        return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) or 1.0
    rng = np.random.default_rng(seed)
    sel = rng.choice(len(pts), size=min(sample, len(pts)), replace=False)
    d, _ = cKDTree(pts).query(pts[sel], k=k + 1)
    return float(np.median(d[:, -1]))


# --------------------------------------------------------------------------------------------
# the ICP loop


@dataclass
class ICPResult:
    """Outcome of :func:`hicp`: transform ``model ~ R data + T``, per-iteration history
    (``error`` normalised, ``error_m`` metric mean association distance, ``n_pairs``,
    ``changed``), final partners (``partner[i]`` model index or -1)."""

    rotation: np.ndarray
    translation: np.ndarray
    iterations: int
    converged: bool
    reason: str
    history: pd.DataFrame
    partner: np.ndarray
    radius: float
    embedding: Embedding
    dof: int
    seconds: float
    hit_box: bool = False
    extra: dict = field(default_factory=dict)

    @property
    def matrix(self) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = self.rotation
        out[:3, 3] = self.translation
        return out

    @property
    def pose4(self) -> np.ndarray:
        return matrix_to_pose4(self.rotation, self.translation)

    @property
    def n_pairs(self) -> int:
        return int((self.partner >= 0).sum())

    @property
    def error_m(self) -> float:
        return float(self.history["error_m"].iloc[-1]) if len(self.history) else np.nan


@dataclass
class ModelIndex:
    """The model side of HICP, built once: embedding, embedded points and k-d tree."""

    xyz: np.ndarray
    embedding: Embedding
    tree: cKDTree

    @classmethod
    def build(cls, model_xyz, model_hue=None, embedding: Embedding | None = None, **emb_kw) -> ModelIndex:
        xyz = np.asarray(model_xyz, dtype=np.float64).reshape(-1, 3)
        emb = embedding or Embedding.from_clouds(xyz, **emb_kw)
        return cls(xyz, emb, cKDTree(emb.embed(xyz, model_hue)))


def hicp(
    model_xyz: np.ndarray,
    data_xyz: np.ndarray,
    model_hue=None,
    data_hue=None,
    *,
    weight: float = 0.2,
    init=None,
    radius: float | None = None,
    k_radius: int = 50,
    scale: str = "per_axis",
    scale_box: str = "model",
    hue_mode: str = "linear",
    dof: int = 6,
    max_iterations: int = 200,
    tol_error: float = 1e-6,
    tol_pairs: float = 1e-3,
    tol_changed: float = 1e-3,
    stable_iterations: int = 2,
    box=None,
    index: ModelIndex | None = None,
    workers: int = 1,
) -> ICPResult:
    """Register ``data_xyz`` to ``model_xyz`` by hue-assisted ICP (spec 5.6); ``weight=0`` is
    plain 3-D ICP with a 3-D tree (spec 5.6 baseline, V13).

    ``init``: starting transform as a 4x4 matrix, an ``(R, T)`` pair or a 4-DoF pose (x, y, z,
    heading_deg). ``radius`` in embedded (normalised) units; default by :func:`default_radius`
    with ``k_radius``. ``box = (centre, half_widths)`` (4-DoF, heading deg; only with
    ``dof=4``) keeps every iterate inside the box (projection after each update, inferred).
    ``index`` reuses a prebuilt :class:`ModelIndex` (its embedding wins over the scale options).
    """
    t0 = time.perf_counter()
    data = np.asarray(data_xyz, dtype=np.float64).reshape(-1, 3)
    if index is None:
        emb = Embedding.from_clouds(model_xyz, data, weight=weight, scale=scale, box=scale_box,
                                    hue_mode=hue_mode)
        index = ModelIndex.build(model_xyz, model_hue, emb)
    emb = index.embedding
    model = index.xyz
    if box is not None and dof != 4:
        raise ValueError("box: the pose box constrains 4-DoF registrations only (dof=4)")
    if radius is None:
        radius = default_radius(index.tree.data, k=k_radius)
    r, t = _initial(init)
    if box is not None:
        r, t, _ = _project_box(r, t, box)
    hue_part = emb.hue_part(data_hue, len(data))
    model_s = emb.spatial(model)
    prev = np.full(len(data), -2, dtype=np.int64)
    rows = []
    stable = 0
    converged = False
    reason = "iteration cap reached"
    hit = False
    need = 3 if dof == 6 else 2
    for it in range(1, max_iterations + 1):
        moved = data @ r.T + t
        ms = emb.spatial(moved)
        dist, idx = index.tree.query(np.hstack([ms, hue_part]), k=1, distance_upper_bound=radius,
                                     workers=workers)
        ok = idx < len(model)
        partner = np.where(ok, idx, -1)
        n = int(ok.sum())
        changed = int((partner != prev).sum()) if it > 1 else n
        if n:
            err = float(np.linalg.norm(ms[ok] - model_s[idx[ok]], axis=1).mean())
            err_m = float(np.linalg.norm(moved[ok] - model[idx[ok]], axis=1).mean())
        else:
            err = err_m = np.nan
        rows.append((it, err, err_m, n, changed))
        if n < need:
            reason = f"only {n} data points associated within the radius {radius:.4g}"
            break
        r, t = rigid_transform(data[ok], model[idx[ok]], dof)
        if box is not None:
            r, t, hit = _project_box(r, t, box)
        if it > 1:
            prev_err, prev_n = rows[-2][1], rows[-2][3]
            if (abs(err - prev_err) < tol_error and abs(n - prev_n) <= tol_pairs * n
                    and changed <= tol_changed * n):
                stable += 1
            else:
                stable = 0
            if stable >= stable_iterations:
                converged = True
                reason = ""
                break
        prev = partner
    history = pd.DataFrame(rows, columns=HISTORY_COLUMNS)
    return ICPResult(r, t, len(rows), converged, reason, history, partner, float(radius), emb, dof,
                     time.perf_counter() - t0, hit)


def icp(model_xyz: np.ndarray, data_xyz: np.ndarray, **kw) -> ICPResult:
    """Plain 3-D ICP: :func:`hicp` with ``weight=0`` (a 3-D tree, same loop, radius, termination)."""
    kw.pop("weight", None)
    return hicp(model_xyz, data_xyz, None, None, weight=0.0, **kw)


def _initial(init) -> tuple[np.ndarray, np.ndarray]:
    if init is None:
        return np.eye(3), np.zeros(3)
    if isinstance(init, tuple | list) and len(init) == 2:
        return np.asarray(init[0], dtype=np.float64), np.asarray(init[1], dtype=np.float64)
    a = np.asarray(init, dtype=np.float64)
    if a.shape == (4, 4):
        return a[:3, :3].copy(), a[:3, 3].copy()
    if a.shape == (4,):
        return pose4_to_matrix(a)
    raise ValueError(f"init: expected a 4x4 matrix, (R, T) or a 4-DoF pose, got shape {a.shape}")


# --------------------------------------------------------------------------------------------
# quality and uncertainty


def normal_quality(model_normals: np.ndarray, merged_normals: np.ndarray) -> float:
    """Surface-normal quality ``eps_n = mean |n . n'|`` (spec 5.7, Eq. 5.10 first): model normals
    before registration vs normals at the same model points in the merged cloud (1 = best)."""
    a = np.asarray(model_normals, dtype=np.float64)
    b = np.asarray(merged_normals, dtype=np.float64)
    ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    return float(np.abs((a[ok] * b[ok]).sum(axis=1)).mean()) if ok.any() else np.nan


def merged_normal_quality(model_xyz: np.ndarray, moved_data: np.ndarray, radius_m: float) -> float:
    """``eps_n`` of spec 5.7: radius-PCA normals of the model alone vs at the same model points in
    the merged cloud (model + registered data), with the same estimator
    (:func:`~.cloud.radius_normals`); 1 when merging leaves the model's surfaces undisturbed."""
    from forestmap_assets.core.cloud import radius_normals

    model = np.asarray(model_xyz, dtype=np.float64)
    centre = model.mean(axis=0)
    before = radius_normals(model, radius_m, centre)
    after = radius_normals(np.vstack([model, np.asarray(moved_data, dtype=np.float64)]), radius_m, centre,
                           at=model)
    return normal_quality(before, after)


def _jacobian(q: np.ndarray, dof: int) -> np.ndarray:
    """d(moved point)/d(delta) (n, 3, dof) for perturbations (dx, dy, dz, [wx, wy,] wz) about
    the pivot; ``q`` = moved point minus translation (the rotated data point)."""
    n = len(q)
    j = np.zeros((n, 3, dof))
    j[:, 0, 0] = j[:, 1, 1] = j[:, 2, 2] = 1.0
    if dof == 4:
        j[:, 0, 3] = -q[:, 1]
        j[:, 1, 3] = q[:, 0]
    else:  # d(w x q)/dw = -[q]_x
        j[:, 0, 4], j[:, 0, 5] = q[:, 2], -q[:, 1]
        j[:, 1, 3], j[:, 1, 5] = -q[:, 2], q[:, 0]
        j[:, 2, 3], j[:, 2, 4] = q[:, 1], -q[:, 0]
    return j


def icp_covariance(
    moved: np.ndarray,
    partners: np.ndarray,
    translation: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    dof: int = 4,
    correlation_m: float = 0.5,
) -> np.ndarray:
    """Covariance of the ICP estimate from its Gauss-Newton Hessian (inferred, see module doc).

    ``moved``: paired data points after the final transform; ``partners``: their model points;
    ``normals``: model normals for the point-to-plane form. Parameters ordered (x, y, z,
    heading_rad) for ``dof=4`` or (x, y, z, wx, wy, wz) for ``dof=6``. The residual variance
    ``sigma^2 = sum e^2 / (n_obs - dof)`` and the inflation ``N / N_eff`` (``N_eff`` = occupied
    voxels of edge ``correlation_m``) account for the noise and for correlated neighbours.
    """
    p = np.asarray(moved, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(partners, dtype=np.float64).reshape(-1, 3)
    n = len(p)
    if n <= dof:
        return np.full((dof, dof), np.nan)
    j = _jacobian(p - np.asarray(translation, dtype=np.float64), dof)
    e = m - p
    if normals is not None:
        nv = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        ok = np.isfinite(nv).all(axis=1)
        jn = np.einsum("ni,nid->nd", nv[ok], j[ok])
        res = (nv[ok] * e[ok]).sum(axis=1)
        h = jn.T @ jn
        dof_obs = max(len(res) - dof, 1)
        pts = p[ok]
    else:
        h = np.einsum("nid,nie->de", j, j)
        res = e.reshape(-1)
        dof_obs = max(res.size - dof, 1)
        pts = p
    sigma2 = float((res**2).sum() / dof_obs)
    keys = np.unique(np.floor(pts / correlation_m).astype(np.int64), axis=0)
    inflation = len(pts) / max(len(keys), 1)
    try:
        cov = np.linalg.inv(h)
    except np.linalg.LinAlgError:
        return np.full((dof, dof), np.inf)
    return sigma2 * inflation * cov


def pose_sd(cov: np.ndarray) -> np.ndarray:
    """Standard deviations (sd_x, sd_y, sd_z, sd_heading_deg) of a 4-DoF covariance."""
    sd = np.sqrt(np.clip(np.diag(cov)[:4], 0.0, None))
    sd[3] = np.degrees(sd[3])
    return sd


# --------------------------------------------------------------------------------------------
# point-to-plane ICP (Open3D) for clouds without colour


def point_to_plane_4dof(
    model_xyz: np.ndarray,
    model_normals: np.ndarray,
    data_xyz: np.ndarray,
    init_pose,
    *,
    max_distance_m: float,
    iterations: int = 5,
    tree: cKDTree | None = None,
    box=None,
    tol: float = 1e-7,
    robust_k: float | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """4-DoF point-to-plane Gauss-Newton ICP (x, y, z, heading): pose, final partner indices
    (-1 none) and iterations (inferred). With ``robust_k``, iteratively re-weighted least squares with Tukey's biweight at
    ``robust_k`` times the residuals' robust spread (1.4826 MAD), so that pairs of different
    surfaces within ``max_distance_m`` do not bias the pose (inferred)."""
    model = np.asarray(model_xyz, dtype=np.float64)
    normals = np.asarray(model_normals, dtype=np.float64)
    data = np.asarray(data_xyz, dtype=np.float64)
    tree = tree or cKDTree(model)
    pose = np.asarray(init_pose, dtype=np.float64).copy()
    partner = np.full(len(data), -1)
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007
        r, t = pose4_to_matrix(pose)
        moved = data @ r.T + t
        _, idx = tree.query(moved, k=1, distance_upper_bound=max_distance_m)
        ok = (idx < len(model))
        ok[ok] &= np.isfinite(normals[idx[ok]]).all(axis=1)
        partner = np.where(ok, idx, -1)
        if ok.sum() < 4:
            break
        nv = normals[idx[ok]]
        jn = np.einsum("ni,nid->nd", nv, _jacobian(moved[ok] - t, 4))
        res = (nv * (model[idx[ok]] - moved[ok])).sum(axis=1)
        if robust_k is not None:
            c = robust_k * max(1.4826 * float(np.median(np.abs(res - np.median(res)))), 1e-6)
            w = np.clip(1.0 - (res / c) ** 2, 0.0, None) ** 2
            jw = jn * w[:, None]
            delta = np.linalg.lstsq(jw.T @ jn, jw.T @ res, rcond=None)[0]
        else:
            delta = np.linalg.lstsq(jn.T @ jn, jn.T @ res, rcond=None)[0]
        # p(delta) = R_z(h + dh) d + t + dt: the increments add to the pose (see _jacobian)
        pose = np.array([*(t + delta[:3]), pose[3] + np.degrees(delta[3])])
        if box is not None:
            r2, t2, _ = _project_box(*pose4_to_matrix(pose), box)
            pose = matrix_to_pose4(r2, t2)
        if np.abs(delta[:3]).max() < tol and abs(delta[3]) < tol:
            break
    return pose, partner, it


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
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(model_xyz, dtype=np.float64)))
    if model_normals is None:
        tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_m, max_nn=30))
    else:
        tgt.normals = o3d.utility.Vector3dVector(np.nan_to_num(np.asarray(model_normals, dtype=np.float64)))
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(data_xyz, dtype=np.float64)))
    r, t = pose4_to_matrix(init_pose)
    init = np.eye(4)
    init[:3, :3], init[:3, 3] = r, t
    estimation = (reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=tukey_k_m)) if tukey_k_m
                  else reg.TransformationEstimationPointToPlane())
    res = reg.registration_icp(src, tgt, max_distance_m, init, estimation,
                               reg.ICPConvergenceCriteria(max_iteration=max_iterations))
    return np.asarray(res.transformation), len(res.correspondence_set), float(res.inlier_rmse)
