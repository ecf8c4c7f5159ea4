"""Parameter sections of the per-scan feature stages: range image, scan-line segments, circle
models, cylinder segments, wall lines, elevation grid and submaps (forsman spec 1-6.2, Tables
4.1-4.3), with the thesis values as defaults."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from forestmap_assets.params.stage import _Stage


class RangeImageParams(_Stage):
    """The range image the per-scan stages get from a scan file (spec 1.2; inferred, issue 18).

    ``min_step_deg``: the finest angular step of that image, per axis. A finer scan (a modern
    scanner's 0.02-0.04 deg, 20-50 M points) is projected onto this grid, per pixel the return
    of the front surface (first return, spec 1.1) nearest its centre; organised scans finer
    than this are thinned the same way. 0.05 deg: 4.7x the points per square degree of the
    Riegl LMS-Z210 (0.108 deg, spec 1.1), 5+ pixels across a 10 cm stem at 20 m (segment
    minimum: 4, Table 4.1), the lowest radius error of 0.05-0.1 deg on simulated fine scans
    (benchmarks/results.md, big scans). ``min_fill``: an angular step estimated from an
    unorganised cloud is coarsened until at least this share of the pixels inside the scanned
    region hold a return (io/projection.py); an explicit ``sensor: {angular_step_deg}`` in
    campaign.yaml is used as given (``min_step_deg`` still applies). ``bridge_gaps``: in a
    projected image that is not the scanner's own grid, row gaps of 1-2 empty pixels between
    returns less than 0.11 m apart (Table 4.1's range step) are filled by interpolation, as
    the scan-line segmentation breaks a run at every empty pixel (spec 2.2)."""

    min_step_deg: float = Field(0.05, ge=0.0)
    min_fill: float = Field(0.5, ge=0.0, lt=1.0)
    bridge_gaps: bool = True


class SegmentationParams(_Stage):
    """Scan-line segmentation, spec 2 / Table 4.1."""

    min_width_m: float = 0.06
    max_width_m: float = 1.0
    max_occluder_m: float = 0.04
    range_sigma_m: float = 0.025
    range_step_m: float = 0.11
    min_points: int = 4
    outlier_sigmas: float = 3.0  # T_out = 0.5 W + outlier_sigmas * sigma (Eq. 4.7)
    link_range_step_m: float = 0.11  # (inferred) max |delta r_mid| to link segments vertically
    max_window_px: int = 101
    # (inferred, issue 16) scan lines closer than this are thinned for the segments and circle
    # models (core/features/segments.py, feature_scan_lines); the thesis' 0.108 deg keeps all
    min_line_step_deg: float = Field(0.2, ge=0.0)


class CircleParams(_Stage):
    """Circle models, spec 3 / Table 4.2."""

    symmetry_threshold_m: float = 0.0041
    initial_symmetry_factor: float = 2.0  # (inferred) relaxation of the symmetry test, initial phase
    collect_height_m: float = 0.15
    max_neighbour_segments: int = 14
    initial_neighbour_segments: int = 2  # (inferred) +-2 segments in the initial phase
    axis_span_m: float = 0.6
    iterations: int = 2
    max_iterations: int = 5
    robust_sigmas: float = 3.0
    robust_max_rounds: int = 10
    max_axis_tilt_deg: float = 30.0
    fit: Literal["linear", "geometric", "ray"] = "linear"  # linear = the thesis's Eq. 4.8-4.11
    symmetry_statistic: Literal["mean", "noise_corrected"] = "mean"
    stable_centre_m: float = 0.001
    stable_radius_m: float = 0.001
    stable_normal_deg: float = 0.5
    stable_share: float = 0.8
    # (inferred) also stop when the share of settled circles rose by less than this in the last
    # iteration: on rough stems the rest move at their noise level and never settle (issue 16)
    stable_gain: float = 0.15
    engine: Literal["auto", "numpy", "numba"] = "auto"
    max_batch_points: int = 2_000_000
    # (inferred) points a circle fit takes at most: a segment whose neighbours hold more takes
    # every k-th of them (0 = all, the thesis)
    max_fit_points: int = 0


class CylinderParams(_Stage):
    """Cylinder (truncated-cone) segments, spec 4 / Table 4.2."""

    min_length_m: float = 0.5
    curvature_deg: float = 12.0
    max_gap_m: float = 0.24
    min_circles: int = 3
    curvature_reference: Literal["first", "running"] = "first"
    # (inferred) largest angle between a cylinder's centre line and its circles' mean normal;
    # None: the curvature threshold. Drops chains of branch/foliage circles (core/cylinders.py)
    axis_normal_deg: float | None = None
    # (inferred) walk a chain on into the chain that continues it across scan lines without a
    # segment, within max_gap_m (step 2c's gap; core/features/cylinders.py, chain_stacks)
    link_chains: bool = True


class LineParams(_Stage):
    """Horizontal wall/ceiling border lines, spec 5 / Table 4.3 (outdoor values)."""

    cell_m: float = 0.2
    tangent_interval_m: float = 1.4
    tangent_change_deg: float = 90.0
    end_distance_m: float = 0.4
    min_length_m: float = 1.5
    max_inclination_deg: float = 5.0
    enabled: bool = True
    max_range_m: float = 40.0
    # (inferred) occupancy-grid and border details, see core/lines.py
    max_beams: int = 100_000
    step_fraction: float = 0.5
    hit_margin_m: float | None = None
    min_wall_extent_m: float = 0.5
    top_tolerance_m: float | None = None
    wall_depth_cells: int = 2
    border_xy: Literal["hits", "edge", "centre"] = "hits"
    link_cells: int = 2
    split_at_outliers: bool = True


class ElevationParams(_Stage):
    """Per-scan lowest/highest-hit grid, spec 9."""

    cell_m: float = 0.1
    mode: Literal["lowest", "highest"] = "lowest"
    render_cell_m: float = 0.6
    n_lowest: int = 5
    supersample: int = 2  # (inferred) merge without holes after rotation
    max_distance_m: float | None = None


class SubmapParams(_Stage):
    """Registration points along feature centre lines, spec 6.2 (Delta_d)."""

    spacing_m: float = 0.05
    # (inferred, issue 10) cylinders sampled cylinder_weight x as densely as wall lines
    # (core/submaps.py): a pillar point fixes both horizontal directions, a line point one
    cylinder_weight: int = 1
