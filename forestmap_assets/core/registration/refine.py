"""Fine registration of accepted pairs on the raw points (men spec 5; forestmap's link between
Forsman's branch and bound and the optimal map).

Every accepted branch-and-bound registration (pose ``(dx, dy, dz, dheading)`` of ``scan`` in the
levelled frame of ``reference`` with its cloud sigmas) is refined on the levelled raw points of
the two range images:

1. each cloud is cropped to ``max_range_m`` around its own sensor and to the height band
   ``z_band_m`` relative to it (drops the noisy, porous canopy, spec 10); the scan's points are
   moved
   by the branch-and-bound pose and both clouds are cut to their overlap (bounding boxes grown by
   ``overlap_margin_m``); the scan (data) is voxel sub-sampled at ``data_voxel_m``, the
   reference (model) at ``model_voxel_m`` (spec 3.2);
2. **HICP** (:func:`~.hicp.hicp`, 4-DoF, weight ``weight``, isotropic shared scale) where both
   scans have colour, finished by the robust point-to-plane steps below (``plane_polish``);
   else **Open3D point-to-plane ICP** with Open3D's Tukey kernel (``open3d_start``), finished by
   robust 4-DoF point-to-plane Gauss-Newton steps in the levelled frame
   (:func:`~.point_to_plane.point_to_plane_4dof`, ``plane_iterations``); the association radius is
   ``radius_m``. Pairs are weighted by Tukey's biweight at ``robust_k`` robust sigmas: two scans
   see different sides of a stem, and plain least squares lets the far side pull the pose by
   several millimetres (the minimum of the least-squares objective lies 5-11 mm from the truth
   on the simulated sample; benchmarks/results.md). Before HICP the median hue difference of
   spatially paired points is removed (``hue_offset``: cameras' white balance differs between
   scans, which the thesis's hue invariance ignores);
3. with ``guard="fit"`` (default) the pose may move as far as the points say, inside a trust
   region of ``max_shift_m`` / ``max_turn_deg`` (a result on its edge is not used), and without
   colour the pair is refined **both ways** and accepted on its own fit
   (:mod:`~.two_way`: the directions agree, the overlap is kept, the residuals fall), because the
   branch-and-bound sigma is smallest exactly where stem shapes bias the coarse pose (issue 19);
   with ``guard="box"`` (before) it is **kept inside the branch-and-bound cloud's box**
   ``centre +- box_sigmas * sd`` and a result on the box edge is not used;
4. the fit (mean point-to-plane distance of data points to their nearest model point within
   ``radius_m``, Eq. 4.9 along the normal, each distance truncated at the robust cut-off of the
   branch-and-bound pose, :func:`fit_error`) is measured at the branch-and-bound pose and at
   the refined pose; the refined pose replaces the branch-and-bound one only when it
   **improves the fit** by at least ``min_fit_gain`` (relative);
5. its uncertainty is the point-to-plane Hessian covariance
(:func:`~.icp_uncertainty.icp_covariance`,
   inflated for correlated neighbours over ``correlation_m``), its sigmas multiplied by
   ``sd_inflation`` and floored at ``sd_floor_m`` (x, y), ``sd_floor_z_m`` and ``sd_floor_deg``.
   The Hessian alone under-states the refined errors about 1.8 times (RMS of error / sd with
   no floors: 1.67, 1.94, 2.06, 1.75 for x, y, z, heading on simulated quarter-resolution
   campaigns, 1.65-2.06 in x, y at half resolution): 1.8 was fitted on the quarter-resolution
   seeds and checked on the half-resolution ones (benchmarks/results.md, mapping section).

6. with ``splat_candidates_m`` (the forest preset), a refined pair whose surfaces come closer by
   ``splat_min_gain`` once a renderer's splat widening is taken back is refined again on the
   corrected points (:mod:`~.splat_widening`), its z sigma floored at ``splat_sd_z_per_m`` times
   the splat radius squared.

All choices are (inferred); they are fields of :class:`RefineSettings`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, replace

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from forestmap_assets.core.cloud import pca_normals, voxel_subsample
from forestmap_assets.core.geometry import wrap_deg
from forestmap_assets.core.registration.hicp import (
    Embedding,
    ModelIndex,
    hicp,
    matrix_to_pose4,
    pose4_to_matrix,
)
from forestmap_assets.core.registration.icp_uncertainty import icp_covariance, pose_sd
from forestmap_assets.core.registration.point_to_plane import (
    open3d_point_to_plane,
    plane_residuals,
    point_to_plane_4dof,
)
from forestmap_assets.core.registration.splat_widening import choose_splat, corrected
from forestmap_assets.core.registration.two_way import (
    RefineCloud,
    crop_mask,
    fuse_heading,
    heading_gap_sigmas,
    two_way_refine,
    with_objective_spread,
)
from forestmap_assets.params.men import RefineSettings

POSE = ["dx", "dy", "dz", "dheading_deg"]
SD = ["sd_x", "sd_y", "sd_z", "sd_heading_deg"]
REFINE_COLUMNS = [
    "scan", "reference", "method", "used", "reason", "bnb_dx", "bnb_dy", "bnb_dz", "bnb_dheading_deg",
    "bnb_sd_x", "bnb_sd_y", "bnb_sd_z", "bnb_sd_heading_deg", "ref_dx", "ref_dy", "ref_dz",
    "ref_dheading_deg", "ref_sd_x", "ref_sd_y", "ref_sd_z", "ref_sd_heading_deg", "fit_bnb_m",
    "fit_refined_m", "pairs_bnb", "pairs_refined", "iterations", "converged", "at_box_edge",
    "hue_offset", "n_data", "n_model", "moved_xy_m", "moved_z_m", "moved_heading_deg", "disagree_xy_m",
    "disagree_z_m", "disagree_heading_deg", "objective_spread_m", "splat_m", "splat_fit_gain", "seconds",
]


def _in_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.all((points >= lo) & (points <= hi), axis=1)


def fit_error(tree: cKDTree, normals: np.ndarray, moved: np.ndarray, radius_m: float,
              truncate_m: float | None = None) -> tuple[float, int]:
    """Mean point-to-plane distance ``|n . (m - p)|`` of the moved data points to their nearest
    model point within ``radius_m``, and the number of such pairs: Eq. 4.9 with the distance
    along the model normal (inferred: the plain nearest distance is dominated by the sampling and
    barely changes with a few millimetres of misalignment). With ``truncate_m`` each distance
    counts at most that much (a pair of different surfaces, e.g. the two sides of a stem, then
    weighs as little as in the robust ICP; inferred)."""
    res = np.abs(plane_residuals(tree, normals, moved, radius_m))
    if res.size == 0:
        return np.nan, 0
    if truncate_m is not None:
        res = np.minimum(res, truncate_m)
    return float(res.mean()), int(res.size)


def robust_scale(tree: cKDTree, normals: np.ndarray, moved: np.ndarray, radius_m: float) -> float:
    """1.4826 x the median absolute deviation of the point-to-plane distances (robust sigma)."""
    res = plane_residuals(tree, normals, moved, radius_m)
    if res.size == 0:
        return np.nan
    return float(1.4826 * np.median(np.abs(res - np.median(res))))


def refine_pair(
    scan_xyz: np.ndarray,
    ref_xyz: np.ndarray,
    pose,
    sd,
    scan_hue=None,
    ref_hue=None,
    settings: RefineSettings | None = None,
) -> dict:
    """Refine one registration (module doc); returns one row of :data:`REFINE_COLUMNS`."""
    s = settings or RefineSettings()
    t0 = time.perf_counter()
    pose = np.asarray(pose, dtype=np.float64)
    sd = np.nan_to_num(np.asarray(sd, dtype=np.float64), nan=0.0)
    row = dict.fromkeys(REFINE_COLUMNS, np.nan)
    row.update({f"bnb_{k}": v for k, v in zip(POSE, pose, strict=True)})
    row.update({f"bnb_{k}": v for k, v in zip(SD, sd, strict=True)})
    row.update(used="branch_and_bound", reason="", converged=False, at_box_edge=False, iterations=0)
    colour = scan_hue is not None and ref_hue is not None
    method = resolved_method(s, colour)
    row["method"] = method
    if method == "none":
        row["reason"] = "refinement switched off"
        return row

    data, model = np.asarray(scan_xyz, dtype=np.float64), np.asarray(ref_xyz, dtype=np.float64)
    keep_d, keep_m = crop_mask(data, s), crop_mask(model, s)
    data, model = data[keep_d], model[keep_m]
    hd = np.asarray(scan_hue)[keep_d] if colour else None
    hm = np.asarray(ref_hue)[keep_m] if colour else None
    r0, t0v = pose4_to_matrix(pose)
    moved = data @ r0.T + t0v
    if len(data) == 0 or len(model) == 0:
        row["reason"] = "no points within range"
        return row
    margin = s.overlap_margin_m
    sel_d = _in_box(moved, model.min(axis=0) - margin, model.max(axis=0) + margin)
    sel_m = _in_box(model, moved.min(axis=0) - margin, moved.max(axis=0) + margin)
    data, model = data[sel_d], model[sel_m]
    hd = hd[sel_d] if colour else None
    hm = hm[sel_m] if colour else None
    if len(data) < s.min_pairs or len(model) < s.min_pairs:
        row["reason"] = "too little overlap of the raw points"
        return row
    kd = voxel_subsample(data, s.data_voxel_m) if s.data_voxel_m else np.arange(len(data))
    km = voxel_subsample(model, s.model_voxel_m) if s.model_voxel_m else np.arange(len(model))
    data, model = data[kd], model[km]
    hd = hd[kd] if colour else None
    hm = hm[km] if colour else None
    row.update(n_data=len(data), n_model=len(model))

    tree3 = cKDTree(model)
    normals, _ = pca_normals(model, s.normal_k, origin=(0.0, 0.0, 0.0), tree=tree3)
    # the fit is truncated at the robust ICP's cut-off, measured once at the branch-and-bound pose
    trunc = (s.robust_k * robust_scale(tree3, normals, data @ r0.T + t0v, s.radius_m)
             if s.robust_k is not None and (method == "point_to_plane" or s.plane_polish) else None)
    fit_b, pairs_b = fit_error(tree3, normals, data @ r0.T + t0v, s.radius_m, trunc)
    row.update(fit_bnb_m=fit_b, pairs_bnb=pairs_b)
    half = (np.maximum(s.box_sigmas * sd, 1e-9) if s.guard == "box"
            else np.array([s.max_shift_m, s.max_shift_m, s.max_shift_m, s.max_turn_deg]))
    box = (pose, half)

    if method in ("hicp", "icp"):
        w = s.weight if method == "hicp" else 0.0
        if w and s.hue_offset:
            # the cameras' white balance differs between scans: remove the median hue difference
            # of spatially paired points at the start pose (inferred; the thesis assumes equal hue)
            dd, ii = tree3.query(data @ r0.T + t0v, distance_upper_bound=s.radius_m)
            ok = np.isfinite(dd)
            if ok.sum() >= s.min_pairs:
                shift = float(np.median(hm[ii[ok]] - hd[ok]))
                hd = hd + shift
                row["hue_offset"] = shift
        emb = Embedding.from_clouds(model, data @ r0.T + t0v, weight=w, scale=s.scale, box="union",
                                    hue_mode=s.hue_mode)
        index = ModelIndex.build(model, hm if w else None, emb)
        radius = s.radius_m / float(emb.scale.max())
        res = hicp(model, data, hm, hd, weight=w, init=pose, radius=radius, dof=4, box=box,
                   index=index, max_iterations=s.max_iterations)
        new_pose = res.pose4
        row.update(iterations=res.iterations, converged=res.converged)
        edge = res.hit_box
        if s.plane_polish:
            new_pose, _, its = point_to_plane_4dof(model, normals, data, new_pose, max_distance_m=s.radius_m,
                                                   iterations=s.plane_iterations, tree=tree3, box=box,
                                                   robust_k=s.robust_k)
            row["iterations"] = res.iterations + its
            rel = np.abs(np.r_[new_pose[:3] - pose[:3], wrap_deg(new_pose[3] - pose[3])])
            edge = edge or bool(np.any(rel >= half * (1 - 1e-9)))
    else:
        start = pose
        if s.open3d_start:
            mat, _, _ = open3d_point_to_plane(model, data, pose, max_distance_m=s.radius_m,
                                              model_normals=normals, max_iterations=s.max_iterations,
                                              tukey_k_m=trunc)
            start = matrix_to_pose4(mat[:3, :3], mat[:3, 3])
            start = pose + np.clip(np.r_[start[:3] - pose[:3], wrap_deg(start[3] - pose[3])], -half, half)
        new_pose, _, its = point_to_plane_4dof(model, normals, data, start, max_distance_m=s.radius_m,
                                               iterations=s.plane_iterations, tree=tree3, box=box,
                                               robust_k=s.robust_k)
        row.update(iterations=its, converged=True)
        rel = np.abs(np.r_[new_pose[:3] - pose[:3], wrap_deg(new_pose[3] - pose[3])])
        edge = bool(np.any(rel >= half * (1 - 1e-9)))
    new_pose[3] = wrap_deg(new_pose[3])
    r1, t1 = pose4_to_matrix(new_pose)
    moved = data @ r1.T + t1
    fit_r, pairs_r = fit_error(tree3, normals, moved, s.radius_m, trunc)
    dist, idx = tree3.query(moved, distance_upper_bound=s.radius_m)
    ok = np.isfinite(dist)
    cov = icp_covariance(moved[ok], model[idx[ok]], t1, normals=normals[idx[ok]], dof=4,
                         correlation_m=s.correlation_m)
    sd_r = s.sd_inflation * pose_sd(cov)
    sd_r = np.maximum(np.nan_to_num(sd_r, nan=np.inf), [s.sd_floor_m, s.sd_floor_m, s.sd_floor_z_m, s.sd_floor_deg])
    row.update({f"ref_{k}": v for k, v in zip(POSE, new_pose, strict=True)})
    row.update({f"ref_{k}": v for k, v in zip(SD, sd_r, strict=True)})
    row.update(fit_refined_m=fit_r, pairs_refined=pairs_r, at_box_edge=edge)
    if edge:
        row["reason"] = (f"refinement reached the edge of the {s.box_sigmas:g}-sigma box" if s.guard == "box" else
                         f"refinement moved to the edge of its trust region ({100 * s.max_shift_m:g} cm, "
                         f"{s.max_turn_deg:g} deg)")
    elif pairs_r < s.min_pairs:
        row["reason"] = f"only {pairs_r} point pairs after refinement"
    elif not (fit_r < fit_b * (1.0 - s.min_fit_gain)):
        row["reason"] = (f"fit not better by {100 * s.min_fit_gain:g} % ({fit_r * 1000:.3f} mm vs "
                         f"{fit_b * 1000:.3f} mm)")
    else:
        row["used"] = "refined"
    row["seconds"] = time.perf_counter() - t0
    return row


def refine_pair_two_way(scan: RefineCloud, ref: RefineCloud, pose, sd, settings: RefineSettings) -> dict:
    """Refine one registration both ways and accept it on its own fit
    (:func:`~.two_way.two_way_refine`); one row of :data:`REFINE_COLUMNS`."""
    t0 = time.perf_counter()
    pose = np.asarray(pose, dtype=np.float64)
    row = dict.fromkeys(REFINE_COLUMNS, np.nan)
    row.update({f"bnb_{k}": v for k, v in zip(POSE, pose, strict=True)})
    row.update({f"bnb_{k}": v for k, v in zip(SD, np.nan_to_num(np.asarray(sd, dtype=np.float64)), strict=True)})
    # the objective's spread (one more refinement) only for the result kept: where a splat is
    # found (every rendered pair) the pair is refined again and this first result is dropped
    res = two_way_refine(scan, ref, pose, settings, spread=False)
    splat, gain = (choose_splat(scan, ref, res["pose"], settings.splat_candidates_m, radius_m=settings.two_way_radii_m[-1],
                                normal_k=settings.normal_k, min_gain=settings.splat_min_gain)
                   if res["used"] and settings.splat_candidates_m else (0.0, np.nan))
    if splat > 0:  # refined again from the branch-and-bound pose, the renderer's widening taken back
        floor = list(settings.two_way_sd_floor)
        floor[2] = settings.splat_sd_z_per_m * splat**2  # its z no longer rests on raised ground
        res = two_way_refine(corrected(scan, splat), corrected(ref, splat), pose,
                             replace(settings, two_way_sd_floor=tuple(floor)))
    else:
        res = with_objective_spread(res, scan, ref, settings)
    if res["used"] and settings.heading_from == "both":
        gap = heading_gap_sigmas(res["pose"], res["sd"], pose, sd)
        if gap > settings.heading_agree_sigmas and not res["fit_refined_m"] < res["fit_bnb_m"]:
            res["used"] = False  # the branch and bound's pose stands (RefineSettings.heading_agree_sigmas)
            res["reason"] = (f"refined heading {abs(wrap_deg(res['pose'][3] - pose[3])):.3f} deg ({gap:.1f} sigma) "
                             "from the branch and bound's, and no better fit")
        else:
            res["pose"], res["sd"] = fuse_heading(res["pose"], res["sd"], pose, np.asarray(sd, dtype=np.float64),
                                                  res["centre"], settings.heading_agree_sigmas)
    new, dis = res["pose"], res["disagree"]
    row.update({f"ref_{k}": v for k, v in zip(POSE, new, strict=True)})
    row.update({f"ref_{k}": v for k, v in zip(SD, res["sd"], strict=True)})
    row.update(method="point_to_plane", used="refined" if res["used"] else "branch_and_bound", reason=res["reason"],
               fit_bnb_m=res["fit_bnb_m"], fit_refined_m=res["fit_refined_m"], pairs_bnb=res["pairs_bnb"],
               pairs_refined=res["pairs_refined"], iterations=res["iterations"], converged=True, at_box_edge=False,
               n_data=res["n_data"], n_model=res["n_model"],
               moved_xy_m=float(np.hypot(*(new[:2] - pose[:2]))), moved_z_m=float(new[2] - pose[2]),
               moved_heading_deg=float(wrap_deg(new[3] - pose[3])), disagree_xy_m=float(np.hypot(dis[0], dis[1])),
               disagree_z_m=float(dis[2]), disagree_heading_deg=float(dis[3]),
               objective_spread_m=float(res["spread_along"]), splat_m=splat, splat_fit_gain=gain)
    row["seconds"] = time.perf_counter() - t0
    return row


def resolved_method(s: RefineSettings, colour: bool) -> str:
    method = s.method if s.method != "auto" else ("hicp" if colour else "point_to_plane")
    return "point_to_plane" if method == "hicp" and not colour else method


def refine_registrations(
    registrations: pd.DataFrame,
    clouds: dict[str, tuple[np.ndarray, np.ndarray | None]],
    settings: RefineSettings | None = None,
    progress: Callable[[str], None] | None = None,
    prepared: dict[str, RefineCloud] | None = None,
) -> dict[str, pd.DataFrame]:
    """Refine every accepted registration; ``clouds`` maps a scan id to (levelled points,
    hue or None); ``prepared``: scans' :class:`RefineCloud` made beforehand (the per-scan
    ``refine_clouds`` asset), used by the two-way point-to-plane refinement instead of
    ``clouds`` (a scan there needs no entry in ``clouds``: ``(None, None)`` for no colour). Returns ``registrations`` (the input table, accepted rows with the refined pose
    and sigmas where they are used, plus ``refined`` and ``refine_method`` columns) and
    ``refinements`` (one :data:`REFINE_COLUMNS` row per accepted pair)."""
    s = settings or RefineSettings()
    regs = registrations.copy()
    rows = []
    accepted = regs.index[regs["status"] == "accepted"] if len(regs) else []
    prepared = dict(prepared or {})  # per scan, shared by all its pairs

    def prepared_cloud(sid: str) -> RefineCloud:
        if sid not in prepared:
            prepared[sid] = RefineCloud.from_points(clouds[sid][0], s)
        return prepared[sid]

    for k, i in enumerate(accepted):
        r = regs.loc[i]
        scan, ref = clouds.get(r["scan"]), clouds.get(r["reference"])
        if scan is None or ref is None:
            row = dict.fromkeys(REFINE_COLUMNS, np.nan)
            row.update(used="branch_and_bound", reason="range image missing", method=s.method)
        elif s.guard == "fit" and resolved_method(s, scan[1] is not None and ref[1] is not None) == "point_to_plane":
            row = refine_pair_two_way(prepared_cloud(r["scan"]), prepared_cloud(r["reference"]),
                                      r[POSE].to_numpy(float), r[SD].to_numpy(float), s)
        else:
            row = refine_pair(scan[0], ref[0], r[POSE].to_numpy(float), r[SD].to_numpy(float),
                              scan[1], ref[1], s)
        row.update(scan=r["scan"], reference=r["reference"])
        rows.append(row)
        if progress:
            progress(f"refine {k + 1}/{len(accepted)}: {r['scan']}-{r['reference']} {row['method']} "
                     f"{row['used']} ({row.get('seconds', 0.0):.1f} s) {row['reason']}")
    table = pd.DataFrame(rows, columns=REFINE_COLUMNS)
    regs["refined"] = False
    regs["refine_method"] = ""
    # the used refinements' objective difference, for the optimal map's common scale (with the
    # scope "link" it is in each link's sigma already: two_way.objective_spread)
    regs["objective_spread_m"] = np.nan
    for i, row in zip(accepted, rows, strict=True):
        regs.loc[i, "refine_method"] = row["method"]
        if row["used"] == "refined":
            regs.loc[i, POSE] = [row[f"ref_{c}"] for c in POSE]
            regs.loc[i, SD] = [row[f"ref_{c}"] for c in SD]
            regs.loc[i, "refined"] = True
            if s.objective_sd_scope == "campaign":
                regs.loc[i, "objective_spread_m"] = row.get("objective_spread_m", np.nan)
    return {"registrations": regs, "refinements": table}


def settings_digest(settings: RefineSettings) -> str:
    """Stable short hash of the settings (for the asset's code version)."""
    import hashlib
    import json

    return hashlib.sha256(json.dumps(asdict(settings), sort_keys=True).encode()).hexdigest()[:16]
