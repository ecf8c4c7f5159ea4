"""Levelling scans from the data: each scan's roll and pitch relative to the reference scan,
from the stems the registered pairs share (beyond the thesis, which levels every scan by its
measured roll and pitch, spec 1.2; inferred).

The method is 4-DoF (x, y, z, heading): a scan whose file is not levelled and whose campaign
entry gives no ``tilt_deg`` is registered with its tilt left in, and a tilt of 0.5 deg moves the
ground 17 cm at 20 m (Sylva's ``simulate_survey(levelled=False)``: z errors up to 15 cm). A
stem is about vertical in every scan's own frame, so the tilt between two scans shows as a lean
of one scan's copy of a stem against the other's. Per accepted pair (scan ``i`` placed in the
frame of reference ``j`` by ``(dx, dy, dz, heading)``), the horizontal offset ``d(z)`` between
the two scans' axes of a stem changes over height by ``s = dd/dz``, which a small rotation ``w``
of ``i`` against ``j`` makes ``s = (w_y, -w_x)`` (:func:`link_tilt`: every stem's whole height
is the lever). In the scan's frame ``delta = R_z(-heading) w``, and with each scan's tilt
``t_i`` (small angles; ``levelling_rotation(roll, pitch) ~ I + [(roll, pitch, 0)]x``)::

    delta_ij = t_i - R_z(-heading_ij) t_j

which :func:`solve_tilts` solves by weighted least squares with the reference's tilt fixed at
0 (the map's frame is the reference scan's, levelled as its entry says). Sylva's unlevelled
seed 44: the scans' tilts to 0.03 deg; levelled surveys read at most 0.02-0.06 deg (Sylva,
rendered, own circular) and up to 0.32 deg (the own simulator's realistic stems and wide beam),
hence :func:`needs_levelling`'s rules (``benchmarks/results.md``, "levelling").
"""

from __future__ import annotations

import numpy as np
import pandas as pd

TILT_COLUMNS = ["tilt_x_deg", "tilt_y_deg", "sd_tilt_deg", "n_tilt"]


def link_tilt(scan_cyl: pd.DataFrame, ref_cyl: pd.DataFrame, pose, *, match_m: float = 0.1,
              min_overlap_m: float = 0.3, huber_m: float = 0.01, min_stems: int = 8,
              ref_stems: np.ndarray | None = None) -> dict:
    """Tilt of scan ``i`` against reference ``j`` in ``i``'s frame (module docstring):
    ``tilt_x_deg, tilt_y_deg``, its sd ``sd_tilt_deg`` and the stems it came from ``n_tilt``
    (NaN and 0 with fewer than ``min_stems``). ``pose``: ``(dx, dy, dz, heading_deg)`` of ``i``
    in ``j``; cylinders: ``x0, y0, z0, x1, y1, z1, radius_m, n_circles`` in each scan's frame.

    Each pair of cylinders that share ``min_overlap_m`` of height and meet within ``match_m``
    gives the two axes' offset ``d`` at both ends of their common heights; the reference's
    cylinders are grouped into stems (:func:`~.stem_groups.group_stems`), and ``d = c_stem + s z``
    is fitted with one intercept per stem and one ``s`` for all (Huber, ``huber_m``), so a
    stem's whole height is the lever (weights: common height times circles); its sd is
    clustered by stem. ``ref_stems``: the reference's stem labels when already known
    (:func:`~.stem_groups.group_stems` of ``ref_cyl``; a scan is the reference of several pairs)."""
    from forestmap_assets.core.geometry import transform_points
    from forestmap_assets.core.mapping.stem_groups import axis_xy, ends, group_stems

    out = dict(zip(TILT_COLUMNS, [np.nan, np.nan, np.nan, 0], strict=True))
    if len(scan_cyl) == 0 or len(ref_cyl) == 0:
        return out
    h = np.radians(float(pose[3]))
    c, s = np.cos(h), np.sin(h)
    ea = ends(scan_cyl)  # the scan's cylinders in the reference's frame
    ea = np.hstack([transform_points(ea[:, :3], pose), transform_points(ea[:, 3:], pose)])
    eb = ends(ref_cyl)
    lo_a, hi_a = np.minimum(ea[:, 2], ea[:, 5]), np.maximum(ea[:, 2], ea[:, 5])
    lo_b, hi_b = np.minimum(eb[:, 2], eb[:, 5]), np.maximum(eb[:, 2], eb[:, 5])
    lo = np.maximum(lo_a[:, None], lo_b[None])
    hi = np.minimum(hi_a[:, None], hi_b[None])
    ia, ib = np.nonzero(hi - lo >= min_overlap_m)
    if not ia.size:
        return out
    z = np.stack([lo[ia, ib], hi[ia, ib]], axis=1)
    d = np.stack([axis_xy(eb[ib], z[:, k]) - axis_xy(ea[ia], z[:, k]) for k in range(2)], axis=1)  # (k, 2 heights, xy)
    near = np.hypot(*d.mean(axis=1).T) <= match_m
    stem = (group_stems(ref_cyl) if ref_stems is None else np.asarray(ref_stems))[ib[near]]
    n_circ = np.minimum(scan_cyl["n_circles"].to_numpy(float)[ia], ref_cyl["n_circles"].to_numpy(float)[ib])[near]
    w = np.repeat((z[near, 1] - z[near, 0]) * np.maximum(n_circ, 1.0), 2)
    zz, dd, g = z[near].ravel(), d[near].reshape(-1, 2), np.repeat(stem, 2)
    _, g = np.unique(g, return_inverse=True)
    n_g = g.max() + 1 if g.size else 0
    # stems whose common heights span at least a metre carry the slope
    top = np.full(n_g, -np.inf)
    bottom = np.full(n_g, np.inf)
    np.maximum.at(top, g, zz)
    np.minimum.at(bottom, g, zz)
    levers = int(((top - bottom) >= 1.0).sum()) if n_g else 0
    if levers < min_stems:
        return out
    slope = np.zeros(2)
    ww = w.copy()
    for _ in range(15):  # one intercept per stem, one slope; Huber weights on the residuals
        sw = np.bincount(g, ww, n_g)
        zm = np.bincount(g, ww * zz, n_g) / sw
        dm = np.column_stack([np.bincount(g, ww * dd[:, k], n_g) / sw for k in range(2)])
        zc, dc = zz - zm[g], dd - dm[g]
        sxx = np.sum(ww * zc**2)
        if sxx <= 0:
            return out
        slope = (ww * zc) @ dc / sxx
        r = np.hypot(*(dc - zc[:, None] * slope).T)
        ww = w * np.minimum(1.0, huber_m / np.maximum(r, 1e-12))
    # sd clustered by stem (a stem's offsets share its axis errors): sum over stems of the
    # squared scores, G / (G - 1), both components pooled
    res = dc - zc[:, None] * slope
    score = np.column_stack([np.bincount(g, ww * zc * res[:, k], n_g) for k in range(2)])
    sd = float(np.sqrt(np.sum(score**2) / 2.0 * n_g / max(n_g - 1, 1)) / sxx)
    wx, wy = -slope[1], slope[0]  # s = (w_y, -w_x), in the reference's frame
    tx, ty = c * wx + s * wy, -s * wx + c * wy  # R_z(-heading) w: the scan's frame
    return dict(zip(TILT_COLUMNS, [float(np.degrees(tx)), float(np.degrees(ty)), float(np.degrees(sd)), levers],
                    strict=True))


