"""Profile the branch-and-bound search (``register_pair``) on the registration benchmark's pairs.

Same pairs, boxes and cached sub-maps as ``bench_registration.py`` (same random draws), but only
the search, so search variants can be compared quickly: per pair wall and CPU seconds, cells
evaluated, the peak and its score. ``--check`` compares every peak score with the one stored by
a ``--save`` run (``<cache>/profile_peaks.json``): an exact search variant must give the same
lattice maximum. Writes nothing to results.md.

Usage: ``python benchmarks/profile_registration.py [--cases box,noprior,low] [--bound lattice]
[--margin 10] [--pairs 0,1] [--save | --check]``
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))

from bench_registration import choose_pairs, ensure_campaigns, low_overlap_jobs  # noqa: E402
from forest_pairs import (  # noqa: E402
    benchmark_box,
    campaign_elevation,
    campaign_submap_tables,
)

from forestmap_assets.core.registration import fast_search  # noqa: E402
from forestmap_assets.core.registration.register import register_pair
from forestmap_assets.params import RegistrationParams  # noqa: E402


def benchmark_jobs(cache: Path, n_box=8, n_noprior=5, n_low=3):
    """(case, plot, pair, scan points, reference points, centre, half, truth) of the benchmark,
    drawn exactly as ``bench_registration.run`` draws them."""
    params = RegistrationParams()
    folders = ensure_campaigns(cache)
    submaps = {str(f): campaign_submap_tables(f) for f in folders}
    elevation = {str(f): campaign_elevation(f) for f in folders}
    rng = np.random.default_rng(4)
    table, box_pairs, np_pairs = choose_pairs(folders, n_box, n_noprior, rng)
    jobs = []
    for case, tab in (("box", box_pairs), ("noprior", np_pairs)):
        for r in tab.itertuples():
            sm = submaps[r.folder]
            jobs.append((case, Path(r.folder).name, f"{r.scan}{r.reference}", sm[r.scan],
                         sm[r.reference], (r.tx, r.ty, r.tz, r.th)))
    for j in low_overlap_jobs(table, submaps, elevation, n_low, rng):
        jobs.append(("low", j[0], j[1], j[2], j[3], j[6]))
    out = []
    for case, camp, name, pb, pa, truth in jobs:
        centre, half = benchmark_box(case == "box", truth, pa, pb, rng, params.max_xy_m)
        xyz = lambda t: t[["x", "y", "z"]].to_numpy(float)  # noqa: E731
        out.append((case, camp, name, xyz(pb), xyz(pa), tuple(centre), half, truth))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cache", type=Path, default=Path("/tmp/forestmap_bench_registration"))
    ap.add_argument("--cases", default="box,noprior")
    ap.add_argument("--pairs", default="", help="indices within the selected cases")
    ap.add_argument("--bound", default=None, help="cell or lattice (default: register_pair's)")
    ap.add_argument("--margin", type=float, default=10.0)
    ap.add_argument("--kw", default="{}", help="extra register_pair keywords (JSON)")
    ap.add_argument("--save", action="store_true")
    ap.add_argument("--check", action="store_true")
    ap.add_argument("--csv", type=Path)
    a = ap.parse_args()
    cases = a.cases.split(",")
    jobs = [j for j in benchmark_jobs(a.cache) if j[0] in cases]
    if a.pairs:
        jobs = [jobs[int(k)] for k in a.pairs.split(",")]
    store = a.cache / "profile_peaks.json"
    saved = json.loads(store.read_text()) if store.exists() else {}
    register_pair(np.zeros((5, 3)), np.ones((5, 3)), (0, 0, 0, 0), (0.1, 0.1, 0.1, 1))  # JIT
    kw = json.loads(a.kw)
    rows = []
    for case, camp, name, pb, pa, centre, half, truth in jobs:
        fast_search._FIELDS.clear()
        t0, c0 = time.perf_counter(), time.process_time()
        r = register_pair(pb, pa, centre, half, RegistrationParams(), bound=a.bound,
                          lattice_margin=a.margin, **kw)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        key = f"{case}/{camp}/{name}"
        e = np.asarray(r.peak, float) - np.asarray(truth if truth is not None else r.peak, float)
        e[3] = (e[3] + 180) % 360 - 180
        row = dict(key=key, n=len(pb), wall=round(wall, 3), cpu=round(cpu, 3),
                   cells=r.n_cells_evaluated, score=r.peak_score, status=r.status,
                   xy=round(float(np.hypot(e[0], e[1])), 4), z=round(float(abs(e[2])), 4),
                   h=round(float(abs(e[3])), 3), cloud=r.cloud_cells,
                   sd=tuple(round(v, 4) for v in r.sigma), load=os.getloadavg()[0])
        if a.check and key in saved:
            ref = saved[key]
            same = (np.isnan(ref) and not np.isfinite(r.peak_score)) or np.isclose(
                r.peak_score, ref, rtol=1e-12, atol=1e-8)
            row["same"] = bool(same)
        if a.save:
            saved[key] = float(r.peak_score) if np.isfinite(r.peak_score) else float("nan")
        rows.append(row)
        print(row, flush=True)
    if a.save:
        store.write_text(json.dumps(saved, indent=1))
    df = pd.DataFrame(rows)
    print(df.drop(columns=["sd"]).to_string())
    print("median wall", df.wall.median(), "median cpu", df.cpu.median())
    if a.csv:
        df.to_csv(a.csv, index=False)


if __name__ == "__main__":
    main()
