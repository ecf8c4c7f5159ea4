"""Least-squares polish of an accepted branch-and-bound pose on its matched stem axes, and the
heading sigma that the stems' own scatter gives (forestmap's step beyond the thesis, issue 19;
inferred).

The branch-and-bound pose is the weighted centre of its final cell cloud (spec 6.5), and its
heading sigma is then mostly the final cell's quantisation, ``step / sqrt(12)``: 0.0226 deg on
Sylva's and rendered surveys, whatever the data say (the headings' errors there were 0.004-0.013
deg RMS, error / sd 0.23-0.57). Here the scan's sub-map points (spec 6.2: samples along the
cylinder segments' axes) are moved by the pose and paired with the nearest reference sub-map
point within ``match_m``; each cylinder segment with at least ``min_points`` pairs gives one
mean horizontal residual ``e_k`` at its mean position ``q_k``. A rotation ``w`` about the
segments' centroid ``c`` and a shift ``t`` are fitted by least squares,

    e_k = t + w (-(q_k - c)_y, (q_k - c)_x),

re-paired and fitted again until the rotation is below 1e-7 rad; segments farther from the fit than
``trim_sigmas`` times their RMS residual are left out, or with ``huber_k`` (the forest preset's
1.345) every segment is weighted by Huber's ``min(1, k s / |e_k - fit|)``, ``s`` the residuals'
median over 1.1774 (a 2-D normal's per-axis sigma), by iterated reweighting: a few one-sided far
stems (60-83 mm off across the ray at 20-30 m) turned one own realistic scan's stems by 0.020 deg
under least squares, 0.007 deg under Huber's weights, and the links' heading error RMS fell from
0.0093 to 0.0069 deg (own realistic), 0.0028 to 0.0021 (Sylva), 0.0029 to 0.0021 (rendered;
benchmarks/results.md "polish_huber").

The heading sigma is ``sd_scale`` times the fit's stem-clustered jackknife sigma (CR3), ``(G - 1)
/ G N^-1 (sum_g A_g^T u_g u_g^T A_g) N^-1`` with ``u_g = (I - H_gg)^-1 r_g``, the segments grouped
into G stems (within ``stem_m`` of each other): the segments of one stem share its shape's bias,
and the far segments, which weigh most on the heading, scatter unlike the near ones (issue 19).
Fewer than 6 stems fall back to the larger of that and the fit's plain sigma (residual variance
times ``N^-1``). With weights both are taken on the weighted (whitened) fit, and ``sd_scale`` (the
forest preset's 1.3) makes up for weights chosen from the same residuals and for far stems that
all of a scan's links share: over 20 own realistic, 10 Sylva and 7 rendered surveys the scans'
heading error / sd RMS was 1.37 / 1.06 / 1.02 with 1.15, 1.15 / 0.94 / 0.83 with 1.3. Without
weights (sd_scale 1.0) the links' heading error / sd RMS was 0.82 / 0.68 / 1.03 over the links of
Sylva 44-48 (58), rendered 16 (12) and own 1-6, 14-64 (661), 0.57 / 0.46 / 0.89 with the plain
sigma times 1.2 (benchmarks/results.md "polish_sd").
The polish took the links' heading error RMS from 0.005-0.013 to 0.0015-0.006 deg on Sylva 1-5,
0.007 / 0.004 to 0.002 / 0.001 deg on rendered 1-2 and 0.017 / 0.011 to 0.009 / 0.015 deg on own
1-2 (benchmarks/results.md "stem_polish"). The fitted shift is applied too, but the sub-maps' axes
share biases that their scatter does not show (the same fit's x, y sigma was 1.4-5.4 times too
small), so the x, y, z sigmas stay the branch and bound's.

The polish is not used (the pose stays) when fewer than ``min_segments`` segments pair, or when
it would move the pose by more than ``max_sigmas`` of the branch-and-bound sigmas."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from forestmap_assets.core.cloud import single_linkage
from forestmap_assets.core.geometry import rot_z, transform_points, wrap_deg


@dataclass(frozen=True)
class Polish:
    """The polished pose (dx, dy, dz, dheading_deg), its heading sigma (deg), the number of
    segments in the last fit, and why the polish was not used ('' when it was)."""

    pose: np.ndarray
    sd_heading_deg: float
    segments: int
    reason: str = ""


def _segment_residuals(moved: np.ndarray, ids: np.ndarray, tree: cKDTree, ref_xy: np.ndarray,
                       match_m: float, min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean position (n, 2) and mean horizontal residual (n, 2) of each segment with at least
    ``min_points`` points paired within ``match_m``."""
    d, j = tree.query(moved, distance_upper_bound=match_m)
    ok = np.isfinite(d)
    if not ok.any():
        return np.zeros((0, 2)), np.zeros((0, 2))
    _, inv, counts = np.unique(ids[ok], return_inverse=True, return_counts=True)
    pos = np.column_stack([np.bincount(inv, moved[ok, k]) for k in (0, 1)]) / counts[:, None]
    res = ref_xy[j[ok]] - moved[ok, :2]
    err = np.column_stack([np.bincount(inv, res[:, k]) for k in (0, 1)]) / counts[:, None]
    keep = counts >= min_points
    return pos[keep], err[keep]


