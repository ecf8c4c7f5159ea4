"""Candidate screening without a prior: a cheap stem-layout comparison of every scan pair
(inferred, issue 17).

A campaign without priors would otherwise search every pair of scans by branch and bound
(quadratic in the scans). Before that search, each pair is scored by how many of its stems can be
laid onto each other by one rigid 2-D motion (the levelled frames differ only by a heading and a
translation), as stem-map matchers do (inferred, issue 17):

1. **Stems** of a scan (:func:`stems_from_cylinders`): the cylinder segments' axes evaluated at
   breast height of the levelled frame (``z_m``, clamped to each segment), segments of one stem
   merged within ``merge_m``, with their radius (length-weighted over the segments near
   ``z_m``). :func:`stems_from_submap` gives positions without radii from a sub-map.
2. **Pair signatures**: every stem pair of a scan with its distance (``min_pair_m`` to
   ``max_pair_m``) and the two radii; rotation- and translation-invariant.
3. **Hypotheses**: a stem pair of one scan and a stem pair of the other whose distances agree
   within ``dist_tol_m`` and whose radii agree (``radius_tol_m`` or ``radius_tol_rel``, the
   larger) fix a 2-D motion; the motions vote in bins of ``heading_bin_deg`` and ``shift_bin_m``.
4. **Score**: the mean motions of the ``top`` most voted bins are checked: the number of stems
   of the scan that land within ``inlier_m`` of a stem of the reference with a compatible
   radius (one-to-one, counted on the side with fewer). The best motion is refitted once by
   least squares on its matches. The score of the pair is the largest count; its motion is
   returned too (the location of ``scan`` in the frame of ``reference``, spec 6.1 convention).

:func:`screen_scores` scores every pair of a campaign (each scan's pair table is built once) and
:func:`keep_best` keeps each scan's best ``keep`` partners and a maximum spanning tree of the
scores; the union grows at most as ``(keep + 1) * N`` (linear in the scans). With
``close_loops`` it adds, across a kept pair on no loop, the best pair that puts it on one
(issue 16, :mod:`.link_graph`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pandas as pd

from forestmap_assets.core.cloud import single_linkage
from forestmap_assets.core.registration.link_graph import bridge_sides, crosses

STEM_COLUMNS = ("x", "y", "radius_m")


@dataclass(frozen=True)
class ScreenSettings:
    """Tolerances of the stem-layout comparison (all inferred, issue 17)."""

    dist_tol_m: float = 0.12
    radius_tol_m: float = 0.03
    radius_tol_rel: float = 0.25
    min_pair_m: float = 1.0
    max_pair_m: float = 20.0
    heading_bin_deg: float = 4.0
    shift_bin_m: float = 0.6
    inlier_m: float = 0.25
    top: int = 8
    max_hypotheses: int = 200_000


def stems_from_cylinders(cylinders: pd.DataFrame | None, *, z_m: float = 0.0, band_m: float = 1.5,
                         merge_m: float = 0.4) -> np.ndarray:
    """Stems (n, 3): ``x, y, radius_m`` of a scan's cylinder segments in its levelled frame
    (inferred, issue 17).

    Each segment's axis is evaluated at ``z_m`` (clamped to the segment); segments whose axis
    points fall within ``merge_m`` of each other are one stem. The radius is the length-weighted
    mean of the stem's segments whose height range comes within ``band_m`` of ``z_m`` (else of
    all its segments).
    """
    if cylinders is None or len(cylinders) == 0:
        return np.zeros((0, 3))
    p0 = cylinders[["x0", "y0", "z0"]].to_numpy(float)
    p1 = cylinders[["x1", "y1", "z1"]].to_numpy(float)
    radius = cylinders["radius_m"].to_numpy(float)
    dz = p1[:, 2] - p0[:, 2]
    t = np.clip(np.divide(z_m - p0[:, 2], dz, out=np.zeros_like(dz), where=np.abs(dz) > 1e-9), 0.0, 1.0)
    xy = p0[:, :2] + t[:, None] * (p1[:, :2] - p0[:, :2])
    length = np.maximum(np.linalg.norm(p1 - p0, axis=1), 1e-3)
    zlo, zhi = np.minimum(p0[:, 2], p1[:, 2]), np.maximum(p0[:, 2], p1[:, 2])
    near = (zhi >= z_m - band_m) & (zlo <= z_m + band_m)
    ok = np.isfinite(xy).all(axis=1) & np.isfinite(radius)
    xy, radius, length, near = xy[ok], radius[ok], length[ok], near[ok]
    if len(xy) == 0:
        return np.zeros((0, 3))
    label = single_linkage(xy, merge_m)[1]
    out = []
    for lab in np.unique(label):
        m = label == lab
        w = length[m] * np.where(near[m].any(), near[m], True)
        centre = np.average(xy[m], axis=0, weights=length[m])
        out.append((centre[0], centre[1], float(np.average(radius[m], weights=w))))
    return np.array(out, dtype=float).reshape(-1, 3)


def stems_from_submap(submap: pd.DataFrame | None, *, merge_m: float = 0.4) -> np.ndarray:
    """Stems (n, 3) ``x, y, NaN`` from a sub-map's cylinder points (no radii; inferred, issue 17):
    the mean position of each cylinder's points, cylinders within ``merge_m`` merged."""
    if submap is None or len(submap) == 0:
        return np.zeros((0, 3))
    cyl = submap[submap["feature"] == "cylinder"]
    if len(cyl) == 0:
        return np.zeros((0, 3))
    xy = cyl.groupby("feature_id")[["x", "y"]].mean().to_numpy(float)
    label = single_linkage(xy, merge_m)[1]
    centres = np.array([xy[label == lab].mean(axis=0) for lab in np.unique(label)])
    return np.column_stack([centres, np.full(len(centres), np.nan)])


