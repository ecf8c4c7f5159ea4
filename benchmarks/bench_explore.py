"""Where to scan next: the planner against a regular grid and random positions.

For the same virtual plots (``--plots`` seeds, ``--plot-size`` m, ``--trees`` stems) and the
same number of scans (``--budget``), three surveys each run the whole pipeline:

* **planner**: ``forestmap explore`` (one scan, pipeline, plan, walk, scan, ...), with the stop
  rule off so that it spends the budget (the scan where the default rule, gain < 1 % of the
  plot, would have stopped is reported);
* **grid**: a regular grid, one position at the centre of each cell of a partition of the plot;
* **random**: the start position, then random positions one can stand at inside the plot;
* **thesis** (``--thesis``): the thesis's own rule (heading, zone, 10 farthest frontier cells,
  50 % area overlap within 8 m).

The surveyor model (walking error, compass prior, pairs with up to 2 earlier scans) is the same
for all. Reported per survey: coverage of the plot by the map (exploration grid, 0.25 m cells),
true trees found by the map (within 0.5 m) and found with a DBH, DBH RMSE, scans registered
(and the largest pose error against the truth), walking distance (planner: planned paths;
baselines: straight lines between consecutive positions), wall time. Writes its section of
``benchmarks/results.md`` between ``<!-- explore:start -->`` and ``<!-- explore:end -->``.

Usage: ``python benchmarks/bench_explore.py [--plots 0,1] [--plot-size 30] [--trees 30]
[--budget 5] [--resolution quarter] [--registration-method fast|thesis] [--thesis]``
(``--thesis`` adds the thesis's own rule).
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from results_md import write_section  # noqa: E402

NAME = "explore"


def _cell(v) -> str:
    """A table cell: empty for missing values, whole numbers without a decimal point."""
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return ""
    if isinstance(v, float) and v.is_integer():
        return str(int(v))
    return str(v)


def summarise(kind: str, seed: int, res) -> dict:
    steps = res.steps
    reg = steps["registered"].astype(bool)
    err = steps.loc[reg, "pose_error_m"].astype(float)
    gains = steps["gain"].astype(float).to_numpy()
    stop_at = next(
        (int(i) + 1 for i in range(1, len(gains)) if np.isfinite(gains[i]) and gains[i] < 0.01),
        None,
    )
    return {
        "plot": seed,
        "survey": kind,
        "scans": len(steps),
        "coverage_pct": round(100 * res.coverage, 1),
        "trees_found": res.trees,
        "with_dbh": res.trees_with_dbh,
        "dbh_rmse_cm": round(100 * res.dbh_rmse_m, 2) if np.isfinite(res.dbh_rmse_m) else np.nan,
        "registered": f"{int(reg.sum())}/{len(steps)}",
        "max_pose_error_m": round(float(err.max()), 3) if len(err) else np.nan,
        "walk_m": round(res.path_m, 1),
        "seconds": round(res.seconds, 0),
        "stop_rule_scans": stop_at if stop_at is not None else len(steps),
        "coverage_by_step": " ".join(f"{100 * c:.0f}" for c in steps["coverage"].dropna()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plots", default="0,1")
    ap.add_argument("--plot-size", type=float, default=30.0)
    ap.add_argument("--trees", type=int, default=30)
    ap.add_argument("--budget", type=int, default=5)
    ap.add_argument("--resolution", default="quarter", choices=["full", "half", "quarter"])
    ap.add_argument(
        "--thesis", action="store_true", help="also run the thesis's own selection rule"
    )
    ap.add_argument(
        "--registration-method",
        choices=["fast", "thesis"],
        default="fast",
        help="registration evaluator (same lattice maximum; 'thesis' is slower)",
    )
    ap.add_argument(
        "--work", type=Path, default=None, help="keep the surveys here (default: a temp dir)"
    )
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument(
        "--resume", action="store_true", help="keep the completed surveys of --work/rows.csv"
    )
    ap.add_argument("--note", default="", help="a sentence added to the results section")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_explore_"))
    work.mkdir(parents=True, exist_ok=True)
    os.environ["FORESTMAP_HOME"] = str(work / "home")  # an isolated store and instance
    os.environ["DAGSTER_HOME"] = str(Path(os.environ["FORESTMAP_HOME"]) / "dagster")

    from forestmap_assets.explore.baseline_survey import (
        grid_positions,
        random_positions,
        survey_positions,
    )
    from forestmap_assets.explore.planned_survey import explore
    from forestmap_assets.explore.virtual_plot import make_plot
    from forestmap_assets.params.men import ExplorationConfig

    seeds = [int(s) for s in args.plots.split(",") if s.strip()]
    light = {"cloud_spacing_m": None, "picture": False, "report": False}
    common = dict(
        plot_size=args.plot_size,
        trees=args.trees,
        resolution=args.resolution,
        export_kwargs=light,
        campaign_params={"registration": {"method": args.registration_method}},
    )
    rows = []
    done: set[tuple[int, str]] = set()
    if args.resume and (work / "rows.csv").is_file():  # keep the surveys that completed
        old = pd.read_csv(work / "rows.csv")
        if "failed" in old:
            old = old[old["failed"].isna()].drop(columns="failed")
        rows = old.to_dict("records")
        done = {(int(r["plot"]), str(r["survey"])) for r in rows}

    def say(msg: str) -> None:
        print(msg, flush=True)

    def record(kind: str, seed: int, run) -> None:
        """Run one survey; a pipeline failure is a row of the table, not the end of the run."""
        if (seed, kind) in done:
            say(f"   (kept from {work / 'rows.csv'})")
            return
        try:
            rows.append(summarise(kind, seed, run()))
        except Exception as exc:  # noqa: BLE001 - reported in the table
            reason = (
                str(exc).strip().splitlines()[0][:120] if str(exc).strip() else type(exc).__name__
            )
            rows.append({"plot": seed, "survey": kind, "failed": reason})
        say(str(rows[-1]))
        pd.DataFrame(rows).to_csv(work / "rows.csv", index=False)

    thesis = ExplorationConfig(overlap_rule="area", coverage_radius_m=8.0)
    for seed in seeds:
        for kind in ["planner"] + (["thesis"] if args.thesis else []):
            say(f"== plot {seed}: {kind}")
            record(
                kind,
                seed,
                lambda kind=kind, seed=seed: explore(
                    work / f"p{seed}_{kind}",
                    seed=seed,
                    budget=args.budget,
                    min_gain=0.0,
                    strategy="coverage" if kind == "planner" else "thesis",
                    config=None if kind == "planner" else thesis,
                    progress=say,
                    **common,
                ),
            )
        vp, _ = make_plot(args.plot_size, args.trees, seed, resolution=args.resolution)
        layouts = {
            "grid": grid_positions(args.budget, args.plot_size),
            "random": random_positions(vp, args.budget, np.random.default_rng(1000 + seed)),
        }
        for kind, positions in layouts.items():
            say(f"== plot {seed}: {kind}")
            record(
                kind,
                seed,
                lambda kind=kind, seed=seed, positions=positions: survey_positions(
                    work / f"p{seed}_{kind}", positions, seed=seed, progress=say, **common
                ),
            )
    table = pd.DataFrame(rows)
    print(table.to_string(index=False))
    if args.no_write:
        return
    cols = [
        "plot",
        "survey",
        "scans",
        "coverage_pct",
        "coverage_by_step",
        "trees_found",
        "with_dbh",
        "dbh_rmse_cm",
        "registered",
        "max_pose_error_m",
        "walk_m",
        "stop_rule_scans",
        "seconds",
    ]
    if "failed" in table:
        cols.append("failed")
    table = table.reindex(columns=cols)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in table[cols].itertuples(index=False):
        lines.append("| " + " | ".join(_cell(v) for v in r) + " |")
    mean = (
        table.groupby("survey", sort=False)[["coverage_pct", "trees_found", "with_dbh"]]
        .mean()
        .round(1)
    )
    summary = [
        "| survey | mean coverage % | mean trees found | mean trees with DBH |",
        "|---|---|---|---|",
    ]
    summary += [
        f"| {k} | {r.coverage_pct} | {r.trees_found} | {r.with_dbh} |" for k, r in mean.iterrows()
    ]
    body = "\n".join(
        [
            "## Next vantage positions: planner vs grid vs random (`benchmarks/bench_explore.py`)",
            "",
            f"`python benchmarks/bench_explore.py --plots {args.plots} --plot-size "
            f"{args.plot_size:g} --trees {args.trees} --budget {args.budget} --resolution "
            f"{args.resolution} --registration-method {args.registration_method}"
            f"{' --thesis' if args.thesis else ''}` on {platform.machine()}, "
            f"{os.cpu_count()} cores shared with other jobs, Python "
            f"{platform.python_version()}, {time.strftime('%Y-%m-%d')}; "
            f"{table['seconds'].sum():.0f} s of surveys"
            + (" (surveys accumulated over interrupted runs with `--resume`)." if done else ".")
            + (f" {args.note}" if args.note else ""),
            "",
            f"Virtual plots of {args.plot_size:g} m x {args.plot_size:g} m with {args.trees} "
            f"trees (understorey, crowns), {args.resolution}-resolution scans, {args.budget} "
            "scans per survey, the same surveyor model (0.3 m walking error, 5 deg compass "
            "prior, pairs with up to 2 earlier scans). Coverage: share of the plot's 0.25 m "
            "cells the final map classifies as ground or obstacle (heights above the local "
            "ground, 15 m map range); `coverage_by_step` after each scan (planned surveys). "
            "Trees: true trees matched by a mapped tree within 0.5 m, and those with a DBH. "
            "`stop_rule_scans`: where the planner's default stop rule (gain < 1 % of the plot) "
            "would have ended the survey. Walking: planned shortest paths (planner) or straight "
            "lines (baselines). Peers are the two baselines, run in the same process"
            + (
                "; `thesis` is the thesis's own rule (preferred heading, zone, 10 farthest "
                "frontier cells, 50 % predicted area overlap within 8 m) in the same loop."
                if args.thesis
                else "."
            ),
            "",
            *lines,
            "",
            *summary,
        ]
    )
    write_section(NAME, body)


if __name__ == "__main__":
    main()
