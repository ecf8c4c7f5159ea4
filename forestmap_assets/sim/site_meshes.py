"""Building blocks of the structured sites of spec 10.1 (Th. ch. 6) as labelled mesh pieces.

Labels KIND_WALL .. KIND_PERSON (5-10, beyond the forest's 0-4), pillar/wall sizes (pillars
r = 0.192 m about 7 m apart, walls about 2.3 m high), walls with openings (a door is a gap from
the floor, a window a gap between sill and lintel, so the wall's top corner line runs on above
them), pillars/poles, ceilings, parked cars, people and park trees, built from the forest's
``box_mesh``, ``tube_mesh``, ``blob_mesh``. Every number is (inferred)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from forestmap_assets.sim.ground import Ground
from forestmap_assets.sim.scene_mesh import (
    KIND_BRANCH,
    KIND_FOLIAGE,
    KIND_STEM,
    blob_mesh,
    box_mesh,
    tube_mesh,
)
from forestmap_assets.sim.stems import BREAST_HEIGHT_M, STEM_COLUMNS

# Labels beyond the forest's KIND_GROUND .. KIND_UNDERSTOREY (0-4).
KIND_WALL, KIND_CEILING, KIND_PILLAR, KIND_POLE, KIND_CAR, KIND_PERSON = 5, 6, 7, 8, 9, 10


SITE_KIND_NAMES = {
    KIND_WALL: "wall",
    KIND_CEILING: "ceiling",
    KIND_PILLAR: "pillar",
    KIND_POLE: "pole",
    KIND_CAR: "car",
    KIND_PERSON: "person",
}


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
        cuts = sorted(
            {
                0.0,
                self.length,
                *(float(np.clip(v, 0, self.length)) for o in self.openings for v in o[:2]),
            }
        )
        out = []
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            if b - a < 1e-6:
                continue
            mid = 0.5 * (a + b)
            gaps = sorted(
                (max(o[2], 0.0), min(o[3], self.height))
                for o in self.openings
                if o[0] <= mid <= o[1]
            )
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


def pillar_mesh(
    xy: np.ndarray, z0: np.ndarray, height: np.ndarray, radius: np.ndarray, n_sides: int = 64
):
    """Vertical circular columns (pillars, poles) standing on ``z0`` (tube_mesh)."""
    xy = np.atleast_2d(xy).astype(float)
    p0 = np.column_stack([xy, np.asarray(z0, float) - 0.05])
    p1 = np.column_stack([xy, np.asarray(z0, float) + np.asarray(height, float)])
    r = np.broadcast_to(np.asarray(radius, float), (len(xy),))
    return tube_mesh(p0, p1, r, r, n_sides=n_sides, n_rings=2)


def car_mesh(
    xy: np.ndarray,
    z0: np.ndarray,
    yaw: np.ndarray,
    *,
    length_m: float = 4.5,
    width_m: float = 1.8,
    body_m: tuple[float, float] = (0.3, 1.0),
    cabin_height_m: float = 1.45,
    cabin_share: float = 0.55,
):
    """Parked cars as two boxes each: a body (``body_m`` above the ground) and a shorter cabin."""
    n = len(xy)
    c, s = np.cos(yaw), np.sin(yaw)
    body = np.column_stack([xy, z0 + body_m[0]])
    bv, bf = box_mesh(body, np.tile([length_m, width_m, body_m[1] - body_m[0]], (n, 1)), yaw)
    shift = -0.1 * length_m
    cab = np.column_stack([xy[:, 0] + c * shift, xy[:, 1] + s * shift, z0 + body_m[1]])
    cv, cf = box_mesh(
        cab,
        np.tile([cabin_share * length_m, 0.9 * width_m, cabin_height_m - body_m[1]], (n, 1)),
        yaw,
    )
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
    hv, hf, hown = blob_mesh(
        np.column_stack([xy, z0 + h - 0.12]), np.full((n, 3), 0.11), rng, jitter=0.05
    )
    v = np.concatenate([tv, hv])
    f = np.concatenate([tf, hf + len(tv)])
    owner = np.concatenate([np.repeat(np.arange(n), 2 * 2 * 12), hown])
    return v, f, owner


def flat_ground() -> Ground:
    """A level floor at z = 0."""
    return Ground((0.0, 0.0), np.zeros(0), np.zeros((0, 2)), np.zeros(0))


def tree_stems(
    xy: np.ndarray,
    ground: Ground,
    rng: np.random.Generator,
    *,
    dbh_range_m: tuple[float, float] = (0.15, 0.45),
    height_range_m: tuple[float, float] = (8.0, 15.0),
    first_id: int = 1,
) -> pd.DataFrame:
    """Stem table (``STEM_COLUMNS`` of :mod:`.forest`) of upright park trees at ``xy``."""
    n = len(xy)
    dbh = rng.uniform(*dbh_range_m, n)
    height = rng.uniform(*height_range_m, n)
    taper = (dbh / 2 - 0.02) / (height - BREAST_HEIGHT_M)
    lean = np.radians(rng.uniform(0.0, 2.0, n))
    lean_dir = rng.uniform(-np.pi, np.pi, n)
    return pd.DataFrame(
        {
            "tree_id": np.arange(first_id, first_id + n),
            "x_base": xy[:, 0],
            "y_base": xy[:, 1],
            "z_base": ground.height(xy[:, 0], xy[:, 1]),
            "lean_x": np.tan(lean) * np.cos(lean_dir),
            "lean_y": np.tan(lean) * np.sin(lean_dir),
            "r_base_m": dbh / 2 + taper * BREAST_HEIGHT_M,
            "taper_m_per_m": taper,
            "height_m": height,
            "crown_base_m": rng.uniform(2.5, 3.5, n),
            "a2_m": rng.uniform(0.001, 0.004, n),
            "phase2_deg": rng.uniform(-180, 180, n),
            "a3_m": rng.uniform(0.0, 0.002, n),
            "phase3_deg": rng.uniform(-180, 180, n),
        }
    )[STEM_COLUMNS]


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
    harm = np.column_stack(
        [
            stems["a2_m"],
            np.radians(stems["phase2_deg"]),
            stems["a3_m"],
            np.radians(stems["phase3_deg"]),
        ]
    )
    sv, sf = tube_mesh(
        base - 0.3 * slope,
        base + height[:, None] * slope,
        r_base + 0.3 * taper,
        r_base - taper * height,
        n_sides=48,
        n_rings=16,
        harmonics=harm,
    )
    per = 2 * 15 * 48
    own = np.repeat(np.arange(n), per)
    pieces = [(sv, sf, np.full(len(sf), KIND_STEM), ids[own], part0 + own)]
    part = part0 + n
    k = 6
    bt = np.repeat(np.arange(n), k)
    hb = stems["crown_base_m"].to_numpy()[bt] + rng.random(bt.size) * 0.6 * (
        height[bt] - stems["crown_base_m"].to_numpy()[bt]
    )
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
