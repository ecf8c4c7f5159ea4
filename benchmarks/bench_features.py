"""Feature-extraction benchmark: segments -> circle models -> cylinder segments (thesis ch. 4).

Builds a full-resolution (3000 x 720, 0.108 deg) analytic forest range image (40 stems of
radius 0.05-0.3 m at 2-20 m, leaning up to 10 deg, flat ground, 2.5 cm range noise) with the
exact ray caster of ``tests/helpers/synthetic.py``, times each stage (median of ``--runs``), measures
stem detection and radius accuracy for the three circle fits, runs the pillar study of spec 4.1
(0.192 m pillar at 1.2-18.4 m, with and without a wide-beam footprint model) and, when
``forestmap_assets.sim`` is available, measures the same on simulated forests (``--seeds`` x
``--scans`` positions) at half and full resolution, for the thesis' circle test and the
(inferred) variants. Prints the tables and writes its section of ``benchmarks/results.md``
(between ``<!-- features:start -->`` and ``<!-- features:end -->``).

    /tmp/fmvenv/bin/python benchmarks/bench_features.py [--runs 3] [--quick] [--no-sim] [--seeds 1,2,3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the analytic scene generator lives with the tests

from helpers import synthetic as S  # noqa: E402
from results_md import write_section  # noqa: E402

from forestmap_assets.core.features._circle_kernels import HAVE_NUMBA
from forestmap_assets.core.features.circle_models import final_circles, fit_circle_models
from forestmap_assets.core.features.cylinders import assemble_cylinders, extract_features  # noqa: E402
from forestmap_assets.core.features.segments import segment_scan_lines  # noqa: E402
from forestmap_assets.params import Params  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results.md"
FITS = ("linear", "geometric", "ray")


def timed(fn, runs):
    out, ts = None, []
    for _ in range(runs):
        t = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t)
    return out, statistics.median(ts)


def stage_times(img, runs, engine="auto", fit="linear"):
    """Median seconds of each stage and of the whole chain."""
    p = Params()
    seg, t_seg = timed(lambda: segment_scan_lines(img, p.segmentation), runs)
    circ, t_circ = timed(lambda: fit_circle_models(img, seg, p.circles, p.segmentation,
                                                   fit=fit, engine=engine), runs)
    fin = final_circles(circ)
    cyl, t_cyl = timed(lambda: assemble_cylinders(fin, p.cylinders), runs)
    return {"segments_s": t_seg, "circles_s": t_circ, "cylinders_s": t_cyl,
            "total_s": t_seg + t_circ + t_cyl, "n_segments": len(seg),
            "n_iterations": int(circ["iteration"].max()) + 1,
            "n_valid_circles": int(fin["valid"].sum()), "n_cylinders": len(cyl)}


# ---- accuracy against analytic truth ------------------------------------------------------

def match_stems(cyl: pd.DataFrame, axes: list[tuple[np.ndarray, np.ndarray]], radius_at,
                tol_min=0.1):
    """Per stem: matched cylinders' length-weighted radius error; cylinders matching none."""
    if len(cyl) == 0:
        return [None] * len(axes), 0
    p0 = cyl[["x0", "y0", "z0"]].to_numpy()
    p1 = cyl[["x1", "y1", "z1"]].to_numpy()
    mid = (p0 + p1) / 2
    owner = np.full(len(cyl), -1)
    errs = []
    for k, (base, axis) in enumerate(axes):
        w = mid - base
        along = w @ axis
        perp = np.linalg.norm(w - along[:, None] * axis, axis=1)
        r_true = radius_at(k, along)
        sel = perp < np.maximum(tol_min, r_true)
        owner[sel] = k
        if not sel.any():
            errs.append(None)
            continue
        L = cyl["length_m"].to_numpy()[sel]
        e = cyl["radius_m"].to_numpy()[sel] - r_true[sel]
        errs.append((float(np.sum(L * e) / L.sum()), float(np.sum(L * e * e) / L.sum())))
    return errs, int(np.sum(owner < 0))


