"""Settings of the stages from Men (2012) (fine registration, occlusion boundaries, exploration)
as plain dataclasses, used by the core and turned into parameter sections by
:mod:`forestmap_assets.params`. Imports nothing of forestmap, so the package may import it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Literal


@dataclass(frozen=True)
class RefineSettings:
    """Settings of the refinement (all inferred; see module doc)."""

    method: str = "auto"  # auto | hicp | icp | point_to_plane | none
    weight: float = 0.05  # hue weight; 0.05 was best on real data (men spec 5.8, Table 5.3)
    hue_offset: bool = True  # remove the median hue difference between the scans first
    plane_polish: bool = True  # finish HICP with robust 4-DoF point-to-plane steps
    scale: str = "isotropic"
    hue_mode: str = "linear"
    max_range_m: float = 20.0
    z_band_m: tuple[float, float] = (-10.0, 1.5)  # relative to each sensor: drops the canopy
    overlap_margin_m: float = 0.5
    data_voxel_m: float = 0.1
    model_voxel_m: float = 0.02
    radius_m: float = 0.2
    box_sigmas: float = 3.0
    max_iterations: int = 100
    normal_k: int = 20
    correlation_m: float = 0.5
    sd_floor_m: float = 0.004
    sd_floor_z_m: float = 0.002
    sd_floor_deg: float = 0.012
    # the ICP-Hessian sigmas are multiplied by this before the floors (refine.py) and in the
    # two-way agreement test (two_way.py)
    sd_inflation: float = 1.8
    min_pairs: int = 200
    min_fit_gain: float = 0.0  # relative: the refined fit must be lower by this share
    # point-to-plane: the number of 4-DoF Gauss-Newton steps, and Open3D's 6-DoF ICP first
    plane_iterations: int = 30
    open3d_start: bool = True
    robust_k: float | None = 4.685  # Tukey's biweight constant (95 % efficiency); None: least squares
    # what decides whether the refined pose is used (core/registration/two_way.py): "fit" = its
    # own fit (both directions agree, overlap kept, residuals lower) inside a trust region of
    # max_shift_m / max_turn_deg; "box" = inside box_sigmas x the branch-and-bound sigma (before)
    guard: str = "fit"
    two_way: bool = True
    # two-way least squares: association radii and Gauss-Newton steps, coarse then fine
    two_way_radii_m: tuple[float, float] = (0.1, 0.05)
    two_way_iterations: tuple[int, int] = (5, 10)
    plane_tol: float = 1e-4  # a Gauss-Newton run stops when its step is below this (m and rad)
    max_shift_m: float = 0.25
    max_turn_deg: float = 0.5
    agree_m: float = 0.01
    agree_deg: float = 0.05
    agree_sigmas: float = 3.0
    min_overlap_kept: float = 0.9
    # the model voxel of the two-way refinement: 5 cm (was 4 cm) keeps 10 % (Sylva) to 25 % (own
    # full resolution) fewer model points; median refinement a pair, own 1.15 / 1.10 -> 0.86 /
    # 0.88 s, rendered 1.00 / 0.93 -> 0.82 / 0.66 s, Sylva 0.57-0.67 -> 0.50-0.61 s; the same
    # accuracy on Sylva, rendered and 100 scans (benchmarks/results.md "refine_time")
    two_way_model_voxel_m: float = 0.05
    # the scanner's beam (a campaign's sensor section sets these): footprint diameter
    # beam_exit_m + beam_divergence_mrad * range, and the share of it a link's sigma takes
    # (x, y, z, heading; two_way.beam_sd)
    beam_exit_m: float = 0.0
    beam_divergence_mrad: float = 0.0
    # a beam diverging by more than this is wide: its mixed pixels are left out of the
    # refinement clouds, and the optimal map widens its scale floor and correlations (mapping)
    wide_beam_min_divergence_mrad: float = 1.0
    # a wide beam's mixed pixels (core/registration/mixed_pixels.py): the points within one
    # footprint radius of a range jump larger than this, on its near side (None: kept). The own
    # simulator's 42 mm + 3 mrad beam, symmetric pairs: max scan error, circular stems 184, 185,
    # 209, 210: 0.92 / 0.65 / 0.42 / 0.48 -> 0.25 / 0.36 / 0.20 / 0.20 cm, links' mean scale
    # +0.24 to +0.53 -> -0.01 to +0.09 mm/m (results.md "wide_symmetric")
    mixed_pixel_jump_m: float | None = 0.3
    # a wide beam's widened silhouettes bias the links more than their Hessian shows. x, y 0.164
    # -> 0.08: the own simulator's scans (3 mrad beam) had x, y error / sd 0.49 / 0.51 (own
    # realistic 14-54, 205 scans), 0.94 / 0.97 with 0.08 (circular 1-4: 0.62 / 0.38 -> 1.13 /
    # 0.70; benchmarks/results.md "beam_share"); z 0.035 -> 0.01: silhouettes widen sideways
    # (z error / sd 0.33 / 0.66 circular / realistic, results.md "scan_offsets")
    beam_sd_share: tuple[float, float, float, float] = (0.08, 0.08, 0.01, 0.11)
    # two-way pairs' normal: the sum of both points' normals (point_to_plane.plane_pairs), also
    # under a wide beam once its mixed pixels are left out (mixed_pixel_jump_m; before, the sum
    # pulled circular stems' scans apart there, results.md "link_sigmas"). The model's normal
    # alone (False) made the wide-beam links of realistic stems short, -0.18 to -0.45 mm/m: own
    # realistic 208-214 max scan error 1.21 / 0.82 / 0.65 / 0.60 / 0.47 / 0.29 / 0.51 -> 0.70 /
    # 0.28 / 0.59 / 0.31 / 0.19 / 0.25 / 0.52 cm, circular 184, 185, 209-212 0.62 / 0.43 / 0.49 /
    # 0.37 / 0.55 / 0.56 -> 0.25 / 0.36 / 0.20 / 0.20 / 0.47 / 0.29 cm (results.md "wide_symmetric")
    symmetric: bool = True
    # with the symmetric pairs, the model-normal objective's pose along the baseline
    # (two_way.objective_spread): the bias of widened silhouettes no residual shows. Scope
    # "link": each link's difference joins its sigma along the baseline; "campaign": the optimal
    # map takes the part common to all links, a scale of the network (mapping.objective_scale_t)
    objective_sd: bool = True
    objective_sd_scope: Literal["link", "campaign"] = "campaign"
    max_data_points: int = 20000  # the data cloud of each scan is thinned to at most this many
    # the two-way sigma: sqrt(H^2 + (d/2)^2 + beam^2) (H: the larger Hessian sd of the two
    # directions, d: their disagreement, beam: two_way.beam_sd) scaled per axis (x, y, z,
    # heading), then floored (m, m, m, deg). Fitted on the links of 3 Sylva surveys and 3 own
    # surveys without a wide beam (scale), then on 8 own surveys with the 3 mrad first-return
    # beam (beam_sd_share); benchmarks/results.md "link_sigmas", "sigmas". x, y 0.8 -> 0.44 once
    # the refined links had become better than that fit (symmetric pairs, stem polish): the
    # scans' error / sd x, y pooled over Sylva 1-5 0.41 / 0.58 -> 0.69 / 1.05; rendered
    # unchanged (floored links, the campaign scale carries them); wide-beam campaigns keep their
    # sigmas through beam_sd_share; benchmarks/results.md "link_scale"
    two_way_sd_scale: tuple[float, float, float, float] = (0.44, 0.44, 0.96, 0.56)
    # the floor: heading 0.005 deg (was 0.003), where the links of scans rendered inside a
    # registered cloud were 1.6 times their floored sd (benchmarks/results.md "render"); z
    # 0.5 -> 0.8 -> 1.0 mm: the floored links were 1.25 (rendered) and 1.08 (Sylva) times it;
    # scans' z error / sd rendered 1, 2, 14, 15 1.22 -> 0.98, Sylva 1, 2, 29-38 1.05 -> 0.94;
    # x, y 1.0 -> 0.7 mm once the voxel thinning's tie no longer shifted each scan along its x
    # axis: the rendered links' errors fell below the floor, and the scans' error / sd x, y over
    # 9 rendered surveys (45 scans) 0.70 / 0.84 -> 0.79 / 0.97, Sylva's 13 0.80 / 0.90 -> 0.82 /
    # 0.92, 120-stem renders 0.55 / 0.49 -> 0.62 / 0.58 (the stored runs' refinement replayed;
    # benchmarks/results.md "session42")
    two_way_sd_floor: tuple[float, float, float, float] = (0.0007, 0.0007, 0.001, 0.005)
    # relative: the refined fit (mean |point-to-plane distance| of both directions at the fine
    # radius) may be this much worse than at the branch-and-bound pose. The least-squares step
    # does not minimise that mean, so a refinement that moved the right way can end up to ~1 %
    # "worse": over Sylva's surveys 1-13 (151 pairs) the 22 pairs held back at 0.5 % lay at
    # 0.5-1.1 % (18, median xy error 3.0 mm branch and bound, 1.6 mm refined) or 2.2-3.3 %
    # (4, 20 m baselines, 3 of them 6-20 mm off); was 0.005 (benchmarks/results.md "fit_loss")
    max_fit_loss: float = 0.015
    # a used two-way refinement's heading: "both" = the inverse-variance mean of the refined and
    # the branch-and-bound headings (their sigmas; the translation kept where the overlap's
    # points were), "refined" = the refinement's alone (before). The raw points fix the
    # translation better, the stems' centres and the ground the heading about as well or better:
    # heading error RMS over the refined links, branch and bound / refined / both, 100-scan
    # campaign 0.0124 / 0.0345 / 0.0130 deg, own full resolution 0.017 / 0.024 / 0.011, Sylva 1-5
    # 0.008 / 0.011 / 0.009, rendered 0.006 / 0.004 / 0.004 (benchmarks/results.md "refine_time")
    heading_from: Literal["both", "refined"] = "both"
    # ... when the two agree within this many sigmas of their difference. Beyond them the
    # refined pose is kept only when it also fits better than the branch and bound's (a coarse
    # heading off by more than its sigma says is what the refinement is for, issue 19); else the
    # refinement is not used (before: always kept). Of 284 refined links on held-out Sylva, own
    # realistic and rendered surveys (sessions 41-45), 6 disagreed beyond 3 sigmas, all on
    # Sylva's clouds, and in all 6 the branch-and-bound heading was the closer (0.0002-0.0026
    # deg off against 0.033-0.153 deg); 5 of them fitted 0.6-1.4 % worse refined. Sylva 168's
    # scan s4 was placed 1.6 cm / 0.15 deg off by two of them (benchmarks/results.md, session 45)
    heading_agree_sigmas: float = 3.0
    # splat radii (m) a refined pair tries taking back (core/registration/splat_widening.py): scans
    # rendered inside a registered cloud have every surface widened by their splats; the one that
    # fits the pair best by splat_min_gain (relative) is taken out and the pair refined again
    splat_candidates_m: tuple[float, ...] = ()
    splat_min_gain: float = 0.1
    # such a pair's z sigma floor (m): this (1/m) times the splat radius squared instead of
    # two_way_sd_floor's 1 mm (0.25 mm for 7 mm splats, 0.72 mm for 12 mm): the links' z errors
    # were 0.13-0.18 mm RMS with 7 mm splats, 0.47 mm with 12 mm (results.md "splat_taken_back")
    splat_sd_z_per_m: float = 5.0

    @property
    def wide_beam(self) -> bool:
        """Whether the campaign's beam diverges by more than ``wide_beam_min_divergence_mrad``."""
        return self.beam_divergence_mrad > self.wide_beam_min_divergence_mrad


