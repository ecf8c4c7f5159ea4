"""Structured sites (issue 10): the pillar study, wall lines, the indoor failure modes and chained
vs optimal maps on the simulated corridor (spec 4.1, 5, 7.2-7.3, 8.3, 10.1-10.5, 11).

    python benchmarks/bench_structured.py [--fresh] [--only pillar,lines,failures,corridor]

Writes its section of ``benchmarks/results.md`` (between ``<!-- structured:start -->`` and
``<!-- structured:end -->``), ``benchmarks/structured_pillar.png`` and prints the tables.
Simulated campaigns, features and registrations are cached under
``/tmp/forestmap_bench_structured`` (``--fresh`` recomputes). Full thesis resolution (3000 x
720) except where a table says otherwise; about 20-30 minutes on 2 shared cores.

Peer: Open3D point-to-plane ICP (6-DoF, from the a priori pose, 0.1 m voxels) on the scans'
levelled raw points, the usual alternative to feature-based global search.
"""

from __future__ import annotations

import argparse
import hashlib
import pickle
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd
from results_md import write_section  # noqa: E402

from forestmap_assets.core.features.cylinders import extract_features
from forestmap_assets.core.mapping.chained_map import chained_map
from forestmap_assets.core.mapping.chaining import OBSERVATION_COLUMNS
from forestmap_assets.core.mapping.link_selection import check_link_hypothesis, select_links
from forestmap_assets.core.registration.candidates import candidate_pairs
from forestmap_assets.core.registration.pair_checks import (
    assess_history,
    assess_pair,
    register_in_box,
    search_box,
)
from forestmap_assets.core.registration.pair_registrations import (
    judge_in_box,
    observation_sigmas,
    register_candidates,
)
from forestmap_assets.io.campaign import load_campaign
from forestmap_assets.params import resolve_params
from forestmap_assets.sim.campaign import simulate_campaign
from forestmap_assets.sim.corridor import corridor_scene, make_corridor
from forestmap_assets.sim.ground import ground_mesh
from forestmap_assets.sim.scanner import ScanPose, VirtualScanner
from forestmap_assets.sim.scene_mesh import KIND_GROUND
from forestmap_assets.sim.site_assembly import SiteBuilder
from forestmap_assets.sim.site_eval import (
    campaign_features,
    extract_scan_features,
    line_recall,
    pillar_detection,
    pillar_surface_points,
    pose_errors_vs_truth,
    relative_truth,
    scan_site,
    truth_relative,
)
from forestmap_assets.sim.site_meshes import (
    KIND_CEILING,
    KIND_PILLAR,
    KIND_WALL,
    PILLAR_RADIUS_M,
    Wall,
    flat_ground,
    pillar_mesh,
    plane_mesh,
    walls_mesh,
)
from forestmap_assets.sim.site_truth import lines_in_frame, points_in_frame

HERE = Path(__file__).parent
PLOT = HERE / "structured_pillar.png"
CACHE = Path("/tmp/forestmap_bench_structured")
MARK = "structured"
CIRCLES = {"symmetry_statistic": "noise_corrected"}  # see the pillar study
INDOOR = resolve_params("indoor")
GUARD = dict(min_support_m=1.0, max_rival_ratio=0.6)
METHOD = "fast"  # registration evaluator of the campaigns, --method (same lattice maximum)


def machine() -> str:
    import os

    return f"{platform.machine()} / {os.cpu_count()} cores shared, Python {platform.python_version()}"


def _cached(name: str, fresh: bool, make):
    path = CACHE / f"{name}.pkl"
    if path.exists() and not fresh:
        return pickle.loads(path.read_bytes())
    value = make()
    CACHE.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(value))
    return value


def md(df: pd.DataFrame, floatfmt: str = ".3f") -> str:
    cols = list(df.columns)
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for row in df.itertuples(index=False):
        out.append("| " + " | ".join(
            ("" if not np.isfinite(v) else format(v, floatfmt)) if isinstance(v, float) else str(v)
            for v in row) + " |")
    return "\n".join(out)


# ---- peer --------------------------------------------------------------------------------------
def levelled_cloud(image, max_range_m: float = 20.0) -> np.ndarray:
    p = image.xyz[image.valid]
    return p[np.linalg.norm(p, axis=1) <= max_range_m]


def open3d_icp(src: np.ndarray, dst: np.ndarray, init, voxel: float = 0.1) -> np.ndarray:
    """Open3D point-to-plane ICP from ``init`` (dx, dy, dz, dheading); returns the same 4 values
    of the 6-DoF result (the peer)."""
    import open3d as o3d

    def pc(p):
        c = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(voxel)
        c.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel, max_nn=30))
        return c

    h = np.radians(init[3])
    t0 = np.eye(4)
    t0[:2, :2] = [[np.cos(h), -np.sin(h)], [np.sin(h), np.cos(h)]]
    t0[:3, 3] = init[:3]
    reg = o3d.pipelines.registration
    res = reg.registration_icp(pc(src), pc(dst), 1.0, t0,
                               reg.TransformationEstimationPointToPlane(),
                               reg.ICPConvergenceCriteria(max_iteration=60))
    t = res.transformation
    return np.array([t[0, 3], t[1, 3], t[2, 3], np.degrees(np.arctan2(t[1, 0], t[0, 0]))])


# ---- 1. pillar study (spec 4.1) ------------------------------------------------------------------
def pillar_scene(d: float):
    """One 0.192 m pillar, floor to a 2.3 m ceiling, ``d`` m in front of the scanner, a wall
    6 m behind it."""
    b = SiteBuilder()
    gv, gf = ground_mesh(flat_ground(), 40.0, 2.0)
    b.pieces.append((gv, gf, np.full(len(gf), KIND_GROUND), np.full(len(gf), -1),
                     np.zeros(len(gf))))
    b.add(*plane_mesh(-5.0, d + 7.0, -10.0, 10.0, 2.3), KIND_CEILING)
    wv, wf, wo = walls_mesh([Wall((d + 6.0, -10.0), (d + 6.0, 10.0), 2.3, 0.2)])
    b.add(wv, wf, KIND_WALL, wo)
    pv, pf = pillar_mesh(np.array([[d, 0.0]]), np.zeros(1), np.array([2.3]),
                         np.array([PILLAR_RADIUS_M]))
    b.add(pv, pf, KIND_PILLAR)
    return b.mesh()