def summarise(errs, radii):
    found = [e for e in errs if e is not None]
    out = {"stems": len(errs), "found": len(found),
           "rmse_cm": 100 * float(np.sqrt(np.mean([e[1] for e in found]))) if found else np.nan,
           "bias_cm": 100 * float(np.mean([e[0] for e in found])) if found else np.nan}
    radii = np.asarray(radii)
    for name, lo, hi in (("thin", 0, 0.1), ("mid", 0.1, 0.2), ("thick", 0.2, 1)):
        sel = [e for e, r in zip(errs, radii, strict=True) if e is not None and lo <= r < hi]
        out[f"bias_{name}_cm"] = 100 * float(np.mean([e[0] for e in sel])) if sel else np.nan
    return out


def analytic_forest(step_deg=S.FULL_STEP_DEG, seed=1, beam=None):
    scene = S.forest_scene(40, seed=seed)
    az, el = S.full_grid(step_deg)
    img, _, label = S.render(scene, az, el, noise_m=0.025, seed=seed, labels=True, beam=beam)
    return img, scene, label


def analytic_accuracy(img, scene, label, beam="ideal", fits=FITS, max_dist=15.0):
    """Accuracy on stems within ``max_dist`` with >= 1 m visible; strays: cylinders on no stem."""
    stems = scene.cylinders
    vis = np.array([S.visible_length_m(img, label, i) for i in range(len(stems))])
    dist = np.array([np.hypot(*s.base[:2]) for s in stems])
    target = np.flatnonzero((vis >= 1.0) & (dist <= max_dist))
    axes = [(np.asarray(s.base), np.asarray(s.axis)) for s in stems]
    radii = np.array([s.radius for s in stems])
    rows = []
    for fit in fits:
        f = extract_features(img, fit=fit)
        errs, stray = match_stems(f["cylinder_segments"], axes,
                                  lambda k, along: np.full(along.shape, radii[k]))
        rows.append({"beam": beam, "fit": fit,
                     **summarise([errs[i] for i in target], radii[target]),
                     "stray_cylinders": stray, "n_cylinders": len(f["cylinder_segments"])})
    return pd.DataFrame(rows)


# ---- pillar study (spec 4.1) --------------------------------------------------------------

def pillar_radius(d, beam, fit, noise=0.025, seed=0):
    floor = -1.3  # sensor 1.3 m above the floor, pillar floor to ceiling (2.3 m)
    scene = S.Scene([S.Cylinder((d, 0.0, floor), (0, 0, 1), 0.192, 2.3)], ground_z=floor,
                    ground_radius_m=d + 5)
    half = np.degrees(np.arctan2(0.6, d)) + 1.0
    az, el = S.grid((-half, half), (np.degrees(np.arctan2(floor, d)) - 0.5,
                                    np.degrees(np.arctan2(1.0, d)) + 0.5))
    img, _ = S.render(scene, az, el, noise_m=noise, seed=seed, beam=beam)
    cyl = extract_features(img, fit=fit)["cylinder_segments"]
    if len(cyl) == 0:
        return np.nan
    w = cyl["length_m"].to_numpy()
    return float(np.sum(w * cyl["radius_m"].to_numpy()) / w.sum())


def pillar_study(distances, quick=False):
    cases = [("ideal beam", None, "linear"), ("ideal beam", None, "ray"),
             ("footprint mean", "mean", "linear"), ("footprint mean", "mean", "ray"),
             ("footprint min", "min", "linear")]
    if quick:
        cases = cases[:3]
    rows = []
    for label, beam, fit in cases:
        rows.append({"model": f"{label}, {fit}",
                     **{f"{d:.1f}": pillar_radius(d, beam, fit, seed=int(d * 10))
                        for d in distances}})
    return pd.DataFrame(rows)


# ---- virtual forest simulator ------------------------------------------------------------

VARIANTS = {  # name: (symmetry statistic, axis/normal check limit (None: curvature_deg))
    "thesis (mean, no axis check)": ("mean", np.inf),
    "mean + axis check": ("mean", None),
    "noise_corrected + axis check": ("noise_corrected", None),
}


def _stem_px_per_row(kind, tree, tree_id):
    """Median stem-labelled pixels per image row of a tree (how wide it is seen)."""
    from forestmap_assets.sim.scene_mesh import KIND_STEM

    m = (kind == KIND_STEM) & (tree == tree_id)
    per_row = m.sum(1)
    return float(np.median(per_row[per_row > 0])) if m.any() else 0.0


