"""``forestmap simulate``: a synthetic survey campaign folder with ground truth (DESIGN.md 2-3).

A virtual forest plot (:mod:`.forest`) is scanned from ``scans`` tripod positions by the
virtual Riegl LMS-Z210 (:mod:`.scanner`), imitating the thesis's forest site (spec 10.1: scans
T, S, R, Q, O, N, tripod levelled, operator a priori alignments for neighbouring pairs, spec
1.2 / 10.6). Written::

    OUT/campaign.yaml            name, environment: forest, sensor, scans, pairs, search
    OUT/scans/<id>.<fmt>         one range image per scan, in the scanner's own (tilted) frame
    OUT/truth/poses.csv          scan,x,y,z,heading_deg       (levelled frame of the first scan)
    OUT/truth/trees.csv          tree_id,x,y,z,dbh_m,n_visible_scans            (same frame)
    OUT/truth/stems.csv          stem axis and radius model per tree (see stems.py; realistic
                                 stems add the shape columns of stem_shapes.py)
    OUT/truth/labels/<id>.npz    per-pixel truth: kind (KIND_*, 255 none), tree_id (-1 none),
                                 mixed (first return from the beam edge, not its centre)

A relative pose (dx, dy, dz, dheading) of pair (scan, reference) is the location of ``scan`` in
the levelled frame of ``reference``: ``p_ref = R_z(dheading) p_scan + d`` (spec 6.1).

``site="corridor"`` / ``"parking-lot"`` simulate the thesis's structured sites instead (spec 10.1,
:mod:`.sites`): scans 1, 2, 3, ... (corridor, ``environment: indoor``) or E, F, G, ... (parking
lot, ``environment: outdoor``) from a cart at about 1.3 m, consecutive along the corridor / the
lot's lane, consecutive pairs a priori (plus the loop-closing pair on a ring corridor), and the
extra truth::

    OUT/truth/pillars.csv        pillar_id,kind,x,y,z,radius_m,height_m,n_visible_scans
    OUT/truth/wall_lines.csv     line_id,x0,y0,z0,x1,y1,z1,wall_id,face  (top edge of every wall
                                 face: the wall/ceiling or wall-top corner lines)
    OUT/truth/visible_lines.csv  scan,line_id,x,y,z  corner-line samples every 0.1 m that the
                                 scan sees (ray cast), in that scan's levelled frame
    OUT/truth/labels/<id>.npz    also ``part`` (mesh object id per pixel)
"""

from __future__ import annotations

import io
import time
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from forestmap_assets.sim.forest import Forest, make_forest
from forestmap_assets.sim.scanner import (
    RESOLUTION_DIVISOR,
    ScanPose,
    ScanResult,
    VirtualScanner,
    rot_z,
)
from forestmap_assets.sim.scene_mesh import KIND_STEM
from forestmap_assets.sim.site_assembly import Site
from forestmap_assets.sim.site_meshes import PILLAR_COLUMNS
from forestmap_assets.sim.site_truth import (
    lines_in_frame,
    points_in_frame,
    visible_line_samples,
    visible_parts,
)
from forestmap_assets.sim.sites import SITE_ENVIRONMENT, SITES, make_site
from forestmap_assets.sim.stem_shapes import STEM_MODELS
from forestmap_assets.sim.stems import STEM_COLUMNS, breast_height_table, stems_in_frame

THESIS_IDS = "TSRQON"  # spec 10.1
_ID_ORDER = THESIS_IDS + "MLKJIHGFEDCBAPUVWXYZ"
_LOT_ORDER = "EFGHIJKLMNOPQRSTUVWXYZABCD"  # parking lot E, F, G, H, I, J (spec 10.1)
PILLAR_TRUTH_COLUMNS = PILLAR_COLUMNS + ["n_visible_scans"]
# Thesis search boxes (spec 6.6) used as the minimum box of a simulated campaign.
_MIN_SEARCH = {"forest": (5.0, 1.25, 60.0), "indoor": (5.0, 0.625, 30.0),
               "outdoor": (10.0, 1.25, 100.0)}
FORMATS = {"npz": ".npz", "las": ".las", "ply": ".ply", "e57": ".e57"}
POSE_COLUMNS = ["scan", "x", "y", "z", "heading_deg"]
TREE_COLUMNS = ["tree_id", "x", "y", "z", "dbh_m", "n_visible_scans"]


