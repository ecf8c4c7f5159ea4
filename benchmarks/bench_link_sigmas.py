"""Where the sigma of a refined link comes from, per data source (issue 19).

The two-way refinement's sigma (core/registration/two_way.py) is
``two_way_sd_scale x sqrt(H^2 + (d / 2)^2 + beam^2)``, floored, where ``H`` is the larger
point-to-plane Hessian sd of the two directions (inflated for correlated neighbours), ``d``
the disagreement of the two directions and ``beam`` the term of a wide beam (zero unless the
campaign's sensor names one). For every accepted pair of a stored run this refines
the pair again from its stored branch-and-bound pose and stored ``refine_clouds`` (the same code
as the ``refined_registrations`` asset) and compares, over the pairs whose refinement is used,
the true error of the link with ``H``, ``d / 2`` and the final sigma: RMS values per axis, and
RMS error / sd (1 if the sigma is honest) for the final sigma and for ``H`` alone.

    python benchmarks/bench_link_sigmas.py LABEL=CAMPAIGN:HOME ... [--no-write]

``CAMPAIGN`` is a simulated campaign with ``truth/poses.csv`` that ``forestmap run`` has run
with ``FORESTMAP_HOME=HOME``. Writes the ``link_sigmas`` section of ``benchmarks/results.md``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np
import pandas as pd
from results_md import write_section

AXES = ("x", "y", "z", "heading")


def true_link(truth: pd.DataFrame, scan: str, ref: str) -> np.ndarray:
    """Pose (dx, dy, dz, dheading deg) of ``scan`` in the levelled frame of ``ref`` (spec 6.1)."""
    from forestmap_assets.core.geometry import relative_pose

    return np.asarray(relative_pose(truth.loc[scan, ["x", "y", "z", "heading_deg"]].to_numpy(float),
                                    truth.loc[ref, ["x", "y", "z", "heading_deg"]].to_numpy(float)), float)


def link_rows(campaign: str, home: str) -> pd.DataFrame:
    """One row per accepted pair whose two-way refinement is used: error, H, d / 2, sd per axis."""
    os.environ["FORESTMAP_HOME"] = home
    os.environ["DAGSTER_HOME"] = os.path.join(home, "dagster")
    from forestmap_assets.access import load_asset
    from forestmap_assets.assets.registration import refine_settings
    from forestmap_assets.core.geometry import wrap_deg
    from forestmap_assets.core.registration import two_way
    from forestmap_assets.io.campaign import load_campaign

    settings = refine_settings(load_campaign(campaign))
    regs = load_asset("pairwise_registrations", campaign=campaign)
    regs = regs["registrations"] if isinstance(regs, dict) else regs
    regs = regs[regs["status"] == "accepted"]
    truth = pd.read_csv(os.path.join(campaign, "truth", "poses.csv"), dtype={"scan": str}).set_index("scan")
    clouds: dict[str, two_way.RefineCloud] = {}

    def cloud(sid: str) -> two_way.RefineCloud:
        if sid not in clouds:
            clouds[sid] = two_way.RefineCloud.from_table(load_asset("refine_clouds", campaign=campaign, scan=sid))
        return clouds[sid]

    rows = []
    for r in regs.itertuples():
        pose = np.array([r.dx, r.dy, r.dz, r.dheading_deg], float)
        out = two_way.two_way_refine(cloud(r.scan), cloud(r.reference), pose, settings)
        if not out["used"]:
            continue
        ways = [two_way._one_way(cloud(r.scan), cloud(r.reference), pose, settings),
                two_way._one_way(cloud(r.reference), cloud(r.scan), two_way.invert_pose(pose), settings)]
        hess = np.nanmax([w.sd for w in ways if w is not None], axis=0)
        err = out["pose"] - true_link(truth, r.scan, r.reference)
        err[3] = wrap_deg(err[3])
        rows.append({"pair": f"{r.scan}-{r.reference}",
                     **{f"e_{a}": v for a, v in zip(AXES, err, strict=True)},
                     **{f"h_{a}": v for a, v in zip(AXES, hess, strict=True)},
                     **{f"d_{a}": abs(v) / 2 for a, v in zip(AXES, out["disagree"], strict=True)},
                     **{f"sd_{a}": v for a, v in zip(AXES, out["sd"], strict=True)}})
    return pd.DataFrame(rows)


def rms(v) -> float:
    v = np.asarray(v, float)
    return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")


def table(frames: dict[str, pd.DataFrame]) -> str:
    head = ("| source | links used | axis | RMS error | RMS H | RMS d/2 | RMS final sd | RMS error / final sd "
            "| RMS error / H |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for label, f in frames.items():
        for a in AXES:
            unit, k = ("deg", 1.0) if a == "heading" else ("mm", 1000.0)
            e, h, d, sd = (f[f"{p}_{a}"].to_numpy(float) for p in ("e", "h", "d", "sd"))
            lines.append(f"| {label} | {len(f)} | {a} ({unit}) | {k * rms(e):.3g} | {k * rms(h):.3g} | {k * rms(d):.3g} "
                         f"| {k * rms(sd):.3g} | {rms(e / sd):.2f} | {rms(e / h):.2f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cases", nargs="+", help="LABEL=CAMPAIGN:HOME")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    frames = {}
    for case in args.cases:
        label, rest = case.split("=", 1)
        campaign, home = rest.rsplit(":", 1)
        t0 = time.perf_counter()
        frames[label] = link_rows(campaign, home)
        print(f"{label}: {len(frames[label])} refined links ({time.perf_counter() - t0:.1f} s)", flush=True)
    body = table(frames)
    print(body)
    if not args.no_write:
        write_section("link_sigmas", (
            f"## Where a refined link's sigma comes from (`benchmarks/bench_link_sigmas.py`, issue 19)\n\n"
            f"{time.strftime('%Y-%m-%d')}, {platform.machine()}. Every accepted pair of a stored run refined again "
            "both ways from its stored branch-and-bound pose (the `refined_registrations` code); over the pairs "
            "whose refinement is used: the true error of the link, H (the larger point-to-plane Hessian sd of "
            "the two directions, inflated for correlated neighbours), d/2 (half the two directions' "
            "disagreement) and the final sigma (`two_way_sd_scale` x sqrt(H^2 + (d/2)^2 + beam^2), floored; "
            "beam: `two_way.beam_sd`, zero unless the campaign's sensor names a wide beam).\n\n" + body + "\n"))


if __name__ == "__main__":
    main()
