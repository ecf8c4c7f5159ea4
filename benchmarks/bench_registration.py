"""Registration benchmark on simulated forest plots: our branch and bound vs Open3D.

Campaigns are simulated at full resolution (``forestmap simulate``: virtual forest, Riegl-like
scanner) into ``--cache`` and every scan's sub-map is computed with the pipeline's own core
functions (``forest_pairs.py``). Pairs (location of ``scan`` in the levelled frame of
``reference``) and truth come from ``truth/poses.csv``; "shared stems" are stems visible in both
scans (truth labels, the simulator's rule).

Cases (issue 4):

* **forest box**: +-5 m, +-1.25 m, +-60 deg around an a priori pose off by the thesis's worst
  error, 4.5 m horizontally (random direction), 32 deg (random sign) and U(-0.3, 0.3) m in z;
  0.02 m final cells;
* **no prior**: full heading circle, xy half-width min(reach_a, reach_b, 20 m) around zero (the
  candidate-pair rule), +-1.25 m in z;
* **low overlap**: pairs sharing fewer than 5 stems, no prior: must not be accepted.

Ours runs with the default ``bound='lattice'`` of ``register_pair`` (cells bounded over their
final-lattice poses only, asymmetric per-axis box, parent terms; the best cell's cloud grown to
``cloud_margin``) and, for reference, with ``bound='cell'`` (spec 6.4: every cell bounded over
its whole volume); both find the same lattice maximum. Both go through the same pipeline
function with ``RegistrationParams.bound`` set.

Reported per registration: exactly what the pipeline writes to ``registrations.csv`` for the
pair (``core.registration.pair_registrations.register_candidates``, the function the
``pairwise_registrations`` asset calls, with the two scans' ground elevation grids computed as
the ``elevation_maps`` asset does: cell-cloud centre, dz from the ground when it agrees, status
from the judge and structure checks), the peak and feature-based dz, wall-clock and CPU seconds
of that call and of its search (this machine is shared: wall time depends on the load, shown in
the table). Success: within 5 cm in xy, 10 cm in z and 0.5 deg in heading of the truth.

Peer, the first ``--peer-pairs`` pairs of each case, same run: Open3D FPFH + RANSAC global registration then point-to-plane ICP on
the raw scans (levelled xyz of the range images within 20 m of the scanner; voxel 0.2 m, normals
at 0.4 m, FPFH radius 1.0 m, mutual filter, 100k RANSAC iterations at confidence 0.999, ICP at
0.2 m then 0.1 m; tuned on one pair: voxel 0.1 m did not finish a pair in 10 minutes, RANSAC
without the mutual filter failed). Its time includes its feature computation (FPFH); ours
excludes the sub-map features (about 8 s per full-resolution scan in the pipeline). The peer uses no prior (it is a global method), so its one result per pair is
compared with both of our cases.

Writes its section of ``benchmarks/results.md``.
Usage: ``python benchmarks/bench_registration.py [--box-pairs 8] [--noprior-pairs 5]
[--peer-pairs 2]`` (the peer takes 1-2 minutes per pair on this machine).
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

from forest_pairs import (  # noqa: E402
    benchmark_box,
    campaign_elevation,
    campaign_pairs,
    campaign_submap_tables,
    sector_crop,
)
from results_md import write_section  # noqa: E402

from forestmap_assets.core.registration import fast_search  # noqa: E402
from forestmap_assets.core.registration.pair_registrations import register_candidates  # noqa: E402
from forestmap_assets.core.registration.register import register_pair
from forestmap_assets.params import ElevationParams, RegistrationParams  # noqa: E402

# (name, seed, plot size m, trees, scans): a dense and an open plot, and a long plot for pairs
# with little overlap
CAMPAIGNS = (("plotA", 11, 40.0, 45, 6), ("plotB", 12, 30.0, 30, 6), ("plotC", 13, 70.0, 70, 6))


def ensure_campaigns(cache: Path, progress=print) -> list[Path]:
    from forestmap_assets.sim import simulate_campaign

    out = []
    for name, seed, plot, trees, scans in CAMPAIGNS:
        folder = cache / name
        if not (folder / "truth" / "poses.csv").exists():
            progress(f"simulating {name} (seed {seed}, {plot:g} m, {trees} trees, {scans} scans)")
            simulate_campaign(folder, scans=scans, trees=trees, plot_size=plot, seed=seed,
                              resolution="full", no_prior=True)
        campaign_submap_tables(folder, progress)
        campaign_elevation(folder, progress)
        out.append(folder)
    return out


def raw_cloud(folder: Path, scan_id: str, crop_m: float = 20.0) -> np.ndarray:
    from forestmap_assets.io.readers import read_scan

    p = read_scan(folder / "scans" / f"{scan_id}.npz").xyz.reshape(-1, 3)
    p = p[np.isfinite(p).all(1)]
    return p[np.hypot(p[:, 0], p[:, 1]) < crop_m]


def open3d_register(src: np.ndarray, dst: np.ndarray, voxel: float = 0.2) -> np.ndarray:
    """FPFH + RANSAC + point-to-plane ICP; pose of ``src`` in ``dst``'s frame (x, y, z, deg)."""
    import open3d as o3d

    reg = o3d.pipelines.registration

    def prep(p):
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(voxel)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        f = reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel,
                                                                             max_nn=100))
        return pc, f

    s, fs = prep(src)
    d, fd = prep(dst)
    ransac = reg.registration_ransac_based_on_feature_matching(
        s, d, fs, fd, True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    t = ransac.transformation
    for dist in (voxel, 0.5 * voxel):
        t = reg.registration_icp(s, d, dist, t, reg.TransformationEstimationPointToPlane(),
                                 reg.ICPConvergenceCriteria(max_iteration=50)).transformation
    return np.array([t[0, 3], t[1, 3], t[2, 3], np.degrees(np.arctan2(t[1, 0], t[0, 0]))])


def errors(est, truth) -> tuple[float, float, float]:
    e = np.asarray(est, float) - np.asarray(truth, float)
    e[3] = (e[3] + 180.0) % 360.0 - 180.0
    return float(np.hypot(e[0], e[1])), float(abs(e[2])), float(abs(e[3]))


def success(exy, ez, eh) -> bool:
    return exy <= 0.05 and ez <= 0.10 and eh <= 0.5


def choose_pairs(folders, n_box, n_noprior, rng):
    table = pd.concat([campaign_pairs(f).assign(folder=str(f)) for f in folders], ignore_index=True)
    good = table[table.shared_stems >= 5]
    box = good.sample(min(n_box, len(good)), random_state=rng.integers(1 << 31))
    noprior = good.sample(min(n_noprior, len(good)), random_state=rng.integers(1 << 31))
    return table, box, noprior


def low_overlap_jobs(table, submaps, elevation, n_low, rng):
    """Pairs that must not be accepted: a scan cropped to a sector holding 1-4 shared stems, and
    two scans of different plots (no common stem at all). Each job: (plot, pair, scan points,
    reference points, scan elevation grid, reference elevation grid, truth or None, shared)."""
    jobs = []
    for r in table.sample(frac=1.0, random_state=rng.integers(1 << 31)).itertuples():
        if len(jobs) >= n_low:
            break
        crop = sector_crop(Path(r.folder), r.scan, r.reference, submaps[r.folder][r.scan])
        if crop is not None:
            ev = elevation[r.folder]
            jobs.append((Path(r.folder).name, f"{r.scan}{r.reference} sector", crop[0],
                         submaps[r.folder][r.reference], ev[r.scan], ev[r.reference],
                         (r.tx, r.ty, r.tz, r.th), crop[1]))
    folders = list(submaps)
    for k in range(min(n_low, len(folders) - 1)):
        a, b = submaps[folders[k]], submaps[folders[k + 1]]
        sa, sb = sorted(a)[k % len(a)], sorted(b)[(k + 1) % len(b)]
        jobs.append((f"{Path(folders[k + 1]).name}/{Path(folders[k]).name}", f"{sb}/{sa}", b[sb],
                     a[sa], elevation[folders[k + 1]][sb], elevation[folders[k]][sa], None, 0))
    return jobs


def pipeline_registration(scan_submap, ref_submap, scan_grid, ref_grid, centre, half, params,
                          elevation_cell_m):
    """The ``registrations.csv`` row and the search result the pipeline writes for one pair:
    :func:`~forestmap_assets.core.registration.pair_registrations.register_candidates` (the function the
    ``pairwise_registrations`` asset calls: search, judge, structure checks, dz from the ground
    elevation grids) on a one-pair candidate table. Returns (row, levels)."""
    cand = pd.DataFrame([dict(scan="B", reference="A", cx=centre[0], cy=centre[1], cz=centre[2],
                              cheading_deg=centre[3], hx=half[0], hy=half[1], hz=half[2],
                              hheading_deg=half[3], box_heading_deg=0.0)])
    sub = {"B": scan_submap, "A": ref_submap}
    out = register_candidates(cand, sub, params, elevation={"B": scan_grid, "A": ref_grid},
                              elevation_cell_m=elevation_cell_m)
    return out["registrations"].iloc[0], out["hypotheses"]


def _score_pair(case, camp, name, pb, pa, gb, ga, truth, shared, centre, half, params, cell_m):
    """One pipeline registration of a benchmark pair, timed and scored against the truth (the
    per-process cache of reference fields is emptied first: the time includes building it)."""
    fast_search._FIELDS.clear()
    t0, c0 = time.perf_counter(), time.process_time()
    reg, hyp = pipeline_registration(pb, pa, gb, ga, centre, half, params, cell_m)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    est = reg[["dx", "dy", "dz", "dheading_deg"]].to_numpy(float)
    peak = reg[["peak_dx", "peak_dy", "peak_dz", "peak_dheading_deg"]].to_numpy(float)
    c_err = errors(est, truth) if truth is not None else (np.nan,) * 3
    p_err = errors(peak, truth) if truth is not None else (np.nan,) * 3
    f_err = (abs(float(reg["dz_features"]) - truth[2]) if truth is not None else np.nan)
    row = dict(case=case, campaign=camp, pair=name, shared=shared, n=len(pb), m=len(pa),
               wall=wall, cpu=cpu, search=float(reg["seconds"]), xy=c_err[0], z=c_err[1],
               h=c_err[2], peak_xy=p_err[0], peak_z=p_err[1], peak_h=p_err[2], z_feat=f_err,
               z_source=str(reg["z_source"]), ok=success(*c_err), status=reg["status"],
               reason=reg["reason"], share=reg["peak_mass_share"], hyp=len(hyp),
               stems=reg["matched_stems"], matched=reg["matched_points"],
               load=os.getloadavg()[0])
    print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()},
          flush=True)
    return row