def simulator_accuracy(resolution, seeds=(1, 2, 3), scans=2, trees=40):
    """Stem detection, false positives and radius error over ``seeds`` x ``scans`` simulated
    scans (``sim.evaluate.scan_feature_accuracy``), for each of :data:`VARIANTS`; also the
    missed stems with their median visible width in pixels."""
    try:
        from forestmap_assets.io.readers import read_scan
        from forestmap_assets.sim import simulate_campaign
        from forestmap_assets.sim.evaluate import scan_feature_accuracy
    except ImportError:
        return None, None
    rows, misses = [], []
    p = Params()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            t = time.perf_counter()
            camp = simulate_campaign(Path(tmp) / f"s{seed}", scans=scans, trees=trees, seed=seed,
                                     resolution=resolution)
            t_sim = (time.perf_counter() - t) / scans
            for path in sorted((camp / "scans").glob("*.npz")):
                img = read_scan(path)
                seg = segment_scan_lines(img, p.segmentation)
                with np.load(camp / "truth" / "labels" / f"{path.stem}.npz") as z:
                    kind, tree = z["kind"], z["tree_id"]
                for name, (stat, limit) in VARIANTS.items():
                    t = time.perf_counter()
                    circ = fit_circle_models(img, seg, p.circles, p.segmentation,
                                             symmetry_statistic=stat)
                    cyl = assemble_cylinders(final_circles(circ), p.cylinders,
                                             axis_normal_deg=limit)
                    t_feat = time.perf_counter() - t
                    a = scan_feature_accuracy(camp, path.stem, cyl)
                    ps = a.pop("per_stem")
                    e = ps.loc[ps["target"], "radius_error_m"].dropna().to_numpy()
                    rows.append({"variant": name, "seed": seed, "scan": path.stem,
                                 "stems": a["stems"], "found": a["found"],
                                 "n_cylinders": a["n_cylinders"],
                                 "false_positives": a["false_positives"],
                                 "se_sum": float(np.sum(e**2)), "e_sum": float(np.sum(e)),
                                 "n_err": e.size, "circles_cylinders_s": t_feat,
                                 "simulate_s": t_sim})
                    miss = ps[ps["target"] & (ps["n_cylinders"] == 0)]
                    for _, r in miss.iterrows():
                        misses.append({"variant": name, "seed": seed, "scan": path.stem,
                                       "tree_id": int(r["tree_id"]),
                                       "distance_m": r["distance_m"], "visible_m": r["visible_m"],
                                       "r_bh_m": r["r_bh_m"],
                                       "px_per_row": _stem_px_per_row(kind, tree, r["tree_id"])})
    per_scan = pd.DataFrame(rows)
    g = per_scan.groupby("variant", sort=False)
    summary = pd.DataFrame({
        "resolution": resolution,
        "image": f"{img.shape[1]}x{img.shape[0]}",
        "scans": g.size(),
        "stems": g["stems"].sum(), "found": g["found"].sum(),
        "detection_pct": 100 * g["found"].sum() / g["stems"].sum(),
        "min_scan_detection_pct": 100 * (per_scan["found"] / per_scan["stems"])
        .groupby(per_scan["variant"], sort=False).min(),
        "n_cylinders": g["n_cylinders"].sum(), "false_positives": g["false_positives"].sum(),
        "fp_pct": 100 * g["false_positives"].sum() / g["n_cylinders"].sum(),
        "rmse_cm": 100 * np.sqrt(g["se_sum"].sum() / g["n_err"].sum()),
        "bias_cm": 100 * g["e_sum"].sum() / g["n_err"].sum(),
        "median_s": g["circles_cylinders_s"].median(),
    }).reset_index()
    return summary, pd.DataFrame(misses)


# ---- report -------------------------------------------------------------------------------

