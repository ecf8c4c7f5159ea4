"""``forestmap simulate``: a synthetic survey campaign folder with ground truth (DESIGN.md 2-3).

A virtual forest plot (:mod:`.forest`) is scanned from ``scans`` tripod positions by the
virtual Riegl LMS-Z210 (:mod:`.scanner`), imitating the thesis's forest site (spec 10.1: scans
T, S, R, Q, O, N, tripod levelled, operator a priori alignments for neighbouring pairs, spec
1.2 / 10.6). Written::

    OUT/campaign.yaml            name, environment: forest, sensor, scans, pairs, search
    OUT/scans/<id>.<fmt>         one range image per scan, in the scanner's own (tilted) frame
    OUT/truth/poses.csv          scan,x,y,z,heading_deg       (levelled frame of the first scan)
    OUT/truth/trees.csv          tree_id,x,y,z,dbh_m,n_visible_scans            (same frame)
    OUT/truth/stems.csv          stem axis and radius model per tree (see forest.py)
    OUT/truth/labels/<id>.npz    per-pixel truth: kind (KIND_*, 255 none), tree_id (-1 none),
                                 mixed (first return from the beam edge, not its centre)

A relative pose (dx, dy, dz, dheading) of pair (scan, reference) is the location of ``scan`` in
the levelled frame of ``reference``: ``p_ref = R_z(dheading) p_scan + d`` (spec 6.1).
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

from .forest import KIND_STEM, Forest, breast_height_table, make_forest, stems_in_frame
from .scanner import RESOLUTION_DIVISOR, ScanPose, ScanResult, VirtualScanner, rot_z

THESIS_IDS = "TSRQON"  # spec 10.1
_ID_ORDER = THESIS_IDS + "MLKJIHGFEDCBAPUVWXYZ"
FORMATS = {"npz": ".npz", "las": ".las", "ply": ".ply", "e57": ".e57"}
POSE_COLUMNS = ["scan", "x", "y", "z", "heading_deg"]
TREE_COLUMNS = ["tree_id", "x", "y", "z", "dbh_m", "n_visible_scans"]


def scan_ids(n: int) -> list[str]:
    """T, S, R, Q, O, N (spec 10.1), then the other letters, then letters with a number."""
    return [_ID_ORDER[i % 26] + (str(i // 26 + 1) if i >= 26 else "") for i in range(n)]


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
    scanner_height_m: float = 1.5,
    neighbour_distance_m: float = 11.0,
    visible_range_m: float = 20.0,
    visible_length_m: float = 1.0,
    write_labels: bool = True,
    forest_kwargs: dict | None = None,
    scanner_kwargs: dict | None = None,
) -> Path:
    """Simulate a campaign into folder ``out`` and return its path (DESIGN.md 3, ``simulate``).

    ``tilt_deg`` (roll, pitch), or one pair per scan, tilts the scanners: scans are then stored
    in the tilted scanner frame and the tilt is written to ``campaign.yaml``. ``prior_error``
    (metres, degrees) bounds the a priori error of neighbouring pairs; ``no_prior`` writes no
    pairs and no search box. Scanner heights are ``scanner_height_m`` + U(-0.1, 0.1) m above
    the ground, headings U(-180, 180) deg. Deterministic for a given ``seed``.
    """
    if fmt not in FORMATS:
        raise ValueError(f"format: {fmt!r} is not one of {list(FORMATS)}")
    if resolution not in RESOLUTION_DIVISOR:
        raise ValueError(f"resolution: {resolution!r} is not one of {list(RESOLUTION_DIVISOR)}")
    if scans < 1:
        raise ValueError("scans: need at least one scan")
    say = progress or (lambda _msg: None)
    out = Path(out)
    (out / "scans").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    if write_labels:
        (out / "truth" / "labels").mkdir(exist_ok=True)
    ss_forest, ss_pose, ss_scan, ss_prior = np.random.SeedSequence(seed).spawn(4)
    t0 = time.perf_counter()

    forest = make_forest(trees, plot_size, n_scans=scans, seed=np.random.default_rng(ss_forest),
                         **(forest_kwargs or {}))
    say(f"forest: {trees} trees in a {plot_size:g} m plot, {forest.mesh.n_triangles} triangles")
    rng = np.random.default_rng(ss_pose)
    ids = scan_ids(scans)
    tilts = _tilts(tilt_deg, scans)
    headings = wrap_deg(rng.uniform(-180.0, 180.0, scans))
    heights = scanner_height_m + rng.uniform(-0.1, 0.1, scans)
    xy = forest.scan_xy
    ground_z = forest.ground.height(xy[:, 0], xy[:, 1])
    poses = [
        ScanPose(float(xy[i, 0]), float(xy[i, 1]), float(ground_z[i] + heights[i]),
                 float(headings[i]), (0.0, 0.0) if tilts is None else tuple(map(float, tilts[i])))
        for i in range(scans)
    ]

    scanner = VirtualScanner(forest, resolution=resolution, **(scanner_kwargs or {}))
    ext = FORMATS[fmt]
    n_visible = np.zeros(trees + 1, dtype=np.int64)
    entries = []
    for i, (sid, pose, ss) in enumerate(zip(ids, poses, ss_scan.spawn(scans), strict=True)):
        ts = time.perf_counter()
        result = scanner.scan(pose, np.random.default_rng(ss))
        vis = visible_trees(result, forest, max_range_m=visible_range_m,
                            min_length_m=visible_length_m)
        n_visible[vis] += 1
        write_scan_file(out / "scans" / f"{sid}{ext}", result, fmt)
        if write_labels:
            save_npz(out / "truth" / "labels" / f"{sid}.npz",
                     {"kind": result.kind, "tree_id": result.tree_id.astype(np.int16),
                      "mixed": result.mixed})
        entry = {"id": sid, "path": f"scans/{sid}{ext}"}
        if tilts is not None:
            entry["tilt_deg"] = [_r(tilts[i, 0]), _r(tilts[i, 1])]
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
    stems_g = stems_in_frame(forest.stems, ref.origin, ref.heading_deg)
    tree_tab = breast_height_table(stems_g)
    tree_tab["n_visible_scans"] = n_visible[tree_tab["tree_id"].to_numpy()]
    tree_tab[TREE_COLUMNS].to_csv(out / "truth" / "trees.csv", index=False, float_format="%.6f")
    stems_g.to_csv(out / "truth" / "stems.csv", index=False, float_format="%.6f")

    # campaign.yaml
    doc: dict = {
        "name": out.resolve().name,
        "environment": "forest",
        "sensor": {"angular_step_deg": [_r(scanner.d_az, 9), _r(scanner.d_el, 9)]},
        "scans": entries,
    }
    if not no_prior:
        prng = np.random.default_rng(ss_prior)
        pairs = []
        for a, b in neighbour_pairs(xy, neighbour_distance_m):
            prior = perturb_prior(relative_pose(poses[a], poses[b]), prior_error, prng)
            pairs.append({"scan": ids[a], "reference": ids[b],
                          "a_priori": [_r(v, 4) for v in prior]})
        doc["pairs"] = pairs
        m, deg = prior_error
        doc["search"] = {"xy_m": _r(max(5.0, 1.5 * m), 4), "z_m": _r(max(1.25, 1.5 * m), 4),
                         "heading_deg": _r(min(180.0, max(60.0, 1.5 * deg)), 4)}
    with open(out / "campaign.yaml", "w") as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None)
    say(f"campaign written to {out} in {time.perf_counter() - t0:.1f} s")
    return out
