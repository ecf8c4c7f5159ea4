"""Accuracy of a campaign's outputs against the simulator's ground truth.

Poses: the estimated poses are expressed in the frame of the reference scan, as is the truth
(``truth/poses.csv``, frame of the first scan). Trees: each true tree is matched to the nearest
estimated tree within ``match_m`` (one to one, greedy by distance).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

from ..core.geometry import wrap_deg


@dataclass
class Accuracy:
    poses: pd.DataFrame  # scan, ex, ey, exy, ez, eheading_deg, nx, ny, nz, nheading (error / sd)
    trees: pd.DataFrame  # truth rows with matched estimate columns
    detection_rate: float  # among trees seen from >= min_scans scans
    dbh_rmse_m: float
    dbh_bias_m: float
    position_rmse_m: float
    false_trees: int

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
    both = matched[matched["est_dbh_m"].notna()]
    err = both["est_dbh_m"] - both["dbh_m"]
    pos = matched["dist_m"].dropna()
    return Accuracy(
        poses=pe,
        trees=matched,
        detection_rate=float(found.mean()) if len(eligible) else np.nan,
        dbh_rmse_m=float(np.sqrt(np.mean(err**2))) if len(err) else np.nan,
        dbh_bias_m=float(err.mean()) if len(err) else np.nan,
        position_rmse_m=float(np.sqrt(np.mean(pos**2))) if len(pos) else np.nan,
        false_trees=int(len(trees) - matched["est_x"].notna().sum()),
    )
