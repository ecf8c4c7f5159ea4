"""Virtual scans rendered inside a registered point cloud (issue 19, inferred).

Issue 19's acceptance scans are rendered inside a real registered TLS cloud of a pine forest
from known poses. That data differs from a ray-cast mesh in ways the pipeline must survive: the
source cloud saw each trunk only from its own scanner positions (the backs and sides it missed
are holes a new vantage point looks through), its points are discrete (a sparse patch lets the
background through, a splat widens a silhouette), and its noise is that of another scanner.
This module renders such scans from any cloud, so that the simulator's realistic forest, first
scanned into a merged "TLS" cloud, can be rendered again from new positions
(``benchmarks/bench_survey.py``, kind ``render``).

:func:`render_scan` is a spherical depth buffer at the render's angular step: each source point
within range falls into its pixel (azimuth, elevation) and is splatted as a disc of radius
``splat_m`` (its angular radius ``splat_m / r`` in pixels, rounded), the nearest depth wins every
pixel, and the pixel returns its own source point when that point's centre fell in it, else a
point on the pixel's centre ray at the winning depth; ``range_sigma_m`` adds range noise along
the ray. Points come back in a levelled frame at the origin with the world's axes (the caller
turns them into a scanner frame).
"""

from __future__ import annotations

import numpy as np


def _disc_offsets(k: int) -> np.ndarray:
    """Pixel offsets (m, 2) (row, col) of a disc of radius ``k`` pixels, centre first."""
    d = np.arange(-k, k + 1)
    dr, dc = np.meshgrid(d, d, indexing="ij")
    inside = dr**2 + dc**2 <= k * k + 0.5
    off = np.column_stack([dr[inside], dc[inside]])
    order = np.argsort(np.abs(off).sum(axis=1), kind="stable")
    return off[order]


