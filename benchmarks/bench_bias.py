"""Do the residual checks catch a biased link? (issue 19: simulated realistic-stem surveys.)

For each stored survey (a simulated campaign already run by ``forestmap run``) the accepted
registrations that fed the optimal map (``refined_registrations``) are read from the store. Each
accepted link in turn gets a bias (2, 3 or 5 cm horizontally in a random direction, 2, 3 or 5
cm in z, 0.1 or 0.2 deg in heading, or 5 cm + 0.2 deg; a random direction / sign per trial) and
the map is recomputed exactly as the ``optimal_map`` asset does (``select_links`` with the
campaign's ``mapping`` parameters, the rho columns of refined links), followed by the
``residual_checks`` verdicts of the final map.

Counted per trial (pipeline):

* **link flagged**: the biased link is rejected by the link test, or its final residual verdict
  is ``inconsistent``;
* **network flagged**: any flag that the unbiased network does not raise (a link rejected that
  was admitted without the bias, or an ``inconsistent`` final verdict);
* **blamed other**: the network is flagged but the biased link is not (it went in as a
  spanning-tree link and a correct link closing its loop was rejected instead).

A second check applies the residual rule of spec 8.5 to the map of *all* accepted links at once
(``solve_network``, no selection): link / network flagged as above from the residual verdicts.
With it the benchmark also gives, per link and component, the redundancy number
``r = var(e) / sigma^2`` (0 for a link on no loop: uncheckable, Th. 7.1) and a what-if: the same
3 / 8 thresholds applied to the standardised residual ``e / (sigma sqrt(r))`` (Baarda's w-test)
instead of ``e / sigma``. The false-alarm rates are those of the unbiased networks.

    python benchmarks/bench_bias.py /tmp/bias/realistic-{1..5} /tmp/bias/circular-{1..5} \\
        --cache /tmp/bias/cache

Each survey folder ``S`` has ``S/campaign.yaml``, ``S/truth/poses.csv`` and its store under
``--home-pattern`` (default ``{parent}/home-{name}``: ``/tmp/bias/home-realistic-1``).
"""

from __future__ import annotations

import argparse
import time
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
from results_md import write_section  # noqa: E402

# (label, kind, size): kind xy (m, random horizontal direction in the reference's frame),
# z (m, random sign), heading (deg, random sign), xyh (5 cm xy + 0.2 deg heading)
BIASES = (
    ("xy 2 cm", "xy", 0.02), ("xy 3 cm", "xy", 0.03), ("xy 5 cm", "xy", 0.05),
    ("z 2 cm", "z", 0.02), ("z 3 cm", "z", 0.03), ("z 5 cm", "z", 0.05),
    ("heading 0.1 deg", "heading", 0.1), ("heading 0.2 deg", "heading", 0.2),
    ("xy 5 cm + heading 0.2 deg", "xyh", 0.05),
)
R_COLS = ["rx", "ry", "rz", "rheading"]
SD_COLS = ["sd_x", "sd_y", "sd_z", "sd_heading_deg"]


def biased(acc: pd.DataFrame, k: int, kind: str, size: float, rng: np.random.Generator) -> pd.DataFrame:
    """``acc`` with row ``k`` biased: ``kind`` xy / z / heading / xyh of ``size`` (m or deg)."""
    out = acc.copy()
    if kind in ("xy", "xyh"):
        a = rng.uniform(0.0, 2.0 * np.pi)
        out.loc[k, "dx"] += size * np.cos(a)
        out.loc[k, "dy"] += size * np.sin(a)
    if kind == "z":
        out.loc[k, "dz"] += size * rng.choice((-1.0, 1.0))
    if kind == "heading":
        out.loc[k, "dheading_deg"] += size * rng.choice((-1.0, 1.0))
    if kind == "xyh":
        out.loc[k, "dheading_deg"] += 0.2 * rng.choice((-1.0, 1.0))
    return out


def with_rho(acc: pd.DataFrame, mp) -> pd.DataFrame:
    """The rho columns the ``optimal_map`` asset adds (refined vs branch-and-bound links)."""
    from forestmap_assets.core.mapping.optimal_map import RHO_COLUMNS

    out = acc.copy()
    refined = out["refined"].to_numpy(bool)[:, None] if "refined" in out else False
    rho = np.where(refined, mp.refined_scan_correlation, mp.scan_correlation)
    out[list(RHO_COLUMNS)] = np.broadcast_to(rho, (len(out), 4))
    return out


