"""A scale of the whole network from the refinement's two objectives (issue 19, inferred).

The symmetric two-way refinement (sum of both points' normals) and the model-normal one of
Men 2012 agree where two scans see the same surfaces. Where every scan sees its surfaces
widened towards itself (a wide beam's mixed pixels, the splats of scans rendered inside a
registered cloud) the symmetric objective lengthens every baseline by about the same share:
+0.32 and +0.39 mm/m between the objectives on the links of the rendered surveys 1-2 (t = 11,
12), their true error +0.45 and +0.31 mm/m; those errors do not average out in the network,
and a scan 15 m from the reference was 5.5 mm off where its sigma said 1.9 mm. On exact rays
(Sylva's simulator) the model's normal is the biased one, shorter by up to 0.4 mm/m, and the
difference cannot tell which objective is off: it is a sigma here, not a correction. Taken
link by link (``refine.objective_sd_scope="link"``, the earlier rule) its noise made the
sigmas of Sylva's surveys along the baselines up to twice the link's other terms.

So the refinement records each link's difference along its baseline
(:func:`~forestmap_assets.core.registration.two_way.objective_spread`), and here only the part
common to all links counts: per metre of baseline over the refined links, the median when the
mean is at least ``t_min`` standard errors from zero, else none (:func:`objective_scale`). Each
refined link's sigma along its baseline then takes ``|s| L`` (:func:`widen_links`) and each
scan's x, y sigma the network's scale about the reference, ``|s| |x|``, ``|s| |y|``
(:func:`scale_sd`).

A second, independent estimate of the network's scale is in the branch-and-bound poses: the
stems' axes, not the raw points. Neither is free of bias (renders: the stems' baselines 0.1-0.3
mm/m shorter than the truth; Sylva's simulator 0.2 mm/m longer; the own 3 mrad beam 0.5 mm/m
shorter), but where the raw points' scale is off by much, the two part by much: renders with 12
mm splats, the refined links (scale not taken out) +0.96 mm/m, the stems' -0.17 mm/m. So half
their mean difference per metre over the refined links (:func:`stem_gap`,
``mapping.stem_gap_share``) is a floor of the scans' scale sigma: error / sd x, y on renders with
1 cm noise and 12 mm splats 2.13 / 2.18 -> 0.97 / 0.95, with 12 mm splats 1.95 / 2.66 -> 1.23 /
1.53; Sylva 44-79 0.93 / 0.99 -> 0.87 / 0.91, own realistic 0.97 / 1.09 -> 0.93 / 1.04, renders
0.87 / 0.80 -> 0.83 / 0.77 (117 stored surveys; results.md "stem_gap"). Only the part of the gap
beyond ``mapping.stem_gap_free`` (0.3 mm/m) counts (:func:`gap_scale`): the stems' own bias
on Sylva's simulator, +0.14 to +0.37 mm/m, had made Sylva 94-100's x, y sigmas 1.5 times too
wide (error / sd 0.66 / 0.65, now 0.79 / 0.78; results.md "gap_free")."""

from __future__ import annotations

import numpy as np
import pandas as pd

SPREAD = "objective_spread_m"


def _with_spread(links: pd.DataFrame) -> np.ndarray:
    """Refined links that carry an objective difference (the refinement records it only for
    the scope ``"campaign"``)."""
    if SPREAD not in links or links.empty:
        return np.zeros(len(links), bool)
    ok = np.isfinite(links[SPREAD].to_numpy(float))
    if "refined" in links:
        ok &= links["refined"].to_numpy(bool)
    return ok


def objective_scale(links: pd.DataFrame, t_min: float = 3.0, min_links: int = 3) -> tuple[float, float, int]:
    """``(scale, t, n)``: the common difference per metre of baseline (0 when there is none),
    the mean's t statistic and the number of refined links with a difference."""
    ok = _with_spread(links)
    if not ok.any():
        return 0.0, 0.0, 0
    spread = links[SPREAD].to_numpy(float)
    length = np.hypot(links["dx"].to_numpy(float), links["dy"].to_numpy(float))
    ok &= length > 0.5
    n = int(ok.sum())
    if n < max(min_links, 2):
        return 0.0, 0.0, n
    per_m = spread[ok] / length[ok]
    se = float(np.std(per_m, ddof=1)) / np.sqrt(n)
    t = float(np.mean(per_m)) / se if se > 0 else float(np.sign(np.mean(per_m))) * np.inf
    return (float(np.median(per_m)) if abs(t) >= t_min else 0.0), t, n


def shorten_links(links: pd.DataFrame, scale: float) -> pd.DataFrame:
    """``links`` with each refined link's baseline (``dx, dy``) shortened by ``scale`` (per
    metre)."""
    if not scale:
        return links
    out = links.copy()
    hit = _with_spread(links)
    for d in ("dx", "dy"):
        out[d] = np.where(hit, (1.0 - scale) * out[d].to_numpy(float), out[d].to_numpy(float))
    return out


