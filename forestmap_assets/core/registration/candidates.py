"""Which sub-map pairs to register, with their search boxes (spec 6.4, 6.6; DESIGN.md 2).

Three sources, in order of precedence:

* ``pairs``: the campaign's explicit a priori alignments; one row each, box centred on it.
* ``a_priori``: global poses of the scans (GNSS/compass). Two scans can overlap when their
  distance is at most the sum of their reaches (or ``max_distance_m`` without reaches); each scan
  is paired with at most its ``k_nearest`` overlapping neighbours, so a long campaign yields at
  most ``k_nearest * N`` pairs (linear growth, inferred). Centre = the relative pose of the priors.
* neither: every pair, with the no-prior box of DESIGN.md 2: heading the full circle (centre 0,
  half-width 180 deg), xy half-width the smaller of the two reaches capped at ``max_xy_m``
  (inferred), z half-width from ``search``. With the scans' ``stems`` and ``screen_keep`` > 0,
  only each scan's ``screen_keep`` best partners by the stem-layout screening of
  :mod:`.screening` (inferred, issue 17): the union grows at most as ``screen_keep * N``;
  campaigns of at most ``screen_keep + 1`` scans keep every pair. A kept pair on no loop gets
  the best pair across it added (issue 16: every link checked by a loop's residuals,
  :mod:`.link_graph`). ``screen_score`` (matched stems; NaN where not screened) is in the table
  either way.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.geometry import relative_pose
from forestmap_assets.core.registration.link_graph import bridge_sides
from forestmap_assets.core.registration.screening import (
    ScreenSettings,
    keep_best,
    pair_table,
    screen_pair,
    screen_scores,
)

CANDIDATE_COLUMNS = (
    "scan", "reference", "cx", "cy", "cz", "cheading_deg", "hx", "hy", "hz", "hheading_deg",
    "source", "box_heading_deg", "screen_score",
)


def _table(rows: list[dict]) -> pd.DataFrame:
    df = pd.DataFrame(rows, columns=list(CANDIDATE_COLUMNS))
    df["box_heading_deg"] = df["box_heading_deg"].fillna(0.0)
    for c in (*CANDIDATE_COLUMNS[2:10], "box_heading_deg", "screen_score"):
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
    stems: dict | None = None,
    screen_keep: int = 0,
    screen_settings=None,
    screen_centre_min: int = 0,
    screen_box: tuple[float, float] | None = None,
    progress=None,
) -> pd.DataFrame:
    """Candidate pairs ``scan, reference`` with box centre ``cx, cy, cz, cheading_deg`` and
    half-widths ``hx, hy, hz, hheading_deg`` (the location of ``scan`` in the levelled frame of
    ``reference``, spec 6.1) and ``source`` ('pairs' | 'a_priori' | 'no_prior').

    ``pairs`` rows are (scan, reference, a_priori[, search]) with an optional per-pair box
    override (:func:`~.pair_checks.search_box`: e.g. narrow across a corridor; the box's axes
    are turned by ``box_heading_deg``, 0 unless ``along_deg`` is given).
    ``search`` = (xy_m, z_m, heading_deg) half-widths; ``reach`` = {scan id: largest horizontal
    distance of its sub-map points from its origin}. ``k_nearest``, ``max_distance_m`` and
    ``max_xy_m`` are (inferred) parameters. ``stems`` = {scan id: (n, 3) ``x, y, radius_m``} and
    ``screen_keep`` screen the no-prior pairs (module docstring; ``screen_settings``: a
    :class:`~.screening.ScreenSettings`). A kept pair whose screening matched at least
    ``screen_centre_min`` (> 0) stems is centred on the screening motion and searched in the
    ``screen_box`` (xy m, heading deg; default the ``search`` box), as around an a priori alignment (``source = 'screened'``; the Fourier
    candidates do the same, men spec 4.4); the pairwise stage searches it again with the
    no-prior box when that fails (inferred, issue 17).
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
    score: dict[tuple[str, str], float] = {}
    motion: dict[tuple[str, str], tuple[float, float, float]] = {}
    kept = None
    if stems is not None and screen_keep > 0:
        empty = np.zeros((0, 3))
        table = screen_scores({s: np.asarray(stems.get(s, empty), float) for s in ids},
                              screen_settings or ScreenSettings(), progress=progress)
        score = {(r.scan, r.reference): float(r.score) for r in table.itertuples(index=False)}
        motion = {(r.scan, r.reference): (float(r.x), float(r.y), float(r.heading_deg))
                  for r in table.itertuples(index=False)}
        if len(ids) > screen_keep + 1:
            kept = keep_best(table, screen_keep, close_loops=True)
    for i in range(len(ids)):
        for j in range(i + 1, len(ids)):
            if kept is not None and (ids[j], ids[i]) not in kept:
                continue
            row = _no_prior_row(ids[j], ids[i], reach, xy_m, z_m, max_xy_m, score.get((ids[j], ids[i]), np.nan))
            m = motion.get((ids[j], ids[i]))
            if screen_centre_min > 0 and row["screen_score"] >= screen_centre_min and m and np.all(np.isfinite(m)):
                bx, bh = screen_box or (xy_m, heading_deg)
                row.update(cx=m[0], cy=m[1], cheading_deg=m[2], hx=bx, hy=bx, hheading_deg=bh, source="screened")
            rows.append(row)
    return _table(rows)


def widened(candidates: pd.DataFrame, reach=None, z_m: float = 1.25, max_xy_m: float = 20.0,
            xy_m: float = 5.0) -> pd.DataFrame:
    """The ``screened`` rows of ``candidates`` with the no-prior box again (centre 0, heading
    the full circle): the second search of a pair whose screening-centred search failed."""
    rows = [_no_prior_row(r.scan, r.reference, reach, xy_m, z_m, max_xy_m, r.screen_score)
            for r in candidates.itertuples(index=False) if r.source == "screened"]
    return _table(rows)


