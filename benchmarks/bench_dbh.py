"""DBH from the merged breast-height slice against the cylinder DBH (issue 19).

For each stem model (``realistic``, ``circular``) and seed: simulate a campaign (default 6
scans, half resolution), run the pipeline, then compute the tree list of the same integrated
map and stored range images both ways, ``trees.dbh_method`` ``cylinders`` (the DBH before issue
19) and ``slice`` (core/mapping/stem_slices.py), and compare with the truth (matched trees,
``sim.evaluate.dbh_errors``). Prints a table and writes the ``dbh`` section of
``benchmarks/results.md``.

    python benchmarks/bench_dbh.py --seeds 1 2 --resolution half --work /tmp/dbh
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from results_md import write_section  # noqa: E402


def tree_lists(root: Path) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Trees of the stored integrated map by cylinders and by slice, and the slice fits."""
    from forestmap_assets.access import load_asset
    from forestmap_assets.core.features.elevation import elevation_from_table
    from forestmap_assets.core.mapping.stem_slices import merged_slice_dbh
    from forestmap_assets.core.mapping.trees import merge_trees
    from forestmap_assets.io.campaign import load_campaign

    camp = load_campaign(root)
    im = load_asset("integrated_map", campaign=root)
    grid = elevation_from_table(im["elevation"])
    cylinders, tree_of = merge_trees(im["cylinders"], grid)
    poses = im["scans"]
    clouds = {}
    for sid in poses["scan"]:
        image = load_asset("range_images", campaign=root, scan=sid)
        clouds[sid] = image.xyz[image.valid]
    sliced, fits = merged_slice_dbh(cylinders, im["cylinders"], tree_of, clouds, poses, camp.params.trees)
    return cylinders, sliced, fits


def run_one(stems: str, seed: int, args, work: Path) -> dict:
    from forestmap_assets.orchestration.runner import run_campaign
    from forestmap_assets.sim import simulate_campaign
    from forestmap_assets.sim.evaluate import dbh_errors, match_trees

    res = "" if args.resolution == "half" else args.resolution
    root = work / f"{stems}{res}_s{seed}"  # e.g. realistic_s1 (half), realisticfull_s1
    if not (root / "campaign.yaml").exists():
        simulate_campaign(root, scans=args.scans, seed=seed, resolution=args.resolution, stems=stems)
    os.environ["FORESTMAP_HOME"] = str(work / f"home_{root.name}")
    os.environ["DAGSTER_HOME"] = str(work / f"home_{root.name}" / "dagster")
    t0 = time.perf_counter()
    summary = run_campaign(root, progress=lambda m: None)
    if summary.failures:
        return {"stems": stems, "seed": seed, "failed": summary.failures[0][2]}
    seconds = time.perf_counter() - t0
    t0 = time.perf_counter()
    cyl, sliced, fits = tree_lists(root)
    slice_seconds = time.perf_counter() - t0
    truth = pd.read_csv(root / "truth" / "trees.csv")
    old, new = dbh_errors(cyl, truth), dbh_errors(sliced, truth)
    # the same matched trees for both: those with a DBH either way (the slice keeps every DBH)
    m_old, m_new = match_trees(cyl, truth), match_trees(sliced, truth)
    both = m_old["est_dbh_m"].notna() & m_new["est_dbh_m"].notna()
    e_old = (m_old.loc[both, "est_dbh_m"] - m_old.loc[both, "dbh_m"]).to_numpy(float)
    e_new = (m_new.loc[both, "est_dbh_m"] - m_new.loc[both, "dbh_m"]).to_numpy(float)
    used = fits[fits["reason"] == ""]
    return {"stems": stems, "seed": seed, "seconds": seconds, "slice_seconds": slice_seconds,
            "n": int(both.sum()), "trees": len(cyl), "slice_used": len(used),
            "fallback": int((fits["reason"] != "").sum() - sliced["dbh_m"].isna().sum()),
            "err_old": e_old, "err_new": e_new,
            **{f"{k}_old": v for k, v in old.items()}, **{f"{k}_new": v for k, v in new.items()}}


def rmse(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def report(rows: list[dict], args) -> str:
    cm = 100.0
    lines = [
        f"Simulated 40 m plots, {args.scans} scans, {args.resolution} resolution, pipeline run once "
        "per campaign; the tree list of the same integrated map and range images computed with "
        "`trees.dbh_method: cylinders` (before issue 19) and `slice` (the merged breast-height "
        "slice, core/mapping/stem_slices.py). Matched trees with a DBH both ways (truth match "
        "within 0.5 m); bias = mean(estimate - truth). "
        f"Machine: {platform.machine()}, {os.cpu_count()} cores (shared).",
        "",
        "| stems | seed | matched trees | slice used / trees | DBH RMSE cylinders (cm) | DBH RMSE slice (cm) | bias cylinders (cm) | bias slice (cm) | RMSE trees seen from >= 2 scans, cylinders -> slice (cm) | slice step (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "failed" in r:
            lines.append(f"| {r['stems']} | {r['seed']} | failed: {r['failed']} ||||||||")
            continue
        lines.append(
            f"| {r['stems']} | {r['seed']} | {r['n']} | {r['slice_used']}/{r['trees']} | "
            f"{cm * rmse(r['err_old']):.2f} | **{cm * rmse(r['err_new']):.2f}** | "
            f"{cm * r['err_old'].mean():+.2f} | {cm * r['err_new'].mean():+.2f} | "
            f"{cm * r['dbh_rmse_multi_m_old']:.2f} -> {cm * r['dbh_rmse_multi_m_new']:.2f} | "
            f"{r['slice_seconds']:.1f} |")
    for stems in dict.fromkeys(r["stems"] for r in rows if "failed" not in r):
        ok = [r for r in rows if r.get("stems") == stems and "failed" not in r]
        eo = np.concatenate([r["err_old"] for r in ok])
        en = np.concatenate([r["err_new"] for r in ok])
        lines.append(f"| {stems} | all | {eo.size} | | {cm * rmse(eo):.2f} | **{cm * rmse(en):.2f}** | "
                     f"{cm * eo.mean():+.2f} | {cm * en.mean():+.2f} | | |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--stems", nargs="+", default=["realistic", "circular"])
    ap.add_argument("--scans", type=int, default=6)
    ap.add_argument("--resolution", default="half", choices=["full", "half", "quarter"])
    ap.add_argument("--work", type=Path, default=None, help="keep campaigns and stores here")
    ap.add_argument("--no-write", action="store_true", help="print only, leave results.md alone")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_dbh_"))
    rows = [run_one(stems, seed, args, work) for stems in args.stems for seed in args.seeds]
    body = report(rows, args)
    print(body)
    if not args.no_write:
        write_section("dbh", "## DBH from the merged breast-height slice (issue 19)\n\n" + body)


if __name__ == "__main__":
    main()
