"""Relative -> global projection (Eq. 6.1-6.3) and incremental chaining of sub-maps (spec 8.2-8.3).

An observation row ``(scan, reference, dx, dy, dz, dheading_deg, sd_x, sd_y, sd_z,
sd_heading_deg)`` is the location of sub-map ``scan`` in the levelled frame of sub-map
``reference`` (spec 6.1): ``p_ref = R_z(dheading) p_scan + (dx, dy, dz)``. Projected into the
global frame with the reference's global heading ``phi_tot`` it becomes an observation of
``x_scan - x_ref`` (spec 8.1-8.2).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
import pandas as pd

OBSERVATION_COLUMNS = (
    "scan", "reference", "dx", "dy", "dz", "dheading_deg",
    "sd_x", "sd_y", "sd_z", "sd_heading_deg",
)
VALUE_COLUMNS = ("dx", "dy", "dz", "dheading_deg")
SD_COLUMNS = ("sd_x", "sd_y", "sd_z", "sd_heading_deg")
POSE_COLUMNS = ("x", "y", "z", "heading_deg")
POSE_SD_COLUMNS = ("sd_x", "sd_y", "sd_z", "sd_heading_deg")

Covariance = Literal["published", "full"]


def wrap_deg(angle_deg):
    """Wrap angles (degrees) into (-180, 180]."""
    return 180.0 - np.mod(180.0 - np.asarray(angle_deg, dtype=float), 360.0)


def project_relative(
    d: np.ndarray,
    sd: np.ndarray,
    heading_ref_deg: np.ndarray,
    heading_ref_var_deg2: np.ndarray | None = None,
    covariance: Covariance = "published",
) -> tuple[np.ndarray, np.ndarray]:
    """Project local observations into the global frame, Eq. 6.1 (values) and 6.2-6.3 (covariance).

    ``d`` (M, 4) = (dx, dy, dz, dheading_deg) in the reference's levelled frame, ``sd`` (M, 4)
    their sigmas, ``heading_ref_deg`` (M,) the reference sub-map's current global heading.
    Returns ``(d_g, C_g)`` with ``C_g`` (M, 4, 4) in the order (x, y, z, heading).

    ``covariance="published"`` (default, spec 8.2 reproduction note, inferred): the diagonal x/y
    variances are rotated, ``s_xg^2 = c^2 s_x^2 + s^2 s_y^2``, ``s_yg^2 = s^2 s_x^2 + c^2 s_y^2``;
    no cross terms, no heading-of-reference term; z and heading unchanged. This reproduces
    Tables 6.3, 6.4, 6.7 and 6.9. ``covariance="full"``: ``C_g* = J C_r* J^T`` with the complete
    Jacobian of Eq. 6.1 (its last column ``-s x_r - c y_r``, ``c x_r - s y_r`` per radian, which
    the printed Eq. 6.3 abbreviates) and ``heading_ref_var_deg2`` as the variance of ``phi_tot``.
    """
    d = np.asarray(d, dtype=float).reshape(-1, 4)
    sd = np.asarray(sd, dtype=float).reshape(-1, 4)
    phi = np.radians(np.asarray(heading_ref_deg, dtype=float).reshape(-1))
    c, s = np.cos(phi), np.sin(phi)
    xr, yr = d[:, 0], d[:, 1]
    dg = np.column_stack([c * xr - s * yr, s * xr + c * yr, d[:, 2], d[:, 3]])
    var = sd**2
    cg = np.zeros((len(d), 4, 4))
    cg[:, 2, 2] = var[:, 2]
    cg[:, 3, 3] = var[:, 3]
    if covariance == "published":
        cg[:, 0, 0] = c**2 * var[:, 0] + s**2 * var[:, 1]
        cg[:, 1, 1] = s**2 * var[:, 0] + c**2 * var[:, 1]
    elif covariance == "full":
        var_phi = np.zeros(len(d)) if heading_ref_var_deg2 is None else np.asarray(
            heading_ref_var_deg2, dtype=float).reshape(-1)
        var_phi = np.nan_to_num(var_phi) * np.radians(1.0) ** 2  # deg^2 -> rad^2
        jac = np.zeros((len(d), 2, 3))  # d(x_g, y_g) / d(x_r, y_r, phi_tot [rad])
        jac[:, 0] = np.column_stack([c, -s, -s * xr - c * yr])
        jac[:, 1] = np.column_stack([s, c, c * xr - s * yr])
        cr = np.zeros((len(d), 3, 3))
        cr[:, 0, 0], cr[:, 1, 1], cr[:, 2, 2] = var[:, 0], var[:, 1], var_phi
        cg[:, :2, :2] = jac @ cr @ jac.transpose(0, 2, 1)
    else:
        raise ValueError(f"covariance must be 'published' or 'full', got {covariance!r}")
    return dg, cg


def observation_arrays(
    observations: pd.DataFrame, scans: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Indices of ``scan`` (i) and ``reference`` (j) in ``scans`` plus values (M, 4) and sigmas (M, 4).

    Rows naming a scan outside ``scans`` get index -1.
    """
    pos = pd.Index([str(s) for s in scans])
    i = pos.get_indexer(observations["scan"].astype(str))
    j = pos.get_indexer(observations["reference"].astype(str))
    d = observations.loc[:, list(VALUE_COLUMNS)].to_numpy(dtype=float)
    sd = observations.loc[:, list(SD_COLUMNS)].to_numpy(dtype=float)
    return i, j, d, sd


