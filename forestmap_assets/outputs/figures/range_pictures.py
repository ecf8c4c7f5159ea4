"""Small pictures of one scan's range image for the Dagster UI (segments, circles, cylinders,
occlusion boundaries over the range image), drawn straight from the arrays with Pillow: a per-scan
step pays milliseconds for its picture instead of a matplotlib figure's layout (issue 16). The
caption says what the axes and colours are; notebooks draw the full figures
(:mod:`.range_images`)."""

from __future__ import annotations

import io

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.outputs.figures.common import Picture
from forestmap_assets.outputs.figures.range_images import angles_extent, range_limits

NO_RETURN_RGB = (207, 227, 245)  # figures.common.NO_RETURN
MASK_RGB, MASK_ALPHA = (230, 13, 13), 0.85
OUTLINE_RGB = (255, 140, 0)


def block_reduce(a: np.ndarray, f: int, how: np.ufunc) -> np.ndarray:
    """``a`` (rows, cols) reduced over ``f`` x ``f`` blocks by the ufunc ``how`` (``np.fmin``:
    the least, NaN only where the whole block is; ``np.logical_or``: any), edges padded with
    the fill value; ``f - 1`` element-wise passes per axis over strided rows, then columns
    (``np.nanmin`` over both axes of the blocks took half of a picture's time)."""
    if f == 1:
        return a
    rows, cols = a.shape
    pr, pc = -rows % f, -cols % f
    fill = np.nan if a.dtype.kind == "f" else False
    if pr or pc:
        a = np.pad(a, ((0, pr), (0, pc)), constant_values=fill)
    rows = a[0::f]
    for k in range(1, f):
        rows = how(rows, a[k::f])
    out = rows[:, 0::f]
    for k in range(1, f):
        out = how(out, rows[:, k::f])
    return out


def range_mask_picture(
    image: RangeImage,
    mask: np.ndarray | None,
    title: str,
    *,
    label: str = "mask",
    outlines: list[np.ndarray] | None = None,
    outline_label: str = "cylinder segments",
    max_width: int = 900,
) -> Picture:
    """The range image in grey (near = dark, robust limits :func:`.range_images.range_limits`,
    pale blue = no return) with a boolean ``mask`` in red and optional ``outlines`` (polygons of
    azimuth/elevation degrees, :func:`.range_images.cylinder_outlines`) in orange; at most
    ``max_width`` pixels wide (blocks of pixels: the nearest range, any mask pixel)."""
    from PIL import Image, ImageDraw

    rows, cols = image.shape
    f = max(1, -(-cols // max_width))
    lo, hi = range_limits(image)
    rng = np.where(image.valid, image.range_m, np.nan).astype(np.float32)
    near = block_reduce(rng, f, np.fmin)  # an all-empty block is no return (NaN)
    grey = np.clip((near - lo) / max(hi - lo, 1e-9), 0.0, 1.0) * 255.0
    rgb = np.repeat(np.nan_to_num(grey, nan=0.0)[..., None], 3, axis=2)
    rgb[np.isnan(near)] = NO_RETURN_RGB
    caption = title
    if mask is not None and mask.any():
        m = block_reduce(np.asarray(mask, bool), f, np.logical_or)
        rgb[m] = (1 - MASK_ALPHA) * rgb[m] + MASK_ALPHA * np.asarray(MASK_RGB, float)
        caption = f"{caption} (red: {label}, {int(np.count_nonzero(mask))} pixels)"
    picture = Image.fromarray(rgb.astype(np.uint8), "RGB")
    a0, a1, e0, e1 = angles_extent(image)
    if outlines:
        draw = ImageDraw.Draw(picture)
        w, h = picture.size
        for poly in outlines:
            x = (poly[:, 0] - a0) / (a1 - a0) * cols / f
            y = (e1 - poly[:, 1]) / (e1 - e0) * rows / f
            draw.line(list(zip(x.tolist(), y.tolist(), strict=True)), fill=OUTLINE_RGB, width=1)
        caption = f"{caption} (orange: {len(outlines)} {outline_label})"
    buf = io.BytesIO()
    picture.save(buf, format="PNG", compress_level=1)
    caption += (
        f"; columns: azimuth {a0:.0f} to {a1:.0f} deg, rows: elevation {e1:.0f} (top) to"
        f" {e0:.0f} deg; grey: range {lo:g}-{hi:g} m (near = dark), pale blue: no return"
        + (f"; 1 pixel = {f} x {f} image pixels" if f > 1 else "")
    )
    return Picture(buf.getvalue(), caption)