@dataclass(frozen=True)
class _PairTable:
    """Every stem pair (i, j), i != j, of one scan sorted by distance (both orders kept)."""

    stems: np.ndarray
    i: np.ndarray
    j: np.ndarray
    d: np.ndarray


def pair_table(stems: np.ndarray, settings: ScreenSettings = ScreenSettings()) -> _PairTable:
    """The rotation- and translation-invariant signature of a scan (inferred, issue 17): all
    ordered stem pairs within ``min_pair_m .. max_pair_m``, sorted by their distance."""
    stems = np.asarray(stems, dtype=float).reshape(-1, 3)
    n = len(stems)
    i, j = np.nonzero(~np.eye(n, dtype=bool))
    d = np.hypot(*(stems[j, :2] - stems[i, :2]).T) if n else np.zeros(0)
    keep = (d >= settings.min_pair_m) & (d <= settings.max_pair_m)
    order = np.argsort(d[keep], kind="stable")
    return _PairTable(stems, i[keep][order], j[keep][order], d[keep][order])


def _radius_ok(ra: np.ndarray, rb: np.ndarray, s: ScreenSettings) -> np.ndarray:
    tol = np.maximum(s.radius_tol_m, s.radius_tol_rel * np.fmax(ra, rb))
    return ~(np.abs(ra - rb) > tol)  # NaN radii (sub-map stems) always agree


def _hypotheses(ref: _PairTable, scan: _PairTable, s: ScreenSettings) -> np.ndarray:
    """Motions (m, 3) ``x, y, heading_rad`` of ``scan`` in the frame of ``ref`` from every
    reference pair (i < j) matched to a scan pair (k, l) of similar length and radii."""
    upper = ref.i < ref.j
    ai, aj, ad = ref.i[upper], ref.j[upper], ref.d[upper]
    lo = np.searchsorted(scan.d, ad - s.dist_tol_m, side="left")
    hi = np.searchsorted(scan.d, ad + s.dist_tol_m, side="right")
    counts = hi - lo
    total = int(counts.sum())
    if total == 0:
        return np.zeros((0, 3))
    if total > s.max_hypotheses:  # cap the work: keep the shortest reference pairs first
        keep = np.cumsum(counts) <= s.max_hypotheses
        ai, aj, lo, counts = ai[keep], aj[keep], lo[keep], counts[keep]
        total = int(counts.sum())
    a = np.repeat(np.arange(len(ai)), counts)
    b = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts) + lo[a]
    pi, pj, qk, ql = ai[a], aj[a], scan.i[b], scan.j[b]
    rs, qs = ref.stems, scan.stems
    ok = _radius_ok(rs[pi, 2], qs[qk, 2], s) & _radius_ok(rs[pj, 2], qs[ql, 2], s)
    pi, pj, qk, ql = pi[ok], pj[ok], qk[ok], ql[ok]
    va, vb = rs[pj, :2] - rs[pi, :2], qs[ql, :2] - qs[qk, :2]
    h = np.arctan2(va[:, 1], va[:, 0]) - np.arctan2(vb[:, 1], vb[:, 0])
    c, sn = np.cos(h), np.sin(h)
    mb = 0.5 * (qs[qk, :2] + qs[ql, :2])
    ma = 0.5 * (rs[pi, :2] + rs[pj, :2])
    t = ma - np.column_stack([c * mb[:, 0] - sn * mb[:, 1], sn * mb[:, 0] + c * mb[:, 1]])
    return np.column_stack([t, h])


