"""The thesis's own next-vantage rule (men_spec 7.2-7.5, Eqs. 6.3-6.7, checklist 23-27):
potential-field heading H,
its zone of 8, the 10 frontier cells of the zone farthest by path, the best aligned one, shrunk
along its A* path
to the farthest cell that passes the overlap rule (50 %)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.exploration.candidates import (
    PROPOSAL_COLUMNS,
    VantagePlan,
    evaluate_positions,
    overlap_constraint,
)
from forestmap_assets.core.exploration.frontier import OBSTACLE, UNMAPPED
from forestmap_assets.core.exploration.paths import astar
from forestmap_assets.params.men import ExplorationConfig


# ---- thesis strategy: preferred heading, zones ---------------------------------------------
def preferred_heading(
    current: np.ndarray,
    unmapped_xy: np.ndarray,
    wall_xy: np.ndarray,
    diagonal: float,
    *,
    w_unmapped: float = 1.0,
    w_wall: float = 1.0,
    min_distance: float = 1e-6,
    tangential_trigger_deg: float = 150.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Potential-field heading (men_spec 7.2, Eqs. 6.3-6.7): ``H = W_u sum K_k u_k - W_w sum K_l
    u_l`` with ``K_k = |x_k - x_i|^2 / D^2`` and ``K_l = D^2 / |x_l - x_i|^2`` (distances clamped
    at ``min_distance``), plus the tangential force ``F_t = (F_w,y, -F_w,x)`` when the attractive
    and repulsive resultants point more than ``tangential_trigger_deg`` apart (inferred trigger).
    Returns ``(H, F_u, F_w)`` with ``F_w`` the repulsive resultant (pointing away from walls)."""
    cur = np.asarray(current, dtype=np.float64)

    def resultant(xy, attract):
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if not len(xy):
            return np.zeros(2)
        v = xy - cur
        d = np.maximum(np.hypot(v[:, 0], v[:, 1]), min_distance)
        unit = v / d[:, None]
        k = d**2 / diagonal**2 if attract else diagonal**2 / d**2
        return (k[:, None] * unit).sum(axis=0)

    f_u = w_unmapped * resultant(unmapped_xy, True)
    f_w = -w_wall * resultant(wall_xy, False)
    h = f_u + f_w
    nu, nw = np.linalg.norm(f_u), np.linalg.norm(f_w)
    if nu > 0 and nw > 0:
        angle = np.degrees(np.arccos(np.clip(f_u @ f_w / (nu * nw), -1, 1)))
        if angle > tangential_trigger_deg:
            h = h + np.array([f_w[1], -f_w[0]])
    return h, f_u, f_w


def zone_of(angles_rad: np.ndarray) -> np.ndarray:
    """Zone 0..7 of directions (45 deg sectors centred on 0, 45, ..., 315 deg; men_spec 7.3)."""
    a = np.mod(np.asarray(angles_rad, dtype=np.float64), 2 * np.pi)
    return (np.floor((a + np.pi / 8) / (np.pi / 4)).astype(int)) % 8


def _angle_diff(a, b):
    return np.abs((np.asarray(a) - b + np.pi) % (2 * np.pi) - np.pi)


def _thesis_row(e, cell, dist: np.ndarray, feasible: bool, source: str) -> dict:
    """A proposal row of the thesis strategy (scored by expected new area alone) from the
    evaluation ``e`` of grid cell ``cell``; ``dist`` the walking distances."""
    return dict(
        x=e.x,
        y=e.y,
        ix=int(cell[0]),
        iy=int(cell[1]),
        expected_new_m2=e.expected_new_m2,
        expected_gain_m2=e.expected_new_m2,
        incomplete_stems=int(e.incomplete_stems),
        overlap_share=e.overlap_share,
        common_stems=int(e.common_stems),
        reference_scan=e.reference_scan,
        visible_stems=int(e.visible_stems),
        path_m=float(dist[cell[0], cell[1]]),
        score=float(e.expected_new_m2),
        feasible=feasible,
        source=source,
    )