def fmt_table(df: pd.DataFrame, floatfmt="{:.3f}") -> str:
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in df.iterrows():
        cells = []
        for c in cols:
            v = r[c]
            cells.append(floatfmt.format(v) if isinstance(v, float | np.floating) else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="timing runs per stage (median)")
    ap.add_argument("--quick", action="store_true", help="fewer pillar distances and models")
    ap.add_argument("--no-sim", action="store_true", help="skip the virtual-forest simulator")
    ap.add_argument("--no-write", action="store_true", help="do not update results.md")
    ap.add_argument("--seeds", default="1,2,3", help="simulator seeds (comma separated)")
    ap.add_argument("--scans", type=int, default=2, help="scan positions per simulated forest")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    img, scene, label = analytic_forest()
    t_render = time.perf_counter() - t0
    print(f"analytic forest {img.shape[1]}x{img.shape[0]}: rendered in {t_render:.1f} s")
    extract_features(img)  # warm-up (numba compile / cache load, page faults)

    timing_rows = []
    engines = ["numba", "numpy"] if HAVE_NUMBA else ["numpy"]
    for engine in engines:
        for fit in FITS:
            if engine == "numpy" and fit != "linear":
                continue
            runs = args.runs if engine == "numba" else 1
            t = stage_times(img, runs, engine=engine, fit=fit)
            timing_rows.append({"engine": engine, "fit": fit, "runs": runs, **t})
            print(timing_rows[-1])
    timing = pd.DataFrame(timing_rows)

    accs = [analytic_accuracy(img, scene, label)]
    for beam in ([] if args.quick else ["mean", "min"]):
        b_img, b_scene, b_label = analytic_forest(beam=beam)
        accs.append(analytic_accuracy(b_img, b_scene, b_label, beam=beam))
    acc = pd.concat(accs, ignore_index=True)
    print(acc.to_string())

    distances = [1.2, 2.0, 3.7, 7.5, 14.5, 18.4] if args.quick else \
        [float(d) for d in np.round(np.linspace(1.2, 18.4, 9), 1)] + [3.7, 14.5]
    distances = sorted(set(distances))
    pillar = pillar_study(distances, quick=args.quick)
    print(pillar.to_string())

    sims, missed = [], []
    if not args.no_sim:
        seeds = tuple(int(v) for v in args.seeds.split(","))
        for res in ("half", "full"):
            s, m = simulator_accuracy(res, seeds=seeds, scans=args.scans)
            if s is not None:
                sims.append(s)
                missed.append(m.assign(resolution=res))
                print(s.to_string())
                print(m.to_string())
    sim = pd.concat(sims, ignore_index=True) if sims else None
    missed = pd.concat(missed, ignore_index=True) if missed else None

    best = timing[(timing["engine"] == engines[0]) & (timing["fit"] == "linear")].iloc[0]
    text = [
        "## Feature extraction (segments -> circle models -> cylinder segments)",
        "",
        f"`benchmarks/bench_features.py`, {time.strftime('%Y-%m-%d %H:%M')}, "
        f"{os.cpu_count()} cores (shared), median of {args.runs} runs. Analytic forest: "
        f"{img.shape[1]}x{img.shape[0]} px at 0.108 deg, 40 stems r 0.05-0.3 m at 2-20 m, "
        "lean <= 10 deg, flat ground, 2.5 cm range noise (exact ray casting, "
        "`tests/helpers/synthetic.py`).",
        "",
        f"**Full-resolution chain, default settings (linear fit, {engines[0]} engine): "
        f"{best['total_s']:.2f} s** (target <= 3 s; thesis ~30 min).",
        "",
        fmt_table(timing[["engine", "fit", "runs", "segments_s", "circles_s", "cylinders_s",
                          "total_s", "n_segments", "n_iterations", "n_valid_circles",
                          "n_cylinders"]]),
        "",
        "### Stem detection and radius accuracy (analytic forest, stems within 15 m with >= 1 m "
        "visible trunk; radius error length-weighted per stem; `stray_cylinders` lie on no "
        "stem at all)",
        "",
        fmt_table(acc),
        "",
        "`linear` is the thesis fit (Eq. 4.10, default); `geometric` refines the final circles "
        "by orthogonal distances; `ray` (inferred) by maximum likelihood for range noise along "
        "ideal beams. `beam`: `ideal` one exact ray per pixel; `mean` / `min` wide first-return "
        "footprint models (inferred, 13 sub-rays over 0.042 m + 3 mrad; mean range of the first "
        "echo / shortest hit). With ideal beams the linear fit is biased low by 2-3 cm at 2.5 cm "
        "noise and `ray` removes most of it; with a wide beam the widening of objects by mixed "
        "pixels offsets the linear fit's bias while `ray` then overestimates by several cm.",
        "",
        "### Pillar study (spec 4.1): cylinder radius (m) vs distance (m), truth 0.192 m",
        "",
        "Ideal beam: one exact ray per pixel. Footprint models (inferred, the thesis gives "
        "none): 13 sub-rays over a 0.042 m + 3 mrad beam; `min` keeps the shortest hit, `mean` "
        "averages the first echo. 2.5 cm noise, forest parameters.",
        "",
        fmt_table(pillar),
        "",
        "Thesis (Fig. 4.17 / JP Fig. 8): accurate far away, too small close up. With an ideal "
        "beam there is no distance trend, only the linear fit's constant noise bias (spec 13.12). "
        "The footprint-averaged first echo with the linear fit shows the thesis' shape, too small "
        "at 1-4 m and close to 0.192 m at 5-16 m, without any tuning; the shortest-hit "
        "footprint widens the pillar more with distance. The beam model is inferred, so this is "
        "a plausibility check, not a reproduction.",
        "",
        "Known limitation: a stem partly hidden behind a nearer one gives partial arcs at the "
        "occlusion edge; their circles are small and bias that stem's cylinder (stem 25 of the "
        "analytic forest: -6 cm with the linear fit, which is most of the ideal-beam RMSE).",
        "",
    ]
    if sim is not None:
        best_sim = sim[(sim["resolution"] == "full")
                       & (sim["variant"] == "noise_corrected + axis check")]
        miss = missed[missed["variant"] == "noise_corrected + axis check"]
        text += [
            f"### Virtual forest simulator (`forestmap_assets.sim`, seeds {args.seeds} x "
            f"{args.scans} scan positions, 40 trees, 40 m plot)",
            "",
            "Riegl-like: 2.5 cm noise, first-return 0.042 m + 3 mrad beam, tapering slightly "
            "non-circular meshed stems, branches, foliage, understorey. Scored with "
            "`sim.evaluate.scan_feature_accuracy`: target stems within 15 m of the scanner with "
            ">= 1 m of visible trunk (per-pixel stem labels of that scan, the simulator's "
            "visibility rule); a stem is *found* when the middle of at least one cylinder's axis "
            "lies within max(r, 10 cm) of the true axis (perpendicular distance, between base "
            "and top); *false positives* are cylinders on no stem at all (branches, saplings, "
            "foliage; share of all cylinders); radius error per found stem is the "
            "length-weighted mean of cylinder radius minus the true mean radius at the "
            "cylinder's middle height, RMSE/bias over stems. `min_scan_detection_pct`: worst "
            "single scan. `median_s`: circles + cylinders per scan.",
            "",
            fmt_table(sim),
            "",
            "Variants: `thesis` = spec 3.5 mean signed residual |e| <= 4.1 mm, no extra check; "
            "`axis check` (inferred) drops cylinders whose centre line deviates from their "
            "circles' mean normal by more than the curvature threshold (12 deg): branches and "
            "foliage chains (20-45 deg) go, stems (95 % below 3 deg) stay; `noise_corrected` "
            "(inferred, as the indoor preset) removes the -sigma^2/(2r) noise bias of the "
            "linear fit's mean residual before the 4.1 mm test, which otherwise rejects thin "
            "trunks beyond ~10 m at full resolution (-4.2 mm on r = 7.5 cm), the thesis' "
            "\"a strict threshold misses distant trunks\".",
            "",
        ]
        if len(best_sim):
            b = best_sim.iloc[0]
            text += [
                f"**Full resolution, proposed default (noise_corrected + axis check): "
                f"{b['found']}/{b['stems']} stems found ({b['detection_pct']:.1f} %, target "
                f">= 95 %), {b['false_positives']}/{b['n_cylinders']} false positives "
                f"({b['fp_pct']:.1f} %, target <= 5 %), radius RMSE {b['rmse_cm']:.2f} cm "
                f"(target <= 1.0 cm), bias {b['bias_cm']:+.2f} cm.**",
                "",
                "Missed stems with the proposed default (`px_per_row`: median stem-labelled "
                "pixels per image row, i.e. how wide the unoccluded part is seen; a segment "
                "needs >= 4 points):",
                "",
                fmt_table(miss.drop(columns="variant")) if len(miss) else "(none)",
                "",
            ]
    write = not args.no_write
    if write:
        write_section("features", "\n".join(text))
        print(f"updated {RESULTS}")
    print(f"benchmark done in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