def _counts(ref: np.ndarray, scan: np.ndarray, motions: np.ndarray, s: ScreenSettings):
    """For each motion (m, 3) ``x, y, heading_rad``: the number of one-to-one stem matches
    (scan stems within ``inlier_m`` of a radius-compatible reference stem, counted on the side
    with fewer), and each scan stem's nearest compatible reference stem (-1: none)."""
    c, sn = np.cos(motions[:, 2])[:, None], np.sin(motions[:, 2])[:, None]
    px = c * scan[None, :, 0] - sn * scan[None, :, 1] + motions[:, 0:1]
    py = sn * scan[None, :, 0] + c * scan[None, :, 1] + motions[:, 1:2]
    d2 = (px[:, :, None] - ref[None, None, :, 0]) ** 2 + (py[:, :, None] - ref[None, None, :, 1]) ** 2
    ok = (d2 < s.inlier_m**2) & _radius_ok(scan[:, 2][:, None], ref[:, 2][None, :], s)[None]
    count = np.minimum(ok.any(axis=2).sum(axis=1), ok.any(axis=1).sum(axis=1))
    nearest = np.where(ok.any(axis=2), np.argmin(np.where(ok, d2, np.inf), axis=2), -1)
    return count, nearest


def _fit(a: np.ndarray, b: np.ndarray):
    """Least-squares 2-D motion (x, y, heading_rad) taking points ``b`` onto ``a``."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    da, db = a - ca, b - cb
    h = np.arctan2((db[:, 0] * da[:, 1] - db[:, 1] * da[:, 0]).sum(), (db * da).sum())
    c, sn = np.cos(h), np.sin(h)
    t = ca - np.array([c * cb[0] - sn * cb[1], sn * cb[0] + c * cb[1]])
    return np.array([t[0], t[1], h])


def screen_pair(ref: _PairTable | np.ndarray, scan: _PairTable | np.ndarray,
                settings: ScreenSettings = ScreenSettings()):
    """Score of one pair (inferred, issue 17): the most stems of ``scan`` one rigid 2-D motion
    lays onto stems of ``ref`` (module docstring), and that motion ``(x, y, heading_deg)`` (the
    location of ``scan`` in the levelled frame of ``ref``; None when no stem pair matched).

    ``ref`` and ``scan`` are stem arrays (n, 3) ``x, y, radius_m`` or their :func:`pair_table`.
    """
    s = settings
    ref = ref if isinstance(ref, _PairTable) else pair_table(ref, s)
    scan = scan if isinstance(scan, _PairTable) else pair_table(scan, s)
    if len(ref.d) == 0 or len(scan.d) == 0:
        return 0, None
    hyp = _hypotheses(ref, scan, s)
    if len(hyp) == 0:
        return 0, None
    nb = max(1, int(round(360.0 / s.heading_bin_deg)))
    hb = np.mod(np.floor(np.mod(hyp[:, 2], 2 * np.pi) / (2 * np.pi) * nb), nb).astype(np.int64)
    xb = np.floor(hyp[:, 0] / s.shift_bin_m).astype(np.int64)
    yb = np.floor(hyp[:, 1] / s.shift_bin_m).astype(np.int64)
    xb -= xb.min()
    yb -= yb.min()
    key = (hb * (xb.max() + 1) + xb) * (yb.max() + 1) + yb
    _, inverse, votes = np.unique(key, return_inverse=True, return_counts=True)
    best_bins = np.argsort(-votes, kind="stable")[: s.top]
    slot = np.full(len(votes), -1)
    slot[best_bins] = np.arange(len(best_bins))
    member = slot[inverse.ravel()]
    m = member >= 0
    n = np.bincount(member[m], minlength=len(best_bins)).astype(float)
    mean = lambda v: np.bincount(member[m], weights=v[m], minlength=len(best_bins)) / n  # noqa: E731
    motions = np.column_stack([mean(hyp[:, 0]), mean(hyp[:, 1]),
                               np.arctan2(mean(np.sin(hyp[:, 2])), mean(np.cos(hyp[:, 2])))])
    count, nearest = _counts(ref.stems, scan.stems, motions, s)
    k = int(np.argmax(count))
    motion, best = motions[k], int(count[k])
    matched = nearest[k] >= 0
    if matched.sum() >= 2:  # one least-squares refit on the best motion's matches
        refit = _fit(ref.stems[nearest[k][matched], :2], scan.stems[matched, :2])
        c2, _ = _counts(ref.stems, scan.stems, refit[None], s)
        if int(c2[0]) >= best:
            motion, best = refit, int(c2[0])
    x, y, h = (float(v) for v in motion)
    return best, (x, y, float(np.degrees(np.arctan2(np.sin(h), np.cos(h)))))


def screen_scores(stems: dict[str, np.ndarray], settings: ScreenSettings = ScreenSettings(),
                  progress=None) -> pd.DataFrame:
    """Score every unordered scan pair (inferred, issue 17): columns ``scan, reference`` (the
    later scan of ``stems``' order located in the earlier's frame, as :mod:`.candidates`),
    ``score`` (matched stems), ``x, y, heading_deg`` (the screening motion, NaN without one)."""
    start = time.perf_counter()
    ids = list(stems)
    tables = {sid: pair_table(stems[sid], settings) for sid in ids}
    rows = []
    for a in range(len(ids)):
        for b in range(a + 1, len(ids)):
            ref, scan = ids[a], ids[b]
            score, motion = screen_pair(tables[ref], tables[scan], settings)
            x, y, h = motion if motion is not None else (np.nan, np.nan, np.nan)
            rows.append(dict(scan=scan, reference=ref, score=int(score), x=x, y=y, heading_deg=h))
    if progress:
        progress(f"screening: {len(rows)} pairs of {len(ids)} scans in {time.perf_counter() - start:.1f} s")
    return pd.DataFrame(rows, columns=["scan", "reference", "score", "x", "y", "heading_deg"])


def keep_best(scores: pd.DataFrame, keep: int, close_loops: bool = False, min_score: int = 3) -> set[tuple[str, str]]:
    """The pairs to search (inferred, issue 17): the union over scans of each scan's ``keep``
    best-scoring partners, plus a maximum spanning tree of the scores (so a scan in a sparse
    stretch keeps its best link to the rest even when its neighbours prefer others): at most
    ``(keep + 1) * N`` ``(scan, reference)`` rows of ``scores``. Ties go to the pair listed first;
    ``keep <= 0`` keeps every pair. ``close_loops`` (issue 16): while a kept pair lies on no loop
    (:func:`~.link_graph.bridges`, a link the residuals could not check), the best pair across
    it with at least ``min_score`` matched stems is added."""
    all_pairs = list(zip(scores["scan"], scores["reference"], strict=True))
    if keep <= 0:
        return set(all_pairs)
    value = scores["score"].to_numpy(float)
    order = np.argsort(-value, kind="stable")
    chosen: set[tuple[str, str]] = set()
    taken: dict[str, int] = {}
    parent: dict[str, str] = {}

    def root(a: str) -> str:
        while parent.setdefault(a, a) != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for n in order:  # best first: per-scan quotas and Kruskal's maximum spanning tree
        sc, ref = all_pairs[n]
        if taken.get(sc, 0) < keep or taken.get(ref, 0) < keep or root(sc) != root(ref):
            chosen.add((sc, ref))
        for s in (sc, ref):
            taken[s] = taken.get(s, 0) + 1
        parent[root(sc)] = root(ref)
    return _close_loops(chosen, all_pairs, value, order, min_score) if close_loops else chosen


def _close_loops(chosen: set[tuple[str, str]], all_pairs: list[tuple[str, str]], value: np.ndarray,
                 order: np.ndarray, min_score: int) -> set[tuple[str, str]]:
    """``chosen`` with, for each bridge in turn, the best-scoring pair across it (module
    docstring of :mod:`.link_graph`) while one with ``min_score`` matched stems exists."""
    chosen = set(chosen)
    while True:
        edges = [all_pairs[n] for n in order if all_pairs[n] in chosen]
        for small, large in bridge_sides(edges):
            best = next((all_pairs[n] for n in order if value[n] >= min_score and all_pairs[n] not in chosen
                         and crosses(all_pairs[n], small, large)), None)
            if best is not None:
                chosen.add(best)
                break
        else:
            return chosen
