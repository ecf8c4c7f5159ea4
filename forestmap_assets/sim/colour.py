"""Surface colour of the virtual forest, seen by a colour camera on the scanner (men spec 2.3).

Men's scanner attaches RGB from cameras in the scan plane to every range sample (spec 2.3); HICP
relies on the **hue** of a surface point being the same from every viewpoint while RGB changes
with light (spec 2.6). The model below (all numbers inferred; forest hues per spec 10) gives
every surface point a world-fixed albedo in HSL and lets each scan see it under its own light:

* **Albedo** per object kind: bark brown (hue ~0.07) with moss/lichen patches (hue ~0.2) and
  vertical streaks; foliage green (0.22-0.33) with per-blob tints; ground litter brown (~0.08)
  with moss and grass patches (0.2-0.3) at 0.5-3 m scales; understorey bushes green, saplings
  brownish, boxes (stones/stumps) grey-brown with low saturation; any other kind (the
  structured sites' walls, pillars, cars) one painted colour per object. Variation comes from smooth
  random fields (sums of plane waves in world coordinates) and a random offset per object
  (``part``), so it is the same for every scan.
* **Illumination per scan**: lightness times ``exposure * (shade + (1 - shade) |cos i|)`` with
  sun flecks (a smooth field that differs between scans), a small white-balance error per scan
  (a few per cent per channel: shifts hue slightly) and camera noise (``noise_dn`` per channel,
  8-bit), so low-saturation and dark pixels have unstable hue, as in real data (spec 10).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from forestmap_assets.core.registration.colour import hsl_to_rgb
from forestmap_assets.sim.scene_mesh import (
    KIND_BRANCH,
    KIND_FOLIAGE,
    KIND_GROUND,
    KIND_STEM,
    KIND_UNDERSTOREY,
)

# kind -> base (hue, saturation, lightness) and per-object standard deviations (inferred)
BASE_HSL = {
    KIND_GROUND: ((0.08, 0.40, 0.28), (0.01, 0.05, 0.03)),
    KIND_STEM: ((0.07, 0.28, 0.27), (0.012, 0.05, 0.04)),
    KIND_BRANCH: ((0.075, 0.25, 0.30), (0.015, 0.05, 0.04)),
    KIND_FOLIAGE: ((0.27, 0.50, 0.30), (0.03, 0.08, 0.05)),
    KIND_UNDERSTOREY: ((0.24, 0.40, 0.30), (0.06, 0.10, 0.05)),
}


@dataclass
class WaveField:
    """Smooth random field in world coordinates: ``sum_k cos(k_k . p + phase_k) / sqrt(K/2)``
    with wavelengths in ``[lo, hi]`` (zero mean, unit variance)."""

    wavevectors: np.ndarray  # (K, 3)
    phases: np.ndarray  # (K,)

    @classmethod
    def make(cls, rng: np.random.Generator, wavelength_m: tuple[float, float], n: int = 10,
             anisotropy=(1.0, 1.0, 1.0)) -> WaveField:
        d = rng.standard_normal((n, 3)) * np.asarray(anisotropy, dtype=np.float64)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        lam = np.exp(rng.uniform(np.log(wavelength_m[0]), np.log(wavelength_m[1]), n))
        return cls(d * (2 * np.pi / lam)[:, None], rng.uniform(0, 2 * np.pi, n))

    def __call__(self, points: np.ndarray) -> np.ndarray:
        arg = np.asarray(points, dtype=np.float64) @ self.wavevectors.T + self.phases
        return np.cos(arg).sum(axis=1) / np.sqrt(len(self.phases) / 2)


@dataclass
class ColourModel:
    """World-fixed albedo plus per-scan illumination (module doc). ``seed`` fixes the albedo;
    each call of :meth:`render` takes the scan's own random generator for its light."""

    seed: int = 0
    shade: float = 0.45
    exposure_range: tuple[float, float] = (0.8, 1.2)
    white_balance_sd: float = 0.03
    fleck_strength: float = 0.35
    noise_dn: float = 2.0
    _fields: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        self._part_offsets = rng.standard_normal((4096, 3))
        f = self._fields
        f["moss"] = WaveField.make(rng, (0.5, 3.0), anisotropy=(1.0, 1.0, 0.3))
        f["litter"] = WaveField.make(rng, (0.3, 1.5))
        f["bark_patch"] = WaveField.make(rng, (0.2, 1.0))
        f["bark_streak"] = WaveField.make(rng, (0.05, 0.2), anisotropy=(1.0, 1.0, 0.05))
        f["leaf"] = WaveField.make(rng, (0.3, 2.0))
        f["fine"] = WaveField.make(rng, (0.05, 0.3))

    def _offset(self, part: np.ndarray) -> np.ndarray:
        return self._part_offsets[np.mod(np.asarray(part, dtype=np.int64), len(self._part_offsets))]

    def albedo_hsl(self, points: np.ndarray, kind: np.ndarray, part: np.ndarray) -> tuple[np.ndarray, ...]:
        """World-fixed (hue, saturation, lightness) of surface points (n, 3) of the given kinds."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        kind = np.asarray(kind).reshape(-1)
        n = len(p)
        h, s, light = np.zeros(n), np.zeros(n), np.zeros(n)
        off = self._offset(part)
        fine = self._fields["fine"](p)
        for k, ((h0, s0, l0), (hs, ss, ls)) in BASE_HSL.items():
            sel = kind == k
            if not sel.any():
                continue
            q, o, fn = p[sel], off[sel], fine[sel]
            hh = h0 + hs * o[:, 0] + 0.004 * fn
            sk = s0 + ss * o[:, 1] + 0.02 * fn
            lk = l0 + ls * o[:, 2] + 0.02 * fn
            if k == KIND_GROUND:
                moss = np.clip(0.5 + 0.6 * self._fields["moss"](q), 0.0, 1.0)  # 0 litter .. 1 moss
                hh = hh + moss * (0.24 - 0.08) + 0.015 * self._fields["litter"](q)
                sk = sk + 0.1 * moss
                lk = lk - 0.04 * moss
            elif k in (KIND_STEM, KIND_BRANCH):
                patch = np.clip(self._fields["bark_patch"](q) - 0.6, 0.0, 1.0)  # lichen/moss
                hh = hh + patch * 0.13 + 0.01 * self._fields["bark_streak"](q)
                sk = sk + 0.1 * patch
                lk = lk + 0.05 * self._fields["bark_streak"](q)
            elif k == KIND_FOLIAGE:
                hh = hh + 0.03 * self._fields["leaf"](q)
            h[sel], s[sel], light[sel] = hh, sk, lk
        # other kinds (walls, pillars, cars of the structured sites): one painted colour per
        # object, any hue, with a faint texture (inferred)
        other = ~np.isin(kind, list(BASE_HSL))
        if other.any():
            o = off[other]
            h[other] = 0.5 + 0.16 * o[:, 0] + 0.004 * fine[other]
            s[other] = 0.35 + 0.1 * o[:, 1]
            light[other] = 0.5 + 0.08 * o[:, 2] + 0.02 * fine[other]
        return np.mod(h, 1.0), np.clip(s, 0.02, 1.0), np.clip(light, 0.05, 0.9)

    def render(self, points: np.ndarray, kind: np.ndarray, part: np.ndarray, cos_incidence: np.ndarray,
               rng: np.random.Generator) -> np.ndarray:
        """8-bit RGB (n, 3) of surface points seen by one scan (its own light, from ``rng``)."""
        h, s, light = self.albedo_hsl(points, kind, part)
        exposure = rng.uniform(*self.exposure_range)
        fleck = WaveField.make(rng, (1.0, 6.0), n=8)(points)
        lit = exposure * (self.shade + (1 - self.shade) * np.abs(np.asarray(cos_incidence, dtype=np.float64)))
        lit = lit * (1.0 + self.fleck_strength * np.clip(fleck, -1.5, 1.5) / 1.5)
        rgb = hsl_to_rgb(h, s, np.clip(light * lit, 0.0, 1.0))
        rgb = rgb * (1.0 + self.white_balance_sd * rng.standard_normal(3))[None, :]
        rgb = rgb * 255.0 + self.noise_dn * rng.standard_normal(rgb.shape)
        return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