def scan_ids(n: int, site: str = "forest") -> list[str]:
    """Scan names of the thesis's sites (spec 10.1): forest T, S, R, Q, O, N, then the other
    letters, then letters with a number; corridor 1, 2, 3, ...; parking lot E, F, G, ..."""
    if site == "corridor":
        return [str(i + 1) for i in range(n)]
    order = _LOT_ORDER if site == "parking-lot" else _ID_ORDER
    return [order[i % 26] + (str(i // 26 + 1) if i >= 26 else "") for i in range(n)]


def wrap_deg(a):
    """Angle(s) wrapped into (-180, 180]."""
    return 180.0 - np.mod(180.0 - np.asarray(a, dtype=np.float64), 360.0)


def relative_pose(scan: ScanPose, reference: ScanPose) -> np.ndarray:
    """(dx, dy, dz, dheading_deg): ``scan`` in the levelled frame of ``reference`` (spec 6.1)."""
    d = rot_z(-reference.heading_deg) @ (scan.origin - reference.origin)
    return np.array([d[0], d[1], d[2], float(wrap_deg(scan.heading_deg - reference.heading_deg))])


def neighbour_pairs(xy: np.ndarray, max_distance_m: float = 11.0) -> list[tuple[int, int]]:
    """(scan, reference) index pairs, reference earlier in the order: every pair closer than
    ``max_distance_m`` plus consecutive scans, so the pair graph is connected (inferred)."""
    i, j = np.tril_indices(len(xy), k=-1)
    dist = np.linalg.norm(xy[i] - xy[j], axis=1)
    keep = (dist <= max_distance_m) | (i == j + 1)
    return [(int(a), int(b)) for a, b in zip(i[keep], j[keep], strict=True)]


def perturb_prior(
    rel: np.ndarray, prior_error: tuple[float, float], rng: np.random.Generator
) -> np.ndarray:
    """A priori alignment (Th. §6.1.2): the true relative pose plus a translation error of
    uniform random 3-D direction and magnitude U(0, metres), and a heading error U(-deg, deg)."""
    m, deg = prior_error
    v = rng.standard_normal(3)
    v *= rng.uniform(0.0, m) / max(np.linalg.norm(v), 1e-12)
    return np.concatenate([rel[:3] + v, [float(wrap_deg(rel[3] + rng.uniform(-deg, deg)))]])


def visible_trees(
    result: ScanResult,
    forest: Forest,
    *,
    max_range_m: float = 20.0,
    min_length_m: float = 1.0,
    max_gap_m: float = 0.25,
) -> np.ndarray:
    """Tree ids whose stem is visible in a scan: stem hits (per-pixel truth labels) within
    ``max_range_m`` covering at least ``min_length_m`` of trunk height, where consecutive hit
    heights further apart than ``max_gap_m`` do not count as covered (inferred)."""
    sel = (result.kind == KIND_STEM) & (result.true_range_m <= max_range_m)
    if not sel.any():
        return np.empty(0, dtype=np.int64)
    tree = result.tree_id[sel].astype(np.int64)
    z = result.world_points(noisy=False)[sel][:, 2]
    z_base = forest.stems.set_index("tree_id")["z_base"].reindex(tree).to_numpy()
    h = z - z_base
    order = np.lexsort((h, tree))
    tree, h = tree[order], h[order]
    dh = np.diff(h)
    same = tree[1:] == tree[:-1]
    covered = np.where(same & (dh <= max_gap_m), dh, 0.0)
    length = np.bincount(tree[1:], weights=covered, minlength=tree.max() + 1)
    return np.flatnonzero(length >= min_length_m)


def save_npz(path: Path, arrays: dict[str, np.ndarray], compresslevel: int = 1) -> None:
    """``np.savez_compressed`` with fixed zip timestamps, so equal arrays give equal bytes."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=compresslevel) as zf:
        for name, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue(), compresslevel=compresslevel)


def write_scan_file(path: Path, result: ScanResult, fmt: str) -> None:
    """Write one scan: npz here (DESIGN.md 2 keys), other formats via ``io.writers``."""
    img = result.image
    if fmt == "npz":
        arrays = {"range": img.range_m, "azimuth_deg": img.azimuth_deg,
                  "elevation_deg": img.elevation_deg}
        if img.intensity is not None:
            arrays["intensity"] = img.intensity
        if img.rgb is not None:
            arrays["rgb"] = img.rgb
        save_npz(path, arrays)
    else:
        from forestmap_assets.io.writers import write_scan

        write_scan(path, img)


def _tilts(tilt_deg, n: int) -> np.ndarray | None:
    if tilt_deg is None:
        return None
    t = np.asarray(tilt_deg, dtype=np.float64)
    if t.shape == (2,):
        t = np.tile(t, (n, 1))
    if t.shape != (n, 2):
        raise ValueError(f"tilt_deg: expected (roll, pitch) or {n} such pairs, got shape {t.shape}")
    return t


def _r(x, nd: int = 6) -> float:
    return float(round(float(x), nd))


def cart_tilt(ground, xy: np.ndarray, heading_deg: np.ndarray, eps_m: float = 0.25) -> np.ndarray:
    """(roll, pitch) (n, 2) deg of a cart standing on ``ground`` at ``xy`` facing ``heading_deg``:
    the scanner's z axis is the ground normal (``p_world = R_z(h) R_y(pitch) R_x(roll) p_s``,
    :class:`~.scanner.ScanPose`; the normal is the gradient over +-``eps_m``, inferred)."""
    x, y = xy[:, 0], xy[:, 1]
    gx = (ground.height(x + eps_m, y) - ground.height(x - eps_m, y)) / (2 * eps_m)
    gy = (ground.height(x, y + eps_m) - ground.height(x, y - eps_m)) / (2 * eps_m)
    up = np.column_stack([-gx, -gy, np.ones_like(gx)])
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    h = np.radians(heading_deg)
    ux = np.cos(h) * up[:, 0] + np.sin(h) * up[:, 1]  # normal in the levelled cart frame
    uy = -np.sin(h) * up[:, 0] + np.cos(h) * up[:, 1]
    roll = np.degrees(np.arcsin(np.clip(-uy, -1, 1)))
    pitch = np.degrees(np.arctan2(ux, up[:, 2]))
    return np.column_stack([roll, pitch])


def site_pairs(xy: np.ndarray, closed: bool, close_factor: float = 1.6,
               span: int = 1) -> list[tuple[int, int]]:
    """(scan, reference) index pairs of a cart survey: consecutive scans (thesis FE ... JI,
    21 ... 87, spec 10.1; ``span`` > 1 adds scans up to ``span`` stops apart, inferred) and, on a
    closed ring whose last scan is at most ``close_factor`` times the median consecutive
    distance from the first, the pairs across the start of the ring (the loop, inferred)."""
    n = len(xy)
    pairs = [(i, i - k) for k in range(1, span + 1) for i in range(k, n)]
    if closed and n > 2:
        step = np.median(np.linalg.norm(np.diff(xy, axis=0), axis=1))
        if np.linalg.norm(xy[-1] - xy[0]) <= close_factor * step:
            pairs += [(n - 1 - a, b) for a in range(span) for b in range(span - a)
                      if n - 1 - a > b + span]
    return sorted(pairs, key=lambda p: (p[0], -p[1]))


def simulate_campaign(
    out,
    *,
    scans: int = 6,
    trees: int = 40,
    plot_size: float = 40.0,
    seed: int = 0,
    resolution: str = "full",
    prior_error: tuple[float, float] = (1.0, 10.0),
    no_prior: bool = False,
    fmt: str = "npz",
    tilt_deg: Sequence[float] | Sequence[Sequence[float]] | None = None,
    progress: Callable[[str], None] | None = None,
    scanner_height_m: float | None = None,
    neighbour_distance_m: float = 11.0,
    visible_range_m: float = 20.0,
    visible_length_m: float = 1.0,
    write_labels: bool = True,
    forest_kwargs: dict | None = None,
    scanner_kwargs: dict | None = None,
    site: str = "forest",
    site_kwargs: dict | None = None,
    follow_ground_tilt: bool = True,
    tilt_noise_deg: float = 0.0,
    pair_span: int = 1,
    stems: str = "circular",
) -> Path:
    """Simulate a campaign into folder ``out`` and return its path (DESIGN.md 3, ``simulate``).

    ``site`` is ``forest`` (tripod, scanner ``scanner_height_m`` = 1.5 +- 0.1 m above the ground,
    headings U(-180, 180) deg, neighbouring pairs), ``corridor`` or ``parking-lot`` (spec 10.1,
    :mod:`.sites` with ``site_kwargs``; ``plot_size`` is the ring / corridor / lot size and
    ``trees`` the parking lot's trees: a cart at ``scanner_height_m`` = 1.3 +- 0.01 m heading
    along its path, consecutive pairs, ``environment`` indoor / outdoor). ``tilt_deg`` (roll,
    pitch), or one pair per scan, tilts the scanners: scans are then stored in the tilted
    scanner frame and the tilt is written to ``campaign.yaml``; without it a cart on sloping
    ground (parking lot) tilts with the ground when ``follow_ground_tilt``. ``tilt_noise_deg``
    adds N(0, sigma) to the tilt written to ``campaign.yaml`` (a tilt-sensor error; the thesis's
    wall-line z spread, spec 10.4). ``prior_error`` (metres, degrees) bounds the a priori error
    of the pairs; ``no_prior`` writes no pairs and no search box; ``pair_span`` > 1 also pairs
    cart stops up to that many apart (the thesis: 1). ``stems`` is the forest's stem model,
    ``circular`` or ``realistic`` (issue 19, :mod:`.stem_shapes`: out-of-round, fluted, rough,
    swept and forked stems, dead branch stubs, dense understorey; the same plot layout for one
    seed; ``truth/stems.csv`` gains the shape columns). Deterministic for ``seed``.
    """
    if fmt not in FORMATS:
        raise ValueError(f"format: {fmt!r} is not one of {list(FORMATS)}")
    if resolution not in RESOLUTION_DIVISOR:
        raise ValueError(f"resolution: {resolution!r} is not one of {list(RESOLUTION_DIVISOR)}")
    if site not in SITES:
        raise ValueError(f"site: {site!r} is not one of {list(SITES)}")
    if scans < 1:
        raise ValueError("scans: need at least one scan")
    if stems not in STEM_MODELS or (stems != "circular" and site != "forest"):
        raise ValueError(f"stems: {stems!r} is not one of {list(STEM_MODELS)} (realistic: forest "
                         "site only)")
    say = progress or (lambda _msg: None)
    out = Path(out)
    (out / "scans").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    if write_labels:
        (out / "truth" / "labels").mkdir(exist_ok=True)
    ss_forest, ss_pose, ss_scan, ss_prior = np.random.SeedSequence(seed).spawn(4)
    t0 = time.perf_counter()
    rng = np.random.default_rng(ss_pose)
    ids = scan_ids(scans, site)
    tilts = _tilts(tilt_deg, scans)
    world: Forest | Site
    if site == "forest":
        world = make_forest(trees, plot_size, n_scans=scans,
                            seed=np.random.default_rng(ss_forest), stems=stems,
                            **(forest_kwargs or {}))
        say(f"forest: {trees} {stems} trees in a {plot_size:g} m plot, "
            f"{world.mesh.n_triangles} triangles")
        environment = "forest"
        headings = wrap_deg(rng.uniform(-180.0, 180.0, scans))
        heights = (1.5 if scanner_height_m is None else scanner_height_m) + rng.uniform(
            -0.1, 0.1, scans)
    else:
        world = make_site(site, scans, plot_size, seed=np.random.default_rng(ss_forest),
                          trees=trees, **(site_kwargs or {}))
        environment = SITE_ENVIRONMENT[site]
        say(f"{site}: {plot_size:g} m, {len(world.pillars)} pillars/poles, {len(world.walls)} "
            f"walls, {len(world.stems)} trees, {world.mesh.n_triangles} triangles")
        headings = wrap_deg(world.scan_heading_deg)
        heights = (1.3 if scanner_height_m is None else scanner_height_m) + rng.uniform(
            -0.01, 0.01, scans)
        if tilts is None and follow_ground_tilt:
            tilts = cart_tilt(world.ground, world.scan_xy, headings)
            if np.abs(tilts).max() < 1e-9:
                tilts = None
    measured = None
    if tilts is not None:
        measured = tilts + (rng.normal(0.0, tilt_noise_deg, tilts.shape) if tilt_noise_deg
                            else 0.0)
    xy = world.scan_xy
    ground_z = world.ground.height(xy[:, 0], xy[:, 1])
    poses = [
        ScanPose(float(xy[i, 0]), float(xy[i, 1]), float(ground_z[i] + heights[i]),
                 float(headings[i]), (0.0, 0.0) if tilts is None else tuple(map(float, tilts[i])))
        for i in range(scans)
    ]

    scanner = VirtualScanner(world, resolution=resolution, **(scanner_kwargs or {}))
    ext = FORMATS[fmt]
    max_tree = int(world.stems["tree_id"].max()) if len(world.stems) else 0
    n_visible = np.zeros(max_tree + 1, dtype=np.int64)
    pillars = getattr(world, "pillars", None)
    pillar_parts = getattr(world, "pillar_parts", np.zeros(0, np.int64))
    n_pillar_visible = np.zeros(len(pillar_parts), dtype=np.int64)
    visible_lines = []
    entries = []
    for i, (sid, pose, ss) in enumerate(zip(ids, poses, ss_scan.spawn(scans), strict=True)):
        ts = time.perf_counter()
        result = scanner.scan(pose, np.random.default_rng(ss))
        vis = visible_trees(result, world, max_range_m=visible_range_m,
                            min_length_m=visible_length_m) if max_tree else np.zeros(0, int)
        n_visible[vis] += 1
        if len(pillar_parts):
            z = result.world_points(noisy=False)[..., 2]
            near = result.true_range_m <= visible_range_m
            n_pillar_visible += visible_parts(np.where(near, result.part, -1), z, pillar_parts,
                                              min_extent_m=visible_length_m)
        if site != "forest":
            vis_l = visible_line_samples(world.mesh, world.wall_lines, pose.origin)
            visible_lines.append(points_in_frame(vis_l, pose.origin, pose.heading_deg)
                                 .assign(scan=sid))
        write_scan_file(out / "scans" / f"{sid}{ext}", result, fmt)
        if write_labels:
            labels = {"kind": result.kind, "tree_id": result.tree_id.astype(np.int16),
                      "mixed": result.mixed}
            if site != "forest":
                labels["part"] = result.part.astype(np.int32)
            save_npz(out / "truth" / "labels" / f"{sid}.npz", labels)
        entry = {"id": sid, "path": f"scans/{sid}{ext}"}
        if measured is not None:
            entry["tilt_deg"] = [_r(measured[i, 0]), _r(measured[i, 1])]
        entries.append(entry)
        say(f"scan {sid} ({i + 1}/{scans}): {result.image.shape[0]}x{result.image.shape[1]}, "
            f"{result.n_rays} rays, {int(vis.size)} stems visible, "
            f"{time.perf_counter() - ts:.1f} s")

    # truth, in the levelled frame of the first scan (the global frame)
    ref = poses[0]
    rel = np.array([relative_pose(p, ref) for p in poses])
    pd.DataFrame({"scan": ids, "x": rel[:, 0], "y": rel[:, 1], "z": rel[:, 2],
                  "heading_deg": rel[:, 3]})[POSE_COLUMNS].to_csv(
        out / "truth" / "poses.csv", index=False, float_format="%.6f")
    stems = world.stems if len(world.stems) else pd.DataFrame(columns=STEM_COLUMNS)
    stems_g = stems_in_frame(stems.astype(float).astype({"tree_id": int}), ref.origin,
                             ref.heading_deg)
    tree_tab = breast_height_table(stems_g)
    tree_tab["n_visible_scans"] = n_visible[tree_tab["tree_id"].to_numpy(dtype=int)]
    tree_tab[TREE_COLUMNS].to_csv(out / "truth" / "trees.csv", index=False, float_format="%.6f")
    stems_g.to_csv(out / "truth" / "stems.csv", index=False, float_format="%.6f")
    if site != "forest":
        pil = points_in_frame(pillars, ref.origin, ref.heading_deg)
        pil["n_visible_scans"] = n_pillar_visible
        pil[PILLAR_TRUTH_COLUMNS].to_csv(out / "truth" / "pillars.csv", index=False,
                                         float_format="%.6f")
        lines_in_frame(world.wall_lines, ref.origin, ref.heading_deg).to_csv(
            out / "truth" / "wall_lines.csv", index=False, float_format="%.6f")
        pd.concat(visible_lines, ignore_index=True)[["scan", "line_id", "x", "y", "z"]].to_csv(
            out / "truth" / "visible_lines.csv", index=False, float_format="%.4f")

    # campaign.yaml
    doc: dict = {
        "name": out.resolve().name,
        "environment": environment,
        "sensor": {"angular_step_deg": [_r(scanner.d_az, 9), _r(scanner.d_el, 9)], **scanner.sensor_beam()},
        "scans": entries,
    }
    if not no_prior:
        prng = np.random.default_rng(ss_prior)
        pairs = []
        index_pairs = (neighbour_pairs(xy, neighbour_distance_m) if site == "forest"
                       else site_pairs(xy, world.closed_loop, span=pair_span))
        for a, b in index_pairs:
            prior = perturb_prior(relative_pose(poses[a], poses[b]), prior_error, prng)
            pairs.append({"scan": ids[a], "reference": ids[b],
                          "a_priori": [_r(v, 4) for v in prior]})
        doc["pairs"] = pairs
        m, deg = prior_error
        bxy, bz, bh = _MIN_SEARCH[environment]
        doc["search"] = {"xy_m": _r(max(bxy, 1.5 * m), 4), "z_m": _r(max(bz, 1.5 * m), 4),
                         "heading_deg": _r(min(180.0, max(bh, 1.5 * deg)), 4)}
    with open(out / "campaign.yaml", "w") as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None)
    say(f"campaign written to {out} in {time.perf_counter() - t0:.1f} s")
    return out
