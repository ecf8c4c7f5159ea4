"""Registering every candidate pair and judging each result (spec 6.5-6.7, 8.6).

:func:`register_candidates` runs :func:`~forestmap_assets.core.registration.register.register_pair`
for
every candidate (in parallel worker processes) and returns the ``registrations.csv`` table plus
every level's surviving cells and the secondary hypotheses. :func:`judge` decides whether a
result may become an observation of the optimal map (inferred rules, all parameters):

* ``failed``: the search could not run (empty submap, ...);
* ``rejected``: too few matched points (``min_matched_points``), the peak on the edge of the
  search box (the true maximum may lie outside), or ambiguous: a secondary hypothesis whose
  score is within ``ambiguity_margin`` log-likelihood units of the best (thesis 5.3.3, spec 8.6);
* ``accepted`` otherwise.

Observation sigmas (beyond the thesis, calibrated; :func:`observation_sigmas`). The cell-cloud
sigma of JP eq. (6) with linear weights ``s - s_floor`` measures how far the branch and bound
could not prune, not the likelihood: on simulated campaigns it was ~3x the true error (normalised
pair and pose errors with RMS 0.2-0.5 at quarter and half resolution), while the thesis warns it can
also underestimate once the cloud shrinks to a few cells (spec 6.5). forestmap therefore takes
the sigma from the *tempered likelihood* over the same final cloud (inferred): weights
``exp((s - s*) / T)`` over the final-level cells within ``hypothesis_separation_m`` of the peak
(the coarse-to-fine history's last level, ``levels``). ``T = 1`` is Olson's likelihood taken
literally, which treats every sub-map point as an independent measurement; but sub-map points
lie every 0.05 m along fitted feature centre lines and all points of one line share its fit
error, so the log-likelihood over-counts the evidence by about the number of points per fitted
feature, and ``T`` = ``likelihood_temperature`` divides it back (default 40: a 2 m cylinder
segment at 0.05 m spacing). The heading has its own ``heading_temperature`` (default 6): a
shared error of one centre line shifts the translation directly but the heading only through
its lever arm among many features, so the heading evidence is over-counted less. Both are
calibrated on simulated 6-scan no-prior campaigns (quarter resolution, 5 seeds;
benchmarks/results.md "mapping" re-derives the sigmas of the same registrations for several
temperatures): T = 10 gives pair ``error / sigma`` RMS 1.6-1.7 in x and y and pose RMS 2.3-2.5;
T = 40 gives pairs 0.85-0.92 and poses 1.2-1.4 (pair errors sharing a scan are correlated,
which the network solution cannot know, so poses stay a little over-confident); heading with
T = 40 would be conservative (0.45), with 6 it is 0.95 (pairs) / 0.85 (poses). No temperature
from 10 to 60 made the link tests reject a correct registration there. The weighted standard
deviation is combined with the final cell's quantisation sigma (``step / sqrt(12)``) and
multiplied by ``sigma_scale``. ``likelihood_temperature=None`` keeps the JP eq. (6) cloud
sigma. z: the dz taken from the ground (:mod:`.ground_z`) keeps its standard error of the
median, floored at ``ground_min_sd_m`` (2 mm instead of the module's 5 mm, which made the
normalised z errors 0.25; with 1 mm pose z came out at RMS 1.6, with 2 mm pairs 0.86 and poses
1.16); a feature-based dz (no ground agreement) has its JP eq. (6) sigma combined in quadrature
with ``feature_z_sd_m`` (0.15 m, inferred: near-vertical trunks barely constrain z, the
thesis's cloud gave 0.29 m for ST and RT, Th. 6.4, and simulated feature-based dz err by
0.16 m RMS while their cloud sigma is 0.02-0.1 m, which made the 8-sigma z test reject correct
links).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import pandas as pd

from forestmap_assets.core.geometry import wrap_deg
from forestmap_assets.core.registration.pair_checks import (
    assess_history,
    assess_pair,
    register_in_box,
)
from forestmap_assets.params import RegistrationParams

REGISTRATION_COLUMNS = [
    "scan", "reference", "dx", "dy", "dz", "dheading_deg", "sd_x", "sd_y", "sd_z", "sd_heading_deg",
    "peak_dx", "peak_dy", "peak_dz", "peak_dheading_deg", "log_score", "n_points", "seconds", "status", "reason",
]
EXTRA_COLUMNS = [
    "matched_points", "matched_stems", "peak_mass_share", "n_hypotheses", "best_rival_gap", "cloud_cells", "confidence",
    "dz_features", "sd_z_features", "z_source",
    "support_m", "weak_direction_deg", "rival_ratio", "rival_separation_m", "rival_dx", "rival_dy",
    "polish_segments", "polish_dheading_deg", "polish_reason",
]


def matched_points(peak_score: float, n_points: int, params: RegistrationParams) -> float:
    """Approximate count of scan points matched at the peak: the score above the all-outlier
    floor divided by the score gain of one perfectly matched point (inferred)."""
    from forestmap_assets.core.registration.score import ScoreModel

    model = ScoreModel.from_params(params)
    return float(max(0.0, (peak_score - model.floor(n_points)) / (model.ln_p0 - model.ln_k1)))


def edge_reason(axis: str) -> str:
    """The rejection reason of a peak on the edge of the search box along ``axis`` (dx, dy, dz,
    dheading)."""
    return f"peak on the edge of the search box in {axis}: the maximum may lie outside"


def judge(result, params: RegistrationParams, centre, half_widths, *, min_matched_points: float = 40.0,
          ambiguity_margin: float = 10.0) -> tuple[str, str, dict]:
    """Status (accepted / rejected / failed), one-line reason and extra figures of one result.

    Besides the rules of the module docstring, a result must match at least
    ``params.min_matched_stems`` distinct features (a single stem fits anywhere along a ring).
    """
    extra = dict.fromkeys(EXTRA_COLUMNS, np.nan)
    if result.status != "ok":
        if (result.reason or "").startswith("ambiguous"):
            return "rejected", result.reason, extra
        return "failed", result.reason or "registration failed", extra
    matched = matched_points(result.peak_score, result.n_points, params)
    hyp = result.hypotheses
    gap = float(result.peak_score - hyp["peak_score"].max()) if len(hyp) else np.inf
    stems = int(getattr(result, "matched_stems", 0))
    extra.update(
        matched_points=round(matched, 1),
        matched_stems=stems,
        peak_mass_share=result.peak_mass_share,
        n_hypotheses=len(hyp),
        best_rival_gap=gap,
        cloud_cells=result.cloud_cells,
        confidence=matched,
    )
    peak = np.asarray(result.peak, dtype=float)
    lo = np.asarray(centre, dtype=float) - np.asarray(half_widths, dtype=float)
    hi = np.asarray(centre, dtype=float) + np.asarray(half_widths, dtype=float)
    step = np.asarray(result.final_step, dtype=float)
    full_circle = half_widths[3] >= 180.0
    axes = [0, 1, 2] if full_circle else [0, 1, 2, 3]
    if matched < min_matched_points:
        return "rejected", f"too little overlap: about {matched:.0f} matched submap points (< {min_matched_points:.0f})", extra
    if stems < params.min_matched_stems:
        return "rejected", f"too little overlap: only {stems} distinct features match (< {params.min_matched_stems})", extra
    for k in axes:
        val = peak[k] if k < 3 else centre[3] + wrap_deg(peak[3] - centre[3])
        if val - lo[k] < 1.01 * step[k] or hi[k] - val < 1.01 * step[k]:
            name = ("dx", "dy", "dz", "dheading")[k]
            return "rejected", edge_reason(name), extra
    if np.isfinite(gap) and gap < ambiguity_margin:
        return "rejected", f"ambiguous: a second hypothesis {hyp['separation_m'].iloc[int(np.argmax(hyp['peak_score'].to_numpy()))]:.2f} m away scores within {gap:.1f} of the best", extra
    return "accepted", "", extra


def judge_in_box(result, params, centre, half_widths, box_heading_deg: float = 0.0, **kwargs):
    """:func:`judge` of a :func:`~.pair_checks.register_in_box` result: with turned box
    axes the box-edge test runs in the box's own frame (peak, centre and cell steps before they
    were turned back)."""
    import copy

    frame = getattr(result, "box_frame", None)
    if not box_heading_deg or frame is None or not result.ok:
        return judge(result, params, centre, half_widths, **kwargs)
    boxed = copy.copy(result)
    boxed.peak, boxed.final_step = frame["peak"], frame["final_step"]
    return judge(boxed, params, frame["centre"], half_widths, **kwargs)


def tempered_cloud_sigma(levels: pd.DataFrame, peak, d_bar_m: float, temperature, *,
                         separation_m: float = 0.3) -> np.ndarray:
    """Standard deviation (dx, dy, dz, dheading_deg) of the final cell cloud around ``peak``
    weighted by the tempered likelihood ``exp((s - s*) / temperature)`` (module docstring,
    inferred; ``temperature`` one value or one per axis). Cells of the last level of ``levels`` (columns ``level, dx, dy, dz, dh_deg,
    score``) farther than ``separation_m`` from the peak (heading as arc at ``d_bar_m``) belong to
    other hypotheses and are left out. NaN when ``levels`` is empty."""
    if levels is None or len(levels) == 0:
        return np.full(4, np.nan)
    last = levels[levels["level"] == levels["level"].max()]
    p = last[["dx", "dy", "dz", "dh_deg"]].to_numpy(dtype=float).copy()
    s = last["score"].to_numpy(dtype=float)
    peak = np.asarray(peak, dtype=float)
    p[:, 3] = peak[3] + wrap_deg(p[:, 3] - peak[3])
    off = p - peak
    off[:, 3] = np.radians(off[:, 3]) * max(float(d_bar_m), 0.0) if np.isfinite(d_bar_m) else 0.0
    near = np.linalg.norm(off, axis=1) <= separation_m
    if not near.any():
        return np.full(4, np.nan)
    p, s = p[near], s[near]
    t = np.broadcast_to(np.asarray(temperature, dtype=float), (4,))
    w = np.exp((s - s.max())[:, None] / t)  # (cells, axes)
    mean = (w * p).sum(0) / w.sum(0)
    return np.sqrt((w * (p - mean) ** 2).sum(0) / w.sum(0))


def observation_sigmas(result, sigma_scale: float = 1.0, likelihood_temperature: float | None = 40.0,
                       separation_m: float = 0.3, tempered_axes=(0, 1, 3),
                       heading_temperature: float | None = 6.0) -> np.ndarray:
    """Sigmas (dx, dy, dz, dheading_deg) of an accepted registration (module docstring): on
    ``tempered_axes`` the tempered-likelihood cloud sigma (the JP eq. 6 cloud sigma when
    ``likelihood_temperature`` is None or the result kept no levels), elsewhere the JP eq. 6
    cloud sigma, combined with the final cell's quantisation sigma ``step / sqrt(12)``, times
    ``sigma_scale``. ``heading_temperature`` (None: ``likelihood_temperature``) tempers the
    heading axis (module docstring). z keeps the JP eq. 6 sigma by default (inferred): near-vertical trunks
    leave the likelihood nearly flat in z and its feature-based peak errs by ~0.15 m, which the
    wide linear-weight cloud covers and a tempered one does not."""
    sigma = np.asarray(result.sigma, dtype=float)
    if likelihood_temperature is not None:
        th = likelihood_temperature if heading_temperature is None else heading_temperature
        tempered = tempered_cloud_sigma(getattr(result, "levels", None), result.peak,
                                        getattr(result, "d_bar_m", np.nan),
                                        [likelihood_temperature] * 3 + [th],
                                        separation_m=separation_m)
        use = np.isin(np.arange(4), list(tempered_axes)) & np.isfinite(tempered)
        sigma = np.where(use, tempered, sigma)
    sigma = np.nan_to_num(sigma)
    step = np.nan_to_num(np.asarray(result.final_step, dtype=float))
    return sigma_scale * np.sqrt(sigma**2 + step**2 / 12.0)


def _register_one(args):

    scan_pts, ref_pts, centre, half, params, box_heading = args
    t0 = time.perf_counter()
    result = register_in_box(scan_pts, ref_pts, centre, half, params, box_heading_deg=box_heading,
                             method=params.method, weight=params.weight,
                             s_floor=params.s_floor, adjacency=params.adjacency,
                             hypothesis_separation_m=params.hypothesis_separation_m,
                             max_cells=params.max_cells,
                             # the lattice bound needs the fast evaluator
                             bound=params.bound if params.method == "fast" else "cell",
                             lattice_margin=params.lattice_margin,
                             cloud_margin=params.cloud_margin)
    result.seconds = time.perf_counter() - t0
    return result


def ground_z_box(centre, half, params: RegistrationParams, elevation, scan: str, reference: str,
                 cell_m: float) -> tuple[tuple, tuple]:
    """A screened pair's box with z centred on the ground grids' dz at the screening motion and
    half-width ``params.screen_ground_hz_m`` (or 3 of its sd; at most the original half-width);
    the box unchanged without grids, without a ground estimate, or with the option off
    (inferred, issue 16; a pair that fails is searched again in the no-prior box). A ground dz
    outside the original z range (``z_m`` about 0, the thesis' 1.25 m) moves the range there at
    its full width: on a slope two scans 19 m apart stood 1.41 m apart in height (Sylva's survey
    3), the search about 0 ended on the range's edge and was rejected twice, and the stems'
    features alone put the dz of such a pair up to 0.25 m from the ground's."""
    hz = params.screen_ground_hz_m
    if hz is None or not elevation or elevation.get(scan) is None or elevation.get(reference) is None:
        return centre, half
    from forestmap_assets.core.registration.ground_z import ground_dz

    g = ground_dz(elevation[scan], elevation[reference], (centre[0], centre[1], 0.0, centre[3]), cell_m)
    if not g.ok:
        return centre, half
    if abs(g.dz - centre[2]) > half[2]:
        return (centre[0], centre[1], g.dz, centre[3]), half
    new_hz = min(half[2], max(hz, 3 * g.sd))
    return (centre[0], centre[1], g.dz, centre[3]), (half[0], half[1], new_hz, half[3])


def _ground_moved_job(job, result, params: RegistrationParams, elevation, candidate, cell_m: float,
                      **judging):
    """The search again of a pair whose peak lay on the edge of its dz range (inferred, issue
    16): the range moved to the ground grids' dz at the peak, at least ``params.z_m`` wide,
    about the peak's x, y and heading in the screening box (``params.screen_box``; the stems fix
    those and hardly z). None without a ground dz or where the range would not change. The
    thesis' range of +-1.25 m about 0 (or about an a priori dz) misses scans on a slope, and a
    screened pair's narrow range about the ground's dz can be too narrow for the features' dz
    (Sylva's 8-scan survey 2: ground 1.20 m, features 1.41 m against a range of 1.20 +- 0.3 m,
    the truth 1.30 m); the ground's dz replaces the features' afterwards where they agree."""
    if not elevation or elevation.get(candidate.scan) is None or elevation.get(candidate.reference) is None:
        return None
    _, reason, _ = judge_in_box(result, params, job[2], job[3], job[5], **judging)
    if reason != edge_reason("dz"):
        return None
    from forestmap_assets.core.registration.ground_z import ground_dz

    peak = np.asarray(result.peak, dtype=float)
    g = ground_dz(elevation[candidate.scan], elevation[candidate.reference], peak, cell_m)
    centre, half = job[2], job[3]
    hz = max(half[2], params.z_m)
    if not g.ok or (abs(g.dz - centre[2]) < params.final_cell_m and hz <= half[2]):
        return None
    bx, bh = params.screen_box
    return (job[0], job[1], (peak[0], peak[1], g.dz, peak[3]),
            (min(bx, half[0]), min(bx, half[1]), hz, min(bh, half[3])), job[4], 0.0)


def register_candidates(
    candidates: pd.DataFrame,
    submaps: dict[str, pd.DataFrame],
    params: RegistrationParams,
    *,
    sigma_scale: float = 1.0,
    likelihood_temperature: float | None = 40.0,
    heading_temperature: float | None = 6.0,
    ground_min_sd_m: float = 0.002,
    feature_z_sd_m: float = 0.15,
    min_matched_points: float = 40.0,
    ambiguity_margin: float = 10.0,
    elevation: dict[str, pd.DataFrame] | None = None,
    elevation_cell_m: float = 0.1,
    progress: Callable[[str], None] | None = None,
) -> dict[str, pd.DataFrame]:
    """Register every candidate pair; return ``registrations``, ``levels`` and ``hypotheses``.

    Sigmas: :func:`observation_sigmas` with ``sigma_scale`` and ``likelihood_temperature``
    (module docstring).

    With ``params.z_from_ground`` and the scans' lowest-hit ``elevation`` grids (their
    ground-like cells, ``params.ground_block_m`` / ``ground_tol_m``), an accepted
    registration's dz and its sigma come from the ground (:mod:`.ground_z`) when the ground
    agrees with the feature-based dz within ``3 sd + 0.1 m`` (``sd``: the feature dz's sd, its
    cloud sd combined with ``feature_z_sd_m``); the feature-based values are
    kept in ``dz_features``/``sd_z_features`` and ``z_source`` says which was used.
    """
    if elevation:  # the ground-like cells only (ground_z.ground_cells)
        from forestmap_assets.core.registration.ground_z import ground_cells

        elevation = {k: ground_cells(g, elevation_cell_m, params.ground_block_m, params.ground_tol_m)
                     for k, g in elevation.items()}
    jobs = []
    for c in candidates.itertuples(index=False):
        scan = submaps.get(c.scan)
        ref = submaps.get(c.reference)
        pts = lambda df: np.zeros((0, 3)) if df is None or df.empty else df[["x", "y", "z"]].to_numpy(float)  # noqa: E731
        centre, half = (c.cx, c.cy, c.cz, c.cheading_deg), (c.hx, c.hy, c.hz, c.hheading_deg)
        if getattr(c, "source", "") == "screened":
            centre, half = ground_z_box(centre, half, params, elevation, c.scan, c.reference, elevation_cell_m)
        jobs.append((pts(scan), pts(ref), centre, half, params, float(getattr(c, "box_heading_deg", 0.0) or 0.0)))
    # one pair after another: the kernels already use every core (numba threads), and parallel
    # work across pairs belongs to the orchestration (partitions), never a pool inside an asset
    results = []
    for k, job in enumerate(jobs):
        results.append(_register_one(job))
        moved = _ground_moved_job(job, results[-1], params, elevation, candidates.iloc[k], elevation_cell_m,
                                  min_matched_points=min_matched_points, ambiguity_margin=ambiguity_margin)
        if moved is not None:  # the dz range moved to the ground's: searched again there
            first = results[-1].seconds
            jobs[k], results[-1] = moved, _register_one(moved)
            results[-1].seconds += first
        if progress:
            progress(f"pair {k + 1}/{len(jobs)}: {candidates.iloc[k]['scan']}-{candidates.iloc[k]['reference']} {results[-1].seconds:.1f} s")

    rows, levels, hyps = [], [], []
    for c, job, res in zip(candidates.itertuples(index=False), jobs, results, strict=True):
        status, reason, extra = judge_in_box(res, params, job[2], job[3], job[5], min_matched_points=min_matched_points,
                                             ambiguity_margin=ambiguity_margin)
        if status == "accepted" and (params.min_support_m > 0 or params.max_rival_ratio is not None):
            why, figures = assess_pair(
                submaps[c.scan], submaps[c.reference], res.peak, job[2], job[3], params,
                box_heading_deg=job[5], min_support_m=params.min_support_m,
                max_rival_ratio=np.inf if params.max_rival_ratio is None else params.max_rival_ratio,
                exclusion_m=params.rival_exclusion_m, match_m=max(3 * params.sigma_m, params.final_cell_m))
            extra.update(figures)
            if why:
                status, reason = "rejected", why
        hyp = res.hypotheses.assign(source="branch and bound") if len(res.hypotheses) else None
        if res.status == "ok" and params.history_max_cell_m is not None:
            why, row = assess_history(res.levels, res.peak, res.d_bar_m,
                                      separation_m=params.rival_exclusion_m,
                                      max_cell_m=params.history_max_cell_m)
            if row is not None:  # the finest late leader is a secondary hypothesis (spec 6.5, 8.6)
                hyp = pd.concat([h for h in (hyp, pd.DataFrame([row])) if h is not None],
                                ignore_index=True)
                extra["n_hypotheses"] = len(hyp)
                extra["peak_mass_share"] = min(extra["peak_mass_share"], 1.0 - row["mass_share"])
                if status == "accepted":
                    status, reason = "rejected", why
        sd = (observation_sigmas(res, sigma_scale, likelihood_temperature,
                                 params.hypothesis_separation_m,
                                 heading_temperature=heading_temperature)
              if res.status == "ok" else np.full(4, np.nan))
        centre = np.asarray(res.centre, dtype=float).copy()
        if res.status == "ok":
            sd[2] = np.hypot(sd[2], feature_z_sd_m)
        extra.update(dz_features=centre[2], sd_z_features=sd[2], z_source="features")
        if status == "accepted" and params.z_from_ground and elevation:
            from forestmap_assets.core.registration.ground_z import ground_dz

            g = ground_dz(elevation.get(c.scan), elevation.get(c.reference), centre, elevation_cell_m,
                          min_sd_m=ground_min_sd_m)
            # the feature dz's own sd (cloud sd with feature_z_sd_m in quadrature): the cloud
            # alone shrinks to a few cells with the lattice bound and refused a correct ground dz
            gate = sd[2]
            if g.ok and abs(g.dz - centre[2]) <= 3 * gate + 0.1:
                centre[2], sd[2] = g.dz, g.sd
                extra["z_source"] = f"ground ({g.n_cells} cells)"
        if status == "accepted" and params.stem_polish:
            from forestmap_assets.core.registration.stem_polish import polish_pose

            done = polish_pose(submaps[c.scan], submaps[c.reference], centre, sd,
                               match_m=max(3 * params.sigma_m, params.final_cell_m),
                               sd_scale=params.polish_sd_scale, max_sigmas=params.polish_max_sigmas,
                               huber_k=params.polish_huber_k)
            extra.update(polish_segments=done.segments, polish_reason=done.reason,
                         polish_dheading_deg=float(wrap_deg(done.pose[3] - centre[3])))
            if not done.reason:
                centre[[0, 1, 3]], sd[3] = done.pose[[0, 1, 3]], done.sd_heading_deg
        peak = np.asarray(res.peak, dtype=float)
        rows.append({
            "scan": c.scan, "reference": c.reference,
            "dx": centre[0], "dy": centre[1], "dz": centre[2], "dheading_deg": wrap_deg(centre[3]) if np.isfinite(centre[3]) else np.nan,
            "sd_x": sd[0], "sd_y": sd[1], "sd_z": sd[2], "sd_heading_deg": sd[3],
            "peak_dx": peak[0], "peak_dy": peak[1], "peak_dz": peak[2],
            "peak_dheading_deg": wrap_deg(peak[3]) if np.isfinite(peak[3]) else np.nan,
            "log_score": res.peak_score, "n_points": res.n_points, "seconds": round(res.seconds, 3),
            "status": status, "reason": reason, **extra,
        })
        if len(res.levels):
            levels.append(res.levels.assign(scan=c.scan, reference=c.reference))
        if hyp is not None:
            hyps.append(hyp.assign(scan=c.scan, reference=c.reference))
    regs = pd.DataFrame(rows, columns=REGISTRATION_COLUMNS + EXTRA_COLUMNS)
    return {
        "registrations": regs,
        "levels": pd.concat(levels, ignore_index=True) if levels else pd.DataFrame(columns=["scan", "reference"]),
        "hypotheses": pd.concat(hyps, ignore_index=True) if hyps else pd.DataFrame(columns=["scan", "reference"]),
    }
