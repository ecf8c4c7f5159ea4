"""Occlusion boundaries on organised range images (Men 2012, section 3.3; men_spec 3.1).

A range image samples the scene on a regular (azimuth, elevation) lattice, so two neighbouring
pixels are two rays separated by a small angle ``Delta``. Where the rays hit one surface the two
points are close; where the nearer ray grazes an edge and the farther one lands on a surface
behind, they are far apart. Two tests (men_spec 3.1.1-3.1.2):

* **Range variance** (3.1.1): ``v_ij = max(|r_ij - r_n|, |r_ij - r_s|, |r_ij - r_e|, |r_ij - r_w|)``
  over the four neighbours (the thesis's "w" neighbour misprint fixed); ``v_ij > v_thres``.
* **Range-normalised spacing** (3.1.2, Eq. 3.3-3.5): for a neighbouring pair with spacing
  ``Delta_s`` (3-D distance of the two points), ``Delta_s / r >= sin(Delta) / sin(alpha_thr -
  Delta)``, i.e. the surface is seen at an incidence angle below ``alpha_thr`` (5 deg): a depth
  discontinuity, or a surface at grazing incidence whose points are unreliable ("mixed pixels",
  must be rescanned). ``r`` is the range of the nearer point of the pair: by the law of sines in
  the triangle (sensor, P_i, P_i+1) the incidence angle in Eq. 3.3 is the one at the nearer
  point (inferred). The tilt direction (rows, Delta = elevation step, threshold ``alpha_thr``) and
  the pan direction (columns, Delta = azimuth step, threshold ``beta_thr``) are tested separately
  and combined by union (inferred: the thesis says "combining"); the pan criterion printed with
  "<=" is read as ">=" (men_spec 3.1.2).

Everything is decided per neighbouring *pair* and a pixel is flagged when one of its pairs is:
for the variance test this is exactly ``v_ij > v_thres``. Both pixels of a flagged pair are
flagged: the near-edge one and the far-surface one (validation target V4). Missing returns
(NaN) form no pair, so sky and range-limit edges are not object occlusions (the thesis detects
only the third cause of occlusion).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import pandas as pd

from forestmap_assets.core.features.range_image import RangeImage, spherical_to_xyz
from forestmap_assets.params.men import Combine

BOUNDARY_COLUMNS = [
    "row",
    "col",
    "range_m",
    "x",
    "y",
    "z",
    "tilt",
    "pan",
    "variance",
    "near",
    "far",
    "tilt_pair",
    "pan_pair",
    "ratio",
]


def occlusion_threshold(
    step_deg: float | np.ndarray, alpha_thr_deg: float = 5.0
) -> np.ndarray | float:
    """``sin(Delta) / sin(alpha_thr - Delta)`` (men_spec Eq. 3.4; V3: 0.05269 at 0.25 deg, 5 deg).

    Infinite where ``Delta >= alpha_thr`` (no incidence angle can be tested at such a step)."""
    d = np.radians(np.asarray(step_deg, dtype=np.float64))
    a = np.radians(alpha_thr_deg)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(d < a, np.sin(d) / np.sin(a - d), np.inf)
    return out if out.ndim else float(out)


@dataclass
class OcclusionBoundaries:
    """Per-pixel and per-pair results of :func:`detect_occlusions` for a (rows, cols) image.

    ``tilt_pair[v, u]`` is the pair (v, u)-(v+1, u) (shape rows-1 x cols); ``pan_pair[v, u]``
    the pair (v, u)-(v, u+1) (shape rows x cols-1, or rows x cols when the azimuth wraps, the
    last column pairing with the first). ``*_ratio`` are ``Delta_s / r_near`` of the pairs and
    ``*_threshold`` the thresholds they were compared with; ``*_jump`` are ``|Delta r|``.
    Pixel masks: ``tilt``, ``pan`` (flagged by a pair of that direction), ``variance`` (the
    range-variance test alone), ``boundary`` (what the chosen ``combine`` rule flags, union of
    the directions), ``near`` / ``far`` (the pixel is the nearer / farther one of a flagged pair).
    """

    tilt_pair: np.ndarray
    pan_pair: np.ndarray
    tilt_ratio: np.ndarray
    pan_ratio: np.ndarray
    tilt_threshold: np.ndarray
    pan_threshold: np.ndarray
    tilt_jump: np.ndarray
    pan_jump: np.ndarray
    variance: np.ndarray
    tilt: np.ndarray
    pan: np.ndarray
    boundary: np.ndarray
    near: np.ndarray
    far: np.ndarray
    wrap: bool

    @property
    def shape(self) -> tuple[int, int]:
        return self.boundary.shape


def _pairs(a: np.ndarray, axis: int, wrap: bool) -> tuple[np.ndarray, np.ndarray]:
    """The two members of every neighbouring pair along ``axis`` (last-first pair if ``wrap``)."""
    if axis == 0:
        return a[:-1], a[1:]
    if wrap:
        return a, np.roll(a, -1, axis=1)
    return a[:, :-1], a[:, 1:]


def _spread(
    pair: np.ndarray,
    axis: int,
    wrap: bool,
    which: Literal["first", "second", "both"] = "both",
    shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """Pixel mask from a pair mask: the first and/or second member of every True pair."""
    rows, cols = (
        shape
        if shape is not None
        else (pair.shape[0] + (axis == 0), pair.shape[1] + (axis == 1 and not wrap))
    )
    out = np.zeros((rows, cols), dtype=bool)
    if axis == 0:
        if which in ("first", "both"):
            out[:-1] |= pair
        if which in ("second", "both"):
            out[1:] |= pair
    elif wrap:
        if which in ("first", "both"):
            out |= pair
        if which in ("second", "both"):
            out |= np.roll(pair, 1, axis=1)
    else:
        if which in ("first", "both"):
            out[:, :-1] |= pair
        if which in ("second", "both"):
            out[:, 1:] |= pair
    return out


def azimuth_wraps(azimuth_deg: np.ndarray, tolerance: float = 0.5) -> bool:
    """True when the columns cover the full circle (the last column neighbours the first)."""
    az = np.asarray(azimuth_deg, dtype=np.float64)
    if az.size < 2:
        return False
    step = float(np.median(np.abs(np.diff(az))))
    return bool(abs(abs(az[-1] - az[0]) + step - 360.0) <= tolerance * step)


def pair_angles_deg(
    azimuth_deg: np.ndarray, elevation_deg: np.ndarray, *, wrap: bool = False, exact: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Angle between the rays of every tilt pair (rows-1, cols) and pan pair (rows, cols-1|cols).

    ``exact`` (inferred, default): the true angle between the two rays; for pan pairs at
    elevation ``el`` this is ``2 asin(cos(el) sin(Delta_az / 2))``, smaller than the azimuth step
    away from the horizon. ``exact=False``: the nominal steps, as in the thesis."""
    az = np.asarray(azimuth_deg, dtype=np.float64)
    el = np.asarray(elevation_deg, dtype=np.float64)
    rows, cols = el.size, az.size
    d_el = np.abs(np.diff(el))[:, None] * np.ones((1, cols))
    a0, a1 = _pairs(az[None, :], 1, wrap)
    d_az = np.abs(((a1 - a0) + 180.0) % 360.0 - 180.0)
    if exact:
        half = np.radians(d_az) / 2
        d_pan = np.degrees(
            2 * np.arcsin(np.clip(np.cos(np.radians(el))[:, None] * np.sin(half), -1, 1))
        )
    else:
        d_pan = np.broadcast_to(d_az, (rows, d_az.shape[1])).copy()
    return d_el, d_pan


