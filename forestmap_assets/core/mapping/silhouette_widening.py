"""How much wider the silhouettes read than the stems, where the campaign names no beam (issue 19,
inferred): a renderer's splats, another scanner's footprint.

:func:`campaign_widening` measures it on the campaign's own trees, as caliper less reference DBH
against the edges' range. Near the scanners the reference is the merged slice's DBH (trees whose
slice saw enough of the circumference): a line ``a + b r`` (Theil-Sen slope, never negative: a
beam's footprint grows with range) or, with too few trees or too short a range for a slope, a
constant. A constant is only known out to the farthest such tree: a splat of fixed size widens the
near stems most and the far ones not at all (rendered plots 70 m wide: 2.2 cm measured within
14 m, about 0 beyond 20 m), a beam the far ones most. Beyond that range the widening is the median
of caliper less cylinder DBH over the farther trees, reached linearly from the last slice tree's
range (the cylinders' DBH: within 0.4 cm of the truth at every range on Sylva's surveys; on the
rendered ones splat-widened too within about 12 m, +1.5 to +2.6 cm, and within 0.8 cm beyond);
with too few farther trees it falls linearly to none at ``taper`` times that range
(``benchmarks/results.md``, "widening_range")."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd


@dataclass(frozen=True)
class Widening:
    """A DBH widening against range: the line ``a + b r`` out to ``near_m``; beyond it linear
    from the line's value there to ``far`` at ``far_at_m``, then ``far`` (``near_m`` infinite:
    the line everywhere)."""

    a: float = 0.0
    b: float = 0.0
    near_m: float = np.inf
    far_at_m: float = np.inf
    far: float = 0.0

    def __bool__(self) -> bool:
        return bool(self.a or self.b or self.far)

    def __call__(self, range_m: np.ndarray) -> np.ndarray:
        r = np.asarray(range_m, dtype=float)
        w = self.a + self.b * r
        if not np.isfinite(self.near_m):
            return w
        beyond = np.interp(r, (self.near_m, self.far_at_m), (self.a + self.b * self.near_m, self.far))
        return np.where(r > self.near_m, beyond, w)

    @property
    def far_m(self) -> float:
        """The widening beyond the slice trees' range (NaN: the line holds everywhere)."""
        return self.far if np.isfinite(self.near_m) else float("nan")


def campaign_widening(calipers: pd.DataFrame, slice_dbh_m: np.ndarray, range_m: np.ndarray,
                      min_trees: int, cylinder_dbh_m: np.ndarray | None = None,
                      taper: float = 1.5) -> Widening:
    """The campaign's :class:`Widening` (module docstring) from its ``calipers`` (whole widths;
    lone sides left out), the merged-slice and cylinder DBH by tree row (NaN where none) and the
    trees' median edge range ``range_m``: with ``2 min_trees`` slice trees over more than 5 m of
    range a line, with ``min_trees`` a constant, else none; a constant continues beyond the
    slice trees as the cylinders say (``min_trees`` farther trees) or falls to none by ``taper``
    times their range. Rendered surveys: about -0.6 to +2.2 cm near the scanners; Sylva's: +1.3
    to +2.5 cm plus up to 0.23 cm per metre."""
    whole = calipers[~calipers["lone_sides"].to_numpy(bool)]
    t = whole["tree"].to_numpy(int)
    cal = whole["caliper_dbh_m"].to_numpy(float)
    ref, r = slice_dbh_m[t], range_m[t]
    ok = np.isfinite(ref) & np.isfinite(r) & np.isfinite(cal)
    if ok.sum() < max(min_trees, 1):
        return Widening()
    d, rs = cal[ok] - ref[ok], r[ok]
    if ok.sum() >= 2 * min_trees and np.ptp(rs) > 5.0:  # robust: a few trees' slices are off
        i, j = np.triu_indices(len(rs), 1)  # Theil-Sen: the median of the pairs' slopes
        apart = np.abs(rs[j] - rs[i]) > 1e-9
        slope = max(float(np.median((d[j] - d[i])[apart] / (rs[j] - rs[i])[apart])), 0.0)
        if slope > 0.0:  # a footprint that grows with range: the line holds beyond the slices too
            return Widening(float(np.median(d - slope * rs)), slope)
    a, near = float(np.median(d)), float(rs.max())
    if cylinder_dbh_m is not None:
        cyl = cylinder_dbh_m[t]
        far = (r > near) & np.isfinite(r) & np.isfinite(cyl) & np.isfinite(cal)
        if far.sum() >= max(min_trees, 1):
            return Widening(a, 0.0, near, float(r[far].min()), float(np.median(cal[far] - cyl[far])))
    return Widening(a, 0.0, near, taper * near, 0.0)
