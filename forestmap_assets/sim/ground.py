"""Uneven ground of the virtual plot (spec 10.1): a plane plus a few long-wave cosines as a
height field ``z(x, y)`` (with ``z(0, 0) = 0``) and its triangulated grid. All numbers
(inferred)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


# ---- ground ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Ground:
    """Smooth random height field: a plane plus a few long-wave cosines (inferred)."""

    slope: tuple[float, float]
    amplitude: np.ndarray
    wavevector: np.ndarray  # (K, 2) rad/m
    phase: np.ndarray

    def height(self, x, y) -> np.ndarray:
        """Ground elevation z(x, y) (vectorised)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        arg = x[..., None] * self.wavevector[:, 0] + y[..., None] * self.wavevector[:, 1]
        waves = (self.amplitude * np.cos(arg + self.phase)).sum(axis=-1)
        base = (self.amplitude * np.cos(self.phase)).sum()  # so that z(0, 0) = 0
        return self.slope[0] * x + self.slope[1] * y + waves - base


def make_ground(
    rng: np.random.Generator,
    *,
    relief_m: float = 0.15,
    slope_range: tuple[float, float] = (0.02, 0.06),
    wavelength_range_m: tuple[float, float] = (8.0, 30.0),
    n_waves: int = 6,
) -> Ground:
    """Random ground: gradient ``slope_range`` (m/m), relief std ``relief_m`` (inferred)."""
    s = rng.uniform(*slope_range)
    a = rng.uniform(-np.pi, np.pi)
    lam = rng.uniform(*wavelength_range_m, n_waves)
    direction = rng.uniform(-np.pi, np.pi, n_waves)
    k = (2 * np.pi / lam)[:, None] * np.stack([np.cos(direction), np.sin(direction)], axis=1)
    amp = relief_m / np.sqrt(n_waves / 2) * rng.uniform(0.6, 1.4, n_waves)
    return Ground((s * np.cos(a), s * np.sin(a)), amp, k, rng.uniform(-np.pi, np.pi, n_waves))


def ground_mesh(ground: Ground, half_extent: float, cell_m: float):
    """Regular triangulated grid of the ground over ``[-half_extent, half_extent]^2``."""
    n = int(np.ceil(2 * half_extent / cell_m)) + 1
    g = np.linspace(-half_extent, half_extent, n)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    verts = np.stack([xx, yy, ground.height(xx, yy)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    faces = np.concatenate([np.stack([a, a + n, a + n + 1], 1), np.stack([a, a + n + 1, a + 1], 1)])
    return verts, faces