def run(n_box=8, n_noprior=5, n_low=3, cache=Path("/tmp/forestmap_bench_registration"),
        peer_pairs=2):
    params = RegistrationParams().model_copy(update={"bound": "lattice"})
    folders = ensure_campaigns(cache)
    submaps = {str(f): campaign_submap_tables(f) for f in folders}
    elevation = {str(f): campaign_elevation(f) for f in folders}
    cell_m = ElevationParams().cell_m
    rng = np.random.default_rng(4)
    table, box_pairs, np_pairs = choose_pairs(folders, n_box, n_noprior, rng)
    jobs = []
    for case, tab in (("forest box", box_pairs), ("no prior", np_pairs)):
        for r in tab.itertuples():
            sm, ev = submaps[r.folder], elevation[r.folder]
            jobs.append((case, Path(r.folder).name, f"{r.scan}{r.reference}", sm[r.scan],
                         sm[r.reference], ev[r.scan], ev[r.reference], (r.tx, r.ty, r.tz, r.th),
                         r.shared_stems))
    jobs += [("low overlap", *j) for j in low_overlap_jobs(table, submaps, elevation, n_low, rng)]
    register_pair(np.zeros((5, 3)), np.ones((5, 3)), (0, 0, 0, 0), (0.1, 0.1, 0.1, 1))  # JIT
    rows = []
    # the thesis's cell bound (register_pair(bound='cell')) on the same pairs and boxes
    cell_params = params.model_copy(update={"bound": "cell"})
    for case, camp, name, pb, pa, gb, ga, truth, shared in jobs:
        centre, half = benchmark_box(case == "forest box", truth, pa, pb, rng, params.max_xy_m)
        for label, prm in ((case, params), (f"{case}, cell bound", cell_params)):
            rows.append(_score_pair(label, camp, name, pb, pa, gb, ga, truth, shared, centre,
                                    half, prm, cell_m))
    peer_rows = []
    if peer_pairs:
        done = {}
        for case, tab in (("forest box", box_pairs), ("no prior", np_pairs)):
            for r in tab.head(peer_pairs).itertuples():
                key = (r.folder, r.scan, r.reference)
                if key not in done:
                    src = raw_cloud(Path(r.folder), r.scan)
                    dst = raw_cloud(Path(r.folder), r.reference)
                    t0, c0 = time.perf_counter(), time.process_time()
                    est = open3d_register(src, dst)
                    done[key] = (est, time.perf_counter() - t0, time.process_time() - c0)
                est, wall, cpu = done[key]
                err = errors(est, (r.tx, r.ty, r.tz, r.th))
                peer_rows.append(dict(case=case, pair=f"{r.scan}{r.reference}", wall=wall,
                                      cpu=cpu, xy=err[0], z=err[1], h=err[2], ok=success(*err)))
                print("peer", peer_rows[-1], flush=True)
    return pd.DataFrame(rows), pd.DataFrame(peer_rows)


