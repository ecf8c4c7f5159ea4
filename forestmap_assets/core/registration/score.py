"""Olson's robust map-similarity score for sub-map registration (spec 6.3, Th. Eq. 5.5-5.10).

Per point of the transformed map B at nearest-neighbour distance ``D`` from map A::

    p(D) = k1 + k2 / (sigma sqrt(2 pi)) exp(-D^2 / (2 sigma^2))

with ``k2`` the inlier share and ``k1 = (1 - k2) g(outlier_distance)`` (g = N(0, sigma) density,
spec 6.3 "recommended reading"). The log-likelihood of a transform is ``sum_i ln p(D_i)``.
``ln p`` is decreasing in ``D``; beyond :attr:`ScoreModel.cap_m` it equals ``ln k1`` to float64
precision, so distances only need to be known up to that cap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SQRT_2PI = float(np.sqrt(2.0 * np.pi))


@dataclass(frozen=True)
class ScoreModel:
    """Constants of the per-point score ``ln p(D)`` (spec 6.3)."""

    sigma_m: float = 0.035
    inlier_share: float = 0.3
    outlier_distance_m: float = 0.3

    @property
    def k2(self) -> float:
        return float(self.inlier_share)

    @property
    def k1(self) -> float:
        """Floor ``(1 - k2) g(outlier_distance)`` (spec 6.3, inferred reading of Th. 5.4.1)."""
        return (1.0 - self.k2) * gaussian_density(self.outlier_distance_m, self.sigma_m)

    @property
    def ln_k1(self) -> float:
        """Per-point score of an unmatched point (D -> infinity)."""
        return float(np.log(self.k1))

    @property
    def ln_p0(self) -> float:
        """Per-point score of a perfectly matched point (D = 0)."""
        return float(np.log(self.k1 + self.k2 / (self.sigma_m * SQRT_2PI)))

    @property
    def cap_m(self) -> float:
        """Distance beyond which ``ln p(D) == ln k1`` in float64 (inferred: k2 g(D) < k1 eps/4)."""
        eps = np.finfo(float).eps / 4.0
        ratio = self.k1 * eps * self.sigma_m * SQRT_2PI / self.k2
        return float(self.sigma_m * np.sqrt(-2.0 * np.log(ratio)))

    def log_p(self, distance: np.ndarray) -> np.ndarray:
        """``ln p(D)`` per point (spec 6.3, Eq. 5.8); vectorised, D >= 0, inf allowed."""
        d = np.asarray(distance, dtype=float)
        with np.errstate(under="ignore", over="ignore"):
            dens = np.exp(-0.5 * (d / self.sigma_m) ** 2) / (self.sigma_m * SQRT_2PI)
        return np.log(self.k1 + self.k2 * dens)

    def floor(self, n_points: int) -> float:
        """All-outlier log-likelihood ``n ln k1`` (s_floor of the cloud weights, spec 6.5)."""
        return float(n_points) * self.ln_k1

    @classmethod
    def from_params(cls, params) -> ScoreModel:
        """From a :class:`~forestmap_assets.params.RegistrationParams`."""
        return cls(params.sigma_m, params.inlier_share, params.outlier_distance_m)


def gaussian_density(d: float | np.ndarray, sigma: float) -> float | np.ndarray:
    """Zero-mean normal density N(d; 0, sigma)."""
    return np.exp(-0.5 * (np.asarray(d, dtype=float) / sigma) ** 2) / (sigma * SQRT_2PI)

