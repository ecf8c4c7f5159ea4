"""The semi-structured parking lot of spec 10.1 (Th. ch. 6, "outdoor", about 120 m square): trees,
light poles, parked cars and an L-shaped building whose wall-top lines are features; scans E-J
from a cart (pairs FE ... JI). Every number is (inferred) and a keyword argument."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.sim.ground import ground_mesh, make_ground
from forestmap_assets.sim.scene_mesh import (
    KIND_GROUND,
    box_mesh,
)
from forestmap_assets.sim.site_assembly import Site, SiteBuilder, openings_along, place_scans
from forestmap_assets.sim.site_meshes import (
    KIND_CAR,
    KIND_CEILING,
    KIND_PERSON,
    KIND_POLE,
    KIND_WALL,
    PILLAR_COLUMNS,
    Wall,
    car_mesh,
    person_mesh,
    pillar_mesh,
    plane_mesh,
    tree_stems,
    trees_mesh,
    wall_lines_table,
    walls_mesh,
)


def make_parking_lot(
    n_scans: int = 6,
    size_m: float = 40.0,
    *,
    seed: int | np.random.Generator = 0,
    trees: int = 6,
    building_height_m: float = 6.0,
    building_depth_m: float = 10.0,
    wall_thickness_m: float = 0.3,
    window_every_m: float = 3.5,
    window_width_m: float = 1.4,
    windows: tuple[tuple[float, float], ...] = ((1.0, 2.2), (3.8, 5.0)),
    door_every_m: float = 15.0,
    poles: int = 2,
    pole_radius_m: float = 0.1,
    pole_height_m: float = 8.0,
    car_share: float = 0.6,
    bay_width_m: float = 2.6,
    scan_spacing_m: float = 10.0,
    along_jitter_m: float = 1.0,
    across_jitter_m: float = 0.5,
    heading_jitter_deg: float = 10.0,
    people: int = 0,
    ground_kwargs: dict | None = None,
) -> Site:
    """The semi-structured parking lot of spec 10.1 (inferred geometry).

    A square lot of side ``size_m`` on gently sloping asphalt (``ground_kwargs`` of
    :func:`~.ground.make_ground`; default relief 0.03 m, slope 0.5-1.5 %), an L-shaped building
    (``building_height_m`` with a flat roof, windows on two floors, doors) along its north and
    east edges, two rows of parking bays with cars (``car_share`` occupied), ``poles`` light
    poles, ``trees`` park trees along the south edge and optional ``people``. The cart drives
    along the lot's middle lane and stops every ``scan_spacing_m`` (FE .. JI were 11-37 m apart).
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    gk = {"relief_m": 0.03, "slope_range": (0.005, 0.015), "wavelength_range_m": (20.0, 60.0)}
    ground = make_ground(rng, **{**gk, **(ground_kwargs or {})})
    half = size_m / 2
    t, H, D = wall_thickness_m, building_height_m, building_depth_m
    # L-shaped building: a north wing (along x) and an east wing (along y)
    n_y, e_x = half + 2.0, half + 2.0  # façade lines
    z_floor = float(ground.height(np.array([half]), np.array([half]))[0]) - 0.3

    def facade(p0, p1):
        length = float(np.hypot(p1[0] - p0[0], p1[1] - p0[1]))
        ops = []
        for lo, hi in windows:
            ops += list(
                openings_along(length, rng, window_every_m, window_width_m, lo, hi, 0.4, 0.9)
            )
        doors = openings_along(length, rng, door_every_m, 1.2, 0.0, 2.3, 1.0, 0.7)
        ops = [
            o
            for o in ops
            if not any(o[0] < d[1] + 0.3 and o[1] > d[0] - 0.3 and o[2] < 2.3 for d in doors)
        ]
        return Wall(p0, p1, H - z_floor, t, z_floor, tuple(ops) + doors)

    x_w0 = -half - 2.0
    y_s0 = -half - 2.0
    walls = [
        facade((x_w0, n_y), (e_x, n_y)),  # north wing, south façade
        Wall((x_w0, n_y + D), (e_x + D, n_y + D), H - z_floor, t, z_floor),  # north back
        Wall((x_w0, n_y), (x_w0, n_y + D), H - z_floor, t, z_floor),  # north wing west end
        facade((e_x, y_s0), (e_x, n_y)),  # east wing, west façade
        Wall((e_x + D, y_s0), (e_x + D, n_y + D), H - z_floor, t, z_floor),  # east back
        Wall((e_x, y_s0), (e_x + D, y_s0), H - z_floor, t, z_floor),  # east wing south end
    ]
    b = SiteBuilder()
    ext = half + D + 25.0
    gv, gf = ground_mesh(ground, ext, 1.0)
    b.pieces.append(
        (gv, gf, np.full(len(gf), KIND_GROUND), np.full(len(gf), -1), np.zeros(len(gf)))
    )
    wv, wf, wown = walls_mesh(walls)
    b.add(wv, wf, KIND_WALL, wown)
    for roof in ((x_w0, e_x + D, n_y, n_y + D), (e_x, e_x + D, y_s0, n_y)):
        b.add(*plane_mesh(*roof, H), KIND_CEILING)
        rv, rf = plane_mesh(*roof, z_floor + 3.0)  # first floor slab, seen through windows
        b.add(rv, rf, KIND_CEILING)

    # parking bays: a row along the north façade and a middle row, cars nose-in
    rows_y = [n_y - 3.5, -half / 3]
    cars_xy, cars_yaw = [], []
    for ry in rows_y:
        xs = np.arange(-half + 2.0, e_x - 3.0, bay_width_m)
        occ = rng.random(xs.size) < car_share
        cars_xy.append(
            np.column_stack(
                [
                    xs[occ] + rng.uniform(-0.2, 0.2, occ.sum()),
                    np.full(occ.sum(), ry) + rng.uniform(-0.2, 0.2, occ.sum()),
                ]
            )
        )
        cars_yaw.append(
            np.pi / 2 + rng.uniform(-0.08, 0.08, occ.sum()) + np.pi * (rng.random(occ.sum()) < 0.5)
        )
    cxy = np.concatenate(cars_xy)
    cyaw = np.concatenate(cars_yaw)
    # the cart's lane: between the two rows, west -> east, then the stops
    lane_y = 0.5 * (rows_y[0] + rows_y[1]) - 0.5
    path = np.array([[-half + 1.0, lane_y], [e_x - 3.0, lane_y]])
    scan_xy, heading, _ = place_scans(
        path,
        n_scans,
        scan_spacing_m,
        False,
        2.0,
        rng,
        along_jitter_m,
        across_jitter_m,
        heading_jitter_deg,
    )
    keep = (np.linalg.norm(cxy[:, None] - scan_xy[None], axis=2) > 3.5).all(1)
    cxy, cyaw = cxy[keep], cyaw[keep]
    cv, cf, cown = car_mesh(cxy, ground.height(cxy[:, 0], cxy[:, 1]), cyaw)
    b.add(cv, cf, KIND_CAR, cown)
    # light poles along the lane, trees along the south edge
    px = np.linspace(-half + 6.0, e_x - 6.0, max(poles, 1))[:poles] + rng.uniform(-1, 1, poles)
    pxy = np.column_stack([px, np.full(poles, lane_y - 4.0)])
    pz = ground.height(pxy[:, 0], pxy[:, 1])
    pv, pf = pillar_mesh(
        pxy, pz, np.full(poles, pole_height_m), np.full(poles, pole_radius_m), n_sides=32
    )
    pparts = b.add(pv, pf, KIND_POLE, np.repeat(np.arange(poles), 2 * 32))
    lv, lf = box_mesh(
        np.column_stack([pxy[:, 0] + 0.5, pxy[:, 1], pz + pole_height_m]),
        np.tile([1.2, 0.3, 0.2], (poles, 1)),
        np.zeros(poles),
    )
    b.add(lv, lf, KIND_POLE, np.repeat(np.arange(poles), 12))
    tx = np.linspace(-half + 3.0, e_x - 4.0, max(trees, 1))[:trees] + rng.uniform(-1.5, 1.5, trees)
    txy = np.column_stack([tx, np.full(trees, -half + 1.5) + rng.uniform(-1.0, 1.0, trees)])
    stems = tree_stems(txy, ground, rng)
    for piece in trees_mesh(stems, rng, b.part):
        b.pieces.append(piece)
        b.part = int(max(b.part, np.max(piece[4]) + 1))
    if people:
        pts = np.column_stack(
            [rng.uniform(-half, e_x - 3.0, 8 * people), lane_y + rng.uniform(-2.0, 2.0, 8 * people)]
        )
        far = (np.linalg.norm(pts[:, None] - scan_xy[None], axis=2) >= 1.5).all(1)
        pts = pts[far][:people]
        hv, hf, hown = person_mesh(pts, ground.height(pts[:, 0], pts[:, 1]), rng)
        b.add(hv, hf, KIND_PERSON, hown)
    pillars = pd.DataFrame(
        {
            "pillar_id": np.arange(1, poles + 1),
            "kind": "pole",
            "x": pxy[:, 0],
            "y": pxy[:, 1],
            "z": pz,
            "radius_m": pole_radius_m,
            "height_m": pole_height_m,
        }
    )[PILLAR_COLUMNS]
    return Site(
        "parking-lot",
        "outdoor",
        size_m,
        ground,
        b.mesh(),
        walls,
        wall_lines_table(walls),
        pillars,
        stems,
        scan_xy,
        heading,
        False,
        pparts,
    )
