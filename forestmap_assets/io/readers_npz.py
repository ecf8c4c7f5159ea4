"""Reader of ``.npz`` organised range images (spec 1.2, DESIGN section 2): read as they are."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.io.readers_common import BadScan, check_signature, to_rgb8


def _npz_array(z, key: str, *, required: bool = True) -> np.ndarray | None:
    if key not in z.files:
        if required:
            raise BadScan(f"missing array '{key}'")
        return None
    arr = z[key]
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise BadScan(f"array '{key}' is not numeric (dtype {arr.dtype})")
    return arr


def read_npz(path: Path, angular_step_deg) -> RangeImage:
    check_signature(path, (b"PK\x03\x04", b"PK\x05\x06"), "an NPZ archive")
    with np.load(path, allow_pickle=False) as z:
        rng = _npz_array(z, "range")
        az = _npz_array(z, "azimuth_deg")
        el = _npz_array(z, "elevation_deg")
        intensity = _npz_array(z, "intensity", required=False)
        rgb = _npz_array(z, "rgb", required=False)
    if rng.ndim != 2 or 0 in rng.shape:
        raise BadScan(f"array 'range' must be 2-D (rows x cols), got shape {rng.shape}")
    rows, cols = rng.shape
    if az.shape != (cols,):
        raise BadScan(f"array 'azimuth_deg' has shape {az.shape}, expected ({cols},)")
    if el.shape != (rows,):
        raise BadScan(f"array 'elevation_deg' has shape {el.shape}, expected ({rows},)")
    if intensity is not None and intensity.shape != (rows, cols):
        raise BadScan(f"array 'intensity' has shape {intensity.shape}, expected {(rows, cols)}")
    if rgb is not None and rgb.shape != (rows, cols, 3):
        raise BadScan(f"array 'rgb' has shape {rgb.shape}, expected {(rows, cols, 3)}")
    az = az.astype(np.float64)
    el = el.astype(np.float64)
    rng = rng.astype(np.float32)
    if not (np.all(np.isfinite(az)) and np.all(np.isfinite(el))):
        raise BadScan("arrays 'azimuth_deg'/'elevation_deg' must be finite")
    if np.any(np.abs(el) > 90.0):
        raise BadScan("array 'elevation_deg' has values outside [-90, 90]")
    # RangeImage convention: azimuth increasing, elevation decreasing (row 0 on top)
    flip_c = cols > 1 and np.all(np.diff(az) < 0)
    flip_r = rows > 1 and np.all(np.diff(el) > 0)
    if cols > 1 and not (flip_c or np.all(np.diff(az) > 0)):
        raise BadScan("array 'azimuth_deg' is not strictly monotonic")
    if rows > 1 and not (flip_r or np.all(np.diff(el) < 0)):
        raise BadScan("array 'elevation_deg' is not strictly monotonic")
    sl = (slice(None, None, -1 if flip_r else 1), slice(None, None, -1 if flip_c else 1))
    if rgb is not None:
        rgb = to_rgb8(rgb.reshape(-1, 3)).reshape(rows, cols, 3)[sl]
    if intensity is not None:
        intensity = intensity.astype(np.float32)[sl]
    return RangeImage(rng[sl], az[sl[1]], el[sl[0]], intensity=intensity, rgb=rgb)
