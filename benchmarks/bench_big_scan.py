"""Big scans (issue 18): a 30 M-point LAZ scan and a 2 M-point unorganised scan through the
per-scan stages, and the detection accuracy of projected clouds against organised scans.

Scans (built once, cached under ``--cache``, default /tmp/forestmap_bench_big_scan):

* **big**: the simulated forest (40 trees, 40 m plot) scanned at ``--resolution fine`` (a modern
  scanner's 0.028 deg over 360 x 100 deg, ``sim/scanner.py`` ``FINE_GRID``) by
  ``VirtualScanner.scan_points``: every beam turned off its grid direction by N(0, 0.3 step),
  the wide first-return beam and 2.5 cm range noise of the LMS-Z210 model; written as LAZ (0.1 mm
  coordinates, 16-bit intensity), about 30 M points;
* **2M**: the same forest from another position at 0.1 deg over 360 x 100 deg (a Riegl VZ-400 at
  0.1 deg), N(0, 0.3 step) angle jitter and 10 % of the returns dropped: about 2 M points, LAZ;
* **2M realistic**: the same scan of the forest with realistic stems (``stems="realistic"``:
  out-of-round, fluted, rough, swept and forked stems, dead branches, dense understorey), whose
  many small segments cost the circle models more than the points do (issue 16).

Each scan is a one-scan campaign (``campaign.yaml`` without ``sensor``: the step is estimated,
campaign defaults otherwise) and each measurement runs in a fresh process: LAZ decompression
alone (laspy chunk iterator), then the pipeline functions of the per-scan assets:
``assets.ingest.read_campaign_scan`` (read + range image), the range image table round trip the
asset store makes (``to_table`` / ``from_table``), ``segment_scan_lines``,
``fit_circle_models`` and ``assemble_cylinders``; wall time per stage, peak memory (ru_maxrss of
that process), image size and fill ratio (share of the pixels inside the scanned region with a
return; ``io/projection.fill_ratio``).

Accuracy (``--seeds``): simulated campaigns (2 scans, 40 trees, full LMS-Z210 resolution) read
as the organised ``.npz``, as LAS of the same image, as the jittered cloud of the same scan
positions (N(0, 0.3 step), 30 % of the returns dropped) and as the organised points thinned to
50 %; segments -> circle models -> cylinders scored with ``sim.evaluate.scan_feature_accuracy``.

``--before DIR`` also runs the measurements with another copy of the package (e.g. the code
before this change, exported with ``git archive``). Writes its section of
``benchmarks/results.md`` (unless ``--no-write``).

    .venv/bin/python benchmarks/bench_big_scan.py [--cache DIR] [--seeds 1,2,3] [--no-accuracy]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests" / "io"))  # the unorganised-scan builders live with the tests

NAME = "big_scan"
SCANS = ("2M", "2M realistic", "big")
CACHE = Path("/tmp/forestmap_bench_big_scan")


# ---- the scans -----------------------------------------------------------------------------

def _campaign(folder: Path, laz: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "campaign.yaml").write_text(
        f"name: {folder.name}\nenvironment: forest\nscans:\n  - {{id: A, path: {laz.name}}}\n")
    return folder


def build_scans(cache: Path, rebuild: bool = False, keys: tuple[str, ...] = SCANS) -> dict[str, Path]:
    """The scans ``keys`` as one-scan campaigns (built once)."""
    from unorganised_scans import write_las

    from forestmap_assets.sim.forest import make_forest
    from forestmap_assets.sim.scanner import ScanPose, VirtualScanner

    out = {"big": cache / "big", "2M": cache / "2m", "2M realistic": cache / "2m-realistic"}
    vz400 = dict(resolution="full", hfov_deg=360.0, vfov_deg=100.0, n_cols=3600, n_rows=1000,
                 jitter=0.3, dropout=0.1, scan=1)
    specs = {"big": dict(resolution="fine", jitter=0.3, dropout=0.0, scan=0), "2M": vz400,
             "2M realistic": vz400}
    worlds: dict[str, object] = {}
    out = {key: out[key] for key in keys}
    for key, folder in out.items():
        laz = folder / "A.laz"
        if laz.exists() and not rebuild:
            continue
        stems = "realistic" if "realistic" in key else "circular"
        if stems not in worlds:
            worlds[stems] = make_forest(40, 40.0, n_scans=2, seed=np.random.default_rng(11),
                                        stems=stems)
        world = worlds[stems]
        spec = dict(specs[key])
        jitter, dropout, i = spec.pop("jitter"), spec.pop("dropout"), spec.pop("scan")
        x, y = world.scan_xy[i]
        pose = ScanPose(float(x), float(y), float(world.ground.height(world.scan_xy[i:i + 1, 0],
                                                                        world.scan_xy[i:i + 1, 1])[0]) + 1.5,
                        heading_deg=30.0 * i)
        t = time.perf_counter()
        xyz, inten = VirtualScanner(world, **spec).scan_points(pose, seed=i, jitter_steps=jitter,
                                                               dropout=dropout)
        folder.mkdir(parents=True, exist_ok=True)
        write_las(laz, xyz, inten)
        print(f"built {key}: {len(xyz):,} points in {time.perf_counter() - t:.0f} s -> {laz}",
              flush=True)
        del xyz, inten
        _campaign(folder, laz)
    return out


# ---- one measurement, in its own process ---------------------------------------------------

def _fill(valid: np.ndarray) -> float:
    """io/projection.fill_ratio (repeated so that --before can measure older code)."""
    m = np.asarray(valid, bool)
    rows = m.copy()
    rows[1:] |= m[:-1]
    rows[:-1] |= m[1:]
    region = rows.copy()
    region[:, 1:] |= rows[:, :-1]
    region[:, :-1] |= rows[:, 1:]
    return float(m.sum() / max(region.sum(), 1))


def measure(campaign_dir: str) -> dict:
    """Per-stage seconds, peak memory, image size and fill of scan A of ``campaign_dir``."""
    import laspy

    from forestmap_assets.assets.ingest import read_campaign_scan
    from forestmap_assets.core.features.circle_models import final_circles, fit_circle_models
    from forestmap_assets.core.features.cylinders import assemble_cylinders
    from forestmap_assets.core.features.range_image import RangeImage
    from forestmap_assets.core.features.segments import feature_scan_lines, segment_scan_lines
    from forestmap_assets.io.campaign import load_campaign

    camp = load_campaign(Path(campaign_dir))
    p = camp.params
    out: dict = {}
    t = time.perf_counter()
    n = 0
    with laspy.open(str(camp.scan("A").path)) as reader:
        for chunk in reader.chunk_iterator(4_000_000):
            n += len(chunk)
    out["points"] = n
    out["decompress_s"] = time.perf_counter() - t
    out["rss_after_decompress_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t = time.perf_counter()
    image = read_campaign_scan(camp, "A")
    out["read_image_s"] = time.perf_counter() - t
    out["rows"], out["cols"] = image.shape
    out["valid"] = int(image.valid.sum())
    out["fill"] = _fill(image.valid)
    out["step_deg"] = [image.azimuth_step_deg, image.elevation_step_deg]
    t = time.perf_counter()
    image = RangeImage.from_table(image.to_table())
    out["table_s"] = time.perf_counter() - t
    image = feature_scan_lines(image, p.segmentation.min_line_step_deg)  # as the assets do
    t = time.perf_counter()
    seg = segment_scan_lines(image, p.segmentation, max_window_px=p.segmentation.max_window_px)
    out["segments_s"] = time.perf_counter() - t
    t = time.perf_counter()
    circles = fit_circle_models(image, seg, p.circles, p.segmentation)
    out["circles_s"] = time.perf_counter() - t
    t = time.perf_counter()
    cyl = assemble_cylinders(final_circles(circles), p.cylinders)
    out["cylinders_s"] = time.perf_counter() - t
    out["n_segments"], out["n_cylinders"] = len(seg), len(cyl)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t = time.perf_counter()  # again, warm: numba kernels loaded, caches filled
    seg = segment_scan_lines(image, p.segmentation, max_window_px=p.segmentation.max_window_px)
    assemble_cylinders(final_circles(fit_circle_models(image, seg, p.circles, p.segmentation)),
                       p.cylinders)
    out["features_warm_s"] = time.perf_counter() - t
    return out


def run_child(campaign_dir: Path, pythonpath: str | None, timeout: float,
              mem_gb: float = 12.0) -> dict:
    """``measure`` in a fresh process (its data segment capped at ``mem_gb``: the machine is
    shared, and code that needs more fails with a MemoryError rather than the OOM killer)."""
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath + os.pathsep + env.get("PYTHONPATH", "")
    cap = int(mem_gb * 2**30)

    def limit():
        resource.setrlimit(resource.RLIMIT_DATA, (cap, cap))

    t = time.perf_counter()
    try:
        res = subprocess.run([sys.executable, __file__, "--measure", str(campaign_dir)], env=env,
                             capture_output=True, text=True, timeout=timeout, preexec_fn=limit)
    except subprocess.TimeoutExpired:
        return {"error": f"over {timeout:.0f} s"}
    if res.returncode != 0:
        lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
        return {"error": lines[-1] if lines else f"exit {res.returncode}"}
    out = json.loads(res.stdout.strip().splitlines()[-1])
    out["wall_s"] = time.perf_counter() - t
    return out


# ---- the whole per-scan pipeline, as a user runs it ----------------------------------------

SCAN_STAGES = ("range_images", "elevation_maps", "line_segments", "refine_clouds", "segments",
               "circle_models", "cylinder_segments", "submaps", "occlusion_boundaries")


def whole_run(campaign_dir: Path, rundir: Path) -> dict:
    """``forestmap run CAMPAIGN --no-cloud`` in a new process with a fresh home (every per-scan
    asset of the one scan, the campaign-level stages, the exports): each step's seconds as the
    run reports them, the wall time from the run's first line to the scan's last step, and the
    peak memory (largest process's maxrss, or the sampled sum of the process tree's PSS)."""
    import shutil

    from bench_survey import STEP, forestmap_exe, peak_gib, run_measured

    shutil.rmtree(rundir, ignore_errors=True)
    rundir.mkdir(parents=True)
    env = {k: v for k, v in os.environ.items() if k not in ("DAGSTER_HOME", "FORESTMAP_STORE")}
    env["FORESTMAP_HOME"] = str(rundir / "home")
    m = run_measured([forestmap_exe(), "run", str(campaign_dir), "--no-cloud", "--out",
                      str(rundir / "out")], rundir / "forestmap.log", env, echo=False)
    steps, t_first, t_last = {}, None, None
    for t, line in m["lines"]:
        if t_first is None and " scans, " in line:
            t_first = t
        if (hit := STEP.match(line.rstrip())) and hit["scan"] == "A" and hit["stage"] in SCAN_STAGES:
            steps[hit["stage"]] = float(hit["s"])
            t_last = t
    out = {"rc": m["rc"], "wall_s": m["wall_s"], "steps": steps,
           "scan_steps_s": sum(steps.values()), "peak_gib": peak_gib(m)}
    if t_first is not None and t_last is not None:
        out["scan_wall_s"] = t_last - t_first
    return out


def whole_table(results: dict[str, dict]) -> list[str]:
    keys = list(results)
    lines = ["| step | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    for stage in SCAN_STAGES:
        cells = [f"{r['steps'][stage]:.1f}" if stage in r.get("steps", {}) else "-"
                 for r in results.values()]
        lines.append(f"| {stage} (s) | " + " | ".join(cells) + " |")
    lines.append("| **per-scan steps, sum (s)** | " + " | ".join(
        f"**{r['scan_steps_s']:.1f}**" if "scan_steps_s" in r else "-" for r in results.values()) + " |")
    lines.append("| scan's steps, wall (s) | " + " | ".join(
        f"{r['scan_wall_s']:.1f}" if "scan_wall_s" in r else "-" for r in results.values()) + " |")
    lines.append("| whole run, wall (s) | " + " | ".join(f"{r['wall_s']:.1f}" for r in results.values()) + " |")
    lines.append("| peak memory (GiB) | " + " | ".join(f"{r['peak_gib']:.2f}" for r in results.values()) + " |")
    lines.append("| exit code | " + " | ".join(str(r["rc"]) for r in results.values()) + " |")
    return lines


# ---- accuracy of projected clouds ----------------------------------------------------------

def accuracy(cache: Path, seeds: list[int]):
    import pandas as pd
    from unorganised_scans import simulate_with_clouds, thinned, write_las

    from forestmap_assets.core.features.cylinders import extract_features
    from forestmap_assets.io.readers import read_scan
    from forestmap_assets.io.readers_common import ProjectionSettings
    from forestmap_assets.io.writers import scan_points, write_scan
    from forestmap_assets.params import resolve_params
    from forestmap_assets.sim.evaluate import scan_feature_accuracy

    params = resolve_params("forest")
    rows = []
    for seed in seeds:
        folder = cache / f"accuracy_s{seed}"
        camp, clouds = simulate_with_clouds(folder / "campaign", seed=seed, scans=2, trees=40,
                                            resolution="full")
        for sid, (xyz, inten) in clouds.items():
            img = read_scan(camp / "scans" / f"{sid}.npz")
            files = {
                "LAS of the image": write_scan(folder / f"{sid}_grid.las", img),
                "jittered, 30 % dropped": write_las(folder / f"{sid}_jitter.laz", xyz, inten),
                "thinned to 50 %": write_las(folder / f"{sid}_thin.laz",
                                             *thinned(scan_points(img)[0], None, 0.5, seed)),
            }
            images = {"organised npz": (img, img)}
            for name, path in files.items():
                images[name] = (read_scan(path), read_scan(path, angular_step_deg=ProjectionSettings(
                    bridge=False)))
            for name, (im, raw) in images.items():
                t = time.perf_counter()
                cyl = extract_features(im, params)["cylinder_segments"]
                dt = time.perf_counter() - t
                a = scan_feature_accuracy(camp, sid, cyl)
                per = a["per_stem"]
                err = per.loc[per["target"], "radius_error_m"].dropna().to_numpy()
                rows.append({"cloud": name, "stems": a["stems"], "found": a["found"],
                             "ncyl": a["n_cylinders"], "fp": a["false_positives"],
                             "se": float(np.sum(err ** 2)), "sum": float(np.sum(err)),
                             "n": err.size, "fill": _fill(raw.valid), "fill_bridged": _fill(im.valid),
                             "step": im.azimuth_step_deg, "features_s": dt})
    df = pd.DataFrame(rows)
    g = df.groupby("cloud", sort=False).agg(
        stems=("stems", "sum"), found=("found", "sum"), ncyl=("ncyl", "sum"), fp=("fp", "sum"),
        se=("se", "sum"), s=("sum", "sum"), n=("n", "sum"), fill=("fill", "min"),
        fill_bridged=("fill_bridged", "mean"), step=("step", "mean"),
        features_s=("features_s", "mean"))
    g["detection"] = g["found"] / g["stems"]
    g["fp_rate"] = g["fp"] / g["ncyl"]
    g["rmse_cm"] = 100 * np.sqrt(g["se"] / g["n"])
    g["bias_cm"] = 100 * g["s"] / g["n"]
    return g


def step_study(cache: Path, steps: list[float], seed: int = 1):
    """Stems found, radius error and feature seconds against ``range_images.min_step_deg`` on
    fine scans (``--resolution fine`` with truth, 2 positions): the organised scan thinned to
    the step, and its jittered LAZ (N(0, 0.3 step)) projected at it."""
    import pandas as pd
    from unorganised_scans import simulate_with_clouds, write_las

    from forestmap_assets.core.features.cylinders import extract_features
    from forestmap_assets.io.readers import read_scan
    from forestmap_assets.io.readers_common import ProjectionSettings, coarsen_range_image
    from forestmap_assets.params import resolve_params
    from forestmap_assets.sim.evaluate import scan_feature_accuracy

    folder = cache / f"fine_s{seed}"
    camp = folder / "campaign"
    if not (camp / "campaign.yaml").exists():
        camp, clouds = simulate_with_clouds(camp, seed=seed, scans=2, trees=40, resolution="fine",
                                            dropout=0.0)
        for sid, (xyz, inten) in clouds.items():
            write_las(folder / f"{sid}.laz", xyz, inten)
        del clouds
    params = resolve_params("forest")
    rows = []
    for laz in sorted(folder.glob("*.laz")):
        organised = read_scan(camp / "scans" / f"{laz.stem}.npz")
        for step in steps:
            for source in ("organised, thinned", "jittered LAZ"):
                t = time.perf_counter()
                if source == "jittered LAZ":
                    im = read_scan(laz, angular_step_deg=ProjectionSettings(min_step_deg=step))
                else:
                    im = coarsen_range_image(organised, step)
                read_s = time.perf_counter() - t
                t = time.perf_counter()
                cyl = extract_features(im, params)["cylinder_segments"]
                feat_s = time.perf_counter() - t
                a = scan_feature_accuracy(camp, laz.stem, cyl)
                per = a["per_stem"]
                err = per.loc[per["target"], "radius_error_m"].dropna().to_numpy()
                rows.append({"step": step, "source": source, "stems": a["stems"],
                             "found": a["found"], "se": float(np.sum(err ** 2)),
                             "s": float(np.sum(err)), "n": err.size, "pixels": im.range_m.size,
                             "read_s": read_s, "features_s": feat_s})
                print(rows[-1], flush=True)
    g = pd.DataFrame(rows).groupby(["step", "source"], sort=False).agg(
        stems=("stems", "sum"), found=("found", "sum"), se=("se", "sum"), s=("s", "sum"),
        n=("n", "sum"), pixels=("pixels", "mean"), read_s=("read_s", "mean"),
        features_s=("features_s", "mean"))
    g["rmse_cm"] = 100 * np.sqrt(g["se"] / g["n"])
    g["bias_cm"] = 100 * g["s"] / g["n"]
    return g


# ---- report --------------------------------------------------------------------------------

STAGES = (("read_image_s", "read + range image"), ("segments_s", "segments"),
          ("circles_s", "circle models"), ("cylinders_s", "cylinder segments"))


def stage_table(results: dict[str, dict]) -> list[str]:
    keys = list(results)
    lines = ["| | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    for r in results.values():  # a failed measurement: its reason, short
        if "error" in r and not r["error"].startswith("failed"):
            kind = r["error"].split(":")[0].rsplit(".", 1)[-1]
            r["error"] = f"failed ({kind})"

    def row(label, fmt):
        cells = []
        for k in keys:
            r = results[k]
            try:
                cells.append(fmt(r))
            except (KeyError, TypeError):
                cells.append(r.get("error", "-") if label == "points" else "-")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")

    row("points", lambda r: f"{r['points']:,}")
    row("LAZ decompression alone (s)", lambda r: f"{r['decompress_s']:.2f}")
    for key, label in STAGES:
        row(f"{label} (s)", lambda r, key=key: f"{r[key]:.2f}")
    row("**per-scan stages (s)**", lambda r: f"**{sum(r[k] for k, _ in STAGES):.2f}**")
    row("features again, warm (s)", lambda r: f"{r['features_warm_s']:.2f}")
    row("range image table round trip (s)", lambda r: f"{r['table_s']:.2f}")
    row("peak memory (MB, ru_maxrss)", lambda r: f"{r['peak_rss_mb']:.0f}")
    row("range image (rows x cols)", lambda r: f"{r['rows']} x {r['cols']}")
    row("step (az, el deg)", lambda r: f"{r['step_deg'][0]:.4f}, {r['step_deg'][1]:.4f}")
    row("fill ratio", lambda r: f"{r['fill']:.3f}")
    row("segments / cylinders", lambda r: f"{r['n_segments']:,} / {r['n_cylinders']}")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--measure", help=argparse.SUPPRESS)
    ap.add_argument("--cache", type=Path, default=CACHE)
    ap.add_argument("--rebuild", action="store_true")
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--no-accuracy", action="store_true")
    ap.add_argument("--scans", default=",".join(SCANS), help=f"of {', '.join(SCANS)}")
    ap.add_argument("--no-whole", action="store_true", help="skip the whole `forestmap run`")
    ap.add_argument("--before", default=None, metavar="DIR",
                    help="also measure another copy of the package (PYTHONPATH), e.g. the code "
                    "before this change: git archive HEAD forestmap_assets | tar -x -C DIR")
    ap.add_argument("--timeout", type=float, default=900.0)
    ap.add_argument("--mem-gb", type=float, default=12.0, help="memory cap of each measurement")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--step-study", default=None, metavar="STEPS",
                    help="also stems and radius error against min_step_deg on fine scans, "
                    "e.g. 0.05,0.07,0.1 (builds two fine scans with truth: ~10 min)")
    args = ap.parse_args()
    if args.measure:
        print(json.dumps(measure(args.measure)))
        return 0
    keys = tuple(k.strip() for k in args.scans.split(","))
    if unknown := set(keys) - set(SCANS):
        ap.error(f"--scans: {', '.join(sorted(unknown))} is not one of {', '.join(SCANS)}")
    scans = build_scans(args.cache, args.rebuild, keys)
    results = {}
    for key in keys:
        for label, path in (("before", args.before), ("after", None)):
            if label == "before" and not path:
                continue
            results[f"{key} ({label})"] = r = run_child(scans[key], path, args.timeout,
                                                        args.mem_gb)
            print(key, label, json.dumps(r), flush=True)
    text = [
        f"Measured {time.strftime('%Y-%m-%d')} on {platform.machine()}, {os.cpu_count()} cores "
        "(shared with other work), one fresh process per scan (the first circle models call "
        "loads the compiled numba kernels: compare the warm repeat), capped at "
        f"{args.mem_gb:g} GB; campaign defaults (params `range_images`: `min_step_deg` 0.05, "
        "`min_fill` 0.5, gaps bridged). Per-scan stages: read + range image, segments, circle "
        "models, cylinders (`assets.ingest.read_campaign_scan` and the core functions); the "
        "table round trip is what the asset store adds. Scans: see "
        "`benchmarks/bench_big_scan.py`."
        + (" *before*: the package before issue 18's big-scan work (`--before`)."
           if args.before else ""), "", *stage_table(results)]
    if not args.no_whole:
        whole = {key: whole_run(scans[key], args.cache / f"run-{key.replace(' ', '-')}")
                 for key in keys}
        for key, r in whole.items():
            print("whole run", key, json.dumps(r), flush=True)
        text += ["", "The whole per-scan pipeline as a user runs it: `forestmap run CAMPAIGN "
                 "--no-cloud` on each one-scan campaign, a new process and a fresh home (every "
                 "per-scan asset, the campaign-level stages, the exports); each step's seconds "
                 "as the run reports them (read, compute, store write, UI pictures); the scan's "
                 "wall time from the run's first line to its last step (a one-scan campaign runs "
                 "every step in the `forestmap run` process); peak memory: the larger of the biggest "
                 "process's maxrss and the sampled sum of the process tree's PSS.", "",
                 *whole_table(whole)]
    if not args.no_accuracy:
        g = accuracy(args.cache, [int(s) for s in args.seeds.split(",")])
        print(g.round(4).to_string())
        text += ["", f"Detection against the simulator's truth (seeds {args.seeds}, 2 scans each, "
                 "full LMS-Z210 resolution; stems within 15 m with >= 1 m visible; "
                 "`sim.evaluate.scan_feature_accuracy`). Fill: the least fill ratio of the "
                 "returns over the scans, before row gaps are bridged.", "",
                 "| cloud | stems found | detection | false positives | radius RMSE (cm) | "
                 "bias (cm) | step (deg) | fill | fill, bridged | features (s) |",
                 "|---|---|---|---|---|---|---|---|---|---|"]
        for name, r in g.iterrows():
            text.append(f"| {name} | {r['found']:.0f} / {r['stems']:.0f} | {r['detection']:.1%} | "
                        f"{r['fp_rate']:.1%} | {r['rmse_cm']:.2f} | {r['bias_cm']:+.2f} | "
                        f"{r['step']:.3f} | {r['fill']:.2f} | {r['fill_bridged']:.2f} | "
                        f"{r['features_s']:.1f} |")
    if args.step_study:
        g = step_study(args.cache, [float(x) for x in args.step_study.split(",")])
        print(g.round(4).to_string())
        text += ["", "Feature grid (`range_images.min_step_deg`) on two `--resolution fine` "
                 "scans with truth (seed 1; the organised 0.028 deg scan thinned to the step, and "
                 "its jittered LAZ projected at it); seconds per scan.", "",
                 "| step (deg) | source | pixels | stems found | radius RMSE (cm) | bias (cm) | "
                 "read + range image (s) | features (s) |", "|---|---|---|---|---|---|---|---|"]
        for (step, source), r in g.iterrows():
            text.append(f"| {step:g} | {source} | {r['pixels'] / 1e6:.1f} M | "
                        f"{r['found']:.0f} / {r['stems']:.0f} | {r['rmse_cm']:.2f} | "
                        f"{r['bias_cm']:+.2f} | {r['read_s']:.1f} | {r['features_s']:.1f} |")
    body = "## Big scans (issue 18)\n\n" + "\n".join(text)
    print(body)
    if not args.no_write:
        from results_md import write_section

        write_section(NAME, body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
