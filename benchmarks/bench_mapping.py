"""Whole-pipeline accuracy and honesty of uncertainty on simulated campaigns (issue 5).

For several seeds: simulate a campaign (default 6 scans, no prior), run the pipeline through
Dagster, compare with the truth: pose errors, normalised pose errors (error / reported sd, which
should behave like a standard normal), tree detection among trees seen from >= 2 scans, DBH
RMSE. Prints a table and writes the ``mapping`` section of ``benchmarks/results.md``.

    python benchmarks/bench_mapping.py --seeds 5 --resolution full
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

RESULTS = Path(__file__).with_name("results.md")


def write_section(name: str, body: str) -> None:
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    text = RESULTS.read_text() if RESULTS.exists() else "# Benchmark results\n"
    block = f"{start}\n{body.rstrip()}\n{end}"
    if start in text:
        text = re.sub(re.escape(start) + r".*?" + re.escape(end), lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    RESULTS.write_text(text)


def run_one(seed: int, args, work: Path) -> dict:
    from forestmap_assets.campaign import load_campaign
    from forestmap_assets.exports import write_exports
    from forestmap_assets.runner import run_campaign
    from forestmap_assets.sim import simulate_campaign
    from forestmap_assets.sim.evaluate import evaluate_campaign

    root = work / f"plot{seed}"
    kw = dict(no_prior=True) if args.no_prior else dict(prior_error=(4.5, 32.0))
    simulate_campaign(root, scans=args.scans, trees=args.trees, plot_size=args.plot_size, seed=seed,
                      resolution=args.resolution, **kw)
    os.environ["FORESTMAP_HOME"] = str(work / f"home{seed}")
    os.environ["DAGSTER_HOME"] = str(work / f"home{seed}" / "dagster")
    t0 = time.perf_counter()
    summary = run_campaign(root, progress=lambda m: None)
    seconds = time.perf_counter() - t0
    if summary.failures:
        return {"seed": seed, "failed": summary.failures[0][2]}
    write_exports(load_campaign(root), root / "outputs", cloud_spacing_m=None, picture=False, report=False)
    acc = evaluate_campaign(root)
    regs = pd.read_csv(root / "outputs" / "registrations.csv")
    poses = acc.poses[acc.poses["scan"] != acc.poses["scan"].iloc[0]]
    return {
        "seed": seed,
        "seconds": seconds,
        "pairs": len(regs),
        "accepted": int((regs["status"] == "accepted").sum()),
        "placed": f"{len(acc.poses)}/{args.scans}",
        **acc.summary(),
        "poses": poses,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first-seed", type=int, default=100)
    ap.add_argument("--scans", type=int, default=6)
    ap.add_argument("--trees", type=int, default=40)
    ap.add_argument("--plot-size", type=float, default=40.0)
    ap.add_argument("--resolution", default="full")
    ap.add_argument("--no-prior", action=argparse.BooleanOptionalAction, default=True)
    args = ap.parse_args()
    rows, norm = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            r = run_one(seed, args, Path(tmp))
            if "poses" in r:
                norm.append(r.pop("poses"))
            rows.append(r)
            print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}, flush=True)
    allp = pd.concat(norm, ignore_index=True) if norm else pd.DataFrame()
    lines = [
        "## Whole pipeline on simulated campaigns (issue 5)",
        "",
        f"`python benchmarks/bench_mapping.py --seeds {args.seeds} --resolution {args.resolution}`: "
        f"{args.scans} scans, {args.trees} trees, {args.plot_size:.0f} m plot, "
        f"{'no prior' if args.no_prior else 'priors off by up to 4.5 m / 32 deg'}; "
        f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}.",
        "",
        "| seed | placed | pairs accepted | max xy err (m) | max z err (m) | max heading err (deg) | trees found (>= 2 scans) | DBH RMSE (m) | DBH bias (m) | seconds |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "failed" in r:
            lines.append(f"| {r['seed']} | failed: {r['failed']} |||||||||")
            continue
        lines.append(
            f"| {r['seed']} | {r['placed']} | {r['accepted']}/{r['pairs']} | {r['max_xy_error_m']:.4f} | "
            f"{r['max_z_error_m']:.4f} | {r['max_heading_error_deg']:.4f} | {r['detection_rate']:.1%} | "
            f"{r['dbh_rmse_m']:.4f} | {r['dbh_bias_m']:+.4f} | {r['seconds']:.0f} |"
        )
    if len(allp):
        lines += ["", "Normalised pose errors (error / reported sd) over all placed scans and seeds; a "
                  "calibrated sd gives RMS ~1 and ~95 % within +-2:", "",
                  "| component | n | RMS | share within +-2 | max abs |", "|---|---|---|---|---|"]
        for c in ("nx", "ny", "nz", "nheading"):
            v = allp[c].dropna().to_numpy()
            if v.size:
                lines.append(f"| {c[1:]} | {v.size} | {np.sqrt(np.mean(v**2)):.2f} | {np.mean(np.abs(v) <= 2):.0%} | {np.abs(v).max():.2f} |")
    body = "\n".join(lines)
    print(body)
    write_section("mapping", body)


if __name__ == "__main__":
    main()
