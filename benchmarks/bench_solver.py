"""Optimal-map solver against its peer, GTSAM (spec 8; ``forestmap solve``).

Same 4-DoF networks, same observations, two solvers:

* GTSAM: Pose2 between-factors for (x, y, heading) with each observation's sigmas given in the
  reference's levelled frame (rotated into the Pose2 error frame), plus a separate 1-D factor
  chain for z; Levenberg-Marquardt on the nonlinear problem.
* forestmap: ``solve_network``. Like with like: GTSAM solves the nonlinear problem, while the
  thesis projects every observation with the reference's heading from the previous phase. So
  our projection is iterated to convergence for the comparison ("projection, converged"; with
  the observation covariance rotated exactly, as GTSAM weighs it), and our Gauss-Newton option
  (``linearisation="gauss_newton"``, beyond the thesis) is the exact counterpart of GTSAM.
* Table 6.6 with the final headings fixed as the linearisation point: the thesis's linear
  problem (published covariance rule), solved by our Eq. 3.20 and by GTSAM (1-D heading
  factors, Point2 factors carrying the projected observations, 1-D z factors).

Prints a table and writes it between ``<!-- solver:start -->`` and ``<!-- solver:end -->`` in
``benchmarks/results.md``. Run: ``python benchmarks/bench_solver.py [--sizes 30,100]``.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # the shared 2-core box: threaded BLAS only adds contention

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import gtsam  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from results_md import write_section  # noqa: E402

from forestmap_assets.core.mapping.chaining import chain_poses, wrap_deg  # noqa: E402
from forestmap_assets.core.mapping.optimal_map import solve_incremental, solve_network  # noqa: E402

ROOT = Path(__file__).resolve().parent
TABLE_6_6 = ROOT.parent / "tests" / "data" / "thesis_tables" / "table_6_6_forest_local.csv"
RESULTS = ROOT / "results.md"
VAL = ["dx", "dy", "dz", "dheading_deg"]
SD = ["sd_x", "sd_y", "sd_z", "sd_heading_deg"]
POSE = ["x", "y", "z", "heading_deg"]


def simulate_network(n_scans: int, seed: int, link_radius_m: float = 12.0):
    """Random scan layout (about one scan per 60 m^2), links between scans closer than
    ``link_radius_m`` (a nearest-placed link keeps it connected), forest-like sigmas and
    Gaussian noise on every relative observation (location of scan in reference's frame)."""
    rng = np.random.default_rng(seed)
    side = np.sqrt(60.0 * n_scans)
    xy = rng.uniform(0, side, (n_scans, 2))
    heading = rng.uniform(-180, 180, n_scans)
    z = rng.uniform(-1.0, 1.0, n_scans)
    # truth in the frame of scan 0
    c, s = np.cos(np.radians(heading[0])), np.sin(np.radians(heading[0]))
    rel = xy - xy[0]
    truth = np.column_stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1],
                             z - z[0], wrap_deg(heading - heading[0])])
    dist = np.linalg.norm(truth[:, None, :2] - truth[None, :, :2], axis=2)
    j, i = np.nonzero(np.triu(dist < link_radius_m, 1))  # scan i newer than reference j
    nearest = [(k, int(np.argmin(dist[k, :k]))) for k in range(1, n_scans)]
    pairs = sorted({*zip(i.tolist(), j.tolist(), strict=True), *nearest})
    i, j = np.array(pairs).T
    phi = np.radians(truth[j, 3])
    dxy = truth[i, :2] - truth[j, :2]
    local = np.column_stack([np.cos(phi) * dxy[:, 0] + np.sin(phi) * dxy[:, 1],
                             -np.sin(phi) * dxy[:, 0] + np.cos(phi) * dxy[:, 1],
                             truth[i, 2] - truth[j, 2], wrap_deg(truth[i, 3] - truth[j, 3])])
    sd = np.column_stack([rng.uniform(0.02, 0.05, (len(i), 2)), rng.uniform(0.03, 0.3, len(i)),
                          rng.uniform(0.1, 0.4, len(i))])
    names = [f"s{k:03d}" for k in range(n_scans)]
    obs = pd.DataFrame({"scan": [names[k] for k in i], "reference": [names[k] for k in j]})
    obs[VAL] = local + sd * rng.standard_normal(sd.shape)
    obs[SD] = sd
    return names, truth, obs


