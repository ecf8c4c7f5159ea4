"""Hue-assisted ICP benchmark (issue 8): Men's speed-ups and the pipeline's fine registration.

One simulated coloured forest campaign at full resolution (``forestmap simulate`` with the
colour camera, ``sim/colour.py``; E57 files, which keep RGB) in ``--cache``:

1. **D6 analogue** (men spec 8.3, Table 5.2): one coloured scan (within 20 m, voxel 0.15 m) is
   copied and moved by 5 deg about x, y and z and t = (1.014969, 2.00582, 0.706715) m; 3-D ICP
   and HICP for w = 0.05 ... 100 from identity (per-axis shared scale, fixed radius): iterations,
   seconds, ratios to ICP next to the thesis's, final errors, eps_n. Peer: Open3D point-to-point
   ICP on the same clouds.
2. **D8 analogue** (Table 5.3): two neighbouring scans (partial overlap, real hue differences),
   started 0.2 m / 1.5 deg off: iterations, seconds, eps (mean pair distance), eps_n and the
   error against the truth per weight.
3. **Pipeline**: ``forestmap run`` (branch and bound on the feature sub-maps), then every accepted
   pair refined on the raw points (``core.registration.refine``) by HICP + robust point-to-plane (the pipeline's
   default for colour scans), HICP alone, plain ICP (w = 0), Open3D point-to-plane with a Tukey
   kernel + robust 4-DoF steps (the default without colour) and the same in least squares; pair
   errors and the optimal map's pose errors against the truth before and after, and the errors
   divided by the reported sigmas.

Writes its section of ``benchmarks/results.md``.
Usage: ``python benchmarks/bench_hicp.py [--cache DIR] [--scans 6] [--trees 40]``.
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
from results_md import write_section  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))

START, END = "<!-- hicp:start -->", "<!-- hicp:end -->"
D6_T = np.array([1.014969, 2.00582, 0.706715])
THESIS_T52 = {0.0: (166.89, 51), 0.05: (98.05, 33), 0.1: (93.07, 30), 0.2: (87.76, 28), 0.4: (73.11, 25),
              1.0: (56.06, 21), 2.0: (52.42, 19), 5.0: (42.25, 16), 10.0: (36.21, 14), 100.0: (28.08, 12)}
THESIS_T53 = {0.0: (678.02, 108, 0.066, 0.9957), 0.01: (437.02, 93, 0.041, 0.9968),
              0.02: (432.58, 94, 0.041, 0.9969), 0.05: (332.69, 74, 0.040, 0.9969),
              0.1: (366.60, 81, 0.042, 0.9969), 0.2: (306.15, 70, 0.043, 0.9971),
              0.3: (277.61, 74, 0.045, 0.9971)}


def rotation_xyz(ax: float, ay: float, az: float) -> np.ndarray:
    a, b, c = np.radians([ax, ay, az])
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


def angle_deg(ra, rb) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(ra.T @ rb) - 1) / 2, -1, 1))))


def ensure_campaign(cache: Path, scans: int, trees: int, plot: float, seed: int, progress=print) -> Path:
    from forestmap_assets.sim import simulate_campaign

    folder = cache / "colour_plot"
    if not (folder / "truth" / "poses.csv").exists():
        progress(f"simulating {folder} ({scans} scans, {trees} trees, {plot:g} m, full resolution, colour)")
        simulate_campaign(folder, scans=scans, trees=trees, plot_size=plot, seed=seed, resolution="full",
                          fmt="e57", scanner_kwargs={"colour": True}, progress=progress)
    return folder


def run_pipeline(folder: Path, progress=print) -> None:
    from forestmap_assets.orchestration.runner import run_campaign

    t0 = time.perf_counter()
    summary = run_campaign(folder, progress=progress)
    if summary.failures:
        raise RuntimeError(f"pipeline failed: {summary.failures[0]}")
    progress(f"pipeline in {time.perf_counter() - t0:.0f} s")


def clouds_of(folder: Path) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    from forestmap_assets.access import load_asset
    from forestmap_assets.core.registration.colour import rgb_to_hue

    out = {}
    for sid in pd.read_csv(folder / "truth" / "poses.csv")["scan"]:
        img = load_asset("range_images", campaign=folder, scan=sid)
        v = img.valid
        out[sid] = (img.xyz[v], rgb_to_hue(img.rgb[v]) if img.rgb is not None else None)
    return out


def truth_rel(truth: pd.DataFrame, scan: str, ref: str) -> np.ndarray:
    from forestmap_assets.core.geometry import relative_pose

    t = truth.set_index("scan")
    return np.array(relative_pose(t.loc[scan].to_numpy(float), t.loc[ref].to_numpy(float)))


# --------------------------------------------------------------------------------------------


def d6_analogue(points, hue, radius=0.05, voxel=0.15, progress=print) -> pd.DataFrame:
    from forestmap_assets.core.cloud import voxel_subsample
    from forestmap_assets.core.registration.hicp import hicp
    from forestmap_assets.core.registration.icp_uncertainty import merged_normal_quality

    keep = np.linalg.norm(points[:, :2], axis=1) < 20.0
    p, h = points[keep], hue[keep]
    k = voxel_subsample(p, voxel)
    p, h = p[k], h[k]
    r_true = rotation_xyz(5, 5, 5)
    data = (p - D6_T) @ r_true
    rows = []
    for w in (0.0, 0.05, 0.1, 0.2, 0.4, 1.0, 2.0, 5.0, 10.0, 100.0):
        c0 = time.process_time()
        res = hicp(p, data, h, h, weight=w, radius=radius)
        cpu = time.process_time() - c0
        moved = data @ res.rotation.T + res.translation
        eps_n = merged_normal_quality(p[::4], moved[::4], 0.45) if w in (0.0, 0.2, 100.0) else np.nan
        rows.append(dict(method="3-D ICP" if w == 0 else f"HICP w = {w:g}", w=w, points=len(p),
                         iterations=res.iterations, seconds=res.seconds, cpu_s=cpu, converged=res.converged,
                         rot_err_deg=angle_deg(res.rotation, r_true),
                         trans_err_m=float(np.linalg.norm(res.translation - D6_T)), eps_n=eps_n))
        progress(f"  D6 {rows[-1]['method']}: {res.iterations} iterations, {res.seconds:.1f} s")
    # peer: Open3D point-to-point ICP, same clouds, same start, correspondence distance = the
    # radius in metres (per-axis scale: the largest extent)
    import open3d as o3d

    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(data))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    dist = radius * float((p.max(0) - p.min(0)).max())
    t0, c0 = time.perf_counter(), time.process_time()
    r = reg.registration_icp(src, dst, dist, np.eye(4), reg.TransformationEstimationPointToPoint(),
                             reg.ICPConvergenceCriteria(1e-9, 1e-9, 200))
    secs, cpu = time.perf_counter() - t0, time.process_time() - c0
    m = np.asarray(r.transformation)
    rows.append(dict(method=f"Open3D point-to-point ICP ({dist:.1f} m)", w=np.nan, points=len(p), iterations=np.nan,
                     seconds=secs, cpu_s=cpu, converged=True, rot_err_deg=angle_deg(m[:3, :3], r_true),
                     trans_err_m=float(np.linalg.norm(m[:3, 3] - D6_T)), eps_n=np.nan))
    out = pd.DataFrame(rows)
    icp = out.iloc[0]
    out["iter_ratio"] = out["iterations"] / icp["iterations"]
    out["time_ratio"] = out["cpu_s"] / icp["cpu_s"]
    out["thesis_iterations"] = [THESIS_T52.get(w, (np.nan, np.nan))[1] for w in out["w"]]
    out["thesis_iter_ratio"] = out["thesis_iterations"] / THESIS_T52[0.0][1]
    out["thesis_time_ratio"] = [THESIS_T52.get(w, (np.nan,))[0] / THESIS_T52[0.0][0] for w in out["w"]]
    return out


def d8_analogue(clouds, truth, scan, ref, progress=print) -> pd.DataFrame:
    from forestmap_assets.core.cloud import voxel_subsample
    from forestmap_assets.core.geometry import wrap_deg
    from forestmap_assets.core.registration.hicp import Embedding, ModelIndex, hicp
    from forestmap_assets.core.registration.icp_uncertainty import merged_normal_quality

    (ps, hs), (pr, hr) = clouds[scan], clouds[ref]

    def crop(p, h, voxel):
        k = (np.linalg.norm(p[:, :2], axis=1) < 20.0) & (p[:, 2] < 1.5)
        p, h = p[k], h[k]
        v = voxel_subsample(p, voxel)
        return p[v], h[v]

    ps, hs = crop(ps, hs, 0.1)
    pr, hr = crop(pr, hr, 0.05)
    tr = truth_rel(truth, scan, ref)
    start = tr + np.array([0.2, -0.15, 0.1, 1.5])
    rows = []
    for w in (0.0, 0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 1.0):
        emb = Embedding.from_clouds(pr, weight=w, scale="isotropic")
        index = ModelIndex.build(pr, hr if w else None, emb)
        radius = 0.4 / emb.scale.max()
        res = hicp(pr, ps, hr, hs, weight=w, init=start, radius=radius, dof=4, index=index, max_iterations=200)
        e = res.pose4 - tr
        e[3] = wrap_deg(e[3])
        moved = ps @ res.rotation.T + res.translation
        eps_n = merged_normal_quality(pr[::6], moved[::6], 0.3)
        rows.append(dict(method="3-D ICP" if w == 0 else f"HICP w = {w:g}", w=w, iterations=res.iterations,
                         seconds=res.seconds, converged=res.converged, eps_mm=res.error_m * 1000, eps_n=eps_n,
                         err_xy_mm=float(np.hypot(e[0], e[1]) * 1000), err_z_mm=float(abs(e[2]) * 1000),
                         err_heading_mdeg=float(abs(e[3]) * 1000)))
        progress(f"  D8 {rows[-1]['method']}: {res.iterations} iterations, {res.seconds:.1f} s, "
                 f"xy error {rows[-1]['err_xy_mm']:.1f} mm")
    out = pd.DataFrame(rows)
    out["thesis_iterations"] = [THESIS_T53.get(w, (np.nan,) * 4)[1] for w in out["w"]]
    out["thesis_eps"] = [THESIS_T53.get(w, (np.nan,) * 4)[2] for w in out["w"]]
    out["thesis_eps_n"] = [THESIS_T53.get(w, (np.nan,) * 4)[3] for w in out["w"]]
    return out


def pipeline_refinement(folder: Path, clouds, truth, progress=print):
    from dataclasses import replace

    from forestmap_assets.access import load_asset
    from forestmap_assets.core.geometry import wrap_deg
    from forestmap_assets.core.mapping.link_selection import select_links
    from forestmap_assets.core.registration.refine import refine_registrations
    from forestmap_assets.params.men import RefineSettings

    regs = load_asset("pairwise_registrations", campaign=folder)["registrations"]
    accepted = regs[regs["status"] == "accepted"].reset_index(drop=True)
    reference = truth["scan"].iloc[0]
    settings = RefineSettings()
    variants = {"branch and bound (features)": None,
                "HICP w = 0.05 + robust point-to-plane (default, colour)": settings,
                "HICP w = 0.05 alone (Men)": replace(settings, plane_polish=False),
                "3-D ICP (w = 0)": replace(settings, method="icp", plane_polish=False),
                "Open3D point-to-plane, Tukey kernel + robust 4-DoF (default, no colour)":
                    replace(settings, method="point_to_plane"),
                "Open3D point-to-plane + 4-DoF, least squares": replace(settings, method="point_to_plane",
                                                                         robust_k=None)}
    pair_rows, pose_rows, raw_rows = [], [], []
    tpos = truth.set_index("scan")
    for name, s in variants.items():
        if s is None:
            table, secs = accepted, np.full(len(accepted), np.nan)
        else:
            t0 = time.perf_counter()
            out = refine_registrations(accepted, clouds, s, progress=progress)
            progress(f"  {name}: {time.perf_counter() - t0:.0f} s")
            table = out["registrations"]
            secs = out["refinements"]["seconds"].to_numpy(float)
            for q in out["refinements"].itertuples():  # the refinement's own result, used or not
                tr = truth_rel(truth, q.scan, q.reference)
                e = np.array([q.ref_dx, q.ref_dy, q.ref_dz, q.ref_dheading_deg]) - tr
                e[3] = wrap_deg(e[3])
                raw_rows.append(dict(method=name, exy=np.hypot(e[0], e[1]), ez=abs(e[2]), eh=abs(e[3]),
                                     used=q.used == "refined", fit_gain_um=(q.fit_bnb_m - q.fit_refined_m) * 1e6,
                                     iterations=q.iterations))
        for k, r in enumerate(table.itertuples()):
            tr = truth_rel(truth, r.scan, r.reference)
            e = np.array([r.dx, r.dy, r.dz, r.dheading_deg]) - tr
            e[3] = wrap_deg(e[3])
            pair_rows.append(dict(method=name, pair=f"{r.scan}{r.reference}", refined=bool(getattr(r, "refined", False)),
                                  exy=np.hypot(e[0], e[1]), ez=abs(e[2]), eh=abs(e[3]),
                                  nx=e[0] / r.sd_x, ny=e[1] / r.sd_y, nz=e[2] / r.sd_z, nh=e[3] / r.sd_heading_deg,
                                  seconds=secs[k]))
        sel = select_links(table, reference, scans=list(truth["scan"]), confidence="confidence")
        poses = sel.solution.poses
        for p in poses.itertuples():
            if p.scan == reference or not p.registered:
                continue
            t = tpos.loc[p.scan]
            e = np.array([p.x - t.x, p.y - t.y, p.z - t.z, wrap_deg(p.heading_deg - t.heading_deg)])
            pose_rows.append(dict(method=name, scan=p.scan, exy=np.hypot(e[0], e[1]), ez=abs(e[2]), eh=abs(e[3]),
                                  nxy=np.hypot(e[0] / p.sd_x, e[1] / p.sd_y) / np.sqrt(2)))
    return pd.DataFrame(pair_rows), pd.DataFrame(pose_rows), pd.DataFrame(raw_rows)


# --------------------------------------------------------------------------------------------


def machine() -> str:
    return f"{platform.machine()} / {os.cpu_count()} cores (shared), Python {platform.python_version()}"


def md(df: pd.DataFrame, cols, fmt) -> str:
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in df.iterrows():
        lines.append("| " + " | ".join(fmt.get(c, "{}").format(r[c]) if pd.notna(r[c]) else "" for c in cols) + " |")
    return "\n".join(lines)


def report(d6, d8, pairs, poses, raw, info) -> str:
    f2, f3 = "{:.2f}", "{:.3f}"
    out = [START, "## Hue-assisted ICP (`benchmarks/bench_hicp.py`, issue 8)", "",
           f"`python benchmarks/bench_hicp.py` on {machine()}, {time.strftime('%Y-%m-%d')}. {info}", "",
           "### D6 analogue: speed-up of HICP over 3-D ICP (Table 5.2)", "",
           "A coloured simulated forest scan (points within 20 m, voxel 0.15 m) and its copy moved by 5 deg "
           "about x, y, z and (1.014969, 2.00582, 0.706715) m; per-axis shared scale, radius 0.05 "
           "(normalised), convergence of eps, N and S (spec 5.5). `seconds` wall clock, `cpu_s` process CPU "
           "time (the machine is shared; `time_ratio` uses CPU time); the thesis's hardware is unknown, "
           "so compare ratios.", "",
           md(d6, ["method", "points", "iterations", "seconds", "cpu_s", "iter_ratio", "time_ratio", "thesis_iterations",
                   "thesis_iter_ratio", "thesis_time_ratio", "rot_err_deg", "trans_err_m", "eps_n"],
              {"iterations": "{:.0f}", "seconds": f2, "cpu_s": f2, "iter_ratio": f2, "time_ratio": f2,
               "thesis_iterations": "{:.0f}",
               "thesis_iter_ratio": f2, "thesis_time_ratio": f2, "rot_err_deg": "{:.1e}", "trans_err_m": "{:.1e}",
               "eps_n": "{:.4f}"}), "",
           "### D8 analogue: two scans, partial overlap (Table 5.3)", "",
           "Neighbouring coloured scans (data voxel 0.1 m, model 0.05 m, below 1.5 m above the sensor), "
           "4-DoF, start 0.2 m / 1.5 deg off, isotropic shared scale, radius 0.4 m. `eps` is the mean "
           "association distance (Eq. 5.5; the thesis's units are unknown).", "",
           md(d8, ["method", "iterations", "seconds", "eps_mm", "eps_n", "err_xy_mm", "err_z_mm", "err_heading_mdeg",
                   "thesis_iterations", "thesis_eps", "thesis_eps_n"],
              {"iterations": "{:.0f}", "seconds": f2, "eps_mm": f2, "eps_n": "{:.4f}", "err_xy_mm": "{:.1f}",
               "err_z_mm": "{:.1f}", "err_heading_mdeg": "{:.1f}", "thesis_iterations": "{:.0f}",
               "thesis_eps": f3, "thesis_eps_n": "{:.4f}"}), ""]
    agg = pairs.groupby("method", sort=False).agg(
        pairs=("pair", "size"), refined=("refined", "sum"), median_exy_mm=("exy", lambda v: 1000 * v.median()),
        max_exy_mm=("exy", lambda v: 1000 * v.max()), median_ez_mm=("ez", lambda v: 1000 * v.median()),
        median_eh_mdeg=("eh", lambda v: 1000 * v.median()),
        rms_norm_xy=("nx", lambda v: float(np.sqrt(np.mean(np.r_[v, pairs.loc[v.index, "ny"]] ** 2)))),
        rms_norm_h=("nh", lambda v: float(np.sqrt(np.mean(v**2)))),
        median_seconds=("seconds", "median")).reset_index()
    pagg = poses.groupby("method", sort=False).agg(
        scans=("scan", "size"), median_exy_mm=("exy", lambda v: 1000 * v.median()),
        max_exy_mm=("exy", lambda v: 1000 * v.max()), median_ez_mm=("ez", lambda v: 1000 * v.median()),
        median_eh_mdeg=("eh", lambda v: 1000 * v.median()),
        rms_norm_xy=("nxy", lambda v: float(np.sqrt(np.mean(v**2))))).reset_index()
    ragg = raw.groupby("method", sort=False).agg(
        pairs=("exy", "size"), used=("used", "sum"), median_exy_mm=("exy", lambda v: 1000 * v.median()),
        max_exy_mm=("exy", lambda v: 1000 * v.max()), median_ez_mm=("ez", lambda v: 1000 * v.median()),
        median_eh_mdeg=("eh", lambda v: 1000 * v.median()), median_iterations=("iterations", "median")).reset_index()
    out += ["### Pipeline: refinement of the accepted pairs (full resolution)", "",
            "Each refinement's own result against the truth (used or not), and how many passed the "
            "fit test (mean point-to-plane distance, truncated at the robust cut-off, lower than at the "
            "branch-and-bound pose; `core/refine.py`). Robust = Tukey's biweight at 4.685 robust sigmas "
            "(`refine.robust_k`); least squares = every pair within the 0.2 m radius at full weight:", "",
            md(ragg, list(ragg.columns), {"median_exy_mm": f2, "max_exy_mm": f2, "median_ez_mm": f2,
                                           "median_eh_mdeg": "{:.1f}", "used": "{:.0f}",
                                           "median_iterations": "{:.0f}"}), "",
            "The observations passed to the optimal map (refined where used, else the branch-and-bound "
            "pose; location of `scan` in `reference`'s frame) and `rms_norm_*` = RMS of error / "
            "reported sigma (1 = honest):", "",
            md(agg, list(agg.columns), {"median_exy_mm": f2, "max_exy_mm": f2, "median_ez_mm": f2,
                                         "median_eh_mdeg": "{:.1f}", "rms_norm_xy": f2, "rms_norm_h": f2,
                                         "median_seconds": "{:.1f}", "refined": "{:.0f}"}), "",
            "Optimal map (link selection + Lu-Milios on the accepted observations), pose errors of the "
            "non-reference scans against the truth:", "",
            md(pagg, list(pagg.columns), {"median_exy_mm": f2, "max_exy_mm": f2, "median_ez_mm": f2,
                                           "median_eh_mdeg": "{:.1f}", "rms_norm_xy": f2}), ""]
    out.append(END)
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/forestmap_bench_hicp"))
    ap.add_argument("--scans", type=int, default=6)
    ap.add_argument("--trees", type=int, default=40)
    ap.add_argument("--plot-size", type=float, default=40.0)
    ap.add_argument("--seed", type=int, default=21)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("FORESTMAP_HOME", str(args.cache / "home"))
    folder = ensure_campaign(args.cache, args.scans, args.trees, args.plot_size, args.seed)
    run_pipeline(folder)
    truth = pd.read_csv(folder / "truth" / "poses.csv")
    clouds = clouds_of(folder)
    first = truth["scan"].iloc[0]
    d6 = d6_analogue(*clouds[first])
    print(d6.to_string())
    rel = {s: np.hypot(*truth_rel(truth, s, first)[:2]) for s in truth["scan"].iloc[1:]}
    near = min(rel, key=rel.get)
    d8 = d8_analogue(clouds, truth, near, first)
    print(d8.to_string())
    pairs, poses, raw = pipeline_refinement(folder, clouds, truth)
    print(pairs.to_string())
    print(poses.to_string())
    print(raw.to_string())
    info = (f"Campaign: {args.scans} scans, {args.trees} trees, {args.plot_size:g} m plot, seed {args.seed}, full "
            f"resolution (720 x 3000), colour camera model of `sim/colour.py`; D8 pair {near}-{first} "
            f"({rel[near]:.1f} m apart).")
    text = report(d6, d8, pairs, poses, raw, info)
    print(text)
    if not args.no_write:
        write_section("hicp", text)


if __name__ == "__main__":
    main()