def place_from_link(
    pose_known: np.ndarray,
    d: np.ndarray,
    known_is_reference: np.ndarray,
) -> np.ndarray:
    """Pose (M, 4) of the unknown end of each link from the known end's global pose (Eq. 6.1).

    ``known_is_reference`` True: the known sub-map is the link's reference, the new pose is
    ``x_ref + project(d, phi_ref)`` with heading ``phi_ref + dphi``. False: the known sub-map is
    the link's scan; the reference's heading is ``phi_scan - dphi`` and its position
    ``x_scan - project(d, phi_ref)``.
    """
    pose_known = np.asarray(pose_known, dtype=float).reshape(-1, 4)
    d = np.asarray(d, dtype=float).reshape(-1, 4)
    k = np.asarray(known_is_reference, dtype=bool).reshape(-1)
    heading_ref = np.where(k, pose_known[:, 3], pose_known[:, 3] - d[:, 3])
    dg, _ = project_relative(d, np.zeros_like(d), heading_ref)
    sign = np.where(k, 1.0, -1.0)[:, None]
    return pose_known + sign * dg


def chain_poses(
    observations: pd.DataFrame,
    order: Sequence[str],
    *,
    link_choice: Literal["latest", "smallest_sigma"] = "latest",
) -> pd.DataFrame:
    """Incremental chaining, spec 8.3 (Th. 6.2): each new sub-map's global pose is the pose of an
    already placed sub-map plus the projected relative observation; headings and projected
    (published-rule, diagonal) variances are summed along the chain.

    ``order[0]`` is the reference (global frame). For each later sub-map a link to an already
    placed sub-map is used: ``link_choice="latest"`` prefers the most recently placed one (the
    thesis's consecutive pairs), ties and ``"smallest_sigma"`` by the smallest summed variance
    (inferred). A sub-map with no link to an earlier placed one in ``order`` is returned with
    ``registered`` False and NaN pose. Headings are not wrapped (sums of the published values).
    """
    scans = [str(s) for s in order]
    n = len(scans)
    i, j, d, sd = observation_arrays(observations, scans)
    valid = (i >= 0) & (j >= 0) & (i != j)
    pose = np.full((n, 4), np.nan)
    var = np.full((n, 4), np.nan)
    rank = np.full(n, -1)
    pose[0], var[0], rank[0] = 0.0, 0.0, 0
    for k in range(1, n):
        as_scan = valid & (i == k) & (rank[np.maximum(j, 0)] >= 0) & (j != k)
        as_ref = valid & (j == k) & (rank[np.maximum(i, 0)] >= 0) & (i != k)
        cand = np.flatnonzero(as_scan | as_ref)
        if cand.size == 0:
            continue
        other = np.where(as_scan[cand], j[cand], i[cand])
        total_var = (sd[cand] ** 2).sum(axis=1)
        first_key = -rank[other] if link_choice == "latest" else np.zeros(cand.size)
        best = np.lexsort((total_var, first_key))[0]
        m, o = cand[best], other[best]
        known_is_ref = bool(as_scan[m])
        pose[k] = place_from_link(pose[o], d[m], np.array([known_is_ref]))[0]
        heading_ref = pose[o, 3] if known_is_ref else pose[k, 3]
        _, cg = project_relative(d[m], sd[m], np.array([heading_ref]))
        var[k] = var[o] + np.diagonal(cg[0])
        rank[k] = k
    out = pd.DataFrame(pose, columns=list(POSE_COLUMNS))
    out.insert(0, "scan", scans)
    out[list(POSE_SD_COLUMNS)] = np.sqrt(var)
    out["registered"] = rank >= 0
    return out
