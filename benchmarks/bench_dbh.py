"""DBH from the merged breast-height slice and the silhouettes' widths against the cylinder
DBH (issue 19).

For each stem model (``realistic``, ``circular``) and seed: simulate a campaign (default 6
scans, half resolution), run the pipeline, then compute the tree list of the same integrated
map and stored range images three ways: ``trees.dbh_method`` ``cylinders`` (the DBH before
issue 19), ``slice`` (core/mapping/stem_slices.py) and ``slice`` blended with the silhouettes'
widths and with one outline through the slice and the silhouette sides (``trees.calipers``,
core/mapping/stem_calipers.py, stem_outline.py; the simulator names its beam, so a run uses
them), and compare with the truth (matched trees, ``sim.evaluate.dbh_errors``).
Prints a table and writes the ``dbh`` section of ``benchmarks/results.md``.

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


def tree_lists(root: Path) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Trees of the stored integrated map by cylinders, by slice and by slice with the
    silhouettes' widths, and the last one's fits."""
    from forestmap_assets.access import load_asset
    from forestmap_assets.core.features.elevation import elevation_from_table
    from forestmap_assets.core.mapping.slice_splats import splat_steps
    from forestmap_assets.core.mapping.tree_dbh import tree_dbh
    from forestmap_assets.core.mapping.trees import beam_options, merge_trees
    from forestmap_assets.io.campaign import load_campaign

    camp = load_campaign(root)
    im = load_asset("integrated_map", campaign=root)
    grid = elevation_from_table(im["elevation"])
    tp = camp.params.trees
    cylinders, tree_of = merge_trees(im["cylinders"], grid, min_top_m=tp.understorey_top_m or None,
                                     **beam_options(tp.beam_exit_m, 1e-3 * tp.beam_divergence_mrad))
    poses = im["scans"]
    clouds, images = {}, {}
    for sid in poses["scan"]:
        image = load_asset("range_images", campaign=root, scan=sid)
        clouds[sid] = image.xyz[image.valid]
        images[sid] = image.to_table()
    sliced, _ = tree_dbh(cylinders, im["cylinders"], tree_of, clouds, poses, tp.model_copy(update={"calipers": False}))
    blended, fits = tree_dbh(cylinders, im["cylinders"], tree_of, clouds, poses,
                             tp.model_copy(update={"calipers": True}), images=images,
                             splats=splat_steps(poses, images))
    return cylinders, sliced, blended, fits


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
    cyl, sliced, blended, fits = tree_lists(root)
    slice_seconds = time.perf_counter() - t0
    truth = pd.read_csv(root / "truth" / "trees.csv")
    old, new = dbh_errors(cyl, truth), dbh_errors(blended, truth)
    # the same matched trees for all: those with a DBH every way (the slice keeps every DBH)
    m_old, m_sl, m_new = match_trees(cyl, truth), match_trees(sliced, truth), match_trees(blended, truth)
    both = m_old["est_dbh_m"].notna() & m_sl["est_dbh_m"].notna() & m_new["est_dbh_m"].notna()

    def err(m):
        return (m.loc[both, "est_dbh_m"] - m.loc[both, "dbh_m"]).to_numpy(float)

    used = fits[fits["reason"] == ""]
    return {"stems": stems, "seed": seed, "seconds": seconds, "slice_seconds": slice_seconds,
            "n": int(both.sum()), "trees": len(cyl), "slice_used": len(used),
            "calipers": int((fits["caliper_scans"] > 0).sum()),
            "err_old": err(m_old), "err_slice": err(m_sl), "err_new": err(m_new),
            **{f"{k}_old": v for k, v in old.items()}, **{f"{k}_new": v for k, v in new.items()}}


def rmse(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def report(rows: list[dict], args) -> str:
    cm = 100.0
    lines = [
        f"Simulated 40 m plots, {args.scans} scans, {args.resolution} resolution, pipeline run once "
        "per campaign; the tree list of the same integrated map and range images computed with "
        "`trees.dbh_method: cylinders` (before issue 19), `slice` (the merged breast-height "
        "slice, core/mapping/stem_slices.py) and `slice` blended with the silhouettes' widths "
        "and the outline through the slice and the sides (`trees.calipers`, "
        "core/mapping/stem_calipers.py, stem_outline.py; a run of these campaigns uses them). "
        "Matched trees with a DBH every way (truth match within 0.5 m); bias = mean(estimate - "
        f"truth). Machine: {platform.machine()}, {os.cpu_count()} cores (shared).",
        "",
        "| stems | seed | matched trees | slice used / with widths / trees | DBH RMSE cylinders (cm) | slice (cm) | slice + widths + outline (cm) | bias cylinders / slice + widths + outline (cm) | RMSE trees seen from >= 2 scans, cylinders -> slice + widths + outline (cm) | DBH step (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "failed" in r:
            lines.append(f"| {r['stems']} | {r['seed']} | failed: {r['failed']} ||||||||")
            continue
        lines.append(
            f"| {r['stems']} | {r['seed']} | {r['n']} | {r['slice_used']} / {r['calipers']} / {r['trees']} | "
            f"{cm * rmse(r['err_old']):.2f} | {cm * rmse(r['err_slice']):.2f} | **{cm * rmse(r['err_new']):.2f}** | "
            f"{cm * r['err_old'].mean():+.2f} / {cm * r['err_new'].mean():+.2f} | "
            f"{cm * r['dbh_rmse_multi_m_old']:.2f} -> {cm * r['dbh_rmse_multi_m_new']:.2f} | "
            f"{r['slice_seconds']:.1f} |")
    for stems in dict.fromkeys(r["stems"] for r in rows if "failed" not in r):
        ok = [r for r in rows if r.get("stems") == stems and "failed" not in r]
        eo, es, en = (np.concatenate([r[k] for r in ok]) for k in ("err_old", "err_slice", "err_new"))
        lines.append(f"| {stems} | all | {eo.size} | | {cm * rmse(eo):.2f} | {cm * rmse(es):.2f} | "
                     f"**{cm * rmse(en):.2f}** | {cm * eo.mean():+.2f} / {cm * en.mean():+.2f} | | |")
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
        write_section("dbh", "## DBH from the merged breast-height slice and the silhouettes' widths (issue 19)\n\n"
                      + body)


if __name__ == "__main__":
    main()
