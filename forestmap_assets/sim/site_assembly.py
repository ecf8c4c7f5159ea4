"""Assembly of a structured site (spec 10.1): the :class:`Site` record (mesh, ground, truth tables
of pillars/poles, wall corner lines and trees, and the cart's scan positions), the labelled-mesh
builder with running part ids, cart stops along a path and wall openings. Numbers (inferred)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from forestmap_assets.sim.ground import Ground
from forestmap_assets.sim.scene_mesh import (
    SceneMesh,
    concat_meshes,
)
from forestmap_assets.sim.site_meshes import Wall


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
        from forestmap_assets.sim.stems import breast_height_table

        return breast_height_table(self.stems)


class SiteBuilder:
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
        return concat_meshes(self.pieces)


def path_points(vertices: np.ndarray, s: np.ndarray, closed: bool):
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


def place_scans(
    path: np.ndarray,
    n: int,
    spacing: float,
    closed: bool,
    start: float,
    rng: np.random.Generator,
    along_jitter: float,
    across_jitter: float,
    heading_jitter_deg: float,
):
    """``n`` cart stops every ``spacing`` m of path (clamped to fit), jittered (inferred)."""
    _, _, total = path_points(path, np.zeros(1), closed)
    usable = total if closed else total - start - 1.0
    spacing = min(spacing, usable / max(n if closed else n - 1, 1))
    s = start + spacing * np.arange(n) + rng.uniform(-along_jitter, along_jitter, n)
    pts, head, _ = path_points(path, s, closed)
    h = np.radians(head)
    pts = pts + rng.uniform(-across_jitter, across_jitter, n)[:, None] * np.column_stack(
        [-np.sin(h), np.cos(h)]
    )
    headings = head + rng.uniform(-heading_jitter_deg, heading_jitter_deg, n)
    return pts, (headings + 180.0) % 360.0 - 180.0, spacing


def openings_along(
    length: float,
    rng: np.random.Generator,
    every_m: float,
    width_m: float,
    zlo: float,
    zhi: float,
    margin_m: float,
    probability: float,
):
    """One opening per ``every_m`` stretch of a wall (with ``probability``), away from ends."""
    out = []
    n = int(length // every_m)
    for k in range(n):
        a, b = k * every_m + margin_m, (k + 1) * every_m - margin_m - width_m
        if b > a and rng.random() < probability:
            s0 = rng.uniform(a, b)
            out.append((s0, s0 + width_m, zlo, zhi))
    return tuple(out)
