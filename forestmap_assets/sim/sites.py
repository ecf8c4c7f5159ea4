"""Structured sites of the thesis as labelled meshes: the office corridor and the parking lot.

Spec 10.1 (Th. ch. 6): besides the forest, the thesis maps

* an **office building interior** ("indoor", about 50 m square): a corridor with cylindrical
  pillars (r = 0.192 m, about 7 m apart), walls about 2.3 m high up to the ceiling, scans 1-8
  taken from a cart along the corridor (consecutive pairs 21 ... 87), features: pillars and
  wall/ceiling lines;
* a **parking lot** ("outdoor", semi-structured, about 120 m square): trees, a light pole and
  building wall-top lines, scans E-J from a cart, consecutive pairs FE ... JI.

This module builds both as one :class:`~forestmap_assets.sim.forest.SceneMesh` each (reusing the
forest's building blocks ``box_mesh``, ``tube_mesh``, ``blob_mesh``, ``ground_mesh``) with
per-triangle labels, plus the ground truth needed to score feature extraction and
registration: pillars/poles (axis and radius), the wall/ceiling (indoor) or wall-top (outdoor)
corner lines, trees (stem table of :mod:`.forest`) and the cart path with the scan positions.

Walls are boxes; a door is a gap from the floor to ``door_height_m`` and a window a gap between
a sill and a lintel, so doors and windows leave the wall's top edge intact (the corner line runs
on above them) but open the free space behind them. Every number here is (inferred): the thesis
describes its sites in words only; all are keyword arguments.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from forestmap_assets.sim.forest import (
    BREAST_HEIGHT_M,
    KIND_BRANCH,
    KIND_FOLIAGE,
    KIND_GROUND,
    KIND_STEM,
    STEM_COLUMNS,
    Ground,
    SceneMesh,
    _concat,
    blob_mesh,
    box_mesh,
    ground_mesh,
    make_ground,
    tube_mesh,
)

# Labels beyond the forest's KIND_GROUND .. KIND_UNDERSTOREY (0-4).
KIND_WALL, KIND_CEILING, KIND_PILLAR, KIND_POLE, KIND_CAR, KIND_PERSON = 5, 6, 7, 8, 9, 10
SITE_KIND_NAMES = {KIND_WALL: "wall", KIND_CEILING: "ceiling", KIND_PILLAR: "pillar",
                   KIND_POLE: "pole", KIND_CAR: "car", KIND_PERSON: "person"}
SITES = ("forest", "parking-lot", "corridor")
SITE_ENVIRONMENT = {"forest": "forest", "parking-lot": "outdoor", "corridor": "indoor"}

PILLAR_RADIUS_M = 0.192  # Th. 4.6.4, spec 4.1 (diameter 0.38 m in Fig. 6.8)
PILLAR_SPACING_M = 7.0  # spec 10.1
WALL_HEIGHT_M = 2.3  # spec 10.1
CART_HEIGHT_M = 1.3  # spec 4.1: sensor height above the floor about 1.3 m

PILLAR_COLUMNS = ["pillar_id", "kind", "x", "y", "z", "radius_m", "height_m"]
WALL_LINE_COLUMNS = ["line_id", "x0", "y0", "z0", "x1", "y1", "z1", "wall_id", "face"]


# ---- building blocks ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Wall:
    """A straight wall: centre line ``p0 -> p1`` (xy), ``thickness``, from ``z0`` up ``height``;
    ``openings`` are (s0, s1, zlo, zhi): gaps along the wall (s from p0) between heights above
    ``z0`` (a door: zlo = 0; a window: zlo = sill)."""

    p0: tuple[float, float]
    p1: tuple[float, float]
    height: float
    thickness: float = 0.15
    z0: float = 0.0
    openings: tuple[tuple[float, float, float, float], ...] = ()

    @property
    def length(self) -> float:
        return float(np.hypot(self.p1[0] - self.p0[0], self.p1[1] - self.p0[1]))

    @property
    def direction(self) -> np.ndarray:
        d = np.subtract(self.p1, self.p0).astype(float)
        return d / max(np.linalg.norm(d), 1e-12)

    def pieces(self) -> list[tuple[float, float, float, float]]:
        """Solid boxes (s0, s1, zlo, zhi) left after cutting the openings."""
        cuts = sorted({0.0, self.length, *(float(np.clip(v, 0, self.length))
                                            for o in self.openings for v in o[:2])})
        out = []
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            if b - a < 1e-6:
                continue
            mid = 0.5 * (a + b)
            gaps = sorted((max(o[2], 0.0), min(o[3], self.height))
                          for o in self.openings if o[0] <= mid <= o[1])
            z = 0.0
            for lo, hi in gaps:
                if lo > z:
                    out.append((a, b, z, lo))
                z = max(z, hi)
            if z < self.height:
                out.append((a, b, z, self.height))
        return out

    def face_lines(self) -> list[tuple[np.ndarray, np.ndarray, int]]:
        """The top edges of both faces (3-D end points, face +1 left / -1 right of p0 -> p1)."""
        d = self.direction
        n = np.array([-d[1], d[0]])
        top = self.z0 + self.height
        out = []
        for side in (1, -1):
            off = side * 0.5 * self.thickness * n
            a = np.array([*(np.asarray(self.p0) + off), top])
            b = np.array([*(np.asarray(self.p1) + off), top])
            out.append((a, b, side))
        return out


def walls_mesh(walls: Sequence[Wall]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices, faces and face -> wall index of the solid pieces of ``walls`` (box_mesh)."""
    centre, size, yaw, owner = [], [], [], []
    for k, w in enumerate(walls):
        d = w.direction
        for s0, s1, lo, hi in w.pieces():
            mid = np.asarray(w.p0) + d * 0.5 * (s0 + s1)
            centre.append([mid[0], mid[1], w.z0 + lo])
            size.append([s1 - s0, w.thickness, hi - lo])
            yaw.append(np.arctan2(d[1], d[0]))
            owner.append(k)
    if not centre:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    v, f = box_mesh(np.array(centre), np.array(size), np.array(yaw))
    return v, f, np.repeat(np.array(owner), 12)


