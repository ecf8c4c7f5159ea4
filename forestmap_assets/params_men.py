"""Settings of the stages from Men (2012) (fine registration, occlusion boundaries, exploration)
as plain dataclasses, used by the core and turned into parameter sections by :mod:`.params`.

Layer: imports nothing of forestmap (numpy-level only), like :mod:`.params`.
"""

from __future__ import annotations

from dataclasses import dataclass
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
    sd_inflation: float = 1.8  # the ICP-Hessian sigmas are multiplied by this before the floors
    min_pairs: int = 200
    min_fit_gain: float = 0.0  # relative: the refined fit must be lower by this share
    # point-to-plane: the number of 4-DoF Gauss-Newton steps, and Open3D's 6-DoF ICP first
    plane_iterations: int = 30
    open3d_start: bool = True
    robust_k: float | None = 4.685  # Tukey's biweight constant (95 % efficiency); None: least squares


Combine = Literal["spacing", "variance", "either", "both"]


@dataclass(frozen=True)
class OcclusionConfig:
    """Parameters of :func:`detect_occlusions` and of the observed-surface voxels derived from
    it (:func:`~.exploration.observed_surface`): thesis thresholds 5 deg / 5 deg (men_spec 3.1.2);
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
