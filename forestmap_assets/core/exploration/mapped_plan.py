"""Where to scan next on a mapped campaign (Men 2012 ch. 3.7-3.8, 6; men_spec 7): the exploration
grid from the stored observed surfaces and the integrated map, the ranked next vantage positions,
and the ``next_vantage_points`` tables."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd

from forestmap_assets.core.exploration.candidates import VantagePlan
from forestmap_assets.core.exploration.frontier import CLASS_NAMES
from forestmap_assets.core.exploration.grid import build_grid
from forestmap_assets.core.exploration.planner import plan_next_vantage
from forestmap_assets.core.features.elevation import elevation_from_table
from forestmap_assets.params.men import ExplorationConfig


def stems_from_trees(trees: pd.DataFrame, default_radius_m: float = 0.1) -> np.ndarray:
    """Mapped stems as ``x, y, r`` rows (r = DBH / 2, ``default_radius_m`` where DBH is missing)."""
    if trees is None or not len(trees):
        return np.zeros((0, 3))
    r = (trees["dbh_m"].astype(float) / 2).fillna(default_radius_m).to_numpy()
    return np.column_stack([trees["x"].to_numpy(float), trees["y"].to_numpy(float), r])


def plan_from_map(
    surfaces: dict[str, pd.DataFrame | dict],
    integrated_map: dict[str, pd.DataFrame],
    trees: pd.DataFrame,
    config: ExplorationConfig,
    *,
    current_xy=None,
    default_voxel_m: float = 0.05,
) -> tuple[VantagePlan, object, np.ndarray]:
    """Exploration grid, classes, coverage and ranked next vantage positions of a mapped campaign.

    ``surfaces``: scan id -> ``occlusion_boundaries`` bundle (or its ``surface`` table);
    ``integrated_map``: the bundle with ``elevation`` and registered ``scans``. Returns the plan,
    the merged elevation grid and the stems (``x, y, r``)."""
    elevation = elevation_from_table(integrated_map["elevation"])
    scans = integrated_map["scans"]
    scans = scans[scans["registered"].astype(bool)] if "registered" in scans else scans
    poses = {r.scan: (r.x, r.y, r.z, r.heading_deg) for r in scans.itertuples()}
    items = []
    for sid, pose in poses.items():
        bundle = surfaces.get(sid)
        if bundle is None:
            continue
        if isinstance(bundle, dict):
            table = bundle["surface"]
            info = bundle.get("info")
            voxel = (
                float(info["voxel_m"].iloc[0])
                if info is not None and len(info)
                else default_voxel_m
            )
        else:
            table, voxel = bundle, default_voxel_m
        items.append((table, pose, voxel))
    scan_xy = scans[["x", "y"]].to_numpy(float)
    steps = [
        float(b["info"]["azimuth_step_deg"].iloc[0])
        for b in surfaces.values()
        if isinstance(b, dict) and "info" in b and "azimuth_step_deg" in b["info"]
    ]
    if config.angular_step_deg is None and steps:  # the scanner's step limits stem detection
        config = replace(config, angular_step_deg=float(np.median(steps)))
    ground_default = float(scans["z"].min()) - 1.5 if len(scans) else -1.5
    grid = build_grid(
        items,
        elevation,
        scan_xy if len(scan_xy) else np.zeros((1, 2)),
        config,
        default_ground_z=ground_default,
    )
    stems = stems_from_trees(trees)
    incomplete = trees["dbh_m"].isna().to_numpy() if trees is not None and len(trees) else None
    ids = scans["scan"].astype(str).tolist()
    plan = plan_next_vantage(
        grid, stems, scan_xy, ids, config, current_xy=current_xy, incomplete=incomplete
    )
    return plan, elevation, stems


def plan_tables(plan: VantagePlan) -> dict[str, pd.DataFrame]:
    """The ``next_vantage_points`` bundle: ``proposals``, ``paths`` (rank, step, x, y),
    ``coverage`` (one row) and ``cells`` (every plot cell: class, ground, density, frontier)."""
    grid = plan.grid
    paths = [
        pd.DataFrame({"rank": rank, "step": np.arange(len(p)), "x": p[:, 0], "y": p[:, 1]})
        for rank, p in sorted(plan.paths.items())
    ]
    paths_df = (
        pd.concat(paths, ignore_index=True)
        if paths
        else pd.DataFrame(
            {
                "rank": pd.Series(dtype="int64"),
                "step": pd.Series(dtype="int64"),
                "x": pd.Series(dtype="float64"),
                "y": pd.Series(dtype="float64"),
            }
        )
    )
    ix, iy = np.nonzero(grid.in_plot)
    xy = grid.cell_xy(ix, iy)
    cells = pd.DataFrame(
        {
            "ix": ix.astype(np.int32),
            "iy": iy.astype(np.int32),
            "x": xy[:, 0],
            "y": xy[:, 1],
            "cell_class": np.asarray(CLASS_NAMES, dtype=object)[plan.classes[ix, iy]],
            "ground_z": grid.ground_z[ix, iy] if grid.ground_z is not None else np.nan,
            "points_per_m2": grid.points[ix, iy] / grid.cell_m**2,
            "frontier": plan.frontier[ix, iy],
        }
    )
    coverage = pd.DataFrame(
        [
            {
                **plan.coverage,
                "cell_m": grid.cell_m,
                "current_ix": plan.current[0],
                "current_iy": plan.current[1],
            }
        ]
    )
    proposals = plan.proposals.copy()
    proposals["reference_scan"] = proposals["reference_scan"].fillna("").astype(str)
    return {"proposals": proposals, "paths": paths_df, "coverage": coverage, "cells": cells}
