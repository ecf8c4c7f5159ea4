"""A small picture of the merged elevation map for the Dagster UI (``integrated_map``), drawn
straight from the grid with Pillow, as the per-scan pictures are (:mod:`.range_pictures`): the
campaign's map stages pay tens of milliseconds for it instead of a matplotlib figure's 0.3-0.45 s
(issue 16). The caption says what the colours are; ``elevation.png`` and the report draw the
full figure with axes and colour bar (:func:`.elevation.elevation_figure`)."""

from __future__ import annotations

import io

import numpy as np
import pandas as pd

from forestmap_assets.outputs.figures.common import ELEVATION_CMAP, NO_VALUE, Picture
from forestmap_assets.outputs.figures.elevation import ground_limits
from forestmap_assets.outputs.figures.range_pictures import block_reduce

SCAN_RGB = (0, 0, 0)


def elevation_picture(grid, scans: pd.DataFrame | None, title: str, *, max_width: int = 600) -> Picture:
    """The merged elevation ``grid`` (:class:`~forestmap_assets.core.features.elevation.ElevationGrid`)
    north up in the colours of ``elevation_figure`` (:data:`.common.ELEVATION_CMAP` over the
    robust limits :func:`.elevation.ground_limits`, lighter = higher, grey = no value), the
    ``scans`` (``scan, x, y``) as black dots with their names; at most ``max_width`` pixels wide
    (blocks of cells: each the lowest of its cells)."""
    from matplotlib import colormaps
    from matplotlib.colors import to_rgb
    from PIL import Image, ImageDraw

    z = np.asarray(grid.z, np.float64)
    rows, cols = z.shape
    f = max(1, -(-max(rows, cols) // max_width))
    low = block_reduce(z, f, np.fmin)[::-1]  # row 0 at the top: north up
    lo, hi = ground_limits(grid)
    lut = np.round(colormaps[ELEVATION_CMAP](np.linspace(0.0, 1.0, 256))[:, :3] * 255).astype(np.uint8)
    level = np.clip((np.nan_to_num(low, nan=lo) - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    rgb = lut[np.round(level * 255).astype(np.intp)]
    rgb[np.isnan(low)] = np.round(np.array(to_rgb(NO_VALUE)) * 255).astype(np.uint8)
    picture = Image.fromarray(np.ascontiguousarray(rgb), "RGB")
    n_scans = 0
    if scans is not None and len(scans):
        draw = ImageDraw.Draw(picture)
        size = grid.cell_m * f
        top = grid.y0 + low.shape[0] * size  # the blocks' top edge (the last may be padded)
        for scan, x, y in scans[["scan", "x", "y"]].itertuples(index=False):
            u, v = (x - grid.x0) / size, (top - y) / size
            draw.ellipse((u - 3, v - 3, u + 3, v + 3), fill=SCAN_RGB)
            draw.text((u + 5, v - 6), str(scan), fill=SCAN_RGB)
            n_scans += 1
    buf = io.BytesIO()
    picture.save(buf, format="PNG", compress_level=1)
    x0, x1, y0, y1 = grid.extent
    caption = (
        f"{title}: ground z {lo:.2f} (dark green) to {hi:.2f} m (pale yellow), {grid.mode} hit per "
        f"{grid.cell_m:g} m cell, grey: no value; north up, x {x0:.0f} to {x1:.0f} m, y {y0:.0f} to "
        f"{y1:.0f} m" + (f"; black dots: the {n_scans} placed scans" if n_scans else "")
        + (f"; 1 pixel = {f} x {f} cells (the lowest)" if f > 1 else "")
    )
    return Picture(buf.getvalue(), caption)