def solve_tilts(links: pd.DataFrame, scans: list[str], reference: str, *, sd_floor_deg: float = 0.005,
                reject_sigmas: float = 4.0) -> pd.DataFrame:
    """Each scan's tilt against ``reference`` (``scan, roll_deg, pitch_deg, sd_deg, n_links``;
    NaN for a scan no measured link reaches; ``dof`` the network's redundant equations) from the pairs' tilts (``links``: ``scan,
    reference, dheading_deg`` and :data:`TILT_COLUMNS`), weighted least squares of the module
    docstring's equation with the sd floored at ``sd_floor_deg``; a link more than
    ``reject_sigmas`` sd from the solution is left out (the worst first) and the rest solved
    again."""
    scans = [str(s) for s in scans]
    free = [s for s in scans if s != reference]
    col = {s: k for k, s in enumerate(free)}
    ok = links["tilt_x_deg"].notna().to_numpy() if len(links) else np.zeros(0, bool)
    use = links[ok].reset_index(drop=True)
    keep = np.ones(len(use), bool)
    x = np.zeros(2 * len(free))
    cov = np.full((2 * len(free), 2 * len(free)), np.nan)
    reached = np.zeros(len(free), bool)
    dof = 0
    for _ in range(len(use) + 1):
        rows, rhs, wts, used = [], [], [], []
        for k, r in use[keep].iterrows():
            i, j = str(r["scan"]), str(r["reference"])
            if i not in col and i != reference or j not in col and j != reference or i == j:
                continue
            h = np.radians(float(r["dheading_deg"]))
            rot = np.array([[np.cos(h), np.sin(h)], [-np.sin(h), np.cos(h)]])  # R_z(-heading)
            a = np.zeros((2, 2 * len(free)))
            if i in col:
                a[:, 2 * col[i]:2 * col[i] + 2] = np.eye(2)
            if j in col:
                a[:, 2 * col[j]:2 * col[j] + 2] = -rot
            rows.append(a)
            used.append(k)
            rhs.append(np.radians([r["tilt_x_deg"], r["tilt_y_deg"]]))
            wts.append(np.full(2, 1.0 / np.radians(max(float(r["sd_tilt_deg"]), sd_floor_deg)) ** 2))
        if not rows or not free:
            break
        a, b, w = np.vstack(rows), np.concatenate(rhs), np.concatenate(wts)
        reached = np.abs(a).reshape(-1, len(free), 2).sum(axis=(0, 2)) > 0
        idx = np.flatnonzero(np.repeat(reached, 2))
        sub = a[:, idx]
        normal = sub.T @ (sub * w[:, None])
        x = np.zeros(2 * len(free))
        x[idx] = np.linalg.lstsq(normal, sub.T @ (w * b), rcond=None)[0]
        cov = np.full((2 * len(free), 2 * len(free)), np.nan)
        cov[np.ix_(idx, idx)] = np.linalg.pinv(normal)
        res = np.hypot(*(a @ x - b).reshape(-1, 2).T) * np.sqrt(w[::2])
        dof = b.size - idx.size
        if res.max() <= reject_sigmas:
            # links that disagree beyond their sd around loops widen every sd (variance factor)
            cov *= max(1.0, float(np.sum(res**2)) / dof) if dof >= 2 else 1.0
            break
        keep[used[int(np.argmax(res))]] = False  # the worst link out, then solved again
    n_links = {s: 0 for s in scans}
    for r in use[keep].itertuples():
        n_links[str(r.scan)] = n_links.get(str(r.scan), 0) + 1
        n_links[str(r.reference)] = n_links.get(str(r.reference), 0) + 1
    out = []
    for s in scans:
        if s == reference:
            out.append((s, 0.0, 0.0, 0.0, n_links[s]))
        elif reached[col[s]]:
            k = 2 * col[s]
            sd = float(np.degrees(np.sqrt(max(np.nanmax(np.diag(cov)[k:k + 2]), 0.0))))
            out.append((s, float(np.degrees(x[k])), float(np.degrees(x[k + 1])), sd, n_links[s]))
        else:
            out.append((s, np.nan, np.nan, np.nan, 0))
    tilts = pd.DataFrame(out, columns=["scan", "roll_deg", "pitch_deg", "sd_deg", "n_links"])
    return tilts.assign(dof=int(dof))