def _no_prior_row(scan: str, ref: str, reach, xy_m: float, z_m: float, max_xy_m: float, score) -> dict:
    """A no-prior candidate row (module docstring's box)."""
    if reach and ref in reach and scan in reach:
        h = min(float(reach[ref]), float(reach[scan]), max_xy_m)
    else:
        h = max(xy_m, max_xy_m) if reach is None else xy_m
    return dict(scan=scan, reference=ref, cx=0.0, cy=0.0, cz=0.0, cheading_deg=0.0, hx=h, hy=h,
                hz=z_m, hheading_deg=180.0, source="no_prior", screen_score=score)


def no_candidates() -> pd.DataFrame:
    """An empty candidate table (``CANDIDATE_COLUMNS`` with their dtypes)."""
    return _table([])


def largest_group(scan_ids, registrations: pd.DataFrame) -> list[str]:
    """The largest group of ``scan_ids`` that the accepted ``registrations`` link (ties: the
    one holding the earliest scan), in ``scan_ids`` order."""
    ids = [str(s) for s in scan_ids]
    parent = {s: s for s in ids}

    def root(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    ok = registrations[registrations["status"] == "accepted"] if len(registrations) else registrations
    for a, b in zip(ok["scan"] if len(ok) else [], ok["reference"] if len(ok) else [], strict=True):
        if a in parent and b in parent:
            parent[root(a)] = root(b)
    groups: dict[str, list[str]] = {}
    for s in ids:
        groups.setdefault(root(s), []).append(s)
    return max(groups.values(), key=len) if groups else []


def _accepted_links(registrations: pd.DataFrame) -> list[tuple[str, str]]:
    ok = registrations[registrations["status"] == "accepted"] if len(registrations) else registrations
    links = zip(ok["scan"], ok["reference"], strict=True) if len(ok) else []
    return list(dict.fromkeys((str(a), str(b)) for a, b in links if a != b))


def weak_links(scan_ids, registrations: pd.DataFrame) -> list[tuple[set[str], set[str]]]:
    """Where the accepted ``registrations`` leave the scans weakly held (inferred, issues 16-17):
    ``[(outside, group)]`` when scans lie outside the largest linked group (:func:`largest_group`),
    else one ``(smaller side, larger side)`` per accepted link on no loop (a bridge, whose error
    no residual would show; :mod:`.link_graph`). Empty when every link is on a loop."""
    return _weak(scan_ids, registrations)[0]


def _weak(scan_ids, registrations: pd.DataFrame) -> tuple[list[tuple[set[str], set[str]]], bool]:
    """:func:`weak_links`, and whether they are the unplaced scans (True) or bridges."""
    ids = [str(s) for s in scan_ids]
    main = largest_group(ids, registrations)
    if len(main) < len(ids):
        return [({s for s in ids if s not in main}, set(main))], True
    return bridge_sides([e for e in _accepted_links(registrations) if e[0] in main and e[1] in main]), False


def retry_candidates(
    scan_ids,
    candidates: pd.DataFrame,
    registrations: pd.DataFrame,
    stems: dict,
    *,
    keep: int = 4,
    search=(5.0, 1.25, 60.0),
    reach: dict | None = None,
    max_xy_m: float = 20.0,
    screen_settings=None,
    min_score: int = 3,
) -> pd.DataFrame:
    """No-prior candidate rows to retry the scans left unplaced or held by a link on no loop
    (inferred, issues 16-17; :func:`weak_links`).

    Unplaced: every scan outside the largest group the accepted ``registrations`` link (ties:
    the one holding the earliest scan of ``scan_ids``) is screened against the scans of that
    group, and its ``keep`` best partners not yet in ``candidates`` with at least ``min_score``
    matched stems are returned (two stems always match by chance; same box as
    :func:`candidate_pairs`, ``scan`` the later of the two in ``scan_ids``). Otherwise, for each
    accepted link on no loop, the ``keep`` best such pairs across it (a failed pair of the
    screened set, which closes a loop over every link it keeps). Empty when every scan is placed
    and every link is on a loop.
    """
    ids = [str(s) for s in scan_ids]
    weak, unplaced = _weak(ids, registrations)
    if not weak:
        return no_candidates()
    searched = {frozenset(p) for p in zip(candidates["scan"], candidates["reference"], strict=True)}
    settings = screen_settings or ScreenSettings()
    empty = np.zeros((0, 3))
    table: dict = {}
    order = {s: n for n, s in enumerate(ids)}
    rows, added = [], set()
    for small, large in weak:  # unplaced: each scan's best partners; a bridge: the best across it
        across = []
        for u in sorted(small, key=order.get):
            scored = []
            for m in sorted(large, key=order.get):
                if frozenset((u, m)) in searched or frozenset((u, m)) in added:
                    continue
                ref, scan = sorted((u, m), key=order.get)
                for s in (ref, scan):
                    if s not in table:
                        table[s] = pair_table(np.asarray(stems.get(s, empty), float), settings)
                score = screen_pair(table[ref], table[scan], settings)[0]
                if score >= min_score:
                    scored.append((-score, order[m], scan, ref))
            across += sorted(scored)[:keep] if unplaced else scored
        for neg, _, scan, ref in across if unplaced else sorted(across)[:keep]:
            added.add(frozenset((scan, ref)))
            rows.append(_no_prior_row(scan, ref, reach, float(search[0]), float(search[1]), max_xy_m,
                                      float(-neg)))
    return _table(rows)