def gtsam_pose2(obs: pd.DataFrame, names: list[str], init: np.ndarray | None = None) -> np.ndarray:
    """Nonlinear 4-DoF network in GTSAM: Pose2 between-factors + 1-D z factors, LM, started
    from ``init`` (default: the poses chained along ``names``, spec 8.3, as odometry would
    give; from all-zero headings LM can stop in a wrong local minimum)."""
    idx = {s: k for k, s in enumerate(names)}
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    px, pz = (lambda k: gtsam.symbol("x", k)), (lambda k: gtsam.symbol("z", k))
    graph.add(gtsam.PriorFactorPose2(px(0), gtsam.Pose2(0, 0, 0),
                                     gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
    graph.add(gtsam.PriorFactorDouble(pz(0), 0.0, gtsam.noiseModel.Isotropic.Sigma(1, 1e-9)))
    for row in obs.itertuples():
        i, j, dphi = idx[row.scan], idx[row.reference], np.radians(row.dheading_deg)
        rot = np.array([[np.cos(dphi), np.sin(dphi)], [-np.sin(dphi), np.cos(dphi)]])
        cov = np.zeros((3, 3))  # sigmas are in the reference's frame; Pose2's error in the scan's
        cov[:2, :2] = rot @ np.diag([row.sd_x ** 2, row.sd_y ** 2]) @ rot.T
        cov[2, 2] = np.radians(row.sd_heading_deg) ** 2
        graph.add(gtsam.BetweenFactorPose2(px(j), px(i), gtsam.Pose2(row.dx, row.dy, dphi),
                                           gtsam.noiseModel.Gaussian.Covariance(cov)))
        graph.add(gtsam.BetweenFactorDouble(pz(j), pz(i), row.dz,
                                            gtsam.noiseModel.Isotropic.Sigma(1, row.sd_z)))
    if init is None:
        init = chain_poses(obs, names)[POSE].to_numpy(dtype=float)
    for k in range(len(names)):
        values.insert(px(k), gtsam.Pose2(init[k, 0], init[k, 1], np.radians(init[k, 3])))
        values.insert(pz(k), float(init[k, 2]))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-14)
    res = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return np.array([[res.atPose2(px(k)).x(), res.atPose2(px(k)).y(), res.atDouble(pz(k)),
                      np.degrees(res.atPose2(px(k)).theta())] for k in range(len(names))])


def gtsam_fixed_headings(obs: pd.DataFrame, names: list[str], headings: dict[str, float]):
    """The thesis's linear problem in GTSAM: headings fixed at ``headings`` for the projection
    (Eq. 6.1, published covariance rule); heading, xy and z solved as factor graphs."""
    idx = {s: k for k, s in enumerate(names)}
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    pp, pz, ph = (lambda k: gtsam.symbol("p", k)), (lambda k: gtsam.symbol("z", k)), \
        (lambda k: gtsam.symbol("h", k))
    tight = gtsam.noiseModel.Isotropic.Sigma(1, 1e-9)
    graph.add(gtsam.PriorFactorPoint2(pp(0), np.zeros(2),
                                      gtsam.noiseModel.Isotropic.Sigma(2, 1e-9)))
    graph.add(gtsam.PriorFactorDouble(pz(0), 0.0, tight))
    graph.add(gtsam.PriorFactorDouble(ph(0), 0.0, tight))
    for row in obs.itertuples():
        i, j = idx[row.scan], idx[row.reference]
        phi = np.radians(headings[row.reference])
        c, s = np.cos(phi), np.sin(phi)
        d_g = np.array([c * row.dx - s * row.dy, s * row.dx + c * row.dy])
        sd_g = np.sqrt([c**2 * row.sd_x**2 + s**2 * row.sd_y**2,
                        s**2 * row.sd_x**2 + c**2 * row.sd_y**2])
        pred = headings[row.scan] - headings[row.reference]
        dh = pred + wrap_deg(row.dheading_deg - pred)
        graph.add(gtsam.BetweenFactorPoint2(pp(j), pp(i), d_g,
                                            gtsam.noiseModel.Diagonal.Sigmas(sd_g)))
        graph.add(gtsam.BetweenFactorDouble(pz(j), pz(i), row.dz,
                                            gtsam.noiseModel.Isotropic.Sigma(1, row.sd_z)))
        graph.add(gtsam.BetweenFactorDouble(ph(j), ph(i), dh,
                                            gtsam.noiseModel.Isotropic.Sigma(1,
                                                                             row.sd_heading_deg)))
    for k in range(len(names)):
        values.insert(pp(k), np.zeros(2))
        values.insert(pz(k), 0.0)
        values.insert(ph(k), 0.0)
    res = gtsam.GaussNewtonOptimizer(graph, values).optimize()
    return np.array([[*res.atPoint2(pp(k)), res.atDouble(pz(k)), res.atDouble(ph(k))]
                     for k in range(len(names))])


def projection_converged(obs: pd.DataFrame, names: list[str], max_rounds: int = 50):
    """The thesis's projection linearisation iterated to convergence, with the observation
    covariance rotated exactly (``covariance="full"`` with zero heading-of-reference variance),
    i.e. weighted as GTSAM weighs it."""
    sol = solve_network(obs, names, iterate=True)
    zero = dict.fromkeys(names, 0.0)
    for _ in range(max_rounds):
        prev = sol.poses["heading_deg"].to_numpy(dtype=float)
        sol = solve_network(obs, names, headings=sol.headings(), heading_variances=zero,
                            covariance="full")
        if np.nanmax(np.abs(sol.poses["heading_deg"].to_numpy(dtype=float) - prev)) < 1e-10:
            break
    return sol


def _timed(fn, repeats: int):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, float(np.median(times))


def _diff(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    dxy = np.linalg.norm(a[:, :2] - b[:, :2], axis=1).max()
    return float(dxy), float(np.abs(a[:, 2] - b[:, 2]).max()), \
        float(np.abs(wrap_deg(a[:, 3] - b[:, 3])).max())


def run(sizes: list[int], seed: int, repeats: int) -> pd.DataFrame:
    rows = []
    for n in sizes:
        names, truth, obs = simulate_network(n, seed)
        peer, t_peer = _timed(lambda o=obs, s=names: gtsam_pose2(o, s), repeats)
        gn, t_gn = _timed(lambda o=obs, s=names: solve_network(o, s,
                                                               linearisation="gauss_newton"),
                          repeats)
        pc, t_pc = _timed(lambda o=obs, s=names: projection_converged(o, s), repeats)
        for label, sol, t in (("Gauss-Newton (ours)", gn, t_gn),
                              ("projection, converged (thesis)", pc, t_pc)):
            ours = sol.poses[POSE].to_numpy(dtype=float)
            rows.append(dict(network=f"simulated, {n} scans", links=len(obs), solver=label,
                             seconds=t, gtsam_seconds=t_peer,
                             **dict(zip(("dxy_mm", "dz_mm", "dheading_deg"),
                                        np.array(_diff(ours, peer)) * [1e3, 1e3, 1],
                                        strict=True)),
                             rms_truth_m=float(np.sqrt(np.mean(
                                 np.sum((ours[:, :2] - truth[:, :2]) ** 2, axis=1))))))
    t66 = pd.read_csv(TABLE_6_6, dtype={"scan": str, "reference": str})
    obs = t66[t66["estimate"] == "cloud"].reset_index(drop=True)
    order = list("TSRQON")
    final, t_inc = _timed(lambda: solve_incremental(obs, order).final, repeats)
    heads = final.headings()
    fixed, t_fixed = _timed(lambda: solve_network(obs, order, headings=heads), repeats)
    peer_fixed, t_peer_fixed = _timed(lambda: gtsam_fixed_headings(obs, order, heads), repeats)
    peer, t_peer = _timed(lambda: gtsam_pose2(obs, order), repeats)
    gn, t_gn = _timed(lambda: solve_network(obs, order, linearisation="gauss_newton"), repeats)
    cases = [
        ("Eq. 3.20 at fixed final headings (thesis)", fixed, t_fixed, peer_fixed, t_peer_fixed,
         "GTSAM, same fixed headings"),
        ("Gauss-Newton (ours)", gn, t_gn, peer, t_peer, "GTSAM Pose2"),
        ("5 phases, thesis projection", final, t_inc, peer, t_peer, "GTSAM Pose2"),
    ]
    for label, sol, t, ref, t_ref, peer_label in cases:
        ours = sol.poses[POSE].to_numpy(dtype=float)
        rows.append(dict(network="Table 6.6 (forest)", links=len(obs),
                         solver=f"{label} vs {peer_label}", seconds=t, gtsam_seconds=t_ref,
                         **dict(zip(("dxy_mm", "dz_mm", "dheading_deg"),
                                    np.array(_diff(ours, ref)) * [1e3, 1e3, 1], strict=True)),
                         rms_truth_m=np.nan))
    return pd.DataFrame(rows)


def to_markdown(table: pd.DataFrame, command: str) -> str:
    lines = [
        "## Optimal-map solver vs GTSAM (`benchmarks/bench_solver.py`)",
        "",
        f"`{command}` on {platform.machine()} / {os.cpu_count()} cores shared, BLAS 1 thread, "
        f"median of repeats, {time.strftime('%Y-%m-%d')}. Differences are the largest over all "
        "scans between our poses and the GTSAM peer's.",
        "",
        "| network | links | our solver (vs peer) | ours (ms) | GTSAM (ms) | max d_xy (mm) "
        "| max d_z (mm) | max d_heading (deg) | RMS xy vs truth (m) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in table.itertuples():
        truth = "" if np.isnan(r.rms_truth_m) else f"{r.rms_truth_m:.3f}"
        lines.append(f"| {r.network} | {r.links} | {r.solver} | {1e3 * r.seconds:.1f} | "
                     f"{1e3 * r.gtsam_seconds:.1f} | {r.dxy_mm:.4f} | {r.dz_mm:.4f} | "
                     f"{r.dheading_deg:.5f} | {truth} |")
    lines += [
        "",
        "Like with like: GTSAM solves the nonlinear problem (Pose2 + 1-D z factors). The thesis "
        "projects each observation with the reference's heading of the previous phase; iterated "
        "to convergence (\"projection, converged\", covariance rotated exactly) it still differs "
        "from the maximum-likelihood map by centimetres, because its linearisation leaves out the "
        "dependence of the projected observation on the reference's heading (the lever arm), so "
        "headings are estimated from heading observations alone. Our `linearisation="
        "\"gauss_newton\"` option includes that term and agrees with GTSAM to well under 1 mm "
        "(the rest is Pose2's log map at second order). With the final headings fixed as the "
        "linearisation point, the thesis's linear problem solved by Eq. 3.20 and by GTSAM agree "
        "to numerical precision.",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="30,100", help="simulated network sizes (scans)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-write", action="store_true", help="do not update results.md")
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",") if s]
    table = run(sizes, args.seed, args.repeats)
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    if not args.no_write:
        cmd = "python benchmarks/bench_solver.py" + (f" --sizes {args.sizes}"
                                                     if args.sizes != "30,100" else "")
        write_section("solver", to_markdown(table, cmd))
        print(f"wrote {RESULTS}")
    return table


if __name__ == "__main__":
    main()
