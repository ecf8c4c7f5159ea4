"""Accuracy of a campaign's outputs against the simulator's ground truth.

Poses: the estimated poses are expressed in the frame of the reference scan, as is the truth
(``truth/poses.csv``, frame of the first scan). Trees: each true tree is matched to the nearest
estimated tree within ``match_m`` (one to one, greedy by distance). ``dbh_rmse_m`` /
``dbh_bias_m`` cover every matched tree with a DBH; ``dbh_rmse_multi_m`` / ``dbh_bias_multi_m``
only those the simulator counts as visible from >= ``min_scans`` scans (the population of the
issue-5 detection target; trees seen only from far away carry the largest beam-widening error).

Features (issue 3): :func:`scan_feature_accuracy` scores one scan's cylinder segments against
the true stems (detection within 15 m, false positives, radius error), see
:func:`feature_accuracy` for the definitions.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

from forestmap_assets.core.geometry import wrap_deg


@dataclass
class Accuracy:
    poses: pd.DataFrame  # scan, ex, ey, exy, ez, eheading_deg, nx, ny, nz, nheading (error / sd)
    trees: pd.DataFrame  # truth rows with matched estimate columns
    detection_rate: float  # among trees seen from >= min_scans scans
    dbh_rmse_m: float
    dbh_bias_m: float
    position_rmse_m: float
    false_trees: int
    dbh_rmse_multi_m: float = np.nan
    dbh_bias_multi_m: float = np.nan

    def summary(self) -> dict:
        p = self.poses
        return {
            "max_xy_error_m": float(p["exy"].max()) if len(p) else np.nan,
            "max_z_error_m": float(p["ez"].abs().max()) if len(p) else np.nan,
            "max_heading_error_deg": float(p["eheading_deg"].abs().max()) if len(p) else np.nan,
            "detection_rate": self.detection_rate,
            "dbh_rmse_m": self.dbh_rmse_m,
            "dbh_bias_m": self.dbh_bias_m,
            "position_rmse_m": self.position_rmse_m,
            "false_trees": self.false_trees,
        }


def pose_errors(poses: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """Per registered scan: error of the estimate and error divided by its reported sd."""
    est = poses[poses["registered"].astype(str).str.lower().isin(["true", "1"])]
    m = est.merge(truth, on="scan", suffixes=("", "_true"))
    out = pd.DataFrame({"scan": m["scan"]})
    for c in ("x", "y", "z"):
        out[f"e{c}"] = m[c] - m[f"{c}_true"]
    out["exy"] = np.hypot(out["ex"], out["ey"])
    out["eheading_deg"] = wrap_deg((m["heading_deg"] - m["heading_deg_true"]).to_numpy(float))
    for c, sd in (("x", "sd_x"), ("y", "sd_y"), ("z", "sd_z"), ("heading", "sd_heading_deg")):
        err = out["eheading_deg"] if c == "heading" else out[f"e{c}"]
        with np.errstate(divide="ignore", invalid="ignore"):
            out[f"n{c}"] = np.where(m[sd] > 0, err / m[sd], np.nan)
    return out


def match_trees(trees: pd.DataFrame, truth: pd.DataFrame, match_m: float = 0.5) -> pd.DataFrame:
    """Truth rows with ``est_x, est_y, est_dbh_m, dist_m`` of the matched estimate (NaN if none)."""
    out = truth.copy()
    for c in ("est_tree_id", "est_x", "est_y", "est_dbh_m", "dist_m"):
        out[c] = np.nan
    if trees.empty or truth.empty:
        return out
    d = np.hypot(truth["x"].to_numpy()[:, None] - trees["x"].to_numpy()[None], truth["y"].to_numpy()[:, None] - trees["y"].to_numpy()[None])
    cost = np.where(d <= match_m, d, 1e6)
    rows, cols = linear_sum_assignment(cost)
    ok = cost[rows, cols] < 1e6
    rows, cols = rows[ok], cols[ok]
    out.loc[out.index[rows], "est_tree_id"] = trees["tree_id"].to_numpy()[cols]
    out.loc[out.index[rows], "est_x"] = trees["x"].to_numpy()[cols]
    out.loc[out.index[rows], "est_y"] = trees["y"].to_numpy()[cols]
    out.loc[out.index[rows], "est_dbh_m"] = trees["dbh_m"].to_numpy()[cols]
    out.loc[out.index[rows], "dist_m"] = d[rows, cols]
    return out


def dbh_errors(trees: pd.DataFrame, truth_trees: pd.DataFrame, *, min_scans: int = 2,
               match_m: float = 0.5) -> dict[str, float]:
    """DBH RMSE and bias (m) of ``trees`` against the truth: over every matched tree with a DBH
    (``dbh_rmse_m``, ``dbh_bias_m``) and over those visible from >= ``min_scans`` scans
    (``dbh_rmse_multi_m``, ``dbh_bias_multi_m``); ``n_dbh``, ``n_dbh_multi`` count them."""
    matched = match_trees(trees, truth_trees, match_m)
    both = matched[matched["est_dbh_m"].notna()]
    err = (both["est_dbh_m"] - both["dbh_m"]).to_numpy(float)
    multi = (both["n_visible_scans"] >= min_scans).to_numpy()

    def rmse(e):
        return float(np.sqrt(np.mean(e**2))) if e.size else np.nan

    return {"dbh_rmse_m": rmse(err), "dbh_bias_m": float(err.mean()) if err.size else np.nan,
            "dbh_rmse_multi_m": rmse(err[multi]),
            "dbh_bias_multi_m": float(err[multi].mean()) if multi.any() else np.nan,
            "n_dbh": int(err.size), "n_dbh_multi": int(multi.sum())}


def evaluate_campaign(campaign_dir: str | Path, outputs: str | Path | None = None, *, min_scans: int = 2,
                      match_m: float = 0.5) -> Accuracy:
    """Compare ``outputs/`` (poses.csv, trees.csv) with ``truth/`` of a simulated campaign."""
    root = Path(campaign_dir)
    out = Path(outputs) if outputs else root / "outputs"
    poses = pd.read_csv(out / "poses.csv")
    poses["registered"] = poses["registered"].astype(str).str.lower() == "true"
    truth_poses = pd.read_csv(root / "truth" / "poses.csv")
    trees = pd.read_csv(out / "trees.csv")
    truth_trees = pd.read_csv(root / "truth" / "trees.csv")
    pe = pose_errors(poses, truth_poses)
    matched = match_trees(trees, truth_trees, match_m)
    eligible = matched[matched["n_visible_scans"] >= min_scans]
    found = eligible["est_x"].notna()
    pos = matched["dist_m"].dropna()
    dbh = dbh_errors(trees, truth_trees, min_scans=min_scans, match_m=match_m)
    return Accuracy(
        poses=pe,
        trees=matched,
        detection_rate=float(found.mean()) if len(eligible) else np.nan,
        dbh_rmse_m=dbh["dbh_rmse_m"],
        dbh_bias_m=dbh["dbh_bias_m"],
        position_rmse_m=float(np.sqrt(np.mean(pos**2))) if len(pos) else np.nan,
        false_trees=int(len(trees) - matched["est_x"].notna().sum()),
        dbh_rmse_multi_m=dbh["dbh_rmse_multi_m"],
        dbh_bias_multi_m=dbh["dbh_bias_multi_m"],
    )


# ---- per-scan feature accuracy (issue 3) ---------------------------------------------------

def scan_stems(campaign_dir: str | Path, scan: str) -> pd.DataFrame:
    """True stems (``truth/stems.csv``, frame of the first scan) in the levelled frame of
    ``scan``, moved with ``truth/poses.csv``; adds the unit axis ``ax, ay, az``."""
    from forestmap_assets.sim.stems import stems_in_frame

    root = Path(campaign_dir)
    stems = pd.read_csv(root / "truth" / "stems.csv")
    pose = pd.read_csv(root / "truth" / "poses.csv").set_index("scan").loc[scan]
    out = stems_in_frame(stems, pose[["x", "y", "z"]].to_numpy(float),
                         float(pose["heading_deg"])).reset_index(drop=True)
    lean = np.column_stack([out["lean_x"], out["lean_y"], np.ones(len(out))])
    axis = lean / np.linalg.norm(lean, axis=1, keepdims=True)
    out["ax"], out["ay"], out["az"] = axis[:, 0], axis[:, 1], axis[:, 2]
    return out


def visible_stem_length(xyz: np.ndarray, kind: np.ndarray, tree_id: np.ndarray,
                        stems: pd.DataFrame, *, max_range_m: float = 20.0,
                        max_gap_m: float = 0.25) -> np.ndarray:
    """Visible trunk length (m) of every row of ``stems`` in one scan, from per-pixel labels.

    The simulator's visibility rule (``sim.campaign.visible_trees``) applied to one scan:
    stem-labelled returns within ``max_range_m`` of the scanner, sorted by height above the
    stem base; consecutive heights further apart than ``max_gap_m`` do not count as covered.
    ``xyz`` are the (noisy) levelled points of the scan, ``kind``/``tree_id`` its labels.
    """
    from forestmap_assets.sim.scene_mesh import KIND_STEM

    pts = np.asarray(xyz, float).reshape(-1, 3)
    sel = (np.asarray(kind).ravel() == KIND_STEM) & np.all(np.isfinite(pts), axis=1)
    sel &= np.linalg.norm(pts, axis=1) <= max_range_m
    out = np.zeros(len(stems))
    if not sel.any() or len(stems) == 0:
        return out
    tid = np.asarray(tree_id).ravel()[sel].astype(np.int64)
    pos = pd.Series(np.arange(len(stems)), index=stems["tree_id"].to_numpy(int))
    row = pos.reindex(tid).to_numpy()
    ok = np.isfinite(row)
    row = row[ok].astype(np.int64)
    h = pts[sel][ok, 2] - stems["z_base"].to_numpy(float)[row]
    order = np.lexsort((h, row))
    row, h = row[order], h[order]
    dh = np.diff(h)
    covered = np.where((row[1:] == row[:-1]) & (dh <= max_gap_m), dh, 0.0)
    return np.bincount(row[1:], weights=covered, minlength=len(stems))[:len(stems)]


def match_cylinders_to_stems(cyl: pd.DataFrame, stems: pd.DataFrame, *,
                             tol_min_m: float = 0.10) -> tuple[np.ndarray, np.ndarray]:
    """Owner stem (row of ``stems``, -1 none) of each cylinder and the true radius there.

    A cylinder belongs to a stem when the middle of its axis lies within
    ``max(r_true, tol_min_m)`` of the true stem axis, measured perpendicular to that axis, at a
    height between the stem's base and top; ``r_true`` is the stem's mean radius
    ``r_base - taper h`` at the cylinder's middle (``stems`` from :func:`scan_stems`). When two
    stems qualify the nearer axis wins.
    """
    n = len(cyl)
    owner = np.full(n, -1, np.int64)
    r_true = np.full(n, np.nan)
    if n == 0 or len(stems) == 0:
        return owner, r_true
    mid = 0.5 * (cyl[["x0", "y0", "z0"]].to_numpy(float) + cyl[["x1", "y1", "z1"]].to_numpy(float))
    base = stems[["x_base", "y_base", "z_base"]].to_numpy(float)
    axis = stems[["ax", "ay", "az"]].to_numpy(float)
    w = mid[:, None, :] - base[None]  # (cyl, stem, 3)
    along = np.einsum("csk,sk->cs", w, axis)
    perp = np.linalg.norm(w - along[..., None] * axis[None], axis=2)
    h = along * axis[None, :, 2]  # vertical height above the base
    r = stems["r_base_m"].to_numpy(float)[None] - stems["taper_m_per_m"].to_numpy(float)[None] * h
    ok = (perp <= np.maximum(r, tol_min_m)) & (h >= 0) & (h <= stems["height_m"].to_numpy()[None])
    d = np.where(ok, perp, np.inf)
    best = np.argmin(d, axis=1)
    has = np.isfinite(d[np.arange(n), best])
    owner[has] = best[has]
    r_true[has] = r[np.arange(n), best][has]
    return owner, r_true


def feature_accuracy(cyl: pd.DataFrame, stems: pd.DataFrame, visible_m: np.ndarray, *,
                     max_distance_m: float = 15.0, min_visible_m: float = 1.0,
                     tol_min_m: float = 0.10) -> dict:
    """Stem detection and radius accuracy of one scan's cylinders (issue 3 targets).

    Target stems: axis within ``max_distance_m`` (horizontal, at the base) of the scanner and
    at least ``min_visible_m`` of visible trunk. A target is *found* when at least one cylinder
    belongs to it (:func:`match_cylinders_to_stems`). *False positives*: cylinders that belong
    to no stem at all (branches, saplings and phantoms alike), as a share of all cylinders.
    Radius error: per found target, the length-weighted mean of (cylinder radius - true radius
    at the cylinder's middle); RMSE and bias over the found targets. Returns a dict with the
    counts, rates, ``rmse_m``, ``bias_m`` and the per-stem table ``per_stem``.
    """
    owner, r_true = match_cylinders_to_stems(cyl, stems, tol_min_m=tol_min_m)
    dist = np.hypot(stems["x_base"].to_numpy(float), stems["y_base"].to_numpy(float))
    target = (dist <= max_distance_m) & (np.asarray(visible_m) >= min_visible_m)
    length = cyl["length_m"].to_numpy(float) if len(cyl) else np.zeros(0)
    err = cyl["radius_m"].to_numpy(float) - r_true if len(cyl) else np.zeros(0)
    sel = owner >= 0
    n_stem = len(stems)
    lw = np.bincount(owner[sel], weights=length[sel], minlength=n_stem)
    lwe = np.bincount(owner[sel], weights=(length * err)[sel], minlength=n_stem)
    ncyl = np.bincount(owner[sel], minlength=n_stem)
    with np.errstate(invalid="ignore", divide="ignore"):
        stem_err = np.where(ncyl > 0, lwe / lw, np.nan)
    per_stem = pd.DataFrame({"tree_id": stems["tree_id"].to_numpy(int), "distance_m": dist,
                             "visible_m": np.asarray(visible_m, float),
                             "r_bh_m": stems["r_base_m"] - stems["taper_m_per_m"] * 1.3,
                             "target": target, "n_cylinders": ncyl, "radius_error_m": stem_err})
    found = target & (ncyl > 0)
    e = stem_err[found]
    n_fp = int(np.count_nonzero(~sel))
    return {
        "stems": int(target.sum()), "found": int(found.sum()),
        "detection_rate": float(found.sum() / target.sum()) if target.any() else np.nan,
        "n_cylinders": int(len(cyl)), "false_positives": n_fp,
        "false_positive_rate": float(n_fp / len(cyl)) if len(cyl) else 0.0,
        "rmse_m": float(np.sqrt(np.mean(e**2))) if e.size else np.nan,
        "bias_m": float(np.mean(e)) if e.size else np.nan,
        "per_stem": per_stem,
    }


def scan_feature_accuracy(campaign_dir: str | Path, scan: str, cylinders: pd.DataFrame,
                          **kwargs) -> dict:
    """:func:`feature_accuracy` of ``cylinders`` (levelled frame of ``scan``) for one scan of a
    simulated campaign written with labels (``truth/labels/<scan>.npz``)."""
    from forestmap_assets.io.readers import read_scan

    root = Path(campaign_dir)
    stems = scan_stems(root, scan)
    img = read_scan(next((root / "scans").glob(f"{scan}.*")))
    with np.load(root / "truth" / "labels" / f"{scan}.npz") as z:
        kind, tree = z["kind"], z["tree_id"]
    vis = visible_stem_length(img.xyz, kind, tree, stems)
    return feature_accuracy(cylinders, stems, vis, **kwargs)
