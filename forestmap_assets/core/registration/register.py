"""Globally optimal 4-DoF registration of two sub-maps by branch and bound (spec 6, Th. ch. 5).

:func:`register_pair` finds the pose ``T(b) = R_z(dh) b + (dx, dy, dz)`` of map B (the scan) in the
levelled frame of map A (the reference) that maximises Olson's log-likelihood
``sum_i ln p(D_i(T))`` (spec 6.3, :mod:`.score`) over the final lattice of a search box centred on
the a priori pose (spec 6.4, :mod:`.search_lattice`), **exactly** (same answer as an exhaustive
evaluation of every lattice point, :func:`~.branch_and_bound.exhaustive_search`). Two evaluators,
same lattice maximum: ``method='fast'`` (default, :mod:`.fast_search`) and ``method='thesis'``
(the plain algorithm, :mod:`.branch_and_bound`).

* **Cell cloud (spec 6.5, JP eq. 6).** The best cell's connected cloud (:mod:`.cell_clouds`) gives
  the weighted centre and standard deviation with ``l = s - s_floor`` (``s_floor = n ln k1``) or
  ``l = exp(s - s_max)``. Other clouds whose peak lies farther than ``hypothesis_separation_m``
  from the best peak are *secondary hypotheses*.
* **Peak-mass share (spec 6.7, Olson).** ``share = M_peak / (M_final + M_pruned)`` with masses in
  units of final-cell volume relative to the best score: ``M_peak = sum_{k in best cloud}
  exp(s_k - s*)``, ``M_final`` the same over every surviving final cell, and ``M_pruned =
  sum_{pruned cells c} n_c exp(s_c - s*)`` (``n_c`` final cells in ``c``, ``s_c`` the score at
  its evaluation point; inferred: with a few thousand points the per-point bounds exceed the
  scores by hundreds of log units, so a bound-weighted mass would say nothing). The thesis
  evaluator keeps the bound-weighted, conservative form."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from forestmap_assets.core.geometry import wrap_deg
from forestmap_assets.core.registration.branch_and_bound import KdEvaluator, _branch_and_bound
from forestmap_assets.core.registration.cell_clouds import (
    cloud_statistics,
    lattice_components,
    matched_stems,
)
from forestmap_assets.core.registration.fast_search import (
    _fast_search,
    grow_cloud,
    reference_field,
)
from forestmap_assets.core.registration.score import ScoreModel
from forestmap_assets.core.registration.search_lattice import SearchLattice, to_output_pose

LEVEL_COLUMNS = (
    "level",
    "cell_m",
    "cell_x_m",
    "cell_y_m",
    "cell_z_m",
    "cell_heading_deg",
    "dx",
    "dy",
    "dz",
    "dh_deg",
    "score",
    "bound",
)


HYPOTHESIS_COLUMNS = (
    "peak_dx",
    "peak_dy",
    "peak_dz",
    "peak_dh_deg",
    "peak_score",
    "dx",
    "dy",
    "dz",
    "dh_deg",
    "sd_x",
    "sd_y",
    "sd_z",
    "sd_heading_deg",
    "n_cells",
    "mass_share",
    "separation_m",
)


@dataclass
class RegistrationResult:
    """Outcome of :func:`register_pair` (spec 6.5, DESIGN.md 4 ``registrations.csv``).

    ``peak`` is the best final cell's centre (dx, dy, dz, dh_deg) and ``peak_score`` its
    log-likelihood; ``centre``/``sigma`` the weighted mean and standard deviation of its connected
    cloud (JP eq. 6); ``levels`` every level's surviving cells; ``hypotheses`` the secondary clouds;
    ``matched_stems`` the number of distinct stems (blobs of matched points, :func:`matched_stems`)
    that support the peak.
    """

    status: str
    reason: str = ""
    peak: tuple[float, float, float, float] = (np.nan,) * 4
    peak_score: float = np.nan
    centre: tuple[float, float, float, float] = (np.nan,) * 4
    sigma: tuple[float, float, float, float] = (np.nan,) * 4
    cloud_cells: int = 0
    peak_mass_share: float = np.nan
    n_points: int = 0
    n_reference: int = 0
    seconds: float = 0.0
    n_cells_evaluated: int = 0
    final_step: tuple[float, float, float, float] = (np.nan,) * 4
    d_bar_m: float = np.nan
    method: str = "fast"
    matched_stems: int = 0
    levels: pd.DataFrame = field(default_factory=lambda: pd.DataFrame(columns=list(LEVEL_COLUMNS)))
    hypotheses: pd.DataFrame = field(
        default_factory=lambda: pd.DataFrame(columns=list(HYPOTHESIS_COLUMNS))
    )

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def _levels_table(lattice: SearchLattice, level_rows) -> pd.DataFrame:
    parts = []
    for li, size, idx, s, b in level_rows:
        edge = size * lattice.step
        pose = to_output_pose(lattice.pose(idx))
        parts.append(
            pd.DataFrame(
                {
                    "level": li,
                    "cell_m": float(np.max(edge * lattice.metric_scale)),
                    "cell_x_m": edge[0],
                    "cell_y_m": edge[1],
                    "cell_z_m": edge[2],
                    "cell_heading_deg": float(np.degrees(edge[3])),
                    "dx": pose[:, 0],
                    "dy": pose[:, 1],
                    "dz": pose[:, 2],
                    "dh_deg": pose[:, 3],
                    "score": s,
                    "bound": b,
                }
            )
        )
    if not parts:
        return pd.DataFrame(columns=list(LEVEL_COLUMNS))
    return pd.concat(parts, ignore_index=True)


def register_pair(
    scan_points: np.ndarray,
    reference_points: np.ndarray,
    centre=(0.0, 0.0, 0.0, 0.0),
    half_widths=None,
    params=None,
    *,
    method: str = "fast",
    weight: str = "linear",
    s_floor: float | None = None,
    adjacency: int = 80,
    hypothesis_separation_m: float = 0.3,
    beam_width: int = 0,
    keep_levels: bool = True,
    seeds=None,
    vote: bool = True,
    tight_bound: bool = True,
    max_cells: int = 60_000,
    bound: str | None = None,
    lattice_margin: float = 10.0,
    cloud_margin: float = 240.0,
    heading_split_scale: float = 2.0,
) -> RegistrationResult:
    """Globally optimal pose of ``scan_points`` (map B) in the frame of ``reference_points``
    (map A) inside the box ``centre +- half_widths`` (dx, dy, dz m, dh deg), spec 6.3-6.7.

    ``params`` is a :class:`~forestmap_assets.params.RegistrationParams` (sigma, inlier share,
    outlier distance, final cell; its xy/z/heading half-widths are used when ``half_widths`` is
    None). ``weight`` 'linear' (``l = s - s_floor``, default ``s_floor = n ln k1``) or 'exp'
    (``l = exp(s - s_max)``) selects the cloud weights of JP eq. 6; ``adjacency`` 80 or 8;
    ``hypothesis_separation_m`` (inferred, metric with heading as arc at ``d_bar``) is the
    distance beyond which a disconnected cloud's peak is a secondary hypothesis. ``seeds``
    (poses, heading deg), ``vote`` (stem-to-stem voting, :mod:`.stem_voting`) and
    ``beam_width`` (a narrow first pass, thesis method only) only help find a good score early;
    ``tight_bound`` enables the per-axis bound at fine levels (speed only). With more than
    ``max_cells`` surviving cells at a level (fast method; an ambiguous pair) the search stops
    with ``status='failed'`` and an "ambiguous" reason. ``method='thesis'``
    is the plain k-d tree algorithm (small problems). Never raises on empty input: returns
    ``status='failed'`` with a reason.

    ``bound``: 'lattice' (default of the fast method; inferred) or 'cell' (default of the
    thesis method, spec 6.4: each cell bounded over its whole volume). 'lattice' bounds each
    cell over the final-lattice poses inside it (offsets ``-(size // 2)`` to ``size - 1 - size
    // 2`` steps instead of half a step more), which is all the lattice maximum needs; a final
    cell's bound is then its own score. Same lattice maximum, 2-3x faster on forest pairs. Its
    search keeps the cells within ``lattice_margin`` of the best (secondary hypotheses within
    that margin are found exactly, which is the judge's ambiguity rule); the best cell's cloud
    is then grown on the final lattice to every connected cell scoring within ``cloud_margin``
    of the best (:func:`grow_cloud`; default 240 = 6x the likelihood temperature 40 of
    :mod:`.pair_registrations`, so the tempered weights are covered down to ``e^-6``), the cloud
    the JP eq. 6 centre/sigma and the tempered sigmas are taken from.
    ``heading_split_scale`` (inferred, speed only; 1 is the thesis's rule) multiplies the
    heading arc when the longest cell dimension is chosen (:meth:`SearchLattice.schedule`).
    """
    from forestmap_assets.params import RegistrationParams

    t0 = time.perf_counter()
    params = params or RegistrationParams()
    if half_widths is None:
        half_widths = (params.xy_m, params.xy_m, params.z_m, params.heading_deg)
    scan = np.asarray(scan_points, dtype=float).reshape(-1, 3)
    ref = np.asarray(reference_points, dtype=float).reshape(-1, 3)
    scan = scan[np.isfinite(scan).all(1)]
    ref = ref[np.isfinite(ref).all(1)]
    base = dict(n_points=len(scan), n_reference=len(ref), method=method)
    if len(scan) == 0 or len(ref) == 0:
        which = "scan" if len(scan) == 0 else "reference"
        return RegistrationResult(
            status="failed",
            reason=f"{which} sub-map has no registration points",
            seconds=time.perf_counter() - t0,
            **base,
        )
    if method not in ("fast", "thesis"):
        raise ValueError(f"method: expected 'fast' or 'thesis', got {method!r}")
    if bound is None:
        bound = "lattice" if method == "fast" else "cell"
    if bound not in ("cell", "lattice") or (bound == "lattice" and method != "fast"):
        raise ValueError(f"bound: expected 'cell' or, with method='fast', 'lattice'; got {bound!r}")
    model = ScoreModel.from_params(params)
    d_bar = float(np.mean(np.hypot(scan[:, 0], scan[:, 1])))
    lattice = SearchLattice.build(centre, half_widths, params.final_cell_m, d_bar)
    seed_rad = None
    if seeds is not None and len(seeds):
        seed_rad = np.array(seeds, dtype=float).reshape(-1, 4)
        seed_rad[:, 3] = np.radians(seed_rad[:, 3])
    if method == "fast":
        from forestmap_assets.core.registration.stem_voting import vote_alignments

        field = reference_field(ref, model)
        starts = vote_alignments(scan, ref, centre, half_widths) if vote else np.zeros((0, 4))
        starts[:, 3] = np.radians(starts[:, 3])
        if seed_rad is not None:
            starts = np.vstack([seed_rad, starts])
        lat = bound == "lattice"
        out = _fast_search(
            scan,
            ref,
            lattice,
            model,
            field,
            keep_levels=keep_levels,
            starts=starts,
            tight=tight_bound,
            max_cells=max_cells,
            lattice_bound=lat,
            margin=float(lattice_margin) if lat else 0.0,
            heading_scale=heading_split_scale,
        )
    else:
        out = _branch_and_bound(
            scan,
            lattice,
            KdEvaluator(ref, model),
            beam_width=beam_width,
            keep_levels=keep_levels,
            seeds=seed_rad,
            ln_k1=model.ln_k1,
            tree=cKDTree(ref),
        )

    if "aborted" in out:
        return RegistrationResult(
            status="failed",
            reason=out["aborted"],
            seconds=time.perf_counter() - t0,
            d_bar_m=d_bar,
            **base,
        )
    cells, scores = out["cells"], out["scores"]
    if method == "fast" and bound == "lattice" and cloud_margin > lattice_margin:
        # every surviving cloud grown (fragments of one alignment, split by the sampling ripple
        # in z, join as the cell bound's clouds do)
        add_c, add_s = grow_cloud(
            out,
            field,
            np.ascontiguousarray(scan),
            lattice,
            cells,
            cells,
            adjacency,
            float(cloud_margin),
            max_cells,
        )
        cells, scores = np.concatenate([cells, add_c]), np.concatenate([scores, add_s])
    n_comp, label = lattice_components(cells, lattice.n, lattice.wrap, adjacency)
    ib = int(np.argmax(scores))
    s_star = float(scores[ib])
    poses = to_output_pose(lattice.pose(cells))
    floor = model.floor(len(scan)) if s_floor is None else float(s_floor)
    if weight == "linear":
        w = scores - floor
    elif weight == "exp":
        w = np.exp(scores - s_star)
    else:
        raise ValueError(f"weight: expected 'linear' or 'exp', got {weight!r}")
    mass = np.exp(scores - s_star)
    pruned = np.array(out["pruned_lse"], dtype=float)
    m_pruned = float(np.sum(np.exp(pruned[np.isfinite(pruned)] - s_star)))
    m_total = float(mass.sum()) + m_pruned
    peak = poses[ib]

    rows = []
    for c in range(n_comp):
        sel = label == c
        j = np.flatnonzero(sel)[int(np.argmax(scores[sel]))]
        mean, sd = cloud_statistics(poses[sel], w[sel], poses[j, 3])
        sep_vec = poses[j] - peak
        sep_vec[3] = np.radians(wrap_deg(sep_vec[3])) * d_bar
        rows.append(
            dict(
                component=c,
                peak_dx=poses[j, 0],
                peak_dy=poses[j, 1],
                peak_dz=poses[j, 2],
                peak_dh_deg=poses[j, 3],
                peak_score=scores[j],
                dx=mean[0],
                dy=mean[1],
                dz=mean[2],
                dh_deg=mean[3],
                sd_x=sd[0],
                sd_y=sd[1],
                sd_z=sd[2],
                sd_heading_deg=sd[3],
                n_cells=int(sel.sum()),
                mass_share=float(mass[sel].sum() / m_total),
                separation_m=float(np.linalg.norm(sep_vec)),
            )
        )
    clouds = pd.DataFrame(rows)
    main = clouds[clouds["component"] == label[ib]].iloc[0]
    hyp = clouds[
        (clouds["component"] != label[ib]) & (clouds["separation_m"] > hypothesis_separation_m)
    ]
    hyp = hyp.sort_values("peak_score", ascending=False)[list(HYPOTHESIS_COLUMNS)].reset_index(
        drop=True
    )
    step = lattice.step.copy()
    step[3] = np.degrees(step[3])
    return RegistrationResult(
        status="ok",
        peak=tuple(float(v) for v in peak),
        peak_score=s_star,
        centre=tuple(float(main[c]) for c in ("dx", "dy", "dz", "dh_deg")),
        sigma=tuple(float(main[c]) for c in ("sd_x", "sd_y", "sd_z", "sd_heading_deg")),
        cloud_cells=int(main["n_cells"]),
        peak_mass_share=float(main["mass_share"]),
        seconds=time.perf_counter() - t0,
        n_cells_evaluated=int(out["n_eval"]),
        final_step=tuple(float(v) for v in step),
        d_bar_m=d_bar,
        matched_stems=matched_stems(scan, ref, peak),
        levels=_levels_table(lattice, out["level_rows"])
        if keep_levels
        else RegistrationResult("ok").levels,
        hypotheses=hyp,
        **base,
    )