def pipeline_flags(acc: pd.DataFrame, scans: list[str], mp) -> tuple[set[int], set[int], pd.DataFrame]:
    """The ``optimal_map`` asset's link selection and the ``residual_checks`` verdicts: returns
    (rows of ``acc`` rejected, rows admitted with an ``inconsistent`` final verdict, links)."""
    from forestmap_assets.core.mapping.link_selection import select_links

    sel = select_links(acc, scans[0], scans=scans, confidence="confidence",
                       covariance=mp.covariance, iterate=mp.iterate,
                       residual_sigmas=mp.residual_sigmas, z_residual_sigmas=mp.z_residual_sigmas,
                       scan_correlation=mp.scan_correlation)
    links = sel.links
    rejected = set(np.flatnonzero((links["status"] == "rejected").to_numpy()))
    sol = sel.solution
    bad_obs = sol.projected.loc[sol.residuals["verdict"].to_numpy() != "ok", "observation"]
    inconsistent = {int(o) for o in bad_obs}  # observation: the row label of ``acc``
    return rejected, inconsistent, links


def all_links_check(acc: pd.DataFrame, scans: list[str], mp) -> dict:
    """Residual rule on the map of all accepted links (no selection) and the w-test what-if:
    per row of ``acc`` the normalised residuals ``r`` (M, 4), redundancy numbers (M, 4) and the
    standardised residuals ``w = r / sqrt(redundancy)``."""
    from forestmap_assets.core.mapping.optimal_map import solve_network

    sol = solve_network(acc, scans, covariance=mp.covariance, iterate=mp.iterate,
                        residual_sigmas=mp.residual_sigmas, z_residual_sigmas=mp.z_residual_sigmas)
    proj = sol.projected
    m = len(acc)
    r = np.full((m, 4), np.nan)
    red = np.zeros((m, 4))
    obs = proj["observation"].to_numpy(int)
    r[obs] = sol.residuals[R_COLS].to_numpy(float)
    pos = {s: k for k, s in enumerate(sol.scans)}
    reg = sol.poses["registered"].to_numpy(bool)
    free = [k for k in range(1, len(scans)) if reg[k]]
    col = {k: c for c, k in enumerate(free)}
    i = proj["scan"].map(pos).to_numpy(int)
    j = proj["reference"].map(pos).to_numpy(int)
    sd = proj[SD_COLS].to_numpy(float)
    for c in range(4):  # with the published covariance each component is its own network
        if mp.covariance != "published":
            raise SystemExit("the redundancy numbers assume covariance: published")
        h = np.zeros((len(proj), len(free)))
        for row, (a, b) in enumerate(zip(i, j, strict=True)):
            if a in col:
                h[row, col[a]] += 1.0
            if b in col:
                h[row, col[b]] -= 1.0
        w = 1.0 / sd[:, c] ** 2
        cx = np.linalg.inv(h.T @ (w[:, None] * h))
        red[obs, c] = 1.0 - np.einsum("mi,ij,mj->m", h, cx, h) * w
    red = np.clip(red, 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        wtest = np.where(red > 1e-9, r / np.sqrt(red), 0.0)
    return {"r": r, "redundancy": red, "w": wtest}


def exceeds(r: np.ndarray, mp) -> np.ndarray:
    """Rows whose |x|, |y|, |heading| > residual_sigmas or |z| > z_residual_sigmas."""
    from forestmap_assets.core.mapping.residuals import normalised_excess

    return (np.nan_to_num(normalised_excess(r, mp.residual_sigmas, mp.z_residual_sigmas)) > 1.0).any(axis=1)


def bridges(acc: pd.DataFrame) -> np.ndarray:
    """True for links on no loop of the accepted network (removing them disconnects their ends)."""
    s = acc["scan"].astype(str).to_numpy()
    t = acc["reference"].astype(str).to_numpy()
    out = np.zeros(len(acc), dtype=bool)
    for k in range(len(acc)):
        adj: dict[str, set[str]] = {}
        for m in range(len(acc)):
            if m != k:
                adj.setdefault(s[m], set()).add(t[m])
                adj.setdefault(t[m], set()).add(s[m])
        seen, todo = {s[k]}, [s[k]]
        while todo:
            for nb in adj.get(todo.pop(), ()):
                if nb not in seen:
                    seen.add(nb)
                    todo.append(nb)
        out[k] = t[k] not in seen
    return out


def survey(root: Path, home: Path, directions: int, pipeline_directions: int, seed: int) -> dict:
    """All trials of one survey: a row per (link, bias, direction) and the per-link facts. The
    residual rule on all links gets ``directions`` random directions / signs per link and bias,
    the (slower) pipeline the first ``pipeline_directions`` of them."""
    from bench_mapping import pair_errors

    from forestmap_assets.access import load_asset
    from forestmap_assets.io.campaign import load_campaign

    camp = load_campaign(root)
    mp = camp.params.mapping
    if mp.method != "optimal":
        raise SystemExit(f"{root}: mapping.method {mp.method!r}, this benchmark needs 'optimal'")
    scans = list(camp.scan_ids)
    store = str(home / "store")
    regs = load_asset("refined_registrations", campaign=root, store_url=store)["registrations"]
    acc = with_rho(regs[regs["status"] == "accepted"].reset_index(drop=True), mp)
    truth = pd.read_csv(root / "truth" / "poses.csv", dtype={"scan": str})
    pe = pair_errors(acc, truth)
    base_rej, base_inc, base_links = pipeline_flags(acc, scans, mp)
    stored = load_asset("optimal_map", campaign=root, store_url=store)["links"]
    if stored["status"].tolist() != base_links["status"].tolist():
        raise SystemExit(f"{root}: select_links does not reproduce the stored optimal_map links")
    base_flags = base_rej | base_inc
    base_all = all_links_check(acc, scans, mp)
    base_all_flags = set(np.flatnonzero(exceeds(base_all["r"], mp)))
    base_w_flags = set(np.flatnonzero(exceeds(base_all["w"], mp)))
    bridge = bridges(acc)
    links = acc[["scan", "reference", *SD_COLS]].copy()
    links["refined"] = acc["refined"].to_numpy(bool) if "refined" in acc else False
    links["checkable"] = ~bridge
    links["wrong"] = pe["wrong"].to_numpy(bool)
    links[["nx", "ny", "nz", "nheading"]] = pe[["nx", "ny", "nz", "nheading"]].to_numpy(float)
    links[["red_x", "red_y", "red_z", "red_heading"]] = base_all["redundancy"]
    links[["r_x", "r_y", "r_z", "r_heading"]] = base_all["r"]
    links["role"] = base_links["role"].to_numpy()
    links["base_status"] = base_links["status"].to_numpy()
    links["base_flag"] = [k in base_flags for k in range(len(acc))]
    links["base_all_flag"] = [k in base_all_flags for k in range(len(acc))]
    links["base_w_flag"] = [k in base_w_flags for k in range(len(acc))]
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(len(acc)):
        for label, kind, size in BIASES:
            for n in range(directions):
                b = biased(acc, k, kind, size, rng)
                al = all_links_check(b, scans, mp)
                af = set(np.flatnonzero(exceeds(al["r"], mp)))
                wf = set(np.flatnonzero(exceeds(al["w"], mp)))
                row = {
                    "link": k, "bias": label, "checkable": not bridge[k],
                    "all_link_flagged": k in af, "all_network_flagged": bool(af - base_all_flags),
                    "w_link_flagged": k in wf, "w_network_flagged": bool(wf - base_w_flags),
                    "own_r": float(np.nanmax(np.abs(al["r"][k]) / np.array(
                        [mp.residual_sigmas, mp.residual_sigmas, mp.z_residual_sigmas,
                         mp.residual_sigmas]))),
                }
                if n < pipeline_directions:
                    rej, inc, sel_links = pipeline_flags(b, scans, mp)
                    flags = rej | inc
                    row.update({
                        "pipeline": True, "link_flagged": k in flags, "link_rejected": k in rej,
                        "link_role": sel_links["role"].iloc[k],
                        "network_flagged": bool(flags - base_flags),
                    })
                rows.append(row)
    trials = pd.DataFrame(rows)
    trials["pipeline"] = trials.get("pipeline", pd.Series(False, index=trials.index)).fillna(False)
    return {"trials": trials, "links": links, "n_scans": len(scans)}


def pct(v: pd.Series) -> str:
    return f"{100.0 * v.astype(bool).mean():.0f} %" if len(v) else "-"


def report(results: dict[str, list[dict]], args, seconds: float) -> str:
    lines = [
        "## Residual checks against a biased link (issue 19)",
        "",
        f"`python benchmarks/bench_bias.py` on {sum(len(v) for v in results.values())} stored "
        f"surveys ({args.describe}). Each accepted link of the refined registrations in turn is "
        "biased and the map recomputed as the `optimal_map` asset does (`select_links` with the "
        "campaign's mapping parameters: 3 sigma x/y/heading, 8 sigma z), then the "
        "`residual_checks` verdicts of the final map. **Link**: the biased link is rejected or "
        "its final verdict is inconsistent; **network**: any flag the unbiased network does not "
        "raise; **other**: the network is flagged but not the biased link (it entered as a "
        "spanning-tree or early loop link and correct links closing its loops were rejected "
        f"instead). Pipeline: {args.pipeline_directions} random direction / sign per link and "
        f"bias; **all links**: the residual rule of spec 8.5 on the map of all accepted links at "
        f"once, {args.directions} directions; **w-test**: what-if, the same 3 / 8 thresholds on "
        "the standardised residual e / (sigma sqrt(r)), r the link's redundancy number, instead "
        "of e / sigma (not what the pipeline does). Rates over checkable links (on a loop of the "
        "accepted network; a link on no loop cannot be checked, Th. 7.1). False alarms: links "
        "flagged in the unbiased network.",
        "",
    ]
    for stems, res in results.items():
        links = pd.concat([r["links"].assign(survey=n, row=np.arange(len(r["links"])))
                           for n, r in enumerate(res)], ignore_index=True)
        trials = pd.concat([r["trials"].assign(survey=n) for n, r in enumerate(res)],
                           ignore_index=True)
        chk = links[links["checkable"]]
        sd = chk[SD_COLS].median()
        red = chk[["red_x", "red_y", "red_z", "red_heading"]].median()
        base_fa = links["base_flag"] & ~links["wrong"]
        nets_fa = sum(bool(r["links"]["base_flag"].any()) for r in res)
        per = ", ".join(f"{int(r['links']['checkable'].sum())}/{len(r['links'])}" for r in res)
        # bias that just reaches the threshold in the link's own residual (no noise): 3 sigma / r
        mdb_xy = (3.0 * chk[["sd_x", "sd_y"]].to_numpy().max(axis=1)
                  / chk[["red_x", "red_y"]].to_numpy().min(axis=1))
        mdb_z = 8.0 * chk["sd_z"] / chk["red_z"]
        mdb_h = 3.0 * chk["sd_heading_deg"] / chk["red_heading"]
        rms = {c: float(np.sqrt(np.nanmean(links.loc[~links["wrong"].astype(bool), c] ** 2)))
               for c in ("nx", "ny", "nz", "nheading")}
        xy_scale = max(rms["nx"], rms["ny"])
        lines += [
            f"### {stems} stems",
            "",
            f"{len(res)} surveys of {int(res[0]['links']['n_scans'].iloc[0])} scans: "
            f"{len(links)} accepted links, **{len(chk)} checkable** ({per} per survey), "
            f"{int(links['wrong'].sum())} wrong (> 0.2 m or 2 deg from the truth), "
            f"{int(links['refined'].sum())} refined. Median sigma of the checkable links: "
            f"x {100 * sd['sd_x']:.1f} cm, y {100 * sd['sd_y']:.1f} cm, z {100 * sd['sd_z']:.1f} cm, "
            f"heading {sd['sd_heading_deg']:.3f} deg; median redundancy number r (share of a "
            f"link's bias left in its own residual): x {red['red_x']:.2f}, y {red['red_y']:.2f}, "
            f"z {red['red_z']:.2f}, heading {red['red_heading']:.2f}. Bias at which the link's own "
            f"residual reaches the threshold without noise (3 sigma / r, z 8 sigma / r), median "
            f"(10-90 %): xy {100 * np.median(mdb_xy):.1f} cm ({100 * np.percentile(mdb_xy, 10):.1f}-"
            f"{100 * np.percentile(mdb_xy, 90):.1f}), z {100 * np.median(mdb_z):.1f} cm "
            f"({100 * np.percentile(mdb_z, 10):.1f}-{100 * np.percentile(mdb_z, 90):.1f}), heading "
            f"{np.median(mdb_h):.3f} deg ({np.percentile(mdb_h, 10):.3f}-"
            f"{np.percentile(mdb_h, 90):.3f}).",
            "",
            f"False alarms (unbiased networks): pipeline {int(links['base_flag'].sum())} of "
            f"{len(links)} links ({int(base_fa.sum())} of them correct links) in {nets_fa} of "
            f"{len(res)} surveys; all links {int(links['base_all_flag'].sum())}; w-test what-if "
            f"{int(links['base_w_flag'].sum())}.",
            "",
            "Normalised true errors (error / sigma against the truth) of the correct accepted "
            "links, RMS: " + ", ".join(f"{c[1:]} {rms[c]:.2f}" for c in rms)
            + " (1 if the sigmas were honest). With sigmas scaled by these (honest), the bias "
            f"reaching the threshold would be xy {100 * np.median(mdb_xy * xy_scale):.1f} cm, "
            f"z {100 * np.median(mdb_z * rms['nz']):.1f} cm, heading "
            f"{np.median(mdb_h * rms['nheading']):.3f} deg (median).",
            "",
            "| bias | trials (pipeline / all links) | pipeline: link | link (tree / loop links) | "
            "network | other | "
            "all links: link | network | w-test: link | network |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for label, _, _ in BIASES:
            t = trials[(trials["bias"] == label) & trials["checkable"]]
            p = t[t["pipeline"].astype(bool)]
            other = p["network_flagged"].astype(bool) & ~p["link_flagged"].astype(bool)
            key = links.groupby(["survey", "row"])["role"].first()
            role = np.array([key.get((sv, lk), "") for sv, lk in zip(p["survey"], p["link"],
                                                                      strict=True)])
            lines.append(
                f"| {label} | {len(p)} / {len(t)} | {pct(p['link_flagged'])} | "
                f"{pct(p.loc[role == 'tree', 'link_flagged'])} / "
                f"{pct(p.loc[role == 'loop', 'link_flagged'])} | "
                f"{pct(p['network_flagged'])} | {pct(other)} | {pct(t['all_link_flagged'])} | "
                f"{pct(t['all_network_flagged'])} | {pct(t['w_link_flagged'])} | "
                f"{pct(t['w_network_flagged'])} |")
        unchk = trials[~trials["checkable"] & trials["pipeline"].astype(bool)]
        if len(unchk):
            lines += ["", f"Uncheckable links: {len(unchk)} pipeline trials, network flagged in "
                      f"{pct(unchk['network_flagged'])}."]
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("surveys", nargs="+", type=Path,
                    help="simulated campaign folders, run by forestmap run; the folder name "
                    "before the last '-' is the stem kind (realistic-1 -> realistic)")
    ap.add_argument("--home-pattern", default="{parent}/home-{name}",
                    help="FORESTMAP_HOME of each survey ({parent}, {name} of the folder)")
    ap.add_argument("--directions", type=int, default=4,
                    help="random directions / signs per link and bias (all-links check)")
    ap.add_argument("--pipeline-directions", type=int, default=1,
                    help="how many of them also go through the pipeline's link selection")
    ap.add_argument("--seed", type=int, default=19)
    ap.add_argument("--describe", default="6 scans, half resolution, no prior, seeds 1-5")
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument("--cache", type=Path, help="per-survey trial and link tables: reused when "
                    "present, written when not")
    args = ap.parse_args()
    t0 = time.perf_counter()
    results: dict[str, list[dict]] = {}
    for root in args.surveys:
        home = Path(args.home_pattern.format(parent=root.parent, name=root.name))
        stems = root.name.rsplit("-", 1)[0]
        cached = [args.cache / f"{x}-{root.name}.csv" for x in ("trials", "links")] if args.cache else []
        if cached and all(p.exists() for p in cached):
            res = {"trials": pd.read_csv(cached[0]), "links": pd.read_csv(cached[1])}
        else:
            res = survey(root, home, args.directions, args.pipeline_directions,
                         args.seed + zlib.crc32(root.name.encode()))
            res["links"]["n_scans"] = res.pop("n_scans")
            if cached:
                args.cache.mkdir(parents=True, exist_ok=True)
                res["trials"].to_csv(cached[0], index=False)
                res["links"].to_csv(cached[1], index=False)
        results.setdefault(stems, []).append(res)
        print(f"{root.name}: {len(res['links'])} links, {int(res['links']['checkable'].sum())} "
              f"checkable, {time.perf_counter() - t0:.0f} s", flush=True)
    body = report(results, args, time.perf_counter() - t0)
    print(body)
    if not args.no_write:
        write_section("bias", body)


if __name__ == "__main__":
    main()
