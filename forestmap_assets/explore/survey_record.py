"""What a virtual survey records (men_spec 7.7): the per-scan rows of ``OUT/explore/steps.csv``
(plan, truth, registration, coverage), the registration and tree checks against the truth, the plan
after scan k (``step_<k>.png``, ``proposals_<k>.csv``) and the survey's result."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from forestmap_assets.explore.survey_map import SurveyMap

STEP_COLUMNS = [
    "step",
    "scan",
    "reference",
    "planned_x",
    "planned_y",
    "true_x",
    "true_y",
    "true_heading_deg",
    "expected_new_m2",
    "predicted_common_stems",
    "predicted_overlap",
    "path_m",
    "registered",
    "pose_error_m",
    "heading_error_deg",
    "coverage",
    "gain",
    "trees",
    "trees_with_dbh",
    "pipeline_seconds",
    "plan_seconds",
]


def registration_check(folder: Path, poses: pd.DataFrame, sid: str) -> tuple[bool, float, float]:
    from forestmap_assets.sim.evaluate import pose_errors

    truth = pd.read_csv(folder / "truth" / "poses.csv")
    row = poses[poses["scan"] == sid]
    if row.empty or not bool(row["registered"].iloc[0]):
        return False, np.nan, np.nan
    pe = pose_errors(poses.assign(registered=poses["registered"].astype(bool)), truth)
    pe = pe[pe["scan"] == sid]
    return True, float(pe["exy"].iloc[0]), float(abs(pe["eheading_deg"].iloc[0]))


def tree_counts(folder: Path, trees: pd.DataFrame, match_m: float = 0.5) -> tuple[int, int, float]:
    """Truth trees matched by a mapped tree, those with a DBH, and the DBH RMSE (m)."""
    from forestmap_assets.sim.evaluate import match_trees

    truth = pd.read_csv(folder / "truth" / "trees.csv")
    m = match_trees(trees, truth, match_m)
    found = m["est_x"].notna()
    dbh = m["est_dbh_m"].notna()
    err = (m.loc[dbh, "est_dbh_m"] - m.loc[dbh, "dbh_m"]).to_numpy()
    return int(found.sum()), int(dbh.sum()), float(np.sqrt(np.mean(err**2))) if err.size else np.nan


@dataclass
class ExploreResult:
    folder: Path
    steps: pd.DataFrame
    coverage: float
    stop_reason: str
    trees: int
    trees_with_dbh: int
    dbh_rmse_m: float
    path_m: float
    seconds: float
    positions_world: np.ndarray

    @property
    def all_registered(self) -> bool:
        return bool(self.steps["registered"].all())


def save_plan(out: Path, k: int, sm: SurveyMap, title: str) -> None:
    from forestmap_assets.outputs.figures.exploration_map import exploration_figure

    sm.plan.proposals.to_csv(
        out / "explore" / f"proposals_{k:02d}.csv", index=False, float_format="%.4f"
    )
    fig = exploration_figure(sm.plan, sm.elevation, sm.stems, sm.scans, title=title)
    fig.savefig(out / "explore" / f"step_{k:02d}.png", dpi=90)