def pillar_study(seeds: int = 3, distances=None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Cylinder radius against distance through simulator + segments/circles/cylinders with the
    indoor preset; beam footprint on (the Riegl's 0.042 m + 3 mrad first return) and off."""
    distances = np.linspace(1.2, 18.4, 17) if distances is None else distances
    rows, prof = [], []
    hfov = 30.0
    for beam in ("footprint", "centre ray"):
        for d in distances:
            for seed in range(seeds):
                y = 0.02 * (seed - 1)  # the pillar a little off the beam grid per repeat
                mesh = pillar_scene(d)
                # repeats sample the pillar at different phases of the 0.11 deg pixel grid
                sc = VirtualScanner(mesh, hfov_deg=hfov, n_cols=int(round(3000 * hfov / 330)),
                                    sub_rays=8 if beam == "footprint" else 0,
                                    azimuth_centre_deg=0.11 * seed / seeds)
                t0 = time.perf_counter()
                r = sc.scan(ScanPose(0.0, -y, 1.3, 0.0), seed)
                f = extract_features(r.image, INDOOR, **CIRCLES)
                circ = f["circle_models"]
                last = circ[circ["iteration"] == circ["iteration"].max()]
                near = np.hypot(last["cx"] - d, last["cy"] - y) < 0.5
                c = f["cylinder_segments"]
                cn = np.hypot((c["x0"] + c["x1"]) / 2 - d, (c["y0"] + c["y1"]) / 2 - y) < 0.5
                mean_stat = extract_features(r.image, INDOOR, symmetry_statistic="mean")["cylinder_segments"] if (
                    seed == 0) else None
                rows.append({
                    "beam": beam, "distance_m": d, "seed": seed,
                    "cylinders": int(cn.sum()),
                    "radius_m": float(np.average(c["radius_m"][cn], weights=c["length_m"][cn]))
                    if cn.any() else np.nan,
                    "circles": int(near.sum()), "valid": int((near & last["valid"]).sum()),
                    "cylinders_mean_stat": np.nan if mean_stat is None else int(
                        (np.hypot((mean_stat["x0"] + mean_stat["x1"]) / 2 - d,
                                  (mean_stat["y0"] + mean_stat["y1"]) / 2 - y) < 0.5).sum()),
                    "seconds": time.perf_counter() - t0,
                })
                if seed == 0 and beam == "footprint" and (abs(d - 3.7) < 0.6 or abs(d - 14.5) < 0.6):
                    v = last[near & last["valid"]]
                    prof.append(pd.DataFrame({"distance_m": d, "height_m": v["cz"] + 1.3,
                                              "radius_m": v["radius_m"]}))
            print(f"pillar {beam} {d:.2f} m: "
                  f"{np.nanmean([r['radius_m'] for r in rows[-seeds:]]):.4f}", flush=True)
    return pd.DataFrame(rows), pd.concat(prof, ignore_index=True) if prof else pd.DataFrame()


def pillar_plot(tab: pd.DataFrame, prof: pd.DataFrame, path: Path = PLOT) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    for beam, style in (("footprint", "o-"), ("centre ray", "s--")):
        g = tab[tab["beam"] == beam].groupby("distance_m")["radius_m"]
        ax[0].errorbar(g.mean().index, g.mean().values, yerr=g.std().values, fmt=style,
                       capsize=3, label=f"cylinder radius, {beam} beam")
    ax[0].axhline(PILLAR_RADIUS_M, color="k", lw=1, label="true radius 0.192 m")
    ax[0].set_xlabel("distance from the scanner (m)")
    ax[0].set_ylabel("radius (m)")
    ax[0].set_title("Pillar radius vs distance (thesis Figs 4.17-4.21)")
    ax[0].legend(fontsize=8)
    for d, g in prof.groupby("distance_m"):
        ax[1].plot(g["radius_m"], g["height_m"], ".", ms=3, label=f"{d:.1f} m")
    ax[1].axvline(PILLAR_RADIUS_M, color="k", lw=1)
    ax[1].set_xlabel("circle radius (m)")
    ax[1].set_ylabel("height above the floor (m)")
    ax[1].set_title("Circle radius along the pillar (footprint beam)")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---- 2. campaigns: corridor ring and parking lot -----------------------------------------------
def corridor_campaign(fresh: bool) -> Path:
    out = CACHE / "corridor"
    if fresh or not (out / "campaign.yaml").exists():
        simulate_campaign(out, site="corridor", scans=20, plot_size=30.0, seed=4,
                          resolution="full", pair_span=2, site_kwargs={"scan_spacing_m": 5.8},
                          progress=print)
    return out


def lot_campaign(fresh: bool) -> Path:
    out = CACHE / "parking_lot"
    if fresh or not (out / "campaign.yaml").exists():
        simulate_campaign(out, site="parking-lot", scans=6, plot_size=60.0, trees=6, seed=4,
                          resolution="full", site_kwargs={"scan_spacing_m": 10.0},
                          progress=print)
    return out


def features_of(folder: Path, fresh: bool):
    return _cached(f"features_{folder.name}", fresh,
                   lambda: campaign_features(folder, circle_options=CIRCLES, progress=print))


def cylinder_weight(folder: Path) -> int:
    """The campaign preset's sub-map cylinder weight (core/submaps.py, issue 10); until
    params.py carries ``SubmapParams.cylinder_weight``: 2 where lines are on, else 1."""
    p = load_campaign(folder).params
    return int(getattr(p.submaps, "cylinder_weight", 2 if p.lines.enabled else 1))


def with_weight(folder: Path, feats, weight: int) -> dict:
    """The cached features with their sub-maps rebuilt at ``weight`` (cheap)."""
    from forestmap_assets.core.registration.submaps import build_submap

    spacing = load_campaign(folder).params.submaps.spacing_m
    return {s: {**f, "submaps": build_submap(f["cylinder_segments"], f["line_segments"], spacing,
                                             weight)} for s, f in feats.items()}


def slide_diagnosis(folder: Path, feats, table: pd.DataFrame) -> tuple[pd.DataFrame, str]:
    """Per wrong pair of ``table`` (truth error >= 0.1 m): Olson's score above the all-outlier
    floor from the line and from the cylinder points of the scan's sub-map at the true and at the
    found pose, and the cylinder weight k above which the true pose scores higher (issue 10)."""
    from scipy.spatial import cKDTree

    from forestmap_assets.core.geometry import transform_points
    from forestmap_assets.core.registration.score import ScoreModel

    model = ScoreModel.from_params(load_campaign(folder).params.registration)
    truth = pd.read_csv(folder / "truth" / "poses.csv", dtype={"scan": str})
    rows = []
    for r in table.itertuples(index=False):
        if not np.isfinite(r.peak_dx) or r.err_xy_m < 0.1:
            continue
        b, a = feats[r.scan]["submaps"], feats[r.reference]["submaps"]
        tree = cKDTree(a[["x", "y", "z"]].to_numpy(float))
        cyl = (b["feature"] == "cylinder").to_numpy()
        tr = truth_relative(truth, r.scan, r.reference)
        found = np.array([r.peak_dx, r.peak_dy, r.peak_dz, r.peak_dheading_deg])
        sep = {}
        out = {"pair": f"{r.scan}-{r.reference}"}
        for name, pose in (("true", tr), ("found", found)):
            d, _ = tree.query(transform_points(b[["x", "y", "z"]].to_numpy(float), pose))
            lp = model.log_p(d) - model.ln_k1
            out[f"lines_{name}"], out[f"cylinders_{name}"] = lp[~cyl].sum(), lp[cyl].sum()
            sep[name] = float(np.hypot(pose[0], pose[1]))
        gain = out["cylinders_true"] - out["cylinders_found"]
        out["true_sep_m"], out["found_sep_m"] = sep["true"], sep["found"]
        out["k_needed"] = ((out["lines_found"] - out["lines_true"]) / gain if gain > 0 else np.inf)
        rows.append(out)
    d = pd.DataFrame(rows)
    if not len(d):
        return d, "No wrong pairs with the thesis's sub-maps."
    closer = int((d["found_sep_m"] < d["true_sep_m"]).sum())
    fin = d[np.isfinite(d["k_needed"])]
    text = (
        "Why pairs come out metres off with the thesis's sub-maps (weight 1; issue 10): of the "
        f"{len(d)} wrong results with a peak, {closer} place the scan *closer* to the reference "
        f"than the truth (median separation {d['found_sep_m'].median():.1f} m found vs "
        f"{d['true_sep_m'].median():.1f} m true), slid along the corridor with the heading right. "
        "Line detection is range limited (recall within 10 m vs 40 m in the lines table), so each "
        "sub-map's wall/ceiling lines cluster round its scanner, and sliding one scan towards the "
        "other along straight walls adds line overlap. Score above the all-outlier floor at the "
        "true vs the found pose, split by the scan's line and cylinder points: lines "
        f"{d['lines_true'].median():.0f} vs {d['lines_found'].median():.0f} (medians), cylinders "
        f"{d['cylinders_true'].median():.0f} vs {d['cylinders_found'].median():.0f}. The lines "
        "are real wall/ceiling borders at the right height and the truth lies inside the box: "
        "the score counts a wall line per metre although its extent along the wall is where the "
        "scanner happened to detect it. Fix (inferred, `core/submaps.build_submap("
        "cylinder_weight=k)`): cylinders sampled k times as densely, k = 2 being the information "
        "ratio of a point fixed in both horizontal directions to one fixed across a line only. "
        f"The true pose outscores the found one from k = {fin['k_needed'].min():.2f} - "
        f"{fin['k_needed'].max():.2f} on {len(fin)} pairs ({int((fin['k_needed'] < 2).sum())} "
        f"below 2); on {len(d) - len(fin)} pairs (corners and ring closure) no pillar matches at "
        "the true pose, so no weighting can help: there the shared features carry no along-wall "
        "information and the judge / structure checks reject the result."
    )
    return d, text


def line_table(folder: Path, feats) -> pd.DataFrame:
    """Per scan: wall/ceiling line recall (visible corners up to 40 m and up to 10 m),
    precision, position error; pillars/poles within 12 m that the scan sees (>= 50 of its
    points on their surface) found, and their radius."""
    from forestmap_assets.io.readers import read_scan

    camp = load_campaign(folder)
    truth = pd.read_csv(folder / "truth" / "poses.csv", dtype={"scan": str}).set_index("scan")
    wl = pd.read_csv(folder / "truth" / "wall_lines.csv")
    vis = pd.read_csv(folder / "truth" / "visible_lines.csv", dtype={"scan": str})
    pil = pd.read_csv(folder / "truth" / "pillars.csv")
    rows = []
    for sid in camp.scan_ids:
        t = truth.loc[sid]
        o = t[["x", "y", "z"]].to_numpy(float)
        lines = lines_in_frame(wl, o, t["heading_deg"])
        v = vis[vis["scan"] == sid]
        det = feats[sid]["line_segments"]
        r40 = line_recall(det, v, lines)
        r10 = line_recall(det, v[np.hypot(v["x"], v["y"]) <= 10.0], lines)
        p = pillar_detection(feats[sid]["cylinder_segments"],
                             points_in_frame(pil, o, t["heading_deg"]), max_range_m=12.0)
        e = camp.scan(sid)
        image = read_scan(e.path, angular_step_deg=camp.angular_step_deg, tilt_deg=e.tilt_deg)
        p = p[pillar_surface_points(image.xyz[image.valid], p) >= 50]  # seen by the scan
        rows.append({"scan": sid, "lines": r40["n_detected"],
                     "length_m": r40["detected_length_m"], "recall_40m": r40["recall"],
                     "recall_10m": r10["recall"], "precision": r40["precision"],
                     "xy_err_m": r40["xy_error_m"], "z_err_m": r40["z_error_m"],
                     "pillars_12m": len(p), "found": int((p["n_cylinders"] > 0).sum()),
                     "radius_m": float(p["radius_est_m"].mean())})
    return pd.DataFrame(rows)


def register_isolated(cand: pd.DataFrame, submaps: dict, reg) -> dict:
    """``register_candidates`` pair by pair in a child process with ``reg.method``; a pair whose
    child crashes is registered with ``method='thesis'`` in this process instead (the 'fast'
    evaluator segfaulted on some corridor pairs when this benchmark was written). Adds the
    column ``evaluator``."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    ctx = multiprocessing.get_context("spawn")
    pool = None
    parts: dict[str, list] = {"registrations": [], "levels": [], "hypotheses": []}
    for k in range(len(cand)):
        row = cand.iloc[[k]].reset_index(drop=True)
        subs = {s: submaps[s] for s in (row["scan"][0], row["reference"][0]) if s in submaps}
        evaluator = reg.method
        t0 = time.perf_counter()
        try:
            if reg.method == "thesis":
                raise BrokenProcessPool("in process")
            pool = pool or ProcessPoolExecutor(1, mp_context=ctx)
            b = pool.submit(register_candidates, row, subs, reg).result()
        except BrokenProcessPool:
            pool = None
            b = register_candidates(row, subs, reg.model_copy(update={"method": "thesis"}))
            if reg.method != "thesis":
                evaluator = "thesis (fast crashed)"
        b["registrations"]["evaluator"] = evaluator
        for key in parts:
            parts[key].append(b[key])
        print(f"pair {k + 1}/{len(cand)}: {row['scan'][0]}-{row['reference'][0]} {evaluator} "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
    if pool is not None:
        pool.shutdown()
    return {key: pd.concat(v, ignore_index=True) for key, v in parts.items()}


def registrations_of(folder: Path, feats, fresh: bool, weight: int = 1):
    camp = load_campaign(folder)
    reg = camp.params.registration.model_copy(update={"method": METHOD})

    def make():
        cand = candidate_pairs(camp.scan_ids, pairs=[(p.scan, p.reference, p.a_priori)
                                                     for p in camp.pairs],
                               search=(reg.xy_m, reg.z_m, reg.heading_deg))
        t0 = time.perf_counter()
        b = register_isolated(cand, {k: v["submaps"] for k, v in feats.items()}, reg)
        b["candidates"] = cand
        b["seconds"] = time.perf_counter() - t0
        return b

    suffix = "" if weight == 1 else f"_w{weight}"
    return _cached(f"registrations_{folder.name}_{METHOD}{suffix}", fresh, make)


def guarded(folder: Path, feats, bundle) -> pd.DataFrame:
    """The registrations with the truth error, the existing judge's status and the structure
    checks' verdict (``status_guarded``)."""
    camp = load_campaign(folder)
    reg = camp.params.registration
    truth = pd.read_csv(folder / "truth" / "poses.csv", dtype={"scan": str})
    regs = bundle["registrations"].copy()
    cand, levels = bundle["candidates"], bundle["levels"]
    out = []
    for r, c in zip(regs.itertuples(index=False), cand.itertuples(index=False), strict=True):
        tr = truth_relative(truth, r.scan, r.reference)
        row = r._asdict()
        row["err_xy_m"] = float(np.hypot(r.dx - tr[0], r.dy - tr[1]))
        row["err_heading_deg"] = float(abs((r.dheading_deg - tr[3] + 180) % 360 - 180))
        row["status_guarded"], row["guard"] = r.status, ""
        if np.isfinite(r.peak_dx):
            why, fig = assess_pair(feats[r.scan]["submaps"], feats[r.reference]["submaps"],
                                   (r.peak_dx, r.peak_dy, r.peak_dz, r.peak_dheading_deg),
                                   (c.cx, c.cy, c.cz, c.cheading_deg),
                                   (c.hx, c.hy, c.hz, c.hheading_deg), reg, **GUARD,
                                   match_m=max(3 * reg.sigma_m, reg.final_cell_m))
            row.update({k: fig[k] for k in ("support_m", "rival_ratio")})
            lv = levels[(levels["scan"] == r.scan) & (levels["reference"] == r.reference)]
            why_h, late = assess_history(lv, (r.peak_dx, r.peak_dy, r.peak_dz,
                                              r.peak_dheading_deg), 0.0,  # only the verdict
                                         separation_m=reg.rival_exclusion_m,
                                         max_cell_m=reg.history_max_cell_m)
            row["history_flag"] = late is not None
            why = why or why_h
            if why and r.status == "accepted":
                row["status_guarded"], row["guard"] = "rejected", why.split(":")[0]
        out.append(row)
    return pd.DataFrame(out)


def refined(folder: Path, table: pd.DataFrame, fresh: bool, tag: str) -> pd.DataFrame:
    """The pipeline's ``refined_registrations`` stage (``core/refine.py`` with the campaign's
    ``refine`` settings, on the levelled raw points of each scan) applied to the links the judge
    and the structure checks accept; returns ``table`` with those links' refined pose and sigmas
    where the refinement is used (``refined``) and their new error against the truth."""
    from forestmap_assets.assets.registration import refine_settings
    from forestmap_assets.core.registration.refine import refine_registrations
    from forestmap_assets.io.readers import read_scan

    camp = load_campaign(folder)
    regs = table.copy()
    regs["status"] = np.where(regs["status_guarded"] == "accepted", "accepted", "rejected")

    def make():
        acc = regs[regs["status"] == "accepted"]
        clouds = {}
        for sid in sorted(set(acc["scan"]) | set(acc["reference"])):
            e = camp.scan(sid)
            img = read_scan(e.path, angular_step_deg=camp.angular_step_deg, tilt_deg=e.tilt_deg)
            clouds[sid] = (img.xyz[img.valid], None)
        return refine_registrations(regs, clouds, refine_settings(camp), progress=print)

    acc = regs.loc[regs["status"] == "accepted", ["scan", "reference", "dx", "dy", "dz",
                                                   "dheading_deg"]].to_numpy().tolist()
    key = hashlib.blake2b(repr(acc).encode(), digest_size=4).hexdigest()  # links and starts
    out = _cached(f"refined_{folder.name}_{tag}_{key}", fresh, make)["registrations"]
    out["status"] = table["status"].to_numpy()
    truth = pd.read_csv(folder / "truth" / "poses.csv", dtype={"scan": str})
    for k, r in out.iterrows():
        tr = truth_relative(truth, r["scan"], r["reference"])
        out.loc[k, "err_xy_m"] = float(np.hypot(r["dx"] - tr[0], r["dy"] - tr[1]))
        out.loc[k, "err_heading_deg"] = float(abs((r["dheading_deg"] - tr[3] + 180) % 360 - 180))
    return out


def _components(ids: list[str], links: pd.DataFrame) -> list[list[str]]:
    """Connected groups of scans (campaign order) under ``links`` (scan, reference)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pos = {s: k for k, s in enumerate(ids)}
    i = np.array([pos[s] for s in links["scan"]], dtype=int)
    j = np.array([pos[s] for s in links["reference"]], dtype=int)
    n, lab = connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(len(ids),) * 2),
                                  directed=False)
    return [[ids[k] for k in np.flatnonzero(lab == c)] for c in range(n)]


def maps_vs_truth(folder: Path, table: pd.DataFrame) -> pd.DataFrame:
    """Chained and optimal maps from three link sets, against truth. The links may split the
    scans into several connected pieces; each piece of 2 or more scans is mapped in the frame of
    its first scan and compared with the truth expressed in that frame."""
    camp = load_campaign(folder)
    truth = pd.read_csv(folder / "truth" / "poses.csv", dtype={"scan": str})
    ids = camp.scan_ids
    ok = table[np.isfinite(table["dx"])]
    consecutive = ok[[ids.index(s) - ids.index(r) == 1 for s, r in zip(ok["scan"], ok["reference"],
                                                                         strict=True)]]
    sets = {
        "thesis: every result, consecutive pairs": consecutive,
        "forestmap judge, no structure checks": ok[ok["status"] == "accepted"],
        "judge + structure checks": ok[ok["status_guarded"] == "accepted"],
    }
    rows = []
    for name, links in sets.items():
        obs = links.reset_index(drop=True)
        pieces = [c for c in _components(ids, obs) if len(c) > 1]
        for method in (("chain",) if name.startswith("thesis") else ("chain", "optimal")):
            t0 = time.perf_counter()
            errs, flagged = [], 0
            for piece in pieces:
                sub = obs[obs["scan"].isin(piece) & obs["reference"].isin(piece)]
                ref = piece[0]
                rel = pd.DataFrame([(s, *truth_relative(truth, s, ref)) for s in piece],
                                   columns=["scan", "x", "y", "z", "heading_deg"])
                if method == "chain":
                    m = chained_map(sub[list(OBSERVATION_COLUMNS)], piece)
                    poses = m.poses
                    flagged += int((m.residuals["verdict"] != "ok").sum())
                else:
                    sel = select_links(sub, ref, scans=piece, confidence="confidence")
                    poses = sel.solution.poses
                    flagged += int((sel.links["status"] == "rejected").sum())
                errs.append(pose_errors_vs_truth(poses, rel).dropna(subset=["exy"]))
            e = pd.concat(errs) if errs else pd.DataFrame(columns=["exy", "ez", "eheading_deg"])
            rows.append({
                "links": name, "map": method, "links_used": len(obs),
                "pieces (scans)": " + ".join(str(len(p)) for p in pieces) or "-",
                "max_xy_err_m": float(e["exy"].max()) if len(e) else np.nan,
                "rms_xy_err_m": float(np.sqrt((e["exy"] ** 2).mean())) if len(e) else np.nan,
                "max_heading_err_deg": float(e["eheading_deg"].abs().max()) if len(e)
                else np.nan,
                "max_z_err_m": float(e["ez"].abs().max()) if len(e) else np.nan,
                "links_flagged": flagged,
                "seconds": time.perf_counter() - t0,
            })
    return pd.DataFrame(rows)


def peer_on_pairs(folder: Path, table: pd.DataFrame, n: int = 8) -> pd.DataFrame:
    """Open3D ICP from the a priori pose on the first ``n`` consecutive pairs."""
    from forestmap_assets.io.readers import read_scan

    camp = load_campaign(folder)
    truth = pd.read_csv(folder / "truth" / "poses.csv", dtype={"scan": str})
    prior = {(p.scan, p.reference): p.a_priori for p in camp.pairs}
    imgs = {}
    rows = []
    for r in table.itertuples(index=False):
        if len(rows) >= n:
            break
        if camp.scan_ids.index(r.scan) - camp.scan_ids.index(r.reference) != 1:
            continue
        for s in (r.scan, r.reference):
            if s not in imgs:
                e = camp.scan(s)
                imgs[s] = levelled_cloud(read_scan(e.path, angular_step_deg=camp.angular_step_deg,
                                                   tilt_deg=e.tilt_deg))
        t0 = time.perf_counter()
        est = open3d_icp(imgs[r.scan], imgs[r.reference], prior[(r.scan, r.reference)])
        tr = truth_relative(truth, r.scan, r.reference)
        rows.append({"pair": f"{r.scan}-{r.reference}",
                     "peer_err_xy_m": float(np.hypot(est[0] - tr[0], est[1] - tr[1])),
                     "peer_err_heading_deg": float(abs((est[3] - tr[3] + 180) % 360 - 180)),
                     "peer_seconds": time.perf_counter() - t0,
                     "ours_err_xy_m": r.err_xy_m, "ours_status": r.status_guarded})
    return pd.DataFrame(rows)


# ---- 3. the failure modes (spec 7.3) ---------------------------------------------------------
def _register(scan_sub, ref_sub, centre, box, axes=0.0):
    reg = INDOOR.registration
    res = register_in_box(scan_sub[["x", "y", "z"]].to_numpy(float),
                          ref_sub[["x", "y", "z"]].to_numpy(float), centre, box, reg,
                          box_heading_deg=axes, method="thesis")
    status, reason, _ = judge_in_box(res, reg, centre, box, axes)
    why, fig = ("", {}) if not res.ok else assess_pair(
        scan_sub, ref_sub, res.peak, centre, box, reg, box_heading_deg=axes, **GUARD)
    return res, status, reason, why, fig


def failure_row(case, truth, res, status, reason, why, fig, peer=None) -> dict:
    c = np.asarray(res.centre, float)
    reg = INDOOR.registration
    _, last = assess_history(res.levels, res.peak, res.d_bar_m,
                             separation_m=reg.rival_exclusion_m,
                             max_cell_m=reg.history_max_cell_m) if res.ok else ("", None)
    return {
        "wrong": bool(np.hypot(c[0] - truth[0], c[1] - truth[1]) > 0.1),
        "case": case,
        "error_dx_dy_m": f"{c[0] - truth[0]:+.2f}, {c[1] - truth[1]:+.2f}",
        "error_heading_deg": float(abs((c[3] - truth[3] + 180) % 360 - 180)),
        "thesis_rules": "accepted (the thesis uses every result)",
        "forestmap_judge": status + (f" ({reason.split(':')[0]})" if reason else ""),
        "structure_checks": (why.split(":")[0] if why else "accepted")
        + (f" (support {fig.get('support_m', np.nan):.1f} m, rival "
           f"{fig.get('rival_ratio', 0.0):.2f})" if fig else ""),
        "peak_mass_share": float(res.peak_mass_share),
        "secondary_hypotheses": int(len(res.hypotheses)) + (last is not None),
        "coarse_to_fine_hypothesis": "-" if last is None else (
            f"leads at {last['cell_m']:.2f} m cells, {last['separation_m']:.1f} m away (share "
            f"{last['mass_share']:.2f})"),
        "peer_icp_err_xy_m": np.nan if peer is None else peer,
    }


def failures(fresh: bool) -> tuple[pd.DataFrame, list[str]]:
    reg = INDOOR.registration
    box = (reg.xy_m, reg.xy_m, reg.z_m, reg.heading_deg)
    rows, notes = [], []

    def scenes():
        s87 = corridor_scene(40.0, 2.4, left_glass=(20.0, 40.0), right_glass=(0.0, 20.0),
                             scan_x=[12.0, 27.0], scan_y=0.0)
        s43 = make_corridor(2, 32.0, seed=3)
        # scan 3 at the south-east corner of the ring, scan 4 north along the east side
        # and scan 5 half way between them (the loop 3-5-4 for the residual check)
        s43.scan_xy = np.array([[15.5, -15.5], [15.5, -5.5], [15.5, -10.5]])
        s43.scan_heading_deg = np.array([5.0, 95.0, 92.0])
        out = {}
        for name, s in (("87", s87), ("43", s43)):
            res = scan_site(s, resolution="full", seed=1)
            out[name] = ([extract_scan_features(r.image, INDOOR, circle_options=CIRCLES)
                          for r in res], [r.pose for r in res],
                         [levelled_cloud(r.image) for r in res])
        return out

    data = _cached("failure_scenes", fresh, scenes)
    # pair 87: no pillars, only the corridor walls; staggered glazing
    feats, poses, clouds = data["87"]
    truth = relative_truth(poses[1], poses[0])
    for label, off in (("true a priori", (0.0, 0.0)), ("corrupted a priori (-2 m, -2 m)",
                                                        (-2.0, -2.0))):
        c = (truth[0] + off[0], truth[1] + off[1], 0.0, 0.0)
        res, st, why0, why, fig = _register(feats[1]["submaps"], feats[0]["submaps"], c, box)
        peer = open3d_icp(clouds[1], clouds[0], c)
        rows.append(failure_row(f"87 (simulated): parallel walls only, {label}", truth, res, st,
                                why0, why, fig, float(np.hypot(*(peer[:2] - truth[:2])))))
    # the opposite-wall match proper: each sub-map holds one wall of the corridor
    from forestmap_assets.core.registration.submaps import build_submap

    def one_line(y, x0, x1):
        t = pd.DataFrame({"line_id": [0], "x0": [x0], "y0": [y], "z0": [1.0], "x1": [x1],
                          "y1": [y], "z1": [1.0]})
        return build_submap(None, t, 0.05)

    a, b = one_line(1.2, -6.0, 6.0), one_line(-1.2, -3.0, 1.0)
    res, st, why0, why, fig = _register(b, a, (8.0, 0.0, 0.0, 0.0), box)
    rows.append(failure_row("87 (sub-maps with one wall each): left wall -> right wall",
                            np.array([8.0, 0.0, 0.0, 0.0]), res, st, why0, why, fig))
    across = search_box((reg.xy_m, reg.z_m, reg.heading_deg), {"along_deg": 0.0, "across_m": 0.5})
    res, st, why0, why, fig = _register(b, a, (8.0, 0.0, 0.0, 0.0), across[:4], across[4])
    rows.append(failure_row("  same, per-pair search {along_deg: 0, across_m: 0.5}",
                            np.array([8.0, 0.0, 0.0, 0.0]), res, st, why0, why, fig))
    # pair 43: pillars 7 m apart, a 90 deg turn, prior 3 m off
    feats, poses, clouds = data["43"]
    truth = relative_truth(poses[1], poses[0])
    along = np.radians(90.0 - 5.0)  # the east side (world +y) in scan 3's frame (heading 5 deg)
    u = np.array([np.cos(along), np.sin(along)])
    for label, k in (("true a priori", 0.0), ("a priori 3 m short", -3.0),
                     ("a priori 3 m long", 3.0)):
        c = (truth[0] + k * u[0], truth[1] + k * u[1], 0.0, truth[3] + 5.0)
        res, st, why0, why, fig = _register(feats[1]["submaps"], feats[0]["submaps"], c, box)
        peer = open3d_icp(clouds[1], clouds[0], c)
        rows.append(failure_row(f"43 (simulated): pillars 7 m apart, {label}", truth, res, st,
                                why0, why, fig, float(np.hypot(*(peer[:2] - truth[:2])))))
        if k == -3.0:
            wrong = res
        if k == 3.0:
            right = res
    box43 = search_box((reg.xy_m, reg.z_m, reg.heading_deg),
                       {"along_deg": 85.0, "along_m": 2.5, "across_m": 0.5})
    c = (truth[0] - 1.0 * u[0], truth[1] - 1.0 * u[1], 0.0, truth[3] + 5.0)
    res, st, why0, why, fig = _register(feats[1]["submaps"], feats[0]["submaps"], c, box43[:4],
                                        box43[4])
    rows.append(failure_row("  a priori 1 m short, search {along_deg: 85, along_m: 2.5, "
                            "across_m: 0.5}", truth, res, st, why0, why, fig))
    # the residual check: scan 5 half way closes the loop 3-5-4
    t53 = relative_truth(poses[2], poses[0])
    t45 = relative_truth(poses[1], poses[2])
    obs, errs, states = [], [], []
    for (i, j, t) in ((2, 0, t53), (1, 2, t45)):
        r, st, _, why, _ = _register(feats[i]["submaps"], feats[j]["submaps"],
                                     (t[0] + 0.5, t[1] - 0.5, 0.0, t[3] + 3.0), box)
        obs.append((f"{i + 3}", f"{j + 3}", *r.centre, *observation_sigmas(r)))
        errs.append(float(np.hypot(*(np.asarray(r.centre[:2]) - t[:2]))))
        states.append(f"{i + 3}{j + 3}: error {errs[-1]:.2f} m, {st}"
                      + (f", checks: {why.split(':')[0]}" if why else ", checks: accepted"))
    obs = pd.DataFrame(obs, columns=list(OBSERVATION_COLUMNS))
    hyp = pd.DataFrame([("4", "3", *wrong.centre, *observation_sigmas(wrong))],
                       columns=list(OBSERVATION_COLUMNS))
    hyp_right = pd.DataFrame([("4", "3", *right.centre, *observation_sigmas(right))],
                             columns=list(OBSERVATION_COLUMNS))
    v = check_link_hypothesis(obs, hyp, "3")
    notes.append(f"Residual check (Th. 7.1) on the loop 3-5-4 (scan 5 half way; "
                 f"{'; '.join(states)}): adding the 7 m-shifted 43 gives **{v.verdict}**: "
                 f"{v.reason}. The correct 43 (a priori 3 m long) added instead: "
                 f"**{check_link_hypothesis(obs, hyp_right, '3').verdict}**.")
    sel = select_links(pd.concat([obs, hyp], ignore_index=True).assign(
        confidence=[1.0, 1.0, 2.0]), "3", scans=["3", "4", "5"])
    lk = sel.links[["scan", "reference", "status", "role"]]
    notes.append("Autonomous link selection with the wrong 43 the most confident: "
                 + "; ".join(f"{r.scan}{r.reference} {r.status} ({r.role or '-'})"
                             for r in lk.itertuples())
                 + " - the inconsistency is reported (a link rejected), but with a three-link "
                 "loop the residual test cannot tell which link is wrong; the structure checks "
                 "reject 43 before it reaches the map.")
    return pd.DataFrame(rows), notes


# ---- results ---------------------------------------------------------------------------------
def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--fresh", action="store_true")
    ap.add_argument("--only", default="pillar,lines,failures,corridor")
    ap.add_argument("--method", default=METHOD, choices=["thesis", "fast"],
                    help="registration evaluator of the campaigns (core/registration.py); a pair "
                    "whose 'fast' search crashes is redone with 'thesis'")
    args = ap.parse_args()
    globals()["METHOD"] = args.method
    only = set(args.only.split(","))
    t_start = time.perf_counter()
    parts = [f"## Structured sites (`benchmarks/bench_structured.py`)\n\n`python "
             f"benchmarks/bench_structured.py` on {machine()}, {time.strftime('%Y-%m-%d')}. "
             "Simulator at the thesis's full resolution (3000 x 720) unless said otherwise; "
             "circle symmetry statistic `noise_corrected` (see the pillar study); registration "
             f"evaluator `method='{METHOD}'` for the campaigns (a pair whose child process "
             "crashed is redone with 'thesis', see the `evaluator` column in the cache) and "
             "'thesis' for the failure modes. Peer: Open3D "
             "point-to-plane ICP from the a priori pose on the levelled raw points."]

    if "pillar" in only:
        tab, prof = _cached("pillar", args.fresh, pillar_study)
        pillar_plot(tab, prof)
        g = tab.groupby(["beam", "distance_m"]).agg(
            radius_m=("radius_m", "mean"), sd_m=("radius_m", "std"),
            cylinders=("cylinders", "mean"), valid_circles=("valid", "mean"),
            cylinders_thesis_mean_test=("cylinders_mean_stat", "max")).reset_index()
        wide = g.pivot(index="distance_m", columns="beam", values="radius_m").reset_index()
        wide.columns = ["distance_m", "radius, centre-ray beam (m)", "radius, footprint beam (m)"]
        wide["bias, footprint (mm)"] = 1000 * (wide["radius, footprint beam (m)"] - PILLAR_RADIUS_M)
        fp = tab[tab["beam"] == "footprint"]

        def band(lo, hi):
            return fp[fp["distance_m"].between(lo, hi)]["radius_m"].mean()

        near, mid, far = band(0, 3.5), band(5, 9), band(13, 19)
        cr = tab[tab["beam"] == "centre ray"]
        slope = np.polyfit(cr["distance_m"], cr["radius_m"], 1)[0]
        n_mean = int(g["cylinders_thesis_mean_test"].sum())
        p14 = prof[prof["distance_m"] > 10]
        ends = p14[(p14["height_m"] < 0.3) | (p14["height_m"] > 2.0)]["radius_m"].median()
        body = p14[p14["height_m"].between(0.3, 2.0)]["radius_m"].median()
        p3 = prof[prof["distance_m"] < 10]["radius_m"].median()
        text = (
            "### Pillar radius study (spec 4.1; thesis Figs 4.17-4.21)\n\n"
            "One 0.192 m pillar from floor to a 2.3 m ceiling, scanner at 1.3 m, 17 distances "
            "1.2-18.4 m, 3 repeats each (noise, pillar 0-4 cm sideways, pixel grid shifted by "
            "thirds of a pixel), through the simulator and segments -> circles -> cylinders with "
            "the indoor preset. 'footprint': the Riegl's first-return beam (0.042 m + 3 mrad); "
            "'centre ray': one ray per pixel (no footprint, the control of spec 13.12). Radius = "
            "length-weighted mean of the cylinders on the pillar, mean of the repeats.\n\n"
            + md(wide, ".4f") + "\n\n"
            f"Footprint beam: {near:.4f} m at 1.2-3.4 m ({1000 * (near - PILLAR_RADIUS_M):+.0f} "
            f"mm), {mid:.4f} m at 5.5-8.7 m ({1000 * (mid - PILLAR_RADIUS_M):+.0f} mm), "
            f"{far:.4f} m at 13-18.4 m ({1000 * (far - PILLAR_RADIUS_M):+.0f} mm). Thesis: too "
            "small close up (below 0.192 at 3.7 m), accurate far away (0.193 at 14.5 m). "
            "**Reproduced: too small close up; accurate at mid range; beyond ~10 m our radius "
            "is a few mm too large and noisier (the thesis calls its 0.193 at 14.5 m 'by "
            "chance').** Along the pillar (right plot) the circles at 14.1 m are too large at "
            f"the top and the floor (median {ends:.3f} m above 2.0 m / below 0.3 m vs "
            f"{body:.3f} m between), the thesis's 'extra echoes' (Fig. 4.20); at 3.3 m they "
            f"stay below the truth all along (median {p3:.3f} m, Fig. 4.21). The centre-ray "
            f"control has no distance trend (slope {1000 * slope:+.2f} mm/m, spec 13.12) but a "
            f"constant {1000 * (cr['radius_m'].mean() - PILLAR_RADIUS_M):+.0f} mm bias: the "
            "thesis's linear circle fit (Eq. 4.10) under 2.5 cm range noise on a half-visible "
            "contour; the footprint widens the pillar by about as much, more with distance. "
            "With the thesis's symmetry test as written (|mean signed residual| <= 0.7 mm) the "
            f"pipeline keeps {n_mean} cylinders on the pillar over all 17 distances: the linear "
            "fit's noise bias sigma^2/(2r) = 1.6 mm alone exceeds the threshold, so these runs "
            "(and the corridor below) use `symmetry_statistic='noise_corrected'` "
            "(core/circles.py). Plot: `benchmarks/structured_pillar.png`.")
        parts.append(text)
        print(text, flush=True)

    corridor = lot = None
    if "lines" in only or "corridor" in only:
        corridor = corridor_campaign(args.fresh)
        cfeat = features_of(corridor, args.fresh)
        lot = lot_campaign(args.fresh)
        lfeat = features_of(lot, args.fresh)
    if "lines" in only:
        lc, ll = line_table(corridor, cfeat), line_table(lot, lfeat)
        summ = pd.DataFrame([
            {"site": name, "scans": len(t), "lines/scan": t["lines"].mean(),
             "line length/scan (m)": t["length_m"].mean(), "recall <= 40 m": t["recall_40m"].mean(),
             "recall <= 10 m": t["recall_10m"].mean(), "precision": t["precision"].mean(),
             "xy error (m)": t["xy_err_m"].median(), "z error (m)": t["z_err_m"].median(),
             "visible pillars/poles <= 12 m found": f"{t['found'].sum()}/{t['pillars_12m'].sum()}",
             "their radius (m)": t["radius_m"].mean()}
            for name, t in (("corridor (indoor preset)", lc), ("parking lot (outdoor preset)", ll))])
        text = ("### Wall/ceiling lines (spec 5, Table 4.3)\n\n"
                "`line_segments` of every scan against the truth corner lines "
                "(`truth/wall_lines.csv`): recall = share of the corner visible from the scanner "
                "(ray cast, every 0.1 m, `truth/visible_lines.csv`) within 0.2 m (xy) / 0.25 m "
                "(z) of a detected line of the same direction (10 deg); precision = share of "
                "detected line length near a truth corner; errors are medians of the detected "
                "lines' distance to their corner. Corridor: 20-scan ring (30 m); parking lot: "
                "6 scans, 60 m lot, 6 m building.\n\n" + md(summ, ".3f") + "\n\n"
                "Lines are found near the scanner (recall within 10 m is the figure that "
                "matters for registration) and lie within 1-3 cm of the corner (a 0.1 m / 0.2 m "
                "cell). The parking lot's lower precision is from car roofs and the building's "
                "window reveals, which are real horizontal edges but not wall tops.")
        parts.append(text)
        print(text, flush=True)

    if "failures" in only:
        tab, notes = failures(args.fresh)
        wrong = tab.pop("wrong")
        sh = tab["peak_mass_share"]
        ctf = tab["coarse_to_fine_hypothesis"]
        text = ("### The thesis's indoor failure modes (spec 7.3) and forestmap's guards\n\n"
                "Indoor search of the thesis (+-5 m, +-0.625 m, +-30 deg, 2 cm cells). 'thesis "
                "rules': the thesis used the best cell of every pair; 'forestmap judge': "
                "`core/pair_registrations.judge` (overlap, box edge, secondary hypotheses within "
                "10 log units); 'structure checks': `core/pair_checks.assess_pair` (support of "
                "the weakest horizontal direction >= 1 m of matched feature; no credible rival "
                "alignment >= 60 % as good). Simulated: full resolution.\n\n"
                + md(tab, ".2f") + "\n\n" + "\n\n".join(notes) + "\n\n"
                "The branch and bound's surviving secondary clouds and its peak-mass share "
                "do **not** flag these pairs: it prunes every alignment scoring "
                "below the best, so a secondary cloud survives to the end only for near-exact "
                f"ties, and the peak-mass share is {sh[~wrong].min():.2f}-{sh[~wrong].max():.2f} "
                f"for the correct results and {sh[wrong].min():.2f}-{sh[wrong].max():.2f} for the "
                "wrong ones. Tempering the likelihood as the sigmas do (T = "
                "`likelihood_temperature`) does not help either (tried, not kept): the shifted 43 "
                "scores higher than the true alignment (its larger overlap matches more points). "
                "What does flag it is the coarse-to-fine history (Th. Figs 5.8-5.9: 'the "
                "maximum-score location jumps between hypotheses at coarse levels'): "
                f"{int((ctf != '-')[wrong].sum())} of the {int(wrong.sum())} wrong results here "
                f"and {int((ctf != '-')[~wrong].sum())} of the {int((~wrong).sum())} correct ones "
                "had a level with cells of at most 0.3 m whose best cell lay more than 1 m from "
                "the final peak (column 'coarse_to_fine_hypothesis'); forestmap keeps the finest "
                "such leader as a secondary hypothesis (counted in 'secondary_hypotheses' and in "
                "the pipeline's `hypotheses`; the peak-mass share becomes at most 1 minus the "
                "leader's share at that level) and rejects the result as ambiguous "
                "(`core/pair_checks.assess_history`, `registration.history_max_cell_m` = 0.3 m "
                "in the indoor and outdoor presets). The forestmap judge "
                "(its distinct-feature count) rejects the wall-only pairs 87; the shifted 43 "
                "passes it. The structure checks (support, the credible rival, whose pose and "
                "ratio `registrations.csv` carries, and the history) flag every "
                "wrong result here, and no correct one.")
        parts.append(text)
        print(text, flush=True)

    if "corridor" in only:
        # before (thesis sampling, weight 1) and after (the preset's cylinder weight, issue 10)
        cw, lw = cylinder_weight(corridor), cylinder_weight(lot)
        cfeat1, lfeat1 = with_weight(corridor, cfeat, 1), with_weight(lot, lfeat, 1)
        cfeat, lfeat = with_weight(corridor, cfeat, cw), with_weight(lot, lfeat, lw)
        tab1 = guarded(corridor, cfeat1, registrations_of(corridor, cfeat1, args.fresh, 1))
        ltab1 = guarded(lot, lfeat1, registrations_of(lot, lfeat1, args.fresh, 1))
        slides, why = slide_diagnosis(corridor, cfeat1, tab1)
        print(md(slides, ".2f"), flush=True)
        bundle = registrations_of(corridor, cfeat, args.fresh, cw)
        tab = guarded(corridor, cfeat, bundle)
        lb = registrations_of(lot, lfeat, args.fresh, lw)
        ltab = guarded(lot, lfeat, lb)

        def good(t):
            return (t["err_xy_m"] < 0.1) & (t["err_heading_deg"] < 0.5)

        pairs = pd.DataFrame([{
            "site": name, "cylinder weight": w, "pairs": len(t),
            "correct (< 0.1 m, 0.5 deg)": int(good(t).sum()),
            "wrong accepted by judge": int((~good(t) & (t["status"] == "accepted")).sum()),
            "wrong accepted after checks": int((~good(t) & (t["status_guarded"] == "accepted"))
                                               .sum()),
            "correct rejected by checks": int((good(t) & (t["status"] == "accepted")
                                               & (t["status_guarded"] != "accepted")).sum()),
            "median s/pair": float(t["seconds"].median()),
        } for name, w, t in (("corridor", 1, tab1), ("corridor", cw, tab),
                             ("parking lot", 1, ltab1), ("parking lot", lw, ltab))])
        for w, t in ((1, tab1), (cw, tab)):
            bad = t[~good(t) & (t["status_guarded"] == "accepted")]
            why += (f" Accepted pairs outside the 'correct' threshold, weight {w}: " + (", ".join(
                f"{r.scan}-{r.reference} ({r.err_xy_m:.2f} m, {r.err_heading_deg:.2f} deg = "
                f"{r.err_heading_deg / r.sd_heading_deg:.1f} of its sd_heading)"
                for r in bad.itertuples()) or "none") + ".")
        right = tab["err_xy_m"] < 0.1
        judged = tab["status"] == "accepted"
        share = (f"Peak-mass share (spec 6.7) on the corridor: correct pairs median "
                 f"{tab.loc[right, 'peak_mass_share'].median():.3f} (range "
                 f"{tab.loc[right, 'peak_mass_share'].min():.3f}-"
                 f"{tab.loc[right, 'peak_mass_share'].max():.3f}), wrong pairs median "
                 f"{tab.loc[~right, 'peak_mass_share'].median():.3f} (range "
                 f"{tab.loc[~right, 'peak_mass_share'].min():.3f}-"
                 f"{tab.loc[~right, 'peak_mass_share'].max():.3f}); secondary hypotheses "
                 f"within 10 log units flagged {int(((~right) & tab['reason'].str.startswith('ambiguous')).sum())}"
                 f" of {int((~right).sum())} wrong pairs; the coarse-to-fine history "
                 f"flagged {int((~right & tab['history_flag'].fillna(False).astype(bool)).sum())} "
                 f"of them and {int((right & tab['history_flag'].fillna(False).astype(bool)).sum())}"
                 f" of the {int(right.sum())} correct ones. Structure-check figures: support of "
                 f"the correct pairs the judge accepts min "
                 f"{tab.loc[right & judged, 'support_m'].min():.2f} m, of the wrong ones it "
                 f"accepts max {tab.loc[~right & judged, 'support_m'].max():.2f} m; credible "
                 f"rival ratio of correct pairs max {tab.loc[right, 'rival_ratio'].max():.2f}.")
        ev = pd.concat([bundle["registrations"], lb["registrations"]])["evaluator"]
        share += (f" Pairs whose 'fast' search crashed and were redone with 'thesis': "
                  f"{int(ev.str.contains('crashed').sum())} of {len(ev)}.")
        ids = load_campaign(corridor).scan_ids
        cons = tab[[ids.index(a) - ids.index(b) == 1 for a, b in zip(tab["scan"], tab["reference"],
                                                                     strict=True)]]
        lost = cons[cons["status_guarded"] != "accepted"]
        share += (" Consecutive pairs not admitted: " + ", ".join(
            f"{r.scan}-{r.reference} ({r.err_xy_m:.1f} m off, {(r.guard or r.reason).split(':')[0]})"
            for r in lost.itertuples()) + "; the ring-closing pairs: "
            + ", ".join(f"{r.scan}-{r.reference} {r.status_guarded}"
                        + (f" ({r.err_xy_m:.1f} m off)" if np.isfinite(r.err_xy_m) else "")
                        for r in tab.itertuples()
                        if abs(ids.index(r.scan) - ids.index(r.reference)) > 2)
            + ". The admitted links leave the pieces listed below.")
        # what the pipeline does next: the admitted links refined on the raw points
        rtab = refined(corridor, tab, args.fresh, f"w{cw}")
        rmaps = maps_vs_truth(corridor, rtab)
        rmaps = rmaps[rmaps["links"] == "judge + structure checks"].assign(
            links="judge + structure checks, refined (the pipeline)")
        maps = pd.concat([maps_vs_truth(corridor, t).assign(**{"cylinder weight": w})
                          for w, t in ((1, tab1), (cw, tab))]
                         + [rmaps.assign(**{"cylinder weight": cw})], ignore_index=True)
        racc = rtab[rtab["status_guarded"] == "accepted"]
        bad_before = tab[~good(tab) & (tab["status_guarded"] == "accepted")]
        refine_note = (
            f"Refinement (`refined_registrations`, `core/refine.py`, Open3D point-to-plane ICP "
            f"with Tukey weights then robust 4-DoF steps, on the levelled raw points): "
            f"{int(racc['refined'].sum())} of the {len(racc)} admitted corridor links refined; "
            f"median xy error {1000 * tab.loc[racc.index, 'err_xy_m'].median():.1f} -> "
            f"{1000 * racc['err_xy_m'].median():.1f} mm, heading "
            f"{tab.loc[racc.index, 'err_heading_deg'].median():.3f} -> "
            f"{racc['err_heading_deg'].median():.3f} deg; the links outside the 'correct' "
            "threshold after the branch and bound: " + (", ".join(
                f"{r.scan}-{r.reference} {r.err_xy_m:.3f} m / {r.err_heading_deg:.2f} deg -> "
                f"{rtab.loc[k, 'err_xy_m']:.3f} m / {rtab.loc[k, 'err_heading_deg']:.2f} deg"
                f" ({'refined' if rtab.loc[k, 'refined'] else 'refinement not used'})"
                for k, r in bad_before.iterrows()) or "none") + f". The largest error of any "
            f"piece of the refined maps (chained or optimal): {rmaps['max_xy_err_m'].max():.2f} m / "
            f"{rmaps['max_heading_err_deg'].max():.2f} deg (same pieces).")
        maps = maps[["cylinder weight", *[c for c in maps.columns if c != "cylinder weight"]]]
        closing = {w: ", ".join(f"{r.scan}-{r.reference} {r.status_guarded}"
                                + (f" ({r.err_xy_m:.2f} m off)" if np.isfinite(r.err_xy_m) else "")
                                for r in t.itertuples()
                                if abs(ids.index(r.scan) - ids.index(r.reference)) > 2)
                   for w, t in ((1, tab1), (cw, tab))}
        lmaps = maps_vs_truth(lot, ltab)
        peer = peer_on_pairs(corridor, tab)
        text = ("### Consecutive scans registered with lines and pillars; chained vs optimal "
                "maps (spec 8.3, 10.4-10.5)\n\n"
                "Corridor: 20 cart stops ~5.8 m apart round a 30 m ring (pillars 7 m apart on "
                "the outer side, offices with doors on both), pairs between stops 1 and 2 apart "
                f"plus 3 across the start of the ring ({len(tab)} pairs), a priori errors up to 1 m / "
                "10 deg, indoor preset. Parking lot: 6 stops 10 m apart, consecutive pairs, "
                "outdoor preset (0.156 m cells). 'cylinder weight' (core/submaps.py, issue 10): "
                "1 = the thesis's sub-maps (every 0.05 m along every feature), "
                f"{cw} = cylinders sampled {cw}x as densely, the point-to-point vs point-to-line "
                "information ratio; the figures after the table are for the latter.\n\n"
                + md(pairs, ".2f") + "\n\n" + why + "\n\n" + share
                + "\n\n"
                "Corridor maps against the truth. Where the admitted links split the scans "
                "into pieces, each piece is mapped in the frame of its first scan and compared "
                "with the truth in that frame; 'pieces' lists their sizes:\n\n"
                + md(maps, ".3f") + "\n\n" + refine_note
                + f"\n\nRing-closing pairs, weight 1: {closing[1]}; "
                f"weight {cw}: {closing[cw]}."
                + "\n\nWithin the pieces the only loops are the pairs two stops apart, so "
                "the chained and the optimal maps agree closely; what matters is which "
                "links are admitted: the thesis's rules (every result, chained) put the far end "
                "of the corridor metres off; with forestmap's admitted links the largest error "
                "of any piece is " + "; ".join(
                    f"{g['max_xy_err_m'].max():.2f} m / {g['max_heading_err_deg'].max():.2f} deg "
                    f"with weight {w} (pieces {g['pieces (scans)'].iloc[0]})"
                    for w, g in maps[maps["links"] == "judge + structure checks"].groupby(
                        "cylinder weight")) + ". A piece joined by a single link (no loop) "
                "carries that link's error unchecked (the accepted pairs outside the 'correct' "
                "threshold are listed above)."
                + "\n\nParking lot (consecutive pairs only, so chain = optimal tree):\n\n"
                + md(lmaps, ".3f") + "\n\nPeer on consecutive corridor pairs (Open3D ICP from "
                "the a priori pose, raw points within 20 m):\n\n" + md(peer, ".3f"))
        parts.append(text)
        print(text, flush=True)

    parts.append(f"Total run time {time.perf_counter() - t_start:.0f} s.")
    write_section(MARK, "\n\n".join(parts))


if __name__ == "__main__":
    main()