def machine() -> str:
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo")
                   if ln.startswith("model name"))
    except (OSError, StopIteration):
        cpu = platform.processor()
    import numba

    return (f"{platform.machine()} {cpu}, {os.cpu_count()} cores shared with other jobs, "
            f"numba {numba.get_num_threads()} threads")


def table(df: pd.DataFrame, peer: pd.DataFrame) -> str:
    lines = [
        f"`python benchmarks/bench_registration.py` on {machine()}, {time.strftime('%Y-%m-%d')}. "
        "Simulated full-resolution plots (virtual Riegl scanner, 720 x 3000 range images), "
        "sub-maps from the pipeline's feature extraction; "
        f"{', '.join(f'{c[0]}: {c[2]:g} m, {c[3]} trees, {c[4]} scans' for c in CAMPAIGNS)}. "
        "Success: within 5 cm xy, 10 cm z and 0.5 deg heading of the truth. Ours is scored on "
        "exactly what the pipeline writes to registrations.csv for the pair "
        "(`core.registration.pair_registrations.register_candidates`, the function of the "
        "`pairwise_registrations` asset: branch-and-bound search, cell-cloud centre, judge and "
        "structure checks, dz from the scans' ground elevation grids when they agree); 'accepted' "
        "is its status. Wall/CPU: that whole call per pair; 'search' is the register_pair part. "
        "Wall time depends on the machine's "
        f"load (1-min load average during the run: {df.load.min():.1f}-{df.load.max():.1f} on "
        "2 cores); CPU time is the process's (both numba threads).",
        "",
        "| case | method | pairs | success | accepted | median wall (s) | max wall (s) "
        "| median CPU (s) | median search wall (s) | median xy err (m) | max xy err (m) "
        "| max z err (m) | max heading err (deg) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case, g in df.groupby("case", sort=False):
        ok = "-" if case.startswith("low overlap") else f"{int(g.ok.sum())}/{len(g)}"
        p = peer[peer.case == case] if len(peer) else peer
        lines.append(
            f"| {case} | branch and bound (0.02 m, {'cell' if 'cell bound' in case else 'lattice'} "
            "bound) "
            f"| {len(g)} | {ok} "
            f"| {int((g.status == 'accepted').sum())}/{len(g)} | {g.wall.median():.2f} "
            f"| {g.wall.max():.2f} | {g.cpu.median():.2f} | {g.search.median():.2f} "
            f"| {g.xy.median():.3f} "
            f"| {g.xy.max():.3f} | {g.z.max():.3f} | {g.h.max():.2f} |")
        if len(p):
            lines.append(
                f"| {case} | Open3D FPFH+RANSAC+ICP (raw scans) | {len(p)} "
                f"| {int(p.ok.sum())}/{len(p)} | - | {p.wall.median():.2f} | {p.wall.max():.2f} "
                f"| {p.cpu.median():.2f} | - | {p.xy.median():.3f} | {p.xy.max():.3f} "
                f"| {p.z.max():.3f} | {p.h.max():.2f} |")
    lines += ["", "Per pair (ours):", "",
              "| case | plot | pair | shared stems | n | wall (s) | CPU (s) | search (s) | xy (m) "
              "| z (m) | heading (deg) | z source | feature z (m) | peak z (m) | status "
              "| matched points | matched stems | peak-mass share | hypotheses | load | reason |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in df.itertuples():
        lines.append(f"| {r.case} | {r.campaign} | {r.pair} | {r.shared} | {r.n} | {r.wall:.2f} "
                     f"| {r.cpu:.2f} | {r.search:.2f} | {r.xy:.3f} | {r.z:.3f} | {r.h:.3f} "
                     f"| {r.z_source} | {r.z_feat:.3f} | {r.peak_z:.3f} | {r.status} "
                     f"| {r.matched} | {r.stems} | {r.share:.3f} | {r.hyp} | {r.load:.1f} "
                     f"| {r.reason} |")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--box-pairs", type=int, default=8)
    ap.add_argument("--noprior-pairs", type=int, default=5)
    ap.add_argument("--low-pairs", type=int, default=3)
    ap.add_argument("--peer-pairs", type=int, default=2,
                    help="pairs per case given to the (slow) peer; 0: no peer")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/forestmap_bench_registration"))
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--save-text", type=Path, help="also write the section's text to this file")
    a = ap.parse_args()
    df, peer = run(a.box_pairs, a.noprior_pairs, a.low_pairs, a.cache, a.peer_pairs)
    text = table(df, peer)
    print(text)
    if a.save_text:
        a.save_text.write_text(text)
    if not a.no_write:
        write_section("registration", "## Registration (`benchmarks/bench_registration.py`)\n\n" + text)


if __name__ == "__main__":
    main()