Combine = Literal["spacing", "variance", "either", "both"]


@dataclass(frozen=True)
class OcclusionConfig:
    """Parameters of :func:`detect_occlusions` and of the observed-surface voxels derived from
    it (:func:`~forestmap_assets.core.exploration.surface.observed_surface`): thesis thresholds 5 deg / 5 deg (men_spec 3.1.2);
    ``variance_threshold_m`` not stated (0.3 m inferred); surface sampling inferred."""

    alpha_thr_deg: float = 5.0
    beta_thr_deg: float = 5.0
    variance_threshold_m: float = 0.3
    combine: Combine = "spacing"
    ratio_cutoff: float | None = None
    exact_angles: bool = True
    surface_voxel_m: float = 0.05
    fill_step_m: float = 0.1
    max_fill_m: float = 2.0

    @classmethod
    def from_params(cls, section=None, **overrides) -> OcclusionConfig:
        """From a pydantic parameter section (or dict) with the same keys; unknown keys ignored."""
        from dataclasses import fields

        values = section.model_dump() if hasattr(section, "model_dump") else dict(section or {})
        values.update(overrides)
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})

    def detector_kwargs(self) -> dict:
        return {
            "alpha_thr_deg": self.alpha_thr_deg,
            "beta_thr_deg": self.beta_thr_deg,
            "variance_threshold_m": self.variance_threshold_m,
            "combine": self.combine,
            "ratio_cutoff": self.ratio_cutoff,
            "exact_angles": self.exact_angles,
        }