def _clustered_cov(A: np.ndarray, r: np.ndarray, q: np.ndarray, stem_m: float,
                   plain: np.ndarray) -> np.ndarray:
    """The stem-clustered jackknife (CR3) covariance of the fit ``y = A sol`` (module
    docstring): ``A`` (2n, 3), residuals ``r`` (n, 2), segment positions ``q`` (n, 2), ``plain``
    the fit's homoscedastic covariance."""
    n_stems, stem = single_linkage(q, stem_m)
    inv = np.linalg.inv(A.T @ A)
    rows = np.repeat(stem, 2)  # A's rows are x, y of each segment in turn
    meat = np.zeros((3, 3))
    for g in range(n_stems):
        a_g = A[rows == g]
        r_g = r[stem == g].reshape(-1)
        lever = np.eye(len(a_g)) - a_g @ inv @ a_g.T  # I - H_gg: the stem left out of the fit
        s_g = a_g.T @ np.linalg.lstsq(lever, r_g, rcond=None)[0]
        meat += np.outer(s_g, s_g)
    cov = (n_stems - 1) / n_stems * inv @ meat @ inv
    return cov if n_stems >= 6 or cov[2, 2] >= plain[2, 2] else plain


def _huber_weights(residuals: np.ndarray, k: float) -> np.ndarray:
    """Huber's weight ``min(1, k s / |r|)`` of each segment's 2-D residual (n, 2), ``s`` the
    residuals' median length over 1.1774 (the per-axis sigma of a 2-D normal)."""
    length = np.hypot(*residuals.T)
    s = max(float(np.median(length)) / 1.1774, 1e-4)
    return np.minimum(1.0, k * s / np.maximum(length, 1e-12))


def polish_pose(scan_submap: pd.DataFrame, reference_submap: pd.DataFrame, pose, sd, *,
                match_m: float = 0.105, min_points: int = 5, min_segments: int = 4,
                trim_sigmas: float = 3.0, sd_scale: float = 1.0, max_sigmas: float = 3.0,
                stem_m: float = 0.5, iterations: int = 5, huber_k: float | None = None) -> Polish:
    """Polish ``pose`` (dx, dy, dz, dheading_deg of the scan in the reference's frame) on the
    two sub-maps' cylinder points (module docstring); ``sd`` are its branch-and-bound sigmas."""
    pose = np.asarray(pose, dtype=np.float64).copy()
    sd = np.asarray(sd, dtype=np.float64)
    start = pose.copy()

    def cylinders(df: pd.DataFrame) -> pd.DataFrame:
        return df[df["feature"] == "cylinder"] if "feature" in df else df

    a, b = cylinders(scan_submap), cylinders(reference_submap)
    if len(a) == 0 or len(b) == 0:
        return Polish(start, np.nan, 0, "no cylinder points")
    pts = a[["x", "y", "z"]].to_numpy(np.float64)
    ids = a["feature_id"].to_numpy() if "feature_id" in a else np.zeros(len(a), np.int64)
    ref = b[["x", "y", "z"]].to_numpy(np.float64)
    tree = cKDTree(ref)
    n, cov, A, r, q_fit = 0, None, None, None, None  # the last fit's
    for _ in range(iterations):
        q, e = _segment_residuals(transform_points(pts, pose), ids, tree, ref[:, :2], match_m, min_points)
        keep = np.ones(len(q), bool)
        wts = np.ones(len(q))
        for _refit in range(2 if huber_k is None else 8):
            n = int(keep.sum())
            if n < min_segments:
                return Polish(start, np.nan, n, f"only {n} stem segments pair")
            q_fit = q[keep]
            c = q_fit.mean(axis=0)
            v = q_fit - c
            sw = np.repeat(np.sqrt(wts[keep]), 2)
            A = np.zeros((2 * n, 3))
            A[0::2, 0], A[1::2, 1] = 1.0, 1.0
            A[0::2, 2], A[1::2, 2] = -v[:, 1], v[:, 0]
            A *= sw[:, None]
            y = e[keep].reshape(-1) * sw
            normal = A.T @ A
            sol = np.linalg.solve(normal, A.T @ y)
            r = (y - A @ sol).reshape(-1, 2)
            s2 = float((r * r).sum()) / max(2 * n - 3, 1)
            cov = s2 * np.linalg.inv(normal)
            if huber_k is not None:
                new_w = _huber_weights(r / np.sqrt(wts[keep])[:, None], huber_k)
                settled = np.allclose(new_w, wts[keep], atol=1e-3)
                wts[keep] = new_w
                if settled:
                    break
                continue
            far = np.hypot(*r.T) > trim_sigmas * max(np.sqrt(2.0 * s2), 1e-4)  # a 2-D residual's RMS
            if not far.any():
                break
            keep[np.flatnonzero(keep)[far]] = False
        w, shift = float(sol[2]), sol[:2]
        pose[:2] = rot_z(np.degrees(w))[:2, :2] @ (pose[:2] - c) + c + shift
        pose[3] = pose[3] + np.degrees(w)
        if abs(w) < 1e-7 and np.all(np.abs(shift) < 1e-6):
            break
    cov = _clustered_cov(A, r, q_fit, stem_m, cov)
    sd_h = sd_scale * float(np.degrees(np.sqrt(cov[2, 2])))
    moved = np.abs(np.r_[pose[:2] - start[:2], pose[3] - start[3]])
    limit = max_sigmas * np.r_[sd[0], sd[1], sd[3]]
    if np.any(~np.isfinite(limit)) or np.any(moved > limit):
        return Polish(start, np.nan, n, "the polish would move the pose by more than "
                      f"{max_sigmas:g} branch-and-bound sigmas")
    pose[3] = wrap_deg(pose[3])
    return Polish(pose, sd_h, n)
