"""Campaigns of 10 to 100 scans (issue 17): time, pairs searched, memory and accuracy.

For each size N, forestmap's own simulator makes a campaign at half resolution without priors,
the plot grown with the scans so that the tree density (250 trees/ha, the sample's) and the scan
spacing (the simulator's serpentine grid, 7 m between neighbours plus 0.75 m jitter) stay
constant. ``forestmap run`` runs on it in a new process with a fresh ``FORESTMAP_HOME`` (as a user
would), measured as in ``bench_survey.py`` (wall, CPU, peak memory of the process tree). Reported
per size: wall time, pairs searched (pair partitions) and accepted, peak memory, the share of
scans placed, the largest pose errors, and the scans with at least 5 stems in common with a
neighbour (truth: stem pixels of the simulator's labels) that were not placed within 2 cm and
0.05 deg. ``--add-one N`` also adds one scan to the N-scan campaign and runs again (the new scan's
own work and only the pairs that involve it, issue 17). A log-log plot of time against scans is
written to ``benchmarks/scale.png``.

    python benchmarks/bench_scale.py --sizes 10,25,50,100 --add-one 50 --cache /tmp/bench-scale
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_survey import code_state, forestmap_exe, peak_gib, run_measured  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SECTION = "scale"
DENSITY = 40 / 40.0**2  # trees per m2, the sample's plot
SPACING, MARGIN = 7.0, 5.0  # sim.forest.scan_layout defaults


def plot_size(n: int) -> float:
    span = max(int(math.ceil(math.sqrt(n))) - 1, 1)
    return SPACING * span + 2 * MARGIN + 6.0


def make_campaign(n: int, seed: int, cache: Path, extra: int) -> Path:
    """A cached campaign of ``n + extra`` simulated scans whose manifest lists the first ``n``."""
    from forestmap_assets.sim import simulate_campaign

    root = cache / f"scale-{n}-s{seed}" / "campaign"
    if not (root / "full.yaml").exists():
        shutil.rmtree(root, ignore_errors=True)
        size = plot_size(n + extra)
        print(f"simulating {n + extra} scans on a {size:.0f} m plot ...", flush=True)
        simulate_campaign(root, scans=n + extra, trees=int(round(DENSITY * size**2)), plot_size=size,
                          resolution="half", seed=seed, no_prior=True)
        (root / "full.yaml").write_text((root / "campaign.yaml").read_text())
    doc = yaml.safe_load((root / "full.yaml").read_text())
    doc["scans"] = doc["scans"][:n]
    (root / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return root


def visible_stems(root: Path, min_pixels: int = 30) -> dict[str, set[int]]:
    from forestmap_assets.sim.scene_mesh import KIND_STEM

    out = {}
    for f in sorted((root / "truth" / "labels").glob("*.npz")):
        d = np.load(f)
        ids = d["tree_id"][(d["kind"] == KIND_STEM) & (d["tree_id"] > 0)]
        counts = np.bincount(ids.astype(np.int64).ravel()) if ids.size else np.zeros(0)
        out[f.stem] = set(np.flatnonzero(counts >= min_pixels).tolist())
    return out


def accuracy(root: Path, out: Path) -> dict:
    truth = pd.read_csv(root / "truth" / "poses.csv", dtype={"scan": str}).set_index("scan")
    ids = [s["id"] for s in yaml.safe_load((root / "campaign.yaml").read_text())["scans"]]
    truth = truth.loc[ids]
    poses = pd.read_csv(out / "poses.csv", dtype={"scan": str}).set_index("scan")
    placed = poses["registered"].astype(str).str.lower() == "true"
    # truth in the frame of the first scan (the simulator's poses are world poses)
    t0 = truth.iloc[0]
    c, s = math.cos(math.radians(t0.heading_deg)), math.sin(math.radians(t0.heading_deg))
    dx, dy = truth["x"] - t0.x, truth["y"] - t0.y
    rel = pd.DataFrame({"x": c * dx + s * dy, "y": -s * dx + c * dy, "z": truth["z"] - t0.z,
                        "h": (truth["heading_deg"] - t0.heading_deg + 180) % 360 - 180}, index=truth.index)
    p = poses[placed]
    err_xy = np.hypot(p["x"] - rel.loc[p.index, "x"], p["y"] - rel.loc[p.index, "y"])
    err_h = ((p["heading_deg"] - rel.loc[p.index, "h"] + 180) % 360 - 180).abs()
    seen = visible_stems(root)
    xy = truth[["x", "y"]].to_numpy()
    eligible = []
    for i, sid in enumerate(ids):
        d = np.hypot(*(xy - xy[i]).T)
        near = [ids[j] for j in np.flatnonzero((d > 0) & (d < 15.0))]
        if max((len(seen.get(sid, set()) & seen.get(o, set())) for o in near), default=0) >= 5:
            eligible.append(sid)
    bad = [sid for sid in eligible if not placed.get(sid, False) or err_xy.get(sid, 1.0) > 0.02
           or err_h.get(sid, 1.0) > 0.05]
    return {"scans": len(ids), "placed": int(placed.sum()), "eligible": len(eligible), "bad": bad,
            "max_xy_cm": float(err_xy.max() * 100) if len(err_xy) else math.nan,
            "max_heading_deg": float(err_h.max()) if len(err_h) else math.nan,
            "wrong_links": int(((err_xy > 0.5) | (err_h > 1.0)).sum())}


def run(root: Path, home: Path, out: Path, log: Path, executor: str, fresh: bool) -> dict:
    if fresh:
        shutil.rmtree(home, ignore_errors=True)
    shutil.rmtree(out, ignore_errors=True)
    env = {k: v for k, v in os.environ.items() if k not in ("DAGSTER_HOME", "FORESTMAP_STORE", "FORESTMAP_CAMPAIGNS")}
    env["FORESTMAP_HOME"] = str(home)
    cmd = [forestmap_exe(), "run", root, "--no-cloud", "--out", out, "--executor", executor]
    m = run_measured(cmd, log, env, echo=False)
    res = {k: m[k] for k in ("rc", "wall_s", "user_s", "sys_s", "load_before", "load_after")}
    res["peak_gib"] = peak_gib(m)
    if not (out / "poses.csv").exists():
        res["error"] = next((s for _, s in reversed(m["lines"]) if s.strip()), "no output")
        return res
    regs = pd.read_csv(out / "registrations.csv")
    res["pairs"] = len(regs)
    res["accepted"] = int((regs["status"] == "accepted").sum())
    res["pairs_run"] = sum(1 for _, s in m["lines"] if "] pairwise_registrations (" in s)
    res.update(accuracy(root, out))
    return res


def report(rows: list[dict], code: str, executor: str) -> str:
    L = [f"Code {code}; executor `{executor}`; 2-core machine. Own simulator at half resolution, no "
         "prior, 250 trees/ha, 7 m scan grid; `forestmap run --no-cloud` in a new process with a "
         "fresh home. `eligible`: scans with >= 5 stems in common with a neighbour (truth labels); "
         "`missed`: eligible scans not placed within 2 cm and 0.05 deg.", "",
         "| scans | run | wall s | CPU s | peak GiB | pairs searched (run) | accepted | placed | "
         "max xy cm | max heading deg | eligible | missed | wrong links |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            L.append(f"| {r['n']} | {r['label']} | {r['wall_s']:.0f} | - | {r['peak_gib']:.2f} | error: {r['error']} |")
            continue
        L.append(f"| {r['scans']} | {r['label']} | {r['wall_s']:.0f} | {r['user_s'] + r['sys_s']:.0f} | "
                 f"{r['peak_gib']:.2f} | {r['pairs']} ({r['pairs_run']}) | {r['accepted']} | {r['placed']}/{r['scans']} | "
                 f"{r['max_xy_cm']:.2f} | {r['max_heading_deg']:.3f} | {r['eligible']} | "
                 f"{len(r['bad'])}{' ' + ','.join(r['bad'][:6]) if r['bad'] else ''} | {r['wrong_links']} |")
    first = [r for r in rows if r["label"] == "first" and "error" not in r]
    if len(first) >= 2:
        n = np.log([r["scans"] for r in first])
        t = np.log([r["wall_s"] for r in first])
        L += ["", f"Time grows as scans^{np.polyfit(n, t, 1)[0]:.2f} (log-log fit over {len(first)} sizes)."]
    for r in rows:
        if r["label"] == "add one" and "error" not in r:
            base = next(f for f in first if f["scans"] == r["scans"] - 1)
            L.append(f"Adding one scan to {base['scans']}: {r['wall_s']:.0f} s, "
                     f"{100 * r['wall_s'] / base['wall_s']:.1f} % of the first run; {r['pairs_run']} pairs registered.")
    return "\n".join(L)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = [r for r in rows if r["label"] == "first" and "error" not in r]
    if not first:
        return
    fig, ax = plt.subplots(figsize=(5, 4))
    n = [r["scans"] for r in first]
    ax.loglog(n, [r["wall_s"] for r in first], "o-", label="forestmap run")
    ax.loglog(n, [first[0]["wall_s"] * (k / n[0]) for k in n], "--", label="linear")
    ax.loglog(n, [first[0]["wall_s"] * (k / n[0]) ** 2 for k in n], ":", label="quadratic")
    ax.axhline(1800, color="grey", lw=0.8)
    ax.set_xlabel("scans")
    ax.set_ylabel("wall time (s)")
    ax.legend()
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="10,25,50,100")
    ap.add_argument("--add-one", type=int, default=50)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--executor", default="in_process")
    ap.add_argument("--cache", type=Path, default=None)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    cache = args.cache or Path(os.environ.get("TMPDIR", "/tmp")) / "bench-scale"
    cache.mkdir(parents=True, exist_ok=True)
    code = code_state()
    rows = []
    for n in [int(s) for s in args.sizes.split(",") if s]:
        extra = 1 if n == args.add_one else 0
        root = make_campaign(n, args.seed, cache, extra)
        case = root.parent
        print(f"{n} scans: forestmap run ...", flush=True)
        r = run(root, case / "home", case / "out", case / "run.log", args.executor, fresh=True)
        rows.append({"n": n, "label": "first", **r})
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "bad"}), flush=True)
        if extra and "error" not in r:
            doc = yaml.safe_load((root / "full.yaml").read_text())
            (root / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
            print(f"{n} scans + 1: forestmap run ...", flush=True)
            r = run(root, case / "home", case / "out", case / "run-add.log", args.executor, fresh=False)
            rows.append({"n": n + 1, "label": "add one", **r})
            print(json.dumps({k: v for k, v in rows[-1].items() if k != "bad"}), flush=True)
    (cache / "rows.json").write_text(json.dumps(rows, indent=1, default=str))
    body = report(rows, code, args.executor)
    print(body)
    if not args.no_write:
        plot(rows, REPO / "benchmarks" / "scale.png")
        from results_md import write_section

        write_section(SECTION, body + "\n\n![time against scans](scale.png)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
