"""Hue-assisted ICP (HICP) and plain 3-D ICP as one algorithm (men spec 5.1-5.6, checklist 13-17):
shared-scale 4-D embedding e(p, h) = ((p - o) / s, w h), fixed-radius 1-NN association on a model
k-d tree built once, closed-form SVD transform with reflection guard (Appendix A; dof=4 about z,
forsman spec 6.1), convergence on eps, N and S (spec 5.5); plain ICP is w = 0."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from forestmap_assets.core.registration.colour import hue_features

HISTORY_COLUMNS = ["iteration", "error", "error_m", "n_pairs", "changed"]


def rot_z(theta_rad: float) -> np.ndarray:
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rigid_transform(
    data: np.ndarray, model: np.ndarray, dof: int = 6
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares ``R, T`` with ``model ~ R data + T`` from paired points (spec 5.4, Eqs.
    5.6-5.9 in the corrected Arun/Horn form with the reflection guard, Appendix A).

    ``dof=6``: any rotation, ``det R = +1`` even for planar or collinear sets. ``dof=4``: rotation
    about z only (levelled scans).
    """
    d = np.asarray(data, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(model, dtype=np.float64).reshape(-1, 3)
    if len(d) != len(m) or len(d) == 0:
        raise ValueError(
            f"rigid_transform: need equal, non-zero numbers of points ({len(d)}, {len(m)})"
        )
    d_bar, m_bar = d.mean(axis=0), m.mean(axis=0)
    dc, mc = d - d_bar, m - m_bar
    if dof == 4:
        theta = np.arctan2(
            (dc[:, 0] * mc[:, 1] - dc[:, 1] * mc[:, 0]).sum(),
            (dc[:, 0] * mc[:, 0] + dc[:, 1] * mc[:, 1]).sum(),
        )
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


def project_box(r: np.ndarray, t: np.ndarray, box) -> tuple[np.ndarray, np.ndarray, bool]:
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
    def from_clouds(
        cls,
        model_xyz,
        data_xyz=None,
        *,
        weight: float = 0.2,
        scale: str = "per_axis",
        box: str = "model",
        hue_mode: str = "linear",
    ) -> Embedding:
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


def default_radius(
    embedded_model: np.ndarray, k: int = 50, sample: int = 2000, seed: int = 0
) -> float:
    """Association radius with about ``k`` model points inside: median distance to the k-th
    nearest embedded neighbour over a random model sample (spec 5.3 rule of thumb, inferred)."""
    pts = np.asarray(embedded_model, dtype=np.float64)
    if len(pts) <= k:
        return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) or 1.0
    rng = np.random.default_rng(seed)
    sel = rng.choice(len(pts), size=min(sample, len(pts)), replace=False)
    d, _ = cKDTree(pts).query(pts[sel], k=k + 1)
    return float(np.median(d[:, -1]))


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
    def build(
        cls, model_xyz, model_hue=None, embedding: Embedding | None = None, **emb_kw
    ) -> ModelIndex:
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
        emb = Embedding.from_clouds(
            model_xyz, data, weight=weight, scale=scale, box=scale_box, hue_mode=hue_mode
        )
        index = ModelIndex.build(model_xyz, model_hue, emb)
    emb = index.embedding
    model = index.xyz
    if box is not None and dof != 4:
        raise ValueError("box: the pose box constrains 4-DoF registrations only (dof=4)")
    if radius is None:
        radius = default_radius(index.tree.data, k=k_radius)
    r, t = _initial(init)
    if box is not None:
        r, t, _ = project_box(r, t, box)
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
        dist, idx = index.tree.query(
            np.hstack([ms, hue_part]), k=1, distance_upper_bound=radius, workers=workers
        )
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
            r, t, hit = project_box(r, t, box)
        if it > 1:
            prev_err, prev_n = rows[-2][1], rows[-2][3]
            if (
                abs(err - prev_err) < tol_error
                and abs(n - prev_n) <= tol_pairs * n
                and changed <= tol_changed * n
            ):
                stable += 1
            else:
                stable = 0
            if stable >= stable_iterations:
                converged = True
                reason = ""
                break
        prev = partner
    history = pd.DataFrame(rows, columns=HISTORY_COLUMNS)
    return ICPResult(
        r,
        t,
        len(rows),
        converged,
        reason,
        history,
        partner,
        float(radius),
        emb,
        dof,
        time.perf_counter() - t0,
        hit,
    )


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
