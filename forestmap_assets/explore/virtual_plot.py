"""The virtual forest plot of ``forestmap explore`` (men_spec 7.7): forest, virtual scanner and the
global frame (levelled frame of the first scan); free standing positions clear of stems and
understorey, scan poses on the ground, and the seeded random streams (scanner noise, walking, a
priori) shared by every survey of one plot."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from forestmap_assets.sim.campaign import relative_pose, wrap_deg
from forestmap_assets.sim.forest import make_forest
from forestmap_assets.sim.scanner import RESOLUTION_DIVISOR, ScanPose, VirtualScanner
from forestmap_assets.sim.scene_mesh import KIND_UNDERSTOREY
from forestmap_assets.sim.stems import breast_height_table


@dataclass
class VirtualPlot:
    """A virtual forest plot, the scanner, and the global frame (levelled frame of the first
    scan, world pose ``origin``)."""

    forest: object
    scanner: VirtualScanner
    origin: ScanPose
    plot_size: float
    _understorey_xy: np.ndarray | None = field(default=None, repr=False)

    def to_global(self, xy_world) -> np.ndarray:
        c, s = (
            np.cos(np.radians(self.origin.heading_deg)),
            np.sin(np.radians(self.origin.heading_deg)),
        )
        d = np.asarray(xy_world, dtype=np.float64).reshape(-1, 2) - [self.origin.x, self.origin.y]
        return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])

    def to_world(self, xy_global) -> np.ndarray:
        c, s = (
            np.cos(np.radians(self.origin.heading_deg)),
            np.sin(np.radians(self.origin.heading_deg)),
        )
        g = np.asarray(xy_global, dtype=np.float64).reshape(-1, 2)
        return np.column_stack([c * g[:, 0] - s * g[:, 1], s * g[:, 0] + c * g[:, 1]]) + [
            self.origin.x,
            self.origin.y,
        ]

    def plot_polygon(self) -> np.ndarray:
        """Plot corners in the global frame."""
        h = self.plot_size / 2
        return self.to_global(np.array([[-h, -h], [h, -h], [h, h], [-h, h]]))

    def ground(self, x, y) -> np.ndarray:
        return self.forest.ground.height(
            np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        )

    def is_free(self, xy_world, clearance_m: float = 0.5) -> np.ndarray:
        """Positions (world) at least ``clearance_m`` from every stem and understorey object."""
        xy = np.asarray(xy_world, dtype=np.float64).reshape(-1, 2)
        bh = breast_height_table(self.forest.stems)
        d = np.hypot(
            xy[:, None, 0] - bh["x"].to_numpy()[None], xy[:, None, 1] - bh["y"].to_numpy()[None]
        )
        ok = (d >= bh["dbh_m"].to_numpy()[None] / 2 + clearance_m).all(axis=1)
        if self._understorey_xy is None:
            mesh = self.forest.mesh
            tri = mesh.triangles[mesh.kind == KIND_UNDERSTOREY]
            self._understorey_xy = (
                mesh.vertices[np.unique(tri.ravel()), :2] if len(tri) else np.zeros((0, 2))
            )
        if len(self._understorey_xy):
            from scipy.spatial import cKDTree

            dist, _ = cKDTree(self._understorey_xy).query(xy)
            ok &= dist >= clearance_m
        return ok

    def free_near(
        self, xy_world, rng: np.random.Generator, clearance_m: float = 0.5, max_shift_m: float = 3.0
    ) -> np.ndarray:
        """The position, or the nearest free one found on rings around it."""
        p = np.asarray(xy_world, dtype=np.float64).reshape(2)
        if self.is_free(p, clearance_m)[0]:
            return p
        for r in np.arange(0.25, max_shift_m + 1e-9, 0.25):
            ang = rng.uniform(0, 2 * np.pi) + np.arange(16) * (2 * np.pi / 16)
            cand = p + r * np.column_stack([np.cos(ang), np.sin(ang)])
            ok = self.is_free(cand, clearance_m)
            if ok.any():
                return cand[np.argmax(ok)]
        return p

    def pose_at(
        self, xy_world, heading_deg: float, rng: np.random.Generator, height_m: float = 1.5
    ) -> ScanPose:
        x, y = (float(v) for v in np.asarray(xy_world).reshape(2))
        z = float(self.ground(x, y)) + height_m + float(rng.uniform(-0.1, 0.1))
        return ScanPose(x, y, z, float(wrap_deg(heading_deg)))

    def global_pose(self, pose: ScanPose) -> np.ndarray:
        """(x, y, z, heading) of a scan in the global frame (truth)."""
        return relative_pose(pose, self.origin)


def make_plot(
    plot_size: float = 40.0,
    trees: int = 40,
    seed: int = 0,
    *,
    resolution: str = "full",
    start_xy: Sequence[float] | None = None,
    forest_kwargs: dict | None = None,
    scanner_kwargs: dict | None = None,
) -> tuple[VirtualPlot, np.random.SeedSequence]:
    """The virtual plot of ``seed`` and the seed sequence for everything that follows; the first
    scan stands at ``start_xy`` (world; default a quarter of the plot in from the south-west
    corner, inferred) with a random heading."""
    if resolution not in RESOLUTION_DIVISOR:
        raise ValueError(f"resolution: {resolution!r} is not one of {list(RESOLUTION_DIVISOR)}")
    ss_forest, ss_origin, ss_rest = np.random.SeedSequence(seed).spawn(3)
    start = np.array(
        [-plot_size / 4, -plot_size / 4] if start_xy is None else start_xy, dtype=np.float64
    )
    forest = make_forest(
        trees,
        plot_size,
        scan_xy=start[None],
        seed=np.random.default_rng(ss_forest),
        **(forest_kwargs or {}),
    )
    scanner = VirtualScanner(forest, resolution=resolution, **(scanner_kwargs or {}))
    rng = np.random.default_rng(ss_origin)
    heading = float(rng.uniform(-180.0, 180.0))
    vp = VirtualPlot(forest, scanner, ScanPose(0.0, 0.0, 0.0), plot_size)
    vp.origin = vp.pose_at(start, heading, rng)
    return vp, ss_rest


def plot_and_streams(plot_size, trees, seed, resolution, start_xy, forest_kwargs, scanner_kwargs):
    """The virtual plot of ``seed`` and its random streams: scanner noise (seed sequence),
    walking and a priori (generators); the same for :func:`explore` and
    :func:`survey_positions`, so both survey one plot alike."""
    vp, ss = make_plot(
        plot_size,
        trees,
        seed,
        resolution=resolution,
        start_xy=start_xy,
        forest_kwargs=forest_kwargs,
        scanner_kwargs=scanner_kwargs,
    )
    ss_walk, ss_noise, ss_prior = ss.spawn(3)
    return vp, ss_noise, np.random.default_rng(ss_walk), np.random.default_rng(ss_prior)
