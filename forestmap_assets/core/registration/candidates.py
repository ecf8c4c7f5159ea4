"""Which sub-map pairs to register, with their search boxes (spec 6.4, 6.6; DESIGN.md 2).

Three sources, in order of precedence:

* ``pairs``: the campaign's explicit a priori alignments; one row each, box centred on it.
* ``a_priori``: global poses of the scans (GNSS/compass). Two scans can overlap when their
  distance is at most the sum of their reaches (or ``max_distance_m`` without reaches); each scan
  is paired with at most its ``k_nearest`` overlapping neighbours, so a long campaign yields at
  most ``k_nearest * N`` pairs (linear growth, inferred). Centre = the relative pose of the priors.
* neither: every pair, with the no-prior box of DESIGN.md 2: heading the full circle (centre 0,
  half-width 180 deg), xy half-width the smaller of the two reaches capped at ``max_xy_m``
  (inferred), z half-width from ``search``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.geometry import relative_pose

CANDIDATE_COLUMNS = (
    "scan", "reference", "cx", "cy", "cz", "cheading_deg", "hx", "hy", "hz", "hheading_deg",
    "source", "box_heading_deg",
)


def _table(rows: list[dict]) -> pd.DataFrame:
    df = pd.DataFrame(rows, columns=list(CANDIDATE_COLUMNS))
    df["box_heading_deg"] = df["box_heading_deg"].fillna(0.0)
    for c in (*CANDIDATE_COLUMNS[2:10], "box_heading_deg"):
        df[c] = df[c].astype(float)
    df["scan"] = df["scan"].astype(object)
    df["reference"] = df["reference"].astype(object)
    df["source"] = df["source"].astype(object)
    return df


def candidate_pairs(
    scan_ids,
    *,
    pairs=None,
    a_priori: dict | None = None,
    search=(5.0, 1.25, 60.0),
    reach: dict | None = None,
    k_nearest: int = 4,
    max_distance_m: float = 30.0,
    max_xy_m: float = 20.0,
) -> pd.DataFrame:
    """Candidate pairs ``scan, reference`` with box centre ``cx, cy, cz, cheading_deg`` and
    half-widths ``hx, hy, hz, hheading_deg`` (the location of ``scan`` in the levelled frame of
    ``reference``, spec 6.1) and ``source`` ('pairs' | 'a_priori' | 'no_prior').

    ``pairs`` rows are (scan, reference, a_priori[, search]) with an optional per-pair box
    override (:func:`~.pair_checks.search_box`: e.g. narrow across a corridor; the box's axes
    are turned by ``box_heading_deg``, 0 unless ``along_deg`` is given).
    ``search`` = (xy_m, z_m, heading_deg) half-widths; ``reach`` = {scan id: largest horizontal
    distance of its sub-map points from its origin}. ``k_nearest``, ``max_distance_m`` and
    ``max_xy_m`` are (inferred) parameters.
    """
    ids = [str(s) for s in scan_ids]
    xy_m, z_m, heading_deg = (float(v) for v in search)
    rows: list[dict] = []
    if pairs:
        from forestmap_assets.core.registration.pair_checks import search_box

        for scan, ref, prior, *box in pairs:
            dx, dy, dz, dh = (float(v) for v in prior)
            hx, hy, hz, hh, axes = search_box((xy_m, z_m, heading_deg),
                                              dict(box[0]) if box and box[0] else None)
            rows.append(dict(scan=str(scan), reference=str(ref), cx=dx, cy=dy, cz=dz,
                             cheading_deg=dh, hx=hx, hy=hy, hz=hz, hheading_deg=hh,
                             source="pairs", box_heading_deg=axes))
        return _table(rows)
    if a_priori:
        known = [s for s in ids if s in {str(k) for k in a_priori}]
        poses = {str(k): tuple(float(x) for x in v) for k, v in a_priori.items()}
        if len(known) < 2:
            return _table(rows)
        xy = np.array([poses[s][:2] for s in known])
        dist = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
        if reach:
            r = np.array([float(reach.get(s, max_distance_m / 2)) for s in known])
            limit = r[:, None] + r[None, :]
        else:
            limit = np.full(dist.shape, max_distance_m)
        ok = (dist <= limit) & ~np.eye(len(known), dtype=bool)
        rank = np.argsort(np.where(ok, dist, np.inf), axis=1)[:, :k_nearest]
        chosen = np.zeros_like(ok)
        np.put_along_axis(chosen, rank, True, axis=1)
        chosen &= ok
        i_idx, j_idx = np.nonzero(np.triu(chosen | chosen.T, 1))
        for i, j in zip(i_idx, j_idx, strict=True):  # one row per selected pair
            rel = relative_pose(poses[known[j]], poses[known[i]])
            rows.append(dict(scan=known[j], reference=known[i], cx=rel[0], cy=rel[1], cz=rel[2],
                             cheading_deg=rel[3], hx=xy_m, hy=xy_m, hz=z_m,
                             hheading_deg=heading_deg, source="a_priori"))
        return _table(rows)
    for i in range(len(ids)):
        for j in range(i + 1, len(ids)):
            if reach and ids[i] in reach and ids[j] in reach:
                h = min(float(reach[ids[i]]), float(reach[ids[j]]), max_xy_m)
            else:
                h = max(xy_m, max_xy_m) if reach is None else xy_m
            rows.append(dict(scan=ids[j], reference=ids[i], cx=0.0, cy=0.0, cz=0.0,
                             cheading_deg=0.0, hx=h, hy=h, hz=z_m, hheading_deg=180.0,
                             source="no_prior"))
    return _table(rows)