def wall_lines_table(walls: Sequence[Wall], wall_ids: Sequence[int] | None = None) -> pd.DataFrame:
    """Truth corner lines: the top edge of both faces of every wall (``WALL_LINE_COLUMNS``)."""
    rows = []
    for k, w in enumerate(walls):
        for a, b, side in w.face_lines():
            rows.append([len(rows), *a, *b, k if wall_ids is None else wall_ids[k], side])
    df = pd.DataFrame(rows, columns=WALL_LINE_COLUMNS)
    return df.astype({"line_id": "int64", "wall_id": "int64", "face": "int64"})


def plane_mesh(x0: float, x1: float, y0: float, y1: float, z: float):
    """A horizontal rectangle (2 triangles), e.g. a ceiling or a roof."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def pillar_mesh(xy: np.ndarray, z0: np.ndarray, height: np.ndarray, radius: np.ndarray,
                n_sides: int = 64):
    """Vertical circular columns (pillars, poles) standing on ``z0`` (tube_mesh)."""
    xy = np.atleast_2d(xy).astype(float)
    p0 = np.column_stack([xy, np.asarray(z0, float) - 0.05])
    p1 = np.column_stack([xy, np.asarray(z0, float) + np.asarray(height, float)])
    r = np.broadcast_to(np.asarray(radius, float), (len(xy),))
    return tube_mesh(p0, p1, r, r, n_sides=n_sides, n_rings=2)


def car_mesh(xy: np.ndarray, z0: np.ndarray, yaw: np.ndarray, *, length_m: float = 4.5,
             width_m: float = 1.8, body_m: tuple[float, float] = (0.3, 1.0),
             cabin_height_m: float = 1.45, cabin_share: float = 0.55):
    """Parked cars as two boxes each: a body (``body_m`` above the ground) and a shorter cabin."""
    n = len(xy)
    c, s = np.cos(yaw), np.sin(yaw)
    body = np.column_stack([xy, z0 + body_m[0]])
    bv, bf = box_mesh(body, np.tile([length_m, width_m, body_m[1] - body_m[0]], (n, 1)), yaw)
    shift = -0.1 * length_m
    cab = np.column_stack([xy[:, 0] + c * shift, xy[:, 1] + s * shift, z0 + body_m[1]])
    cv, cf = box_mesh(cab, np.tile([cabin_share * length_m, 0.9 * width_m,
                                    cabin_height_m - body_m[1]], (n, 1)), yaw)
    v = np.concatenate([bv, cv])
    f = np.concatenate([bf, cf + len(bv)])
    owner = np.concatenate([np.repeat(np.arange(n), 12), np.repeat(np.arange(n), 12)])
    return v, f, owner


def person_mesh(xy: np.ndarray, z0: np.ndarray, rng: np.random.Generator):
    """People-shaped occluders: legs+torso as a tapered tube (0.15-0.2 m radius, 1.45 m) and a
    head blob (0.11 m) on top; heights U(1.6, 1.9) m (inferred)."""
    n = len(xy)
    h = rng.uniform(1.6, 1.9, n)
    p0 = np.column_stack([xy, z0])
    p1 = np.column_stack([xy, z0 + h - 0.25])
    tv, tf = tube_mesh(p0, p1, np.full(n, 0.15), np.full(n, 0.2), n_sides=12, n_rings=3)
    hv, hf, hown = blob_mesh(np.column_stack([xy, z0 + h - 0.12]), np.full((n, 3), 0.11), rng,
                             jitter=0.05)
    v = np.concatenate([tv, hv])
    f = np.concatenate([tf, hf + len(tv)])
    owner = np.concatenate([np.repeat(np.arange(n), 2 * 2 * 12), hown])
    return v, f, owner


def flat_ground() -> Ground:
    """A level floor at z = 0."""
    return Ground((0.0, 0.0), np.zeros(0), np.zeros((0, 2)), np.zeros(0))


def tree_stems(xy: np.ndarray, ground: Ground, rng: np.random.Generator, *,
               dbh_range_m: tuple[float, float] = (0.15, 0.45),
               height_range_m: tuple[float, float] = (8.0, 15.0),
               first_id: int = 1) -> pd.DataFrame:
    """Stem table (``STEM_COLUMNS`` of :mod:`.forest`) of upright park trees at ``xy``."""
    n = len(xy)
    dbh = rng.uniform(*dbh_range_m, n)
    height = rng.uniform(*height_range_m, n)
    taper = (dbh / 2 - 0.02) / (height - BREAST_HEIGHT_M)
    lean = np.radians(rng.uniform(0.0, 2.0, n))
    lean_dir = rng.uniform(-np.pi, np.pi, n)
    return pd.DataFrame({
        "tree_id": np.arange(first_id, first_id + n),
        "x_base": xy[:, 0], "y_base": xy[:, 1], "z_base": ground.height(xy[:, 0], xy[:, 1]),
        "lean_x": np.tan(lean) * np.cos(lean_dir), "lean_y": np.tan(lean) * np.sin(lean_dir),
        "r_base_m": dbh / 2 + taper * BREAST_HEIGHT_M, "taper_m_per_m": taper,
        "height_m": height, "crown_base_m": rng.uniform(2.5, 3.5, n),
        "a2_m": rng.uniform(0.001, 0.004, n), "phase2_deg": rng.uniform(-180, 180, n),
        "a3_m": rng.uniform(0.0, 0.002, n), "phase3_deg": rng.uniform(-180, 180, n),
    })[STEM_COLUMNS]


def trees_mesh(stems: pd.DataFrame, rng: np.random.Generator, part0: int) -> list[tuple]:
    """Mesh pieces (vertices, faces, kind, tree, part) of stems with a crown of a few branches
    and foliage blobs (a light version of the forest's crowns)."""
    if stems.empty:
        return []
    n = len(stems)
    base = stems[["x_base", "y_base", "z_base"]].to_numpy()
    slope = np.column_stack([stems["lean_x"], stems["lean_y"], np.ones(n)])
    r_base = stems["r_base_m"].to_numpy()
    taper = stems["taper_m_per_m"].to_numpy()
    height = stems["height_m"].to_numpy()
    ids = stems["tree_id"].to_numpy()
    harm = np.column_stack([stems["a2_m"], np.radians(stems["phase2_deg"]), stems["a3_m"],
                            np.radians(stems["phase3_deg"])])
    sv, sf = tube_mesh(base - 0.3 * slope, base + height[:, None] * slope, r_base + 0.3 * taper,
                       r_base - taper * height, n_sides=48, n_rings=16, harmonics=harm)
    per = 2 * 15 * 48
    own = np.repeat(np.arange(n), per)
    pieces = [(sv, sf, np.full(len(sf), KIND_STEM), ids[own], part0 + own)]
    part = part0 + n
    k = 6
    bt = np.repeat(np.arange(n), k)
    hb = stems["crown_base_m"].to_numpy()[bt] + rng.random(bt.size) * 0.6 * (
        height[bt] - stems["crown_base_m"].to_numpy()[bt])
    az = rng.uniform(-np.pi, np.pi, bt.size)
    up = np.radians(rng.uniform(15, 45, bt.size))
    d = np.column_stack([np.cos(up) * np.cos(az), np.cos(up) * np.sin(az), np.sin(up)])
    start = base[bt] + hb[:, None] * slope[bt]
    end = start + rng.uniform(1.0, 2.5, bt.size)[:, None] * d
    rb = np.full(bt.size, 0.03)
    bv, bf = tube_mesh(start, end, rb, 0.3 * rb, n_sides=6, n_rings=2)
    bown = np.repeat(np.arange(bt.size), 12)
    pieces.append((bv, bf, np.full(len(bf), KIND_BRANCH), ids[bt[bown]], part + bown))
    part += bt.size
    centres = np.concatenate([end, base + height[:, None] * slope])
    owner = np.concatenate([bt, np.arange(n)])
    radii = rng.uniform(0.6, 1.2, (len(centres), 1)) * np.array([[1.0, 1.0, 0.7]])
    fv, ff, fown = blob_mesh(centres, radii, rng, porosity=0.3)
    pieces.append((fv, ff, np.full(len(ff), KIND_FOLIAGE), ids[owner[fown]], part + fown))
    return pieces


# ---- the site ----------------------------------------------------------------------------------
@dataclass
class Site:
    """A structured site: mesh, ground, truth tables and the cart's scan positions.

    ``pillars``: ``PILLAR_COLUMNS`` (world frame; ``z`` the floor under the axis) with the mesh
    ``part`` of each; ``wall_lines``: ``WALL_LINE_COLUMNS`` (top edges of every wall face);
    ``stems``: trees (forest ``STEM_COLUMNS``, may be empty); ``scan_xy`` (n, 2) and
    ``scan_heading_deg`` (n,): the cart's positions and headings; ``closed_loop``: the path is a
    ring, so the last scan neighbours the first.
    """

    name: str
    environment: str
    plot_size: float
    ground: Ground
    mesh: SceneMesh
    walls: list[Wall]
    wall_lines: pd.DataFrame
    pillars: pd.DataFrame
    stems: pd.DataFrame
    scan_xy: np.ndarray
    scan_heading_deg: np.ndarray
    closed_loop: bool = False
    pillar_parts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def trees_at_breast_height(self) -> pd.DataFrame:
        from forestmap_assets.sim.forest import breast_height_table

        return breast_height_table(self.stems)


class _Builder:
    """Collects labelled mesh pieces with running part ids."""

    def __init__(self) -> None:
        self.pieces: list[tuple] = []
        self.part = 1  # 0 is the ground

    def add(self, v, f, kind: int, owner: np.ndarray | None = None, tree=None) -> np.ndarray:
        if len(f) == 0:
            return np.zeros(0, np.int64)
        owner = np.zeros(len(f), np.int64) if owner is None else np.asarray(owner)
        parts = self.part + owner
        tree = np.full(len(f), -1) if tree is None else tree
        self.pieces.append((v, f, np.full(len(f), kind), tree, parts))
        first = self.part
        self.part += int(owner.max()) + 1
        return np.arange(first, self.part)

    def mesh(self) -> SceneMesh:
        return _concat(self.pieces)


def _path_points(vertices: np.ndarray, s: np.ndarray, closed: bool):
    """Points and tangent headings (deg) at arc lengths ``s`` along a polyline."""
    v = np.vstack([vertices, vertices[:1]]) if closed else vertices
    seg = np.diff(v, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0.0], np.cumsum(length)])
    s = np.mod(s, cum[-1]) if closed else np.clip(s, 0, cum[-1])
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    t = (s - cum[k]) / length[k]
    pts = v[k] + t[:, None] * seg[k]
    return pts, np.degrees(np.arctan2(seg[k, 1], seg[k, 0])), float(cum[-1])


