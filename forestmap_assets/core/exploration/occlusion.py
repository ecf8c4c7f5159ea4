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

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import pandas as pd

from forestmap_assets.core.exploration import _surface_kernels as kernels
from forestmap_assets.core.features.range_image import RangeImage
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
    ``*_threshold`` the thresholds they were compared with (a read-only broadcast view when one
    per row); ``*_jump`` are ``|Delta r|``.
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
    _distinct: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def shape(self) -> tuple[int, int]:
        return self.boundary.shape

    def median_threshold(self, direction: Literal["tilt", "pan"]) -> float:
        """``np.median`` of ``tilt_threshold`` / ``pan_threshold`` (NaN when empty), from the
        distinct thresholds and their counts when :func:`detect_occlusions` recorded them."""
        thr = getattr(self, f"{direction}_threshold")
        if not thr.size:
            return np.nan
        if direction in self._distinct:
            return _repeated_median(*self._distinct[direction])
        return float(np.median(thr))


def _repeated_median(values: np.ndarray, counts: np.ndarray) -> float:
    """``np.median`` of ``values`` each repeated ``counts`` times, without the repeats (the mean
    of the middle one or two of the sorted repeats, as numpy takes it)."""
    if np.isnan(values).any():
        return np.nan
    order = np.argsort(values, kind="stable")
    values, end = values[order], np.cumsum(counts[order])
    n = int(end[-1])
    middle = [(n - 1) // 2, n // 2] if n % 2 == 0 else [n // 2]
    return float(np.mean(values[np.searchsorted(end, middle, side="right")]))


def _pairs(a: np.ndarray, axis: int, wrap: bool) -> tuple[np.ndarray, np.ndarray]:
    """The two members of every neighbouring pair along ``axis`` (last-first pair if ``wrap``)."""
    if axis == 0:
        return a[:-1], a[1:]
    if wrap:
        return a, np.roll(a, -1, axis=1)
    return a[:, :-1], a[:, 1:]


def azimuth_wraps(azimuth_deg: np.ndarray, tolerance: float = 0.5) -> bool:
    """True when the columns cover the full circle (the last column neighbours the first)."""
    az = np.asarray(azimuth_deg, dtype=np.float64)
    if az.size < 2:
        return False
    step = float(np.median(np.abs(np.diff(az))))
    return bool(abs(abs(az[-1] - az[0]) + step - 360.0) <= tolerance * step)


def _pan_angles_deg(elevation_deg: np.ndarray, d_az: np.ndarray, exact: bool) -> np.ndarray:
    """Angles (rows, len(d_az)) of pan pairs whose azimuths differ by ``d_az`` (deg)."""
    el = np.asarray(elevation_deg, dtype=np.float64)
    d_az = np.asarray(d_az, dtype=np.float64)[None, :]
    if not exact:
        return np.broadcast_to(d_az, (el.size, d_az.shape[1])).copy()
    half = np.radians(d_az) / 2
    return np.degrees(2 * np.arcsin(np.clip(np.cos(np.radians(el))[:, None] * np.sin(half), -1, 1)))


def _azimuth_steps(azimuth_deg: np.ndarray, wrap: bool) -> np.ndarray:
    """``|Delta az|`` (deg, folded to [0, 180]) of every pan pair."""
    a0, a1 = _pairs(np.asarray(azimuth_deg, dtype=np.float64)[None, :], 1, wrap)
    return np.abs(((a1 - a0) + 180.0) % 360.0 - 180.0)[0]


def pair_angles_deg(
    azimuth_deg: np.ndarray, elevation_deg: np.ndarray, *, wrap: bool = False, exact: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Angle between the rays of every tilt pair (rows-1, cols) and pan pair (rows, cols-1|cols).

    ``exact`` (inferred, default): the true angle between the two rays; for pan pairs at
    elevation ``el`` this is ``2 asin(cos(el) sin(Delta_az / 2))``, smaller than the azimuth step
    away from the horizon. ``exact=False``: the nominal steps, as in the thesis."""
    az = np.asarray(azimuth_deg, dtype=np.float64)
    el = np.asarray(elevation_deg, dtype=np.float64)
    d_el = np.abs(np.diff(el))[:, None] * np.ones((1, az.size))
    return d_el, _pan_angles_deg(el, _azimuth_steps(az, wrap), exact)


def _pair_thresholds(
    azimuth_deg, elevation_deg, wrap: bool, exact: bool, alpha_thr_deg: float, beta_thr_deg: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`occlusion_threshold` of the tilt and pan pairs (as :func:`pair_angles_deg`) with the
    trigonometry done once per row and distinct azimuth step: tilt thresholds (rows-1, 1), pan
    thresholds (rows, steps) and the step of every pan pair (its column in the latter)."""
    el = np.asarray(elevation_deg, dtype=np.float64)
    tilt = occlusion_threshold(np.abs(np.diff(el))[:, None], alpha_thr_deg)
    steps, step_of = np.unique(_azimuth_steps(azimuth_deg, wrap), return_inverse=True)
    pan = occlusion_threshold(_pan_angles_deg(el, steps, exact), beta_thr_deg)
    return np.asarray(tilt), np.asarray(pan), step_of.astype(np.int64)


def ray_trig(image: RangeImage) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``cos az, sin az`` per column and ``cos el, sin el`` per row (as ``spherical_to_xyz``)."""
    az = np.radians(np.asarray(image.azimuth_deg, dtype=np.float64))
    el = np.radians(np.asarray(image.elevation_deg, dtype=np.float64))
    return np.cos(az), np.sin(az), np.cos(el), np.sin(el)


def point_source(image: RangeImage) -> tuple[np.ndarray, tuple]:
    """What the kernels read ``image.xyz`` from at the valid pixels, without its float64 copy
    where none is needed: the float32 ``points`` when no levelling rotation applies, nothing
    (points from the range and :func:`ray_trig`) without points and rotation, else ``xyz``."""
    trig = ray_trig(image)
    if any(image.tilt_deg):
        return image.xyz, trig
    if image.points is not None:
        return image.points, trig
    return np.zeros((0, 0, 3)), trig


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
    azimuths cover 360 deg). One pass of :func:`~._surface_kernels.pair_tests` per direction; the
    thresholds are computed per row and distinct azimuth step."""
    rows, cols = image.shape
    if wrap is None:
        wrap = azimuth_wraps(image.azimuth_deg)
    tilt_thr, pan_thr, step_of = _pair_thresholds(
        image.azimuth_deg, image.elevation_deg, wrap, exact_angles, alpha_thr_deg, beta_thr_deg
    )
    trig = ray_trig(image)
    masks = {
        k: np.zeros((rows, cols), dtype=bool) for k in ("tilt", "pan", "variance", "near", "far")
    }
    out: dict[str, np.ndarray] = {}
    distinct = {}
    for name, axis, n_pairs, thr, thr_col in (
        ("tilt", 0, max(rows - 1, 0), tilt_thr, np.zeros(cols, dtype=np.int64)),
        ("pan", 1, cols if wrap else max(cols - 1, 0), pan_thr, step_of),
    ):
        if ratio_cutoff is not None:
            thr, thr_col = np.full((thr.shape[0], 1), float(ratio_cutoff)), np.zeros_like(thr_col)
        # pair (v, u) is tested against thr[v, thr_col[u]]
        ratio, jump, flag = kernels.pair_tests(
            image.range_m, trig, axis, n_pairs, thr, thr_col, float(variance_threshold_m),
            kernels.COMBINE[combine], masks[name], masks["near"], masks["far"], masks["variance"],
        )  # fmt: skip
        out[f"{name}_pair"], out[f"{name}_ratio"], out[f"{name}_jump"] = flag, ratio, jump
        out[f"{name}_threshold"] = (
            np.broadcast_to(thr, ratio.shape) if thr.shape[1] == 1 else thr[:, thr_col]
        )
        per_col = np.bincount(thr_col, minlength=thr.shape[1])
        distinct[name] = (thr.ravel(), np.tile(per_col, thr.shape[0]))
    if variance_threshold_m < 0:  # v_ij >= 0 everywhere (0 without neighbours or return)
        masks["variance"][:] = True
    ob = OcclusionBoundaries(
        **out,
        variance=masks["variance"],  # range_variance(...) > variance_threshold_m
        tilt=masks["tilt"],
        pan=masks["pan"],
        boundary=masks["tilt"] | masks["pan"],
        near=masks["near"],
        far=masks["far"],
        wrap=bool(wrap),
    )
    ob._distinct.update(distinct)
    return ob


def boundaries_table(image: RangeImage, ob: OcclusionBoundaries) -> pd.DataFrame:
    """Flagged pixels as a table (``BOUNDARY_COLUMNS``): levelled ``x, y, z``; ``tilt_pair`` /
    ``pan_pair`` tell that the pair with the next row / column is flagged (so the pair masks can
    be rebuilt with :func:`pair_masks`); ``ratio`` the largest ``Delta_s / r`` of its pairs."""
    flat = np.flatnonzero(ob.boundary | ob.variance)
    v, u = np.divmod(flat, ob.shape[1])
    xyz, trig = point_source(image)
    pts, ratio, tilt_next, pan_next = kernels.boundary_columns(
        v, u, xyz, image.range_m, trig, ob.tilt_ratio, ob.pan_ratio, ob.tilt_pair, ob.pan_pair,
        ob.wrap,
    )  # fmt: skip
    return pd.DataFrame(
        {
            "row": v.astype(np.int32),
            "col": u.astype(np.int32),
            "range_m": image.range_m.ravel()[flat].astype(np.float32),
            "x": pts[:, 0],
            "y": pts[:, 1],
            "z": pts[:, 2],
            "tilt": ob.tilt.ravel()[flat],
            "pan": ob.pan.ravel()[flat],
            "variance": ob.variance.ravel()[flat],
            "near": ob.near.ravel()[flat],
            "far": ob.far.ravel()[flat],
            "tilt_pair": tilt_next,
            "pan_pair": pan_next,
            "ratio": ratio,
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
