"""Colour of scan points: HSL hue, hue filter and hue histogram (men spec 2.3, 2.6, 4.5).

Men attaches RGB to every range sample (spec 2.3) and uses only the HSL **hue**, normalised to
[0, 1], because it is approximately invariant to lighting and view angle while RGB is not
(spec 2.6). The thesis gives no formula; the standard hexcone hue is used (inferred):

* max = R: h = ((G - B) / (max - min)) mod 6
* max = G: h = (B - R) / (max - min) + 2
* max = B: h = (R - G) / (max - min) + 4

then h / 6. Grey (max = min) has no hue; Table 5.1 gives it 0. Hue is **linear** as in the
thesis (pure red may read 0 or 1, no wrap-around); :func:`hue_features` offers the circular
embedding as an option that is off by default (spec 11 item 3).

Hue is computed once per scan (:func:`table_hue`) and carried unchanged through every rigid
transform (spec 5.2).
"""

from __future__ import annotations

import numpy as np
import pandas as pd


def _unit_rgb(rgb) -> np.ndarray:
    """RGB as float in [0, 1], shape (..., 3); uint8 is divided by 255, uint16 by 65535."""
    a = np.asarray(rgb)
    if a.shape[-1:] != (3,):
        raise ValueError(f"rgb: expected a last axis of 3 channels, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a.astype(np.float64) / 255.0
    if a.dtype == np.uint16:
        return a.astype(np.float64) / 65535.0
    a = a.astype(np.float64)
    return a / 255.0 if a.size and np.nanmax(a) > 1.0 else a


def rgb_to_hsl(rgb) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """HSL hue, saturation and lightness, each in [0, 1] (spec 2.6; hexcone hue, grey -> 0)."""
    c = _unit_rgb(rgb)
    r, g, b = c[..., 0], c[..., 1], c[..., 2]
    mx = c.max(axis=-1)
    mn = c.min(axis=-1)
    chroma = mx - mn
    safe = np.where(chroma > 0, chroma, 1.0)
    h = np.where(
        mx == r,
        np.mod((g - b) / safe, 6.0),
        np.where(mx == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0),
    )
    h = np.where(chroma > 0, h / 6.0, 0.0)
    light = (mx + mn) / 2.0
    denom = 1.0 - np.abs(2.0 * light - 1.0)
    sat = np.where((chroma > 0) & (denom > 0), chroma / np.where(denom > 0, denom, 1.0), 0.0)
    return h, np.clip(sat, 0.0, 1.0), light


def rgb_to_hue(rgb) -> np.ndarray:
    """HSL hue in [0, 1] (linear, grey = 0) of RGB values, shape (..., 3) -> (...) (spec 2.6)."""
    return rgb_to_hsl(rgb)[0]


def hsl_to_rgb(h, s, light) -> np.ndarray:
    """Inverse of :func:`rgb_to_hsl`: float RGB in [0, 1], shape (..., 3) (used by the
    simulator's colour model)."""
    h = np.mod(np.asarray(h, dtype=np.float64), 1.0)
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
    light = np.clip(np.asarray(light, dtype=np.float64), 0.0, 1.0)
    chroma = (1.0 - np.abs(2.0 * light - 1.0)) * s
    hp = h * 6.0
    x = chroma * (1.0 - np.abs(np.mod(hp, 2.0) - 1.0))
    k = np.floor(hp).astype(int) % 6
    z = np.zeros_like(chroma)
    r = np.choose(k, [chroma, x, z, z, x, chroma])
    g = np.choose(k, [x, chroma, chroma, x, z, z])
    b = np.choose(k, [z, z, x, chroma, chroma, x])
    m = light - chroma / 2.0
    return np.stack([r + m, g + m, b + m], axis=-1)


def hue_features(hue, mode: str = "linear") -> np.ndarray:
    """Hue as embedding coordinates: ``linear`` (n, 1) = h (thesis), or ``circular`` (n, 2) =
    (cos 2 pi h, sin 2 pi h) / (2 pi), whose chord length equals |dh| for small differences and
    which has no jump between red at 0 and at 1 (an improvement beyond the thesis, inferred)."""
    h = np.asarray(hue, dtype=np.float64).reshape(-1)
    if mode == "linear":
        return h[:, None]
    if mode == "circular":
        a = 2.0 * np.pi * h
        return np.column_stack([np.cos(a), np.sin(a)]) / (2.0 * np.pi)
    raise ValueError(f"hue mode: expected 'linear' or 'circular', got {mode!r}")


def hue_filter(hue, threshold: float = 0.5) -> np.ndarray:
    """Mask of the "low-pass hue filter" ``h <= threshold`` (spec 4.1 step 3, 4.5)."""
    return np.asarray(hue, dtype=np.float64) <= threshold


def hue_histogram(hue, bins: int = 50) -> pd.DataFrame:
    """Histogram of hue over [0, 1] (``bin_lo, bin_hi, count, share``): the utility the thesis
    uses to choose the hue-filter threshold (spec 4.5, 11 item 4)."""
    h = np.asarray(hue, dtype=np.float64).reshape(-1)
    h = h[np.isfinite(h)]
    counts, edges = np.histogram(h, bins=bins, range=(0.0, 1.0))
    share = counts / max(int(counts.sum()), 1)
    return pd.DataFrame({"bin_lo": edges[:-1], "bin_hi": edges[1:], "count": counts, "share": share})


def table_hue(table: pd.DataFrame) -> np.ndarray | None:
    """Hue of every row of a ``range_images`` table (columns ``r, g, b``), or None when the scan
    has no colour. Computed once per scan; rigid transforms leave it unchanged (spec 5.2)."""
    if not {"r", "g", "b"} <= set(table.columns):
        return None
    rgb = np.column_stack([table[c].to_numpy() for c in "rgb"]).astype(np.uint8)
    return rgb_to_hue(rgb)


def image_hue(image) -> np.ndarray | None:
    """Hue (rows, cols) of a :class:`~forestmap_assets.core.features.range_image.RangeImage` with colour,
    NaN where there is no return; None without colour."""
    if image.rgb is None:
        return None
    h = rgb_to_hue(image.rgb)
    return np.where(image.valid, h, np.nan)
