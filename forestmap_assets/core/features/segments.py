"""Scan-line segmentation of a range image (spec 2; Th. 4.6.1, Table 4.1; JP II-A).

Every row of the range image is a horizontal scan line. Each row is

1. filtered with the "blocking object" **max filter** (spec 2.2 step 1): every range is replaced
   by the largest range in a window whose width in pixels is the odd count covering
   ``max_occluder_m`` at the pixel's own range, so that occluders narrower than that vanish;
2. cut into **runs** wherever two consecutive filtered ranges differ by more than
   ``range_step_m`` (or a pixel has no return);
3. each run is **widened back** by the filter's half window (the max filter erodes a near object
   by that much on each side), clipped to the outermost pixels with a return;
4. a run is **accepted** as a segment if its metric width W lies in [min_width_m, max_width_m]
   and it holds at least ``min_points`` inlier measurements;
5. inside a segment every point with ``|r - r_mid| > T_out = 0.5 W + 3 sigma`` (Eq. 4.7) is an
   **outlier**, ``r_mid`` being the filtered range at the middle of the run;
6. segments of adjacent rows whose column intervals overlap and whose ``r_mid`` differ by less
   than ``link_range_step_m`` are **linked** into vertical chains (spec 2.4).

The whole-image passes (window widths, the sparse-table max filter, runs, widening, inlier
counts, chain linking) are numba kernels in :mod:`._segment_kernels`; the per-run arithmetic
left in numpy (chord widths, T_out) is vectorised over the runs. There is no Python loop over
rows or pixels.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.features import _segment_kernels as K
from forestmap_assets.core.features.range_image import RangeImage, levelling_rotation
from forestmap_assets.params import SegmentationParams

SEGMENT_COLUMNS: dict[str, str] = {
    "segment_id": "int64",
    "row": "int64",
    "col0": "int64",
    "col1": "int64",
    "n_points": "int64",
    "n_inliers": "int64",
    "width_m": "float64",
    "r_mid": "float64",
    "t_out_m": "float64",
    "half_window_px": "int64",
    "elevation_deg": "float64",
    "azimuth_mid_deg": "float64",
    "chain_id": "int64",
}


def empty_segments() -> pd.DataFrame:
    """A well-formed segment table with no rows."""
    return pd.DataFrame({k: pd.Series([], dtype=v) for k, v in SEGMENT_COLUMNS.items()})


def _angular_step_rad(values_deg: np.ndarray) -> float:
    if values_deg.size < 2:
        return np.radians(0.108)
    return float(np.radians(np.median(np.abs(np.diff(values_deg)))))


def occluder_window(range_m: np.ndarray, elevation_deg: np.ndarray, azimuth_step_rad: float,
                    max_occluder_m: float, max_window_px: int = 101) -> np.ndarray:
    """Odd window width (pixels) of the blocking-object max filter at each pixel (spec 2.2).

    The width is the smallest odd integer >= ``max_occluder_m / pitch + 1`` where
    ``pitch = r cos(el) d_az`` is the metric horizontal pixel pitch at the pixel's own range
    (inferred: horizontal pitch of a row at elevation el). Capped at ``max_window_px``
    (inferred). No-return pixels get width 1.
    """
    r = np.asarray(range_m)
    if r.dtype not in (np.float32, np.float64):
        r = r.astype(np.float64)
    cos_el = np.cos(np.radians(elevation_deg))[:, None]
    shape = np.broadcast_shapes(r.shape, cos_el.shape)  # numpy broadcasting of r * cos_el
    r = np.broadcast_to(r, shape).reshape(int(np.prod(shape[:-1])), shape[-1])
    cos_rows = np.broadcast_to(cos_el, shape[:-1] + (1,)).reshape(-1)
    w = K.occluder_window(r, cos_rows, float(azimuth_step_rad), float(max_occluder_m),
                          float(max_window_px))
    return w.reshape(shape)


def blocking_max_filter(range_m: np.ndarray, window_px: np.ndarray) -> np.ndarray:
    """Row-wise max filter with a per-pixel odd window (spec 2.2 step 1).

    No-return pixels are ignored inside windows and stay NaN. Uses a per-row sparse table of
    power-of-two running maxima (numba kernel), so the cost is O(pixels log(max window)).
    """
    r = np.asarray(range_m)
    if r.dtype not in (np.float32, np.float64):
        r = r.astype(np.float64)
    if r.ndim != 2:
        raise ValueError(f"range_m: expected a 2-D array, got shape {r.shape}")
    return K.max_filter(r, np.broadcast_to(np.asarray(window_px), r.shape))


def _chord(r0: np.ndarray, r1: np.ndarray, az0: np.ndarray, az1: np.ndarray,
           el: np.ndarray) -> np.ndarray:
    """Euclidean distance between two points of one scan line (same elevation)."""
    ce, se = np.cos(el), np.sin(el)
    p0 = np.stack([r0 * ce * np.cos(az0), r0 * ce * np.sin(az0), r0 * se], -1)
    p1 = np.stack([r1 * ce * np.cos(az1), r1 * ce * np.sin(az1), r1 * se], -1)
    return np.linalg.norm(p1 - p0, axis=-1)


def feature_scan_lines(image: RangeImage, min_line_step_deg: float) -> RangeImage:
    """The scan lines the segments and circle models work on (inferred, issue 16): every k-th
    row of ``image``, ``k = floor(1.05 min_line_step_deg / row step)`` (at least 1), so that the
    rows are no closer than ``min_line_step_deg`` (within 5 %). A scan at the thesis' 0.108 deg
    (spec 1.1) keeps every row; a 0.1 deg scan keeps every second. The columns stay whole, so
    each segment keeps all its points across the stem; the circle models collect the
    neighbouring rows within +-collect_height_m along the axis, which 0.2 deg rows still fill
    (2+ rows at 30 m). Segment and circle rows are rows of the returned image."""
    step = image.elevation_step_deg
    k = int(np.floor(1.05 * min_line_step_deg / step)) if step > 0 and min_line_step_deg > 0 else 1
    if k <= 1:
        return image
    rows = slice(None, None, k)

    def thin(a):
        return None if a is None else a[rows]

    return RangeImage(image.range_m[rows], image.azimuth_deg, image.elevation_deg[rows], image.tilt_deg,
                      thin(image.intensity), thin(image.rgb), thin(image.points))


def segment_scan_lines(image: RangeImage, params: SegmentationParams | None = None, *,
                       max_window_px: int = 101) -> pd.DataFrame:
    """Scan-line segments of ``image`` (spec 2.2-2.4, Eq. 4.7), one row per accepted segment.

    Columns: ``segment_id, row, col0, col1`` (widened run, inclusive), ``n_points`` (returns in
    the run), ``n_inliers`` (returns passing the T_out gate), ``width_m`` (W: chord between the
    run's end pixels at the filtered end ranges, inferred), ``r_mid`` (filtered range at the
    run's middle), ``t_out_m`` (Eq. 4.7), ``half_window_px``, ``elevation_deg``,
    ``azimuth_mid_deg``, ``chain_id`` (vertical overlap chain, spec 2.4). Inlier pixels are
    recovered with :func:`segment_pixels` / :func:`segment_mask`.
    """
    p = params or SegmentationParams()
    rng = np.asarray(image.range_m, np.float32)
    if rng.size == 0 or not np.isfinite(rng).any():
        return empty_segments()
    rows, cols = rng.shape
    az = np.radians(image.azimuth_deg)
    el = np.radians(image.elevation_deg)
    daz = _angular_step_rad(image.azimuth_deg)
    window = occluder_window(rng, image.elevation_deg, daz, p.max_occluder_m, max_window_px)
    filt = blocking_max_filter(rng, window)

    # --- runs of the filtered profile (spec 2.2 step 2), on the flattened image ------------
    f = filt.ravel()
    starts, ends = K.find_runs(filt, K.weak_threshold(filt.dtype, p.range_step_m))
    if starts.size == 0:
        return empty_segments()
    row = starts // cols
    s_col, e_col = starts - row * cols, ends - row * cols
    mid = (starts + ends) // 2
    r_mid = f[mid].astype(np.float64)

    # --- widen back by the half window at r_mid, clip to pixels with a return (step 3) ------
    w_mid = occluder_window(r_mid[:, None], image.elevation_deg[row], daz, p.max_occluder_m,
                            max_window_px)[:, 0]
    hw = (w_mid - 1) // 2
    c0, c1, n_points = K.widen_runs(rng.ravel(), cols, row, s_col, e_col, hw)

    # --- width W and acceptance (step 3) ---------------------------------------------------
    width = _chord(f[starts].astype(np.float64), f[ends].astype(np.float64), az[c0], az[c1],
                   el[row])
    keep = (width >= p.min_width_m) & (width <= p.max_width_m) & (n_points >= p.min_points)
    if not keep.any():
        return empty_segments()
    row, c0, c1, r_mid, width, n_points, hw, s_col, e_col = (
        a[keep] for a in (row, c0, c1, r_mid, width, n_points, hw, s_col, e_col))

    # --- outlier gate T_out = 0.5 W + 3 sigma (Eq. 4.7, step 4) ----------------------------
    t_out = 0.5 * width + p.outlier_sigmas * p.range_sigma_m
    n_inl = K.inlier_counts(rng, row, c0, c1, r_mid, t_out)
    keep = n_inl >= p.min_points
    if not keep.any():
        return empty_segments()
    df = pd.DataFrame({
        "segment_id": np.arange(int(keep.sum()), dtype=np.int64),
        "row": row[keep].astype(np.int64),
        "col0": c0[keep].astype(np.int64),
        "col1": c1[keep].astype(np.int64),
        "n_points": n_points[keep].astype(np.int64),
        "n_inliers": n_inl[keep],
        "width_m": width[keep],
        "r_mid": r_mid[keep],
        "t_out_m": t_out[keep],
        "half_window_px": hw[keep].astype(np.int64),
        "elevation_deg": image.elevation_deg[row[keep]].astype(np.float64),
        "azimuth_mid_deg": image.azimuth_deg[(c0[keep] + c1[keep]) // 2].astype(np.float64),
    })
    df["chain_id"] = link_chains(df, cols, p.link_range_step_m)
    return df.astype(SEGMENT_COLUMNS)


def _expand(row: np.ndarray, c0: np.ndarray, c1: np.ndarray):
    """(segment index, row, col) of every pixel of every interval [c0, c1] of ``row``."""
    n = (c1 - c0 + 1).astype(np.int64)
    seg = np.repeat(np.arange(n.size), n)
    first = np.concatenate([[0], np.cumsum(n)[:-1]])
    col = c0[seg] + (np.arange(seg.size) - first[seg])
    return seg, row[seg], col


def link_chains(segments: pd.DataFrame, cols: int, link_range_step_m: float) -> np.ndarray:
    """Vertical chain label per segment (spec 2.4): adjacent rows, overlapping column intervals,
    ``|delta r_mid| <= link_range_step_m`` (inferred); connected components, numbered in order
    of their first segment. ``cols`` (the image width) is not needed by the union-find kernel
    and is kept for callers."""
    n = len(segments)
    if n == 0:
        return np.zeros(0, np.int64)
    row = segments["row"].to_numpy(np.int64)
    c0 = segments["col0"].to_numpy(np.int64)
    c1 = segments["col1"].to_numpy(np.int64)
    rm = segments["r_mid"].to_numpy()
    if rm.dtype not in (np.float32, np.float64):
        rm = rm.astype(np.float64)
    order = np.lexsort((c0, row))
    return K.chain_labels(row, c0, c1, rm, K.weak_threshold(rm.dtype, link_range_step_m), order)


def segment_pixels(image: RangeImage, segments: pd.DataFrame, *, inliers_only: bool = True):
    """Pixels of every segment: ``(segment_index, row, col, inlier)`` arrays, grouped by segment.

    ``segment_index`` is the positional index into ``segments``. With ``inliers_only`` only
    pixels passing the T_out gate (Eq. 4.7) are returned (``inlier`` then all True).
    """
    if len(segments) == 0:
        z = np.zeros(0, np.int64)
        return z, z, z, np.zeros(0, bool)
    row = segments["row"].to_numpy(np.int64)
    seg, pr, pc = _expand(row, segments["col0"].to_numpy(np.int64),
                          segments["col1"].to_numpy(np.int64))
    rr = image.range_m[pr, pc]
    with np.errstate(invalid="ignore"):
        inl = np.abs(rr - segments["r_mid"].to_numpy()[seg]) <= segments["t_out_m"].to_numpy()[seg]
    if inliers_only:
        return seg[inl], pr[inl], pc[inl], inl[inl]
    return seg, pr, pc, inl


def segment_mask(image: RangeImage, segments: pd.DataFrame) -> np.ndarray:
    """Boolean (rows, cols) image of segment inlier pixels (the Fig. 4.9 / 4.15b artefact)."""
    mask = np.zeros(image.shape, bool)
    _, pr, pc, _ = segment_pixels(image, segments)
    mask[pr, pc] = True
    return mask


def pixel_xyz(image: RangeImage, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """Levelled xyz (n, 3) of the given pixels, without building the whole point image."""
    if image._xyz is not None:
        return image._xyz[row, col]
    if image.points is not None:  # each pixel's own point (io/projection.py)
        pts = image.points[row, col].astype(np.float64)
        return pts @ levelling_rotation(*image.tilt_deg).T if any(image.tilt_deg) else pts
    r = image.range_m[row, col].astype(np.float64)
    az = np.radians(image.azimuth_deg[col])
    el = np.radians(image.elevation_deg[row])
    ce = np.cos(el)
    pts = np.stack([r * ce * np.cos(az), r * ce * np.sin(az), r * np.sin(el)], -1)
    if any(image.tilt_deg):
        pts = pts @ levelling_rotation(*image.tilt_deg).T
    return pts