def render_scan(points: np.ndarray, origin, *, step_deg: float = 0.1, splat_m: float = 0.007,
                min_range_m: float = 0.5, max_range_m: float = 60.0,
                elevation_deg: tuple[float, float] = (-50.0, 60.0), max_splat_px: int = 6,
                range_sigma_m: float = 0.0, rng: np.random.Generator | None = None,
                source: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """The returns (m, 3) of a scan at ``origin`` rendered from ``points`` (n, 3, same frame),
    relative to ``origin`` (world axes); see the module docstring. ``source``: also each
    return's source point (m,), an index into ``points`` (its colour is the return's)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    v = p - np.asarray(origin, dtype=np.float64).reshape(1, 3)
    r = np.sqrt((v * v).sum(axis=1))
    keep = (r > min_range_m) & (r < max_range_m)
    index = np.flatnonzero(keep)
    v, r = v[keep], r[keep]
    step = np.radians(step_deg)
    el0, el1 = np.radians(elevation_deg[0]), np.radians(elevation_deg[1])
    az = np.arctan2(v[:, 1], v[:, 0])
    el = np.arcsin(np.clip(v[:, 2] / r, -1.0, 1.0))
    inside = (el >= el0) & (el < el1)
    v, r, az, el, index = v[inside], r[inside], az[inside], el[inside], index[inside]
    n_cols = int(np.ceil(2 * np.pi / step))
    n_rows = int(np.ceil((el1 - el0) / step))
    col = np.minimum(((az + np.pi) / step).astype(np.int64), n_cols - 1)
    row = np.minimum(((el - el0) / step).astype(np.int64), n_rows - 1)
    k = np.minimum(np.floor(splat_m / (r * step) + 0.5).astype(np.int64), max_splat_px)
    keys, depth, src, own = [row * n_cols + col], [r], [np.arange(r.size)], [np.ones(r.size, bool)]
    for kk in range(1, int(k.max(initial=0)) + 1):
        idx = np.flatnonzero(k == kk)
        if not idx.size:
            continue
        off = _disc_offsets(kk)[1:]
        rr = row[idx, None] + off[None, :, 0]
        cc = (col[idx, None] + off[None, :, 1]) % n_cols
        ok = (rr >= 0) & (rr < n_rows)
        keys.append((rr * n_cols + cc)[ok])
        depth.append(np.broadcast_to(r[idx, None], rr.shape)[ok])
        src.append(np.broadcast_to(idx[:, None], rr.shape)[ok])
        own.append(np.zeros(int(ok.sum()), bool))
    key, dep, s, mine = (np.concatenate(a) for a in (keys, depth, src, own))
    order = np.lexsort((dep, key))
    key, dep, s, mine = key[order], dep[order], s[order], mine[order]
    first = np.ones(key.size, bool)
    first[1:] = key[1:] != key[:-1]
    key, dep, s, mine = key[first], dep[first], s[first], mine[first]
    pr, pc = key // n_cols, key % n_cols
    a = -np.pi + (pc + 0.5) * step
    e = el0 + (pr + 0.5) * step
    ray = np.column_stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    own_ray = v[s] / r[s, None]
    ray = np.where(mine[:, None], own_ray, ray)
    if range_sigma_m:
        rng = rng or np.random.default_rng(0)
        dep = dep + rng.normal(0.0, range_sigma_m, dep.size)
    return (ray * dep[:, None], index[s]) if source else ray * dep[:, None]


def write_ply_xyz(path, xyz: np.ndarray, rgb: np.ndarray | None = None, *, double: bool = False) -> None:
    """A binary little-endian PLY of float32 ``x, y, z`` (float64 with ``double``, as Sylva's
    simulator writes them; and uchar ``red, green, blue`` from ``rgb``, (n, 3) uint8), written
    atomically."""
    from forestmap_assets.io.writers import atomic_write

    xyz = np.asarray(xyz).reshape(-1, 3)
    real = "<f8" if double else "<f4"
    names = [("x", real), ("y", real), ("z", real)] + (
        [] if rgb is None else [("red", "u1"), ("green", "u1"), ("blue", "u1")])
    table = np.empty(len(xyz), names)
    for i, c in enumerate("xyz"):
        table[c] = xyz[:, i]
    if rgb is not None:
        for i, c in enumerate(("red", "green", "blue")):
            table[c] = rgb[:, i]
    kinds = {"<f4": "float", "<f8": "double", "u1": "uchar"}
    props = "".join(f"property {kinds[t]} {n}\n" for n, t in names)
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n{props}end_header\n"
    with atomic_write(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(head.encode("ascii"))
            f.write(table.tobytes())


def registered_cloud(world, positions: np.ndarray, *, seed: int = 0, n_cols: int = 6000,
                     n_rows: int = 1440, range_sigma_m: float = 0.003, voxel_m: float = 0.01,
                     scanner_height_m: float = 1.5, colour: bool = False, mixed_range: str = "first",
                     progress=None) -> tuple[np.ndarray, np.ndarray | None]:
    """The "registered TLS cloud" of ``world`` (a :class:`~.forest.Forest`): scans from
    ``positions`` (n, 2) with a survey-grade scanner (a finer grid than the thesis's, 3 mm range
    noise, a 0.3 mrad beam leaving a 5 mm exit; inferred) merged in the world frame and thinned
    to one point per ``voxel_m`` voxel, as such clouds are shared: its points (n, 3) and, with
    ``colour``, their 8-bit RGB (n, 3) as a colourised cloud has (``sim/colour.py``; else None);
    ``mixed_range`` the source scanner's mixed pixels (``"blend"``: ghost points behind edges)."""
    from forestmap_assets.core.cloud import voxel_subsample
    from forestmap_assets.sim.scanner import ScanPose, VirtualScanner

    scanner = VirtualScanner(world, resolution="full", n_cols=n_cols, n_rows=n_rows,
                             range_sigma_m=range_sigma_m, beam_exit_m=0.005, divergence_mrad=0.3,
                             intensity=False, colour=colour, mixed_range=mixed_range)
    rng = np.random.default_rng(seed)
    ground = world.ground.height(positions[:, 0], positions[:, 1])
    parts, colours = [], []
    for i, (x, y) in enumerate(positions):
        pose = ScanPose(float(x), float(y), float(ground[i] + scanner_height_m),
                        float(rng.uniform(-180.0, 180.0)))
        scan = scanner.scan(pose, rng)
        pts = scan.world_points(noisy=True).reshape(-1, 3)
        ok = np.isfinite(pts).all(axis=1)
        parts.append(pts[ok])
        if colour:
            colours.append(scan.image.rgb.reshape(-1, 3)[ok])
        if progress:
            progress(f"source scan {i + 1}/{len(positions)}: {len(parts[-1])} points")
    cloud = np.vstack(parts)
    keep = voxel_subsample(cloud, voxel_m) if voxel_m else np.arange(len(cloud))
    return cloud[keep], (np.vstack(colours)[keep] if colour else None)


def render_campaign(out, *, seed: int = 1, scans: int = 6, source_scans: int = 9, trees: int = 40,
                    plot_size: float = 40.0, stems: str = "realistic", step_deg: float = 0.1,
                    splat_m: float = 0.007, range_sigma_m: float = 0.003, colour: bool = False,
                    source_kwargs: dict | None = None, progress=None):
    """A campaign folder of ``scans`` PLY scans rendered (:func:`render_scan`) inside the
    registered cloud (:func:`registered_cloud`) of a simulated forest seen from
    ``source_scans`` other positions: ``campaign.yaml`` without prior or sensor block,
    ``scans/<id>.ply`` in each scanner's levelled frame (unknown heading), ``truth/poses.csv``
    and ``truth/trees.csv`` (axis at 1.3 m, DBH, renders that see the stem) in the frame of the
    first scan; ``colour``: the cloud is colourised and the scans carry its RGB. Returns the
    folder's path."""
    from pathlib import Path

    import pandas as pd

    from forestmap_assets.core.geometry import rot_z
    from forestmap_assets.sim.forest import make_forest, scan_layout

    say = progress or (lambda _m: None)
    out = Path(out)
    (out / "scans").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    ss_layout, ss_forest, ss_source, ss_render = np.random.SeedSequence(seed).spawn(4)
    rng = np.random.default_rng(ss_layout)
    render_xy = scan_layout(scans, plot_size, rng)
    source_xy = scan_layout(source_scans, plot_size, rng, spacing_m=9.0, jitter_m=2.0)
    world = make_forest(trees, plot_size, n_scans=scans + source_scans,
                        scan_xy=np.vstack([render_xy, source_xy]),
                        seed=np.random.default_rng(ss_forest), stems=stems)
    cloud, rgb = registered_cloud(world, source_xy, seed=int(ss_source.generate_state(1)[0]), colour=colour,
                                  progress=say, **(source_kwargs or {}))
    say(f"registered cloud: {len(cloud)} points from {source_scans} scans")
    rng = np.random.default_rng(ss_render)
    ground = world.ground.height(render_xy[:, 0], render_xy[:, 1])
    origins = np.column_stack([render_xy, ground + 1.5 + rng.uniform(-0.1, 0.1, scans)])
    headings = rng.uniform(-180.0, 180.0, scans)
    truth = world.trees_at_breast_height()
    ids = [f"r{k + 1}" for k in range(scans)]
    seen = np.zeros(len(truth), int)
    for k, sid in enumerate(ids):
        rel, src = render_scan(cloud, origins[k], step_deg=step_deg, splat_m=splat_m,
                               range_sigma_m=range_sigma_m, rng=rng, source=True)
        write_ply_xyz(out / "scans" / f"{sid}.ply", rel @ rot_z(headings[k]),  # world -> scanner
                      None if rgb is None else rgb[src])
        pts = rel + origins[k]
        band = np.abs(pts[:, 2, None] - (truth["z"].to_numpy() + 1.3)) < 0.5
        near = np.hypot(pts[:, 0, None] - truth["x"].to_numpy(), pts[:, 1, None] - truth["y"].to_numpy())
        seen += ((near < truth["dbh_m"].to_numpy() / 2 + 0.03) & band).sum(axis=0) >= 30
        say(f"render {sid}: {len(rel)} points")
    first = rot_z(headings[0]).T  # world -> first scan's frame
    rel0 = (origins - origins[0]) @ first.T
    poses = pd.DataFrame({"scan": ids, "x": rel0[:, 0], "y": rel0[:, 1], "z": rel0[:, 2],
                          "heading_deg": (headings - headings[0] + 180.0) % 360.0 - 180.0})
    poses.to_csv(out / "truth" / "poses.csv", index=False, float_format="%.6f")
    t = (truth[["x", "y", "z"]].to_numpy() - origins[0]) @ first.T
    pd.DataFrame({"tree_id": truth["tree_id"], "x": t[:, 0], "y": t[:, 1], "z": t[:, 2],
                  "dbh_m": truth["dbh_m"], "n_visible_scans": seen}).to_csv(
        out / "truth" / "trees.csv", index=False, float_format="%.6f")
    listing = "\n".join(f"  - {{id: {sid}, path: scans/{sid}.ply}}" for sid in ids)
    (out / "campaign.yaml").write_text(
        f"# {scans} scans rendered inside the registered cloud of a simulated {stems}-stem forest "
        f"(seed {seed}, {source_scans} source scans)\nname: {out.name}\nenvironment: forest\n"
        f"scans:\n{listing}\n")
    return out
