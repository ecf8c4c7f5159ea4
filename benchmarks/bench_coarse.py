"""Coarse registration without any prior on simulated forest pairs (issue 8, men spec 4).

The pairs are those of ``bench_registration.py``'s "no prior" case (same simulated
full-resolution plots, same seeded choice among pairs sharing at least 5 stems) plus further
pairs of the same plots. For each pair, in one run:

* (a) **Fourier, thesis** (``core.registration.fourier_coarse.coarse_register``, heading mode for levelled scans,
  ``rotation='egi'``): PCA normals -> EGI -> heading by spherical-harmonic correlation (L = 32),
  its peaks verified by the translation correlation of occupancy grids (0.2 m, zero padded);
* (a') **Fourier, occupancy scan** (``rotation='occupancy_scan'``, inferred forest adaptation):
  the occupancy correlation itself over 64 headings, the best refined on a 4x finer grid;
* (a'') **Fourier + branch and bound**: (a') as the centre of the forest search box
  (+-5 m, +-1.25 m, +-60 deg) of the branch and bound on the feature sub-maps: the pipeline's
  ``no_prior_method='fourier'`` option (``core.registration.fourier_coarse.coarse_candidates``);
* (b) **branch and bound, no prior**: ``core.registration.register.register_pair`` over the full heading
  circle and xy half-width min(reach_a, reach_b, 20 m) (the candidate-pair rule);
* (c) **Open3D FPFH + RANSAC + point-to-plane ICP** on the raw scans (``bench_registration``'s
  peer).

Raw clouds: levelled points within 25 m of the sensor; the Fourier methods keep -4..+2 m around
the sensor height (ground and stems, no canopy) and voxel 0.1 m. Success: within 5 cm xy, 10 cm z
and 0.5 deg (final accuracy); "coarse ok": within 0.5 m xy and 2 deg, i.e. inside the box a fine
stage searches. Seconds are wall clock on a shared 2-core machine, including each method's
pre-processing of both scans.

Writes its section of ``benchmarks/results.md``.
Usage: ``python benchmarks/bench_coarse.py [--extra-pairs 6] [--cache DIR]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))

from bench_registration import (  # noqa: E402
    choose_pairs,
    ensure_campaigns,
    errors,
    open3d_register,
    raw_cloud,
    success,
)
from forest_pairs import campaign_submaps  # noqa: E402
from results_md import write_section  # noqa: E402

from forestmap_assets.core.registration.fourier_coarse import coarse_register, prepare_cloud
from forestmap_assets.core.registration.pair_registrations import judge  # noqa: E402
from forestmap_assets.core.registration.register import register_pair
from forestmap_assets.params import RegistrationParams  # noqa: E402

START, END = "<!-- coarse:start -->", "<!-- coarse:end -->"
PREP = dict(voxel_m=0.1, normal_k=20, max_range_m=25.0, z_band_m=(-4.0, 2.0))


def coarse_ok(exy, eh) -> bool:
    return exy <= 0.5 and eh <= 2.0


def pick_pairs(folders, extra: int) -> pd.DataFrame:
    rng = np.random.default_rng(4)  # bench_registration's seed and draw order
    table, _, noprior = choose_pairs(folders, 10, 6, rng)
    good = table[(table.shared_stems >= 5)].drop(noprior.index)
    more = good.sample(min(extra, len(good)), random_state=7)
    return pd.concat([noprior.assign(origin="bench_registration"), more.assign(origin="extra")])


def run(extra: int, cache: Path, progress=print) -> pd.DataFrame:
    params = RegistrationParams()
    folders = ensure_campaigns(cache, progress)
    submaps = {str(f): campaign_submaps(f, progress) for f in folders}
    pairs = pick_pairs(folders, extra)
    register_pair(np.zeros((5, 3)), np.ones((5, 3)), (0, 0, 0, 0), (0.1, 0.1, 0.1, 1))  # JIT
    coarse_register(np.random.rand(100, 3), np.random.rand(100, 3), bandwidth=32, voxel_m=0.0)  # caches
    rows = []
    for r in pairs.itertuples():
        folder = Path(r.folder)
        truth = (r.tx, r.ty, r.tz, r.th)
        name = f"{folder.name}/{r.scan}{r.reference}"
        src, dst = raw_cloud(folder, r.scan), raw_cloud(folder, r.reference)
        pb, pa = submaps[r.folder][r.scan], submaps[r.folder][r.reference]
        base = dict(pair=name, shared=r.shared_stems, distance_m=float(np.hypot(r.tx, r.ty)), origin=r.origin)

        def add(method, est, secs, extra_cols=None, truth=truth, base=base, name=name):
            exy, ez, eh = errors(est, truth)
            rows.append(dict(base, method=method, seconds=secs, exy=exy, ez=ez, eh=eh, ok=success(exy, ez, eh),
                             coarse_ok=coarse_ok(exy, eh), **(extra_cols or {})))
            progress(f"{name} {method}: xy {exy:.3f} m, z {ez:.3f} m, heading {eh:.2f} deg, {secs:.1f} s")

        t0 = time.perf_counter()
        prepared = (prepare_cloud(dst, **PREP), prepare_cloud(src, **PREP))
        t_prep = time.perf_counter() - t0
        for rot, label in (("egi", "(a) Fourier: EGI heading + occupancy FFT"),
                           ("occupancy_scan", "(a') Fourier: occupancy-scan heading + FFT")):
            res = coarse_register(None, None, mode="heading", rotation=rot, bandwidth=32, top_k=4,
                                  prepared=prepared)
            add(label, res.pose4, t_prep + res.seconds)
            if rot == "occupancy_scan":
                fourier_pose, fourier_secs = res.pose4, t_prep + res.seconds
        half = (params.xy_m, params.xy_m, params.z_m, params.heading_deg)
        t0 = time.perf_counter()
        fine = register_pair(pb, pa, fourier_pose, half, params)
        secs = time.perf_counter() - t0
        status, _, _ = judge(fine, params, fourier_pose, half)
        add("(a'') Fourier (a') + branch and bound in the forest box", fine.centre, fourier_secs + secs,
            {"status": status})
        reach = min(np.hypot(pa[:, 0], pa[:, 1]).max(), np.hypot(pb[:, 0], pb[:, 1]).max(), params.max_xy_m)
        half = (reach, reach, 1.25, 180.0)
        t0 = time.perf_counter()
        bb = register_pair(pb, pa, np.zeros(4), half, params)
        secs = time.perf_counter() - t0
        status, _, _ = judge(bb, params, np.zeros(4), half)
        add("(b) branch and bound, no prior (full circle)", bb.centre, secs, {"status": status})
        t0 = time.perf_counter()
        est = open3d_register(src, dst)
        add("(c) Open3D FPFH + RANSAC + ICP", est, time.perf_counter() - t0)
    return pd.DataFrame(rows)


def machine() -> str:
    return f"{platform.machine()} / {os.cpu_count()} cores (shared with other jobs)"


def report(df: pd.DataFrame) -> str:
    agg = df.groupby("method", sort=False).agg(
        pairs=("pair", "size"), success=("ok", "sum"), coarse_ok=("coarse_ok", "sum"),
        median_xy_m=("exy", "median"), max_xy_m=("exy", "max"), median_heading_deg=("eh", "median"),
        max_heading_deg=("eh", "max"), median_s=("seconds", "median"), max_s=("seconds", "max")).reset_index()
    lines = [START, "## Coarse registration without a prior (`benchmarks/bench_coarse.py`, issue 8)", "",
             f"`python benchmarks/bench_coarse.py` on {machine()}, {time.strftime('%Y-%m-%d')}. Pairs: "
             "bench_registration's 6 no-prior pairs plus further pairs of its simulated full-resolution "
             "plots (>= 5 shared stems). Success: 5 cm xy / 10 cm z / 0.5 deg; coarse ok: 0.5 m / 2 deg.", "",
             "| method | pairs | success | coarse ok | median xy (m) | max xy (m) | median heading (deg) "
             "| max heading (deg) | median s | max s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in agg.itertuples():
        lines.append(f"| {r.method} | {r.pairs} | {r.success}/{r.pairs} | {r.coarse_ok}/{r.pairs} "
                     f"| {r.median_xy_m:.3f} | {r.max_xy_m:.3f} | {r.median_heading_deg:.2f} "
                     f"| {r.max_heading_deg:.2f} | {r.median_s:.1f} | {r.max_s:.1f} |")
    by = agg.set_index("method")

    def pick(tag, col):
        sel = by[by.index.str.startswith(tag)]
        return float(sel[col].iloc[0]) if len(sel) else np.nan

    occ, occ_bb = "(a')", "(a'')"
    fails = df[df["method"].str.startswith("(b)") & ~df["ok"].astype(bool)]
    zs = f"{fails['ez'].min():.2f}-{fails['ez'].max():.2f} m" if len(fails) else "none"
    lines += ["", f"The thesis's EGI heading (a) is a coarse method, as Men says (median {pick('(a)', 'median_heading_deg'):.1f} "
              f"deg, up to {pick('(a)', 'max_heading_deg'):.1f} deg off here: stems' normals face each scanner, so the "
              "orientation histograms differ between viewpoints); the occupancy-scan variant (a') stays within "
              f"{pick(occ, 'max_xy_m'):.2f} m / "
              f"{pick(occ, 'max_heading_deg'):.2f} deg. As the centre of the forest box it "
              "lets the branch and bound reach the same result as the no-prior search (b), but (b) alone is "
              f"faster (median {pick('(b)', 'median_s'):.1f} s vs {pick(occ_bb, 'median_s'):.1f} s) "
              "and needs no raw points. **Default for no-prior pairs: the branch-and-bound no-prior search "
              "(b)**; `registration.no_prior_method: fourier` selects (a'') (the coarse result centres the "
              f"search box). Failures of (b) are z errors ({zs}; this benchmark calls the bare register_pair, "
              "the pipeline refines dz from the elevation maps). FPFH + RANSAC often fails on forests "
              "(repetitive stems)."]
    lines += ["", "Per pair:", "", "| pair | shared stems | distance (m) | method | xy (m) | z (m) | heading (deg) "
              "| s |", "|---|---|---|---|---|---|---|---|"]
    for r in df.itertuples():
        lines.append(f"| {r.pair} | {r.shared} | {r.distance_m:.1f} | {r.method.split(' ')[0]} | {r.exy:.3f} "
                     f"| {r.ez:.3f} | {r.eh:.2f} | {r.seconds:.1f} |")
    lines.append(END)
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--extra-pairs", type=int, default=6)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/forestmap_bench_registration"))
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--rows", type=Path, default=None, help="re-render from a saved rows CSV")
    args = ap.parse_args()
    if args.rows:
        df = pd.read_csv(args.rows)
    else:
        df = run(args.extra_pairs, args.cache)
        df.to_csv(args.cache / "bench_coarse_rows.csv", index=False)
    text = report(df)
    print(text)
    if not args.no_write:
        write_section("coarse", text)


if __name__ == "__main__":
    main()