def take_out(links: pd.DataFrame, scale: float, t: float, correct_t: float) -> tuple[pd.DataFrame, float]:
    """``(links, sigma scale)``: where the objectives' common scale is clear (``|t| >=
    correct_t``, ``mapping.objective_scale_correct_t``) the refined links take the model-normal
    objective's length (:func:`shorten_links`) and no scale is left as a sigma (the floor
    ``mapping.scale_sd_floor`` still applies); else the links stay and the scale is a sigma
    (:func:`widen_links`, :func:`scale_sd`). Scans rendered inside a registered cloud, where
    the splats widen every silhouette, differed by 0.28-0.38 mm/m at t 9-16; Sylva's surveys at
    t -0.8 to 4.2 (results.md "scale_taken_out"). Since the refinement takes the splats back
    (``refine.splat_candidates_m``) they differ by 0.07-0.12 mm/m at t 4-7 while the network is
    0.11-0.15 mm/m short, and taking the scale out doubled that: the forest preset keeps
    ``correct_t`` at inf (results.md "scale_kept_in")."""
    if scale and abs(t) >= correct_t:
        return shorten_links(links, scale), 0.0
    return links, scale


def stem_gap(links: pd.DataFrame, refinements: pd.DataFrame | None, min_links: int = 3) -> tuple[float, int]:
    """``(gap, n)``: the mean over the ``n`` refined links (baseline over 0.5 m) of how much
    longer, per metre, the branch-and-bound pose (``refinements``' ``bnb_dx, bnb_dy``) puts the
    baseline than the link's own ``dx, dy``; 0 with fewer than ``min_links`` such links."""
    if refinements is None or refinements.empty or "refined" not in links or links.empty:
        return 0.0, 0
    bnb = refinements[["scan", "reference", "bnb_dx", "bnb_dy"]].drop_duplicates(["scan", "reference"])
    m = links[links["refined"].to_numpy(bool)].merge(bnb, on=["scan", "reference"])
    dx, dy = m["dx"].to_numpy(float), m["dy"].to_numpy(float)
    length2 = dx * dx + dy * dy
    ok = (length2 > 0.25) & np.isfinite(m["bnb_dx"].to_numpy(float))
    if int(ok.sum()) < max(min_links, 1):
        return 0.0, int(ok.sum())
    gap = ((m["bnb_dx"].to_numpy(float) - dx) * dx + (m["bnb_dy"].to_numpy(float) - dy) * dy)[ok] / length2[ok]
    return float(gap.mean()), int(ok.sum())


def gap_scale(gap: float, share: float, free: float = 0.0) -> float:
    """The network scale sigma (per metre) the stems' gap ``gap`` (:func:`stem_gap`) says:
    ``share`` of the part of ``|gap|`` beyond ``free``, the gap the stems' own bias leaves."""
    return share * max(abs(gap) - free, 0.0)


def widen_links(links: pd.DataFrame, scale: float) -> pd.DataFrame:
    """``links`` with each refined link's x, y sigma grown by ``|scale| L`` along its baseline
    (``|scale dx|``, ``|scale dy|`` in quadrature)."""
    if not scale:
        return links
    out = links.copy()
    hit = _with_spread(links)
    for axis, d in (("sd_x", "dx"), ("sd_y", "dy")):
        sd = out[axis].to_numpy(float)
        out[axis] = np.where(hit, np.hypot(sd, scale * out[d].to_numpy(float)), sd)
    return out


def scale_floor(floor: float, wide_beam_floor: float, beam_divergence_mrad: float, wide_above_mrad: float) -> float:
    """The network scale sigma no link shows (per metre, :func:`scale_sd`'s ``floor``): ``floor``,
    or ``wide_beam_floor`` where the campaign's beam diverges by more than ``wide_above_mrad``
    (inferred, issue 19). A wide first-return beam moves each scan's surfaces by part of its
    footprint, differently from each side, and a network of such links comes out contracted or
    stretched: the own simulator's 42 mm + 3 mrad beam, 6-scan surveys, -0.16 to -0.24 mm/m
    on realistic stems and +0.17 mm/m on circular ones (benchmarks/results.md "wide_beam_scale")."""
    return max(floor, wide_beam_floor) if beam_divergence_mrad > wide_above_mrad else floor


def scale_sd(poses: pd.DataFrame, scale: float, floor: float = 0.0) -> pd.DataFrame:
    """``poses`` (the reference at the origin) with the x, y sigma of a network scale
    ``scale`` about the reference added in quadrature: ``|scale x|``, ``|scale y|``; at least
    ``floor`` per metre (a scale that no link shows: ``mapping.scale_sd_floor``)."""
    scale = max(abs(scale), floor)
    if not scale:
        return poses
    out = poses.copy()
    for axis, c in (("sd_x", "x"), ("sd_y", "y")):
        out[axis] = np.hypot(out[axis].to_numpy(float), scale * out[c].to_numpy(float))
    return out