def range_variance(range_m: np.ndarray, *, wrap: bool = False) -> np.ndarray:
    """``v_ij`` of men_spec 3.1.1: largest |range difference| to the valid N/S/E/W neighbours
    (NaN-free neighbours only; 0 where a pixel has none; NaN where the pixel has no return)."""
    r = np.asarray(range_m, dtype=np.float64)
    v = np.zeros_like(r)
    for axis in (0, 1):
        a, b = _pairs(r, axis, wrap and axis == 1)
        with np.errstate(invalid="ignore"):
            jump = np.abs(a - b)
        jump = np.where(np.isfinite(jump), jump, 0.0)
        first = np.zeros_like(r)
        second = np.zeros_like(r)
        if axis == 0:
            first[:-1], second[1:] = jump, jump
        elif wrap:
            first, second = jump, np.roll(jump, 1, axis=1)
        else:
            first[:, :-1], second[:, 1:] = jump, jump
        v = np.maximum(v, np.maximum(first, second))
    return np.where(np.isfinite(r), v, np.nan)


def detect_occlusions(
    image: RangeImage,
    *,
    alpha_thr_deg: float = 5.0,
    beta_thr_deg: float = 5.0,
    variance_threshold_m: float = 0.3,
    combine: Combine = "spacing",
    ratio_cutoff: float | None = None,
    exact_angles: bool = True,
    wrap: bool | None = None,
) -> OcclusionBoundaries:
    """Occlusion-boundary pixels of an organised range image (men_spec 3.1, checklist item 5).

    ``alpha_thr_deg`` / ``beta_thr_deg``: incidence thresholds of the tilt / pan tests (5 deg,
    thesis). ``ratio_cutoff``: use one fixed cutoff for both directions instead (the thesis
    rounds 0.0527 to 0.05 at 0.25 deg). ``variance_threshold_m``: ``v_thres`` of the range-
    variance test (not stated in the thesis, "from analysis of the scene"; 0.3 m inferred, ~12
    range sigmas of the Riegl). ``combine``: which test decides a pair: ``"spacing"`` (default,
    the thesis's primary detector), ``"variance"``, ``"either"`` or ``"both"``; the directions are
    always combined by union. ``wrap``: pair the last column with the first (default: when the
    azimuths cover 360 deg)."""
    rng = np.asarray(image.range_m, dtype=np.float64)
    if wrap is None:
        wrap = azimuth_wraps(image.azimuth_deg)
    xyz = spherical_to_xyz(rng, image.azimuth_deg, image.elevation_deg)
    d_tilt, d_pan = pair_angles_deg(
        image.azimuth_deg, image.elevation_deg, wrap=wrap, exact=exact_angles
    )
    out: dict[str, np.ndarray] = {}
    for name, axis, thr_deg, delta in (
        ("tilt", 0, alpha_thr_deg, d_tilt),
        ("pan", 1, beta_thr_deg, d_pan),
    ):
        p0, p1 = _pairs(xyz, axis, wrap and axis == 1)
        r0, r1 = _pairs(rng, axis, wrap and axis == 1)
        spacing = np.linalg.norm(p1 - p0, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = spacing / np.fmin(r0, r1)
            jump = np.abs(r1 - r0)
        valid = np.isfinite(ratio)
        thr = (
            np.full(ratio.shape, ratio_cutoff, dtype=np.float64)
            if ratio_cutoff is not None
            else (np.broadcast_to(occlusion_threshold(delta, thr_deg), ratio.shape))
        )
        spacing_flag = valid & (ratio >= thr)
        variance_flag = valid & (jump > variance_threshold_m)
        flag = {
            "spacing": spacing_flag,
            "variance": variance_flag,
            "either": spacing_flag | variance_flag,
            "both": spacing_flag & variance_flag,
        }[combine]
        out[f"{name}_pair"] = flag
        out[f"{name}_ratio"] = np.where(valid, ratio, np.nan)
        out[f"{name}_threshold"] = np.asarray(thr, dtype=np.float64)
        out[f"{name}_jump"] = np.where(valid, jump, np.nan)
        out[name] = _spread(flag, axis, wrap and axis == 1, shape=rng.shape)
        first_near = np.where(valid, r0 <= r1, False)
        out[f"{name}_near"] = _spread(
            flag & first_near, axis, wrap and axis == 1, "first", rng.shape
        ) | _spread(flag & ~first_near, axis, wrap and axis == 1, "second", rng.shape)
        out[f"{name}_far"] = _spread(
            flag & ~first_near, axis, wrap and axis == 1, "first", rng.shape
        ) | _spread(flag & first_near, axis, wrap and axis == 1, "second", rng.shape)
    v = range_variance(rng, wrap=wrap)
    return OcclusionBoundaries(
        tilt_pair=out["tilt_pair"],
        pan_pair=out["pan_pair"],
        tilt_ratio=out["tilt_ratio"],
        pan_ratio=out["pan_ratio"],
        tilt_threshold=out["tilt_threshold"],
        pan_threshold=out["pan_threshold"],
        tilt_jump=out["tilt_jump"],
        pan_jump=out["pan_jump"],
        variance=np.nan_to_num(v, nan=0.0) > variance_threshold_m,
        tilt=out["tilt"],
        pan=out["pan"],
        boundary=out["tilt"] | out["pan"],
        near=out["tilt_near"] | out["pan_near"],
        far=out["tilt_far"] | out["pan_far"],
        wrap=bool(wrap),
    )


def boundaries_table(image: RangeImage, ob: OcclusionBoundaries) -> pd.DataFrame:
    """Flagged pixels as a table (``BOUNDARY_COLUMNS``): levelled ``x, y, z``; ``tilt_pair`` /
    ``pan_pair`` tell that the pair with the next row / column is flagged (so the pair masks can
    be rebuilt with :func:`pair_masks`); ``ratio`` the largest ``Delta_s / r`` of its pairs."""
    v, u = np.nonzero(ob.boundary | ob.variance)
    rows, cols = ob.shape
    tilt_pair = np.zeros((rows, cols), dtype=bool)
    tilt_pair[:-1] = ob.tilt_pair
    pan_pair = np.zeros((rows, cols), dtype=bool)
    pan_pair[:, : ob.pan_pair.shape[1]] = ob.pan_pair
    ratio = np.zeros((rows, cols))
    for pr, axis in ((ob.tilt_ratio, 0), (ob.pan_ratio, 1)):
        r = np.nan_to_num(pr, nan=0.0)
        first = np.zeros((rows, cols))
        second = np.zeros((rows, cols))
        if axis == 0:
            first[:-1], second[1:] = r, r
        elif ob.wrap:
            first, second = r, np.roll(r, 1, axis=1)
        else:
            first[:, :-1], second[:, 1:] = r, r
        ratio = np.maximum(ratio, np.maximum(first, second))
    pts = image.xyz[v, u]
    return pd.DataFrame(
        {
            "row": v.astype(np.int32),
            "col": u.astype(np.int32),
            "range_m": image.range_m[v, u].astype(np.float32),
            "x": pts[:, 0].astype(np.float32),
            "y": pts[:, 1].astype(np.float32),
            "z": pts[:, 2].astype(np.float32),
            "tilt": ob.tilt[v, u],
            "pan": ob.pan[v, u],
            "variance": ob.variance[v, u],
            "near": ob.near[v, u],
            "far": ob.far[v, u],
            "tilt_pair": tilt_pair[v, u],
            "pan_pair": pan_pair[v, u],
            "ratio": ratio[v, u].astype(np.float32),
        },
        columns=BOUNDARY_COLUMNS,
    )


def pair_masks(
    table: pd.DataFrame, shape: tuple[int, int], wrap: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Flagged tilt and pan pair masks rebuilt from a :func:`boundaries_table`."""
    rows, cols = shape
    tilt = np.zeros((max(rows - 1, 0), cols), dtype=bool)
    pan = np.zeros((rows, cols if wrap else max(cols - 1, 0)), dtype=bool)
    if len(table):
        v = table["row"].to_numpy()
        u = table["col"].to_numpy()
        t = table["tilt_pair"].to_numpy(bool) & (v < rows - 1)
        tilt[v[t], u[t]] = True
        p = table["pan_pair"].to_numpy(bool) & ((u < cols - 1) | wrap)
        pan[v[p], u[p]] = True
    return tilt, pan