def _place_scans(path: np.ndarray, n: int, spacing: float, closed: bool, start: float,
                 rng: np.random.Generator, along_jitter: float, across_jitter: float,
                 heading_jitter_deg: float):
    """``n`` cart stops every ``spacing`` m of path (clamped to fit), jittered (inferred)."""
    _, _, total = _path_points(path, np.zeros(1), closed)
    usable = total if closed else total - start - 1.0
    spacing = min(spacing, usable / max(n if closed else n - 1, 1))
    s = start + spacing * np.arange(n) + rng.uniform(-along_jitter, along_jitter, n)
    pts, head, _ = _path_points(path, s, closed)
    h = np.radians(head)
    pts = pts + rng.uniform(-across_jitter, across_jitter, n)[:, None] * np.column_stack(
        [-np.sin(h), np.cos(h)])
    headings = head + rng.uniform(-heading_jitter_deg, heading_jitter_deg, n)
    return pts, (headings + 180.0) % 360.0 - 180.0, spacing


def _openings_along(length: float, rng: np.random.Generator, every_m: float, width_m: float,
                    zlo: float, zhi: float, margin_m: float, probability: float):
    """One opening per ``every_m`` stretch of a wall (with ``probability``), away from ends."""
    out = []
    n = int(length // every_m)
    for k in range(n):
        a, b = k * every_m + margin_m, (k + 1) * every_m - margin_m - width_m
        if b > a and rng.random() < probability:
            s0 = rng.uniform(a, b)
            out.append((s0, s0 + width_m, zlo, zhi))
    return tuple(out)


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
        doors = _openings_along(length, rng, room_width_m, door_width_m, 0.0, door_height_m,
                                0.4, door_probability) if with_rooms else ()
        walls.append(Wall(tuple(p0), tuple(p1), h, t, 0.0, doors))
        if not with_rooms:
            return
        back0, back1 = p0 + outward * room_depth_m, p1 + outward * room_depth_m
        wins = _openings_along(length, rng, room_width_m, window_width_m, window_sill_m,
                               window_top_m, 0.5, 1.0) if facade else ()
        walls.append(Wall(tuple(back0), tuple(back1), h, t, 0.0, wins))
        for k in range(int(length // room_width_m) + 1):
            s = min(k * room_width_m, length)
            a = p0 + d * s
            walls.append(Wall(tuple(a), tuple(a + outward * room_depth_m), h, t))

    b = _Builder()
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
    b.pieces.append((gv, gf, np.full(len(gf), KIND_GROUND), np.full(len(gf), -1),
                     np.zeros(len(gf))))
    wv, wf, wown = walls_mesh(walls)
    b.add(wv, wf, KIND_WALL, wown)
    b.add(*plane_mesh(*ceil, h), KIND_CEILING)
    n_p = len(pillar_xy)
    pv, pf = pillar_mesh(pillar_xy, np.zeros(n_p), np.full(n_p, h), np.full(n_p, pillar_radius_m))
    pparts = b.add(pv, pf, KIND_PILLAR, np.repeat(np.arange(n_p), 2 * 64))
    scan_xy, heading, _ = _place_scans(path, n_scans, scan_spacing_m, closed, path_start_m, rng,
                                       along_jitter_m, across_jitter_m, heading_jitter_deg)
    if people:
        pts, _, _ = _path_points(path, rng.uniform(0, 1e4, 8 * people), closed)
        pts = pts + rng.uniform(-0.6, 0.6, pts.shape)
        far = (np.linalg.norm(pts[:, None] - scan_xy[None], axis=2) >= people_clearance_m).all(1)
        if n_p:
            far &= (np.linalg.norm(pts[:, None] - pillar_xy[None], axis=2) >= 0.6).all(1)
        pts = pts[far][:people]
        hv, hf, hown = person_mesh(pts, np.zeros(len(pts)), rng)
        b.add(hv, hf, KIND_PERSON, hown)
    pillars = pd.DataFrame({"pillar_id": np.arange(1, n_p + 1), "kind": "pillar",
                            "x": pillar_xy[:, 0], "y": pillar_xy[:, 1], "z": 0.0,
                            "radius_m": pillar_radius_m, "height_m": h})[PILLAR_COLUMNS]
    return Site("corridor", "indoor", size_m, ground, b.mesh(), walls, wall_lines_table(walls),
                pillars, pd.DataFrame(columns=STEM_COLUMNS), scan_xy, heading, closed,
                pparts)


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
                ops.append((x + post_width_m / 2, min(x + post_every_m - post_width_m / 2, g1),
                            0.0, h + 1.0))
                x += post_every_m
        walls.append(Wall((0.0, y), (length_m, y), h, t, 0.0, tuple(ops)))
        if doors:
            walls.append(Wall((0.0, y + outward * room_depth_m),
                              (length_m, y + outward * room_depth_m), h, t))
            for x in (0.0, length_m):
                walls.append(Wall((x, y), (x, y + outward * room_depth_m), h, t))

    side(w / 2, list(left_doors), left_glass, 1.0)
    side(-w / 2, list(right_doors), right_glass, -1.0)
    walls.append(Wall((0.0, -w / 2 - t / 2), (0.0, w / 2 + t / 2), h, t))
    walls.append(Wall((length_m, -w / 2 - t / 2), (length_m, w / 2 + t / 2), h, t))
    b = _Builder()
    ground = flat_ground()
    gv, gf = ground_mesh(ground, length_m + 30.0, 2.0)
    b.pieces.append((gv, gf, np.full(len(gf), KIND_GROUND), np.full(len(gf), -1),
                     np.zeros(len(gf))))
    wv, wf, wown = walls_mesh(walls)
    b.add(wv, wf, KIND_WALL, wown)
    yl = w / 2 + (room_depth_m if left_doors else 0.0) + t
    yr = -w / 2 - (room_depth_m if right_doors else 0.0) - t
    b.add(*plane_mesh(-t, length_m + t, yr, yl, h), KIND_CEILING)
    px = np.asarray(pillars_x, float)
    pxy = np.column_stack([px, np.full(px.size, pillar_y)])
    pv, pf = pillar_mesh(pxy, np.zeros(px.size), np.full(px.size, h),
                         np.full(px.size, pillar_radius_m))
    pparts = b.add(pv, pf, KIND_PILLAR, np.repeat(np.arange(px.size), 2 * 64))
    sx = np.asarray(scan_x, float)
    pillars = pd.DataFrame({"pillar_id": np.arange(1, px.size + 1), "kind": "pillar",
                            "x": px, "y": pillar_y, "z": 0.0, "radius_m": pillar_radius_m,
                            "height_m": h})[PILLAR_COLUMNS]
    return Site("corridor", "indoor", length_m, ground, b.mesh(), walls,
                wall_lines_table(walls), pillars, pd.DataFrame(columns=STEM_COLUMNS),
                np.column_stack([sx, np.full(sx.size, scan_y)]),
                np.broadcast_to(np.asarray(scan_heading_deg, float), sx.shape).copy(), False,
                pparts)


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
    :func:`~.forest.make_ground`; default relief 0.03 m, slope 0.5-1.5 %), an L-shaped building
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
            ops += list(_openings_along(length, rng, window_every_m, window_width_m, lo, hi,
                                        0.4, 0.9))
        doors = _openings_along(length, rng, door_every_m, 1.2, 0.0, 2.3, 1.0, 0.7)
        ops = [o for o in ops if not any(o[0] < d[1] + 0.3 and o[1] > d[0] - 0.3 and o[2] < 2.3
                                         for d in doors)]
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
    b = _Builder()
    ext = half + D + 25.0
    gv, gf = ground_mesh(ground, ext, 1.0)
    b.pieces.append((gv, gf, np.full(len(gf), KIND_GROUND), np.full(len(gf), -1),
                     np.zeros(len(gf))))
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
        cars_xy.append(np.column_stack([xs[occ] + rng.uniform(-0.2, 0.2, occ.sum()),
                                        np.full(occ.sum(), ry) + rng.uniform(-0.2, 0.2,
                                                                             occ.sum())]))
        cars_yaw.append(np.pi / 2 + rng.uniform(-0.08, 0.08, occ.sum()) + np.pi * (
            rng.random(occ.sum()) < 0.5))
    cxy = np.concatenate(cars_xy)
    cyaw = np.concatenate(cars_yaw)
    # the cart's lane: between the two rows, west -> east, then the stops
    lane_y = 0.5 * (rows_y[0] + rows_y[1]) - 0.5
    path = np.array([[-half + 1.0, lane_y], [e_x - 3.0, lane_y]])
    scan_xy, heading, _ = _place_scans(path, n_scans, scan_spacing_m, False, 2.0, rng,
                                       along_jitter_m, across_jitter_m, heading_jitter_deg)
    keep = (np.linalg.norm(cxy[:, None] - scan_xy[None], axis=2) > 3.5).all(1)
    cxy, cyaw = cxy[keep], cyaw[keep]
    cv, cf, cown = car_mesh(cxy, ground.height(cxy[:, 0], cxy[:, 1]), cyaw)
    b.add(cv, cf, KIND_CAR, cown)
    # light poles along the lane, trees along the south edge
    px = np.linspace(-half + 6.0, e_x - 6.0, max(poles, 1))[:poles] + rng.uniform(-1, 1, poles)
    pxy = np.column_stack([px, np.full(poles, lane_y - 4.0)])
    pz = ground.height(pxy[:, 0], pxy[:, 1])
    pv, pf = pillar_mesh(pxy, pz, np.full(poles, pole_height_m), np.full(poles, pole_radius_m),
                         n_sides=32)
    pparts = b.add(pv, pf, KIND_POLE, np.repeat(np.arange(poles), 2 * 32))
    lv, lf = box_mesh(np.column_stack([pxy[:, 0] + 0.5, pxy[:, 1], pz + pole_height_m]),
                      np.tile([1.2, 0.3, 0.2], (poles, 1)), np.zeros(poles))
    b.add(lv, lf, KIND_POLE, np.repeat(np.arange(poles), 12))
    tx = np.linspace(-half + 3.0, e_x - 4.0, max(trees, 1))[:trees] + rng.uniform(-1.5, 1.5, trees)
    txy = np.column_stack([tx, np.full(trees, -half + 1.5) + rng.uniform(-1.0, 1.0, trees)])
    stems = tree_stems(txy, ground, rng)
    for piece in trees_mesh(stems, rng, b.part):
        b.pieces.append(piece)
        b.part = int(max(b.part, np.max(piece[4]) + 1))
    if people:
        pts = np.column_stack([rng.uniform(-half, e_x - 3.0, 8 * people),
                               lane_y + rng.uniform(-2.0, 2.0, 8 * people)])
        far = (np.linalg.norm(pts[:, None] - scan_xy[None], axis=2) >= 1.5).all(1)
        pts = pts[far][:people]
        hv, hf, hown = person_mesh(pts, ground.height(pts[:, 0], pts[:, 1]), rng)
        b.add(hv, hf, KIND_PERSON, hown)
    pillars = pd.DataFrame({"pillar_id": np.arange(1, poles + 1), "kind": "pole",
                            "x": pxy[:, 0], "y": pxy[:, 1], "z": pz,
                            "radius_m": pole_radius_m, "height_m": pole_height_m})[PILLAR_COLUMNS]
    return Site("parking-lot", "outdoor", size_m, ground, b.mesh(), walls,
                wall_lines_table(walls), pillars, stems, scan_xy, heading, False, pparts)


def make_site(site: str, n_scans: int, size_m: float, *, seed=0, trees: int = 6,
              **kwargs) -> Site:
    """``corridor`` or ``parking-lot`` (the forest is :func:`~.forest.make_forest`)."""
    if site == "corridor":
        return make_corridor(n_scans, size_m, seed=seed, **kwargs)
    if site == "parking-lot":
        return make_parking_lot(n_scans, size_m, seed=seed, trees=trees, **kwargs)
    raise ValueError(f"site: expected one of {', '.join(SITES[1:])}, got {site!r}")


# ---- truth helpers -----------------------------------------------------------------------------
def lines_in_frame(lines: pd.DataFrame, origin: np.ndarray, heading_deg: float) -> pd.DataFrame:
    """Line table (x0..z1) expressed in a levelled frame at ``origin`` with ``heading_deg``."""
    c, s = np.cos(np.radians(heading_deg)), np.sin(np.radians(heading_deg))
    out = lines.copy()
    for e in ("0", "1"):
        dx = lines[f"x{e}"].to_numpy() - origin[0]
        dy = lines[f"y{e}"].to_numpy() - origin[1]
        out[f"x{e}"], out[f"y{e}"] = c * dx + s * dy, -s * dx + c * dy
        out[f"z{e}"] = lines[f"z{e}"].to_numpy() - origin[2]
    return out


def points_in_frame(table: pd.DataFrame, origin: np.ndarray, heading_deg: float,
                    cols=("x", "y", "z")) -> pd.DataFrame:
    """Point table (``cols``) expressed in a levelled frame at ``origin`` with ``heading_deg``."""
    c, s = np.cos(np.radians(heading_deg)), np.sin(np.radians(heading_deg))
    out = table.copy()
    dx = table[cols[0]].to_numpy(float) - origin[0]
    dy = table[cols[1]].to_numpy(float) - origin[1]
    out[cols[0]], out[cols[1]] = c * dx + s * dy, -s * dx + c * dy
    out[cols[2]] = table[cols[2]].to_numpy(float) - origin[2]
    return out


def visible_parts(part: np.ndarray, points_z: np.ndarray, parts: np.ndarray, *,
                  min_extent_m: float = 1.0) -> np.ndarray:
    """Which of ``parts`` (mesh part ids) were hit over a vertical extent >= ``min_extent_m``
    (per-pixel ``part`` labels and hit heights of one scan)."""
    out = np.zeros(len(parts), bool)
    sel = np.isin(part, parts) & np.isfinite(points_z)
    if not sel.any():
        return out
    p, z = part[sel], points_z[sel]
    lo = pd.Series(z).groupby(p).min()
    hi = pd.Series(z).groupby(p).max()
    ext = (hi - lo).reindex(parts).fillna(0.0).to_numpy()
    return ext >= min_extent_m


def visible_line_samples(mesh: SceneMesh, lines: pd.DataFrame, origin: np.ndarray, *,
                         spacing_m: float = 0.1, max_range_m: float = 40.0,
                         inset_m: float = 0.05, tolerance_m: float = 0.1) -> pd.DataFrame:
    """Sample points every ``spacing_m`` along truth corner lines (world frame) that the sensor
    at ``origin`` can see: the ray towards the point, moved ``inset_m`` down and towards the
    sensor off the corner, reaches it within ``tolerance_m`` (open3d ray casting). Returns
    ``line_id, x, y, z`` of the visible samples (the truth for recall)."""
    import open3d as o3d

    from forestmap_assets.core.registration_.submaps import sample_segments

    p0 = lines[["x0", "y0", "z0"]].to_numpy(float)
    p1 = lines[["x1", "y1", "z1"]].to_numpy(float)
    pts, seg = sample_segments(p0, p1, spacing_m)
    if not len(pts):
        return pd.DataFrame(columns=["line_id", "x", "y", "z"])
    v = pts - origin
    dist = np.linalg.norm(v, axis=1)
    horiz = np.column_stack([v[:, :2], np.zeros(len(v))])
    horiz /= np.maximum(np.linalg.norm(horiz, axis=1, keepdims=True), 1e-9)
    target = pts - inset_m * horiz - np.array([0.0, 0.0, inset_m])
    d = target - origin
    n = np.linalg.norm(d, axis=1)
    rays = np.column_stack([np.broadcast_to(origin, d.shape), d / n[:, None]]).astype(np.float32)
    ans = mesh.raycasting_scene().cast_rays(o3d.core.Tensor(rays))
    t_hit = ans["t_hit"].numpy()
    ok = (t_hit >= n - tolerance_m) & (dist <= max_range_m)
    return pd.DataFrame({"line_id": lines["line_id"].to_numpy()[seg[ok]], "x": pts[ok, 0],
                         "y": pts[ok, 1], "z": pts[ok, 2]})