def thesis_next_vantage(
    grid,
    classes,
    frontier,
    coverage,
    nav,
    dist,
    pred,
    current,
    stems,
    scan_xy,
    scan_ids,
    config: ExplorationConfig,
) -> VantagePlan:
    """The thesis's rule (men_spec 7.2-7.5, checklist 23-27): preferred heading H, its zone (or the
    zone with most unmapped cells), the 10 frontier cells of the zone farthest by path distance
    (2nd and 3rd kept as backups), the one best aligned with the principal direction, and on its
    A* path the farthest cell whose predicted overlap (visibility, coverage radius) passes the
    overlap rule (``area``: >= 50 %)."""
    xc, yc = grid.centres()
    cur_xy = grid.cell_xy(*current)[0]
    diag = float(np.hypot(grid.nx * grid.cell_m, grid.ny * grid.cell_m))
    unm = np.argwhere((classes == UNMAPPED) & grid.in_plot)
    wall = np.argwhere(classes == OBSTACLE)
    heading, _, _ = preferred_heading(
        cur_xy,
        grid.cell_xy(unm[:, 0], unm[:, 1]),
        grid.cell_xy(wall[:, 0], wall[:, 1]),
        diag,
        w_unmapped=config.w_unmapped,
        w_wall=config.w_wall,
        min_distance=grid.cell_m,
        tangential_trigger_deg=config.tangential_trigger_deg,
    )
    reach = frontier & np.isfinite(dist)
    fc = np.argwhere(reach)
    fz = (
        zone_of(np.arctan2(*(grid.cell_xy(fc[:, 0], fc[:, 1]) - cur_xy)[:, ::-1].T))
        if len(fc)
        else np.zeros(0, int)
    )
    uz = (
        zone_of(np.arctan2(*(grid.cell_xy(unm[:, 0], unm[:, 1]) - cur_xy)[:, ::-1].T))
        if len(unm)
        else np.zeros(0, int)
    )
    counts = np.bincount(uz, minlength=8)
    if config.zone_rule == "heading" and np.linalg.norm(heading) > 0:
        order = np.argsort(
            _angle_diff(np.arange(8) * np.pi / 4, np.arctan2(heading[1], heading[0]))
        )
    else:
        order = np.argsort(-counts, kind="stable")
    zone = None
    for z in order:  # fall back to the next zone when the selected one has no reachable frontier
        if (fz == z).any():
            zone = int(z)
            break
    rows = []
    paths: dict[int, np.ndarray] = {}
    if zone is not None:
        zc = fc[fz == zone]
        dz = dist[zc[:, 0], zc[:, 1]]
        top = zc[np.argsort(-dz, kind="stable")[: config.n_proposals]]
        principal = zone * np.pi / 4
        ang = np.arctan2(*(grid.cell_xy(top[:, 0], top[:, 1]) - cur_xy)[:, ::-1].T)
        pick = np.argsort(_angle_diff(ang, principal), kind="stable")
        chosen = top[pick[0]]
        path, _ = astar(nav, current, tuple(chosen), grid.cell_m)
        ev = evaluate_positions(
            grid, classes, grid.cell_xy(path[:, 0], path[:, 1]), stems, scan_xy, scan_ids, config
        )
        ok = overlap_constraint(config, ev["common_stems"].to_numpy(), ev["overlap_share"].to_numpy())
        far = np.flatnonzero(ok)
        k = int(far.max()) if len(far) else 0
        sel = path[k]
        first = ev.iloc[k]
        rows.append(_thesis_row(first, sel, dist, bool(ok[k]), "thesis"))
        paths[1] = grid.cell_xy(path[: k + 1, 0], path[: k + 1, 1])
        # the other candidates (backups first), unshrunk, in the thesis's order of alignment
        rest = top[pick[1:]]
        if len(rest):
            ev2 = evaluate_positions(
                grid,
                classes,
                grid.cell_xy(rest[:, 0], rest[:, 1]),
                stems,
                scan_xy,
                scan_ids,
                config,
            )
            ok2 = overlap_constraint(
                config, ev2["common_stems"].to_numpy(), ev2["overlap_share"].to_numpy()
            )
            for j, (c, e) in enumerate(zip(rest, ev2.itertuples(), strict=True)):
                rows.append(
                    _thesis_row(e, c, dist, bool(ok2[j]), "backup" if j < 2 else "candidate")
                )
    table = pd.DataFrame(rows, columns=[c for c in PROPOSAL_COLUMNS if c != "rank"])
    table.insert(0, "rank", np.arange(1, len(table) + 1))
    return VantagePlan(
        table[PROPOSAL_COLUMNS],
        paths,
        grid,
        classes,
        frontier,
        coverage,
        current,
        heading=heading,
        zone=zone,
        config=config,
    )