def needs_levelling(tilts: pd.DataFrame, min_tilt_deg: float, sigmas: float, min_dof: int = 2) -> pd.DataFrame:
    """The scans whose tilt is at least ``min_tilt_deg`` and ``sigmas`` times its sd, in a
    network of pair tilts with ``min_dof`` or more redundant equations (loops that check the
    tilts and scale their sd; a chain of pairs cannot tell a tilt from a biased pair)."""
    size = np.hypot(tilts["roll_deg"], tilts["pitch_deg"])
    checked = tilts["dof"].to_numpy() >= min_dof if "dof" in tilts else np.zeros(len(tilts), bool)
    return tilts[((size >= min_tilt_deg) & (size >= sigmas * tilts["sd_deg"])).to_numpy() & checked]


def compose_tilt(current_deg, correction_deg) -> tuple[float, float]:
    """Roll and pitch that level a scan already levelled by ``current_deg`` and then found tilted
    by ``correction_deg`` against the reference: ``L = L(correction) L(current)``, ``L`` the
    levelling rotation ``R_y(pitch) R_x(roll)`` (the small heading it leaves is the
    registration's to find)."""
    from forestmap_assets.core.features.range_image import levelling_rotation
    from forestmap_assets.core.geometry import roll_pitch_heading

    roll, pitch, _ = roll_pitch_heading(levelling_rotation(*correction_deg) @ levelling_rotation(*current_deg))
    return roll, pitch


def widen_levelled_links(links: pd.DataFrame, tilt_sd_deg: dict[str, float], floor_deg: float) -> pd.DataFrame:
    """Links (``scan, reference, dx, dy, sd_z``) with the z sd of a scan levelled by an estimate
    (``tilt_sd_deg``: scan -> that estimate's sd; others are not levelled here): a tilt left in
    moves z by the tilt times the distance, so ``sd_z^2 + (baseline x tilt)^2``, the tilt the
    root sum of the two scans' sd, each at least ``floor_deg`` (the estimate's own sd leaves
    out the stems' common lean: Sylva's unlevelled surveys, z 0.1-0.6 cm off at 10-15 m)."""
    if not tilt_sd_deg or links.empty:
        return links
    def sd(scan):
        return np.array([max(tilt_sd_deg[s], floor_deg) if s in tilt_sd_deg else 0.0 for s in scan])
    tilt = np.radians(np.hypot(sd(links["scan"].astype(str)), sd(links["reference"].astype(str))))
    out = links.copy()
    out["sd_z"] = np.hypot(out["sd_z"].to_numpy(float), np.hypot(out["dx"], out["dy"]).to_numpy(float) * tilt)
    return out
