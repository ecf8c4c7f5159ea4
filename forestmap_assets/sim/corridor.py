"""The office corridor of spec 10.1 (Th. ch. 6, "indoor", about 50 m square): a corridor with
cylindrical pillars (r = 0.192 m, about 7 m apart), walls about 2.3 m high up to the ceiling,
offices with doors and windows, scans 1-8 from a cart (pairs 21 ... 87); features: pillars and
wall/ceiling lines. Random (:func:`make_corridor`) and hand-placed (:func:`corridor_scene`)
layouts; every number is (inferred) and a keyword argument."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from forestmap_assets.sim.ground import ground_mesh
from forestmap_assets.sim.scene_mesh import (
    KIND_GROUND,
)
from forestmap_assets.sim.site_assembly import (
    Site,
    SiteBuilder,
    openings_along,
    path_points,
    place_scans,
)
from forestmap_assets.sim.site_meshes import (
    KIND_CEILING,
    KIND_PERSON,
    KIND_PILLAR,
    KIND_WALL,
    PILLAR_COLUMNS,
    PILLAR_RADIUS_M,
    PILLAR_SPACING_M,
    WALL_HEIGHT_M,
    Wall,
    flat_ground,
    person_mesh,
    pillar_mesh,
    plane_mesh,
    wall_lines_table,
    walls_mesh,
)
from forestmap_assets.sim.stems import STEM_COLUMNS


def make_corridor(
    n_scans: int = 8,
    size_m: float = 40.0,
    *,
    seed: int | np.random.Generator = 0,
    layout: str = "ring",
    width_m: float = 3.0,
    height_m: float = WALL_HEIGHT_M,
    wall_thickness_m: float = 0.15,
    pillar_radius_m: float = PILLAR_RADIUS_M,
    pillar_spacing_m: float = PILLAR_SPACING_M,
    pillar_offset_m: float = 0.6,
    room_depth_m: float = 4.0,
    room_width_m: float = 5.0,
    door_width_m: float = 0.9,
    door_height_m: float = 2.05,
    door_probability: float = 0.8,
    window_width_m: float = 1.6,
    window_sill_m: float = 0.9,
    window_top_m: float = 2.0,
    path_offset_m: float = -0.5,
    scan_spacing_m: float = 10.0,
    path_start_m: float = 3.0,
    along_jitter_m: float = 0.5,
    across_jitter_m: float = 0.15,
    heading_jitter_deg: float = 8.0,
    people: int = 0,
    people_clearance_m: float = 1.5,
) -> Site:
    """The office corridor of spec 10.1 (inferred geometry, every number a keyword argument).

    ``layout="ring"``: a square ring corridor of centre-line side ``size_m`` around an inner
    block of offices, a row of offices outside it with windows in the façade (a closed loop, so
    the registration network has loops); ``layout="straight"``: one corridor of length ``size_m``
    along +x with closed ends. The corridor is ``width_m`` wide with walls and a ceiling at
    ``height_m`` (2.3 m); pillars of radius 0.192 m every ``pillar_spacing_m`` (7 m) stand
    ``pillar_offset_m`` off the centre line; offices of ``room_depth_m`` x ``room_width_m`` open
    onto it through doors (``door_probability`` per office). The cart drives ``path_offset_m``
    off the centre line and stops every ``scan_spacing_m`` (the thesis's consecutive scans were
    7.6-22 m apart), heading along the corridor +- ``heading_jitter_deg``. ``people``
    people-shaped occluders stand in the corridor (Th. 11: people leave holes in indoor scans).
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    if layout not in ("ring", "straight"):
        raise ValueError(f"layout: expected 'ring' or 'straight', got {layout!r}")
    t, w, h = wall_thickness_m, width_m, height_m
    walls: list[Wall] = []

    def corridor_side(p0, p1, outward, with_rooms=True, facade=True):
        """Corridor wall p0 -> p1 (centre line), offices behind it on the ``outward`` side."""
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        length = float(np.linalg.norm(p1 - p0))
        d = (p1 - p0) / length
        doors = (
            openings_along(
                length, rng, room_width_m, door_width_m, 0.0, door_height_m, 0.4, door_probability
            )
            if with_rooms
            else ()
        )
        walls.append(Wall(tuple(p0), tuple(p1), h, t, 0.0, doors))
        if not with_rooms:
            return
        back0, back1 = p0 + outward * room_depth_m, p1 + outward * room_depth_m
        wins = (
            openings_along(
                length, rng, room_width_m, window_width_m, window_sill_m, window_top_m, 0.5, 1.0
            )
            if facade
            else ()
        )
        walls.append(Wall(tuple(back0), tuple(back1), h, t, 0.0, wins))
        for k in range(int(length // room_width_m) + 1):
            s = min(k * room_width_m, length)
            a = p0 + d * s
            walls.append(Wall(tuple(a), tuple(a + outward * room_depth_m), h, t))

    b = SiteBuilder()
    if layout == "ring":
        half = size_m / 2
        hi, ho = half - w / 2, half + w / 2  # inner / outer corridor wall (centre lines)
        ei, eo = hi - t / 2, ho + t / 2  # extend so the corners close
        corners = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
        for k in range(4):
            (ax, ay), (bx, by) = corners[k], corners[(k + 1) % 4]
            mid = np.array([ax + bx, ay + by], float) / 2  # unit outward normal of this side
            corridor_side((ax * eo, ay * eo), (bx * eo, by * eo), mid, facade=True)
            corridor_side((ax * ei, ay * ei), (bx * ei, by * ei), -mid, facade=False)
        ext = ho + room_depth_m + 1.0
        # the cart's path: a square path_offset_m outside (> 0) or inside (< 0) the centre line
        path = np.array(corners, float) * (half + path_offset_m)
        closed = True
        # pillars on the other side of the centre line, every pillar_spacing_m along each side
        prow = half - np.sign(path_offset_m or 1.0) * pillar_offset_m
        pil = []
        for k in range(4):
            (ax, ay), (bx, by) = corners[k], corners[(k + 1) % 4]
            a, bb = np.array([ax, ay]) * prow, np.array([bx, by]) * prow
            length = float(np.linalg.norm(bb - a))
            s = np.arange(pillar_spacing_m / 2, length - 1.0, pillar_spacing_m)
            s = s[(s > w) & (s < length - w)]
            pil.append(a + np.outer(s / length, bb - a))
        pillar_xy = np.concatenate(pil) if pil else np.zeros((0, 2))
        ceil = (-ext, ext, -ext, ext)
    else:
        length = size_m
        corridor_side((0.0, w / 2), (length, w / 2), np.array([0.0, 1.0]), facade=True)
        corridor_side((0.0, -w / 2), (length, -w / 2), np.array([0.0, -1.0]), facade=False)
        walls.append(Wall((0.0, -w / 2 - t / 2), (0.0, w / 2 + t / 2), h, t))
        walls.append(Wall((length, -w / 2 - t / 2), (length, w / 2 + t / 2), h, t))
        path = np.array([[0.0, path_offset_m], [length, path_offset_m]])
        closed = False
        py = -pillar_offset_m if path_offset_m > 0 else pillar_offset_m
        s = np.arange(pillar_spacing_m / 2, length - 0.5, pillar_spacing_m)
        pillar_xy = np.column_stack([s, np.full(s.size, py)])
        ext = max(length, room_depth_m) + 2.0
        ceil = (-2.0, length + 2.0, -w / 2 - room_depth_m - 1.0, w / 2 + room_depth_m + 1.0)

    ground = flat_ground()
    gv, gf = ground_mesh(ground, ext + 30.0, 2.0)
    b.pieces.append(
        (gv, gf, np.full(len(gf), KIND_GROUND), np.full(len(gf), -1), np.zeros(len(gf)))
    )
    wv, wf, wown = walls_mesh(walls)
    b.add(wv, wf, KIND_WALL, wown)
    b.add(*plane_mesh(*ceil, h), KIND_CEILING)
    n_p = len(pillar_xy)
    pv, pf = pillar_mesh(pillar_xy, np.zeros(n_p), np.full(n_p, h), np.full(n_p, pillar_radius_m))
    pparts = b.add(pv, pf, KIND_PILLAR, np.repeat(np.arange(n_p), 2 * 64))
    scan_xy, heading, _ = place_scans(
        path,
        n_scans,
        scan_spacing_m,
        closed,
        path_start_m,
        rng,
        along_jitter_m,
        across_jitter_m,
        heading_jitter_deg,
    )
    if people:
        pts, _, _ = path_points(path, rng.uniform(0, 1e4, 8 * people), closed)
        pts = pts + rng.uniform(-0.6, 0.6, pts.shape)
        far = (np.linalg.norm(pts[:, None] - scan_xy[None], axis=2) >= people_clearance_m).all(1)
        if n_p:
            far &= (np.linalg.norm(pts[:, None] - pillar_xy[None], axis=2) >= 0.6).all(1)
        pts = pts[far][:people]
        hv, hf, hown = person_mesh(pts, np.zeros(len(pts)), rng)
        b.add(hv, hf, KIND_PERSON, hown)
    pillars = pd.DataFrame(
        {
            "pillar_id": np.arange(1, n_p + 1),
            "kind": "pillar",
            "x": pillar_xy[:, 0],
            "y": pillar_xy[:, 1],
            "z": 0.0,
            "radius_m": pillar_radius_m,
            "height_m": h,
        }
    )[PILLAR_COLUMNS]
    return Site(
        "corridor",
        "indoor",
        size_m,
        ground,
        b.mesh(),
        walls,
        wall_lines_table(walls),
        pillars,
        pd.DataFrame(columns=STEM_COLUMNS),
        scan_xy,
        heading,
        closed,
        pparts,
    )


def corridor_scene(
    length_m: float = 40.0,
    width_m: float = 3.0,
    *,
    height_m: float = WALL_HEIGHT_M,
    wall_thickness_m: float = 0.15,
    left_doors: Sequence[float] = (),
    right_doors: Sequence[float] = (),
    door_width_m: float = 0.9,
    door_height_m: float = 2.05,
    room_depth_m: float = 4.0,
    left_glass: tuple[float, float] | None = None,
    right_glass: tuple[float, float] | None = None,
    post_every_m: float = 2.0,
    post_width_m: float = 0.3,
    pillars_x: Sequence[float] = (),
    pillar_y: float = 0.6,
    pillar_radius_m: float = PILLAR_RADIUS_M,
    scan_x: Sequence[float] = (),
    scan_y: float = -0.5,
    scan_heading_deg: Sequence[float] | float = 0.0,
) -> Site:
    """One straight corridor along +x from 0 to ``length_m`` (closed ends), explicitly laid out
    for controlled experiments (the failure modes of spec 7.3).

    ``left_doors`` / ``right_doors``: door positions (start, along x) in the wall at
    ``y = +width/2`` / ``-width/2``; doors open into one long room of ``room_depth_m`` behind the
    wall. ``left_glass`` / ``right_glass`` = (x0, x1): that stretch of the wall is floor-to-ceiling
    glazing (invisible to the laser) held by ``post_width_m`` posts every ``post_every_m``, with
    the open outside behind it (no lines can form there: every post is shorter than the minimum
    line length). ``pillars_x`` at ``y = pillar_y``; scans at ``scan_x`` on ``y = scan_y``.
    """
    w, t, h = width_m, wall_thickness_m, height_m
    walls: list[Wall] = []

    def side(y, doors, glass, outward):
        ops = [(x, x + door_width_m, 0.0, door_height_m) for x in doors]
        if glass is not None:
            g0, g1 = glass
            x = g0
            while x < g1:
                ops.append(
                    (
                        x + post_width_m / 2,
                        min(x + post_every_m - post_width_m / 2, g1),
                        0.0,
                        h + 1.0,
                    )
                )
                x += post_every_m
        walls.append(Wall((0.0, y), (length_m, y), h, t, 0.0, tuple(ops)))
        if doors:
            walls.append(
                Wall(
                    (0.0, y + outward * room_depth_m), (length_m, y + outward * room_depth_m), h, t
                )
            )
            for x in (0.0, length_m):
                walls.append(Wall((x, y), (x, y + outward * room_depth_m), h, t))

    side(w / 2, list(left_doors), left_glass, 1.0)
    side(-w / 2, list(right_doors), right_glass, -1.0)
    walls.append(Wall((0.0, -w / 2 - t / 2), (0.0, w / 2 + t / 2), h, t))
    walls.append(Wall((length_m, -w / 2 - t / 2), (length_m, w / 2 + t / 2), h, t))
    b = SiteBuilder()
    ground = flat_ground()
    gv, gf = ground_mesh(ground, length_m + 30.0, 2.0)
    b.pieces.append(
        (gv, gf, np.full(len(gf), KIND_GROUND), np.full(len(gf), -1), np.zeros(len(gf)))
    )
    wv, wf, wown = walls_mesh(walls)
    b.add(wv, wf, KIND_WALL, wown)
    yl = w / 2 + (room_depth_m if left_doors else 0.0) + t
    yr = -w / 2 - (room_depth_m if right_doors else 0.0) - t
    b.add(*plane_mesh(-t, length_m + t, yr, yl, h), KIND_CEILING)
    px = np.asarray(pillars_x, float)
    pxy = np.column_stack([px, np.full(px.size, pillar_y)])
    pv, pf = pillar_mesh(
        pxy, np.zeros(px.size), np.full(px.size, h), np.full(px.size, pillar_radius_m)
    )
    pparts = b.add(pv, pf, KIND_PILLAR, np.repeat(np.arange(px.size), 2 * 64))
    sx = np.asarray(scan_x, float)
    pillars = pd.DataFrame(
        {
            "pillar_id": np.arange(1, px.size + 1),
            "kind": "pillar",
            "x": px,
            "y": pillar_y,
            "z": 0.0,
            "radius_m": pillar_radius_m,
            "height_m": h,
        }
    )[PILLAR_COLUMNS]
    return Site(
        "corridor",
        "indoor",
        length_m,
        ground,
        b.mesh(),
        walls,
        wall_lines_table(walls),
        pillars,
        pd.DataFrame(columns=STEM_COLUMNS),
        np.column_stack([sx, np.full(sx.size, scan_y)]),
        np.broadcast_to(np.asarray(scan_heading_deg, float), sx.shape).copy(),
        False,
        pparts,
    )
