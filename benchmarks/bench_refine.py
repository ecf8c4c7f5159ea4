"""Fine registration on the raw points: the coarse-sigma box (before) against the two-way
refinement guarded by its own fit (issue 19; ``RefineSettings.guard``), on the same stored
branch-and-bound registrations.

Input: stores of finished ``forestmap run``s with the truth of their campaign, e.g. the runs of
``bench_survey.py`` (``--runs /tmp/bench-survey/runs``: each ``<case>/case.json`` names the campaign
whose ``truth/poses.csv`` holds the scan poses) or ``--case LABEL=STORE:TRUTH_POSES_CSV``. For each
case both guards refine every accepted pair of ``pairwise_registrations``; reported: pairs used,
the pair errors against the truth of the links that go to the map (the refined pose where used,
else the branch-and-bound one), error / sigma per axis (RMS and share within 2 sigma) and the
seconds per pair. Writes the section ``refine`` of ``benchmarks/results.md``.

    python benchmarks/bench_refine.py --runs /tmp/bench-survey/runs
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from forestmap_assets.access import load_asset
from forestmap_assets.assets.registration import _cloud
from forestmap_assets.core.geometry import relative_pose
from forestmap_assets.core.registration.refine import POSE, SD, refine_registrations
from forestmap_assets.params.men import RefineSettings

GUARDS = {"box (before)": replace(RefineSettings(), guard="box"), "own fit (new)": RefineSettings()}


def cases_from_runs(runs: Path) -> list[tuple[str, Path, Path]]:
    out = []
    for case in sorted(runs.glob("*/case.json")):
        root = Path(json.loads(case.read_text())["root"])
        # a campaign-level bundle (before issue 17) or a folder of pair partitions
        stores = sorted((case.parent / "fm-home" / "store").glob("*/pairwise_registrations*"))
        if stores and (root / "truth" / "poses.csv").exists():
            out.append((case.parent.name, stores[0].parent, root / "truth" / "poses.csv"))
    return out


def relative_truth(truth: pd.DataFrame, scan: str, ref: str) -> np.ndarray:
    """Pose of ``scan`` in ``ref``'s levelled frame (x, y, z, heading_deg) from world poses."""
    cols = ["x", "y", "z", "heading_deg"]
    return np.array(relative_pose(truth.loc[scan, cols].to_numpy(float), truth.loc[ref, cols].to_numpy(float)))


def run_case(label: str, store: Path, truth_csv: Path) -> list[dict]:
    truth = pd.read_csv(truth_csv).set_index("scan")
    regs = load_asset("pairwise_registrations", campaign=store.name, store_url=str(store.parent))["registrations"]
    acc = regs[regs["status"] == "accepted"]
    ids = sorted(set(acc["scan"]) | set(acc["reference"]))
    clouds = {sid: _cloud(pq.read_table(store / "range_images" / f"{sid}.parquet")) for sid in ids}
    rows = []
    for name, settings in GUARDS.items():
        t0 = time.perf_counter()
        out = refine_registrations(regs, clouds, settings)
        wall = time.perf_counter() - t0
        links = out["registrations"][out["registrations"]["status"] == "accepted"]
        tab = out["refinements"]
        err = np.array([r[POSE].to_numpy(float) - relative_truth(truth, r["scan"], r["reference"])
                        for _, r in links.iterrows()])
        bnb = np.array([r[POSE].to_numpy(float) - relative_truth(truth, r["scan"], r["reference"])
                        for _, r in acc.iterrows()])
        z = err / links[SD].to_numpy(float)
        used = tab[tab["used"] == "refined"]
        rows.append({
            "case": label, "guard": name, "pairs": len(links), "used": len(used),
            "moved_mm": 1000 * float(np.hypot(used["ref_dx"] - used["bnb_dx"], used["ref_dy"] - used["bnb_dy"]).median())
            if len(used) else np.nan,
            "bnb_xy_mm": 1000 * float(np.median(np.hypot(bnb[:, 0], bnb[:, 1]))),
            "xy_mm": 1000 * float(np.median(np.hypot(err[:, 0], err[:, 1]))),
            "max_xy_mm": 1000 * float(np.max(np.hypot(err[:, 0], err[:, 1]))),
            "rms_z": np.sqrt((z ** 2).mean(axis=0)), "in2": (np.abs(z) <= 2).mean(axis=0),
            "pair_s": float(tab["seconds"].median()), "wall_s": wall,
        })
        print(f"{label:14s} {name:14s} used {len(used)}/{len(links)} median xy {rows[-1]['xy_mm']:.1f} mm "
              f"(b&b {rows[-1]['bnb_xy_mm']:.1f}) median pair {rows[-1]['pair_s']:.2f} s", flush=True)
    return rows


def table(rows: list[dict]) -> str:
    ax = ("x", "y", "z", "heading")
    head = ("| case | guard | pairs used | median move of used mm | median xy error mm (b&b) | max xy mm | "
            + " | ".join(f"RMS err/sd {a}" for a in ax) + " | " + " | ".join(f"within 2 sd {a}" for a in ax)
            + " | median s / pair | wall s |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        lines.append(f"| {r['case']} | {r['guard']} | {r['used']}/{r['pairs']} | {r['moved_mm']:.1f} | "
                     f"{r['xy_mm']:.1f} ({r['bnb_xy_mm']:.1f}) | {r['max_xy_mm']:.1f} | "
                     + " | ".join(f"{v:.2f}" for v in r["rms_z"]) + " | "
                     + " | ".join(f"{100 * v:.0f} %" for v in r["in2"])
                     + f" | {r['pair_s']:.2f} | {r['wall_s']:.1f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=Path, help="a bench_survey.py runs folder")
    ap.add_argument("--case", action="append", default=[], help="LABEL=STORE:TRUTH_POSES_CSV")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    cases = cases_from_runs(args.runs) if args.runs else []
    for c in args.case:
        label, rest = c.split("=", 1)
        store, truth = rest.split(":", 1)
        cases.append((label, Path(store), Path(truth)))
    if not cases:
        raise SystemExit("bench_refine: no cases (give --runs or --case)")
    rows = [r for c in cases for r in run_case(*c)]
    body = ("## Fine registration: coarse-sigma box vs own-fit guard (`benchmarks/bench_refine.py`, issue 19)\n\n"
            f"{time.strftime('%Y-%m-%d')}, 2 cores shared with other work. The same stored branch-and-bound "
            "registrations of each run refined with `guard=\"box\"` (before: inside 3 x the coarse sigma, "
            "one way, Tukey point-to-plane) and with the default `guard=\"fit\"` (both ways, least squares, "
            "used when the directions agree, the overlap is kept and the residuals do not grow). Errors are "
            "of the links that go to the map (refined where used, else branch and bound) against the truth; "
            "err/sd with the sigma of that link.\n\n" + table(rows))
    print(body)
    if not args.no_write:
        from results_md import write_section

        write_section("refine", body)


if __name__ == "__main__":
    main()