@dataclass(frozen=True)
class ExplorationConfig:
    """Parameters of the exploration grid and the planner (men_spec 7.8; forest values inferred).

    Thesis values: ``obstacle_min_m`` 0.3 m above the floor, ``min_overlap`` 0.5, ``n_proposals``
    10 candidates, 8 zones, ``coverage_radius_m`` 8 m indoors (15 m here: the range within which
    the pipeline finds stems), ``cell_m`` 0.2 m (0.25 m here). ``plot``: polygon vertices
    ``[[x, y], ...]`` in the global frame; None = the scan positions' bounding box grown by
    ``plot_margin_m``.
    """

    cell_m: float = 0.25
    height_min_m: float = -0.5
    height_max_m: float = 3.0
    dz_m: float = 0.1
    obstacle_min_m: float = 0.3
    clearance_m: float = 1.8
    min_ground_points: int = 1
    min_obstacle_points: int = 3
    ground_quantile: float = 0.25
    ground_window_m: float = 1.0
    map_range_m: float = 15.0
    coverage_radius_m: float = 15.0
    blind_radius_m: float = 1.8
    n_rays: int = 720
    stem_range_m: float = 15.0
    stem_visible_share: float = 0.5
    stem_min_pixels: float = 3.0
    angular_step_deg: float | None = None
    stem_margin_m: float = 0.05
    overlap_rule: Literal["stems", "area", "either", "both"] = "stems"
    min_common_stems: int = 5
    min_overlap: float = 0.5
    obstacle_clearance_m: float = 0.5
    candidate_spacing_m: float = 2.0
    min_scan_distance_m: float = 2.0
    path_step_m: float = 1.0
    distance_scale_m: float = 30.0
    stem_bonus_m2: float = 10.0
    n_proposals: int = 10
    strategy: Literal["coverage", "thesis"] = "coverage"
    zone_rule: Literal["heading", "unmapped"] = "heading"
    w_unmapped: float = 1.0
    w_wall: float = 1.0
    tangential_trigger_deg: float = 150.0
    min_density_per_m2: float = 100.0
    plot: tuple[tuple[float, float], ...] | None = None
    plot_margin_m: float = 10.0

    @classmethod
    def from_params(cls, section=None, **overrides) -> ExplorationConfig:
        """From a pydantic parameter section (or dict) with the same keys; unknown keys ignored."""
        values = section.model_dump() if hasattr(section, "model_dump") else dict(section or {})
        values.update(overrides)
        names = {f.name for f in fields(cls)}
        values = {k: v for k, v in values.items() if k in names}
        if values.get("plot") is not None:
            values["plot"] = tuple((float(x), float(y)) for x, y in values["plot"])
        return cls(**values)
